#!/usr/bin/env python
"""Speed of the scan pipeline: scanner setup (rays), decode, triangulate, clean (+ normals), grid
mesh, the writers, and the whole ``gbscan scan`` command as a user runs it.

    python scripts/bench_scan.py [--scene plane|sphere|head] [--repeats 7] [--sizes 640x480 1280x1024]
                                 [--no-command]

Frames come from the simulated rig (typical preset) with its exact calibration; the 1280x1024
camera has the same horizontal field of view as the paper's 640x480 one.  Prints the median
milliseconds per stage per frame size ("triangulate" is the scanner's frame kernel,
"triangulate ref" the float64 reference :func:`gbscan.triangulate.triangulate`; "clean" and
"normals" the public functions on the whole frame, "clean in scan()" the cleaning as the scanner
runs it, on the decoded pixels' window when that is small; "decode (stream)" the frames of one
stream as a Scanner decodes them, the camera's measurements reused between every 16th frame
(:class:`gbscan.decode.StreamMemo`): "decode" times the ratio of the two means over whole cycles
(the measuring frames included) alternating with single frames in one loop; the
write stages include the fsync of the atomic write), then the wall time of the command in a fresh process
(Python start-up and imports included), without and with --mesh (.ply, .obj, .stl).  Numbers
depend on the machine and on its load: run it on a quiet machine (``uptime`` load < 1.5).
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # measure this checkout, whatever the environment's install points at
    sys.path.insert(0, str(ROOT))
if str(ROOT / "scripts") not in sys.path:  # bench_decode's stream timing (run as a script: already there)
    sys.path.insert(0, str(ROOT / "scripts"))


def rig_of_size(width: int, height: int):
    from gbscan.rig import paper_rig

    return paper_rig(camera_px=(width, height))   # the same lens, a sensor of width x height pixels


def scene_of(name: str):
    from gbscan import sim

    return {"plane": lambda: sim.scenes.plane(650.0, tilt_deg=(0.0, 20.0)),
            "sphere": lambda: sim.scenes.sphere(),
            "head": lambda: sim.scenes.head()}[name]()


def median_ms(fn, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append((time.perf_counter() - t) * 1e3)
    return statistics.median(ts)


def bench_size(width: int, height: int, scene: str, repeats: int, workdir: Path, command: bool = True) -> dict:
    from gbscan import sim
    from gbscan.calibfile import calibration_from_rig, save_calibration
    from gbscan.clean import clean, grid_normals
    from gbscan.decode import DecodeParams, decode
    from gbscan.io import write_png
    from gbscan.mesh import grid_mesh, write_mesh
    from gbscan.pattern import PatternSpec, render_pattern
    from gbscan.scan import Scanner
    from gbscan.triangulate import triangulate

    spec = PatternSpec()
    rig = rig_of_size(width, height)
    print(f"[{width}x{height}] rendering the {scene} scene ...", file=sys.stderr, flush=True)
    r = sim.render(rig, scene_of(scene), render_pattern(spec), sim.preset("typical"), seed=0)
    calib = calibration_from_rig(rig, spec)
    scanner = Scanner(calib)  # warm-up (numba compilation or cache load)
    params = DecodeParams()
    sm = decode(r.image, spec, params)
    xyz = np.empty((height, width, 3), np.float32)
    col = np.where(sm.valid, sm.column, np.nan)
    scanner.triangulator(col, out=xyz)
    rays = scanner.rays
    triangulate(rays, col, scanner.planes, out=xyz)
    res = clean(xyz, sm.confidence, scanner.clean_params)
    scan = scanner.scan(r.image)
    mesh = grid_mesh(scan.xyz, scan.valid, normals=scan.normals_map)
    for suffix in ("ply", "obj", "stl"):
        write_mesh(workdir / f"warm.{suffix}", mesh)
    scan.save_ply(workdir / "warm_cloud.ply")
    print(f"[{width}x{height}] timing ({repeats} repeats) ...", file=sys.stderr, flush=True)
    out = {
        "points": scan.n_points,
        "setup (rays)": median_ms(lambda: Scanner(calib), max(3, repeats // 2)),
        "decode": median_ms(lambda: decode(r.image, spec, params), repeats),
        "triangulate": median_ms(lambda: scanner.triangulator(col, out=xyz), repeats),
        "triangulate ref": median_ms(lambda: triangulate(rays, col, scanner.planes, out=xyz), repeats),
        "clean": median_ms(lambda: clean(xyz, sm.confidence, scanner.clean_params), repeats),
        "normals": median_ms(lambda: grid_normals(xyz, res.kept, 2), repeats),
        "mesh": median_ms(lambda: grid_mesh(scan.xyz, scan.valid, normals=scan.normals_map), repeats),
        "scan()": median_ms(lambda: scanner.scan(r.image), repeats),
    }
    # frames of one stream, as a Scanner decodes them (gbscan.decode.StreamMemo: the camera's
    # measurements made every 16th frame): means over whole cycles, alternating with single frames
    # (bench_decode.stream_ms); the stream's figure is the single frame's median times their ratio
    from bench_decode import stream_ms

    one, stream = stream_ms(r.image, spec, params, 2 * repeats)
    out["decode (stream)"] = out["decode"] * stream / one
    # the cleaning as scan() runs it: on the decoded pixels' window when that is small (an object
    # before darkness), with the masking of the rejected points (the rows above: the whole frame)
    tim = [scanner.scan(r.image).timings_ms for _ in range(repeats)]
    out["clean in scan()"] = statistics.median(t["clean"] + t["normals"] for t in tim)
    out["scan()+mesh"] = out["scan()"] + out["mesh"]
    out["write cloud"] = median_ms(lambda: scan.save_ply(workdir / "cloud_b.ply"), repeats)
    for suffix in ("ply", "obj", "stl"):
        out[f"write .{suffix}"] = median_ms(lambda: write_mesh(workdir / f"mesh_b.{suffix}", mesh),
                                            max(3, repeats // 2))
    out["triangles"] = mesh.n_triangles
    if not command:
        return out
    img = write_png(workdir / f"frame_{width}x{height}.png", r.image)
    cal = save_calibration(workdir / f"calib_{width}x{height}.yaml", calib)
    base = [sys.executable, "-m", "gbscan.cli", "scan", str(img), "--calib", str(cal),
            "-o", str(workdir / "cloud.ply")]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    variants = [("command", [])] + [(f"command --mesh .{x}", ["--mesh", str(workdir / f"mesh.{x}")])
                                    for x in ("ply", "obj", "stl")]
    subprocess.run(base, capture_output=True, text=True, env=env)  # numba caches of a fresh checkout
    for label, extra in variants:
        ts = []
        for _ in range(max(3, repeats // 2)):
            t = time.perf_counter()
            p = subprocess.run(base + extra, capture_output=True, text=True, env=env)
            ts.append((time.perf_counter() - t) * 1e3)
            if p.returncode != 0:
                raise SystemExit(f"gbscan scan failed: {p.stderr.strip()}")
        out[label] = statistics.median(ts)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", choices=("plane", "sphere", "head"), default="plane")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--sizes", nargs="+", default=["640x480", "1280x1024"])
    ap.add_argument("--no-command", action="store_true", help="skip the command runs (fresh processes)")
    args = ap.parse_args(argv)
    sizes = [tuple(int(v) for v in s.lower().split("x")) for s in args.sizes]
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for w, h in sizes:
            rows[f"{w}x{h}"] = bench_size(w, h, args.scene, args.repeats, Path(tmp), command=not args.no_command)
    keys = ["points", "triangles", "setup (rays)", "decode", "decode (stream)", "triangulate", "triangulate ref", "clean", "normals", "clean in scan()",
            "mesh", "scan()", "scan()+mesh", "write cloud", "write .ply", "write .obj", "write .stl", "command",
            "command --mesh .ply", "command --mesh .obj", "command --mesh .stl"]
    print(f"median ms per frame, scene '{args.scene}', typical preset ({args.repeats} repeats), "
          f"load average {os.getloadavg()[0]:.2f}")
    print(f"{'stage':<20}" + "".join(f"{k:>14}" for k in rows))
    for k in keys:
        if not all(k in rows[s] for s in rows):
            continue
        vals = [rows[s][k] for s in rows]
        print(f"{k:<20}" + "".join(f"{v:>14.0f}" if k in ("points", "triangles") else f"{v:>14.1f}" for v in vals))
    print("decode+triangulate: " + ", ".join(f"{s} {r['decode'] + r['triangulate']:.1f} ms" for s, r in rows.items()))
    print("decode+triangulate in a stream (a Scanner's frames; mean over whole cycles of its camera measurements): "
          + ", ".join(f"{s} {r['decode (stream)'] + r['triangulate']:.1f} ms" for s, r in rows.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
