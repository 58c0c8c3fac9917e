"""Calibrate the camera alone from checkerboard images.

Give images, folders (their images, sorted by name) or glob patterns ('caps/*.png').  Every image
must have the same size.  Each image's board is detected (status printed: found, or rejected
with the reason), then the intrinsics are fitted and captures that fit far worse than the others
are dropped.  The output is a calibration file with the camera only (no light planes), per-image
residuals and parameter standard deviations; 'gbcal calibrate' then adds the projector.

Example:
  gbcal camera caps/ --board 9x6 --square-mm 25 -o camera.yaml --preview caps_preview/
"""
from __future__ import annotations

HELP = "calibrate the camera alone from checkerboard images"


def add_arguments(p):
    from gbcal.intrinsics import MODELS

    p.add_argument("images", nargs="+", metavar="IMAGE", help="images, folders of images, or glob patterns")
    p.add_argument("--board", required=True, metavar="COLSxROWS", help="inner corners, e.g. 9x6")
    p.add_argument("--square-mm", type=float, required=True, help="square side in mm")
    p.add_argument("-o", "--output", required=True, help="output calibration file (YAML)")
    p.add_argument("--model", choices=MODELS, default="k1k2p1p2k3",
                   help="distortion model (default k1k2p1p2k3; k1k2p1p2 = k3 fixed at 0, steadier with few images)")
    from .calibrate import add_corners_argument

    add_corners_argument(p)
    p.add_argument("--fix-aspect", action="store_true", help="hold fx = fy (square pixels)")
    p.add_argument("--zero-tangent", action="store_true", help="hold p1 = p2 = 0")
    p.add_argument("--max-blur-px", type=float, default=None,
                   help="reject boards whose edges are wider than this (px, default 7)")
    p.add_argument("--no-outlier-rejection", action="store_true", help="keep every detected board")
    p.add_argument("--preview", metavar="DIR", help="write each image with its detected corners to DIR")


def expand_images(args_images) -> list:
    """IMAGE arguments (files, folders, globs) -> naturally sorted unique list of image paths; GBError if none."""
    import glob
    import re
    from pathlib import Path

    from gbscan.errors import GBError
    from gbscan.io import IMAGE_SUFFIXES

    def natural(f):  # Image2 before Image10
        return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", str(f))]

    out = []
    for a in args_images:
        p = Path(a)
        if p.is_dir():
            found = sorted((f for f in p.iterdir() if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES), key=natural)
            if not found:
                raise GBError(f"folder {p} holds no images ({', '.join(IMAGE_SUFFIXES)})")
            out += found
        elif p.is_file():
            out.append(p)
        elif any(ch in a for ch in "*?["):
            found = sorted((Path(f) for f in glob.glob(a) if Path(f).is_file()), key=natural)
            if not found:
                raise GBError(f"no file matches '{a}'")
            out += found
        else:
            raise GBError(f"image {p} does not exist")
    seen, uniq = set(), []
    for f in out:
        key = f.resolve()
        if key not in seen:
            seen.add(key)
            uniq.append(f)
    return uniq


def run(args) -> int:
    import sys
    from pathlib import Path

    from gbscan.calibfile import save_calibration
    from gbscan.errors import GBError
    from gbscan.io import make_dir, read_image_gray, write_png

    from ..board import MAX_SHARPNESS_PX, detect_with_reason, draw_detection, parse_board
    from ..intrinsics import calibrate_camera

    board = parse_board(args.board, args.square_mm)
    out = Path(args.output)
    if not out.parent.is_dir() and str(out.parent):
        raise GBError(f"cannot write {out}: folder {out.parent} does not exist (create it first)")
    preview = Path(args.preview) if args.preview else None
    if preview is not None:
        make_dir(preview, "preview folder")
    paths = expand_images(args.images)
    max_blur = MAX_SHARPNESS_PX if args.max_blur_px is None else args.max_blur_px

    detections, names, size, images = [], [], None, {}
    print(f"board: {board}; {len(paths)} images", file=sys.stderr)
    for k, path in enumerate(paths):
        gray = read_image_gray(path)
        s = (gray.shape[1], gray.shape[0])
        if size is None:
            size = s
        elif s != size:
            raise GBError(f"image {path} is {s[0]}x{s[1]} but {paths[0]} is {size[0]}x{size[1]}; all images "
                          "must come from one camera at one resolution")
        det, reason = detect_with_reason(gray, board, max_sharpness_px=max_blur, what=f"image {path}",
                                         refiner=args.corners)
        detections.append(det)
        names.append(path.name)
        status = (f"found ({det.method}, edges {det.sharpness_px:.1f} px)" if det is not None
                  else f"rejected: {reason}")
        print(f"[{k + 1}/{len(paths)}] {path}: {status}", file=sys.stderr)
        if preview is not None:
            images[k] = gray

    res = calibrate_camera(detections, board, size, model=args.model, fix_aspect=args.fix_aspect,
                           zero_tangent=args.zero_tangent, names=names,
                           reject_outliers=not args.no_outlier_rejection)
    for v in res.views:
        if v.reason and detections[v.index] is not None:
            print(f"{v.name}: dropped: {v.reason}", file=sys.stderr)
    cam = res.camera
    sd = res.std

    def pm(name, value, fmt):
        s = sd.get(name)
        return f"{name} = {value:{fmt}}" + (f" ± {s:{fmt}}" if s else " (fixed)")

    print(f"camera {cam.width}x{cam.height}, model {res.model}: {int(res.used.sum())} of {len(paths)} images used, "
          f"reprojection RMS {res.rms_px:.3f} px")
    print("  " + ", ".join(pm(n, v, ".2f") for n, v in
                           zip(("fx", "fy", "cx", "cy"), (cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]))))
    print("  " + ", ".join(pm(n, v, ".5f") for n, v in zip(("k1", "k2", "p1", "p2", "k3"), cam.dist)))
    worst = max((v for v in res.views if v.used), key=lambda v: v.rms_px)
    print(f"  worst image: {worst.name} (RMS {worst.rms_px:.3f} px); ±: 1-sigma")
    for w in res.warnings:
        print(f"warning: {w}", file=sys.stderr)

    calib = res.calibration(board, args.corners)
    if preview is not None:
        obj = board.object_points()
        for v in res.views:
            det = detections[v.index]
            rep = None if v.R is None else cam.project(obj @ v.R.T + v.t)
            write_png(preview / (Path(v.name).stem + "_corners.png"),
                      draw_detection(images[v.index], board, det, rep))
        print(f"wrote corner previews to {preview}", file=sys.stderr)
    save_calibration(out, calib)
    print(f"wrote {out}")
    return 0
