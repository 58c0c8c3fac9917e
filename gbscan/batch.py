"""Many frames -> one range image each: the engine behind ``gbscan batch``.

Outputs (``OUTDIR``), one set per frame number ``N`` (see ``gbscan.frames`` for numbering)::

    frame_NNNNNN.xyz.npy    float32 (H, W, 3) mm, camera frame, NaN where no point   (always)
    frame_NNNNNN.ply        the cloud (--ply): the scanner's organised PLY (Scan.save_ply);
                            a generic processor gets x y z float32 mm (+ rgb), write_ply
    frame_NNNNNN.mesh.ply   grid mesh                                                (--mesh)
    manifest.csv            one row per frame (below), sorted by frame
    job.yaml                the settings the outputs belong to (input, calibration hash, options)

``manifest.csv`` columns: ``frame`` (number in the input), ``source`` (file name, or
``video.mkv#N``), ``status`` (``ok`` | ``failed`` | ``skipped``), ``reason`` (why it failed or
was skipped; empty when ok), ``points`` (valid pixels), ``coverage`` (points / pixels),
``time_ms`` (wall time to read + process + write the frame in its worker), ``cpu_ms`` (CPU
time of the same, in the worker's thread: ``time_ms`` much larger means the machine is
oversubscribed), ``outputs`` (``;``-separated file names), ``temporal_px`` (``--temporal``: pixels of marker-less regions indexed from the
previous frame).  CSV because it is rewritten often (cheap to write, opens in any spreadsheet).

Execution.  A :class:`Processor` is a small picklable description of the per-frame work (for
scanning: the calibration and parameters, see :class:`ScannerProcessor`).  Each worker process
turns it into a per-frame function once (``Processor.setup``) and caches it under
``Processor.key`` -- the calibration is shipped once per worker, never per frame.  Workers read
their frame (folder input; a video is decoded sequentially by the parent and frames are sent),
process it and write its outputs atomically (``gbscan.io``), returning one small manifest row.
Local runs use ``concurrent.futures.ProcessPoolExecutor`` (``forkserver`` start: safe with the
parent's OpenCV threads; one OpenCV thread per worker, glibc malloc tuned, see
``_tune_malloc``).  ``scheduler=ADDRESS`` submits the same tasks to a Dask distributed cluster:
the processor travels once per worker in a WorkerPlugin (also to workers that join or restart
later) and tasks carry only its key.  Dask workers must see INPUT (folder) and OUTDIR at the
same paths (a shared file system); a video is decoded by the client and frames are sent.
Measured (scripts/bench_batch.py): workers reading their PNG frames were at least as fast as the
parent reading and sending them in every run here, so folders are read in the workers.

Robustness.  A bad frame (unreadable, wrong size, no stripes, an exception in the processor) is
recorded ``failed`` with its reason and the batch goes on.  A worker process that dies takes
its in-flight frames with it: those frames are re-run one at a time in a fresh pool, so the
frame that kills a worker is identified and recorded ``failed`` while the others complete
(on Dask the same isolation re-run follows a ``KilledWorker``).
The manifest is rewritten atomically at most every ``manifest_interval_s`` seconds and at the
end, so a crash loses at most the frames in flight plus the last interval's rows (their outputs
are complete files; they are simply recomputed).  A rerun skips the frames listed ``ok`` whose
outputs all exist, and retries the rest.

Temporal help (``temporal=True``): consecutive selected frames are processed in order within
chunks; each chunk first re-processes the frame before it (not written) so that every frame has
its predecessor's state (``FrameResult.state``; for scanning a :class:`TemporalState`) as a
prior.  What the scanner does with it: :func:`temporal_offsets` and :func:`temporal_stripes`.

Timeouts (``timeout_s``): a frame running longer is abandoned and recorded ``failed`` with reason
``timeout: ...``; the worker raises in the frame's code (:func:`_deadline`), and a local worker
stuck inside a C call past the deadline plus a grace period is killed by the parent (each worker
publishes the frame it runs in a shared array), its other frames re-run as for a dying worker.
On Dask only the first mechanism exists (a task thread cannot be killed).
"""
from __future__ import annotations

import contextlib
import csv
import hashlib
import io as _io
import math
import os
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from .errors import GBError
from .frames import FrameRef, FrameSource, read_frame
from .io import atomic_path, atomic_path_unsynced, fsync_paths, load_yaml, save_yaml, write_text_atomic

MANIFEST = "manifest.csv"
JOB = "job.yaml"
#: Version of the --temporal borrowing rules (part of the job key: outputs made with other rules
#: are not mixed in one OUTDIR).
TEMPORAL_RULES = "temporal-2: column agreement, pixel confirmation, 3 px rim"
COLUMNS = ("frame", "source", "status", "reason", "points", "coverage", "time_ms", "cpu_ms", "outputs",
           "temporal_px", "rig")
#: ScannerProcessor runs the rig check (gbscan.diagnose, ~10 ms) on each worker's first frame and
#: every RIG_EVERY-th one after it; the manifest's ``rig`` column then lists the warnings' keys
#: ("ok": none), empty for the frames not checked
RIG_EVERY = 25


# -- the per-frame contract ----------------------------------------------------------------------
@dataclass
class FrameResult:
    """What a per-frame function returns.

    xyz : (H, W, 3) float32 mm, camera frame, NaN where no point.
    colors : (H, W, 3) uint8 RGB of each pixel for the default cloud writer, or None.
    write_cloud : ``f(path)`` writing this frame's cloud atomically (default: :func:`write_ply`
        of the valid xyz with ``colors``).
    write_mesh : ``f(path)`` writing this frame's mesh atomically (needed for ``mesh=True``).
    state : anything the next frame of a temporal chain receives as ``prior`` (e.g. the absolute
        stripe map); None breaks the chain.
    extra : values of further manifest columns (``temporal_px``, ``rig``).
    """

    xyz: np.ndarray
    colors: np.ndarray | None = None
    write_cloud: Callable | None = None
    write_mesh: Callable | None = None
    state: object = None
    extra: dict = field(default_factory=dict)  # more manifest columns (e.g. temporal_px)


class Processor:
    """Picklable description of the per-frame work; ``setup()`` runs once per worker process.

    ``key`` identifies everything that changes the outputs (calibration, parameters): workers
    cache the set-up function under it and a rerun refuses an OUTDIR made with another key.
    ``size`` = (width, height) every frame must have, or None.  ``setup()`` returns
    ``process(image_rgb, prior) -> FrameResult`` that raises GBError for a bad frame.
    """

    key: str = ""
    size: tuple[int, int] | None = None
    description: dict | None = None  # shown in job.yaml
    first_frame_extra_s: float = 0.0  # the first frame of a worker may take this much longer (compilation)

    def setup(self) -> Callable[[np.ndarray, object], FrameResult]:
        raise NotImplementedError


# -- worker side ---------------------------------------------------------------------------------
_CACHE: dict[str, Callable] = {}  # worker-process-local: Processor.key -> process function
_POOL_PROCESSOR: Processor | None = None
_BOARD = None  # local pool worker: shared array [pid, frame, deadline (monotonic s)] per worker slot
_SLOT = -1


def _tune_malloc() -> None:
    """Let glibc keep freed large arrays in the heap for reuse (worker processes only).

    A frame's scan allocates tens of MB of temporaries.  With glibc's defaults, and much more
    with the ``MALLOC_TRIM_THRESHOLD_=65536`` a Dask nanny sets for its workers, each of them is
    mmap'ed, page-faulted and unmapped again every frame.  Measured here (Scanner.scan, one
    thread): 103 ms CPU/frame by default, 285 ms under Dask's setting, 75 ms with this tuning
    (the process keeps up to 256 MB of freed memory for reuse).
    """
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
        libc.mallopt(M_MMAP_THRESHOLD, 32 << 20)  # the largest glibc accepts
        libc.mallopt(M_TRIM_THRESHOLD, 256 << 20)
    except (OSError, AttributeError):  # not glibc (musl...): keep the defaults
        pass


def _prepare_worker() -> None:
    """Tune a worker process: malloc (above) and one OpenCV/numba thread each -- the pool is the
    parallelism, more threads per worker only oversubscribe the cores."""
    _tune_malloc()
    try:
        import cv2

        cv2.setNumThreads(1)
    except Exception:  # noqa: BLE001 -- best effort
        pass
    if "numba" in sys.modules:
        try:
            sys.modules["numba"].set_num_threads(1)
        except Exception:  # noqa: BLE001
            pass


def _process_fn(proc: Processor) -> Callable:
    fn = _CACHE.get(proc.key)
    if fn is None:
        _prepare_worker()
        _CACHE.clear()  # one job at a time per worker: free the previous calibration
        fn = _CACHE[proc.key] = proc.setup()
    return fn


@dataclass
class _Task:
    """Frames one worker call handles, in order.  ``images[i]`` is the frame's pixels when the
    parent read it (video), None to read ``refs[i].path`` in the worker, or the GBError met."""

    refs: list[FrameRef]
    images: list
    warmup: FrameRef | None = None  # temporal: processed first (not written) to seed the prior
    warmup_image: object = None
    attempt: int = 0


@dataclass(frozen=True)
class OutputSpec:
    outdir: str
    ply: bool = False
    mesh: bool = False
    temporal: bool = False
    timeout_s: float | None = None  # per frame, in the worker (see _deadline)

    def names(self, index: int) -> list[str]:
        stem = f"frame_{index:06d}"
        out = [f"{stem}.xyz.npy"]
        if self.ply:
            out.append(f"{stem}.ply")
        if self.mesh:
            out.append(f"{stem}.mesh.ply")
        return out


def _get_image(ref, image, size):
    if image is None:
        image = read_frame(ref, size)
    if isinstance(image, GBError):
        raise image
    return image


class FrameTimeout(Exception):
    """Raised inside a worker when one frame has run longer than the batch's ``timeout_s``."""


@contextlib.contextmanager
def _deadline(timeout_s: float | None):
    """Raise :class:`FrameTimeout` in this thread if the block runs longer than ``timeout_s``.

    In a process's main thread (local pool workers) a ``SIGALRM`` interval timer does it; in any
    other thread (a Dask worker's task thread) a timer thread injects the exception with
    ``PyThreadState_SetAsyncExc``.  Either way the exception surfaces when the frame's code next
    runs Python bytecode: a frame stuck inside one C call is not interrupted (local runs: the
    parent's stall watchdog kills the worker instead, see :func:`_run_local`).
    """
    if not timeout_s or timeout_s <= 0:
        yield
        return
    import threading

    if threading.current_thread() is threading.main_thread() and hasattr(signal, "setitimer"):
        def on_alarm(signum, frame):
            raise FrameTimeout()

        previous = signal.signal(signal.SIGALRM, on_alarm)
        signal.setitimer(signal.ITIMER_REAL, float(timeout_s))
        try:
            yield
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0.0)
            signal.signal(signal.SIGALRM, previous)
        return
    import ctypes

    tid = threading.get_ident()
    lock = threading.Lock()
    state = {"active": True, "fired": False}

    def inject():
        with lock:
            if state["active"]:
                state["fired"] = True
                ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(tid), ctypes.py_object(FrameTimeout))

    timer = threading.Timer(float(timeout_s), inject)
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        with lock:
            state["active"] = False
        timer.cancel()
        if state["fired"]:  # never let a pending injection escape into the caller's later code
            ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(tid), None)
            raise FrameTimeout()


_FRAMES_STARTED = 0  # per worker process


def _allowance(timeout_s: float | None, first_extra_s: float) -> float | None:
    """Seconds the next frame of this worker process may take (None: no limit); the first one
    gets ``first_extra_s`` more (``Processor.first_frame_extra_s``)."""
    global _FRAMES_STARTED
    _FRAMES_STARTED += 1
    if not timeout_s:
        return None
    return float(timeout_s) + (float(first_extra_s) if _FRAMES_STARTED == 1 else 0.0)


def _timeout_reason(timeout_s) -> str:
    return (f"timeout: no result after {timeout_s:g} s, the frame was abandoned "
            "(raise --timeout-s if frames are legitimately this slow)")


def _run_task(proc: Processor, task: _Task, spec: OutputSpec) -> list[dict]:
    """Process and write every frame of ``task``; one manifest row per frame (never raises)."""
    try:
        fn = _process_fn(proc)
    except Exception as e:  # noqa: BLE001 -- every frame of the task fails with the reason
        why = f"could not set up the per-frame processing: {type(e).__name__}: {e}"
        return [_failed_row(r, why) for r in task.refs]
    prior = None
    if spec.temporal and task.warmup is not None:
        allowed = _allowance(spec.timeout_s, proc.first_frame_extra_s)
        _board_start(task.warmup.index, allowed)
        try:
            with _deadline(allowed):
                prior = fn(_get_image(task.warmup, task.warmup_image, proc.size), None).state
        except Exception:  # noqa: BLE001 -- the chain simply starts without a prior (FrameTimeout too)
            prior = None
        _board_stop()
    rows = []
    for ref, image in zip(task.refs, task.images):
        t0, c0 = time.perf_counter(), time.thread_time()
        row = {"frame": ref.index, "source": ref.source}
        allowed = _allowance(spec.timeout_s, proc.first_frame_extra_s)
        _board_start(ref.index, allowed)
        try:
            with _deadline(allowed):
                rgb = _get_image(ref, image, proc.size)
                res = fn(rgb, prior if spec.temporal else None)
                written = _write_outputs(spec, ref.index, res)
            prior = res.state
            row.update(written)
            row.update({k: v for k, v in res.extra.items() if k in COLUMNS})
            row["status"], row["reason"] = "ok", ""
        except FrameTimeout:
            prior = None
            row.update(status="failed", reason=_timeout_reason(spec.timeout_s), points=0, coverage=0.0, outputs="")
        except GBError as e:
            prior = None
            row.update(status="failed", reason=_one_line(str(e)), points=0, coverage=0.0, outputs="")
        except Exception as e:  # noqa: BLE001 -- a processor bug must not stop the batch
            prior = None
            row.update(status="failed", reason=_one_line(f"internal error: {type(e).__name__}: {e}"),
                       points=0, coverage=0.0, outputs="")
        _board_stop()
        row["time_ms"] = round((time.perf_counter() - t0) * 1e3, 1)
        row["cpu_ms"] = round((time.thread_time() - c0) * 1e3, 1)
        rows.append(row)
    return rows


def _pool_init(proc: Processor, board=None, counter=None) -> None:
    global _POOL_PROCESSOR, _BOARD, _SLOT
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    _POOL_PROCESSOR = proc
    if board is not None:
        with counter.get_lock():
            _SLOT = counter.value
            counter.value += 1
        _BOARD = board
        board[3 * _SLOT] = os.getpid()
    try:
        _process_fn(proc)  # set up now, not inside the first frame's time
    except Exception:  # noqa: BLE001 -- reported per frame by _run_task
        pass


def _board_start(frame: int, allowed_s: float | None) -> None:
    """Local pool worker: tell the parent's watchdog which frame runs and when it is overdue."""
    if _BOARD is not None:
        i = 3 * _SLOT
        _BOARD[i + 2] = 0.0
        _BOARD[i + 1] = frame
        _BOARD[i + 2] = time.monotonic() + (allowed_s if allowed_s else math.inf)


def _board_stop() -> None:
    if _BOARD is not None:
        _BOARD[3 * _SLOT + 2] = 0.0


def _pool_task(task: _Task, spec: OutputSpec) -> list[dict]:
    return _run_task(_POOL_PROCESSOR, task, spec)


_WORKER_PROCESSORS: dict[str, Processor] = {}  # Dask worker-local: key -> processor (plugin-installed)


def _dask_task(key: str, task: _Task, spec: OutputSpec) -> list[dict]:
    proc = _WORKER_PROCESSORS.get(key)
    if proc is None:
        return [_failed_row(r, "this Dask worker has no scanner for the job (plugin not installed)")
                for r in task.refs]
    return _run_task(proc, task, spec)


def _plugin_class():
    """``_ProcessorPlugin``, a Dask WorkerPlugin (made on first use: distributed is optional)."""
    from distributed.diagnostics.plugin import WorkerPlugin

    class _ProcessorPlugin(WorkerPlugin):
        """Installs the job's processor on every worker, also on workers that (re)join later.

        The processor (calibration + parameters) travels once per worker with the plugin; tasks
        carry only its key, and _process_fn caches the set-up scanner per worker process.
        """

        idempotent = False

        def __init__(self, proc: Processor):
            self.proc = proc
            self.name = f"gbscan-batch-{proc.key}"

        def setup(self, worker):
            _WORKER_PROCESSORS[self.proc.key] = self.proc

        def teardown(self, worker):
            _WORKER_PROCESSORS.pop(self.proc.key, None)
            _CACHE.pop(self.proc.key, None)

    _ProcessorPlugin.__module__ = __name__
    _ProcessorPlugin.__qualname__ = "_ProcessorPlugin"
    globals()["_ProcessorPlugin"] = _ProcessorPlugin
    return _ProcessorPlugin


def __getattr__(name):  # unpickling the plugin on a worker defines its class there too
    if name == "_ProcessorPlugin":
        return _plugin_class()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _failed_row(ref: FrameRef, why: str, time_ms="") -> dict:
    return {"frame": ref.index, "source": ref.source, "status": "failed", "reason": _one_line(why),
            "points": 0, "coverage": 0.0, "time_ms": time_ms, "outputs": ""}


def _one_line(text: str) -> str:
    return " ".join(str(text).split())[:300]


# -- outputs -------------------------------------------------------------------------------------
def _write_outputs(spec: OutputSpec, index: int, res: FrameResult) -> dict:
    xyz = np.asarray(res.xyz)
    if xyz.ndim != 3 or xyz.shape[2] != 3:
        raise GBError(f"processor returned xyz of shape {xyz.shape}; expected (H, W, 3)")
    xyz = xyz.astype(np.float32, copy=False)
    # (per coordinate: numpy's all() over a length-3 last axis is ~25x slower, 7 against 0.3 ms)
    ok = np.isfinite(xyz[:, :, 0]) & np.isfinite(xyz[:, :, 1]) & np.isfinite(xyz[:, :, 2])
    n = int(ok.sum())
    if n == 0:
        raise GBError("no stripes decoded: the frame gave no range point (is the pattern visible?)")
    out = Path(spec.outdir)
    names = spec.names(index)
    with atomic_path_unsynced(out / names[0], suffix=".npy") as tmp:  # the parent syncs (_RunState.flush)
        np.save(tmp, xyz)
    if spec.ply:
        if res.write_cloud is not None:
            res.write_cloud(out / names[1])
        else:
            cols = None if res.colors is None else np.asarray(res.colors, dtype=np.uint8)[ok]
            write_ply(out / names[1], xyz[ok], cols)
    if spec.mesh:
        if res.write_mesh is None:
            raise GBError("--mesh was asked but this processor makes no mesh")
        res.write_mesh(out / names[2])
    return {"points": n, "coverage": round(n / ok.size, 5), "outputs": ";".join(names)}


def write_ply(path, points: np.ndarray, colors: np.ndarray | None = None,
              triangles: np.ndarray | None = None) -> Path:
    """Binary little-endian PLY, atomically: points (N, 3) mm as float32, optional colours (N, 3)
    uint8 RGB, optional triangles (T, 3) vertex indices."""
    p = np.asarray(points, dtype="<f4").reshape(-1, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    v = np.empty(len(p), dtype=fields)
    v["x"], v["y"], v["z"] = p[:, 0], p[:, 1], p[:, 2]
    if colors is not None:
        c = np.asarray(colors, dtype=np.uint8).reshape(-1, 3)
        v["red"], v["green"], v["blue"] = c[:, 0], c[:, 1], c[:, 2]
    head = ["ply", "format binary_little_endian 1.0", "comment gbscan batch, units mm, camera frame",
            f"element vertex {len(p)}", "property float x", "property float y", "property float z"]
    if colors is not None:
        head += ["property uchar red", "property uchar green", "property uchar blue"]
    body = [v.tobytes()]
    if triangles is not None:
        t = np.asarray(triangles).reshape(-1, 3)
        f = np.empty(len(t), dtype=[("n", "u1"), ("i", "<i4", (3,))])
        f["n"], f["i"] = 3, t
        head += [f"element face {len(t)}", "property list uchar int vertex_indices"]
        body.append(f.tobytes())
    head.append("end_header\n")
    with atomic_path(path, suffix=".ply") as tmp:
        with open(tmp, "wb") as fh:
            fh.write("\n".join(head).encode("ascii"))
            for b in body:
                fh.write(b)
    return Path(path)


# -- manifest ------------------------------------------------------------------------------------
def read_manifest(path) -> dict[int, dict]:
    """manifest.csv -> {frame: row}; a missing file gives {} and an unreadable one a GBError."""
    path = Path(path)
    if not path.is_file():
        return {}
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            if reader.fieldnames is None or "frame" not in reader.fieldnames or "status" not in reader.fieldnames:
                raise ValueError("missing the frame/status columns")
            rows = {}
            for r in reader:
                r["frame"] = int(r["frame"])
                rows[r["frame"]] = r
            return rows
    except (ValueError, csv.Error, UnicodeDecodeError) as e:
        raise GBError(f"manifest {path} is not a gbscan batch manifest ({e}); move it away or use --restart") from None


def write_manifest(path, rows: dict[int, dict]) -> Path:
    buf = _io.StringIO()
    w = csv.DictWriter(buf, fieldnames=COLUMNS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for k in sorted(rows):
        w.writerow({c: rows[k].get(c, "") for c in COLUMNS})
    return write_text_atomic(path, buf.getvalue())


def is_done(row: dict | None, ref: FrameRef, spec: OutputSpec) -> bool:
    """A frame is done when the manifest lists it ok from the same source and its outputs exist."""
    if not row or row.get("status") != "ok" or row.get("source") != ref.source:
        return False
    return all((Path(spec.outdir) / n).is_file() for n in spec.names(ref.index))


# -- progress ------------------------------------------------------------------------------------
class Progress:
    """'batch: 120/500 frames  31.2 frames/s  0:12 left  2 failed' on stderr: rewritten in place on a
    TTY, one line every ``interval_s`` otherwise."""

    def __init__(self, total: int, stream=None, interval_s: float | None = None, label: str = "batch"):
        self.total, self.label = total, label
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.interval_s = interval_s if interval_s is not None else (0.2 if self.tty else 5.0)
        self.t0 = time.monotonic()
        self.last = -math.inf
        self.done = self.failed = 0

    def update(self, done: int, failed: int, force: bool = False) -> None:
        self.done, self.failed = done, failed
        now = time.monotonic()
        if not force and now - self.last < self.interval_s:
            return
        self.last = now
        dt = now - self.t0
        fps = done / dt if dt > 0 else 0.0
        left = (self.total - done) / fps if fps > 0 else math.nan
        eta = "--:--" if not math.isfinite(left) else f"{int(left) // 60}:{int(left) % 60:02d}"
        msg = (f"{self.label}: {done}/{self.total} frames  {fps:.1f} frames/s  {eta} left"
               + (f"  {failed} failed" if failed else ""))
        if self.tty:
            self.stream.write("\r" + msg + "\033[K")
        else:
            self.stream.write(msg + "\n")
        self.stream.flush()

    def close(self) -> None:
        self.update(self.done, self.failed, force=True)
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()


# -- the engine ----------------------------------------------------------------------------------
@dataclass
class BatchSummary:
    selected: int           # frames in the selection
    already_done: int       # skipped because a previous run completed them
    ok: int                 # completed in this run
    failed: int             # failed in this run
    elapsed_s: float
    manifest: Path
    failures: list[tuple[int, str]] = field(default_factory=list)
    first_result_s: float = math.nan  # start-up: time until the first frame came back

    @property
    def frames_per_s(self) -> float:
        """Frames handled in this run per second of wall time, start-up included."""
        n = self.ok + self.failed
        return n / self.elapsed_s if self.elapsed_s > 0 else 0.0

    @property
    def steady_frames_per_s(self) -> float:
        """Frames per second after the first result (excludes pool start and scanner set-up)."""
        n = self.ok + self.failed - 1
        dt = self.elapsed_s - self.first_result_s
        return n / dt if n > 0 and dt > 0 else math.nan


def run_batch(source: FrameSource, processor: Processor, outdir, *, start: int = 0, stop: int | None = None,
              every: int = 1, workers: int | None = None, scheduler: str | None = None, ply: bool = False,
              mesh: bool = False, temporal: bool = False, restart: bool = False, read_in: str = "auto",
              chunk: int | None = None, progress: bool | Progress = True,
              manifest_interval_s: float = 0.5, max_in_flight: int | None = None,
              scheduler_timeout_s: float = 10.0, timeout_s: float | None = None,
              frames_per_task: int | None = None) -> BatchSummary:
    """Process the selected frames of ``source`` into ``outdir`` (see the module docstring).

    workers : local processes (default: all cores); ignored with ``scheduler``.
    scheduler : address of a Dask distributed scheduler (``tcp://host:8786``) or a
        ``distributed.Client``; None runs locally.
    read_in : 'worker' (workers read image files), 'parent', or 'auto' (workers for a folder;
        a video is always decoded by the parent, sequentially).
    restart : ignore a previous run's outputs in ``outdir`` (they are overwritten frame by frame).
    chunk : frames per task in temporal mode (default: about four tasks per worker, 4..32).
    frames_per_task : frames per task otherwise.  Default 1 locally; on Dask up to 8 (at least
        four tasks per local core), as each Dask task costs ~7 ms of scheduler + client CPU and
        ~6 ms of worker CPU here (measured with a no-op processor: 31-38 frames/s at 1 frame per
        task, 95-149 at 8), as much as a whole frame's scan.
    timeout_s : a frame still running after this many seconds is abandoned and recorded failed
        with reason "timeout" (None: no limit).  The worker stops it at its next Python bytecode;
        a local worker still on the frame ``max(2, timeout_s / 4)`` s later (stuck inside a C
        call) is killed by the parent, which records the frame and re-runs the worker's other
        frames one at a time as for a dying worker.  A worker's first frame gets the processor's
        ``first_frame_extra_s`` more (the scanner's: 300 s, for compiling the kernels).
    """
    outdir = Path(outdir)
    if outdir.exists() and not outdir.is_dir():
        raise GBError(f"output {outdir} exists and is not a folder")
    outdir.mkdir(parents=True, exist_ok=True)
    if read_in not in ("auto", "worker", "parent"):
        raise GBError(f"read_in must be 'auto', 'worker' or 'parent', got {read_in!r}")
    if workers is not None and (isinstance(workers, bool) or int(workers) < 1):
        raise GBError(f"--workers must be a positive integer, got {workers!r}")
    workers = int(workers or os.cpu_count() or 1)
    if timeout_s is not None and not (isinstance(timeout_s, (int, float)) and timeout_s > 0):
        raise GBError(f"--timeout-s must be a positive number of seconds, got {timeout_s!r}")
    spec = OutputSpec(str(outdir.resolve()), bool(ply), bool(mesh), bool(temporal),
                      None if timeout_s is None else float(timeout_s))
    refs = source.refs(start, stop, every)
    if not refs:
        raise GBError(f"no frame selected: the input has {len(source)} frames and the selection is "
                      f"--start {start} --stop {stop} --every {every}")

    manifest_path = outdir / MANIFEST
    job = {"schema": "gbscan.batch", "version": 1, "input": str(Path(source.path).resolve()),
           "input_kind": source.kind, "processor_key": processor.key, "temporal": bool(temporal),
           "processor": processor.description}
    rows = {} if restart else _check_previous(outdir, manifest_path, job)
    save_yaml(outdir / JOB, job)

    pending = [r for r in refs if not is_done(rows.get(r.index), r, spec)]
    already = len(refs) - len(pending)
    parent_reads = read_in == "parent" or not source.random_access
    if frames_per_task is None:  # a Dask task costs ~13 ms of scheduler + worker CPU here: share it
        frames_per_task = 1 if scheduler is None else max(1, min(8, len(pending) // (4 * workers)))
    elif isinstance(frames_per_task, bool) or int(frames_per_task) < 1:
        raise GBError(f"frames_per_task must be a positive integer, got {frames_per_task!r}")
    tasks = _make_tasks(refs, pending, temporal, chunk or _default_chunk(len(pending), workers), frames_per_task)

    prog = progress if isinstance(progress, Progress) else (Progress(len(pending)) if progress else None)
    state = _RunState(rows, manifest_path, manifest_interval_s, prog)
    t0 = time.perf_counter()
    try:
        if pending:
            feeder = _Feeder(source, tasks, processor.size, parent_reads)
            if scheduler is not None:
                _run_dask(scheduler, processor, feeder, spec, state, max_in_flight, scheduler_timeout_s)
            else:
                _run_local(workers, processor, feeder, spec, state, max_in_flight)
    except BaseException:
        for r in pending:
            if r.index not in state.finished:
                rows[r.index] = {"frame": r.index, "source": r.source, "status": "skipped",
                                 "reason": "not processed: the run was interrupted (rerun to resume)"}
        state.flush(force=True)
        if prog:
            prog.close()
        raise
    state.flush(force=True)
    if prog:
        prog.close()
    failures = [(i, rows[i].get("reason", "")) for i in sorted(state.finished)
                if rows[i].get("status") != "ok"]
    return BatchSummary(len(refs), already, state.n_ok, len(failures), time.perf_counter() - t0,
                        manifest_path, failures, state.first_result - t0)


def _check_previous(outdir: Path, manifest_path: Path, job: dict) -> dict[int, dict]:
    rows = read_manifest(manifest_path)
    prev_file = outdir / JOB
    if prev_file.is_file():
        prev = load_yaml(prev_file, "batch job file")
        for k, what in (("processor_key", "calibration or scan parameters"), ("temporal", "--temporal")):
            if prev.get(k) != job[k]:
                raise GBError(f"{outdir} holds results made with other {what} ({prev_file}); "
                              "use another -o folder, or --restart to overwrite them")
    return rows


def _default_chunk(n: int, workers: int) -> int:
    return int(min(32, max(4, math.ceil(n / (4 * workers)))))


def _make_tasks(refs: list[FrameRef], pending: list[FrameRef], temporal: bool, chunk: int,
                frames_per_task: int = 1) -> list[_Task]:
    if not temporal:
        k = max(1, int(frames_per_task))
        return [_Task(pending[j:j + k], [None] * len(pending[j:j + k])) for j in range(0, len(pending), k)]
    pos = {r.index: i for i, r in enumerate(refs)}
    tasks: list[_Task] = []
    run: list[FrameRef] = []

    def close_run():
        for j in range(0, len(run), chunk):
            part = run[j:j + chunk]
            k = pos[part[0].index]
            tasks.append(_Task(part, [None] * len(part), warmup=refs[k - 1] if k > 0 else None))

    for r in pending:  # runs of consecutive selected frames
        if run and pos[r.index] != pos[run[-1].index] + 1:
            close_run()
            run = []
        run.append(r)
    close_run()
    return tasks


class _Feeder:
    """Yields tasks in order; when the parent reads (video), fills their images sequentially."""

    def __init__(self, source: FrameSource, tasks: list[_Task], size, parent_reads: bool):
        self.tasks, self.parent_reads = tasks, parent_reads
        if parent_reads:
            need = sorted({r.index for t in tasks for r in ([t.warmup] if t.warmup else []) + t.refs})
            byidx = {r.index: r for t in tasks for r in ([t.warmup] if t.warmup else []) + t.refs}
            self._frames = source.frames([byidx[i] for i in need], size)
            self._have: dict[int, object] = {}

    def _image(self, ref: FrameRef):
        while ref.index not in self._have:
            r, img = next(self._frames)
            self._have[r.index] = img
        return self._have[ref.index]

    def __iter__(self):
        for t in self.tasks:
            if self.parent_reads:
                if t.warmup is not None:
                    t.warmup_image = self._image(t.warmup)
                t.images = [self._image(r) for r in t.refs]
                last = max(self._have)  # keep only the newest frame (a later chunk's warm-up)
                self._have = {last: self._have[last]}
            yield t


class _RunState:
    """Rows, counters, throttled atomic manifest writes and the progress line (parent side).

    Workers write their outputs without waiting for the disk (``atomic_path_unsynced``); before
    each manifest write the parent flushes the outputs of the frames it is about to list as ok
    (``fsync_paths``), so a manifest never lists a frame whose files a power failure could lose.
    """

    def __init__(self, rows, manifest_path, interval_s, prog):
        self.rows, self.path, self.interval_s, self.prog = rows, manifest_path, interval_s, prog
        self.finished: set[int] = set()
        self.n_ok = self.n_failed = 0
        self.dirty, self.last = False, -math.inf
        self.first_result = math.nan
        self.unsynced: list[Path] = []

    def record(self, new_rows: list[dict]) -> None:
        if math.isnan(self.first_result):
            self.first_result = time.perf_counter()
        for r in new_rows:
            self.rows[r["frame"]] = r
            self.finished.add(r["frame"])
            if r["status"] == "ok":
                self.n_ok += 1
                self.unsynced += [self.path.parent / n for n in str(r.get("outputs") or "").split(";") if n]
            else:
                self.n_failed += 1
        self.dirty = True
        self.flush()
        if self.prog:
            self.prog.update(self.n_ok + self.n_failed, self.n_failed)

    def flush(self, force: bool = False) -> None:
        now = time.monotonic()
        if self.dirty and (force or now - self.last >= self.interval_s):
            fsync_paths(self.unsynced)
            self.unsynced = []
            write_manifest(self.path, self.rows)
            self.dirty, self.last = False, now


def _died_rows(task: _Task, why: str) -> list[dict]:
    return [_failed_row(r, why) for r in task.refs]


def _singles(task: _Task) -> list[_Task]:
    return [_Task([r], [img], attempt=task.attempt + 1) for r, img in zip(task.refs, task.images)]


def _run_local(workers, processor, feeder, spec, state, max_in_flight) -> None:
    import multiprocessing as mp
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool

    ctx = mp.get_context("forkserver")
    limit = max_in_flight or 2 * workers
    it = iter(feeder)
    suspects: list[_Task] = []  # tasks in flight when a worker died: re-run one at a time
    exhausted = False
    # Watchdog (timeout_s): each worker publishes [pid, frame, deadline] of the frame it runs; a
    # frame past its deadline + grace did not stop at the worker's own deadline (stuck in C
    # code): the parent kills that worker and records the frame "timeout".
    grace_s = None if spec.timeout_s is None else max(2.0, 0.25 * spec.timeout_s)
    hung: set[int] = set()

    def new_pool():
        board = ctx.Array("d", 3 * workers, lock=False) if spec.timeout_s else None
        counter = ctx.Value("i", 0) if spec.timeout_s else None
        pool = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_pool_init,
                                   initargs=(processor, board, counter))
        return pool, board

    def watchdog(board) -> None:
        now = time.monotonic()
        for i in range(workers):
            pid, frame, due = int(board[3 * i]), int(board[3 * i + 1]), board[3 * i + 2]
            if due > 0 and now > due + grace_s and pid > 0 and board[3 * i + 2] == due:
                hung.add(frame)
                with contextlib.suppress(OSError):
                    os.kill(pid, signal.SIGKILL)

    pool, board = new_pool()
    inflight: dict = {}
    pending: list[_Task] = []   # tasks a broken pool refused: next in line, in order
    try:
        while True:
            cap = 1 if suspects else limit
            refused = False
            while len(inflight) < cap:
                if suspects:
                    if inflight:
                        break
                    t, src = suspects.pop(0), suspects
                elif pending:
                    t, src = pending.pop(0), pending
                else:
                    t, src = (next(it, None) if not exhausted else None), pending
                    if t is None:
                        exhausted = True
                        break
                try:
                    inflight[pool.submit(_pool_task, t, spec)] = t
                except BrokenProcessPool:
                    # a worker died since the last wait: the frames in flight report it below
                    # (and the pool is made anew there); this task has not run, it waits its turn
                    src.insert(0, t)
                    refused = True
                    break
            if refused and not inflight:   # nothing in flight to report the death: a new pool now
                hung.clear()
                pool.shutdown(wait=True, cancel_futures=True)
                pool, board = new_pool()
                continue
            if not inflight:
                if exhausted and not suspects and not pending:
                    return
                continue
            done, _ = wait(inflight, timeout=None if board is None else min(1.0, grace_s),
                           return_when=FIRST_COMPLETED)
            if board is not None:
                watchdog(board)
            broken = False
            for f in done:
                t = inflight.pop(f)
                try:
                    state.record(f.result())
                except BrokenProcessPool:
                    broken = True
                    suspects.extend(_after_crash(t, hung, spec, state))
            if broken:
                for f, t in list(inflight.items()):  # every other in-flight frame died with the pool
                    suspects.extend(_after_crash(t, hung, spec, state, victim=True))
                inflight.clear()
                hung.clear()
                pool.shutdown(wait=True, cancel_futures=True)
                pool, board = new_pool()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _after_crash(t: _Task, hung: set[int], spec: OutputSpec, state, victim: bool = False) -> list[_Task]:
    """Frames of a task whose worker died: record the ones the watchdog killed (timeout) and the
    single frame that died again alone; return the others as single-frame tasks to re-run."""
    timed_out = [r for r in t.refs if r.index in hung]
    if timed_out:
        state.record([_failed_row(r, _timeout_reason(spec.timeout_s)) for r in timed_out])
    rest = [(r, img) for r, img in zip(t.refs, t.images) if r.index not in hung]
    if not victim and not timed_out and len(t.refs) == 1 and t.attempt >= 1:
        state.record(_died_rows(t, "worker process died while processing this frame "
                                   "(crashed or killed; e.g. out of memory)"))
        return []
    return [_Task([r], [img], attempt=t.attempt + 1) for r, img in rest]


def _run_dask(scheduler, processor, feeder, spec, state, max_in_flight, timeout_s) -> None:
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise GBError("--scheduler needs dask.distributed: pip install 'gbscan[batch]'") from None
    own = not isinstance(scheduler, Client)
    try:
        client = Client(scheduler, timeout=f"{timeout_s}s") if own else scheduler
    except (OSError, TimeoutError) as e:
        raise GBError(f"cannot reach the Dask scheduler at {scheduler} ({_one_line(str(e))}); "
                      "check the address (tcp://HOST:8786) and that the scheduler runs") from None
    try:
        n_workers = max(1, len(client.scheduler_info().get("workers", {})))
        limit = max_in_flight or 2 * n_workers
        plugin = _plugin_class()(processor)
        client.register_plugin(plugin, name=plugin.name)
        it = iter(feeder)
        ac = as_completed()
        inflight: dict = {}
        suspects: list[_Task] = []  # tasks that failed with a worker: re-run one at a time
        exhausted = False

        def submit(t: _Task):
            f = client.submit(_dask_task, processor.key, t, spec, pure=False)
            inflight[f.key] = t
            ac.add(f)

        def fill():
            nonlocal exhausted
            if suspects:
                if not inflight:
                    submit(suspects.pop(0))
                return
            while not exhausted and len(inflight) < limit:
                t = next(it, None)
                if t is None:
                    exhausted = True
                else:
                    submit(t)

        fill()
        while inflight:
            f = next(ac)
            t = inflight.pop(f.key)
            try:
                state.record(f.result())
            except Exception as e:  # noqa: BLE001 -- KilledWorker, lost worker, serialisation...
                if len(t.refs) == 1 and t.attempt >= 1:
                    state.record(_died_rows(t, f"dask worker died on this frame ({type(e).__name__}: "
                                               f"{_one_line(str(e))[:120]})"))
                else:  # maybe the victim of another frame: retry alone
                    suspects.extend(_singles(t))
            f.release()
            fill()
    finally:
        with contextlib.suppress(Exception):
            client.unregister_worker_plugin(f"gbscan-batch-{processor.key}")
        if own:
            client.close()


# -- scanning -------------------------------------------------------------------------------------
def file_sha256(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


class ScannerProcessor(Processor):
    """Per-frame work of ``gbscan batch``: a :class:`gbscan.scan.Scanner` built once per worker.

    The object holds the loaded Calibration (a few hundred planes: tens of kB) and the
    parameters; it is pickled once per worker process, never per frame.  Frames are decoded,
    triangulated and cleaned by ``Scanner.scan``; the cloud is written by ``Scan.save_ply`` (the
    organised PLY ``gbscan mesh`` reads) and the mesh is the grid mesh (``Scan.mesh_arrays``).
    """

    #: The first frame of each worker compiles the numba kernels when their on-disk cache is stale
    #: (after an update; tens of seconds on a busy machine): it is not held to ``timeout_s`` alone.
    first_frame_extra_s = 300.0

    def __init__(self, calibration_path, *, decode_params=None, clean_params=None, temporal: bool = False):
        from .calibfile import load_calibration

        path = Path(calibration_path)
        self.calibration = load_calibration(path)
        self.decode_params, self.clean_params = decode_params, clean_params
        self.temporal = bool(temporal)
        cam = self.calibration.camera
        self.size = (cam.width, cam.height)
        sha = file_sha256(path)
        # --temporal outputs depend on the borrowing rules too: their version is part of the key
        rules = TEMPORAL_RULES if self.temporal else ""
        self.key = hashlib.sha256((sha + repr(decode_params) + repr(clean_params) + rules).encode()).hexdigest()[:16]
        self.description = {"calibration": str(path.resolve()), "calibration_sha256": sha,
                            "decode_params": repr(decode_params), "clean_params": repr(clean_params)}

    def setup(self):
        from .scan import Scanner

        # every frame measures the camera itself (remeasure_every=1): a frame's outputs must not
        # depend on which worker scanned it, or after which frame (parallel, resumable runs)
        scanner = Scanner(self.calibration, decode_params=self.decode_params, clean_params=self.clean_params,
                          remeasure_every=1)
        temporal = self.temporal
        calls = [0]

        def process(rgb, prior=None):
            scan = scanner.scan(rgb)
            extra, state = {}, None
            if temporal:
                scan, state, extra = _temporal_scan(scanner, scan, prior)
            calls[0] += 1
            warns = None
            if scan.stripemap is not None and (calls[0] % RIG_EVERY == 1 or scan.n_points == 0):
                from .diagnose import check_frame

                warns = check_frame(rgb, scan.stripemap, scanner.decode_params).warnings()
                extra = {**extra, "rig": ";".join(f.key for f in warns) or "ok"}
            if scan.n_points == 0:
                why = (scan.stripemap.stats.get("why") if scan.stripemap is not None else None) or \
                    "no stripes decoded: the frame gave no range point"
                rig = [f.short for f in warns or () if f.key != "no_stripes"]
                if rig:
                    why += f" (rig check: {'; '.join(rig[:2])})"
                raise GBError(f"no points: {why}")

            def write_mesh(path):
                from .mesh import write_mesh as _write_mesh

                _write_mesh(path, scan.mesh_arrays("grid"))

            return FrameResult(scan.xyz, write_cloud=scan.save_ply, write_mesh=write_mesh, state=state, extra=extra)

        return process


@dataclass
class TemporalState:
    """What a frame hands to the next one in ``--temporal`` mode (camera pixel grid, H x W).

    stripe : int32 absolute stripe index (-1 none): the decoder's plus the borrowed ones.
    column : float32 projector column (px, NaN none) of the same pixels.
    """

    stripe: np.ndarray
    column: np.ndarray


def _temporal_scan(scanner, scan, prior):
    """Index the frame's unindexed regions from the previous frame (:class:`TemporalState` or None).

    Returns (scan, state for the next frame, manifest extras).  The borrowed offsets and pixels
    come from :func:`temporal_stripes` (checked against the previous frame's columns); their
    points are triangulated from the decoder's offset-0 columns (``StripeMap.column_relative``)
    plus the borrowed offset, with confidence at most 0.5.
    """
    from .decode import UNINDEXED

    sm = scan.stripemap
    stripe = scan.stripe
    if sm is None or stripe is None:
        return scan, None, {}
    own = TemporalState(stripe, np.where(sm.valid, sm.column, np.nan).astype(np.float32))
    unindexed = sm.mask == UNINDEXED
    # (read only when needed: a frame decoded shrunk expands the relative maps on first read)
    col_rel = getattr(sm, "column_relative", None) if prior is not None and unindexed.any() else None
    if col_rel is None:
        return scan, own, {"temporal_px": 0}
    if not isinstance(prior, TemporalState):
        raise GBError(f"temporal prior must be a TemporalState, got {type(prior).__name__}")
    filled, offsets, recovered = temporal_stripes(
        stripe, sm.relative, sm.region, unindexed, sm.labels, prior.stripe, sm.pattern.marker_indices(),
        column_relative=col_rel, prev_column=prior.column, stripe_px=sm.pattern.stripe_px)
    if not recovered.any():
        return scan, own, {"temporal_px": 0}
    off_px = np.zeros(recovered.shape, np.float32)
    for rid, off in offsets.items():
        off_px[sm.region == rid] = off * sm.pattern.stripe_px
    column = np.where(recovered, np.asarray(col_rel, np.float32) + off_px, sm.column)
    conf = np.where(recovered, 0.5 * np.maximum(sm.confidence, 0.5), sm.confidence)  # a prior, not markers
    # (the recovered pixels have no predicted column error: NaN, so a max_sigma_mm drops them)
    sigma = sm.column_sigma if scanner.clean_params.max_sigma_mm is not None else None
    new = scanner.reconstruct(column, conf, decoded=sm.valid | recovered, column_sigma=sigma)
    new.stripe, new.stripemap = filled, sm
    new.timings_ms = {**scan.timings_ms, "temporal": new.timings_ms.get("total", 0.0)}
    state = TemporalState(filled, np.where(sm.valid | recovered, column, np.nan).astype(np.float32))
    return new, state, {"temporal_px": int(recovered.sum())}


# -- temporal help (pure) ---------------------------------------------------------------------------
def temporal_stripes(stripe: np.ndarray, relative: np.ndarray, region: np.ndarray, unindexed: np.ndarray,
                     labels: np.ndarray, prev_stripe: np.ndarray, marker_stripes: np.ndarray, *,
                     column_relative: np.ndarray | None = None, prev_column: np.ndarray | None = None,
                     stripe_px: int = 8, rim_px: int = 3, **options):
    """The absolute stripe map with unindexed regions indexed from the previous frame.

    stripe : (H, W) int32 the decoder's absolute stripes (-1 none), kept where set.
    relative, region : (H, W) int32 from the decoder (``StripeMap.relative``/``region``).
    unindexed : (H, W) bool pixels of regions the markers could not index.
    labels : (H, W) uint8 colour classes (``gbscan.pattern.CYAN`` marks marker stripes seen).
    prev_stripe : (H, W) int32 previous frame's absolute stripes (-1 none).
    marker_stripes : absolute marker stripe indices (``PatternSpec.marker_indices()``).
    column_relative, prev_column : (H, W) projector columns (px, NaN none): this frame's at offset
        0 (``StripeMap.column_relative``) and the previous frame's absolute ones.  With them the
        offsets are checked on columns, and only the pixels whose column agrees with the
        previous frame's at the same pixel (within ``tol_px``) are recovered; without them, on
        stripe indices.
    rim_px : pixels within this many px of another region are never recovered: in the simulated
        sequences the wrong ones were all on the first two px of a region's rim, where the
        decoder welds two surfaces into one region.  A region left with fewer than
        ``min_overlap_px`` such pixels is not recovered at all.
    options : thresholds of :func:`temporal_offsets`.

    Returns ``(stripe (H, W) int32, {region: offset}, recovered (H, W) bool)``: the decoder's
    stripes plus ``relative + offset`` on the recovered pixels, -1 elsewhere.
    """
    from .pattern import CYAN

    relative = np.asarray(relative)
    region = np.asarray(region)
    unindexed = np.asarray(unindexed, bool)
    ids = np.unique(region[unindexed & (region >= 0)])
    markers_rel = {}
    cyan = (np.asarray(labels) == CYAN) & unindexed
    for rid in ids:
        seen = np.unique(relative[cyan & (region == rid)])
        markers_rel[int(rid)] = seen[seen >= 0]
    use_columns = column_relative is not None and prev_column is not None
    offsets = temporal_offsets(relative, region, prev_stripe, ids, markers_rel=markers_rel,
                               marker_stripes=marker_stripes, column_relative=column_relative,
                               prev_column=prev_column, stripe_px=stripe_px, **options)
    out = np.array(stripe, dtype=np.int32, copy=True)
    recovered = np.zeros(relative.shape, bool)
    inner = _region_interior(region, rim_px)  # rims: where the decoder welds surfaces
    if use_columns:
        col_rel = np.asarray(column_relative, np.float64)
        prev_col = np.asarray(prev_column, np.float64)
        tol_px = options.get("tol_px") or 0.75 * stripe_px
    min_px = options.get("min_overlap_px", 50)
    for rid, off in list(offsets.items()):
        sel = unindexed & (region == rid) & (relative >= 0) & inner
        if use_columns:  # pixel-wise confirmation by the previous frame
            with np.errstate(invalid="ignore"):
                sel &= np.abs(col_rel + off * stripe_px - prev_col) <= tol_px
        if int(sel.sum()) < min_px:  # a few confirmed pixels are no evidence
            del offsets[rid]
            continue
        out[sel] = relative[sel] + off
        recovered |= sel
    return out, offsets, recovered


def _region_interior(region: np.ndarray, rim_px: int) -> np.ndarray:
    """(H, W) bool: pixels farther than ``rim_px`` (chessboard distance) from any pixel of another
    region (or none) and from the image border."""
    import cv2

    r = np.asarray(region).astype(np.float32)  # exact for ids < 2**24
    k = np.ones((2 * rim_px + 1, 2 * rim_px + 1), np.uint8)
    lo = cv2.erode(r, k, borderType=cv2.BORDER_CONSTANT, borderValue=-1.0)
    hi = cv2.dilate(r, k, borderType=cv2.BORDER_CONSTANT, borderValue=-1.0)
    return (lo == r) & (hi == r) & (r >= 0)


def temporal_offsets(relative: np.ndarray, region: np.ndarray, prev_stripe: np.ndarray,
                     unindexed: np.ndarray | list[int], *, markers_rel: dict | None = None,
                     marker_stripes: np.ndarray | None = None, column_relative: np.ndarray | None = None,
                     prev_column: np.ndarray | None = None, stripe_px: int = 8, min_overlap_px: int = 50,
                     min_overlap_frac: float = 0.5, min_agree: float = 0.9, max_alias: float = 0.05,
                     tol_px: float | None = None) -> dict[int, int]:
    """Absolute offsets for regions the markers could not index, from the previous frame.

    relative : (H, W) int32 stripe index relative to its region's unknown offset, -1 where none.
        Its parity is the stripe colour (even green, odd blue), so true offsets are even.
    region : (H, W) int32 region id, -1 where none.
    prev_stripe : (H, W) int32 absolute stripe index of the previous frame, -1 where none.
    unindexed : ids of the regions to resolve.
    markers_rel : optional {region id: relative indices of the cyan marker stripes seen in it}.
    marker_stripes : absolute marker stripe indices (``PatternSpec.marker_indices()``).
    column_relative, prev_column : optional (H, W) projector columns (px, NaN none) of this frame
        at offset 0 and of the previous frame; without them the columns are taken as the stripe
        centres ``(index + 0.5) * stripe_px`` (a coarser check, one stripe of slack).

    A region is indexed with offset ``c`` (even) only when all of these hold -- otherwise it stays
    unindexed (dropped), since a wrong offset is a whole-stripe-pair depth error on the region:

    * overlap: at least ``min_overlap_px`` of its pixels, and ``min_overlap_frac`` of them, have
      a previous column;
    * small motion, unambiguous: on at least ``min_agree`` of the overlap the column with offset
      ``c`` is within ``tol_px`` of the previous frame's (default: 3/4 of a stripe, 6 px for
      8 px stripes, about 2.5 camera px at 650 mm; without columns: the same stripe index), and
      with ``c +- 2`` on at most ``max_alias`` of it;
    * markers: every cyan marker seen in the region falls on a marker stripe with offset ``c``.

    It is right while the projector column under each camera pixel changes by less than
    ``tol_px`` between frames over most of the region (slow motion, or motion along the stripes);
    faster motion makes the agreement fail and the region is left out.  It can be wrong when the
    previous frame itself was wrong there, or when the column moved by a whole multiple of two
    stripes everywhere in the region (not seen in the simulated sequences).
    """
    relative = np.asarray(relative)
    region = np.asarray(region)
    prev_stripe = np.asarray(prev_stripe)
    if not (relative.shape == region.shape == prev_stripe.shape):
        raise GBError(f"temporal_offsets: relative {relative.shape}, region {region.shape} and "
                      f"prev_stripe {prev_stripe.shape} must have the same (H, W) shape")
    w = float(stripe_px)
    if column_relative is not None and prev_column is not None:
        col = np.asarray(column_relative, np.float64)
        prev = np.asarray(prev_column, np.float64)
        if col.shape != relative.shape or prev.shape != relative.shape:
            raise GBError(f"temporal_offsets: column maps {col.shape}, {prev.shape} must be {relative.shape}")
        col = np.where(relative >= 0, col, np.nan)
    else:
        col = np.where(relative >= 0, (relative + 0.5) * w, np.nan)
        prev = np.where(prev_stripe >= 0, (prev_stripe + 0.5) * w, np.nan)
    tol = 0.75 * w if tol_px is None else float(tol_px)
    mset = None if marker_stripes is None else np.asarray(marker_stripes, dtype=np.int64)
    have = np.isfinite(col)
    both = have & np.isfinite(prev)
    out: dict[int, int] = {}
    for rid in unindexed:
        in_region = region == rid
        sel = both & in_region
        n = int(sel.sum())
        if n < min_overlap_px or n < min_overlap_frac * int((have & in_region).sum()):
            continue
        diff = prev[sel] - col[sel]  # = c * w + motion
        best = 2 * int(np.round(np.median(diff) / (2 * w)))

        def agree(c):
            return float(np.mean(np.abs(diff - c * w) <= tol))

        if agree(best) < min_agree or max(agree(best - 2), agree(best + 2)) > max_alias:
            continue
        seen = None if markers_rel is None else markers_rel.get(int(rid))
        if seen is not None and len(seen) and mset is not None and len(mset):
            if not np.isin(np.asarray(seen, dtype=np.int64) + best, mset).all():
                continue  # the markers contradict the borrowed offset
        out[int(rid)] = best
    return out
