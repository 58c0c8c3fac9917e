"""Write the single-shot projector frame: green/blue stripes (with cyan markers by default).

Show it full-screen on the projector while scanning.  The frame must be the pattern the
calibration was made with: --calib CALIB writes exactly that one (the calibration file records
it: size, stripe width, markers and their code); otherwise --projector, --stripe-px,
--no-markers and --marker-code must match it.
"""
from __future__ import annotations

HELP = "write the single-shot projector frame (PNG)"


def add_arguments(p):
    from ..cli_common import size_arg

    p.add_argument("-o", "--output", required=True, help="output PNG path")
    p.add_argument("--calib", metavar="YAML",
                   help="write the pattern this calibration file was made with (ignores the options below)")
    p.add_argument("--projector", type=size_arg, default=(1024, 768), metavar="WxH",
                   help="projector resolution (default 1024x768)")
    p.add_argument("--stripe-px", type=int, default=8, help="stripe width in projector pixels (default 8)")
    p.add_argument("--no-markers", action="store_true",
                   help="the paper's pure green/blue pattern (relative stripe index only)")
    from .decode import add_marker_code_argument

    add_marker_code_argument(p)


def run(args) -> int:
    from ..io import write_png
    from ..pattern import MARKER_CODE, PatternSpec, render_pattern

    if args.calib:
        from ..calibfile import load_calibration
        from ..errors import GBError

        cal = load_calibration(args.calib, require_planes=False)
        if cal.pattern is None:
            raise GBError(f"--calib {args.calib} records no pattern (a camera-only calibration?); give "
                          f"--projector/--stripe-px/--no-markers instead")
        spec = cal.pattern
    else:
        spec = PatternSpec(args.projector[0], args.projector[1], args.stripe_px, not args.no_markers,
                           marker_code=args.marker_code)
    path = write_png(args.output, render_pattern(spec))
    code = f" (marker code {spec.marker_code})" if spec.marker_code != MARKER_CODE else ""
    print(f"wrote {path}: {spec.width}x{spec.height}, {spec.n_stripes} stripes of {spec.stripe_px} px, "
          f"{len(spec.marker_indices())} cyan markers{code}")
    return 0
