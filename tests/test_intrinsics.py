"""Camera calibration: exact recovery, noise, outliers, degenerate capture sets, real images, the CLI."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gbcal.board import Board, Detection, detect
from gbcal.intrinsics import board_normals, board_pose, calibrate_camera
from gbscan.calibfile import load_calibration
from gbscan.camera import Camera
from gbscan.errors import GBError

SHARED = Path(__file__).resolve().parents[2] / "shared"
BOUGUET = SHARED / "data" / "bouguet_calib_example"
BOARD = Board(9, 6, 25.0)
CAM = Camera(640, 480, np.array([[812.3, 0.0, 321.7], [0.0, 806.9, 236.2], [0.0, 0.0, 1.0]]),
             np.array([-0.21, 0.13, 0.0012, -0.0008, -0.03]))


def rot(rx=0.0, ry=0.0, rz=0.0):
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("xyz", [rx, ry, rz], degrees=True).as_matrix()


def poses(n, seed=0, tilt_deg=35.0, board=BOARD, spread=(0.15, 0.1), depth_mm=(450, 800)):
    """n varied board poses (tilts up to ``tilt_deg``, depth range, centres spread over the image)."""
    rng = np.random.default_rng(seed)
    centre = np.array([(board.cols - 1) * board.square_mm / 2, (board.rows - 1) * board.square_mm / 2, 0.0])
    out = []
    for _ in range(n):
        R = rot(*rng.uniform(-tilt_deg, tilt_deg, 2), rng.uniform(-20, 20))
        z = rng.uniform(*depth_mm)
        c = np.array([rng.uniform(-spread[0], spread[0]) * z, rng.uniform(-spread[1], spread[1]) * z, z])
        out.append((R, c - R @ centre))
    return out


def corners(cam, pose_list, noise_px=0.0, seed=1, board=BOARD):
    rng = np.random.default_rng(seed)
    obj = board.object_points()
    return [cam.project(obj @ R.T + t) + rng.normal(0, noise_px, (board.n_corners, 2)) for R, t in pose_list]


def params(cam):
    return np.r_[cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2], cam.dist]


# -- recovery ----------------------------------------------------------------------------------
def test_exact_recovery_on_clean_corners():
    ps = poses(12)
    res = calibrate_camera(corners(CAM, ps), BOARD, (640, 480))
    np.testing.assert_allclose(res.camera.K, CAM.K, rtol=1e-6)
    np.testing.assert_allclose(res.camera.dist, CAM.dist, rtol=1e-5, atol=1e-8)
    assert res.rms_px < 1e-4 and res.used.all()
    for (R, t), v in zip(ps, res.views):
        np.testing.assert_allclose(v.R, R, atol=1e-7)
        np.testing.assert_allclose(v.t, t, rtol=1e-6)
        R2, t2 = board_pose(res.camera, corners(CAM, [(R, t)])[0], BOARD)
        np.testing.assert_allclose(R2, R, atol=1e-7)
        np.testing.assert_allclose(t2, t, rtol=1e-6)
    np.testing.assert_allclose(res.R_cam_board[3], ps[3][0], atol=1e-7)
    np.testing.assert_allclose(res.t_cam_board[3], ps[3][1], rtol=1e-6)


def test_bouguet_model_holds_k3_at_zero():
    cam = Camera(640, 480, CAM.K, np.r_[CAM.dist[:4], 0.0])
    res = calibrate_camera(corners(cam, poses(10, seed=4)), BOARD, (640, 480), model="k1k2p1p2")
    np.testing.assert_allclose(params(res.camera), params(cam), rtol=1e-6, atol=1e-9)
    assert res.camera.dist[4] == 0.0 and "k3" not in res.std and set(res.std) >= {"fx", "fy", "p1", "p2"}
    res = calibrate_camera(corners(cam, poses(10, seed=4)), BOARD, (640, 480), model="k1k2", fix_aspect=True)
    assert res.camera.dist[2] == res.camera.dist[3] == res.camera.dist[4] == 0.0
    assert res.camera.K[0, 0] == pytest.approx(res.camera.K[1, 1])


def test_noisy_corners_within_their_uncertainty():
    res = calibrate_camera(corners(CAM, poses(15, seed=2), noise_px=0.15, seed=5), BOARD, (640, 480))
    assert 0.18 < res.rms_px < 0.22  # 2-D RMS of 0.15 px per axis: 0.21 px less the fitted dof
    true = dict(zip(("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"), params(CAM)))
    est = dict(zip(true, params(res.camera)))
    for k in ("fx", "fy", "cx", "cy", "k1", "p1", "p2"):
        assert abs(est[k] - true[k]) < 4 * res.std[k], (k, est[k], true[k], res.std[k])
    assert abs(est["fx"] / true["fx"] - 1) < 0.003 and res.std["fx"] < 2.0


def test_residuals_are_observed_minus_projected():
    pts = corners(CAM, poses(6, seed=8), noise_px=0.1, seed=9)
    res = calibrate_camera(pts, BOARD, (640, 480), reject_outliers=False)
    v = res.views[0]
    obj = BOARD.object_points() @ v.R.T + v.t
    np.testing.assert_allclose(v.residuals_px, pts[0] - res.camera.project(obj), atol=1e-9)
    np.testing.assert_allclose(np.sqrt(np.mean(np.sum(v.residuals_px**2, 1))), v.rms_px, rtol=1e-12)


def test_outlier_capture_is_dropped_with_a_reason():
    pts = corners(CAM, poses(10, seed=3), noise_px=0.1, seed=6)
    pts[4] = pts[4] + np.random.default_rng(7).normal(0, 2.0, pts[4].shape)  # a bent or moving board
    res = calibrate_camera(pts, BOARD, (640, 480), names=[f"cap{i}.png" for i in range(10)])
    assert not res.views[4].used and "outlier" in res.views[4].reason and res.views[4].rms_px > 1.0
    assert res.used.sum() == 9 and res.rms_px < 0.15
    assert abs(res.camera.K[0, 0] / CAM.K[0, 0] - 1) < 0.003
    d = res.residuals_dict()
    assert d["captures"][4]["capture"] == "cap4.png" and not d["captures"][4]["used"]
    keep = calibrate_camera(pts, BOARD, (640, 480), reject_outliers=False)
    assert keep.used.all() and keep.rms_px > res.rms_px


# -- degenerate capture sets -------------------------------------------------------------------
def test_too_few_captures():
    pts = corners(CAM, poses(2))
    with pytest.raises(GBError, match="too few captures.*2 of 4"):
        calibrate_camera(pts + [None, None], BOARD, (640, 480))


def test_parallel_boards_name_the_unobservable_parameters():
    R = np.eye(3)
    centre = np.array([100.0, 62.5, 0.0])
    fronto = [(R, np.array([x, y, z]) - centre) for x, y, z in [(0, 0, 500), (60, -40, 650), (-50, 30, 800),
                                                                (20, 50, 700)]]
    with pytest.raises(GBError, match=r"face the camera squarely.*fx, fy.*cx, cy"):
        calibrate_camera(corners(CAM, fronto), BOARD, (640, 480))
    Rt = rot(30, 20, 0)
    tilted = [(Rt @ rot(0, 0, a), np.array([x, y, z]) - Rt @ rot(0, 0, a) @ centre)
              for a, (x, y, z) in zip((0, 15, -20, 40), [(0, 0, 500), (60, -40, 650), (-50, 30, 800), (20, 50, 700)])]
    with pytest.raises(GBError, match=r"share one orientation.*not separately observable"):
        calibrate_camera(corners(CAM, tilted), BOARD, (640, 480))


def test_board_normals_agree_with_true_poses():
    ps = poses(6, seed=11)
    n = board_normals(corners(CAM, ps), BOARD, (640, 480))
    true = np.array([R[:, 2] for R, _ in ps])
    ang = np.degrees(np.arccos(np.clip(np.sum(n * true, 1), -1, 1)))
    assert ang.max() < 6.0  # a rough estimate (guessed focal length, distortion ignored), enough for the check


def test_mixed_image_sizes_are_refused():
    pts = corners(CAM, poses(4))
    dets = [Detection(p, (640, 480), 2.0, 30.0, 200.0, "sb") for p in pts]
    dets[2] = Detection(pts[2], (1280, 960), 2.0, 30.0, 200.0, "sb")
    with pytest.raises(GBError, match="mixed image sizes.*1280x960: c2"):
        calibrate_camera(dets, BOARD, names=["c0", "c1", "c2", "c3"])
    with pytest.raises(GBError, match="mixed image sizes"):
        calibrate_camera(dets[:2] + dets[3:], BOARD, (800, 600))


def test_bad_arguments():
    pts = corners(CAM, poses(4))
    with pytest.raises(GBError, match="image_size"):
        calibrate_camera(pts, BOARD)
    with pytest.raises(GBError, match=r"capture 1: expected \(54, 2\)"):
        calibrate_camera([pts[0], pts[1][:10]] + pts[2:], BOARD, (640, 480))
    with pytest.raises(GBError, match="unknown distortion model"):
        calibrate_camera(pts, BOARD, (640, 480), model="fisheye")
    with pytest.raises(GBError, match="outside the 320x240 image"):
        calibrate_camera(pts, BOARD, (320, 240))


# -- real images -------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def bouguet_detections():
    if not BOUGUET.is_dir():
        pytest.skip(f"{BOUGUET} not present (shared developer data)")
    from gbscan.io import read_image_gray

    b = Board(13, 12, 30.0)
    files = sorted(BOUGUET.glob("Image*.tif"))
    assert len(files) == 20
    return b, [detect(read_image_gray(f), b) for f in files]


def test_bouguet_published_intrinsics(bouguet_detections):
    b, dets = bouguet_detections
    assert all(d is not None for d in dets)
    res = calibrate_camera(dets, b, model="k1k2p1p2")
    K = res.camera.K
    # published: fc = 657.4629 657.9467, cc = 303.1366 242.5693, kc = -0.254025 0.121433 -0.000209 0.000019
    assert abs(K[0, 0] - 657.4629) < 1.0 and abs(K[1, 1] - 657.9467) < 1.0
    assert abs(K[0, 2] - 303.1366) < 2.0 and abs(K[1, 2] - 242.5693) < 2.0
    assert abs(res.camera.dist[0] - (-0.254025)) < 0.005 and abs(res.camera.dist[1] - 0.121433) < 0.02
    assert res.rms_px < 0.25 and res.used.all()


# -- simulator ---------------------------------------------------------------------------------
@pytest.mark.slow
def test_simulator_boards_calibrate_to_truth():
    sim = pytest.importorskip("gbscan.sim")
    from gbscan.rig import Rig

    base = sim.paper_rig()
    cam = Camera(320, 240, np.array([[600.0, 0, 159.5], [0, 600.0, 119.5], [0, 0, 1]]), [-0.1, 0.05, 0, 0, 0])
    rig = Rig(cam, base.projector, base.R_cam_proj, base.t_cam_proj)
    b = Board(8, 5, 20.0)
    white = np.full((rig.projector.height, rig.projector.width, 3), 255, np.uint8)
    dets = []
    # near the projector's crossing distance, so that the white frame lights the whole board (corners on
    # the edge of the projector's light are biased by that edge)
    for k, (R, t) in enumerate(poses(7, seed=21, tilt_deg=40.0, board=b, spread=(0.04, 0.04), depth_mm=(560, 700))):
        r = sim.render(rig, sim.scenes.board(b.cols, b.rows, b.square_mm, R, t), white, "typical", seed=k)
        ij = np.round(cam.project(b.object_points() @ R.T + t)).astype(int)
        assert r.lit[ij[:, 1], ij[:, 0]].all()
        dets.append(detect(r.image, b))
    assert all(d is not None for d in dets)
    res = calibrate_camera(dets, b, model="k1k2p1p2")
    assert res.rms_px < 0.1
    for i, name in ((0, "fx"), (1, "fy")):
        err = res.camera.K[i, i] - 600.0
        assert abs(err) < 0.6 and abs(err) < 3 * res.std[name], (name, err, res.std[name])


# -- the command -------------------------------------------------------------------------------
SMALL = Camera(320, 240, np.array([[400.0, 0.0, 160.3], [0.0, 399.0, 119.1], [0.0, 0.0, 1.0]]),
               np.array([-0.15, 0.08, 0.001, -0.0005, 0.0]))


def gbcal(*args):
    return subprocess.run([sys.executable, "-m", "gbcal.cli", *map(str, args)], capture_output=True, text=True)


def gbcal_inprocess(capsys, *args):
    """Run the dispatcher in this process (fast): (exit code, stdout, stderr)."""
    from gbcal.cli import main

    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module")
def board_images(tmp_path_factory):
    from test_board import render_board

    from gbscan.io import write_png

    folder = tmp_path_factory.mktemp("caps")
    for i, (R, t) in enumerate(poses(6, seed=13, tilt_deg=30.0, spread=(0.08, 0.06), depth_mm=(550, 750))):
        img, _ = render_board(BOARD, R, t, camera=SMALL, ss=3, noise=1.0, seed=i)
        write_png(folder / f"cap{i:02d}.png", np.repeat(img[:, :, None], 3, 2))
    return folder, SMALL


def test_camera_command_writes_a_camera_only_calibration(board_images, tmp_path):
    folder, cam = board_images
    empty = tmp_path / "empty.png"
    from gbscan.io import write_png

    write_png(empty, np.full((240, 320), 200, np.uint8))
    out = tmp_path / "camera.yaml"
    r = gbcal("camera", folder, empty, "--board", "9x6", "--square-mm", 25, "-o", out, "--model", "k1k2p1p2",
              "--preview", tmp_path / "prev")
    assert r.returncode == 0, r.stderr
    assert "empty.png: rejected:" in r.stderr and "6 of 7 images used" in r.stdout and "fx = " in r.stdout
    calib = load_calibration(out, require_planes=False)
    assert calib.n_planes == 0
    assert abs(calib.camera.K[0, 0] / cam.K[0, 0] - 1) < 0.005
    assert calib.residuals["captures_used"] == 6 and "fx" in calib.uncertainty["camera_std"]
    assert calib.created["board"] == {"cols": 9, "rows": 6, "square_mm": 25.0}
    assert calib.residuals["corner_refiner"] == "symmetric"
    assert len(list((tmp_path / "prev").glob("*_corners.png"))) == 7
    old = tmp_path / "camera_csp.yaml"
    r = gbcal("camera", folder, "--board", "9x6", "--square-mm", 25, "-o", old, "--model", "k1k2p1p2",
              "--corners", "cornersubpix")
    assert r.returncode == 0, r.stderr
    csp = load_calibration(old, require_planes=False)
    assert csp.residuals["corner_refiner"] == "cornersubpix"
    # the symmetric refiner's corners fit one camera better than cornerSubPix's alone
    assert calib.residuals["camera_rms_px"] < csp.residuals["camera_rms_px"], (calib.residuals, csp.residuals)


def test_camera_command_bad_input_is_one_line_and_leaves_no_file(board_images, tmp_path, capsys):
    folder, _ = board_images
    out = tmp_path / "camera.yaml"
    corrupt = tmp_path / "corrupt.png"
    corrupt.write_bytes(b"not a png at all")
    from gbscan.io import write_png

    small = tmp_path / "small.png"
    write_png(small, np.zeros((120, 160), np.uint8))
    tiny = tmp_path / "tiny.png"
    write_png(tiny, np.zeros((10, 10), np.uint8))
    noboard = tmp_path / "noboard"
    noboard.mkdir()
    for i in range(3):
        write_png(noboard / f"n{i}.png", np.full((240, 320), 90 + 40 * i, np.uint8))
    cases = [
        ([folder / "cap00.png", corrupt], "corrupt.png could not be read"),
        ([folder / "cap00.png", small], "small.png is 160x120"),
        ([folder / "cap00.png", folder / "cap01.png"], "too few captures"),
        ([noboard], "too few captures with a detected board: 0 of 3"),
        ([tmp_path / "missing.png"], "missing.png does not exist"),
        ([tiny], "tiny.png: image of 10x10 px is too small to hold a board"),
        ([str(tmp_path / "*.jpeg")], "no file matches"),
        ([folder, "--board", "9by6"], "COLSxROWS"),
    ]
    with pytest.raises(SystemExit) as exit_:
        gbcal_inprocess(capsys, "camera", folder, "--board", "9x6", "--square-mm", 25, "-o", out, "--corners", "harris")
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and "invalid choice: 'harris'" in err and not out.exists()
    assert len(err.strip().splitlines()) == 1, err
    for images, message in cases:
        board = [] if "--board" in images else ["--board", "9x6"]
        code, _, err = gbcal_inprocess(capsys, "camera", *images, *board, "--square-mm", 25, "-o", out)
        assert code == 1, (images, err)
        last = err.strip().splitlines()[-1]
        assert last.startswith("gbcal camera: error:") and message in last, last
        assert not out.exists()
    r = gbcal("camera", corrupt, "--board", "9x6", "--square-mm", 25, "-o", out)
    assert r.returncode == 1 and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 2
    assert not out.exists()


def test_projection_jacobian_matches_finite_differences():
    from gbcal.intrinsics import _projection_jacobian

    obj = BOARD.object_points()[::7]
    rvec, tvec = np.array([0.3, -0.2, 0.1]), np.array([-80.0, -40.0, 600.0])
    x = np.r_[rvec, tvec, CAM.K[0, 0], CAM.K[1, 1], CAM.K[0, 2], CAM.K[1, 2], CAM.dist]

    def f(x):
        K = np.array([[x[6], 0, x[8]], [0, x[7], x[9]], [0, 0, 1.0]])
        return _projection_jacobian(K, x[10:15], x[:3], x[3:6], obj)[0].ravel()

    _, J = _projection_jacobian(CAM.K, CAM.dist, rvec, tvec, obj)
    step = np.maximum(np.abs(x), 1e-3) * 1e-6
    Jn = np.stack([(f(x + np.eye(15)[i] * step[i]) - f(x - np.eye(15)[i] * step[i])) / (2 * step[i])
                   for i in range(15)], axis=1)
    np.testing.assert_allclose(J, Jn, rtol=1e-5, atol=1e-5 * np.abs(Jn).max())
