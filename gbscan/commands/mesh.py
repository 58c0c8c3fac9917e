"""Mesh a saved point cloud: grid (the organised pixel grid stored by 'gbscan scan') or Poisson.

--method grid needs the per-point camera pixel (PLY vertex properties 'row' and 'col' and the
header comment 'gbscan_grid W H') that 'gbscan scan' writes; it triangulates neighbouring pixels
and cuts the surface at depth jumps (--max-jump).  --method poisson works on any PLY cloud with
normals (open3d's screened Poisson, trimmed where the data is thin: --trim).  The output format
follows the name: .ply (binary, vertex normals; the cloud's colours -- the scan's grey texture --
as vertex colours), .obj, .stl (binary, triangle normals).
"""
from __future__ import annotations

import sys
import time

HELP = "mesh a point cloud (grid or poisson) -> .ply / .obj / .stl"


def add_arguments(p):
    p.add_argument("cloud", help="point cloud .ply (from 'gbscan scan')")
    p.add_argument("-o", "--output", required=True, help="output mesh (.ply, .obj or .stl)")
    p.add_argument("--method", choices=("grid", "poisson"), default="grid",
                   help="grid (default; needs the pixel grid gbscan stores) or poisson")
    p.add_argument("--depth", type=int, default=9, help="Poisson octree depth (default 9)")
    p.add_argument("--trim", type=float, default=0.05,
                   help="Poisson: drop this fraction of least-supported vertices (default 0.05)")
    p.add_argument("--max-jump", type=float, default=0.01,
                   help="grid: no triangle across a depth jump above this fraction of depth (default 0.01)")
    p.add_argument("--smooth", type=int, default=0, metavar="N", help="Taubin smoothing iterations (default 0)")


def run(args) -> int:
    t0 = time.perf_counter()
    from ..errors import GBError
    from ..mesh import grid_mesh, poisson_mesh, read_cloud_ply, taubin_smooth, write_mesh
    from .scan import _check_output

    out = _check_output(args.output, (".ply", ".obj", ".stl"), "mesh")
    if args.smooth < 0:
        raise GBError(f"--smooth must be >= 0, got {args.smooth}")
    if not 0 <= args.trim < 1:
        raise GBError(f"--trim must be in [0, 1), got {args.trim}")
    if args.max_jump <= 0:
        raise GBError(f"--max-jump must be > 0, got {args.max_jump}")
    cloud = read_cloud_ply(args.cloud)
    if len(cloud.points) == 0:
        raise GBError(f"point cloud {args.cloud} has no points")
    if args.method == "grid":
        if not cloud.organised:
            raise GBError(f"point cloud {args.cloud} has no pixel grid (vertex row/col and a 'gbscan_grid' "
                          "comment, written by 'gbscan scan'); use --method poisson")
        xyz, valid = cloud.grid()
        mesh = grid_mesh(xyz, valid, max_jump=args.max_jump, normals=cloud.normal_grid(), colors=cloud.color_grid())
    else:
        if cloud.normals is None:
            raise GBError(f"point cloud {args.cloud} has no normals (nx ny nz); Poisson meshing needs them")
        print(f"Poisson reconstruction of {len(cloud.points)} points at depth {args.depth} ...", file=sys.stderr,
              flush=True)
        mesh = poisson_mesh(cloud.points, cloud.normals, depth=args.depth, density_quantile=args.trim,
                            colors=cloud.colors)
    if args.smooth:
        print(f"Taubin smoothing, {args.smooth} iterations ...", file=sys.stderr, flush=True)
        mesh = taubin_smooth(mesh, args.smooth)
    if mesh.n_triangles == 0:
        raise GBError(f"meshing {args.cloud} gave no triangles (too few neighbouring points; "
                      "try --method poisson or a larger --max-jump)")
    write_mesh(out, mesh)
    print(f"{args.cloud}: {len(cloud.points)} points -> {args.method} mesh, {mesh.n_vertices} vertices, "
          f"{mesh.n_triangles} triangles ({1e3 * (time.perf_counter() - t0):.0f} ms)")
    print(f"wrote {out}")
    return 0
