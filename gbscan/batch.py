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
its predecessor's state (``FrameResult.state``) as a prior.  What the scanner does with it:
:func:`temporal_offsets`.
"""
from __future__ import annotations

import contextlib
import csv
import hashlib
import io as _io
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from .errors import GBError
from .frames import FrameRef, FrameSource, read_frame
from .io import atomic_path, load_yaml, save_npy, save_yaml, write_text_atomic

MANIFEST = "manifest.csv"
JOB = "job.yaml"
COLUMNS = ("frame", "source", "status", "reason", "points", "coverage", "time_ms", "cpu_ms", "outputs",
           "temporal_px")


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
    extra : values of further manifest columns (``temporal_px``).
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

    def setup(self) -> Callable[[np.ndarray, object], FrameResult]:
        raise NotImplementedError


# -- worker side ---------------------------------------------------------------------------------
_CACHE: dict[str, Callable] = {}  # worker-process-local: Processor.key -> process function
_POOL_PROCESSOR: Processor | None = None


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


def _run_task(proc: Processor, task: _Task, spec: OutputSpec) -> list[dict]:
    """Process and write every frame of ``task``; one manifest row per frame (never raises)."""
    try:
        fn = _process_fn(proc)
    except Exception as e:  # noqa: BLE001 -- every frame of the task fails with the reason
        why = f"could not set up the per-frame processing: {type(e).__name__}: {e}"
        return [_failed_row(r, why) for r in task.refs]
    prior = None
    if spec.temporal and task.warmup is not None:
        try:
            prior = fn(_get_image(task.warmup, task.warmup_image, proc.size), None).state
        except Exception:  # noqa: BLE001 -- the chain simply starts without a prior
            prior = None
    rows = []
    for ref, image in zip(task.refs, task.images):
        t0, c0 = time.perf_counter(), time.thread_time()
        row = {"frame": ref.index, "source": ref.source}
        try:
            rgb = _get_image(ref, image, proc.size)
            res = fn(rgb, prior if spec.temporal else None)
            prior = res.state
            row.update(_write_outputs(spec, ref.index, res))
            row.update({k: v for k, v in res.extra.items() if k in COLUMNS})
            row["status"], row["reason"] = "ok", ""
        except GBError as e:
            prior = None
            row.update(status="failed", reason=_one_line(str(e)), points=0, coverage=0.0, outputs="")
        except Exception as e:  # noqa: BLE001 -- a processor bug must not stop the batch
            prior = None
            row.update(status="failed", reason=_one_line(f"internal error: {type(e).__name__}: {e}"),
                       points=0, coverage=0.0, outputs="")
        row["time_ms"] = round((time.perf_counter() - t0) * 1e3, 1)
        row["cpu_ms"] = round((time.thread_time() - c0) * 1e3, 1)
        rows.append(row)
    return rows


def _pool_init(proc: Processor) -> None:
    import signal

    global _POOL_PROCESSOR
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    _POOL_PROCESSOR = proc
    try:
        _process_fn(proc)  # set up now, not inside the first frame's time
    except Exception:  # noqa: BLE001 -- reported per frame by _run_task
        pass


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
    ok = np.isfinite(xyz).all(axis=2)
    n = int(ok.sum())
    if n == 0:
        raise GBError("no stripes decoded: the frame gave no range point (is the pattern visible?)")
    out = Path(spec.outdir)
    names = spec.names(index)
    save_npy(out / names[0], xyz)
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
              scheduler_timeout_s: float = 10.0) -> BatchSummary:
    """Process the selected frames of ``source`` into ``outdir`` (see the module docstring).

    workers : local processes (default: all cores); ignored with ``scheduler``.
    scheduler : address of a Dask distributed scheduler (``tcp://host:8786``) or a
        ``distributed.Client``; None runs locally.
    read_in : 'worker' (workers read image files), 'parent', or 'auto' (workers for a folder;
        a video is always decoded by the parent, sequentially).
    restart : ignore a previous run's outputs in ``outdir`` (they are overwritten frame by frame).
    chunk : frames per task in temporal mode (default: about four tasks per worker, 4..32).
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
    spec = OutputSpec(str(outdir.resolve()), bool(ply), bool(mesh), bool(temporal))
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
    tasks = _make_tasks(refs, pending, temporal, chunk or _default_chunk(len(pending), workers))

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


def _make_tasks(refs: list[FrameRef], pending: list[FrameRef], temporal: bool, chunk: int) -> list[_Task]:
    if not temporal:
        return [_Task([r], [None]) for r in pending]
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
    """Rows, counters, throttled atomic manifest writes and the progress line (parent side)."""

    def __init__(self, rows, manifest_path, interval_s, prog):
        self.rows, self.path, self.interval_s, self.prog = rows, manifest_path, interval_s, prog
        self.finished: set[int] = set()
        self.n_ok = self.n_failed = 0
        self.dirty, self.last = False, -math.inf
        self.first_result = math.nan

    def record(self, new_rows: list[dict]) -> None:
        if math.isnan(self.first_result):
            self.first_result = time.perf_counter()
        for r in new_rows:
            self.rows[r["frame"]] = r
            self.finished.add(r["frame"])
            if r["status"] == "ok":
                self.n_ok += 1
            else:
                self.n_failed += 1
        self.dirty = True
        self.flush()
        if self.prog:
            self.prog.update(self.n_ok + self.n_failed, self.n_failed)

    def flush(self, force: bool = False) -> None:
        now = time.monotonic()
        if self.dirty and (force or now - self.last >= self.interval_s):
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

    def new_pool():
        return ProcessPoolExecutor(workers, mp_context=ctx, initializer=_pool_init, initargs=(processor,))

    pool = new_pool()
    inflight: dict = {}
    try:
        while True:
            cap = 1 if suspects else limit
            while len(inflight) < cap:
                if suspects:
                    if inflight:
                        break
                    t = suspects.pop(0)
                else:
                    t = next(it, None) if not exhausted else None
                    if t is None:
                        exhausted = True
                        break
                inflight[pool.submit(_pool_task, t, spec)] = t
            if not inflight:
                if exhausted and not suspects:
                    return
                continue
            done, _ = wait(inflight, return_when=FIRST_COMPLETED)
            broken = False
            for f in done:
                t = inflight.pop(f)
                try:
                    state.record(f.result())
                except BrokenProcessPool:
                    broken = True
                    if len(t.refs) == 1 and t.attempt >= 1:
                        state.record(_died_rows(t, "worker process died while processing this frame "
                                                   "(crashed or killed; e.g. out of memory)"))
                    else:
                        suspects.extend(_singles(t))
            if broken:
                for f, t in list(inflight.items()):  # every other in-flight frame died with the pool
                    suspects.extend(_singles(t))
                inflight.clear()
                pool.shutdown(wait=True, cancel_futures=True)
                pool = new_pool()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


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

    def __init__(self, calibration_path, *, decode_params=None, clean_params=None, temporal: bool = False):
        from .calibfile import load_calibration

        path = Path(calibration_path)
        self.calibration = load_calibration(path)
        self.decode_params, self.clean_params = decode_params, clean_params
        self.temporal = bool(temporal)
        cam = self.calibration.camera
        self.size = (cam.width, cam.height)
        sha = file_sha256(path)
        self.key = hashlib.sha256((sha + repr(decode_params) + repr(clean_params)).encode()).hexdigest()[:16]
        self.description = {"calibration": str(path.resolve()), "calibration_sha256": sha,
                            "decode_params": repr(decode_params), "clean_params": repr(clean_params)}

    def setup(self):
        from .scan import Scanner

        scanner = Scanner(self.calibration, decode_params=self.decode_params, clean_params=self.clean_params)
        temporal = self.temporal

        def process(rgb, prior=None):
            scan = scanner.scan(rgb)
            extra, state = {}, None
            if temporal:
                scan, state, extra = _temporal_scan(scanner, scan, prior)
            if scan.n_points == 0:
                why = (scan.stripemap.stats.get("why") if scan.stripemap is not None else None) or \
                    "no stripes decoded: the frame gave no range point"
                raise GBError(f"no points: {why}")

            def write_mesh(path):
                from .mesh import write_mesh as _write_mesh

                _write_mesh(path, scan.mesh_arrays("grid"))

            return FrameResult(scan.xyz, write_cloud=scan.save_ply, write_mesh=write_mesh, state=state, extra=extra)

        return process


def _temporal_scan(scanner, scan, prev_stripe):
    """Index the frame's unindexed regions from the previous frame's stripe map.

    Returns (scan, stripe map for the next frame, manifest extras).  The offsets come from
    :func:`temporal_stripes`.  Turning the recovered regions into points needs the decoder's
    projector column of unindexed regions computed with offset 0 (``StripeMap.column_relative``);
    while the decoder does not provide it, the recovered stripes only carry the chain forward
    (``temporal_px`` counts them) and the points are the frame's own.
    """
    from .decode import UNINDEXED

    sm = scan.stripemap
    stripe = scan.stripe
    if sm is None or stripe is None:
        return scan, None, {}
    if prev_stripe is None or not (sm.mask == UNINDEXED).any():
        return scan, stripe, {"temporal_px": 0}
    filled, offsets, recovered = temporal_stripes(
        stripe, sm.relative, sm.region, sm.mask == UNINDEXED, sm.labels, prev_stripe, sm.pattern.marker_indices())
    col_rel = getattr(sm, "column_relative", None)
    if col_rel is not None and recovered.any():
        off_px = np.zeros(recovered.shape, np.float64)
        for rid, off in offsets.items():
            off_px[sm.region == rid] = off * sm.pattern.stripe_px
        column = np.where(recovered, np.asarray(col_rel, np.float64) + off_px, sm.column)
        conf = np.where(recovered, 0.5 * np.maximum(sm.confidence, 0.5), sm.confidence)  # a prior, not markers
        new = scanner.reconstruct(column, conf, decoded=sm.valid | recovered)
        new.stripe, new.stripemap = filled, sm
        new.timings_ms = {**scan.timings_ms, "temporal": new.timings_ms.get("total", 0.0)}
        scan = new
    return scan, filled, {"temporal_px": int(recovered.sum())}


# -- temporal help (pure) ---------------------------------------------------------------------------
def temporal_stripes(stripe: np.ndarray, relative: np.ndarray, region: np.ndarray, unindexed: np.ndarray,
                     labels: np.ndarray, prev_stripe: np.ndarray, marker_stripes: np.ndarray, **options):
    """The absolute stripe map with unindexed regions indexed from the previous frame.

    stripe : (H, W) int32 the decoder's absolute stripes (-1 none), kept where set.
    relative, region : (H, W) int32 from the decoder (``StripeMap.relative``/``region``).
    unindexed : (H, W) bool pixels of regions the markers could not index.
    labels : (H, W) uint8 colour classes (``gbscan.pattern.CYAN`` marks marker stripes seen).
    prev_stripe : (H, W) int32 previous frame's absolute stripes (-1 none).
    marker_stripes : absolute marker stripe indices (``PatternSpec.marker_indices()``).

    Returns ``(stripe (H, W) int32, {region: offset}, recovered (H, W) bool)``: the decoder's
    stripes plus ``relative + offset`` on the recovered pixels, -1 elsewhere.  See
    :func:`temporal_offsets` for when it is right.
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
    offsets = temporal_offsets(relative, region, prev_stripe, ids, markers_rel=markers_rel,
                               marker_stripes=marker_stripes, **options)
    out = np.array(stripe, dtype=np.int32, copy=True)
    recovered = np.zeros(relative.shape, bool)
    for rid, off in offsets.items():
        sel = unindexed & (region == rid) & (relative >= 0)
        out[sel] = relative[sel] + off
        recovered |= sel
    return out, offsets, recovered


def temporal_offsets(relative: np.ndarray, region: np.ndarray, prev_stripe: np.ndarray,
                     unindexed: np.ndarray | list[int], *, markers_rel: dict | None = None,
                     marker_stripes: np.ndarray | None = None, min_overlap_px: int = 50,
                     min_agree: float = 0.6) -> dict[int, int]:
    """Absolute offsets for regions the markers could not index, from the previous frame.

    relative : (H, W) int32 stripe index relative to its region's unknown offset, -1 where none.
        Its parity is the stripe colour (even green, odd blue), so true offsets are even.
    region : (H, W) int32 region id, -1 where none.
    prev_stripe : (H, W) int32 absolute stripe index of the previous frame, -1 where none.
    unindexed : ids of the regions to resolve.
    markers_rel : optional {region id: relative indices of the cyan marker stripes seen in it}.
    marker_stripes : absolute marker stripe indices (``PatternSpec.marker_indices()``).

    Returns {region id: offset} (absolute = relative + offset) for the regions resolved; a
    region is left out when it overlaps the previous frame's indexed pixels on fewer than
    ``min_overlap_px`` pixels or fewer than ``min_agree`` of them agree.

    The prior offset of a region is the even ``c`` that best explains ``prev_stripe - relative``
    on its overlap (votes: 1 where equal to ``c``, 1/2 where one off).  Without a marker in the
    region it is used as is: correct while the stripes move by less than one stripe width between
    frames (about 3.4 camera px at 650 mm; the colours repeat every two stripes, so a larger
    shift cannot be told from the neighbouring even offset).  With markers seen in the
    region, the candidate offsets are those that put every seen marker on a marker stripe, and
    the one nearest the prior wins: correct while the motion is below half the gap between
    markers (2 to 4 stripes).  Faster motion gives a wrong offset -- a whole-stripe-pair depth
    error on that region -- which is why unindexed regions stay unindexed without a prior.
    """
    relative = np.asarray(relative)
    region = np.asarray(region)
    prev_stripe = np.asarray(prev_stripe)
    if not (relative.shape == region.shape == prev_stripe.shape):
        raise GBError(f"temporal_offsets: relative {relative.shape}, region {region.shape} and "
                      f"prev_stripe {prev_stripe.shape} must have the same (H, W) shape")
    out: dict[int, int] = {}
    mset = None if marker_stripes is None else np.asarray(marker_stripes, dtype=np.int64)
    both = (relative >= 0) & (prev_stripe >= 0)
    for rid in unindexed:
        sel = both & (region == rid)
        n = int(sel.sum())
        if n < min_overlap_px:
            continue
        diff = prev_stripe[sel].astype(np.int64) - relative[sel].astype(np.int64)
        # Score every even offset c: a pixel votes 1 if diff == c (the stripe did not move there)
        # and 1/2 if diff == c +- 1 (it moved by part of a stripe, across a boundary).
        vals, counts = np.unique(diff, return_counts=True)
        cands = np.unique(np.concatenate([vals - (vals % 2), vals + (vals % 2)]))
        near = np.abs(vals[None, :] - cands[:, None])
        score = ((near == 0) * 1.0 + (near == 1) * 0.5) @ counts
        support = (near <= 1) @ counts
        i = int(np.argmax(score))
        best = int(cands[i])
        if support[i] < min_agree * n:
            continue
        seen = None if markers_rel is None else markers_rel.get(rid)
        if seen is not None and len(seen) and mset is not None and len(mset):
            seen = np.asarray(seen, dtype=np.int64)
            cands = (mset[:, None] - seen[None, :]).ravel()
            cands = np.unique(cands[cands % 2 == 0])
            ok = [c for c in cands if np.isin(seen + c, mset).all()]
            if ok:
                best = int(min(ok, key=lambda c: (abs(c - best), c)))
        out[int(rid)] = best
    return out
