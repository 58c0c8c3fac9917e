"""Which stripe width?  Decode simulated frames at stripe_px 4, 6, 8, 10, 12 and print a table.

    python scripts/stripe_width_study.py [--scenes plane,sphere] [--preset typical] [--bayer RGGB] [--jpeg 90]
                                         [--scale-windows]

For each width: coverage (reported / lit non-edge pixels), index correctness (reported non-edge
pixels whose column is within half a stripe of the truth), column RMS (projector px) and the
same in depth (mm, with the true light planes), on the paper's rig at 650 mm.  Narrow stripes
give more boundaries (denser depth) but fewer camera pixels per stripe (harder classification,
larger sub-pixel error in projector px); wide stripes the opposite.

The decoder's local windows (threshold and min/max normalisation, ``--local-window-px``) are 15 px
by default, tuned for 8 px stripes (~4 stripes in the camera); ``--scale-windows`` decodes each
width with windows of ``15 * stripe_px / 8`` px (odd, at least 5), as a rig built for that width
would be set up (``gbscan check`` suggests the same).
"""
from __future__ import annotations

import argparse
import sys

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--widths", default="4,6,8,10,12")
    ap.add_argument("--scenes", default="plane,sphere")
    ap.add_argument("--preset", default="typical")
    ap.add_argument("--scale-windows", action="store_true",
                    help="decode each width with local windows of 15 * stripe_px / 8 px (default: 15 px for all)")
    from gbscan.cli_common import add_bayer_argument, add_capture_arguments, capture_fields, capture_label

    add_bayer_argument(ap)
    add_capture_arguments(ap)
    args = ap.parse_args(argv)
    import dataclasses

    from gbscan import sim
    from gbscan.decode import DecodeParams, decode
    from gbscan.pattern import PatternSpec, render_pattern

    rig = sim.paper_rig()
    rays = rig.camera.pixel_rays()
    cond = dataclasses.replace(sim.preset(args.preset), bayer=args.bayer, **capture_fields(args))
    bayer = f", Bayer {args.bayer}" if args.bayer else ""
    print(f"# stripe width study, preset {args.preset}{bayer}{capture_label(args)}, "
          f"paper rig at 650 mm, local windows {'15 * stripe_px / 8' if args.scale_windows else '15'} px")
    print(f"{'scene':8s} {'stripe_px':>9s} {'cam px/stripe':>13s} {'coverage %':>10s} {'index ok %':>10s} "
          f"{'col RMS px':>10s} {'depth RMS mm':>12s} {'boundaries':>10s}")
    for scene_name in args.scenes.split(","):
        scene = getattr(sim.scenes, scene_name)()
        for w in (int(x) for x in args.widths.split(",")):
            spec = PatternSpec(stripe_px=w)
            print(f"rendering {scene_name} at {w} px ...", file=sys.stderr, flush=True)
            r = sim.render(rig, scene, render_pattern(spec), cond, seed=0)
            win = max(5, int(round(15 * w / 8)) | 1) if args.scale_windows else 15
            sm = decode(r.image, spec, DecodeParams(threshold_window_px=win, norm_window_px=win))
            truth = r.proj_xy[..., 0]
            ok = sm.valid & np.isfinite(truth) & ~r.depth_edge
            err = (sm.column - truth)[ok]
            good = np.abs(err) < w / 2
            cand = r.lit & ~r.depth_edge
            n, d = rig.column_planes(np.where(ok, sm.column, 0.0))
            t = d / np.einsum("...i,...i->...", n, rays)
            dz = ((rays * t[..., None])[..., 2] - r.point[..., 2])[ok]
            cam_px = np.nanmedian(np.abs(np.diff(truth, axis=1)))
            print(f"{scene_name:8s} {w:9d} {w / max(cam_px, 1e-9):13.2f} "
                  f"{100 * (sm.valid & cand).sum() / max(cand.sum(), 1):10.2f} "
                  f"{100 * good.mean() if good.size else float('nan'):10.3f} "
                  f"{np.sqrt(np.mean(err[good] ** 2)) if good.any() else float('nan'):10.3f} "
                  f"{np.sqrt(np.mean(dz[good] ** 2)) if good.any() else float('nan'):12.3f} "
                  f"{sm.stats.get('boundaries', 0):10d}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
