"""Checkerboard model and detection: conventions, accuracy on rendered boards, rejections with reasons."""
from pathlib import Path

import cv2
import numpy as np
import pytest

from gbcal.board import (Board, Detection, canonical_order, detect, detect_with_reason, draw_detection,
                         grid_irregularity, parse_board, refine_corners, refine_corners_symmetric)
from gbscan.camera import Camera
from gbscan.errors import GBError

SHARED = Path(__file__).resolve().parents[2] / "shared"
BOUGUET = SHARED / "data" / "bouguet_calib_example"
K = np.array([[800.0, 0.0, 319.5], [0.0, 800.0, 239.5], [0.0, 0.0, 1.0]])


def rot(rx=0.0, ry=0.0, rz=0.0):
    """Rotation from Euler angles in degrees (x, then y, then z; extrinsic)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("xyz", [rx, ry, rz], degrees=True).as_matrix()


def centred_pose(board, R, distance_mm=600.0, shift=(0.0, 0.0)):
    """Pose putting the board's centre on the optical axis at ``distance_mm`` (plus a shift in mm)."""
    centre = np.array([(board.cols - 1) * board.square_mm / 2, (board.rows - 1) * board.square_mm / 2, 0.0])
    return R, np.array([shift[0], shift[1], distance_mm]) - R @ centre


def render_board(board, R, t, *, camera=None, ss=4, blur_px=0.7, white=210.0, black=35.0, background=90.0,
                 noise=0.0, seed=0):
    """Area-sampled render of a board (convention of docs/design.md) -> (grey uint8, true corners (N, 2)).

    ``ss`` x ``ss`` samples per pixel through the exact camera model, Gaussian blur, optional noise.
    The printed grid is (cols+1) x (rows+1) squares with a one-square white margin.
    """
    cam = camera or Camera(640, 480, K)
    h, w = cam.height, cam.width
    n, d = R[:, 2], R[:, 2] @ t
    s = board.square_mm
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    acc = np.zeros((h, w))
    offs = (np.arange(ss) + 0.5) / ss - 0.5
    for dv in offs:
        for du in offs:
            xn = cam.normalize(np.stack([u + du, v + dv], -1))
            ray = np.concatenate([xn, np.ones((h, w, 1))], -1)
            with np.errstate(divide="ignore", invalid="ignore"):
                lam = d / (ray @ n)
            pb = (ray * lam[..., None] - t) @ R
            x, y = pb[..., 0] / s, pb[..., 1] / s
            grid = (x >= -1) & (x < board.cols) & (y >= -1) & (y < board.rows)
            paper = (x >= -2) & (x < board.cols + 1) & (y >= -2) & (y < board.rows + 1) & (lam > 0)
            is_white = (np.floor(x) + np.floor(y)) % 2 == 0
            acc += np.where(paper, np.where(grid & ~is_white, black, white), background)
    img = acc / ss**2
    if blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    if noise > 0:
        img = img + np.random.default_rng(seed).normal(0, noise, img.shape)
    truth = cam.project(board.object_points() @ R.T + t)
    return np.clip(np.round(img), 0, 255).astype(np.uint8), truth


# -- model -------------------------------------------------------------------------------------
def test_object_points_follow_the_convention():
    b = Board(4, 3, 25.0)
    p = b.object_points()
    assert p.shape == (12, 3) and p.dtype == np.float64
    np.testing.assert_array_equal(p[0], [0, 0, 0])
    np.testing.assert_array_equal(p[1], [25, 0, 0])  # x fastest
    np.testing.assert_array_equal(p[4], [0, 25, 0])
    np.testing.assert_array_equal(p[-1], [75, 50, 0])
    assert b.pattern_size == (4, 3) and b.n_corners == 12


@pytest.mark.parametrize("args, match", [((1, 5, 20.0), "cols"), ((5, 0, 20.0), "rows"), ((5, 4, 0.0), "square_mm"),
                                         ((5, 4, float("nan")), "square_mm"), ((5.5, 4, 20.0), "cols")])
def test_board_rejects_bad_parameters(args, match):
    with pytest.raises(GBError, match=match):
        Board(*args)


def test_parse_board():
    assert parse_board("9x6", 25) == Board(9, 6, 25.0)
    assert parse_board("9X6", 25) == Board(9, 6, 25.0)
    for bad in ("9", "9x", "axb", "9x6x2"):
        with pytest.raises(GBError, match="COLSxROWS"):
            parse_board(bad, 25)


# -- detection accuracy ------------------------------------------------------------------------
@pytest.mark.parametrize("angles", [(20, -25, 5), (-30, 15, -10), (10, 35, 30)])
def test_detected_corners_match_truth(angles):
    b = Board(9, 6, 25.0)
    R, t = centred_pose(b, rot(*angles), 620.0, (10.0, -5.0))
    img, truth = render_board(b, R, t, noise=1.0, seed=3)
    det = detect(img, b)
    assert isinstance(det, Detection) and det.image_size == (640, 480)
    err = np.linalg.norm(det.corners - truth, axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.1 and err.max() < 0.3
    assert det.corners.shape == (54, 2) and det.corners.dtype == np.float64
    assert 1.0 < det.sharpness_px < 4.0 and det.contrast > 100


def test_refinement_beats_the_sector_detector_alone():
    b = Board(9, 6, 25.0)
    errs = {}
    for refine in (True, False):
        e = []
        for k, ang in enumerate([(20, -25, 5), (-30, 15, -10)]):
            R, t = centred_pose(b, rot(*ang), 600.0)
            img, truth = render_board(b, R, t, blur_px=1.0, noise=1.0, seed=k)
            e.append(detect(img, b, refine=refine).corners - truth)
        errs[refine] = np.sqrt(np.mean(np.sum(np.concatenate(e) ** 2, axis=1)))
    assert errs[True] < 0.8 * errs[False], errs


# -- the symmetric corner refiner --------------------------------------------------------------
def x_junction(q, e1, e2, *, size=(120, 100), width_px=1.2, gamma=1.0, gain=(0.0, 0.0), offset=(0.0, 0.0)):
    """An exactly point-symmetric corner at ``q``: two smooth edges along unit directions ``e1``,
    ``e2`` (any angle), contrast ``tanh(.) * tanh(.)``, then a tone curve, a lighting gain and an
    offset that are linear across the image (float64 (H, W) grey levels)."""
    v, u = np.mgrid[0:size[1], 0:size[0]].astype(np.float64)
    p = np.stack([u - q[0], v - q[1]], -1)
    n1, n2 = np.array([-e1[1], e1[0]]), np.array([-e2[1], e2[0]])
    s = np.tanh(p @ n1 / width_px) * np.tanh(p @ n2 / width_px)
    img = 255.0 * ((0.5 + 0.4 * s) ** (1.0 / gamma))
    return img * (1.0 + p @ np.asarray(gain)) + p @ np.asarray(offset)


def grid_around(q, e1, e2, spacing):
    """A 3x3 (rows, cols) corner grid of spacing ``spacing`` px centred on ``q`` (for the window size)."""
    j, i = np.mgrid[-1:2, -1:2]
    return q + spacing * (i.reshape(-1, 1) * np.asarray(e1) + j.reshape(-1, 1) * np.asarray(e2))


@pytest.mark.parametrize("case", [
    dict(),                                                    # square corner
    dict(e2=(0.45, 0.893)),                                    # perspective: 63 degrees
    dict(gamma=2.2, width_px=2.0),                             # tone curve, more blur
    dict(gain=(0.004, -0.003), offset=(0.3, 0.2)),             # lighting gradient
])
def test_symmetric_refiner_finds_an_exact_corner(case):
    case = dict(case)
    e1 = np.array([0.995, 0.0998])
    e2 = np.asarray(case.pop("e2", (-0.0998, 0.995)))
    e2 = e2 / np.linalg.norm(e2)
    b = Board(3, 3, 10.0)
    photometric = "gain" in case
    # On the half-pixel lattice the sample pairs fall on mirrored pixels: exact (the linear light
    # model leaves a second-order residual there).  Elsewhere bilinear interpolation of the two
    # sides differs a little ("pixel locking"): up to ~0.013 px on these sharp edges.
    for q, tol in (((60.5, 50.0), 5e-3 if photometric else 1e-6), ((60.37, 49.71), 0.015), ((60.12, 50.2), 0.015)):
        q = np.array(q)
        img = x_junction(q, e1, e2, **case)
        start = grid_around(q, e1, e2, 24.0) + np.array([0.6, -0.5])
        got = refine_corners_symmetric(img, b, start)
        assert np.linalg.norm(got[4] - q) < tol, (q, got[4] - q)


def test_symmetric_refiner_halves_cornersubpix_error_on_rendered_boards():
    b = Board(9, 6, 25.0)
    errs = {"cornersubpix": [], "symmetric": []}
    for k, ang in enumerate([(20, -25, 5), (-30, 15, -10), (10, 35, 30)]):
        R, t = centred_pose(b, rot(*ang), 620.0)
        img, truth = render_board(b, R, t, ss=3, noise=1.0, seed=k)
        start = detect(img, b, refine=False).corners
        for name in errs:
            errs[name].append(refine_corners(img, b, start, name) - truth)
    rms = {k: float(np.sqrt(np.mean(np.concatenate(v) ** 2))) for k, v in errs.items()}
    assert rms["symmetric"] < 0.6 * rms["cornersubpix"] and rms["symmetric"] < 0.03, rms


def test_symmetric_refiner_keeps_corners_it_cannot_place():
    b = Board(3, 3, 10.0)
    flat = np.full((100, 120), 128.0)
    c = grid_around(np.array([60.0, 50.0]), (1.0, 0.0), (0.0, 1.0), 20.0)
    np.testing.assert_array_equal(refine_corners_symmetric(flat, b, c), c)  # no corner: singular
    e1, e2 = np.array([1.0, 0.0]), np.array([0.0, 1.0])
    img = x_junction(np.array([60.0, 50.0]), e1, e2)
    far = grid_around(np.array([63.0, 50.0]), e1, e2, 20.0)  # 3 px off: out of reach of max_shift_px
    np.testing.assert_array_equal(refine_corners_symmetric(img, b, far, max_shift_px=1.0)[4], far[4])
    np.testing.assert_allclose(refine_corners_symmetric(img, b, far, max_shift_px=5.0)[4], [60.0, 50.0], atol=1e-6)
    assert refine_corners_symmetric(img, b, np.zeros((0, 2))).shape == (0, 2)


def test_unknown_corner_refiner_is_an_error():
    b = Board(9, 6, 25.0)
    img, _ = render_board(b, *centred_pose(b, rot(10, 10, 0), 620.0))
    with pytest.raises(GBError, match="corner refiner must be one of symmetric, cornersubpix"):
        detect(img, b, refiner="harris")


def test_colour_and_grey_input_agree():
    b = Board(7, 5, 30.0)
    R, t = centred_pose(b, rot(15, -20, 0), 650.0)
    img, _ = render_board(b, R, t, ss=3)
    rgb = np.repeat(img[:, :, None], 3, axis=2)
    np.testing.assert_allclose(detect(rgb, b).corners, detect(img, b).corners, atol=1e-9)


# -- canonical order ---------------------------------------------------------------------------
@pytest.mark.parametrize("spin", [0.0, 90.0, 180.0, 270.0, 150.0])
def test_order_follows_white_first_square_on_asymmetric_boards(spin):
    # cols + rows odd: the first square's colour fixes the order whatever the in-plane rotation
    b = Board(8, 5, 25.0)
    R, t = centred_pose(b, rot(15, -10, 0) @ rot(0, 0, spin), 600.0)
    img, truth = render_board(b, R, t, ss=3)
    det = detect(img, b)
    assert det is not None
    np.testing.assert_allclose(det.corners, truth, atol=0.3)


def test_symmetric_board_takes_the_order_with_x_to_the_right():
    # cols + rows even: 180-degree turns look the same; the documented tie-break is x -> image right
    b = Board(7, 5, 25.0)
    for spin in (0.0, 180.0):
        R, t = centred_pose(b, rot(0, 0, spin), 600.0)
        img, truth = render_board(b, R, t, ss=3)
        det = detect(img, b)
        expected = truth if spin == 0 else truth[::-1]
        np.testing.assert_allclose(det.corners, expected, atol=0.3)
        assert det.corners[b.cols - 1, 0] > det.corners[0, 0]


def test_canonical_order_undoes_any_detector_order():
    b = Board(6, 4, 25.0)
    R, t = centred_pose(b, rot(10, 20, 0), 600.0)
    img, truth = render_board(b, R, t, ss=3)
    g = truth.reshape(b.rows, b.cols, 2)
    for scrambled in (g[::-1, ::-1], g[:, ::-1], g[::-1, :], g):
        np.testing.assert_array_equal(canonical_order(scrambled.reshape(-1, 2), b, img), truth)


# -- rejections with reasons -------------------------------------------------------------------
def test_no_board_gives_a_reason():
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(0, 255, (240, 320)).astype(np.uint8), (0, 0), 3)
    det, why = detect_with_reason(img, Board(9, 6, 25.0))
    assert det is None and "no 9x6 checkerboard" in why
    det, why = detect_with_reason(np.full((240, 320), 128, np.uint8), Board(9, 6, 25.0))
    assert det is None and "contrast" in why
    assert detect(img, Board(9, 6, 25.0)) is None


def test_blurred_board_is_rejected_with_its_edge_width():
    b = Board(7, 5, 30.0)
    R, t = centred_pose(b, rot(10, -15, 0), 550.0)
    img, _ = render_board(b, R, t, ss=2, blur_px=3.5)
    det, why = detect_with_reason(img, b)
    assert det is None and "blurred" in why and "px wide" in why
    assert detect(img, b, max_sharpness_px=50.0) is not None  # the limit is the only reason


def test_partial_board_is_rejected():
    b = Board(9, 6, 25.0)
    R, t = centred_pose(b, rot(0, 10, 0), 600.0, (-230.0, 0.0))  # left part outside the frame
    img, truth = render_board(b, R, t, ss=2)
    assert truth[:, 0].min() < 0 < truth[:, 0].max()
    det, why = detect_with_reason(img, b)
    assert det is None and why


def test_low_contrast_board_is_rejected():
    b = Board(7, 5, 30.0)
    R, t = centred_pose(b, rot(10, -15, 0), 550.0)
    img, _ = render_board(b, R, t, ss=2, white=130, black=118, background=125)
    det, why = detect_with_reason(img, b)
    assert det is None and why
    if "contrast too low" not in why:  # OpenCV may not find so faint a board at all
        assert "checkerboard" in why


def test_grid_irregularity_separates_real_grids_from_scrambled_ones():
    b = Board(7, 5, 30.0)
    for angles in ((0, 0, 0), (35, -40, 10), (-50, 20, 30)):
        R, t = centred_pose(b, rot(*angles), 550.0)
        truth = Camera(640, 480, K, np.array([-0.3, 0.12, 0, 0, 0])).project(b.object_points() @ R.T + t)
        assert grid_irregularity(truth, b) < 0.35, angles
    bad = truth.copy()
    bad[[8, 9]] = bad[[9, 8]]  # two neighbours swapped: a corner in the wrong square
    assert grid_irregularity(bad, b) > 0.9


def test_a_scrambled_detector_grid_is_rejected_with_the_reason(monkeypatch):
    b = Board(7, 5, 30.0)
    R, t = centred_pose(b, rot(10, -15, 0), 550.0)
    img, truth = render_board(b, R, t, ss=2)
    assert detect(img, b) is not None
    bad = truth.copy()
    bad[[8, 15]] = bad[[15, 8]]
    monkeypatch.setattr(cv2, "findChessboardCornersSBWithMeta",
                        lambda *a: (True, bad.astype(np.float32).reshape(-1, 1, 2), None))
    det, why = detect_with_reason(img, b, refine=False)
    assert det is None and "not a regular checkerboard" in why


def test_wrong_board_size_is_not_found():
    b = Board(7, 5, 30.0)
    R, t = centred_pose(b, rot(10, -15, 0), 550.0)
    img, _ = render_board(b, R, t, ss=2)
    det, why = detect_with_reason(img, Board(8, 5, 30.0))
    assert det is None and "8x5" in why


def test_bad_image_arrays_raise():
    b = Board(7, 5, 30.0)
    with pytest.raises(GBError, match="8-bit"):
        detect(np.zeros((100, 100), np.float32), b)
    with pytest.raises(GBError, match="shape"):
        detect(np.zeros((10, 100, 100), np.uint8), b)


def test_preview_picture():
    b = Board(7, 5, 30.0)
    R, t = centred_pose(b, rot(10, -15, 0), 550.0)
    img, truth = render_board(b, R, t, ss=2)
    det = detect(img, b)
    pic = draw_detection(img, b, det, reprojected=truth)
    assert pic.shape == (480, 640, 3) and pic.dtype == np.uint8
    assert np.any(pic[:, :, 0] != pic[:, :, 1])  # something coloured was drawn


# -- the simulator and real images -------------------------------------------------------------
@pytest.mark.slow
def test_simulator_board_corners():
    sim = pytest.importorskip("gbscan.sim")
    from gbscan.rig import Rig

    base = sim.paper_rig()
    cam = Camera(320, 240, np.array([[600.0, 0, 159.5], [0, 600.0, 119.5], [0, 0, 1]]), [-0.1, 0.05, 0, 0, 0])
    rig = Rig(cam, base.projector, base.R_cam_proj, base.t_cam_proj)
    b = Board(8, 5, 20.0)  # cols + rows odd: the white first square fixes the order
    white = np.full((rig.projector.height, rig.projector.width, 3), 255, np.uint8)
    for k, ang in enumerate([(25, -20, 5), (-20, 25, 160)]):
        R, t = centred_pose(b, rot(*ang), 550.0)
        r = sim.render(rig, sim.scenes.board(b.cols, b.rows, b.square_mm, R, t), white, "typical", seed=k)
        det = detect(r.image, b)
        assert det is not None
        truth = cam.project(b.object_points() @ R.T + t)
        err = np.linalg.norm(det.corners - truth, axis=1)
        assert np.sqrt(np.mean(err**2)) < 0.1, k


def test_bouguet_images_detected_in_canonical_order():
    if not BOUGUET.is_dir():
        pytest.skip(f"{BOUGUET} not present (shared developer data)")
    from gbscan.io import read_image_gray

    b = Board(13, 12, 30.0)
    for name in ("Image1.tif", "Image11.tif", "Image20.tif"):
        img = read_image_gray(BOUGUET / name)
        det = detect(img, b)
        assert det is not None and 2.0 < det.sharpness_px < 6.0
        # first square white: the mean grey inside it exceeds that of its neighbour square
        c = det.corners.reshape(b.rows, b.cols, 2)
        first = np.mean([c[0, 0], c[0, 1], c[1, 0], c[1, 1]], axis=0)
        second = np.mean([c[0, 1], c[0, 2], c[1, 1], c[1, 2]], axis=0)
        val = lambda p: float(img[int(round(p[1])), int(round(p[0]))])  # noqa: E731
        assert val(first) > val(second) + 40


def test_symmetric_refiner_keeps_a_corner_whose_window_holds_nan():
    b = Board(3, 3, 10.0)
    e1, e2 = np.array([1.0, 0.0]), np.array([0.0, 1.0])
    img = x_junction(np.array([60.3, 50.2]), e1, e2)
    img[45:48, 63:66] = np.nan  # a dead patch inside the middle corner's window only
    c = grid_around(np.array([60.0, 50.0]), e1, e2, 20.0)
    got = refine_corners_symmetric(img, b, c)
    np.testing.assert_array_equal(got[4], c[4])
    assert np.all(np.isfinite(got))
