"""Check one camera frame of the stripe pattern: what the frame says about the rig.

Decodes IMAGE and prints the figures that decide how well the stripes decode (stripe
signal-to-noise, level and saturation, contrast, ambient light, colour balance, camera pixels per
stripe, and where the pattern's pixels went), then one line per finding: the figure, what it
means, what to change (exposure, ambient light, projector focus, colour settings, distance,
stripe width).  Take a frame at the rig, run this, change one thing, run it again.

IMAGE may also be a video or a folder of frames (as 'gbscan batch' reads them): --frame N picks
the frame (default 0), e.g. the one 'gbscan batch' names in its rig-check line.

--json FILE writes the same figures and findings for other tools (stable keys: see
gbscan.diagnose.FrameCheck and Finding.key).  Exit status 0 whatever the findings; --strict: 3
when there is a warning (scripts that gate a capture on it).
"""
from __future__ import annotations

import sys

HELP = "what a frame says about the rig: stripe SNR, exposure, contrast, ambient light, what to change"

#: exit status of --strict when the frame has a warning
WARN_EXIT = 3


def add_arguments(p):
    from .decode import add_decode_arguments, add_pattern_arguments

    p.add_argument("image", help="camera image (colour PNG/JPEG/TIFF) of the projected stripe pattern, or a video "
                                 "or folder of frames (with --frame)")
    p.add_argument("--frame", type=int, default=None, metavar="N",
                   help="with a video or a folder of frames: the frame to check (default 0)")
    p.add_argument("--calib", metavar="YAML", help="calibration file: the pattern (and camera size) come from it")
    p.add_argument("--json", metavar="FILE", help="also write the figures and findings as JSON")
    p.add_argument("--strict", action="store_true", help=f"exit with status {WARN_EXIT} when there is a warning")
    add_pattern_arguments(p)
    add_decode_arguments(p)


def _read_frame(args, size):
    """(RGB image, input warning or None) of IMAGE: an image file, or frame --frame of a video
    or folder (:func:`gbscan.frames.open_frames`)."""
    from pathlib import Path

    from ..errors import GBError
    from ..io import IMAGE_SUFFIXES, input_warning, read_image_rgb

    path = Path(args.image)
    if path.is_dir() or (path.is_file() and path.suffix.lower() not in IMAGE_SUFFIXES):
        from ..frames import open_frames

        n = 0 if args.frame is None else args.frame
        with open_frames(path, args.bayer) as source:
            if not 0 <= n < len(source):
                raise GBError(f"--frame {n}: {path} has frames 0 to {len(source) - 1}")
            ref = source.ref(n)
            _, rgb = next(iter(source.frames([ref], size)))
            if isinstance(rgb, GBError):
                raise rgb
            return rgb, source.input_warning()
    if args.frame is not None:
        raise GBError(f"--frame applies to a video or a folder of frames; {path} is one image")
    return read_image_rgb(path, size=size, bayer=args.bayer), input_warning(path)


def run(args) -> int:
    from .decode import decode_params_from_args, pattern_from_args
    from .scan import _check_output

    json_path = _check_output(args.json, (".json",), "--json")
    import json

    from ..decode import DecodeParams, decode
    from ..diagnose import check_frame, report
    from ..io import input_warning, read_image_rgb, write_text_atomic

    size = None
    cal = None
    if args.calib:
        from ..calibfile import load_calibration

        cal = load_calibration(args.calib, require_planes=False)
        size = cal.camera.size
    pattern = pattern_from_args(args, cal)
    params = decode_params_from_args(args) or DecodeParams()
    image, warning = _read_frame(args, size)
    if warning:
        print(warning, flush=True)
    sm = decode(image, pattern, params)
    chk = check_frame(image, sm, params)
    print(f"{args.image}: {image.shape[1]}x{image.shape[0]}, pattern {pattern.stripe_px} px stripes"
          f"{' with markers' if pattern.markers else ' (no markers)'}")
    print(report(chk))
    if json_path is not None:
        d = chk.to_dict()
        d["image"] = str(args.image)
        d["input_warning"] = warning
        write_text_atomic(json_path, json.dumps(d, indent=1) + "\n")
        print(f"wrote {json_path}")
    return WARN_EXIT if args.strict and chk.warnings() else 0
