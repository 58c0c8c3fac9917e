"""Decode one camera frame of the green-blue stripe pattern into projector columns (no geometry).

Writes stripes.npz with `column` (continuous projector column, px, NaN where not reported),
`stripe` (absolute stripe index, -1), `confidence` (0..1), `mask` (reason code; `reasons` lists
the names), `relative`/`region`/`labels` (the unwrapping), and the pattern, parameters and
statistics as JSON.  --preview DIR writes one PNG per decoder stage.

The pattern must be the one projected: take it from the calibration file (--calib) or give
--stripe-px/--no-markers/--projector as used with 'gbscan pattern'.
"""
from __future__ import annotations

HELP = "decode one frame's stripes -> projector columns (stripes.npz, stage previews)"


def add_arguments(p):
    from ..cli_common import size_arg

    p.add_argument("image", help="camera image (colour PNG/JPEG/TIFF) of the projected stripe pattern")
    p.add_argument("-o", "--output", help="output .npz (column, stripe, confidence, mask, ...)")
    p.add_argument("--preview", metavar="DIR", help="write the decoder's stage pictures (PNG) into DIR")
    p.add_argument("--calib", metavar="YAML", help="calibration file: the pattern (and camera size) come from it")
    p.add_argument("--stripe-px", type=int, default=8, help="stripe width in projector px (default 8)")
    p.add_argument("--no-markers", action="store_true", help="the pure green/blue pattern (relative index only)")
    p.add_argument("--projector", type=size_arg, default=(1024, 768), metavar="WxH",
                   help="projector resolution (default 1024x768)")
    p.add_argument("--window", type=int, metavar="N",
                   help="colour-balance window (px, odd; 0 = whole image, e.g. 31 for faces)")
    p.add_argument("--blur", type=float, metavar="SIGMA", help="motion-blur sigma along the stripes (camera px)")
    p.add_argument("--angle", type=float, metavar="DEG", help="stripe direction from vertical (degrees)")
    p.add_argument("--threshold", choices=("local", "global"), help="thresholding (default local)")
    p.add_argument("--gamma", type=float, metavar="G", help="camera encoding gamma (default 2.2; 1 = linear)")


def _params(args):
    from ..decode import DecodeParams

    kw = {}
    if args.window is not None:
        kw["balance_window_px"] = args.window
    if args.blur is not None:
        kw["blur_sigma_along_px"] = args.blur
    if args.angle is not None:
        kw["stripe_angle_deg"] = args.angle
    if args.threshold is not None:
        kw["threshold"] = args.threshold
    if args.gamma is not None:
        kw["camera_gamma"] = args.gamma
    return DecodeParams(**kw)


def summary(sm) -> str:
    """One paragraph: pixels reported, % per reason, regions indexed/dropped, time."""
    st = sm.stats
    n = max(st["pixels"], 1)
    parts = [f"{name} {100.0 * c / n:.1f}%" for name, c in st["reasons"].items() if c and name != "ok"]
    text = (f"reported {st['reported']} of {st['pixels']} pixels ({100.0 * st['reported'] / n:.1f}%); "
            f"not reported: {', '.join(parts) if parts else 'none'}. ")
    if "regions_kept" in st:
        text += (f"Regions: {st.get('regions_found', 0)} found, {st['regions_kept']} kept, "
                 f"{st.get('regions_indexed', 0)} indexed, {st.get('regions_unindexed', 0)} unindexed"
                 f" ({', '.join(f'{k}: {v}' for k, v in st.get('region_why', {}).items())}); "
                 f"{st.get('boundaries', 0)} stripe boundaries. ")
    if "why" in st:
        text += st["why"] + ". "
    total_ms = st.get("ms", {}).get("total")
    if total_ms is not None:
        text += f"Decoded in {total_ms:.1f} ms."
    return text


def run(args) -> int:
    import json
    from pathlib import Path

    from ..decode import decode
    from ..errors import GBError
    from ..io import read_image_rgb, save_npz
    from ..pattern import PatternSpec

    if not args.output and not args.preview:
        raise GBError("nothing to write: give -o stripes.npz and/or --preview DIR")
    if args.output and not str(args.output).endswith(".npz"):
        raise GBError(f"-o {args.output}: the output must end in .npz")
    size = None
    if args.calib:
        from ..calibfile import load_calibration

        cal = load_calibration(args.calib, require_planes=False)
        if cal.pattern is None:
            raise GBError(f"--calib {args.calib} records no pattern; give --stripe-px/--no-markers instead")
        pattern = cal.pattern
        size = cal.camera.size
    else:
        pattern = PatternSpec(args.projector[0], args.projector[1], args.stripe_px, not args.no_markers)
    params = _params(args)
    if args.preview:
        d = Path(args.preview)
        if d.exists() and not d.is_dir():
            raise GBError(f"--preview {d} exists and is not a folder")
        if not d.parent.is_dir():
            raise GBError(f"--preview {d}: folder {d.parent} does not exist (create it first)")
    image = read_image_rgb(args.image, size=size)
    sm = decode(image, pattern, params, keep_stages=bool(args.preview))
    if args.output:
        arrays = sm.arrays()
        arrays["params"] = __import__("numpy").array(json.dumps(params.to_dict()))
        save_npz(args.output, **arrays)
        print(f"wrote {args.output}")
    if args.preview:
        from ..preview.decode import write_decode_previews

        Path(args.preview).mkdir(exist_ok=True)
        paths = write_decode_previews(args.preview, image, sm)
        print(f"wrote {len(paths)} pictures into {args.preview}")
    print(summary(sm))
    return 0
