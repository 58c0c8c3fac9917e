"""How far two calibration files disagree.

For camera pixels on a grid and every light plane both files hold (matched by index), the point
the scanner would report is triangulated with A and with B; where A's point lies within the
working depth range, their distance is the disagreement (median / 95th percentile / max, mm).
The camera models are compared too: intrinsic differences (B - A) and the pixel distance after
back-projecting with A (at several depths in the range) and projecting with B.  Camera-only
files (from 'gbcal camera') get the camera comparison alone.

Example:
  gbcal diff monday.yaml friday.yaml --depth-mm 500 900
"""
from __future__ import annotations

HELP = "how far two calibrations disagree (mm over the working volume)"


def add_arguments(p):
    p.add_argument("a", metavar="A.yaml", help="first calibration file")
    p.add_argument("b", metavar="B.yaml", help="second calibration file")
    p.add_argument("--depth-mm", "--volume", dest="depth_mm", type=float, nargs=2, metavar=("MIN", "MAX"),
                   default=None, help="working depth range z in mm (default 400 1000)")
    p.add_argument("--step-px", type=float, default=None, help="pixel grid step (default 8)")


def run(args) -> int:
    from gbscan.calibfile import load_calibration

    from ..diff import DEFAULT_DEPTH_MM, DEFAULT_STEP_PX, compare

    depth = tuple(args.depth_mm) if args.depth_mm else DEFAULT_DEPTH_MM
    step = DEFAULT_STEP_PX if args.step_px is None else args.step_px
    a = load_calibration(args.a, require_planes=False)
    b = load_calibration(args.b, require_planes=False)
    r = compare(a, b, depth_mm=depth, step_px=step)
    d = r["intrinsics"]
    print(f"A = {args.a}\nB = {args.b}")
    print("intrinsics (B - A): " + ", ".join(f"{k} {d[k]:+.3f} px" for k in ("fx", "fy", "cx", "cy")) + "; "
          + ", ".join(f"{k} {d[k]:+.2e}" for k in ("k1", "k2", "p1", "p2", "k3")))
    rp = r["reprojection_px"]
    print(f"camera reprojection (A back-projected at {depth[0]:g}-{depth[1]:g} mm, B projected): "
          f"median {rp.median:.3f} px, 95% {rp.p95:.3f} px, max {rp.max:.3f} px")
    pl = r["planes"]
    if r["distance_mm"] is None:
        if a.n_planes or b.n_planes:
            print(f"light planes: none in common (A has {a.n_planes}, B has {b.n_planes}); no 3D comparison")
        else:
            print("light planes: none (camera-only files); no 3D comparison")
        return 0
    dm = r["distance_mm"]
    extra = ""
    if pl["only_a"] or pl["only_b"]:
        extra = f" ({pl['only_a']} only in A, {pl['only_b']} only in B, ignored)"
    print(f"light planes: {pl['common']} in common{extra}")
    if dm.count == 0:
        print(f"3D distance: no plane crosses the {depth[0]:g}-{depth[1]:g} mm depth range of A's rays")
        return 0
    print(f"3D distance over {dm.count} (pixel, plane) points at depth {depth[0]:g}-{depth[1]:g} mm: "
          f"median {dm.median:.4f} mm, 95% {dm.p95:.4f} mm, max {dm.max:.4f} mm")
    return 0
