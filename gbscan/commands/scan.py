"""Scan one camera frame: decode the stripes, triangulate, clean, and write the point cloud.

Outputs (each written atomically; a failed run leaves none half-written):
  -o cloud.ply     binary PLY: x y z nx ny nz (float32, mm, camera frame), confidence, the
                   camera pixel row/col of each point (int32), so 'gbscan mesh --method grid'
                   can rebuild the organised grid, and sigma_mm (float32: the point's predicted
                   error along its camera ray, mm, one standard deviation); any PLY viewer reads
                   the points and normals.
  --xyz xyz.npy    float32 (H, W, 3) organised point map, mm, NaN where no point.
  --mesh mesh.ply  triangle mesh (.ply, .obj or .stl), grid (default) or poisson.
  --preview DIR    PNG pictures: depth map, coverage by reason, shaded mesh from the camera and
                   from an angle (DIR is created if its parent exists).

The cleaning counts, points, coverage, the points' predicted error (median, 90th percentile) and
timings are printed.  --no-clean keeps every
triangulated point (for looking at what the filters remove).
"""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path

HELP = "scan one frame: decode, triangulate, clean -> point cloud (+ xyz map, mesh, previews)"


def add_arguments(p):
    from .decode import add_decode_arguments

    p.add_argument("image", help="camera frame of the stripe pattern (colour PNG/JPEG/TIFF...)")
    p.add_argument("--calib", required=True, help="calibration file (gbcal calibrate)")
    p.add_argument("-o", "--output", required=True, help="output point cloud (.ply)")
    p.add_argument("--xyz", help="also write the organised point map (.npy, float32 H x W x 3, NaN holes)")
    p.add_argument("--mesh", help="also write a mesh (.ply, .obj or .stl)")
    p.add_argument("--preview", metavar="DIR", help="write preview pictures into DIR")
    g = p.add_argument_group("meshing")
    g.add_argument("--method", choices=("grid", "poisson"), default="grid",
                   help="grid: triangulate the pixel grid (fast, default); poisson: watertight-ish surface")
    g.add_argument("--depth", type=int, default=9, help="Poisson octree depth (default 9)")
    g.add_argument("--smooth", type=int, default=0, metavar="N", help="Taubin smoothing iterations (default 0)")
    add_decode_arguments(p)
    add_clean_arguments(p)


def add_clean_arguments(parser, *, no_clean: bool = True) -> None:
    """The cleaning options (:class:`gbscan.clean.CleanParams`), the same in 'scan' and 'batch';
    read them back with :func:`clean_params_from_args`."""
    g = parser.add_argument_group("cleaning (defaults: gbscan.clean.CleanParams)")
    if no_clean:
        g.add_argument("--no-clean", action="store_true", help="keep every triangulated point")
    g.add_argument("--min-confidence", type=float, help="drop points below this decoder confidence (0..1)")
    g.add_argument("--max-sigma-mm", type=float, metavar="MM",
                   help="drop points whose predicted error along the camera ray (one standard deviation, the "
                        "cloud's sigma_mm) is above MM, e.g. 0.2; unlike --min-confidence the same on every scene")
    g.add_argument("--depth-range", type=float, nargs=2, metavar=("MIN_MM", "MAX_MM"),
                   help="accepted z range, mm; also the working volume the decoder's indexing may assume: a "
                        "region whose few markers fit two offsets is indexed when only one keeps it inside "
                        "(give your rig's, e.g. 400 1200)")
    g.add_argument("--max-jump", type=float, help="depth discontinuity: neighbour jump as a fraction of depth")
    g.add_argument("--max-angle-deg", type=float, help="maximum angle between viewing ray and surface normal")
    g.add_argument("--outlier-tol", type=float,
                   help="spikes: deviation from the neighbours' mean, as a fraction of depth (default 0.002)")
    g.add_argument("--min-cluster-px", type=int, help="drop connected pieces smaller than this (px)")
    g.add_argument("--max-gap-px", type=int,
                   help="depth edges across holes: compare run ends with the first point up to this many px "
                        "beyond a hole (default 8, 0 disables; --clean-param gap_far_px=N / gap_near_px=N: how many px "
                        "the farther / nearer run end loses, default 2 / 0)")
    g.add_argument("--clean-param", action="append", default=[], metavar="NAME=VALUE",
                   help="any other CleanParams field, e.g. normal_step_px=3 (repeatable)")


def _check_output(path: str | None, suffixes: tuple[str, ...], what: str) -> Path | None:
    from ..errors import GBError

    if path is None:
        return None
    path = Path(path)
    if path.suffix.lower() not in suffixes:
        raise GBError(f"{what} {path}: the name must end in {' or '.join(suffixes)}")
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise GBError(f"cannot write {what} {path}: folder {folder} does not exist (create it first)")
    if not os.access(folder, os.W_OK):
        raise GBError(f"cannot write {what} {path}: folder {folder} is not writable")
    return path


def _check_preview_dir(path: str | None) -> Path | None:
    from ..errors import GBError

    if path is None:
        return None
    d = Path(path)
    if d.exists() and not d.is_dir():
        raise GBError(f"--preview {d} exists and is not a folder")
    parent = d if d.is_dir() else (d.parent if str(d.parent) else Path("."))
    if not parent.is_dir():
        raise GBError(f"--preview {d}: folder {parent} does not exist (create it first)")
    if not os.access(parent, os.W_OK):
        raise GBError(f"--preview {d}: folder {parent} is not writable")
    return d


def decode_params_from_args(args):
    """DecodeParams from the decoding options, or None for the defaults (see commands.decode)."""
    from .decode import decode_params_from_args as from_args

    return from_args(args)


def clean_params_from_args(args, *, none_if_default: bool = False):
    """CleanParams from the options of :func:`add_clean_arguments` (named flags win over
    --clean-param); ``none_if_default``: None when no option was given."""
    from ..clean import CleanParams
    from .decode import build_params, pairs_to_kwargs

    kw = pairs_to_kwargs(CleanParams, getattr(args, "clean_param", None) or [], "--clean-param")
    if args.min_confidence is not None:
        kw["min_confidence"] = args.min_confidence
    if args.depth_range is not None:
        kw["min_depth_mm"], kw["max_depth_mm"] = args.depth_range
    for name in ("max_jump", "max_angle_deg", "outlier_tol", "min_cluster_px", "max_gap_px", "max_sigma_mm"):
        if getattr(args, name) is not None:
            kw[name] = getattr(args, name)
    if none_if_default and not kw:
        return None
    return build_params(CleanParams, kw, "cleaning options")


def run(args) -> int:
    t_start = time.perf_counter()
    from ..errors import GBError

    out = _check_output(args.output, (".ply",), "point cloud")
    xyz_path = _check_output(args.xyz, (".npy",), "--xyz")
    mesh_path = _check_output(args.mesh, (".ply", ".obj", ".stl"), "--mesh")
    preview = _check_preview_dir(args.preview)
    if args.smooth < 0:
        raise GBError(f"--smooth must be >= 0, got {args.smooth}")
    clean_params = clean_params_from_args(args)

    import numpy as np

    from ..calibfile import load_calibration
    from ..io import input_warning, read_image_rgb, save_npy
    from ..scan import Scanner

    calib = load_calibration(args.calib)
    cam = calib.camera
    image = read_image_rgb(args.image, size=(cam.width, cam.height), what="image", bayer=args.bayer)
    warning = input_warning(args.image)
    if warning:
        print(warning, file=sys.stderr, flush=True)
    decode_params = decode_params_from_args(args)
    t_load = time.perf_counter()
    scanner = Scanner(calib, decode_params=decode_params, clean_params=clean_params)
    t_setup = time.perf_counter()
    scan = scanner.scan(image, clean=not args.no_clean, keep_stages=preview is not None)
    warns = []
    if scan.stripemap is not None:
        from ..diagnose import check_frame

        warns = check_frame(image, scan.stripemap, scanner.decode_params).warnings()
    if scan.n_points == 0:
        why = (scan.stripemap.stats.get("why") if scan.stripemap is not None else None) or \
            "no pixel both decoded and triangulated"
        rig = [f.short for f in warns if f.key != "no_stripes"]
        if rig:     # one line still: the rig check's findings join the reason
            why += f" (rig check: {'; '.join(rig[:2])})"
        chroma = (scan.stripemap.stats.get("chroma") or {}) if scan.stripemap is not None else {}
        if chroma.get("withheld"):   # the reason says what to do
            raise GBError(f"no points reconstructed from {args.image}: {why}")
        raise GBError(f"no points reconstructed from {args.image}: {why}. Check that the projector shows the "
                      "'gbscan pattern' frame, the exposure, and that the calibration belongs to this rig")

    from .decode import print_hints

    print_hints(warns)
    c = scan.counts
    steps = [k for k in c if k not in ("pixels", "input", "kept")]
    print(f"{args.image}: {cam.width}x{cam.height}, {calib.n_planes} light planes")
    print("removed: " + ", ".join(f"{k} {c[k]}" for k in steps))
    print(f"points: {scan.n_points} ({100 * scan.coverage:.1f}% of the image)")
    sig = scan.point_sigma_mm   # (computed for the cloud's sigma_mm anyway)
    if sig is not None and np.isfinite(sig).any():
        med, p90 = np.nanpercentile(sig, [50, 90])
        print(f"predicted error along the ray (1 sigma): median {med:.3f} mm, 90 % of the points under {p90:.3f} mm "
              "(--max-sigma-mm MM keeps only the points under MM)")

    written = []
    scan.save_ply(out)
    written.append(("cloud", out))
    if xyz_path is not None:
        save_npy(xyz_path, np.ascontiguousarray(scan.xyz, dtype=np.float32))
        written.append(("xyz map", xyz_path))
    mesh = None
    t_mesh = time.perf_counter()
    if mesh_path is not None or preview is not None:
        if args.method == "poisson" and mesh_path is not None:
            print(f"Poisson reconstruction at depth {args.depth} ...", file=sys.stderr, flush=True)
        mesh = scan.mesh_arrays(args.method if mesh_path is not None else "grid", depth=args.depth,
                                smooth=args.smooth)
    t_mesh = (time.perf_counter() - t_mesh) * 1e3
    if mesh_path is not None:
        from ..mesh import write_mesh

        write_mesh(mesh_path, mesh)
        written.append((f"{args.method} mesh ({mesh.n_vertices} vertices, {mesh.n_triangles} triangles)", mesh_path))
    if preview is not None:
        from ..preview.scan import write_scan_previews

        print(f"drawing previews into {preview} ...", file=sys.stderr, flush=True)
        preview.mkdir(exist_ok=True)
        for p in write_scan_previews(scan, preview, camera=cam, mesh=mesh):
            written.append(("preview", p))
    tm = dict(scan.timings_ms)
    tm.pop("total", None)
    timing = ", ".join(f"{k} {v:.0f}" for k, v in tm.items())
    if mesh is not None:
        timing += f", mesh {t_mesh:.0f}"
    print(f"time (ms): load {1e3 * (t_load - t_start):.0f}, setup {1e3 * (t_setup - t_load):.0f}, {timing}, "
          f"command {1e3 * (time.perf_counter() - t_start):.0f}")
    for what, path in written:
        print(f"wrote {path}  ({what})")
    sys.stdout.flush()
    return 0
