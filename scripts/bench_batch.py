"""Frames per second of ``gbscan batch`` end to end (read, decode, triangulate, clean, write).

A 640x480 sequence of the simulated paper rig (a sphere moving across in front of a wall,
"typical" conditions) is rendered once (the unique poses are cycled to make a longer sequence;
the cost of a frame does not depend on having seen it before), written as PNG frames and as an
FFV1 video, and run through the batch engine:

* one scan in this process (the per-frame cost without any batch machinery),
* local workers 1 and 2, frames read by the workers (folder) and by the parent (folder, video),
* a two-worker ``dask.distributed.LocalCluster`` on loopback.

    python scripts/bench_batch.py [--frames 48] [--unique 6] [--cache DIR]

Prints one line per configuration and the 2-vs-1 scaling ratios.  Figures depend on the load
of the machine: run it on an otherwise idle one.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # measure this checkout, whatever the environment's install points at
    sys.path.insert(0, str(ROOT))


def render_sequence(n_unique: int, supersample: int = 1, seed: int = 0) -> list[np.ndarray]:
    """``n_unique`` 640x480 RGB frames: a 100 mm sphere moving left to right 650 mm away, before a wall."""
    from gbscan import sim
    from gbscan.pattern import PatternSpec, render_pattern

    rig = sim.paper_rig()
    proj = render_pattern(PatternSpec())
    cond = dataclasses.replace(sim.preset("typical"), supersample=supersample)
    frames = []
    for i in range(n_unique):
        x = -80.0 + 160.0 * i / max(1, n_unique - 1)
        scene = sim.combine(sim.scenes.plane(900.0), sim.scenes.sphere((x, 0.0, 650.0), 100.0))
        frames.append(sim.render(rig, scene, proj, cond, seed=seed + i).image)
        print(f"rendered frame {i + 1}/{n_unique}", file=sys.stderr)
    return frames


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=48, help="sequence length (default 48)")
    ap.add_argument("--unique", type=int, default=6, help="distinct rendered poses (default 6)")
    ap.add_argument("--cache", help="folder to keep the rendered poses in between runs")
    ap.add_argument("--no-dask", action="store_true")
    args = ap.parse_args(argv)

    from gbscan import sim
    from gbscan.batch import Processor, ScannerProcessor, read_manifest, run_batch
    from gbscan.calibfile import calibration_from_rig, save_calibration
    from gbscan.frames import open_frames, write_video
    from gbscan.io import read_image_rgb, write_png
    from gbscan.pattern import PatternSpec
    from gbscan.scan import Scanner

    with tempfile.TemporaryDirectory(prefix="bench_batch_") as tmp:
        tmp = Path(tmp)
        cache = Path(args.cache) if args.cache else tmp / "poses"
        cache.mkdir(parents=True, exist_ok=True)
        poses = sorted(cache.glob("pose_*.png"))
        if len(poses) < args.unique:
            for i, img in enumerate(render_sequence(args.unique)):
                write_png(cache / f"pose_{i:03d}.png", img)
            poses = sorted(cache.glob("pose_*.png"))
        unique = [read_image_rgb(p) for p in poses[: args.unique]]
        seq = [unique[i % len(unique)] for i in range(args.frames)]
        folder = tmp / "frames"
        folder.mkdir()
        for i, img in enumerate(seq):
            write_png(folder / f"frame_{i:04d}.png", img)
        video = write_video(tmp / "seq.mkv", seq)
        calib_path = save_calibration(tmp / "calib.yaml", calibration_from_rig(sim.paper_rig(), PatternSpec()))
        print(f"sequence: {len(seq)} frames 640x480 ({len(unique)} distinct), folder + FFV1 video "
              f"{os.path.getsize(video) / 1e6:.1f} MB; {os.cpu_count()} cores; load average "
              f"{os.getloadavg()[0]:.1f}")

        scanner = Scanner(calib_path)
        scanner.scan(seq[0])
        t, c = time.perf_counter(), time.process_time()
        scans = [scanner.scan(img) for img in unique]
        ms = (time.perf_counter() - t) * 1e3 / len(unique)
        cpu = (time.process_time() - c) * 1e3 / len(unique)
        print(f"{'Scanner.scan in-process':42s} {ms:7.1f} ms/frame  {1e3 / ms:6.1f} frames/s  "
              f"(CPU {cpu:.0f} ms/frame, points/frame {int(np.mean([s.n_points for s in scans]))}, no I/O)")
        stages = {k: np.mean([s.timings_ms.get(k, 0.0) for s in scans]) for k in scans[0].timings_ms}
        print("  stages (ms): " + ", ".join(f"{k} {v:.0f}" for k, v in stages.items()))
        dec = {k: np.mean([s.stripemap.stats["ms"].get(k, 0.0) for s in scans])
               for k in scans[0].stripemap.stats.get("ms", {})}
        print("  decode (ms): " + ", ".join(f"{k} {v:.0f}" for k, v in dec.items()))

        proc: Processor = ScannerProcessor(calib_path)
        results = {}

        def bench(name, src_path, cluster_pids=(), **kw):
            out = tmp / f"out_{len(results)}"
            c0, o0 = _cpu_s(cluster_pids), os.times()
            with open_frames(src_path) as src:
                s = run_batch(src, proc, out, progress=False, **kw)
            c1, o1 = _cpu_s(cluster_pids), os.times()
            rows = read_manifest(s.manifest).values()
            cpu = np.mean([float(r["cpu_ms"]) for r in rows])
            wall = np.mean([float(r["time_ms"]) for r in rows])
            n = max(1, s.ok + s.failed)
            parent = 1e3 * ((o1.user - o0.user) + (o1.system - o0.system)) / n
            extra = f"parent {parent:.1f} ms CPU/frame"
            if cluster_pids:
                extra += f", Dask processes beyond the tasks {1e3 * (c1 - c0) / n - cpu:.1f} ms CPU/frame"
            results[name] = s.steady_frames_per_s
            print(f"{name:42s} {1e3 / s.steady_frames_per_s:7.1f} ms/frame  {s.steady_frames_per_s:6.1f} frames/s  "
                  f"({s.ok} ok, {s.failed} failed; {s.frames_per_s:.1f} frames/s incl. "
                  f"{s.first_result_s:.1f} s start-up; per frame in a worker: wall {wall:.0f} ms, "
                  f"CPU {cpu:.0f} ms; {extra}; load {os.getloadavg()[0]:.1f})", flush=True)

        bench("local 1 worker, folder, worker reads", folder, workers=1, read_in="worker")
        bench("local 2 workers, folder, worker reads", folder, workers=2, read_in="worker")
        bench("local 2 workers, folder, parent reads", folder, workers=2, read_in="parent")
        bench("local 2 workers, video (parent decodes)", video, workers=2)
        bench("local 2 workers, folder, + ply", folder, workers=2, ply=True)
        if not args.no_dask:
            from dask.distributed import LocalCluster

            with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                              dashboard_address=None) as cluster:
                import psutil

                pids = [p.pid for p in psutil.Process().children(recursive=True)]  # nannies + workers
                with open_frames(folder) as src:  # warm the workers (set-up, compilation) outside the figures
                    run_batch(src, proc, tmp / "warm", progress=False, stop=2, scheduler=cluster.scheduler_address)
                bench("dask LocalCluster 2 workers, folder", folder, pids, scheduler=cluster.scheduler_address)
                bench("dask LocalCluster 2 workers, video", video, pids, scheduler=cluster.scheduler_address)
        one = results["local 1 worker, folder, worker reads"]
        print(f"scaling 2 vs 1 local workers: {results['local 2 workers, folder, worker reads'] / one:.2f}x")
        if not args.no_dask:
            print(f"scaling dask 2 workers vs 1 local worker: "
                  f"{results['dask LocalCluster 2 workers, folder'] / one:.2f}x")
    return 0


def _cpu_s(pids) -> float:
    """CPU seconds (user + system) used so far by the processes ``pids`` (those still alive)."""
    if not pids:
        return 0.0
    import psutil

    total = 0.0
    for pid in pids:
        try:
            t = psutil.Process(pid).cpu_times()
            total += t.user + t.system
        except psutil.Error:
            pass
    return total


if __name__ == "__main__":
    sys.exit(main())
