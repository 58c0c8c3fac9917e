"""Speed and memory of the single-shot decoder, with peers on equivalent frames.

    python scripts/bench_decode.py [--runs N] [--threads 1] [--scene plane|head|sphere|multi_object] [--preset typical]

Renders a plane at 650 mm (or ``--scene``: the head, the sphere, the multi-object scene, at their
default distance; ``--preset`` the conditions) once per size (640x480 with the paper's rig; 1280x1024 with the same
lens scaled, supersample 1 to keep rendering short), then prints the median milliseconds per
decoder stage and in total over N runs, and peak memory (tracemalloc: numpy buffers; OpenCV's
own buffers are not traced).  Peers on the same sizes:

* OpenCV FTP (``cv2.structured_light.SinusoidalPattern``, methodId FTP): ``computePhaseMap`` on
  the three frames it requires (shadow mask) + ``unwrapPhaseMap``;
* a per-pixel Gray-code decode in numpy (10 bit images + white + black, threshold at the
  white/black midpoint, Gray -> binary by cumulative XOR) on frames made from the true columns.

Threads are limited to one (``cv2.setNumThreads``, ``numba.set_num_threads``) for the
single-core figures.  The first decode compiles/loads the numba kernels and is not timed.  A
frame whose stripes are wide in the camera (the 1280x1024 one: ~7.4 px per stripe) is decoded
shrunk by default (``DecodeParams.resample``); the script then also times the decoder at the
frame's own size (``--resample never``), its throughput there.  A frame decoded shrunk expands
only the maps a scan reads (column, stripe, confidence, mask); the others are expanded when first
read, and the script prints what reading them as well costs.  A frame whose object stands before
darkness (the head, the sphere) is decoded in its lit window alone (``DecodeParams.crop``: the same
result, or for a frame decoded shrunk a grid starting at the window's corner); the script then
also times the whole frame (``--decode-param crop=false``).

For the default decode also the mean per frame of a stream (:class:`gbscan.decode.StreamMemo`,
as a Scanner and the live scan decode: the camera's resampling factor and lens
aberration measured every 16th frame and reused between), alternating with single frames.

Also printed: CPU milliseconds of the calling thread (less sensitive than wall time to other
processes on the machine), minor page faults per frame (fresh output pages: on this virtual
machine a fault costs about 2 us, i.e. 1-4 ms per frame in a process whose malloc returns freed
memory to the system; ``--malloc keep``, the default, sets it to keep freed memory as the commands
do, :mod:`gbscan.heap`; ``--malloc system`` leaves glibc's adaptive thresholds), and peak
memory in bytes per pixel, measured from a released fast-path workspace
(``gbscan.decode.release_workspace``) so that it counts.  The stage names are decode's
``stats['ms']`` keys (on the fast path "input" is validation and the automatic blur's SNR,
"blur" only the colour-balance sampling, and "classify" includes linearising and blurring: one
streamed pass; compare blur + balance + classify with older figures).  The script measures the gbscan of its own checkout.
"""
from __future__ import annotations

import argparse
import resource
import sys
import time
import tracemalloc
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's gbscan, not another install


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def frames(width: int, scene: str = "plane", preset: str = "typical"):
    from gbscan import sim
    from gbscan.pattern import PatternSpec, render_pattern

    # 640 -> the paper's 640x480 camera; wider: a 5:4 sensor behind the same lens (1280x1024)
    rig = sim.paper_rig(camera_px=(640, 480) if width == 640 else (width, int(round(width * 1024 / 1280))))
    cond = sim.preset(preset)
    if width != 640:
        cond = replace(cond, supersample=1)
    log(f"rendering {scene} {rig.camera.width}x{rig.camera.height} ...")
    sc = sim.scenes.plane(distance_mm=650) if scene == "plane" else getattr(sim.scenes, scene)()
    r = sim.render(rig, sc, render_pattern(PatternSpec()), cond, seed=0)
    return r


def stream_ms(img, spec, prm, runs: int) -> tuple[float, float]:
    """Mean ms per frame of ``decode`` alone and of frames of one stream (a shared
    :class:`gbscan.decode.StreamMemo`), alternating frame by frame over whole cycles of the memo
    (at least ``runs`` frames each)."""
    from gbscan.decode import STREAM_REMEASURE_EVERY, StreamMemo, decode

    memo = StreamMemo()
    n = STREAM_REMEASURE_EVERY * max(2, -(-runs // STREAM_REMEASURE_EVERY))
    one, stream = [], []
    for _ in range(n):
        t = time.perf_counter()
        decode(img, spec, prm)
        one.append(time.perf_counter() - t)
        t = time.perf_counter()
        decode(img, spec, prm, memo=memo)
        stream.append(time.perf_counter() - t)
    return float(np.mean(one)) * 1e3, float(np.mean(stream)) * 1e3


def median_ms(f, runs: int) -> tuple[float, object]:
    out = f()
    ts = []
    for _ in range(runs):
        t = time.perf_counter()
        out = f()
        ts.append((time.perf_counter() - t) * 1e3)
    return float(np.median(ts)), out


def cpu_ms_and_faults(f, runs: int) -> tuple[float, float]:
    """Median CPU ms of this thread and minor page faults per call."""
    f()
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    ts = []
    for _ in range(runs):
        t = time.thread_time()
        f()
        ts.append((time.thread_time() - t) * 1e3)
    return float(np.median(ts)), (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0) / runs


def peak_mb(f) -> float:
    tracemalloc.start()
    f()
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return peak / 2 ** 20


def gray_frames(column: np.ndarray, n_bits: int = 10, seed: int = 0):
    rng = np.random.default_rng(seed)
    col = np.nan_to_num(column, nan=-1).astype(np.int64)
    lit = col >= 0
    gray = np.where(lit, col ^ (col >> 1), 0)
    imgs = []
    for b in range(n_bits - 1, -1, -1):
        bit = (gray >> b) & 1
        imgs.append(np.clip(30 + 170 * bit * lit + rng.normal(0, 2, col.shape), 0, 255).astype(np.uint8))
    white = np.clip(30 + 170 * lit + rng.normal(0, 2, col.shape), 0, 255).astype(np.uint8)
    black = np.clip(30 + rng.normal(0, 2, col.shape), 0, 255).astype(np.uint8)
    return imgs, white, black


def gray_decode(imgs, white, black):
    mid = (white.astype(np.int16) + black) // 2
    valid = (white.astype(np.int16) - black) > 20
    code = np.zeros(white.shape, np.int32)
    acc = np.zeros(white.shape, np.int32)
    for im in imgs:  # Gray -> binary: b_i = b_{i-1} xor g_i
        g = (im > mid).astype(np.int32)
        acc ^= g
        code = (code << 1) | acc
    return np.where(valid, code, -1)


def ftp_peer(image_rgb: np.ndarray):
    import cv2

    sl = cv2.structured_light
    H, W = image_rgb.shape[:2]
    p = sl.SinusoidalPattern.Params()
    p.width, p.height = W, H
    p.nbrOfPeriods = max(8, W // 16)
    p.methodId = sl.FTP
    p.setMarkers = False
    p.horizontal = False
    s = sl.SinusoidalPattern.create(p)
    ok, pats = s.generate()
    caps = [np.ascontiguousarray(x) for x in pats]  # equivalent frames: FTP needs three (shadow mask)

    def run():
        w, sh = s.computePhaseMap(caps)
        return s.unwrapPhaseMap(w, (W, H), shadowMask=sh)

    return run


def _widths(text: str) -> list[int]:
    import argparse

    try:
        widths = [int(x.split("x")[0]) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected widths like 640,1280 (or 640x480), got {text!r}") from None
    if not widths or min(widths) < 64:
        raise argparse.ArgumentTypeError(f"widths must be >= 64 px, got {text!r}")
    return widths


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=15)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--sizes", default="640,1280", type=_widths,
                    help="camera widths, comma-separated (640 -> 640x480, 1280 -> 1280x1024)")
    ap.add_argument("--scene", default="plane", choices=("plane", "head", "sphere", "multi_object"))
    ap.add_argument("--preset", default="typical", choices=("clean", "typical", "hard"))
    ap.add_argument("--no-peers", action="store_true", help="decoder figures only (skip FTP and Gray code)")
    ap.add_argument("--malloc", choices=("keep", "system"), default="keep",
                    help="keep: freed memory reused as the gbscan commands and Scanner set it "
                         "(gbscan.heap.keep_freed_memory, the default); system: glibc's adaptive thresholds")
    args = ap.parse_args(argv)

    import cv2
    import numba

    from gbscan.decode import STREAM_REMEASURE_EVERY, DecodeParams, decode, release_workspace
    from gbscan.pattern import PatternSpec

    cv2.setNumThreads(args.threads)
    numba.set_num_threads(max(1, min(args.threads, numba.config.NUMBA_NUM_THREADS)))
    spec = PatternSpec()
    kept = False
    if args.malloc == "keep":
        from gbscan.heap import keep_freed_memory

        kept = keep_freed_memory()
    print(f"# decoder benchmark, {args.scene} ({args.preset}), {args.threads} thread(s), median of {args.runs} runs (ms), "
          f"malloc: {'freed memory kept (gbscan.heap)' if kept else 'glibc adaptive thresholds'}")
    for w in args.sizes:
        r = frames(w, args.scene, args.preset)
        img = r.image
        H, W = img.shape[:2]
        log("warming up (numba kernels) ...")
        runs = [("", DecodeParams())]
        first = decode(img, spec)
        if "resample" in first.stats:
            # a frame of wide stripes: decoded shrunk (the default); the decoder at the frame's own
            # size as well (its throughput; results with wrong pixels there, see resample_study.py)
            runs.append((" (as it is: --resample never)", DecodeParams(resample=1.0)))
        y0, y1, x0, x1 = first.stats["decoded_window"]
        if (y1 - y0, x1 - x0) != (H, W):
            # an object before darkness: its lit window decoded alone (the default); the whole
            # frame as well (DecodeParams.crop)
            runs.append((" (whole frame: --decode-param crop=false)", DecodeParams(crop=False)))
        for label, prm in runs:
            decode(img, spec, prm)
            stage_runs = []
            for _ in range(args.runs):
                stage_runs.append(decode(img, spec, prm).stats["ms"])
            total, sm = median_ms(lambda: decode(img, spec, prm), args.runs)
            stages = {k: float(np.median([s[k] for s in stage_runs])) for k in stage_runs[0]}
            cpu, faults = cpu_ms_and_faults(lambda: decode(img, spec, prm), args.runs)
            release_workspace()
            mem = peak_mb(lambda: decode(img, spec, prm))
            shrunk = f", decoded shrunk by {sm.stats['resample']:g}" if "resample" in sm.stats else ""
            y0, y1, x0, x1 = sm.stats["decoded_window"]
            if (y1 - y0, x1 - x0) != (H, W):
                shrunk += (f", lit window {x1 - x0}x{y1 - y0} decoded ({(y1 - y0) * (x1 - x0) / (H * W) * 100:.0f}% "
                           f"of the frame)")
            print(f"\n## {W}x{H}: gbscan decode{label}  total {total:.2f} ms  (target {'3' if W <= 640 else '12'} ms)  "
                  f"cpu {cpu:.2f} ms, {faults:.0f} page faults/frame, reported {sm.valid.mean() * 100:.1f}% of pixels"
                  f"{shrunk}")
            print(f"   peak numpy memory {mem:.1f} MB = {mem * 2 ** 20 / (H * W):.0f} bytes/px (workspace included)")
            print("   stages: " + "  ".join(f"{k} {v:.2f}" for k, v in stages.items() if k != "total"))
            if not label:
                # frames of one stream (gbscan.decode.StreamMemo, as a Scanner decodes them): the
                # camera's measurements made every STREAM_REMEASURE_EVERY frames, reused between;
                # the mean over whole cycles (the measuring frames included), alternating with
                # single frames in the same loop (the ratio is what the load leaves comparable)
                t_one, t_stream = stream_ms(img, spec, prm, args.runs)
                print(f"   in a stream (camera measured every {STREAM_REMEASURE_EVERY} frames, reused between; "
                      f"mean over whole cycles): {t_stream:.2f} ms against {t_one:.2f} alone, "
                      f"{t_stream / t_one:.3f} x")
            if "resample" in sm.stats:
                # relative / region / labels / column_relative are expanded when first read (a scan
                # never reads them): what a caller that does read them pays on top
                t_all, _ = median_ms(lambda: decode(img, spec, prm).region, args.runs)
                print(f"   reading relative / region / labels / column_relative as well (expanded on first "
                      f"read): {t_all:.2f} ms in all, +{t_all - total:.2f}")
        if args.no_peers:
            continue
        ftp = ftp_peer(img)
        t_ftp, _ = median_ms(ftp, max(3, args.runs // 3))
        m_ftp = peak_mb(ftp)
        print(f"   peer OpenCV FTP (computePhaseMap + unwrapPhaseMap): {t_ftp:.2f} ms, peak numpy memory "
              f"{m_ftp:.1f} MB (buffers inside OpenCV not traced)")
        imgs, white, black = gray_frames(r.proj_xy[..., 0])
        t_gc, code = median_ms(lambda: gray_decode(imgs, white, black), args.runs)
        m_gc = peak_mb(lambda: gray_decode(imgs, white, black))
        print(f"   peer Gray code (10 bits + white + black, numpy): {t_gc:.2f} ms, peak memory {m_gc:.1f} MB "
              f"(needs 12 frames instead of 1)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
