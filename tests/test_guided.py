"""Guided calibration: the flow (gbcal.guided), the displays (gbcal.display), the simulated rig
(gbcal.guidedsim) and scripts/guided_calibration.py, headless; the Tk backend under Xvfb when
the machine has it (skipped otherwise)."""
import dataclasses
import importlib.util
import os
import struct
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from gbcal.board import Board, Detection
from gbcal.display import NullDisplay, TkDisplay, choose_display, compose_feedback, fit_size, ppm_bytes
from gbcal.guided import (Action, Coverage, GuidedState, QualityLimits, SessionWriter, capture_pose,
                          check_capture, check_new_session_folder, run_capture, tilt_bin)
from gbcal.guidedsim import SimulatedRig, Step, parse_faults, script_for
from gbcal.patterns import calibration_frames
from gbscan.calibfile import load_calibration
from gbscan.errors import GBError
from gbscan.io import load_session
from gbscan.pattern import PatternSpec
from gbscan.rig import Rig, paper_rig

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "guided_calibration.py"
BOARD = Board(7, 5, 25.0)
SPEC = PatternSpec(1024, 768)


def _module():
    spec = importlib.util.spec_from_file_location("guided_calibration", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def simrig():
    """Half-resolution paper rig (320x240 camera), a 7x5 board and 4 poses inside both views."""
    from gbcal.simsession import board_poses

    true = paper_rig()
    rig = Rig(true.camera.scaled(0.5), true.projector, true.R_cam_proj, true.t_cam_proj)
    return rig, board_poses(rig, (BOARD.cols, BOARD.rows, BOARD.square_mm), 4, seed=1)


def _world(simrig, steps, **kw):
    from gbscan import sim

    rig, poses = simrig
    cond = dataclasses.replace(sim.preset("clean"), supersample=1)  # fast; corners still ~0.05 px
    return SimulatedRig(rig, BOARD, poses, steps, preset=cond, **kw)


def _corners(R, t, board=BOARD):
    cam = paper_rig().camera.scaled(0.5)
    return cam.project(board.object_points() @ R.T + t)


def _detection(corners):
    return Detection(np.asarray(corners, float), (320, 240), 1.5, 20.0, 200.0, "sb")


# -- coverage and tilts ------------------------------------------------------------------------
def test_coverage_bookkeeping():
    cov = Coverage.of((320, 240), grid=(4, 3))
    assert "12 of 12" in cov.missing() and "left/right/up/down" in cov.missing() and not cov.complete
    cov = Coverage.of((320, 240), [np.array([[10.0, 10.0], [300.0, 230.0]])], [np.array([0.5, 0.0, 0.866])])
    assert cov.cells[0, 0] == 1 and cov.cells[2, 3] == 1 and cov.cells.sum() == 2 and cov.tilts["right"] == 1
    assert "10 of 12" in cov.missing() and "left/up/down" in cov.missing()
    assert cov.hint() == "next: tilt the board left by 20-40 degrees"
    # a cell boundary: pixel centres at integers, cell 0 spans u in [-0.5, 79.5)
    cov = Coverage.of((320, 240), [np.array([[79.4, 0.0], [79.6, 0.0]])], [np.array([0.0, 0.0, 1.0])])
    assert cov.cells[0, 0] == 1 and cov.cells[0, 1] == 1


def test_tilt_bins():
    assert tilt_bin(np.array([0.0, 0.0, 1.0])) == "square-on"
    assert tilt_bin(np.array([0.1, 0.05, 1.0])) == "square-on"  # 6.4 deg
    assert tilt_bin(np.array([0.5, 0.1, 0.86])) == "right"
    assert tilt_bin(np.array([-0.5, 0.1, 0.86])) == "left"
    assert tilt_bin(np.array([0.0, -0.4, 0.9])) == "up"
    assert tilt_bin(np.array([0.1, 0.4, 0.9])) == "down"
    with pytest.raises(GBError, match="3-vector"):
        tilt_bin(np.array([0.0, 0.0]))


def test_coverage_complete_and_hints():
    size = (320, 240)
    # corners spread over every cell, one capture per tilt
    u, v = np.meshgrid(np.linspace(5, 315, 8), np.linspace(5, 235, 6))
    c = np.stack([u.ravel(), v.ravel()], 1)
    normals = [np.array(n, float) for n in ([0.5, 0, 0.86], [-0.5, 0, 0.86], [0, -0.5, 0.86], [0, 0.5, 0.86])]
    cov = Coverage.of(size, [c] * 4, normals)
    assert cov.complete and cov.missing() == "coverage complete" and "q to finish" in cov.hint()
    assert cov.tilts == {"left": 1, "right": 1, "up": 1, "down": 1, "square-on": 0}
    cov = Coverage.of(size, [c[c[:, 0] < 200]] * 4, normals)
    assert cov.missing_regions() == ["top-right", "middle-right", "bottom-right"]
    assert cov.hint() == "next: move the board towards the top-right of the image"


# -- the state machine ---------------------------------------------------------------------------
def test_decisions_accept_undo(simrig):
    st = GuidedState(BOARD, (320, 240), n_poses=2)
    assert st.decide("", True) == Action.NONE
    assert st.decide(" ", False) == Action.NO_BOARD
    assert st.decide(" ", True) == Action.CAPTURE
    assert st.decide("u", True) == Action.NOTHING_TO_UNDO
    assert st.decide("q", False) == Action.FINISH and st.decide("esc", True) == Action.ABORT
    from gbcal.guided import CaptureCheck

    _, poses = simrig
    a = st.accept("pose_000", CaptureCheck(True, "", _detection(_corners(*poses[1])), sharpness_px=1.5, motion_px=0.02))
    assert a.tilt in ("left", "right", "up", "down") and st.left == 1 and st.message_ok
    assert st.coverage.cells.sum() >= 2 and st.coverage.tilts[a.tilt] == 1
    v = st.view(True)
    assert v.status_ok and v.captured == 1 and v.left == 1 and "accepted" in v.message
    st.reject("board blurred")
    v = st.view(False, "no 7x5 board found")
    assert not v.status_ok and "no 7x5" in v.status and not v.message_ok and "blurred" in v.message
    assert st.decide("u", True) == Action.UNDO
    assert st.undo().name == "pose_000" and st.left == 2 and st.coverage.cells.sum() == 0
    st.accept("pose_000", CaptureCheck(True, "", _detection(_corners(*poses[0]))))
    st.accept("pose_001", CaptureCheck(True, "", _detection(_corners(*poses[1]))))
    assert st.left == 0 and st.decide(" ", True) == Action.FINISH
    with pytest.raises(GBError, match="positive integer"):
        GuidedState(BOARD, (320, 240), n_poses=0)


def test_live_detect(simrig):
    from gbcal.guided import live_detect

    world = _world(simrig, [Step(1)])
    world.project(calibration_frames(SPEC)["white"])
    img = world.camera.read()
    corners, problem = live_detect(img, BOARD)
    assert problem == "" and corners.shape == (BOARD.n_corners, 2)
    truth = _corners(*simrig[1][1])
    # detector order may differ from the canonical one: compare as point sets
    d = np.linalg.norm(corners[:, None] - truth[None], axis=-1).min(axis=1)
    assert d.max() < 1.0
    c2, problem = live_detect(img, BOARD, max_sharpness_px=0.5)
    assert c2 is not None and "blurred" in problem
    x0 = int(np.floor(truth[:, 0].min())) - 20  # crop so that the board sticks out of the frame
    corners, problem = live_detect(np.ascontiguousarray(img[:, x0 + 25:]), BOARD)
    assert problem != "" and ("border" in problem or "no 7x5" in problem)
    corners, problem = live_detect(np.full((240, 320, 3), 90, np.uint8), BOARD)
    assert corners is None and "no 7x5 board found" in problem


# -- quality checks on simulated captures ----------------------------------------------------------
FEW_FRAMES = {k: v for k, v in calibration_frames(SPEC).items() if k in ("white", "black")}


def _check(simrig, fault, limits=QualityLimits(max_sharpness_px=3.5), pose=0):
    world = _world(simrig, [Step(pose, " ", fault)])
    disp = world.display(NullDisplay())
    disp.show_projector(FEW_FRAMES["white"])
    assert disp.poll_key() == "" and disp.poll_key() == " "  # look, then press SPACE
    shots, end = capture_pose(disp, world.camera, FEW_FRAMES, 0, 0)
    return check_capture(shots["white"], shots["black"], end, BOARD, limits)


def test_check_capture_accepts_a_good_capture(simrig):
    chk = _check(simrig, "")
    assert chk.ok and chk.reason == "" and chk.detection is not None
    f = chk.figures()
    assert f["motion_px"] < 0.1 and f["saturated_fraction"] == 0 and f["modulation_dn"] > 100
    assert f["unlit_fraction"] == 0 and f["sharpness_px"] < 3.0


@pytest.mark.parametrize("fault, words", [
    ("move", "board moved during the capture"),
    ("blur", "board blurred"),
    ("bright", "overexposed"),
    ("dim", "too little projector light"),
    ("lag", "black frame looks the same as the white one"),
])
def test_check_capture_rejects_with_reason(simrig, fault, words):
    chk = _check(simrig, fault)
    assert not chk.ok and words in chk.reason, chk.reason
    if fault == "move":
        assert chk.motion_px > 1.0
    if fault == "bright":
        assert chk.saturated_fraction > 0.05
    if fault == "dim":
        assert 4 < chk.modulation_dn < 30


def test_check_capture_no_board_and_sizes():
    grey = np.full((240, 320, 3), 90, np.uint8)
    chk = check_capture(grey, grey, grey, BOARD)
    assert not chk.ok and chk.detection is None and "checkerboard" in chk.reason
    with pytest.raises(GBError, match="differ in size"):
        check_capture(grey, grey[:100], grey, BOARD)
    with pytest.raises(GBError, match="positive"):
        QualityLimits(max_motion_px=0)


# -- the flow, headless ----------------------------------------------------------------------------
def test_flow_capture_reject_undo_finish(simrig, tmp_path):
    steps = [Step(0), Step(None), Step(1, " ", "bright"), Step(1), Step(1, "u"), Step(2), Step(3, "q")]
    world = _world(simrig, steps)
    disp = world.display(NullDisplay())
    logs = []
    out = run_capture(tmp_path / "s", disp, world.camera, BOARD, SPEC, n_poses=5, settle_ms=0, drop_frames=0,
                      limits=QualityLimits(max_sharpness_px=3.5), log=logs.append)
    assert out.status == "complete" and len(out.accepted) == 2 and out.rejected == 2
    s = load_session(tmp_path / "s")
    assert [p.name for p in s.poses] == ["pose_000", "pose_001"] and s.camera_size == (320, 240)
    assert s.frames == tuple(calibration_frames(SPEC)) and s.extra["rejected_captures"] == 2
    assert all(s.frame_path(1, f).is_file() for f in s.frames)
    log = yaml.safe_load((tmp_path / "s" / "capture_log.yaml").read_text())["attempts"]
    assert [e["event"] for e in log] == ["accepted", "rejected", "rejected", "accepted", "undo", "accepted"]
    assert "no 7x5 board found" in log[1]["reason"] and "overexposed" in log[2]["reason"]
    assert log[4]["pose"] == "pose_001" and log[5]["pose"] == "pose_001"
    assert log[0]["modulation_dn"] > 100 and log[0]["motion_px"] < 0.2
    # the undone capture was replaced by pose 2's: its corners are where pose 2 puts them
    rig, poses = simrig
    assert np.abs(out.accepted[1].corners - _corners(*poses[2])).max() < 1.0
    assert any("rejected" in line and "overexposed" in line for line in logs)
    # nothing else beside the session: no staging folder left
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]
    # the live window was told about the rejection and the coverage
    views = disp.inner.views
    assert any(not v.message_ok and "overexposed" in v.message for v in views)
    assert views[-1].captured == 2 and views[-1].coverage.cells.sum() >= 2


def test_flow_abort_leaves_nothing(simrig, tmp_path):
    world = _world(simrig, [Step(0), Step(1, "esc")])
    logs = []
    out = run_capture(tmp_path / "s", world.display(NullDisplay()), world.camera, BOARD, SPEC, n_poses=3,
                      settle_ms=0, drop_frames=0, log=logs.append)
    assert out.status == "aborted" and len(out.accepted) == 1
    assert list(tmp_path.iterdir()) == [] and "nothing written" in logs[-1]


def test_flow_finish_without_capture_writes_nothing(tmp_path):
    class Camera:  # a scripted fake camera: a grey wall
        def read(self):
            return np.full((120, 160, 3), 80, np.uint8)

        def drop(self, n):
            pass

    out = run_capture(tmp_path / "s", NullDisplay(["", " ", "q"]), Camera(), BOARD, SPEC, n_poses=3, log=lambda s: None)
    assert out.status == "empty" and out.rejected == 1 and list(tmp_path.iterdir()) == []


def test_flow_error_keeps_captures_marked_incomplete(simrig, tmp_path):
    world = _world(simrig, [Step(0), Step(1)])
    reads = {"n": 0}

    class Dying:  # the camera fails during the second capture
        def read(self):
            reads["n"] += 1
            if reads["n"] > 24:
                raise GBError("camera 'sim' stopped delivering frames")
            return world.camera.read()

        def drop(self, n):
            pass

    logs = []
    with pytest.raises(GBError, match="stopped delivering"):
        run_capture(tmp_path / "s", world.display(NullDisplay()), Dying(), BOARD, SPEC, n_poses=3, settle_ms=0,
                    drop_frames=0, log=logs.append)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.incomplete"]
    inc = tmp_path / "s.incomplete"
    assert (inc / "pose_000").is_dir() and not (inc / "pose_001").exists() and not (inc / "session.yaml").exists()
    assert "stopped delivering" in (inc / "INCOMPLETE.txt").read_text() and "incomplete" in logs[-1]
    with pytest.raises(GBError, match="session.yaml is missing"):
        load_session(inc)


def test_flow_camera_changing_size_is_an_error(tmp_path):
    class Camera:
        n = 0

        def read(self):
            self.n += 1
            return np.zeros((120, 160, 3) if self.n < 3 else (240, 320, 3), np.uint8)

        def drop(self, n):
            pass

    with pytest.raises(GBError, match="--camera-size"):
        run_capture(tmp_path / "s", NullDisplay(), Camera(), BOARD, SPEC, n_poses=2, log=lambda s: None)
    assert list(tmp_path.iterdir()) == []


def test_session_folder_must_be_new(tmp_path):
    (tmp_path / "a" / "pose_000").mkdir(parents=True)
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "notes.txt").write_text("x")
    (tmp_path / "c").mkdir()
    with pytest.raises(GBError, match="already holds captures"):
        check_new_session_folder(tmp_path / "a")
    with pytest.raises(GBError, match="not empty"):
        SessionWriter(tmp_path / "b")
    w = SessionWriter(tmp_path / "c")  # an empty folder is fine
    assert w.staging.name.startswith(".c.partial-")
    w.add_pose({"white": np.zeros((4, 4, 3), np.uint8)})
    root = w.publish(board=(7, 5, 25.0), camera_size=(4, 4), projector_size=(8, 8), frames=["white"])
    assert root == tmp_path / "c" and (root / "pose_000" / "white.png").is_file()
    assert oct(root.stat().st_mode & 0o777) == oct(0o777 & ~_umask())


def _umask():
    m = os.umask(0)
    os.umask(m)
    return m


def test_simulated_operator_script():
    assert [(s.pose, s.fault) for s in script_for(3, {2: "move", 3: "lag"})] == \
        [(0, ""), (1, "move"), (1, "lag"), (1, ""), (2, "")]
    assert parse_faults("2:move, 4:blur", 5) == {2: "move", 4: "blur"}
    for bad in ("2-move", "x:move", "2:wobble", "0:move"):
        with pytest.raises(GBError, match="sim-faults"):
            parse_faults(bad, 5)


# -- the live picture --------------------------------------------------------------------------
def test_compose_feedback(simrig):
    _, poses = simrig
    st = GuidedState(BOARD, (320, 240), n_poses=3)
    from gbcal.guided import CaptureCheck

    st.accept("pose_000", CaptureCheck(True, "", _detection(_corners(*poses[0]))))
    img = np.full((240, 320, 3), 60, np.uint8)
    ok = compose_feedback(img, _corners(*poses[0]), BOARD.pattern_size, st.view(True))
    assert fit_size((320, 240)) == (3.0, (960, 720)) and fit_size((1920, 1080))[1] == (960, 540)
    assert ok.dtype == np.uint8 and ok.shape[1] == 960 and ok.shape[0] > 720
    red = lambda a: np.sum((a[..., 0] > 200) & (a[..., 1] < 110) & (a[..., 2] < 110))  # noqa: E731
    st.reject("overexposed: 40 % of the board is saturated")
    bad = compose_feedback(img, None, BOARD.pattern_size, st.view(False, "no 7x5 board found"))
    assert red(bad[720:]) > 10 * max(red(ok[720:]), 1)  # status and message in red
    # covered cells are tinted green, uncovered ones are not
    cells = st.coverage.cells
    j, i = np.argwhere(cells > 0)[0]
    jj, ii = np.argwhere(cells == 0)[0]
    centre = lambda a, j, i: a[int((j + 0.5) * 240), int((i + 0.5) * 240)]  # noqa: E731
    assert centre(bad, j, i)[1] > centre(bad, j, i)[0] + 20 and abs(int(centre(bad, jj, ii)[1]) - 60) < 3


# -- display backends ------------------------------------------------------------------------------
def test_ppm_bytes_round_trip():
    import cv2

    f = np.random.default_rng(0).integers(0, 256, (5, 7, 3), dtype=np.uint8)
    b = ppm_bytes(f)
    back = cv2.imdecode(np.frombuffer(b, np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]
    assert np.array_equal(back, f)
    with pytest.raises(GBError, match="uint8"):
        ppm_bytes(f.astype(np.float32))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="X11 display variables")
def test_chooser_says_clearly_when_no_window_can_be_opened(monkeypatch):
    import gbcal.display as gd

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(gd, "opencv_gui", lambda: (False, "the installed OpenCV has no GUI (headless wheel)"))
    with pytest.raises(GBError) as e:
        choose_display("auto", (1024, 768))
    msg = str(e.value)
    tk_why = "Tk cannot open a window" if importlib.util.find_spec("tkinter") else "no tkinter"
    assert tk_why in msg and "headless" in msg and "DISPLAY=:0" in msg and "--simulate" in msg
    with pytest.raises(GBError, match="must be auto, tk, opencv or none"):
        choose_display("gtk", (1024, 768))
    assert isinstance(choose_display("none", (1024, 768)), NullDisplay)


def test_opencv_backend_refuses_the_headless_wheel():
    from gbcal.display import OpenCVDisplay, opencv_gui

    if opencv_gui()[0]:
        pytest.skip("this OpenCV has a GUI")
    with pytest.raises(GBError, match="no GUI"):
        OpenCVDisplay((1024, 768))


# -- Tk under Xvfb ---------------------------------------------------------------------------------
def _screen(path) -> np.ndarray:
    """The Xvfb screen (H, W, 3) RGB from its XWD frame-buffer file (24-bit TrueColor, 32 bpp)."""
    raw = Path(path).read_bytes()
    hdr = struct.unpack(">25I", raw[:100])
    size, order, bpp, bpl, ncolors, w, h = hdr[0], hdr[7], hdr[11], hdr[12], hdr[19], hdr[4], hdr[5]
    assert bpp == 32 and order == 0, "expected a little-endian 32-bit XWD"
    px = np.frombuffer(raw, np.uint8, count=bpl * h, offset=size + 12 * ncolors).reshape(h, bpl // 4, 4)
    return px[:, :w, 2::-1]


def test_tk_projector_window_is_pixel_exact_and_keys_arrive(xvfb, monkeypatch):
    display, fb = xvfb
    monkeypatch.setenv("DISPLAY", display)
    d = TkDisplay((320, 240), (1000, 100), pattern_size=BOARD.pattern_size)
    try:
        assert d.problems() == []
        frame = np.random.default_rng(3).integers(0, 256, (240, 320, 3), dtype=np.uint8)
        d.show_projector(frame)
        d.wait_ms(50)
        scr = _screen(fb)
        assert np.array_equal(scr[100:340, 1000:1320], frame)  # pixel for pixel, where it was asked
        assert d.geometry() == (1000, 100, 320, 240)
        with pytest.raises(GBError, match="does not match the 320x240 projector"):
            d.show_projector(frame[:, :300])
        # keys typed in either window arrive as the flow's names
        d.root.focus_force()
        d.root.update()
        for keysym in ("space", "u", "Escape", "x", "q"):
            d.root.event_generate("<KeyPress>", keysym=keysym)
        assert [d.poll_key() for _ in range(5)] == [" ", "u", "esc", "q", ""]
        st = GuidedState(BOARD, (320, 240), 2)
        d.show_live(np.full((240, 320, 3), 50, np.uint8), None, st.view(False, "no board"))
        d.wait_ms(20)
        live = _screen(fb)[: d.root.winfo_height(), : d.root.winfo_width()]
        assert live.shape[0] > 720 and np.any(live[:700, :900] == 50)
    finally:
        d.close()
    far = TkDisplay((1024, 768), (1000, 0))  # does not fit the 1400x800 desktop
    try:
        assert any("does not fit" in p for p in far.problems())
    finally:
        far.close()


@pytest.mark.slow
def test_simulated_session_through_tk_windows(xvfb, tmp_path, monkeypatch, capsys):
    display, fb = xvfb
    monkeypatch.setenv("DISPLAY", display)
    g = _module()
    rc = g.main([str(tmp_path / "s"), "--simulate", "--display", "tk", "--screen-x", "376", "--screen-y", "0",
                 "--poses", "2", "--board", "7x5", "--square-mm", "25", "--settle-ms", "20", "--sim-faults", "1:lag",
                 "--no-calibrate"])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "display tk+simulated rig" in err and "warning" not in err and "black frame looks the same" in err
    assert len(load_session(tmp_path / "s").poses) == 2


# -- the script ------------------------------------------------------------------------------------
@pytest.mark.slow
def test_simulated_guided_session_end_to_end(tmp_path, capsys):
    g = _module()
    sess = tmp_path / "session"
    rc = g.main([str(sess), "--simulate", "--poses", "5", "--board", "7x5", "--square-mm", "25",
                 "--sim-preset", "typical", "-o", str(tmp_path / "calib.yaml")])
    out = capsys.readouterr()
    assert rc == 0, out.err
    s = load_session(sess)
    assert len(s.poses) == 5 and s.camera_size == (320, 240) and s.extra["pattern"]["stripe_px"] == 8
    assert all(s.frame_path(4, f).is_file() for f in s.frames)
    assert "pose 5/5 captured" in out.err and "still missing" in out.err
    # typical noise: today one scripted pose's white frame gives an irregular corner grid; the capture
    # is rejected with that reason and the simulated operator takes a spare pose instead
    assert s.extra["rejected_captures"] <= 1 and s.extra["simulated"] is True
    cal = load_calibration(tmp_path / "calib.yaml")
    assert abs(cal.camera.K[0, 0] / 400.0 - 1) < 0.01 and cal.n_planes > 40
    assert (tmp_path / "calib.residuals.npz").is_file()
    # a second run into the same folder is refused, with one line and nothing overwritten
    rc = g.main([str(sess), "--simulate", "--poses", "1", "--no-calibrate"])
    assert rc == 1 and "already holds captures" in capsys.readouterr().err
    # another session, its camera held to the first calibration's
    rc = g.main([str(tmp_path / "session2"), "--simulate", "--poses", "4", "--board", "7x5", "--square-mm", "25",
                 "--sim-preset", "typical", "--camera-calib", str(tmp_path / "calib.yaml"), "-o", str(tmp_path / "c2.yaml")])
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert "camera held to camera file" in out.out and "depth uncertainty of a scan at" in out.out
    assert load_calibration(tmp_path / "c2.yaml").residuals["camera_prior"]["file"].endswith("calib.yaml")


def test_bad_options_are_one_line(tmp_path, capsys):
    g = _module()
    assert g.main([str(tmp_path / "s"), "--simulate", "--board", "9by7"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "COLSxROWS" in err[0]
    assert g.main([str(tmp_path / "s"), "--simulate", "--sim-faults", "2:wobble"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown fault" in err[0] and not (tmp_path / "s").exists()
    # a camera file that cannot serve is refused before any capture
    assert g.main([str(tmp_path / "s"), "--simulate", "--camera-calib", str(tmp_path / "missing.yaml")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "missing.yaml does not exist" in err[0] and not (tmp_path / "s").exists()


def test_help_documents_the_procedure(capsys):
    g = _module()
    with pytest.raises(SystemExit):
        g.main(["--help"])
    text = capsys.readouterr().out
    for words in ("SPACE capture", "u undo", "ESC abort", "--settle-ms", "--drop-frames", "--screen-x",
                  "Lock the camera's exposure", "INCOMPLETE.txt", "--display"):
        assert words in text, words
