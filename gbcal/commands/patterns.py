"""Write every projector frame one calibration pose needs, and OUTDIR/patterns.yaml.

patterns.yaml lists `frames: [name, ...]` in display order; show each frame full-screen and
capture one camera image of the board per frame, saved as pose_NNN/<name>.png in a session.
"""
from __future__ import annotations

HELP = "write the projector frames of one calibration pose (+ patterns.yaml)"


def add_arguments(p):
    from gbscan.cli_common import size_arg

    p.add_argument("outdir", help="output folder (created if missing)")
    p.add_argument("--projector", type=size_arg, default=(1024, 768), metavar="WxH",
                   help="projector resolution (default 1024x768)")
    p.add_argument("--stripe-px", type=int, default=8, help="stripe width in projector pixels (default 8)")
    p.add_argument("--no-markers", action="store_true", help="the paper's pure green/blue stripe frame")


def run(args) -> int:
    from pathlib import Path

    from gbscan.io import make_dir, save_yaml, write_png
    from gbscan.pattern import PatternSpec

    from ..patterns import calibration_frames

    spec = PatternSpec(args.projector[0], args.projector[1], args.stripe_px, not args.no_markers)
    out = Path(args.outdir)
    make_dir(out, "output folder")
    frames = calibration_frames(spec)
    for name, img in frames.items():
        write_png(out / f"{name}.png", img)
    save_yaml(out / "patterns.yaml", {"schema": "gbcal.patterns", "version": 1,
                                      "pattern": spec.to_dict(), "frames": list(frames)})
    print(f"wrote {len(frames)} frames ({spec.width}x{spec.height}) and patterns.yaml to {out}")
    return 0
