"""Where do the lit pixels of a curved object go?  Scan simulated frames and print a breakdown.

    python scripts/coverage_study.py [--scenes sphere,head] [--seeds 0] [--preset typical] [--out DIR]
                                     [--yaw-deg DEG] [--decode-param NAME=VALUE ...]

Scans each frame with the true calibration (``gbscan.scan.Scanner``, default decoder and cleaning)
and prints, over the lit non-edge pixels (the accuracy targets' denominator):

* kept %, depth RMS (mm) and the worst kept point's 3D error (mm; on depth-edge pixels to the
  nearest of the 3x3 true points, :func:`gbscan.sim.point_errors_mm`, as the tests count it);
* kept % by camera and projector incidence of the true surface (``gbscan.sim.incidence_deg``):
  stripes arrive dim and compressed at grazing projector incidence, edge-on at grazing camera
  incidence, so this splits what the decoder could do better from what the geometry denies;
* the lost pixels by the decoder's reason (``StripeMap.mask``; "ok" = decoded, then removed by
  the cleaning), within 70 degrees of both and beyond;
* the ceiling: what a decoder would keep that got every pixel within 70 / 75 / 80 / 85 degrees of
  both and none beyond (the target's 95 % asks for pixels beyond the angle where the ceiling
  reaches it).

``--depth-range MIN_MM MAX_MM`` scans as ``gbscan scan --depth-range`` does: the cleaning's range
and the decoder's working volume.  ``--decode-param NAME=VALUE`` scans with a decoder parameter off its default (compare a change:
run once with and once without); ``--yaw-deg`` turns the head / the real face (``fran_face``).

``--projector 1920x1080`` (with ``--camera 1280x1024``: stripes about as wide in the camera as
the paper rig's) scans through a projector of that many pixels behind the paper projector's
lens, 240 stripes of 8 px; ``--marker-code 1`` projects and decodes the marker sequence used
before 2026-11-28, periodic beyond 167 stripes (:mod:`gbscan.pattern`).

``--bayer RGGB`` renders through a colour filter mosaic and OpenCV's demosaicing (most colour
cameras) instead of full RGB per pixel (the paper's 3-CCD camera); ``--jpeg QUALITY
[--jpeg-sampling 4:2:0]`` stores the frames as JPEG (webcams, most "photo" modes); ``--ambient
LEVEL`` lights the scene with warm room light (a fraction of the projector's light).

``--edge-profile`` also prints the decoded columns' error near the edges of the reported area:
signed mean and RMS in camera px (the projector-column error over the true stripe spacing
``|d column / du|``) of the reported lit non-edge pixels at 1, 2, 3, 4 and 5+ px along the row
from the nearest unreported pixel, split by the side it lies on (toward the projector or away
from it), and at 1 ... 4 rows from one along the column.  It says whether the pixels at a rim are
biased or merely noisy (with ``--decode-param rim_bias_px=0 ...`` it shows what the rim rules mask).

``--confidence`` also prints what a higher ``--min-confidence`` keeps: for thresholds 0.3 ... 0.7,
the kept % of the lit non-edge pixels, their depth RMS (mm) and worst point (mm), and the column
error RMS (projector px) of the decoded pixels above and below the threshold.

``--sigma`` also prints how well each kept point's predicted error (``Scan.sigma_mm``, mm along
the ray, one standard deviation) predicts its actual 3D error: per band of sigma (quantiles 0, 25,
50, 75, 90, 97, 100 % of the kept lit non-edge points) the predicted and the actual RMS, their
ratio and the fraction within 2 sigma; then what ``--max-sigma-mm`` keeps for 0.1 ... 0.5 mm
(kept %, depth RMS, worst point; the scan's columns reconstructed again with the filter on).

``--out DIR`` writes ``coverage_<scene>_s<seed>.png`` per frame: the lit non-edge pixels, kept in
grey, lost ones coloured by reason (the decoder preview's colours), grazing ones (beyond 70
degrees) darker, with a legend.
"""
from __future__ import annotations

import argparse
import inspect
import sys
from pathlib import Path

import numpy as np

GRAZING_DEG = 70.0
BINS_DEG = (0, 40, 60, 70, 75, 80, 90)


def study(name: str, seed: int, preset: str, out: Path | None, bayer: str = "", decode_params=None,
          yaw_deg: float | None = None, depth_range=None, conditions: dict | None = None,
          baseline_mm: float = 200.0, camera_px: tuple[int, int] = (640, 480), edge_profile: bool = False,
          confidence: bool = False, sigma: bool = False, projector_px: tuple[int, int] = (1024, 768),
          marker_code: int = 2) -> dict:
    from gbscan import sim
    from gbscan.calibfile import calibration_from_rig
    from gbscan.decode import REASONS
    from gbscan.pattern import PatternSpec, render_pattern
    from gbscan.scan import Scanner

    rig = sim.paper_rig(baseline_mm=baseline_mm, camera_px=camera_px, projector_px=projector_px)
    spec = PatternSpec(rig.projector.width, rig.projector.height, marker_code=marker_code)
    import dataclasses

    print(f"rendering {name} (seed {seed}, {preset}{', ' + bayer if bayer else ''}) ...", file=sys.stderr, flush=True)
    cond = dataclasses.replace(sim.preset(preset), bayer=bayer, **(conditions or {}))
    scene = getattr(sim.scenes, name)(**({} if yaw_deg is None else {"yaw_deg": yaw_deg}))
    r = sim.render(rig, scene, render_pattern(spec), cond, seed=seed)
    from gbscan.clean import CleanParams

    clean = CleanParams() if depth_range is None else CleanParams(min_depth_mm=depth_range[0],
                                                                   max_depth_mm=depth_range[1])
    scanner = Scanner(calibration_from_rig(rig, spec), decode_params=decode_params, clean_params=clean)
    s = scanner.scan(r.image)
    P = r.point.astype(np.float64)
    good = r.lit & ~r.depth_edge & np.isfinite(P[..., 2])
    kept = good & s.valid
    dz = (s.xyz[..., 2] - P[..., 2])[kept]
    err_map = sim.point_errors_mm(r, s.xyz, s.valid)   # depth-edge pixels: the nearest of 3x3 truths
    err = err_map[s.valid]
    cam, proj = sim.incidence_deg(rig, r)
    facing = good & (cam < GRAZING_DEG) & (proj < GRAZING_DEG)
    mask = s.stripemap.mask
    res = {"scene": name, "seed": seed, "lit": int(good.sum()), "kept": float(kept.sum() / good.sum()),
           "rms_mm": float(np.sqrt(np.mean(dz ** 2))), "worst_mm": float(np.nanmax(err)) if err.size else np.nan,
           "facing_frac": float(facing.sum() / good.sum()), "facing_kept": float((kept & facing).sum() / facing.sum())}
    print(f"\n## {name}, seed {seed}: kept {100 * res['kept']:.1f} % of {res['lit']} lit non-edge pixels, depth RMS "
          f"{res['rms_mm']:.3f} mm, worst {res['worst_mm']:.2f} mm")
    for label, ang in (("camera", cam), ("projector", proj)):
        cells = []
        for lo, hi in zip(BINS_DEG[:-1], BINS_DEG[1:]):
            m = good & (ang >= lo) & (ang < hi)
            if m.any():
                cells.append(f"{lo}-{hi}: {100 * m.sum() / good.sum():4.1f} % of px, kept {100 * (m & kept).sum() / m.sum():5.1f} %")
        print(f"   {label:9s} incidence  " + " | ".join(cells))
    print(f"   within {GRAZING_DEG:.0f} deg of both: {100 * res['facing_frac']:.1f} % of the pixels, kept "
          f"{100 * res['facing_kept']:.2f} %; beyond: kept "
          f"{100 * (kept & ~facing).sum() / max((good & ~facing).sum(), 1):.1f} %")
    worst_inc = np.maximum(cam, proj)
    res["ceiling"] = {a: float((good & (worst_inc < a)).sum() / good.sum()) for a in (70, 75, 80, 85)}
    print("   ceiling (every pixel within the angle of both, none beyond): " +
          ", ".join(f"{a} deg {100 * c:.1f} %" for a, c in res["ceiling"].items()))
    for label, sel in (("within", facing), ("beyond", good & ~facing)):
        lost = sel & ~s.valid
        codes, counts = np.unique(mask[lost], return_counts=True)
        parts = ", ".join(f"{'cleaned' if c == 0 else REASONS[int(c)]} {100 * n / good.sum():.2f}"
                          for c, n in sorted(zip(codes, counts), key=lambda t: -t[1]))
        print(f"   lost {label:6s} (% of lit non-edge): {parts if parts else 'none'}")
    if edge_profile:
        res["edge_profile"] = print_edge_profile(rig, r, s.stripemap, good)
    if confidence:
        res["confidence"] = print_confidence_table(r, s, good, err_map)
    if sigma:
        res["sigma"] = print_sigma_table(r, s, good, err_map, scanner)
    if out is not None:
        res["picture"] = str(picture(out / f"coverage_{name}_s{seed}.png", r.image, good, kept, facing, mask))
    return res


def edge_distances(unreported: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel, the distance (px) along its row to the nearest ``unreported`` pixel on the left
    and on the right, and along its column to the nearest above or below (a large number where
    there is none): (left, right, vertical), (H, W) int64 each."""
    H, W = unreported.shape
    big = H + W

    def run_from_start(m: np.ndarray) -> np.ndarray:
        # distance to the last True at or before each index along the last axis
        idx = np.where(m, np.arange(m.shape[-1]), -big)
        return np.arange(m.shape[-1]) - np.maximum.accumulate(idx, axis=-1)

    left = run_from_start(unreported)
    right = run_from_start(unreported[:, ::-1])[:, ::-1]
    up = run_from_start(unreported.T).T
    down = run_from_start(unreported[::-1].T).T[::-1]
    return left, right, np.minimum(up, down)


def print_edge_profile(rig, r, sm, good) -> dict:
    """The ``--edge-profile`` table of one frame (see the module's docstring); returns its cells
    as {(direction, distance): (n, mean, rms)} in camera px."""
    truth = np.asarray(r.proj_xy[..., 0], np.float64)
    spacing = np.abs(np.gradient(truth, axis=1))      # projector px per camera px along the row
    err = (sm.column - truth) / np.where(spacing > 1e-3, spacing, np.nan)
    reported = sm.valid
    left, right, vert = edge_distances(~reported)
    use = good & reported & np.isfinite(err)
    # the projector lies toward +u when its centre is right of the camera's (x right)
    proj_right = rig.t_cam_proj[0] > 0
    toward = np.where(proj_right, right <= left, left < right)   # the nearer unreported pixel's side
    horiz = np.minimum(left, right)
    cells = {}

    def cell(key, m) -> str:
        # one cell: (pixels, mean, RMS) of the errors under m, and its text
        e = err[m]
        cells[key] = (int(e.size), float(e.mean()) if e.size else np.nan, _rms(e))
        return f"{key[1]}: {e.mean():+.2f} / {_rms(e):.2f} ({e.size})" if e.size else f"{key[1]}: -"

    cell(("interior", 5), use & (horiz >= 5) & (vert >= 5))
    n5, m5, r5 = cells[("interior", 5)]
    print("   column error near the reported area's edges, camera px, mean / RMS (pixels) at 1-4 px from the "
          f"nearest unreported pixel; 5+ px from any: {m5:+.2f} / {r5:.2f} ({n5})")
    for label, side in (("toward the projector", toward), ("away from it", ~toward)):
        parts = [cell((label, d), use & side & (horiz == d) & (vert >= 5)) for d in (1, 2, 3, 4)]
        print(f"   along the row, unreported pixel {label:21s} " + " | ".join(parts))
    parts = [cell(("vertical", d), use & (vert == d) & (horiz >= 5)) for d in (1, 2, 3, 4)]
    print(f"   along the column (5+ px from one along the row)                " + " | ".join(parts))
    return cells


CONF_THRESHOLDS = (0.3, 0.4, 0.5, 0.6, 0.7)


def _rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e ** 2))) if e.size else float("nan")


def print_confidence_table(r, s, good, err_map) -> dict:
    """The ``--confidence`` table of one scan (see the module's docstring; ``err_map`` (H, W) the
    scan's point errors, :func:`gbscan.sim.point_errors_mm`); returns
    {threshold: (kept fraction, depth RMS mm, worst mm, column RMS above, column RMS below)}."""
    sm = s.stripemap
    conf = sm.confidence
    P = np.asarray(r.point, np.float64)
    col_err = sm.column - np.asarray(r.proj_xy[..., 0], np.float64)
    decoded = good & sm.valid & np.isfinite(col_err)
    out = {}
    parts = []
    for t in CONF_THRESHOLDS:
        kept = good & s.valid & (conf >= t)
        dz = (s.xyz[..., 2] - P[..., 2])[kept]
        above, below = col_err[decoded & (conf >= t)], col_err[decoded & (conf < t)]
        worst = float(np.max(err_map[kept])) if kept.any() else float("nan")
        out[t] = (float(kept.sum() / good.sum()), _rms(dz), worst, _rms(above), _rms(below))
        parts.append(f"{t:.1f}: {100 * out[t][0]:.1f} % / {out[t][1]:.3f} mm / {worst:.2f} mm "
                     f"(column {out[t][3]:.3f} above, {out[t][4]:.3f} below)")
    print("   --min-confidence T keeps (% of lit non-edge / depth RMS / worst; column RMS proj px above / below T):")
    for p in parts:
        print("      " + p)
    return out


SIGMA_QUANTILES = (0.0, 0.25, 0.5, 0.75, 0.9, 0.97, 1.0)
SIGMA_THRESHOLDS_MM = (0.1, 0.15, 0.2, 0.3, 0.5)


def print_sigma_table(r, s, good, err_map, scanner) -> dict:
    """The ``--sigma`` tables of one scan (see the module's docstring); returns {"bands": [(lo, hi,
    n, predicted RMS, actual RMS, fraction within 2 sigma)], "max_sigma_mm": {T: (kept fraction,
    depth RMS mm, worst mm)}}."""
    import dataclasses

    sig = s.sigma_mm
    if sig is None:
        print("   --sigma: the scan has no predicted error (decoder confidence_spread_px 0)")
        return {}
    sel = good & s.valid
    e, sg = err_map[sel], sig[sel]
    qs = np.quantile(sg, SIGMA_QUANTILES)
    bands = []
    print("   predicted error sigma_mm against the actual 3D error (kept lit non-edge points, by band of sigma):")
    for k, (lo, hi) in enumerate(zip(qs[:-1], qs[1:])):
        m = (sg >= lo) & ((sg < hi) if k < len(qs) - 2 else (sg <= hi))
        pred, act = _rms(sg[m]), _rms(e[m])
        within = float(np.mean(e[m] < 2 * sg[m])) if m.any() else float("nan")
        bands.append((float(lo), float(hi), int(m.sum()), pred, act, within))
        print(f"      {100 * SIGMA_QUANTILES[k]:3.0f}-{100 * SIGMA_QUANTILES[k + 1]:3.0f} % ({lo:.3f}-{hi:.3f} mm): "
              f"predicted {pred:.3f}, actual RMS {act:.3f} mm (x{act / pred:.2f}), within 2 sigma {100 * within:.1f} %")
    P = np.asarray(r.point, np.float64)
    sm = s.stripemap
    from gbscan import sim

    out = {}
    parts = []
    for t in SIGMA_THRESHOLDS_MM:
        saved = scanner.clean_params     # the same scanner (its rays and planes), the filter on
        scanner.clean_params = dataclasses.replace(saved, max_sigma_mm=t)
        try:
            fs = scanner.reconstruct(sm.column, sm.confidence, decoded=sm.valid, column_sigma=sm.column_sigma)
        finally:
            scanner.clean_params = saved
        kept = good & fs.valid
        dz = (fs.xyz[..., 2] - P[..., 2])[kept]
        em = sim.point_errors_mm(r, fs.xyz, fs.valid)
        worst = float(np.max(em[kept])) if kept.any() else float("nan")
        out[t] = (float(kept.sum() / good.sum()), _rms(dz), worst)
        parts.append(f"{t:.2f} mm: {100 * out[t][0]:.1f} % / {out[t][1]:.3f} mm / {worst:.2f} mm")
    print("   --max-sigma-mm T keeps (% of lit non-edge / depth RMS / worst):")
    for p_ in parts:
        print("      " + p_)
    return {"bands": bands, "max_sigma_mm": out}


def picture(path: Path, image: np.ndarray, good, kept, facing, mask) -> Path:
    """Lit non-edge pixels: kept grey, lost coloured by reason; grazing ones at half brightness."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    from gbscan.decode import REASONS
    from gbscan.io import write_figure_png
    from gbscan.preview.decode import REASON_RGB

    rgb = (image * 0.25).astype(np.float64)
    rgb[kept] = (150, 150, 150)
    lost = good & ~kept
    # the decoder preview's colours, but for the ones that vanish on this picture's grey / black
    own = {"dark": (150, 90, 40), "low_contrast": (210, 210, 120), "saturated": (255, 0, 255)}
    colours = {0: (255, 255, 0)}   # decoded, removed by the cleaning
    colours.update({code: own.get(name, REASON_RGB.get(name, (255, 0, 255))) for code, name in REASONS.items()
                    if code})
    for code, col in colours.items():
        rgb[lost & (mask == code)] = col
    rgb[good & ~facing] *= 0.55
    ys, xs = np.nonzero(good)
    crop = rgb[max(ys.min() - 4, 0):ys.max() + 5, max(xs.min() - 4, 0):xs.max() + 5].astype(np.uint8)
    fig, ax = plt.subplots(figsize=(7, 7 * crop.shape[0] / crop.shape[1] + 0.6), dpi=110)
    ax.imshow(crop, interpolation="nearest")
    ax.set_axis_off()
    handles = [Patch(color=np.array((150, 150, 150)) / 255, label="kept")]
    for code, col in colours.items():
        n = int((lost & (mask == code)).sum())
        if n:
            handles.append(Patch(color=np.array(col) / 255,
                                 label=f"{'cleaned' if code == 0 else REASONS[code]} ({n})"))
    ax.legend(handles=handles, loc="lower right", fontsize=7, framealpha=0.8)
    ax.set_title(f"lost lit non-edge pixels by reason (darker: beyond {GRAZING_DEG:.0f} deg incidence)", fontsize=9)
    path = write_figure_png(path, fig, bbox_inches="tight")
    plt.close(fig)
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="sphere,head", help="gbscan.sim.scenes names (default sphere,head)")
    ap.add_argument("--seeds", default="0", help="comma-separated render seeds (default 0)")
    ap.add_argument("--preset", default="typical", choices=("clean", "typical", "hard"))
    ap.add_argument("--out", help="folder for the coverage pictures (created)")
    ap.add_argument("--yaw-deg", type=float, help="turn the scenes that take a yaw (head, fran_face) by this much")
    ap.add_argument("--depth-range", type=float, nargs=2, metavar=("MIN_MM", "MAX_MM"),
                    help="scan with this depth range, as gbscan scan --depth-range (cleaning and the decoder's "
                         "working volume)")
    ap.add_argument("--decode-param", action="append", default=[], metavar="NAME=VALUE",
                    help="a gbscan.decode.DecodeParams field other than the default (repeatable), "
                         "e.g. extrapolate_fit=0")
    ap.add_argument("--confidence", action="store_true",
                    help="also print what higher --min-confidence thresholds keep, and the column error above/below")
    ap.add_argument("--sigma", action="store_true",
                    help="also print how the points' predicted error (sigma_mm) matches their actual error, and "
                         "what --max-sigma-mm thresholds keep")
    ap.add_argument("--edge-profile", action="store_true",
                    help="also print the decoded columns' signed error by distance to the reported area's edges")
    from gbscan.cli_common import (add_rig_arguments, add_ambient_argument, add_bayer_argument, add_capture_arguments,
                                   ambient_fields, ambient_label, capture_fields, capture_label, rig_from_args)
    from gbscan.commands.decode import add_marker_code_argument

    add_rig_arguments(ap)
    add_marker_code_argument(ap)   # --marker-code, as gbscan pattern / decode take it
    add_ambient_argument(ap)
    add_bayer_argument(ap)
    add_capture_arguments(ap)
    args = ap.parse_args(argv)
    from gbscan import sim
    from gbscan.errors import GBError
    from gbscan.io import make_dir

    try:
        seeds = [int(x) for x in args.seeds.split(",") if x.strip()]
    except ValueError:
        ap.error(f"--seeds: expected comma-separated integers, got {args.seeds!r}")
    names = [x.strip() for x in args.scenes.split(",") if x.strip()]
    for n in names:
        if not callable(getattr(sim.scenes, n, None)):
            ap.error(f"--scenes: no simulated scene {n!r} in gbscan.sim.scenes")
        if args.yaw_deg is not None and "yaw_deg" not in inspect.signature(getattr(sim.scenes, n)).parameters:
            ap.error(f"--yaw-deg: scene {n!r} takes no yaw")
    from gbscan.commands.decode import params_from_pairs
    from gbscan.decode import DecodeParams

    try:
        decode_params = params_from_pairs(DecodeParams, args.decode_param, "--decode-param")
    except GBError as e:
        ap.error(str(e))
    out = None
    if args.out:
        try:
            out = make_dir(args.out, "--out")
        except GBError as e:
            ap.error(str(e))
    if args.depth_range is not None and not 0 < args.depth_range[0] < args.depth_range[1]:
        ap.error(f"--depth-range: expected 0 < MIN_MM < MAX_MM, got {args.depth_range}")
    dec = "default decoder" if decode_params is None else "decoder " + ", ".join(args.decode_param)
    if args.depth_range is not None:
        dec += f", depth range {args.depth_range[0]:g}-{args.depth_range[1]:g} mm"
    yaw = "" if args.yaw_deg is None else f", yaw {args.yaw_deg:g} deg"
    try:
        rig_from_args(args)
        conditions = {**capture_fields(args), **ambient_fields(args)}
    except GBError as e:
        ap.error(str(e))
    print(f"# coverage study, paper rig (baseline {args.baseline_mm:g} mm, camera {args.camera[0]}x{args.camera[1]}, "
          f"projector {args.projector[0]}x{args.projector[1]}"
          f"{', marker code 1' if args.marker_code == 1 else ''}), "
          f"preset {args.preset}{', Bayer ' + args.bayer if args.bayer else ''}"
          f"{capture_label(args)}{ambient_label(args)}{yaw}, "
          f"{dec}, default cleaning")
    for name in names:
        for seed in seeds:
            res = study(name, seed, args.preset, out, args.bayer, decode_params, args.yaw_deg, args.depth_range,
                        conditions, args.baseline_mm, args.camera, args.edge_profile, args.confidence, args.sigma,
                        tuple(args.projector), args.marker_code)
            if "picture" in res:
                print(f"   wrote {res['picture']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
