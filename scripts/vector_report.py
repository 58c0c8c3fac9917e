"""Which loops of the decoder's kernels did LLVM vectorise on this machine, and why not the others?

    python scripts/vector_report.py [--width 640|1280] [--missed | --all] [--out report.txt]

The kernels' row loops are written so that LLVM vectorises them (see ``gbscan/kernels/__init__``,
"Row loops that vectorise").  Whether it does depends on the CPU numba compiles for: a loop that
vectorises with AVX-512 can stay scalar with AVX2 alone (a byte read on one branch of a select,
an int64 -> float64 conversion), and run several times slower.  This script compiles the kernels
afresh (an empty numba cache in a temporary folder, debug line information on) in a child process
with LLVM's loop-vectoriser remarks switched on, decodes simulated frames (``--width 1280``:
1280x1024 frames, so the resampled decoder's kernels compile too), scans one and writes its cloud
and meshes, and prints, per source line of ``gbscan/kernels`` and ``gbscan/geomkernels.py`` that
holds a loop LLVM looked at:

* by default the loops LLVM **could** have vectorised but did not, in no function they were inlined
  into, because "the cost-model indicates that vectorization is not beneficial" on this CPU: the
  ones to look at (often a select that reads memory on one branch only, or a conversion this CPU
  has no vector instruction for);
* with ``--missed`` every line never vectorised, with LLVM's reasons (most are loops over runs,
  segments or junctions, sequential by nature, or remarks of early passes on a loop body whose
  loop was vectorised later under its header's line);
* with ``--all`` every line, vectorised ones with their width.

It takes a few minutes (every kernel compiles).  The numba cache of the checkout is not touched.
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
KERNELS = ROOT / "gbscan" / "kernels"
#: the compiled code looked at: the decoder's and cleaning's kernels, and the geometry's (rays,
#: triangulation, meshes, writers)
FILES = {p.name: p for p in sorted(KERNELS.glob("*.py"))} | {"geomkernels.py": ROOT / "gbscan" / "geomkernels.py"}
REMARK = re.compile(r"^remark: (?P<file>[\w.]+):(?P<line>\d+):\d+: (?P<msg>.*)$")


def child(width: int) -> int:
    """Compile and run the decoder, a scan and the writers once with the remarks on (LLVM writes
    them to stderr)."""
    import llvmlite.binding as ll

    for opt in ("-pass-remarks=loop-vectorize", "-pass-remarks-missed=loop-vectorize",
                "-pass-remarks-analysis=loop-vectorize"):
        ll.set_option("", opt)
    sys.path.insert(0, str(ROOT))
    sys.path.insert(0, str(ROOT / "scripts"))
    from bench_decode import frames
    from gbscan import sim
    from gbscan.calibfile import calibration_from_rig
    from gbscan.decode import decode
    from gbscan.mesh import grid_mesh, write_mesh
    from gbscan.pattern import PatternSpec
    from gbscan.scan import Scanner

    decode(frames(width, "plane").image, PatternSpec())
    head = frames(width, "head").image
    decode(head, PatternSpec())
    # a whole scan (rays, triangulation, cleaning, normals), its mesh and the writers
    h = head.shape[0]
    rig = sim.paper_rig() if width == 640 else sim.paper_rig(camera_px=(width, h))
    scan = Scanner(calibration_from_rig(rig, PatternSpec())).scan(head)
    mesh = grid_mesh(scan.xyz, scan.valid, normals=scan.normals_map)
    with tempfile.TemporaryDirectory() as d:
        scan.save_ply(Path(d) / "cloud.ply")
        for suffix in ("ply", "obj", "stl"):
            write_mesh(Path(d) / f"mesh.{suffix}", mesh)
    return 0


def parse(stderr: str) -> dict[tuple[str, int], dict]:
    """Per (file, line) of the compiled code (FILES): vectorisation widths seen and reasons for not."""
    out: dict[tuple[str, int], dict] = defaultdict(lambda: {"widths": set(), "why": set()})
    for raw in stderr.splitlines():
        m = REMARK.match(raw.strip())
        if not m or m["file"] not in FILES or int(m["line"]) == 0:
            continue
        entry = out[(m["file"], int(m["line"]))]   # (a bare "loop not vectorized": seen, no reason)
        msg = m["msg"]
        w = re.search(r"vectorization width: (\d+)", msg)
        if msg.startswith("vectorized loop") and w:
            entry["widths"].add(int(w[1]))
        elif msg != "loop not vectorized":
            entry["why"].add(msg.replace("loop not vectorized: ", ""))
    return out


def source_line(file: str, line: int) -> tuple[str, str]:
    """The function a line belongs to and the line's text."""
    lines = FILES[file].read_text().splitlines()
    fn = "?"
    for i in range(min(line, len(lines)) - 1, -1, -1):
        if lines[i].startswith("def "):
            fn = lines[i][4:lines[i].index("(")]
            break
    return fn, lines[line - 1].strip() if 0 < line <= len(lines) else ""


COST_MODEL = "the cost-model indicates that vectorization is not beneficial"


def report(found: dict, show: str = "cost-model") -> str:
    """The report; ``show``: "cost-model" (never vectorised, refused by the cost model), "missed"
    (never vectorised) or "all"."""
    rows = []
    n_vec = sum(1 for v in found.values() if v["widths"])
    for (file, line), v in sorted(found.items()):
        if show != "all" and (v["widths"] or (show == "cost-model" and COST_MODEL not in v["why"])):
            continue
        fn, text = source_line(file, line)
        if v["widths"]:
            status = "vectorised, width " + "/".join(str(w) for w in sorted(v["widths"]))
        else:
            status = "NOT vectorised: " + ("; ".join(sorted(v["why"])) or "(no reason given)")
        rows.append(f"{file}:{line} {fn}: {text}\n    {status}")
    which = {"all": "all of them", "missed": "the others",
             "cost-model": "the others that the cost model refused"}[show]
    head = (f"# {len(found)} loop lines of gbscan/kernels and geomkernels.py seen by LLVM's loop vectoriser, {n_vec} vectorised in at "
            f"least one function they were inlined into; below {which} ({len(rows)})")
    return "\n".join([head] + rows) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--width", type=int, choices=(640, 1280), default=640,
                    help="simulated frame width (1280: the resampled decoder's kernels too)")
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--missed", action="store_true", help="every line never vectorised, whatever the reason")
    g.add_argument("--all", action="store_true", help="every line, vectorised ones too")
    ap.add_argument("--out", help="also write the report to this file")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        return child(args.width)
    with tempfile.TemporaryDirectory(prefix="gbscan-vec-") as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache, NUMBA_DEBUGINFO="1", PYTHONWARNINGS="ignore")
        print("compiling every kernel afresh with LLVM's remarks on (a few minutes) ...", file=sys.stderr, flush=True)
        r = subprocess.run([sys.executable, __file__, "--child", "--width", str(args.width)], env=env,
                           capture_output=True, text=True)
    if r.returncode != 0:
        print(r.stderr[-3000:], file=sys.stderr)
        print("vector_report: the decode with remarks failed (its error above)", file=sys.stderr)
        return 1
    text = report(parse(r.stderr), "all" if args.all else "missed" if args.missed else "cost-model")
    sys.stdout.write(text)
    if args.out:
        Path(args.out).write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
