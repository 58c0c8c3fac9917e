"""A camera with more pixels than the paper's: decode its frames as they are, and shrunk.

    python scripts/resample_study.py [--scales 1,2,3] [--scenes plane,sphere,head,multi_object]
                                     [--preset typical] [--seed 0] [--resample 0,1]
                                     [--decode-param NAME=VALUE ...] [--yuv yuyv|i420] [--jpeg Q]

The paper rig's camera has 640x480 pixels (fx 800): a stripe of 8 projector px spans ~3.7
camera px at 650 mm, the width the decoder's pixel-sized rules are tuned for.  A camera of
``640 s x 480 s`` pixels over the same field of view (fx ``800 s``, same lens distortion) sees the
same stripes ``s`` times wider.  For each scale and scene this renders one frame (``--supersample``
rays per pixel side, 2 by default: a sensor integrates over its pixels) and decodes it with each ``--resample`` (``DecodeParams.resample``: 0
automatic, 1 never, f > 1 a fixed shrink factor), then prints, against the simulator's truth at
every camera pixel: camera px per stripe (the truth's, and the decoder's estimate from the colour
runs, :func:`gbscan.decode.frame_stripe_px`), the factor used, reported % of the lit non-edge pixels,
pixels on a wrong stripe (column half a stripe or more off; off depth edges, and on them), the
column RMS (projector px) of the right ones and the decode time (one thread, median of 3).
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # measure this checkout, whatever the environment's install points at
    sys.path.insert(0, str(ROOT))


def scaled_rig(scale: float):
    """The paper rig with its camera's pixel grid ``scale`` times finer (same field of view)."""
    from gbscan import sim

    return sim.paper_rig(camera_px=(int(round(640 * scale)), int(round(480 * scale))))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scales", default="1,2,3", help="camera pixel-grid scales (default 1,2,3)")
    ap.add_argument("--scenes", default="plane,sphere,head,multi_object")
    ap.add_argument("--preset", default="typical", choices=("clean", "typical", "hard"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--supersample", type=int, default=2,
                    help="rays per pixel side (default 2: each camera pixel integrates 4 samples, as a sensor "
                         "integrates over its area; 1 samples the pixel centre only and aliases the stripes)")
    ap.add_argument("--resample", default="0,1", help="DecodeParams.resample values to compare (default 0,1)")
    ap.add_argument("--decode-param", action="append", default=[], metavar="NAME=VALUE",
                    help="a DecodeParams field off its default for every decode (repeatable; unwrap.NAME=VALUE for "
                         "the unwrapping's), e.g. crop=false")
    from gbscan.cli_common import add_capture_arguments, capture_fields, capture_label

    add_capture_arguments(ap)   # --jpeg, --jpeg-sampling, --yuv, --lateral-ca-px, --gloss: the camera, lens, surfaces
    args = ap.parse_args(argv)
    try:
        scales = [float(x) for x in args.scales.split(",") if x.strip()]
        factors = [float(x) for x in args.resample.split(",") if x.strip()]
    except ValueError:
        ap.error("--scales and --resample take comma-separated numbers")
    if args.supersample < 1:
        ap.error("--supersample must be at least 1")
    if not scales or min(scales) <= 0 or not factors:
        ap.error("--scales: positive numbers; --resample: at least one value")
    import numba

    from gbscan import sim
    from gbscan.decode import DecodeParams, decode, frame_stripe_px
    from gbscan.errors import GBError
    from gbscan.pattern import PatternSpec, render_pattern

    numba.set_num_threads(1)
    try:
        import cv2

        cv2.setNumThreads(1)
    except ImportError:
        pass
    spec = PatternSpec()
    names = [x.strip() for x in args.scenes.split(",") if x.strip()]
    for n in names:
        if not callable(getattr(sim.scenes, n, None)):
            ap.error(f"--scenes: no simulated scene {n!r} in gbscan.sim.scenes")
    from gbscan.commands.decode import pairs_to_kwargs

    try:
        over = pairs_to_kwargs(DecodeParams, args.decode_param, "--decode-param")
        params = {f: DecodeParams(**{**over, "resample": f}) for f in factors}
    except GBError as e:
        ap.error(str(e))
    try:
        cond = dataclasses.replace(sim.preset(args.preset), supersample=args.supersample, **capture_fields(args))
    except GBError as e:
        ap.error(str(e))
    print(f"# resample study, paper rig, camera 640x480 x scale, preset {args.preset}, seed {args.seed}, "
          f"supersample {args.supersample}, 8 px stripes at 650 mm{capture_label(args)}")
    print(f"{'scene':13s} {'camera':>9s} {'px/stripe':>9s} {'est.':>5s} {'resample':>8s} {'used':>5s} "
          f"{'reported %':>10s} {'wrong':>6s} {'wrong_edge':>10s} {'col RMS':>7s} {'ms':>7s}")
    for scale in scales:
        rig = scaled_rig(scale)
        for name in names:
            print(f"rendering {name} at {rig.camera.width}x{rig.camera.height} ...", file=sys.stderr, flush=True)
            r = sim.render(rig, getattr(sim.scenes, name)(), render_pattern(spec), cond, seed=args.seed)
            truth = r.proj_xy[..., 0]
            true_px = spec.stripe_px / float(np.nanmedian(np.abs(np.diff(truth, axis=1))))
            est, _ = frame_stripe_px(r.image)
            cand = r.lit & ~r.depth_edge
            for b in factors:
                sm = decode(r.image, spec, params[b])
                ts = []
                for _ in range(3):
                    t = time.perf_counter()
                    decode(r.image, spec, params[b])
                    ts.append(time.perf_counter() - t)
                err, bad = sim.column_errors(sm.column, sm.valid, truth, spec.stripe_px)
                good = sm.valid & np.isfinite(truth) & ~bad & ~r.depth_edge
                rms = float(np.sqrt(np.mean(err[good].astype(np.float64) ** 2))) if good.any() else float("nan")
                print(f"{name:13s} {rig.camera.width:4d}x{rig.camera.height:<4d} {true_px:9.2f} {est:5.2f} "
                      f"{b:8g} {sm.stats.get('resample', 1.0):5.2f} {100 * (sm.valid & cand).sum() / max(cand.sum(), 1):10.2f} "
                      f"{int((bad & ~r.depth_edge).sum()):6d} {int((bad & r.depth_edge).sum()):10d} {rms:7.3f} "
                      f"{1e3 * float(np.median(ts)):7.1f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
