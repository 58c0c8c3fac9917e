"""Write the single-shot projector frame: green/blue stripes (with cyan markers by default).

Show it full-screen on the projector while scanning.  --stripe-px and --no-markers must match
the calibration you scan with (the calibration file records the pattern it was made with).
"""
from __future__ import annotations

HELP = "write the single-shot projector frame (PNG)"


def add_arguments(p):
    from ..cli_common import size_arg

    p.add_argument("-o", "--output", required=True, help="output PNG path")
    p.add_argument("--projector", type=size_arg, default=(1024, 768), metavar="WxH",
                   help="projector resolution (default 1024x768)")
    p.add_argument("--stripe-px", type=int, default=8, help="stripe width in projector pixels (default 8)")
    p.add_argument("--no-markers", action="store_true",
                   help="the paper's pure green/blue pattern (relative stripe index only)")


def run(args) -> int:
    from ..io import write_png
    from ..pattern import PatternSpec, render_pattern

    spec = PatternSpec(args.projector[0], args.projector[1], args.stripe_px, not args.no_markers)
    path = write_png(args.output, render_pattern(spec))
    print(f"wrote {path}: {spec.width}x{spec.height}, {spec.n_stripes} stripes of {spec.stripe_px} px, "
          f"{len(spec.marker_indices())} cyan markers")
    return 0
