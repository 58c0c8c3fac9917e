"""Simulated calibration sessions: poses, layout round trip, ground truth, per-frame noise."""
from __future__ import annotations

import numpy as np
import pytest

from gbcal.patterns import calibration_frames, gray_decode, n_gray_bits
from gbcal.simsession import _grid_projector_x, _pose_ok, board_poses, load_truth, write_session
from gbscan import sim
from gbscan.errors import GBError
from gbscan.io import load_session, read_image_rgb
from gbscan.pattern import PatternSpec
from gbscan.rig import Rig

SPEC = PatternSpec()


@pytest.fixture(scope="module")
def small_rig():
    r = sim.paper_rig()
    return Rig(r.camera.scaled(0.5), r.projector, r.R_cam_proj, r.t_cam_proj)


@pytest.fixture(scope="module")
def session(small_rig, tmp_path_factory):
    out = tmp_path_factory.mktemp("sess") / "s"
    write_session(out, small_rig, SPEC, board=(7, 5, 25.0), n_poses=2, preset="typical", seed=3, progress=False)
    return out


def test_board_poses_are_varied_valid_and_deterministic():
    rig = sim.paper_rig()
    b = (9, 7, 20.0)
    poses = board_poses(rig, b, 12, seed=0)
    assert len(poses) == 12
    tilts = [np.degrees(np.arccos(R[2, 2])) for R, _ in poses]
    assert max(tilts) > 30 and min(tilts) < 10
    centres = np.array([R @ [80.0, 60.0, 0.0] + t for R, t in poses])
    assert np.ptp(centres[:, 2]) > 120 and 500 < centres[:, 2].min() and centres[:, 2].max() < 850
    assert np.ptp(centres[:, 0] / centres[:, 2]) > 0.1 and np.ptp(centres[:, 1] / centres[:, 2]) > 0.1
    for R, t in poses:
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert _pose_ok(rig, R, t, *b, b[2])
    # together the boards cross every light plane: projector columns from near 0 to near 1023
    cov = [_grid_projector_x(rig, R, t, *b) for R, t in poses]
    assert min(c[0] for c in cov) < 30 and max(c[1] for c in cov) > 1023 - 30
    again = board_poses(rig, b, 12, seed=0)
    assert all(np.array_equal(R1, R2) and np.array_equal(t1, t2) for (R1, t1), (R2, t2) in zip(poses, again))
    with pytest.raises(GBError, match="smaller board"):
        board_poses(rig, (9, 7, 60.0), 2, seed=0)


def test_session_round_trip(session, small_rig):
    s = load_session(session)
    assert (s.board_cols, s.board_rows, s.square_mm) == (7, 5, 25.0)
    assert s.camera_size == small_rig.camera.size and s.projector_size == (1024, 768)
    assert list(s.frames) == list(calibration_frames(SPEC)) and len(s.poses) == 2
    for k in range(2):
        for name in s.frames:
            img = read_image_rgb(s.frame_path(k, name), size=s.camera_size)
            assert img.dtype == np.uint8
    tr = load_truth(session)
    assert tr["board"] == (7, 5, 25.0) and tr["pattern"] == SPEC and len(tr["poses"]) == 2
    np.testing.assert_allclose(tr["camera"].K, small_rig.camera.K)
    np.testing.assert_allclose(tr["camera"].dist, small_rig.camera.dist)
    np.testing.assert_allclose(tr["rig"].t_cam_proj, small_rig.t_cam_proj)
    np.testing.assert_allclose(tr["rig"].R_cam_proj, small_rig.R_cam_proj)
    assert tr["conditions"] == sim.preset("typical")


def test_frames_carry_their_own_noise(session):
    s = load_session(session)
    black = read_image_rgb(s.frame_path(0, "black")).astype(int)
    # where gray_00 is dark too (most of the unlit background), the images must still differ
    g = read_image_rgb(s.frame_path(0, "gray_00")).astype(int)
    g_inv = read_image_rgb(s.frame_path(0, "gray_00_inv")).astype(int)
    dark = (g.max(-1) < 12) & (g_inv.max(-1) < 12) & (black.max(-1) < 12)
    assert dark.sum() > 5000
    assert np.mean(black[dark] != g[dark]) > 0.2


def test_gray_code_frames_match_the_true_stripe(session):
    """Decode the Gray code at lit board pixels; it must equal the stripe of the true projector column."""
    s = load_session(session)
    tr = load_truth(session)
    cols, rows, sq = tr["board"]
    R, t = tr["poses"][1]
    truth = sim.trace(tr["rig"], sim.scenes.board(cols, rows, sq, R, t), sim.preset("clean"))
    nb = n_gray_bits(SPEC)
    bits = []
    for b in range(nb):
        a = read_image_rgb(s.frame_path(1, f"gray_{b:02d}")).astype(int).sum(-1)
        c = read_image_rgb(s.frame_path(1, f"gray_{b:02d}_inv")).astype(int).sum(-1)
        bits.append(a > c)
    code = np.zeros(bits[0].shape, np.int64)
    for bit in bits:
        code = (code << 1) | bit
    stripe = gray_decode(code)
    x = truth.proj_xy[..., 0].astype(np.float64)
    frac = np.mod(x + 0.5, SPEC.stripe_px)
    white = read_image_rgb(s.frame_path(1, "white")).astype(int).sum(-1)
    ok = truth.lit & ~truth.depth_edge & (frac > 2) & (frac < SPEC.stripe_px - 2)
    ok &= white > 3 * 100  # white squares (the black ones return too little light to read bits reliably)
    assert ok.sum() > 1000
    assert np.mean(stripe[ok] == SPEC.stripe_of_column(x[ok])) > 0.99


def test_white_frame_shows_the_board_where_the_truth_says(session):
    import cv2

    s = load_session(session)
    tr = load_truth(session)
    cols, rows, sq = tr["board"]
    R, t = tr["poses"][0]
    grey = cv2.cvtColor(read_image_rgb(s.frame_path(0, "white")), cv2.COLOR_RGB2GRAY)
    found, corners = cv2.findChessboardCornersSB(grey, (cols, rows))
    assert found
    truth = tr["camera"].project(sim.scenes.board_corners(cols, rows, sq) @ R.T + t)
    got = corners.reshape(-1, 2)
    if np.linalg.norm(got[0] - truth[0]) > np.linalg.norm(got[0] - truth[-1]):
        got = got[::-1]
    assert np.median(np.linalg.norm(got - truth, axis=1)) < 0.2


def test_write_session_rejects_bad_input(small_rig, tmp_path):
    with pytest.raises(GBError, match="projector"):
        write_session(tmp_path / "x", small_rig, PatternSpec(800, 600), n_poses=1, progress=False)
    with pytest.raises(GBError, match="board"):
        write_session(tmp_path / "x", small_rig, SPEC, board=(2, 5, 20.0), n_poses=1, progress=False)
    with pytest.raises(GBError, match="preset"):
        write_session(tmp_path / "x", small_rig, SPEC, n_poses=1, preset="sunny", progress=False)
    with pytest.raises(GBError, match="truth"):
        load_truth(tmp_path)


@pytest.mark.slow
def test_cli_simulate_session(tmp_path, capsys):
    from gbcal.cli import main

    out = tmp_path / "sess"
    assert main(["simulate-session", str(out), "--poses", "1", "--preset", "clean", "--quiet"]) == 0
    s = load_session(out)
    assert len(s.poses) == 1 and s.camera_size == (640, 480)
    assert "truth.yaml" in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        main(["simulate-session", str(tmp_path / "b"), "--board", "9by7"])
    assert e.value.code == 2


def test_cli_simulate(tmp_path):
    from gbscan.cli import main

    png = tmp_path / "step.png"
    assert main(["simulate", "step", "-o", str(png), "--truth", str(tmp_path / "t.npz"), "--preset", "clean"]) == 0
    img = read_image_rgb(png, size=(640, 480))
    t = np.load(tmp_path / "t.npz")
    assert t["point"].shape == (480, 640, 3) and t["lit"].dtype == bool
    np.testing.assert_array_equal(t["image"], img)
    assert main(["simulate", "plane", "-o", str(tmp_path / "a.png"), "--truth", str(tmp_path / "t.txt")]) == 1


def test_cli_simulate_takes_room_light(tmp_path, capsys):
    """--ambient LEVEL lights the scene with warm room light (red / green / blue 1 / 0.8 / 0.6 of
    LEVEL): the frame's unlit background brightens with that tint; a level outside 0-2 is one
    error line."""
    from gbscan.cli import main

    dark, lit = tmp_path / "dark.png", tmp_path / "lit.png"
    assert main(["simulate", "step", "-o", str(dark), "--preset", "clean", "--ambient", "0"]) == 0
    assert main(["simulate", "step", "-o", str(lit), "--preset", "clean", "--ambient", "0.4"]) == 0
    assert "ambient 0.4" in capsys.readouterr().out
    a = read_image_rgb(dark, size=(640, 480)).astype(float)
    b = read_image_rgb(lit, size=(640, 480)).astype(float)
    gain = (b - a).reshape(-1, 3).mean(axis=0)
    assert gain[0] > gain[1] > gain[2] > 5          # warm: red most, blue least
    assert main(["simulate", "step", "-o", str(tmp_path / "x.png"), "--ambient", "3"]) == 1
    assert "--ambient must be 0-2" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()


def test_cli_simulators_take_a_bayer_camera(tmp_path, capsys):
    """--bayer renders through a colour filter mosaic and OpenCV's demosaicing (most colour
    cameras): the image differs from the full-RGB one of the same scene and seed, and a session
    records the mosaic in its truth's conditions."""
    from gbcal.cli import main as gbcal_main
    from gbscan.cli import main

    paths = [tmp_path / "rgb.png", tmp_path / "bayer.png"]
    assert main(["simulate", "step", "-o", str(paths[0]), "--preset", "clean"]) == 0
    assert main(["simulate", "step", "-o", str(paths[1]), "--preset", "clean", "--bayer", "RGGB"]) == 0
    assert "Bayer RGGB" in capsys.readouterr().out
    a, b = (read_image_rgb(p, size=(640, 480)).astype(int) for p in paths)
    assert 0.5 < np.abs(a - b).mean() < 20   # the same scene, another camera
    out = tmp_path / "sess"
    assert gbcal_main(["simulate-session", str(out), "--poses", "1", "--preset", "clean", "--bayer", "GRBG",
                       "--quiet"]) == 0
    assert load_truth(out)["conditions"].bayer == "GRBG"
    with pytest.raises(SystemExit) as e:
        main(["simulate", "step", "-o", str(paths[0]), "--bayer", "RGB"])
    assert e.value.code == 2


def test_cli_simulators_take_a_baseline(tmp_path, capsys):
    """--baseline-mm puts the simulated projector that far right of the camera (toed in to 650 mm as
    the default rig): a session records that rig in its truth, and a frame rendered at that baseline
    scans right with that rig's calibration and far off with the default one (plan a rig on the
    command line).  Non-positive baselines: one line, exit 1."""
    from gbcal.cli import main as gbcal_main
    from gbscan.calibfile import calibration_from_rig, save_calibration
    from gbscan.cli import main

    out = tmp_path / "sess"
    assert gbcal_main(["simulate-session", str(out), "--poses", "1", "--preset", "clean", "--baseline-mm", "150",
                       "--quiet"]) == 0
    assert "baseline 150 mm" in capsys.readouterr().out
    rig150 = sim.paper_rig(baseline_mm=150.0)
    truth = load_truth(out)["rig"]
    np.testing.assert_allclose(truth.t_cam_proj, [150.0, 0.0, 0.0])
    np.testing.assert_allclose(truth.R_cam_proj, rig150.R_cam_proj, atol=1e-12)
    assert not np.allclose(rig150.R_cam_proj, sim.paper_rig().R_cam_proj)   # toed in from another place

    png, t = tmp_path / "sphere.png", tmp_path / "t.npz"
    assert main(["simulate", "sphere", "-o", str(png), "--truth", str(t), "--preset", "clean",
                 "--baseline-mm", "150"]) == 0
    assert "baseline 150 mm" in capsys.readouterr().out
    true_z = np.load(t)["point"][..., 2]
    med = {}
    for name, rig in (("150", rig150), ("200", sim.paper_rig())):
        cal = save_calibration(tmp_path / f"c{name}.yaml", calibration_from_rig(rig, SPEC))
        xyz = tmp_path / f"xyz{name}.npy"
        assert main(["scan", str(png), "--calib", str(cal), "-o", str(tmp_path / f"c{name}.ply"),
                     "--xyz", str(xyz)]) == 0
        z = np.load(xyz)[..., 2]
        ok = np.isfinite(z) & np.isfinite(true_z)
        assert ok.sum() > 20000
        med[name] = float(np.median(np.abs(z[ok] - true_z[ok])))
    assert med["150"] < 0.25 and med["200"] > 20.0, med   # measured 0.10 and 29 mm
    capsys.readouterr()
    for bad in ("0", "inf", "nan"):
        assert main(["simulate", "plane", "-o", str(tmp_path / "x.png"), "--baseline-mm", bad]) == 1
        assert "--baseline-mm" in capsys.readouterr().err
        assert gbcal_main(["simulate-session", str(tmp_path / "y"), "--baseline-mm", bad, "--quiet"]) == 1
        assert "--baseline-mm" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists() and not (tmp_path / "y").exists()
    with pytest.raises(GBError, match="baseline_mm"):
        sim.paper_rig(baseline_mm=float("inf"))
    # a negative baseline: the projector on the camera's left, the rig mirrored
    left, right = sim.paper_rig(baseline_mm=-200.0), sim.paper_rig()
    np.testing.assert_allclose(left.t_cam_proj, [-200.0, 0.0, 0.0])
    flip = np.diag([-1.0, 1.0, 1.0])
    np.testing.assert_allclose(left.R_cam_proj, flip @ right.R_cam_proj @ flip, atol=1e-12)


def test_cli_simulators_take_a_camera(tmp_path, capsys):
    """--camera WxH puts a sensor of that many pixels behind the paper camera's lens: a session
    records that camera, and a frame from twice the paper camera's pixels (stripes twice as wide
    in the image) scans right with its rig's calibration, the decoder shrinking it (resample)."""
    from gbcal.cli import main as gbcal_main
    from gbscan.calibfile import calibration_from_rig, save_calibration
    from gbscan.cli import main

    out = tmp_path / "sess"
    assert gbcal_main(["simulate-session", str(out), "--poses", "1", "--preset", "clean", "--camera", "800x600",
                       "--quiet"]) == 0
    assert "camera 800x600" in capsys.readouterr().out
    cam = load_truth(out)["rig"].camera
    assert (cam.width, cam.height) == (800, 600)
    np.testing.assert_allclose(cam.K, [[1000.0, 0, 399.5], [0, 1000.0, 299.5], [0, 0, 1]])
    assert load_session(out).camera_size == (800, 600)

    png, t = tmp_path / "sphere.png", tmp_path / "t.npz"
    assert main(["simulate", "sphere", "-o", str(png), "--truth", str(t), "--preset", "clean",
                 "--camera", "1280x960"]) == 0
    assert "camera 1280x960" in capsys.readouterr().out
    rig = sim.paper_rig(camera_px=(1280, 960))
    cal = save_calibration(tmp_path / "c.yaml", calibration_from_rig(rig, SPEC))
    xyz = tmp_path / "xyz.npy"
    assert main(["scan", str(png), "--calib", str(cal), "-o", str(tmp_path / "c.ply"), "--xyz", str(xyz)]) == 0
    z = np.load(xyz)[..., 2]
    truth = np.load(t)
    true_z = truth["point"][..., 2]
    ok = np.isfinite(z) & np.isfinite(true_z)
    assert z.shape == (960, 1280) and ok.sum() > 80000
    assert float(np.median(np.abs(z[ok] - true_z[ok]))) < 0.1
    off_edge = ok & ~truth["depth_edge"]       # (a silhouette pixel sees the sphere and the wall)
    assert float(np.abs(z[off_edge] - true_z[off_edge]).max()) < 3.0
    with pytest.raises(SystemExit) as e:
        main(["simulate", "plane", "-o", str(tmp_path / "x.png"), "--camera", "1280"])
    assert e.value.code == 2
    with pytest.raises(GBError, match="camera_px"):
        sim.paper_rig(camera_px=(1280.5, 960))


def test_cli_simulate_moving_object(tmp_path, capsys):
    """--move-mm / --turn-deg: the object moves during the exposure, the wall behind it stays; the
    truth file gains ``motion_edge`` (around the moving silhouette only); bad values are one error
    line and no file."""
    from gbscan.cli import main
    from gbscan.commands.simulate import make_scene
    from gbscan.sim.scenes import exposure_poses

    scene = make_scene("sphere")
    poses = exposure_poses(scene, (0.0, 0.0, 4.0), 2.0, 3)
    assert len(poses) == 3 and all(p.objects[-1] is scene.objects[-1] for p in poses)     # the wall stays
    assert not any(p.objects[0] is scene.objects[0] for p in poses)                         # the ball moves
    png, t = tmp_path / "m.png", tmp_path / "m.npz"
    assert main(["simulate", "sphere", "-o", str(png), "--truth", str(t), "--move-mm", "0,0,4",
                 "--exposure-steps", "3", "--preset", "clean"]) == 0
    assert "moving 0,0,4 mm during the exposure (3 instants)" in capsys.readouterr().out
    z = np.load(t)
    edge, oid = z["motion_edge"], z["object_id"]
    assert edge.any() and not edge[:20, :20].any() and not edge[oid == 0][::50].all()
    for argv, msg in ((["--move-mm", "1,2"], "three numbers"), (["--move-mm", "1,0,0", "--exposure-steps", "2"],
                                                                "odd number"), (["--turn-deg", "120"], "-90 .. 90")):
        assert main(["simulate", "sphere", "-o", str(tmp_path / "x.png"), *argv]) == 1
        assert msg in capsys.readouterr().err
        assert not (tmp_path / "x.png").exists()
