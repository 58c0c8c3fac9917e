"""Speed and accuracy of board detection and camera calibration (prints figures; not a test).

Usage: python scripts/bench_camera.py [FOLDER --board 13x12 --square-mm 30]
Default: Bouguet's 20 real captures in ../shared (skipped with a message when absent).

For each corner refiner (none = the detector's corners; cornersubpix; symmetric, the default):
detection time, the calibration of every image (two distortion models), and a held-out figure:
the camera is calibrated on the even images and each odd image's corners are predicted from
its pose alone (solvePnP with the camera fixed), and the other way round; the RMS of those
predictions (px) measures how consistent the corners are with one camera model.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    here = Path(__file__).resolve()
    default = here.parents[2] / "shared" / "data" / "bouguet_calib_example"
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("folder", nargs="?", default=str(default))
    p.add_argument("--board", default="13x12")
    p.add_argument("--square-mm", type=float, default=30.0)
    args = p.parse_args(argv)

    import cv2

    from gbcal.board import detect_with_reason, parse_board
    from gbcal.intrinsics import calibrate_camera
    from gbscan.io import IMAGE_SUFFIXES, read_image_gray

    folder = Path(args.folder)
    if not folder.is_dir():
        print(f"{folder} not found; nothing to measure", file=sys.stderr)
        return 0
    board = parse_board(args.board, args.square_mm)
    files = sorted(f for f in folder.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
    images = [read_image_gray(f) for f in files]
    obj = board.object_points()
    for label, refine, refiner in (("none", False, "symmetric"), ("cornersubpix", True, "cornersubpix"),
                                   ("symmetric", True, "symmetric")):
        t0 = time.perf_counter()
        dets = [detect_with_reason(g, board, refine=refine, refiner=refiner)[0] for g in images]
        dt = (time.perf_counter() - t0) / len(images)
        found = [d for d in dets if d is not None]
        print(f"corners {label}: {len(found)}/{len(images)} found, {1000 * dt:.0f} ms per "
              f"{images[0].shape[1]}x{images[0].shape[0]} image")
        for model in ("k1k2p1p2", "k1k2p1p2k3"):
            t0 = time.perf_counter()
            res = calibrate_camera(dets, board, model=model)
            dt = time.perf_counter() - t0
            K = res.camera.K
            print(f"  {model:11s} {dt:5.2f} s  RMS {res.rms_px:.3f} px  fx {K[0, 0]:.2f}±{res.std['fx']:.2f}  "
                  f"fy {K[1, 1]:.2f}±{res.std['fy']:.2f}  cx {K[0, 2]:.2f}±{res.std['cx']:.2f}  "
                  f"cy {K[1, 2]:.2f}±{res.std['cy']:.2f}  k1 {res.camera.dist[0]:.4f}  k2 {res.camera.dist[1]:.4f}  "
                  f"used {int(res.used.sum())}")
        folds = []
        for train in (0, 1):
            cam = calibrate_camera([d for i, d in enumerate(found) if i % 2 == train], board,
                                   model="k1k2p1p2").camera
            err = []
            for d in (d for i, d in enumerate(found) if i % 2 != train):
                ok, rv, tv = cv2.solvePnP(obj, d.corners, cam.K, cam.dist)
                q, _ = cv2.projectPoints(obj, rv, tv, cam.K, cam.dist)
                err.append(q.reshape(-1, 2) - d.corners)
            folds.append(float(np.sqrt(np.mean(np.sum(np.concatenate(err) ** 2, axis=1)))))
        print(f"  held out (k1k2p1p2, even->odd, odd->even): RMS {folds[0]:.3f} / {folds[1]:.3f} px")
    print("published (Bouguet, k3 = 0): fx 657.46 fy 657.95 cx 303.14 cy 242.57 k1 -0.2540 k2 0.1214")
    return 0


if __name__ == "__main__":
    sys.exit(main())
