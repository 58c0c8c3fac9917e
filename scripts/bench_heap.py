#!/usr/bin/env python
"""What keeping freed memory (gbscan.heap) is worth: scans of two frame sizes in turn, per malloc mode.

    python scripts/bench_heap.py [--repeats 30] [--sizes 1280x960,640x480] [--scene plane|sphere|head]

Renders one frame per size (typical preset, supersample 1), then, in a fresh process for each mode
(``GBSCAN_MALLOC=keep``: what the commands and ``Scanner`` set, see ``gbscan/heap.py``;
``GBSCAN_MALLOC=system``: glibc's adaptive thresholds), builds a ``Scanner`` per size and scans the
frames in turn ``--repeats`` times.  Prints per mode the median ``Scanner.scan`` milliseconds of
each size, the minor page faults per round (one frame of each size) and the resident size at the
end.  A process that scans one size only may settle either way; alternating sizes is what shows
glibc handing the memory back.  Figures depend on the load of the machine.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # measure this checkout, whatever the environment's install points at
    sys.path.insert(0, str(ROOT))


def _sizes(text: str) -> list[tuple[int, int]]:
    from gbscan.cli_common import camera_size

    return [camera_size(t) for t in text.split(",")]


def worker(frames: str, repeats: int) -> None:
    """Child process: scan the saved frames in turn; one JSON line on stdout."""
    import resource
    import statistics
    import time

    import numpy as np

    from gbscan.calibfile import calibration_from_rig
    from gbscan.heap import keep_freed_memory
    from gbscan.pattern import PatternSpec
    from gbscan.rig import paper_rig
    from gbscan.scan import Scanner

    data = np.load(frames)
    images = [data[k] for k in sorted(data.files)]
    scanners = [Scanner(calibration_from_rig(paper_rig(camera_px=(im.shape[1], im.shape[0])), PatternSpec()))
                for im in images]
    for sc, im in zip(scanners, images):   # warm-up: kernels loaded, first allocations made
        sc.scan(im)
    times = [[] for _ in images]
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(repeats):
        for k, (sc, im) in enumerate(zip(scanners, images)):
            t = time.perf_counter()
            sc.scan(im)
            times[k].append((time.perf_counter() - t) * 1e3)
    faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0) / repeats
    with open("/proc/self/statm") as f:
        rss_mb = int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6
    print(json.dumps({"ms": [statistics.median(t) for t in times], "faults": faults, "rss_mb": rss_mb,
                      "kept": keep_freed_memory()}))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--sizes", default="1280x960,640x480", type=_sizes, help="camera sizes scanned in turn")
    ap.add_argument("--scene", default="plane", choices=("plane", "sphere", "head"))
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        worker(args.worker, args.repeats)
        return 0

    import dataclasses

    import numpy as np

    from gbscan import sim
    from gbscan.pattern import PatternSpec, render_pattern

    scene = {"plane": lambda: sim.scenes.plane(650.0, tilt_deg=(0.0, 20.0)), "sphere": sim.scenes.sphere,
             "head": sim.scenes.head}[args.scene]()
    cond = dataclasses.replace(sim.preset("typical"), supersample=1)
    with tempfile.TemporaryDirectory() as tmp:
        frames = Path(tmp) / "frames.npz"
        images = {}
        for k, (w, h) in enumerate(args.sizes):
            print(f"rendering {args.scene} {w}x{h} ...", file=sys.stderr, flush=True)
            images[f"f{k}"] = sim.render(sim.paper_rig(camera_px=(w, h)), scene, render_pattern(PatternSpec()),
                                         cond, seed=0).image
        np.savez(frames, **images)
        names = " / ".join(f"{w}x{h}" for w, h in args.sizes)
        print(f"# Scanner.scan of {names} in turn ({args.scene}, typical), median of {args.repeats} rounds")
        for mode in ("keep", "system"):
            print(f"scanning, GBSCAN_MALLOC={mode} ...", file=sys.stderr, flush=True)
            out = subprocess.run([sys.executable, __file__, "--worker", str(frames), "--repeats", str(args.repeats)],
                                 env={**os.environ, "GBSCAN_MALLOC": mode}, capture_output=True, text=True)
            if out.returncode != 0:
                print(out.stderr, file=sys.stderr)
                return 1
            r = json.loads(out.stdout.strip().splitlines()[-1])
            ms = " / ".join(f"{m:.1f}" for m in r["ms"])
            label = "freed memory kept" if r["kept"] else "glibc adaptive"
            print(f"{mode:6s} ({label:17s}): {ms} ms, {r['faults']:.0f} page faults a round, "
                  f"resident {r['rss_mb']:.0f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
