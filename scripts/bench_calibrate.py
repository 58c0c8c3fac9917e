#!/usr/bin/env python3
"""Benchmark `gbcal calibrate` on a simulated 12-capture session of the paper's rig.

Prints the time of every stage and the accuracy against the simulator's truth: focal lengths
(%), principal point (px), light-plane normals (deg), and the depth RMS of a simulated plane scan
(true projector columns + 0.1 px noise) triangulated with the estimated vs the true calibration;
then the same plane at 650 mm scanned end to end (`Scanner`, decoded columns), where the
calibration's own error shows (the noise above hides most of it).

    python scripts/bench_calibrate.py [--session DIR] [--poses 12] [--preset typical] [--max-samples N]
                                      [--corners symmetric|cornersubpix] [--camera-captures N]

With --camera-captures N the camera is first calibrated on its own (`gbcal camera`'s fit) from N
simulated captures of a bigger board close up in room light (11x8 inner corners of 25 mm at
420-620 mm, tilted 20-45 degrees), and the rig is calibrated again holding the camera to it
(`gbcal calibrate --camera`); both planes are printed.

Without --session a session is rendered into a temporary folder first (minutes; not timed).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--session", help="an existing simulated session (with truth.yaml)")
    p.add_argument("--poses", type=int, default=12)
    p.add_argument("--preset", default="typical")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-samples", type=int, default=20000)
    from gbcal.board import CORNER_REFINERS, DEFAULT_CORNER_REFINER

    p.add_argument("--corners", default=DEFAULT_CORNER_REFINER, choices=CORNER_REFINERS,
                   help="corner refiner (gbcal calibrate --corners)")
    p.add_argument("--camera-captures", type=int, default=0, metavar="N",
                   help="also calibrate with a camera calibrated on its own from N captures of a big board")
    args = p.parse_args(argv)

    from gbcal.calibrate import calibrate_session
    from gbcal.simsession import load_truth, write_session
    from gbscan import sim
    from gbscan.calibfile import calibration_from_rig
    from gbscan.pattern import PatternSpec, render_pattern
    from gbscan.triangulate import PlaneTable, triangulate

    tmp = None
    if args.session:
        session = Path(args.session)
    else:
        tmp = tempfile.TemporaryDirectory()
        session = Path(tmp.name) / "session"
        t0 = time.perf_counter()
        write_session(session, sim.paper_rig(), PatternSpec(), n_poses=args.poses, preset=args.preset,
                      seed=args.seed, progress=False)
        print(f"rendered a {args.poses}-pose '{args.preset}' session in {time.perf_counter() - t0:.0f} s (not timed)")
    truth = load_truth(session)
    rig = truth["rig"]
    t0 = time.perf_counter()
    run = calibrate_session(session, max_samples_per_capture=args.max_samples, log=lambda s: None,
                            corner_refiner=args.corners)
    total = time.perf_counter() - t0
    cal = run.calibration
    t = run.timings
    print(f"calibrate: {total:.1f} s  (captures {t['captures_s']:.1f} s, camera {t['camera_s']:.1f} s, "
          f"planes {t['planes_s']:.1f} s, bundle {t['bundle_s']:.1f} s; {run.bundle.info['nfev']} evaluations)")
    K, K0 = cal.camera.K, rig.camera.K
    print(f"fx {K[0, 0]:.3f} ({100 * (K[0, 0] / K0[0, 0] - 1):+.4f} %)  fy {K[1, 1]:.3f} "
          f"({100 * (K[1, 1] / K0[1, 1] - 1):+.4f} %)  cx {K[0, 2] - K0[0, 2]:+.3f} px  cy {K[1, 2] - K0[1, 2]:+.3f} px")
    n, d = rig.column_planes(cal.plane_column)
    ang = np.degrees(np.arccos(np.clip(np.sum(n * cal.plane_normal, axis=1), -1, 1)))
    print(f"light planes: {cal.n_planes}, normal error max {ang.max():.4f} deg, median {np.median(ang):.4f} deg; "
          f"d error max {np.abs(cal.plane_d - d).max():.3f} mm")
    r = cal.residuals
    print(f"residuals: corner RMS {r['corner_rms_px']:.3f} px, stripe RMS {r['stripe_rms_px']:.3f} px "
          f"({r['stripe_rms_proj_px']:.3f} projector px), {r['stripe_samples']} samples")
    spec = PatternSpec()
    for dist, tilt in ((550.0, (10.0, -15.0)), (650.0, (0.0, 20.0)), (780.0, (0.0, 0.0))):
        rr = sim.render(rig, sim.scenes.plane(dist, tilt), render_pattern(spec), args.preset, seed=1)
        col = np.where(rr.lit, rr.proj_xy[..., 0], np.nan) + np.random.default_rng(0).normal(0, 0.1, rr.lit.shape)
        rms = []
        for c in (cal, calibration_from_rig(rig, spec)):
            pts = triangulate(c.camera.pixel_rays(), col.astype(np.float64), PlaneTable.from_calibration(c))
            rms.append(float(np.sqrt(np.nanmean((pts[..., 2] - rr.point[..., 2]) ** 2))))
        print(f"plane scan at {dist:.0f} mm: depth RMS {rms[0]:.4f} mm (estimated) vs {rms[1]:.4f} mm (true), "
              f"ratio {rms[0] / rms[1]:.2f}")
    from gbscan.scan import Scanner

    rr = sim.render(rig, sim.scenes.plane(650.0), render_pattern(cal.pattern or spec), args.preset, seed=0)
    keep = rr.lit & ~rr.depth_edge

    def plane_error(c):
        """(depth RMS, mean depth error) mm of that plane scanned end to end with calibration ``c``."""
        s = Scanner(c).scan(rr.image)
        dz = (s.xyz[..., 2] - rr.point[..., 2])[s.valid & keep]
        return float(np.sqrt(np.mean(dz ** 2))), float(np.mean(dz))

    out = [plane_error(c) for c in (cal, calibration_from_rig(rig, cal.pattern or spec))]
    ds = cal.uncertainty.get("depth_std_mm") or {}
    print(f"plane at 650 mm scanned end to end (decoded columns): depth RMS {out[0][0]:.4f} mm (estimated, mean "
          f"{out[0][1]:+.4f}) vs {out[1][0]:.4f} mm (true); the calibration states +- {ds.get('centre', float('nan')):.4f} "
          f"mm at {ds.get('distance_mm', float('nan')):.0f} mm (1 sigma, image centre); corners refined by {args.corners}")
    if args.camera_captures > 0:
        t0 = time.perf_counter()
        camera_file = camera_alone(rig, args.camera_captures, args.seed, args.preset, args.corners)
        K = camera_file.camera.K
        st = camera_file.uncertainty["camera_std"]
        print(f"camera alone from {args.camera_captures} captures of an 11x8 board of 25 mm ({time.perf_counter() - t0:.0f} "
              f"s with rendering): fx {K[0, 0] - K0[0, 0]:+.3f} ± {st['fx']:.3f} px, fy {K[1, 1] - K0[1, 1]:+.3f} ± "
              f"{st['fy']:.3f} px (against the truth), RMS {camera_file.residuals['camera_rms_px']:.3f} px")
        run2 = calibrate_session(session, max_samples_per_capture=args.max_samples, log=lambda s: None,
                                 corner_refiner=args.corners, camera_prior=camera_file,
                                 camera_prior_name="the camera calibrated alone")
        cal2 = run2.calibration
        rms2, mean2 = plane_error(cal2)
        ds2 = cal2.uncertainty.get("depth_std_mm") or {}
        K2 = cal2.camera.K
        print(f"with the camera held to it: fx {K2[0, 0] - K0[0, 0]:+.3f} px, plane at 650 mm depth RMS "
              f"{rms2:.4f} mm (mean {mean2:+.4f}); the calibration states +- "
              f"{ds2.get('centre', float('nan')):.4f} mm at {ds2.get('distance_mm', float('nan')):.0f} mm; prior z "
              + " ".join(f"{k} {v:+.1f}" for k, v in cal2.residuals["camera_prior"]["z"].items()))
    if tmp:
        tmp.cleanup()
    return 0


def camera_alone(rig, n: int, seed: int, preset: str, corners: str):
    """A camera-only calibration (what `gbcal camera` writes) from ``n`` simulated captures of an
    11x8 board of 25 mm squares in room light (ambient as bright as the projector's white)."""
    import dataclasses

    from gbcal.board import Board, detect_with_reason
    from gbcal.bundle import rodrigues
    from gbcal.intrinsics import calibrate_camera
    from gbscan import sim

    board = Board(11, 8, 25.0)
    cond = dataclasses.replace(sim.preset(preset), ambient_rgb=(1.0, 1.0, 1.0))
    black = np.zeros((rig.projector.height, rig.projector.width, 3), np.uint8)
    rng = np.random.default_rng([seed, 77])
    cam = rig.camera
    obj = board.object_points()
    centre = obj.mean(axis=0)
    dets = []
    while len(dets) < n:
        tilt, phi = np.radians(rng.uniform(20, 45)), rng.uniform(0, 2 * np.pi)
        R = rodrigues(np.array([tilt * np.sin(phi), tilt * np.cos(phi), np.radians(rng.uniform(-20, 20))]))
        z = rng.uniform(420, 620)
        c = np.array([rng.uniform(-0.12, 0.12) * z, rng.uniform(-0.08, 0.08) * z, z])
        t = c - R @ centre
        q = cam.project(obj @ R.T + t)
        if not (np.all(np.isfinite(q)) and q[:, 0].min() > 12 and q[:, 1].min() > 12
                and q[:, 0].max() < cam.width - 13 and q[:, 1].max() < cam.height - 13):
            continue
        img = sim.render(rig, sim.scenes.board(board.cols, board.rows, board.square_mm, R, t), black, cond,
                         seed=int(rng.integers(1 << 30))).image
        det, _ = detect_with_reason(img, board, refiner=corners)
        if det is not None:
            dets.append(det)
    return calibrate_camera(dets, board, cam.size, model="k1k2p1p2").calibration(board, corners)


if __name__ == "__main__":
    sys.exit(main())
