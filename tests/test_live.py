"""Live scanning (gbscan.live, scripts/live_scan.py): simulated camera, windowless and under Xvfb."""
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from gbcal.display import NullDisplay
from gbscan.calibfile import calibration_from_rig, save_calibration
from gbscan.errors import GBError
from gbscan.io import read_image_rgb
from gbscan.live import SimulatedCamera, depth_picture, run_live, save_scan
from gbscan.pattern import PatternSpec, render_pattern
from gbscan.rig import paper_rig
from gbscan.scan import Scanner

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def scanner():
    return Scanner(calibration_from_rig(paper_rig(), PatternSpec()))


def _script():
    spec = importlib.util.spec_from_file_location("live_scan", ROOT / "scripts" / "live_scan.py")
    m = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(m)
    return m


def test_live_session_scans_every_frame_and_saves_on_space(tmp_path, scanner):
    d = NullDisplay(keys=["", " ", "", "q"])
    cam = SimulatedCamera(render_pattern(scanner.pattern), period=8)
    res = run_live(d, cam, scanner, tmp_path / "out", near_mm=500, far_mm=1000)
    assert (res.frames, res.status, d.n_projector, d.images) == (4, "quit", 1, 4)
    assert np.array_equal(d.projector_frame, render_pattern(scanner.pattern))
    pic = d.last_image
    assert pic.dtype == np.uint8 and pic.shape[1] == 1280 and pic.shape[0] > 480   # frame | depth, then the panel
    assert len(res.saved) == 1 and res.saved[0].name == "scan_001"
    folder = res.saved[0]
    assert sorted(p.name for p in folder.iterdir()) == ["cloud.ply", "frame.png", "mesh.ply", "xyz.npy"]
    assert not list((tmp_path / "out").glob(".*"))
    # the saved frame is lossless and its scan is the saved one (frame 2 of the session)
    again = scanner.scan(read_image_rgb(folder / "frame.png"))
    np.testing.assert_array_equal(np.load(folder / "xyz.npy"), again.xyz)
    assert again.n_points > 100_000
    # a second session into the same folder numbers on from the highest scan there
    (tmp_path / "out" / "scan_007").mkdir()
    res2 = run_live(NullDisplay(keys=[" "]), cam, scanner, tmp_path / "out", max_frames=1)
    assert res2.status == "frames" and [p.name for p in res2.saved] == ["scan_008"]


def test_live_window_shows_the_rig_check(scanner):
    # a good rig: no hint line; a dim, noisy, washed-out one (the hard preset): the rig check's first two
    # warnings (gbscan.diagnose), one more line in the window's panel
    good, bad = NullDisplay(), NullDisplay()
    r_good = run_live(good, SimulatedCamera(render_pattern(scanner.pattern)), scanner, "unused", max_frames=1)
    r_bad = run_live(bad, SimulatedCamera(render_pattern(scanner.pattern), preset="hard"), scanner, "unused",
                     max_frames=1)
    assert r_good.hint == ""
    assert "noisy stripes (SNR 4)" in r_bad.hint and r_bad.hint.count("; ") == 1    # measured: dim, noisy
    assert bad.last_image.shape[0] == good.last_image.shape[0] + 20


def test_save_scan_is_all_or_nothing(tmp_path, scanner, monkeypatch):
    cam = SimulatedCamera(render_pattern(scanner.pattern))
    frame = cam.read()
    scan = scanner.scan(frame)
    save_scan(tmp_path, 1, frame, scan)
    with pytest.raises(GBError, match="exists already"):
        save_scan(tmp_path, 1, frame, scan)
    import gbscan.mesh

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(gbscan.mesh, "write_mesh", boom)
    with pytest.raises(OSError):
        save_scan(tmp_path, 2, frame, scan)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scan_001"]   # no half-written scan_002
    # a failed save in a session is reported in the window and the session goes on
    d = NullDisplay(keys=[" ", "q"])
    res = run_live(d, cam, scanner, tmp_path, near_mm=500, far_mm=1000)
    assert res.saved == [] and res.frames == 2 and res.status == "quit"


def test_depth_picture_colours_near_red_far_blue_none_black():
    z = np.linspace(500, 1000, 11, dtype=np.float32)
    xyz = np.zeros((1, 11, 3), np.float32)
    xyz[0, :, 2] = z
    valid = np.ones((1, 11), bool)
    valid[0, 5] = False
    pic = depth_picture(xyz, valid, 500, 1000)
    assert pic[0, 0, 0] > 100 and pic[0, 0, 2] < 60       # near: red
    assert pic[0, 10, 2] > 100 and pic[0, 10, 0] < 80     # far: blue
    assert (pic[0, 5] == 0).all()
    assert not depth_picture(xyz, np.zeros((1, 11), bool)).any()


def test_a_camera_of_another_size_is_one_clear_error(tmp_path, scanner):
    class Small:
        def read(self):
            return np.zeros((240, 320, 3), np.uint8)

    with pytest.raises(GBError, match="320x240 but the calibration's camera is 640x480"):
        run_live(NullDisplay(), Small(), scanner, tmp_path)


def test_live_scan_script_simulated(tmp_path, capsys):
    calib = save_calibration(tmp_path / "calib.yaml", calibration_from_rig(paper_rig(), PatternSpec()))
    m = _script()
    rc = m.main(["--calib", str(calib), "--simulate", "--frames", "2", "--save-every", "2", "-o", str(tmp_path / "s"),
                 "--depth-range", "400", "1200"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert "2 frames scanned" in out.out and "1 scans saved" in out.out and (tmp_path / "s" / "scan_001").is_dir()
    for args, match in ((["--display", "none"], "only with --simulate"), (["--simulate"], "needs --frames"),
                        (["--simulate", "--frames", "0"], "--frames must be >= 1"),
                        (["--simulate", "--frames", "1", "--depth-range", "900", "400"], "--depth-range")):
        rc = m.main(["--calib", str(calib), "-o", str(tmp_path / "x")] + args)
        err = capsys.readouterr().err
        assert rc == 1 and err.startswith("live_scan: error:") and match in err and len(err.strip().splitlines()) == 1
    rc = m.main(["--calib", str(tmp_path / "missing.yaml"), "--simulate", "--frames", "1"])
    assert rc == 1 and "missing.yaml" in capsys.readouterr().err


@pytest.mark.slow
def test_live_scan_through_tk_windows(xvfb, tmp_path, monkeypatch, capsys):
    display, fb = xvfb
    monkeypatch.setenv("DISPLAY", display)
    calib = save_calibration(tmp_path / "calib.yaml", calibration_from_rig(paper_rig(), PatternSpec()))
    rc = _script().main(["--calib", str(calib), "--simulate", "--display", "tk", "--screen-x", "376",
                         "--frames", "2", "-o", str(tmp_path / "s")])
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert "2 frames scanned" in out.out


def test_video_camera_reports_its_pixel_format_and_warns_for_subsampled_chroma(tmp_path):
    from gbcal.display import VideoCamera
    from gbscan.frames import write_video

    imgs = [np.random.default_rng(k).integers(0, 256, (48, 64, 3), dtype=np.uint8) for k in range(3)]
    mjpg = VideoCamera(str(write_video(tmp_path / "m.avi", imgs, fourcc="MJPG")))
    ffv1 = VideoCamera(str(write_video(tmp_path / "f.mkv", imgs)))
    try:
        assert mjpg.fourcc == "MJPG" and "JPEG-compressed" in mjpg.input_warning()
        assert ffv1.fourcc.lower() == "ffv1" and ffv1.input_warning() is None
    finally:
        mjpg.close()
        ffv1.close()
    with pytest.raises(GBError, match="4 characters"):
        VideoCamera(str(tmp_path / "f.mkv"), fourcc="RGB")
