"""Decode one camera frame of the green-blue stripe pattern into projector columns (no geometry).

Writes stripes.npz with `column` (continuous projector column, px, NaN where not reported),
`stripe` (absolute stripe index, -1), `confidence` (0..1), `column_sigma` (the column's predicted
error, projector px, one standard deviation; absent with confidence_spread_px=0), `mask` (reason
code; `reasons` lists the names), `relative`/`region`/`labels` (the unwrapping), and the pattern,
parameters and statistics as JSON.  --preview DIR writes one PNG per decoder stage.

The pattern must be the one projected: take it from the calibration file (--calib) or give
--stripe-px/--no-markers/--projector/--marker-code as used with 'gbscan pattern'.
"""
from __future__ import annotations

import sys

HELP = "decode one frame's stripes -> projector columns (stripes.npz, stage previews)"


def add_arguments(p):
    p.add_argument("image", help="camera image (colour PNG/JPEG/TIFF) of the projected stripe pattern")
    p.add_argument("-o", "--output", help="output .npz (column, stripe, confidence, mask, ...)")
    p.add_argument("--preview", metavar="DIR", help="write the decoder's stage pictures (PNG) into DIR")
    p.add_argument("--calib", metavar="YAML", help="calibration file: the pattern (and camera size) come from it")
    p.add_argument("--depth-range", type=float, nargs=2, metavar=("MIN_MM", "MAX_MM"),
                   help="the working volume (needs --calib with light planes): the indexing rules out offsets "
                        "that would put a region outside it, as 'gbscan scan --depth-range' does")
    add_pattern_arguments(p)
    add_decode_arguments(p)


def add_pattern_arguments(p) -> None:
    """The projected pattern when no --calib gives it: --stripe-px, --no-markers, --projector,
    --marker-code (read back with :func:`pattern_from_args`)."""
    from ..cli_common import size_arg

    p.add_argument("--stripe-px", type=int, default=8, help="stripe width in projector px (default 8)")
    p.add_argument("--no-markers", action="store_true", help="the pure green/blue pattern (relative index only)")
    p.add_argument("--projector", type=size_arg, default=(1024, 768), metavar="WxH",
                   help="projector resolution (default 1024x768)")
    add_marker_code_argument(p)


def add_marker_code_argument(p) -> None:
    """``--marker-code {1,2}``: the marker sequence of a pattern of more than 167 stripes
    (:mod:`gbscan.pattern`); 1 for a pattern written before 2026-11-28."""
    from ..pattern import MARKER_CODE, MARKER_CODES

    p.add_argument("--marker-code", type=int, choices=MARKER_CODES, default=MARKER_CODE,
                   help=f"the markers' sequence (default {MARKER_CODE}); 1: a pattern of more than 167 stripes (e.g. "
                        "1920 px at 8 px a stripe) written before 2026-11-28 -- narrower patterns are the same "
                        "under both")


def pattern_from_args(args, cal=None):
    """The :class:`gbscan.pattern.PatternSpec` of ``cal`` (a loaded calibration, from --calib) or
    of the flags of :func:`add_pattern_arguments`."""
    from ..errors import GBError
    from ..pattern import PatternSpec

    if cal is not None:
        if cal.pattern is None:
            raise GBError(f"--calib {args.calib} records no pattern; give --stripe-px/--no-markers instead")
        return cal.pattern
    return PatternSpec(args.projector[0], args.projector[1], args.stripe_px, not args.no_markers,
                       marker_code=args.marker_code)


# -- the decoder's flags: one set for every command that decodes (decode, scan, batch) ----------
def blur_value(text: str):
    """``--blur-px``: a sigma (px, float) or ``auto`` (returned as the string)."""
    import argparse

    if text.strip().lower() == "auto":
        return "auto"
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a sigma in camera px or 'auto', got {text!r}") from None


def resample_value(text: str):
    """``--resample``: ``auto`` (0), ``never`` (1) or a shrink factor above 1."""
    import argparse

    t = text.strip().lower()
    if t in ("auto", "never"):
        return 0.0 if t == "auto" else 1.0
    try:
        return float(t)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected auto, never or a shrink factor such as 2, got {text!r}") from None


#: flag -> (DecodeParams field(s) it sets, type, metavar, help)
DECODE_FLAGS = {
    "--blur-px": (("blur_sigma_along_px",), blur_value, "SIGMA|auto",
                  "motion-blur sigma along the stripes, camera px, or auto (the default: from each frame's "
                  "stripe signal-to-noise ratio, 1-3 px)"),
    "--balance-window-px": (("balance_window_px",), int, "N",
                            "colour-balance window, camera px (odd; 0 = whole image, the default; e.g. 31 "
                            "for faces)"),
    "--local-window-px": (("threshold_window_px", "norm_window_px"), int, "N",
                          "window of the local threshold and of the local min/max normalisation, camera px "
                          "(default 15; should span two stripe periods)"),
    "--resample": (("resample",), resample_value, "auto|never|F",
                   "decode frames whose stripes are wide in the camera (over 5 px: a camera with more pixels "
                   "than the paper's) shrunk to ~3.75 px per stripe, the results expanded back to every pixel "
                   "(auto, the default), never, or shrink by F"),
    "--follow-envelope-px": (("envelope_follow_px",), int, "N",
                             "let the local normalisation follow the stripes' brightness over N px (about a "
                             "stripe period: 9 at the paper rig; 0 = off, the default): more of a glossy or "
                             "shaded face is decoded (docs/method.md, 'Glossy surfaces'; not yet safe at "
                             "every geometry, so not the default)"),
    "--angle-deg": (("stripe_angle_deg",), float, "DEG", "stripe direction from vertical, degrees (default 0)"),
    "--threshold": (("threshold",), str, None, "thresholding: local (default) or global"),
    "--gamma": (("camera_gamma",), float, "G", "camera encoding gamma (default 2.2; 1 = linear camera)"),
}
#: Earlier spellings, still accepted but not shown: 'gbscan decode' --window (colour balance),
#: --blur, --angle; 'gbscan scan' --window-px (the local windows, not the colour balance).
DECODE_ALIASES = {"--blur": "--blur-px", "--window": "--balance-window-px", "--angle": "--angle-deg",
                  "--window-px": "--local-window-px"}


def _dest(flag: str) -> str:
    return "decode_" + flag.lstrip("-").replace("-", "_")


def add_decode_arguments(parser) -> None:
    """The decoder's options with the same names and meanings in every command: the flags of
    :data:`DECODE_FLAGS`, their hidden old spellings (:data:`DECODE_ALIASES`) and ``--decode-param
    NAME=VALUE`` for any other :class:`gbscan.decode.DecodeParams` field (the named flags win).
    Read them back with :func:`decode_params_from_args`."""
    import argparse

    g = parser.add_argument_group("decoding (defaults: gbscan.decode.DecodeParams)")
    for flag, (_, typ, metavar, text) in DECODE_FLAGS.items():
        kw = {"choices": ("local", "global")} if flag == "--threshold" else {"type": typ, "metavar": metavar}
        g.add_argument(flag, dest=_dest(flag), help=text, **kw)
    for old, flag in DECODE_ALIASES.items():
        g.add_argument(old, dest=_dest(flag), type=DECODE_FLAGS[flag][1], help=argparse.SUPPRESS)
    g.add_argument("--decode-param", action="append", default=[], metavar="NAME=VALUE",
                   help="any other DecodeParams field, e.g. min_contrast=0.2 (repeatable)")
    from ..io import BAYER_CODES

    parser.add_argument("--bayer", default="", choices=tuple(BAYER_CODES), metavar="PATTERN",
                        help="the frames are a colour camera's raw Bayer mosaics (one channel, 8 or 16 bit) with "
                             f"this top-left 2x2 ({', '.join(BAYER_CODES)}), demosaiced by OpenCV's edge-aware "
                             "method; default: colour frames")


def decode_params_from_args(args):
    """:class:`gbscan.decode.DecodeParams` from the options of :func:`add_decode_arguments`, or None
    when none was given (the decoder's defaults)."""
    from ..decode import DecodeParams

    kw = pairs_to_kwargs(DecodeParams, getattr(args, "decode_param", None) or [], "--decode-param")
    for flag, (fields, _, _, _) in DECODE_FLAGS.items():
        value = getattr(args, _dest(flag), None)
        if value is not None:
            kw.update(dict.fromkeys(fields, None if value == "auto" else value))
    return build_params(DecodeParams, kw, "decoder options") if kw else None


def params_from_pairs(cls, pairs: list[str], option: str):
    """A dataclass ``cls`` from ``NAME=VALUE`` strings (defaults elsewhere), or None if none given."""
    return build_params(cls, pairs_to_kwargs(cls, pairs, option), option) if pairs else None


def pairs_to_kwargs(cls, pairs: list[str], option: str) -> dict:
    """``NAME=VALUE`` strings -> {field: value} for dataclass ``cls``; GBError naming ``option``.

    Values are converted like the field's default (bool, int, float, str); ``none`` gives None.
    A field that is a dataclass itself (``DecodeParams.unwrap``) is set field by field as
    ``FIELD.NAME=VALUE`` (``unwrap.link_rows=3``), the rest of it at its defaults.
    """
    import dataclasses

    from ..errors import GBError

    defaults = cls()
    optional_float = {f.name for f in dataclasses.fields(cls) if "float" in str(f.type)}
    nested = {f.name: type(getattr(defaults, f.name)) for f in dataclasses.fields(cls)
              if dataclasses.is_dataclass(getattr(defaults, f.name))}
    settable = [f.name for f in dataclasses.fields(cls) if f.name not in nested]
    kw = {}
    inner_pairs: dict[str, list[str]] = {}
    for item in pairs:
        name, sep, value = item.partition("=")
        name, value = name.strip().replace("-", "_"), value.strip()
        head, dot, rest = name.partition(".")
        if sep and dot and head in nested:
            inner_pairs.setdefault(head, []).append(f"{rest}={value}")
            continue
        if not sep or name not in settable:
            names = settable + [f"{n}.NAME" for n in nested]
            raise GBError(f"{option} {item!r}: expected NAME=VALUE with NAME one of {', '.join(names)}")
        current = getattr(defaults, name)
        try:
            if value.lower() in ("none", "null"):
                kw[name] = None
            elif isinstance(current, bool):
                if value.lower() not in ("1", "0", "true", "false", "yes", "no", "on", "off"):
                    raise ValueError
                kw[name] = value.lower() in ("1", "true", "yes", "on")
            elif current is None and name in optional_float:
                kw[name] = float(value)
            elif isinstance(current, int) or (current is None and name.endswith("_px")):
                kw[name] = int(value)
            elif isinstance(current, float):
                kw[name] = float(value)
            elif current is None:  # optional field: a number if it looks like one
                try:
                    kw[name] = int(value)
                except ValueError:
                    kw[name] = float(value)
            else:
                kw[name] = value
        except ValueError:
            raise GBError(f"{option} {item!r}: {value!r} is not a valid value for {name} "
                          f"(default {current!r})") from None
    for name, items in inner_pairs.items():
        inner = nested[name]
        kw[name] = build_params(inner, pairs_to_kwargs(inner, items, f"{option} {name}."), f"{option} {name}.*")
    return kw


def build_params(cls, kw: dict, what: str):
    """``cls(**kw)``; a TypeError/ValueError becomes a GBError naming ``what`` (the class's own
    checks raise GBError already)."""
    from ..errors import GBError

    try:
        return cls(**kw)
    except (TypeError, ValueError) as e:
        raise GBError(f"{what}: {e}") from None


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
                 f"{st.get('boundaries', 0)} stripe boundaries")
        if st.get("transitions_joined"):
            text += f", {st['transitions_joined']} one-pixel stripe transitions called dark joined"
        if st.get("fit_alt_regions"):
            n_alt = st["fit_alt_regions"]
            text += (f"; {n_alt} region{'s' if n_alt > 1 else ''} fitted over {st['fit_alt_boundaries']} boundaries "
                     f"instead of {st['fit_boundaries']} (their relief changes within {st['fit_boundaries']})")
        text += ". "
        again = [f"{st[key]} px indexed {how}" for key, how in (
            ("weld_retry_px", "after cutting their rows at weaker spacing jumps"),
            ("weld_split_px", "after splitting them at the row where their markers change offset")) if st.get(key)]
        if again:
            text += f"Large regions the markers could not index unwrapped again: {'; '.join(again)}. "
    if "why" in st:
        text += st["why"] + ". "
    if "blur_sigma_along_px" in st:
        text += (f"Blur along the stripes {st['blur_sigma_along_px']:g} px"
                 + (f" (automatic: stripe SNR {st['snr']:.1f}). " if "snr" in st else ". "))
    if "resample" in st:
        w, h = st.get("decoded_size", (0, 0))
        px = f" ({st['stripe_camera_px']:g} camera px per stripe)" if "stripe_camera_px" in st else ""
        text += (f"Wide stripes{px}: decoded shrunk by {st['resample']:g} to {w}x{h} and expanded back to every "
                 "pixel. ")
    if "decoded_window" in st:
        y0, y1, x0, x1 = st["decoded_window"]
        H, W = sm.mask.shape
        if (y1 - y0, x1 - x0) != (H, W):
            text += (f"Lit window {x1 - x0}x{y1 - y0} at ({x0}, {y0}) decoded alone "
                     f"({100.0 * (y1 - y0) * (x1 - x0) / max(H * W, 1):.0f}% of the frame; the rest is dark). ")
    total_ms = st.get("ms", {}).get("total")
    if total_ms is not None:
        text += f"Decoded in {total_ms:.1f} ms."
    return text


def run(args) -> int:
    import json
    from pathlib import Path

    from ..decode import decode
    from ..errors import GBError
    from ..io import input_warning, read_image_rgb, save_npz

    if not args.output and not args.preview:
        raise GBError("nothing to write: give -o stripes.npz and/or --preview DIR")
    if args.output and not str(args.output).endswith(".npz"):
        raise GBError(f"-o {args.output}: the output must end in .npz")
    size = None
    stripe_range = None
    if args.depth_range is not None and not args.calib:
        raise GBError("--depth-range needs --calib (the light planes map depths to stripes)")
    if args.depth_range is not None and not 0 < args.depth_range[0] < args.depth_range[1]:
        raise GBError(f"--depth-range: expected 0 < MIN_MM < MAX_MM, got {args.depth_range[0]:g} {args.depth_range[1]:g}")
    if args.calib:
        from ..calibfile import load_calibration

        cal = load_calibration(args.calib, require_planes=args.depth_range is not None)
        pattern = pattern_from_args(args, cal)
        size = cal.camera.size
        if args.depth_range is not None:
            from ..clean import CleanParams
            from ..scan import Scanner

            scanner = Scanner(cal, clean_params=CleanParams(min_depth_mm=args.depth_range[0],
                                                            max_depth_mm=args.depth_range[1]))
            stripe_range = scanner.stripe_range
            if stripe_range is None:
                print(f"note: --calib {args.calib}: the light planes are not one projector's pencil (or the range "
                      "bounds nothing); decoding without a working volume")
    else:
        pattern = pattern_from_args(args)
    from ..decode import DecodeParams

    params = decode_params_from_args(args) or DecodeParams()
    if args.preview:
        d = Path(args.preview)
        if d.exists() and not d.is_dir():
            raise GBError(f"--preview {d} exists and is not a folder")
        if not d.parent.is_dir():
            raise GBError(f"--preview {d}: folder {d.parent} does not exist (create it first)")
    image = read_image_rgb(args.image, size=size, bayer=args.bayer)
    warning = input_warning(args.image)
    if warning:
        print(warning, file=sys.stderr, flush=True)
    sm = decode(image, pattern, params, keep_stages=bool(args.preview), stripe_range=stripe_range)
    if args.output:
        arrays = sm.arrays()
        used = params.to_dict()
        if used["blur_sigma_along_px"] is None:   # the automatic blur: record the sigma it chose
            used["blur_sigma_along_px"] = sm.stats.get("blur_sigma_along_px")
            used["blur_auto_snr"] = sm.stats.get("snr")
        arrays["params"] = __import__("numpy").array(json.dumps(used))
        save_npz(args.output, **arrays)
        print(f"wrote {args.output}")
    if args.preview:
        from ..preview.decode import write_decode_previews

        Path(args.preview).mkdir(exist_ok=True)
        paths = write_decode_previews(args.preview, image, sm)
        print(f"wrote {len(paths)} pictures into {args.preview}")
    print(summary(sm))
    from ..diagnose import check_frame

    print_hints(check_frame(image, sm, params).warnings())
    return 0


def print_hints(warnings) -> None:
    """One ``hint:`` line on stderr per warning (``gbscan.diagnose.Finding``) of the rig check
    (what to change at the rig: exposure, ambient light, focus, ...); nothing for a frame that
    looks like a good rig's.  'gbscan check IMAGE' prints all the figures."""
    for f in warnings:
        print(f"hint: {f.text}", file=sys.stderr)
    sys.stderr.flush()
