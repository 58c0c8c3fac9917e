"""The batch engine: outputs, manifest, resume, bad frames, dying workers, Dask, temporal help.

The engine is tested with a small deterministic processor (``Fake``) so that every value written
can be checked exactly; the scanner end to end runs in the ``slow`` tests at the bottom.
"""
import os
import subprocess
import sys

import numpy as np
import pytest

from gbscan import batch
from gbscan.batch import FrameResult, Processor, read_manifest, run_batch, temporal_offsets
from gbscan.errors import GBError
from gbscan.frames import open_frames, write_video
from gbscan.io import write_png

H, W = 24, 32
DIE = (13, 37, 99)  # a frame whose pixel (0, 0) has this colour kills its worker process
SPIN = (21, 42, 77)  # ... loops forever in Python code (stopped by the worker's own deadline)
STUCK = (22, 44, 88)  # ... blocks forever with SIGALRM masked (like a C call that never returns)


class Fake(Processor):
    """xyz = (u, v, 500 + frame id) where green > 0, NaN elsewhere; frame id = pixel (0,0) red.

    A frame with no green pixel fails ("no stripes"); state = frame id, and xyz[0, 0, 0] records
    the prior received (-1 for none) so temporal chaining can be checked.
    """

    size = (W, H)

    def __init__(self, key="fake-1", setup_log=None):
        self.key = key
        self.description = {"fake": key}
        self.setup_log = setup_log

    def setup(self):
        if self.setup_log is not None:
            with open(self.setup_log, "a") as fh:
                fh.write(f"{os.getpid()}\n")
        v, u = np.mgrid[0:H, 0:W].astype(np.float32)

        def process(rgb, prior):
            if tuple(int(c) for c in rgb[0, 0]) == DIE:
                os._exit(3)
            if tuple(int(c) for c in rgb[0, 0]) == SPIN:
                while True:
                    pass
            if tuple(int(c) for c in rgb[0, 0]) == STUCK:
                import signal
                import time

                signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGALRM})
                time.sleep(3600)
            if rgb[..., 1].max() == 0:
                raise GBError("no stripes found in this frame")
            fid = float(rgb[0, 0, 0])
            xyz = np.stack([u, v, np.full_like(u, 500 + fid)], axis=-1)
            xyz[rgb[..., 1] == 0] = np.nan
            xyz[0, 0, 0] = -1 if prior is None else prior
            return FrameResult(xyz, colors=rgb, state=fid)

        return process


def _frame(fid, seed=0):
    rng = np.random.default_rng(seed + fid)
    img = np.zeros((H, W, 3), np.uint8)
    img[..., 1] = (rng.random((H, W)) > 0.3) * 200
    img[0, 0] = (fid, 255, 0)
    return img


def _folder(tmp_path, n=8, name="in"):
    d = tmp_path / name
    d.mkdir()
    for i in range(n):
        write_png(d / f"img_{i}.png", _frame(i))
    return d


def _check_frame(out, fid, prior_ok=None):
    xyz = np.load(out / f"frame_{fid:06d}.xyz.npy")
    assert xyz.dtype == np.float32 and xyz.shape == (H, W, 3)
    img = _frame(fid)
    valid = img[..., 1] > 0
    np.testing.assert_array_equal(np.isfinite(xyz[..., 2]), valid)
    assert np.all(xyz[..., 2][valid] == 500 + fid)
    return xyz


def test_folder_outputs_and_manifest(tmp_path):
    src = open_frames(_folder(tmp_path))
    log = tmp_path / "setups.txt"
    s = run_batch(src, Fake(setup_log=log), tmp_path / "out", workers=2, ply=True, progress=False)
    assert (s.selected, s.already_done, s.ok, s.failed) == (8, 0, 8, 0)
    pids = log.read_text().split()
    assert 1 <= len(pids) <= 2 and len(set(pids)) == len(pids)  # set up once per worker process
    rows = read_manifest(tmp_path / "out" / "manifest.csv")
    assert sorted(rows) == list(range(8))
    for i in range(8):
        _check_frame(tmp_path / "out", i)
        r = rows[i]
        assert r["status"] == "ok" and r["source"] == f"img_{i}.png"
        n = int((_frame(i)[..., 1] > 0).sum())
        assert int(r["points"]) == n and abs(float(r["coverage"]) - n / (H * W)) < 1e-4
        ply = (tmp_path / "out" / f"frame_{i:06d}.ply").read_bytes()
        assert f"element vertex {n}\n".encode() in ply
    assert not list((tmp_path / "out").glob(".*"))  # no temporaries left


def test_a_point_is_finite_in_all_three_coordinates(tmp_path):
    """A generic processor's xyz may be non-finite in one coordinate only: no such point is counted
    or written."""
    from gbscan.batch import OutputSpec, _write_outputs

    rng = np.random.default_rng(5)
    xyz = rng.normal(size=(H, W, 3)).astype(np.float32)
    for c, bad in ((0, np.inf), (1, np.nan), (2, -np.inf)):
        xyz[rng.random((H, W)) < 0.1, c] = bad
    ok = np.isfinite(xyz).all(axis=2)
    assert 0 < ok.sum() < H * W - 3
    row = _write_outputs(OutputSpec(str(tmp_path), ply=True), 3, FrameResult(xyz))
    assert row["points"] == ok.sum()
    assert f"element vertex {ok.sum()}\n".encode() in (tmp_path / "frame_000003.ply").read_bytes()
    np.testing.assert_array_equal(np.load(tmp_path / "frame_000003.xyz.npy"), xyz)


def test_ply_reads_back_in_open3d(tmp_path):
    o3d = pytest.importorskip("open3d")
    pts = np.random.default_rng(0).normal(size=(100, 3)).astype(np.float32)
    col = np.random.default_rng(1).integers(0, 256, (100, 3), dtype=np.uint8)
    batch.write_ply(tmp_path / "c.ply", pts, col)
    pc = o3d.io.read_point_cloud(str(tmp_path / "c.ply"))
    np.testing.assert_allclose(np.asarray(pc.points), pts, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(pc.colors) * 255, col, atol=1e-3)
    batch.write_ply(tmp_path / "m.ply", pts[:4], None, np.array([[0, 1, 2], [1, 2, 3]]))
    m = o3d.io.read_triangle_mesh(str(tmp_path / "m.ply"))
    np.testing.assert_array_equal(np.asarray(m.triangles), [[0, 1, 2], [1, 2, 3]])


def test_video_selection_and_resume(tmp_path):
    video = write_video(tmp_path / "seq.avi", [_frame(i) for i in range(10)])
    out = tmp_path / "out"
    s = run_batch(open_frames(video), Fake(), out, workers=2, start=1, stop=9, every=2, progress=False)
    assert s.ok == 4
    rows = read_manifest(out / "manifest.csv")
    assert sorted(rows) == [1, 3, 5, 7] and rows[3]["source"] == "seq.avi#3"
    for i in (1, 3, 5, 7):
        _check_frame(out, i)
    # Rerun over everything: the four done frames are skipped, a deleted output is redone.
    (out / "frame_000005.xyz.npy").unlink()
    s = run_batch(open_frames(video), Fake(), out, workers=2, progress=False)
    assert (s.selected, s.already_done, s.ok) == (10, 3, 7)
    assert sorted(read_manifest(out / "manifest.csv")) == list(range(10))
    # Other settings in the same folder are refused, unless --restart.
    with pytest.raises(GBError, match="other calibration"):
        run_batch(open_frames(video), Fake("fake-2"), out, workers=1, progress=False)
    s = run_batch(open_frames(video), Fake("fake-2"), out, workers=1, restart=True, stop=2, progress=False)
    assert (s.already_done, s.ok) == (0, 2)


def test_bad_frames_are_recorded_and_batch_goes_on(tmp_path):
    d = _folder(tmp_path, n=5)
    write_png(d / "img_2.png", np.zeros((H, W, 3), np.uint8))        # no stripes
    write_png(d / "img_3.png", np.zeros((H + 2, W, 3), np.uint8))    # wrong size
    (d / "img_4.png").write_bytes(b"garbage")                         # unreadable
    (d / "readme.txt").write_text("ignored")
    out = tmp_path / "out"
    s = run_batch(open_frames(d), Fake(), out, workers=2, progress=False)
    assert (s.ok, s.failed) == (2, 3)
    rows = read_manifest(out / "manifest.csv")
    assert [rows[i]["status"] for i in range(5)] == ["ok", "ok", "failed", "failed", "failed"]
    assert "no stripes" in rows[2]["reason"]
    assert f"{W}x{H + 2}" in rows[3]["reason"] and "expected" in rows[3]["reason"]
    assert "could not be read" in rows[4]["reason"]
    assert not (out / "frame_000002.xyz.npy").exists()
    # Fix the frames; the rerun does exactly the failed ones.
    for i in (2, 3, 4):
        write_png(d / f"img_{i}.png", _frame(i))
    s = run_batch(open_frames(d), Fake(), out, workers=2, progress=False)
    assert (s.already_done, s.ok, s.failed) == (2, 3, 0)
    for i in range(5):
        _check_frame(out, i)


@pytest.mark.parametrize("read_in", ["worker", "parent"])
def test_worker_dying_mid_batch(tmp_path, read_in):
    d = _folder(tmp_path, n=8)
    killer = _frame(4)
    killer[0, 0] = DIE
    write_png(d / "img_4.png", killer)
    out = tmp_path / "out"
    s = run_batch(open_frames(d), Fake(), out, workers=2, read_in=read_in, progress=False)
    rows = read_manifest(out / "manifest.csv")
    assert (s.ok, s.failed) == (7, 1)
    assert rows[4]["status"] == "failed" and "worker process died" in rows[4]["reason"]
    for i in set(range(8)) - {4}:
        assert rows[i]["status"] == "ok"
        _check_frame(out, i)
    write_png(d / "img_4.png", _frame(4))
    s = run_batch(open_frames(d), Fake(), out, workers=2, progress=False)
    assert (s.already_done, s.ok) == (7, 1)


def test_a_pool_broken_before_a_submit_loses_no_frame(tmp_path, monkeypatch):
    """A worker may die between the parent's wait and its next submit: the submit then raises
    BrokenProcessPool (seen once in CI, test_worker_dying_mid_batch[parent]).  The refused task
    waits its turn and nothing is lost: simulated here by refusing the first submit (nothing in
    flight: a new pool at once) and a later one (frames in flight: they report, then it goes)."""
    from concurrent.futures import ProcessPoolExecutor
    from concurrent.futures.process import BrokenProcessPool

    real = ProcessPoolExecutor.submit
    calls = {"n": 0}

    def flaky(self, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] in (1, 4):
            raise BrokenProcessPool("simulated: a worker died since the last wait")
        return real(self, *args, **kwargs)

    monkeypatch.setattr(ProcessPoolExecutor, "submit", flaky)
    d = _folder(tmp_path, n=8)
    out = tmp_path / "out"
    s = run_batch(open_frames(d), Fake(), out, workers=2, read_in="parent", progress=False)
    assert (s.ok, s.failed) == (8, 0) and calls["n"] >= 10
    rows = read_manifest(out / "manifest.csv")
    for i in range(8):
        assert rows[i]["status"] == "ok"
        _check_frame(out, i)


def test_hanging_frames_time_out_and_the_batch_goes_on(tmp_path):
    d = _folder(tmp_path, n=7)
    for i, colour in ((2, SPIN), (4, STUCK)):
        img = _frame(i)
        img[0, 0] = colour
        write_png(d / f"img_{i}.png", img)
    out = tmp_path / "out"
    s = run_batch(open_frames(d), Fake(), out, workers=2, timeout_s=1.0, progress=False)
    rows = read_manifest(out / "manifest.csv")
    assert (s.ok, s.failed) == (5, 2)
    for i in (2, 4):  # 2 stops at its deadline in the worker; 4 ignores it and is killed by the parent
        assert rows[i]["status"] == "failed" and rows[i]["reason"].startswith("timeout"), rows[i]
        assert not (out / f"frame_{i:06d}.xyz.npy").exists()
    for i in (0, 1, 3, 5, 6):
        assert rows[i]["status"] == "ok"
        _check_frame(out, i)
    assert s.elapsed_s < 30
    with pytest.raises(GBError, match="--timeout-s"):
        run_batch(open_frames(d), Fake(), tmp_path / "o2", timeout_s=-1, progress=False)


def test_deadline_in_a_thread_raises_there_and_never_later():
    import threading

    result = {}

    def spin():
        try:
            with batch._deadline(0.2):
                while True:
                    pass
        except batch.FrameTimeout:
            result["timeout"] = True
        with batch._deadline(0.2):  # finishes in time: no exception, now or after the deadline
            pass
        import time

        time.sleep(0.4)
        result["after"] = True

    th = threading.Thread(target=spin)
    th.start()
    th.join(10)
    assert result == {"timeout": True, "after": True}


def test_several_frames_per_task_and_a_killer_among_them(tmp_path):
    d = _folder(tmp_path, n=8)
    killer = _frame(4)
    killer[0, 0] = DIE
    write_png(d / "img_4.png", killer)
    out = tmp_path / "out"
    s = run_batch(open_frames(d), Fake(), out, workers=2, frames_per_task=3, progress=False)
    rows = read_manifest(out / "manifest.csv")
    assert (s.ok, s.failed) == (7, 1) and "worker process died" in rows[4]["reason"]
    for i in set(range(8)) - {4}:
        _check_frame(out, i)


def test_outputs_are_synced_before_the_manifest_lists_them(tmp_path, monkeypatch):
    synced, listed_unsynced = set(), []
    real_sync, real_write = batch.fsync_paths, batch.write_manifest

    def fsync_paths(paths):
        paths = list(paths)
        synced.update(str(p) for p in paths)
        real_sync(paths)

    def write_manifest(path, rows):
        for r in rows.values():
            if r.get("status") == "ok":
                listed_unsynced.extend(n for n in r["outputs"].split(";") if str(path.parent / n) not in synced)
        return real_write(path, rows)

    monkeypatch.setattr(batch, "fsync_paths", fsync_paths)
    monkeypatch.setattr(batch, "write_manifest", write_manifest)
    s = run_batch(open_frames(_folder(tmp_path, n=6)), Fake(), tmp_path / "out", workers=2, ply=True,
                  manifest_interval_s=0.0, progress=False)
    assert s.ok == 6 and len(synced) == 12 and listed_unsynced == []


def test_temporal_chains_every_frame_to_its_predecessor(tmp_path):
    video = write_video(tmp_path / "seq.avi", [_frame(i) for i in range(11)])
    out = tmp_path / "out"
    s = run_batch(open_frames(video), Fake(), out, workers=2, temporal=True, chunk=3, progress=False)
    assert s.ok == 11
    for i in range(11):
        assert np.load(out / f"frame_{i:06d}.xyz.npy")[0, 0, 0] == (i - 1 if i else -1)
    # Resume in temporal mode: the redone frame still gets its predecessor (a warm-up frame).
    (out / "frame_000007.xyz.npy").unlink()
    s = run_batch(open_frames(video), Fake(), out, workers=1, temporal=True, progress=False)
    assert (s.already_done, s.ok) == (10, 1)
    assert np.load(out / "frame_000007.xyz.npy")[0, 0, 0] == 6


def test_manifest_never_half_written_and_interrupt_marks_skipped(tmp_path, monkeypatch):
    src = open_frames(_folder(tmp_path, n=6))
    out = tmp_path / "out"
    calls = {"n": 0}
    real = batch._RunState.record

    def record(self, rows):
        real(self, rows)
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt

    monkeypatch.setattr(batch._RunState, "record", record)
    with pytest.raises(KeyboardInterrupt):
        run_batch(src, Fake(), out, workers=1, max_in_flight=1, progress=False)
    rows = read_manifest(out / "manifest.csv")
    assert [rows[i]["status"] for i in range(6)] == ["ok"] * 3 + ["skipped"] * 3
    monkeypatch.undo()
    s = run_batch(src, Fake(), out, workers=1, progress=False)
    assert (s.already_done, s.ok) == (3, 3)


def test_argument_errors(tmp_path):
    src = open_frames(_folder(tmp_path, n=2))
    with pytest.raises(GBError, match="no frame selected"):
        run_batch(src, Fake(), tmp_path / "o", start=5, progress=False)
    with pytest.raises(GBError, match="--workers"):
        run_batch(src, Fake(), tmp_path / "o", workers=0, progress=False)
    (tmp_path / "file").write_text("x")
    with pytest.raises(GBError, match="not a folder"):
        run_batch(src, Fake(), tmp_path / "file", progress=False)
    (tmp_path / "o2").mkdir()
    (tmp_path / "o2" / "manifest.csv").write_text("what,ever\n1,2\n")
    with pytest.raises(GBError, match="not a gbscan batch manifest"):
        run_batch(src, Fake(), tmp_path / "o2", progress=False)


def test_progress_lines(capsys):
    p = batch.Progress(10, stream=sys.stderr, interval_s=0)
    p.update(5, 1)
    p.close()
    err = capsys.readouterr().err
    assert "5/10 frames" in err and "frames/s" in err and "left" in err and "1 failed" in err


# -- temporal offsets (pure) -----------------------------------------------------------------------
def _columns(shift_px, w=200, h=20, stripe_cam_px=3.4, stripe_px=8):
    """Projector columns (px) of a plane whose stripes are ``stripe_cam_px`` camera px wide,
    shifted by ``shift_px`` camera px, and their stripe indices (stripe 40 at u = shift)."""
    u = np.arange(w, dtype=np.float64)[None, :].repeat(h, 0)
    col = ((u - shift_px) / stripe_cam_px + 40) * stripe_px
    return col, np.floor(col / stripe_px).astype(np.int32)


def _stripes(shift_px, **kw):
    return _columns(shift_px, **kw)[1]


def test_temporal_offsets_recovers_small_motion():
    prev_col, prev = _columns(0.0)
    true_off = 30
    for shift in (0.0, 1.5, -2.5):  # camera px: up to 5.9 projector px of motion (tolerance 6)
        col, cur = _columns(shift)
        rel, region = cur - true_off, np.zeros(cur.shape, np.int32)
        off = temporal_offsets(rel, region, prev, [0], column_relative=col - 8 * true_off, prev_column=prev_col)
        assert off == {0: true_off}, shift
    # Without columns the stripe index itself must not change on 90% of the overlap.
    for shift, ok in ((0.0, True), (0.2, True), (1.5, False)):
        cur = _stripes(shift)
        off = temporal_offsets(cur - true_off, np.zeros(cur.shape, np.int32), prev, [0])
        assert off == ({0: true_off} if ok else {}), shift


def test_temporal_offsets_refuses_ambiguous_motion_and_contradicting_markers():
    prev_col, prev = _columns(0.0)
    true_off = 30
    markers = np.array([41, 46, 52, 59, 67, 72])
    for shift in (3.5, -3.0):  # ~8 projector px: halfway between offsets, neither agrees
        col, cur = _columns(shift)
        off = temporal_offsets(cur - true_off, np.zeros(cur.shape, np.int32), prev, [0],
                               column_relative=col - 8 * true_off, prev_column=prev_col)
        assert off == {}, shift
    # Two whole stripes of motion look exactly like the neighbouring offset (the limitation the
    # docstring states); markers seen in the region veto it.
    col, cur = _columns(7.0)
    rel = cur - true_off
    kw = dict(column_relative=col - 8 * true_off, prev_column=prev_col)
    assert temporal_offsets(rel, np.zeros(rel.shape, np.int32), prev, [0], **kw) == {0: true_off + 2}
    seen = [m - true_off for m in markers if rel.min() <= m - true_off <= rel.max()]
    assert temporal_offsets(rel, np.zeros(rel.shape, np.int32), prev, [0], markers_rel={0: seen},
                            marker_stripes=markers, **kw) == {}
    # Consistent markers do not veto the right offset.
    col, cur = _columns(1.0)
    rel = cur - true_off
    seen = [m - true_off for m in markers if rel.min() <= m - true_off <= rel.max()]
    assert temporal_offsets(rel, np.zeros(rel.shape, np.int32), prev, [0], markers_rel={0: seen},
                            marker_stripes=markers, column_relative=col - 8 * true_off,
                            prev_column=prev_col) == {0: true_off}


def test_temporal_offsets_refuses_without_overlap():
    prev = np.full((10, 10), -1, np.int32)
    rel = np.zeros((10, 10), np.int32)
    assert temporal_offsets(rel, np.zeros_like(rel), prev, [0]) == {}
    with pytest.raises(GBError, match="same"):
        temporal_offsets(rel, np.zeros((5, 5), np.int32), prev, [0])
    # Overlap on less than half of the region: refused even though it agrees.
    prev_col, prev = _columns(0.0)
    col, cur = _columns(0.0)
    prev_col[:, 80:] = np.nan
    assert temporal_offsets(cur - 30, np.zeros(cur.shape, np.int32), prev, [0], column_relative=col - 240,
                            prev_column=prev_col) == {}


# -- Dask --------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def dask_cluster():
    distributed = pytest.importorskip("distributed")
    import dask

    with dask.config.set({"distributed.scheduler.allowed-failures": 1}):
        cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                           host="127.0.0.1", dashboard_address=None)
        try:
            yield cluster
        finally:
            cluster.close()


def test_dask_cluster_with_a_killer_frame(tmp_path, dask_cluster):
    d = _folder(tmp_path, n=6)
    killer = _frame(2)
    killer[0, 0] = DIE
    write_png(d / "img_2.png", killer)
    write_png(d / "img_3.png", np.zeros((H, W, 3), np.uint8))
    out = tmp_path / "out"
    log = tmp_path / "setups.txt"
    s = run_batch(open_frames(d), Fake(setup_log=log), out, scheduler=dask_cluster.scheduler_address,
                  progress=False)
    rows = read_manifest(out / "manifest.csv")
    assert (s.ok, s.failed) == (4, 2)
    pids = log.read_text().split()
    # Setup runs once per worker process, never per frame: every pid appears once.  Dask retries a
    # task that killed its worker up to `allowed-failures` times, so the killer frame may take out
    # that many + 1 workers per submission, each replaced by a fresh process that sets up once;
    # the engine submits it twice (in its task, then alone to tell it from its victims).
    import dask

    kills = int(dask.config.get("distributed.scheduler.allowed-failures")) + 1
    assert len(set(pids)) == len(pids) <= 2 + 2 * kills
    assert rows[2]["status"] == "failed" and "KilledWorker" in rows[2]["reason"]
    assert "no stripes" in rows[3]["reason"]
    for i in (0, 1, 4, 5):
        _check_frame(out, i)
    # The video path (frames decoded by the client) and a resume through the cluster.
    video = write_video(tmp_path / "seq.avi", [_frame(i) for i in range(6)])
    out2 = tmp_path / "out2"
    s = run_batch(open_frames(video), Fake(), out2, scheduler=dask_cluster.scheduler_address, stop=3,
                  progress=False)
    assert s.ok == 3
    s = run_batch(open_frames(video), Fake(), out2, scheduler=dask_cluster.scheduler_address, progress=False)
    assert (s.already_done, s.ok) == (3, 3)
    for i in range(6):
        _check_frame(out2, i)
    # A frame looping in Python on a Dask worker (task thread) is stopped by its deadline.
    spin = _frame(1)
    spin[0, 0] = SPIN
    d3 = tmp_path / "in3"
    d3.mkdir()
    write_png(d3 / "a.png", _frame(0))
    write_png(d3 / "b.png", spin)
    s = run_batch(open_frames(d3), Fake(), tmp_path / "out3", scheduler=dask_cluster.scheduler_address,
                  timeout_s=2.0, progress=False)
    rows = read_manifest(tmp_path / "out3" / "manifest.csv")
    assert (s.ok, s.failed) == (1, 1) and rows[1]["reason"].startswith("timeout")


def test_unreachable_scheduler(tmp_path):
    pytest.importorskip("distributed")
    src = open_frames(_folder(tmp_path, n=1))
    with pytest.raises(GBError, match="cannot reach the Dask scheduler"):
        run_batch(src, Fake(), tmp_path / "o", scheduler="tcp://127.0.0.1:9", progress=False,
                  scheduler_timeout_s=1.0)


# -- the command, with the real scanner --------------------------------------------------------------
def _gbscan(*args):
    return subprocess.run([sys.executable, "-m", "gbscan.cli", *map(str, args)], capture_output=True, text=True)


@pytest.fixture(scope="module")
def calib_file(tmp_path_factory):
    from gbscan import sim
    from gbscan.calibfile import calibration_from_rig, save_calibration
    from gbscan.pattern import PatternSpec

    return save_calibration(tmp_path_factory.mktemp("calib") / "calib.yaml",
                            calibration_from_rig(sim.paper_rig(), PatternSpec()))


def test_cli_bad_input_is_one_line(tmp_path, calib_file):
    (tmp_path / "bad.avi").write_bytes(b"\x00garbage" * 100)
    (tmp_path / "empty").mkdir()
    for args in (["batch", tmp_path / "bad.avi", "--calib", calib_file, "-o", tmp_path / "o"],
                 ["batch", tmp_path / "empty", "--calib", calib_file, "-o", tmp_path / "o"],
                 ["batch", tmp_path / "missing", "--calib", calib_file, "-o", tmp_path / "o"],
                 ["batch", tmp_path / "empty", "--calib", tmp_path / "nocalib.yaml", "-o", tmp_path / "o"],
                 ["batch", tmp_path / "empty", "--calib", calib_file, "-o", tmp_path / "o", "--every", "0"],
                 ["batch", tmp_path / "empty", "--calib", calib_file, "-o", tmp_path / "o", "--timeout-s", "-1"],
                 ["batch", tmp_path / "empty", "--calib", calib_file, "-o", tmp_path / "o", "--max-jump", "0"]):
        r = _gbscan(*args)
        assert r.returncode == 1, (args, r.stderr)
        assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


@pytest.mark.slow
def test_cli_folder_of_raw_bayer_frames(tmp_path, calib_file):
    """gbscan batch --bayer: each raw mosaic demosaiced as gbscan.io.demosaic does, scanned as gbscan scan does;
    --bayer on a video is one line."""
    import dataclasses

    from gbscan import sim
    from gbscan.io import demosaic
    from gbscan.pattern import PatternSpec, render_pattern
    from gbscan.scan import Scanner

    cond = dataclasses.replace(sim.preset("typical"), supersample=1, bayer="GBRG", bayer_raw=True)
    frames = tmp_path / "raw"
    frames.mkdir()
    mosaics = []
    for i in range(2):
        m = sim.render(sim.paper_rig(), sim.scenes.sphere((-20.0 + 40.0 * i, 0.0, 650.0), 100.0, wall_mm=900.0),
                       render_pattern(PatternSpec()), cond, seed=i).image
        write_png(frames / f"f{i}.png", m)
        mosaics.append(m)
    r = _gbscan("batch", frames, "--calib", calib_file, "-o", tmp_path / "out", "--workers", "1", "--bayer", "GBRG",
                "--quiet")
    assert r.returncode == 0, r.stdout + r.stderr
    scanner = Scanner(calib_file, remeasure_every=1)
    for i, m in enumerate(mosaics):
        np.testing.assert_array_equal(np.load(tmp_path / "out" / f"frame_{i:06d}.xyz.npy"),
                                      scanner.scan(demosaic(m, "GBRG")).xyz)
    video = write_video(tmp_path / "v.mkv", [np.zeros((48, 64, 3), np.uint8)] * 2)
    r = _gbscan("batch", video, "--calib", calib_file, "-o", tmp_path / "o2", "--bayer", "RGGB")
    assert r.returncode == 1 and "applies to a folder of raw frames" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_cli_batch_rig_check(tmp_path, calib_file):
    """The rig check (gbscan.diagnose) runs on each worker's first frame and every RIG_EVERY-th:
    its warnings' keys go into the manifest's rig column, and the command sums them up in one
    line with the frame to look at."""
    import dataclasses

    from gbscan import batch, sim
    from gbscan.commands.batch import rig_summary
    from gbscan.pattern import PatternSpec, render_pattern

    base = dataclasses.replace(sim.preset("typical"), supersample=1)
    frames = tmp_path / "frames"
    frames.mkdir()
    for name, cond in (("a.png", dataclasses.replace(base, exposure=base.exposure * 0.2)), ("b.png", base)):
        write_png(frames / name, sim.render(sim.paper_rig(), sim.scenes.plane(650.0), render_pattern(PatternSpec()),
                                            cond, seed=0).image)
    r = _gbscan("batch", frames, "--calib", calib_file, "-o", tmp_path / "out", "--workers", "1", "--quiet")
    assert r.returncode == 0, r.stdout + r.stderr
    rows = read_manifest(tmp_path / "out" / "manifest.csv")
    assert batch.RIG_EVERY > 1 and rows[0]["rig"] == "dim" and rows[1]["rig"] == ""     # the second: not checked
    assert f"rig check on 1 frame(s): dim 1 (what to change: gbscan check {frames / 'a.png'})" in r.stdout
    # the summary alone: "ok" rows count as checked without findings; a video names the frame
    m = tmp_path / "m.csv"
    batch.write_manifest(m, {0: {"frame": 0, "source": "v.mkv#0", "status": "ok", "rig": "ok"},
                             1: {"frame": 1, "source": "v.mkv#1", "status": "ok", "rig": ""}})
    assert rig_summary(m) == "rig check on 1 frame(s): no findings"
    batch.write_manifest(m, {0: {"frame": 0, "source": "v.mkv#0", "status": "ok", "rig": "noise;ambient"},
                             25: {"frame": 25, "source": "v.mkv#25", "status": "ok", "rig": "noise"}})
    assert rig_summary(m, tmp_path / "v.mkv", "video") == (
        f"rig check on 2 frame(s): noise 2, ambient 1 (what to change: gbscan check {tmp_path / 'v.mkv'} --frame 0)")
    assert rig_summary(m).endswith("(what to change: gbscan check on frame 0)")
    batch.write_manifest(m, {0: {"frame": 0, "source": "v.mkv#0", "status": "ok", "rig": ""}})
    assert rig_summary(m) == ""


def _sphere_sequence(n):
    """n frames (640x480) of the simulated rig: a sphere moving right in front of a wall + truth."""
    import dataclasses

    from gbscan import sim
    from gbscan.pattern import PatternSpec, render_pattern

    rig = sim.paper_rig()
    cond = dataclasses.replace(sim.preset("typical"), supersample=1)
    out = []
    for i in range(n):
        scene = sim.combine(sim.scenes.plane(900.0), sim.scenes.sphere((-40.0 + 20.0 * i, 0.0, 650.0), 100.0))
        out.append(sim.render(rig, scene, render_pattern(PatternSpec()), cond, seed=i))
    return out



def test_batch_frames_measure_the_camera_each(calib_file, monkeypatch):
    """A batch worker's Scanner measures the camera on every frame (``remeasure_every=1``): a
    frame's outputs do not depend on which worker scanned it after which frame."""
    import gbscan.scan as scan_module
    from gbscan.batch import ScannerProcessor

    seen = {}
    real = scan_module.Scanner

    class Spy(real):
        def __init__(self, *a, **kw):
            seen.update(kw)
            super().__init__(*a, **kw)

    monkeypatch.setattr(scan_module, "Scanner", Spy)
    process = ScannerProcessor(calib_file).setup()
    assert seen["remeasure_every"] == 1 and callable(process)

@pytest.mark.slow
def test_cli_video_end_to_end_with_scanner(tmp_path, calib_file):
    renders = _sphere_sequence(3)
    video = write_video(tmp_path / "seq.mkv", [r.image for r in renders])
    out = tmp_path / "out"
    r = _gbscan("batch", video, "--calib", calib_file, "-o", out, "--workers", "2", "--ply", "--mesh")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "3 frames selected" in r.stdout and "frames/s" in r.stderr
    rows = read_manifest(out / "manifest.csv")
    from gbscan.mesh import read_cloud_ply, read_mesh
    from gbscan.scan import Scanner

    scanner = Scanner(calib_file, remeasure_every=1)
    for i, rend in enumerate(renders):
        xyz = np.load(out / f"frame_{i:06d}.xyz.npy")
        # The batch result is exactly the one-frame scan of the same (losslessly coded) image: each
        # frame measures the camera itself, whichever worker scanned it after which frame.
        np.testing.assert_array_equal(xyz, scanner.scan(rend.image).xyz)
        ok = np.isfinite(xyz).all(-1)
        assert rows[i]["status"] == "ok" and int(rows[i]["points"]) == ok.sum() > 5000
        err = np.linalg.norm(xyz[ok] - rend.point[ok], axis=-1)
        assert np.median(err) < 1.0, np.median(err)
        cloud = read_cloud_ply(out / f"frame_{i:06d}.ply")
        np.testing.assert_array_equal(cloud.points, xyz[ok])
        assert read_mesh(out / f"frame_{i:06d}.mesh.ply").n_triangles > 0
    # --temporal: each frame after the first gets its predecessor's stripes; marker-less regions
    # overlapping them are indexed (counted in temporal_px).
    r = _gbscan("batch", video, "--calib", calib_file, "-o", tmp_path / "outT", "--workers", "2", "--temporal",
                "--quiet")
    assert r.returncode == 0, r.stdout + r.stderr
    rows_t = read_manifest(tmp_path / "outT" / "manifest.csv")
    assert [rows_t[i]["status"] for i in range(3)] == ["ok"] * 3
    assert all(rows_t[i]["temporal_px"].isdigit() for i in range(3))
    import dataclasses

    from gbscan.decode import StripeMap

    if "column_relative" not in {f.name for f in dataclasses.fields(StripeMap)}:
        for i in range(3):  # without the decoder's relative columns the points are the frame's own
            np.testing.assert_array_equal(np.load(tmp_path / "outT" / f"frame_{i:06d}.xyz.npy"),
                                          np.load(out / f"frame_{i:06d}.xyz.npy"))
    # A black frame (no stripes) in a folder is reported, the others done; exit status 1.
    frames = tmp_path / "frames"
    frames.mkdir()
    write_png(frames / "a.png", renders[0].image)
    write_png(frames / "b.png", np.zeros_like(renders[0].image))
    r = _gbscan("batch", frames, "--calib", calib_file, "-o", tmp_path / "out2", "--workers", "1", "--quiet")
    assert r.returncode == 1 and "frame 1:" in r.stdout and "Traceback" not in r.stderr
    rows = read_manifest(tmp_path / "out2" / "manifest.csv")
    assert rows[0]["status"] == "ok" and rows[1]["status"] == "failed" and "no points" in rows[1]["reason"]


def test_temporal_stripes_fills_only_unindexed_regions():
    from gbscan.pattern import CYAN, GREEN

    prev_col, prev = _columns(0.0)
    col, cur = _columns(1.0)
    region = np.where(np.arange(cur.shape[1])[None, :] < 100, 0, 1).repeat(cur.shape[0], 0).astype(np.int32)
    rel = cur - np.where(region == 0, 0, 30)        # region 0 indexed by the decoder, region 1 not
    col_rel = col - np.where(region == 0, 0, 240)
    unindexed = region == 1
    stripe = np.where(unindexed, -1, cur).astype(np.int32)
    labels = np.full(cur.shape, GREEN, np.uint8)
    markers = np.array([41, 46, 52, 59, 67, 72, 80, 84])
    labels[np.isin(cur, markers)] = CYAN
    prev_col[5, 150] = prev_col[5, 150] + 16  # the previous frame disagrees at one pixel
    out, offsets, recovered = batch.temporal_stripes(stripe, rel, region, unindexed, labels, prev, markers,
                                                     column_relative=col_rel, prev_column=prev_col)
    assert offsets == {1: 30}
    interior = np.zeros(cur.shape, bool)
    interior[3:-3, 103:-3] = True  # 3 px from region 0 and from the image border
    interior[5, 150] = False
    np.testing.assert_array_equal(recovered, interior)
    np.testing.assert_array_equal(out[recovered], cur[recovered])
    np.testing.assert_array_equal(out[~unindexed], cur[~unindexed])
    assert (out[unindexed & ~recovered] == -1).all()


@pytest.mark.slow
def test_temporal_borrowed_pixels_are_right_on_a_moving_scene():
    """--temporal on several objects moving 5 mm per frame away from the camera (the decoder
    leaves regions unindexed there), with the previous frame's true projector columns as the
    prior (the rules are under test, not the previous frame's decoder): every borrowed pixel's
    column is right (truth: the simulator's projector pixel)."""
    import dataclasses

    from gbscan import sim
    from gbscan.calibfile import calibration_from_rig
    from gbscan.decode import UNINDEXED
    from gbscan.pattern import PatternSpec, render_pattern
    from gbscan.scan import Scanner

    rig, spec = sim.paper_rig(), PatternSpec()
    cond = dataclasses.replace(sim.preset("typical"), supersample=1)
    scanner = Scanner(calibration_from_rig(rig, spec))
    borrowed = right = 0
    prev_truth = None
    for i in range(4):
        r = sim.render(rig, sim.scenes.multi_object(650.0 + 5.0 * i), render_pattern(spec), cond, seed=i)
        truth = r.proj_xy[..., 0]
        if prev_truth is not None:
            prior = batch.TemporalState(np.where(np.isfinite(prev_truth), prev_truth // spec.stripe_px, -1)
                                        .astype(np.int32), prev_truth.astype(np.float32))
            s = scanner.scan(r.image)
            new, state, extra = batch._temporal_scan(scanner, s, prior)
            assert isinstance(state, batch.TemporalState)
            rec = (s.stripemap.mask == UNINDEXED) & np.isfinite(state.column)
            assert extra["temporal_px"] == rec.sum()
            assert np.array_equal(new.valid & ~s.stripemap.valid, new.valid & rec)  # new points only there
            ok = rec & np.isfinite(truth)
            borrowed += int(ok.sum())
            right += int((np.abs(state.column[ok] - truth[ok]) < spec.stripe_px).sum())
        prev_truth = truth
    print(f"borrowed {borrowed} px, {100 * right / max(borrowed, 1):.2f}% right")
    assert borrowed > 1000 and right >= 0.999 * borrowed
