"""Camera model, rig geometry and the pattern layout against OpenCV and first principles."""
import cv2
import numpy as np
import pytest

from gbscan.camera import Camera
from gbscan.errors import GBError
from gbscan.pattern import BLUE, CYAN, GREEN, MARKER_GAPS, PatternSpec, render_pattern
from gbscan.rig import column_planes, paper_rig


@pytest.fixture
def cam():
    K = np.array([[812.3, 0.0, 321.7], [0.0, 806.9, 236.2], [0.0, 0.0, 1.0]])
    return Camera(640, 480, K, np.array([-0.21, 0.13, 0.0012, -0.0008, -0.03]))


def test_project_matches_opencv(cam):
    rng = np.random.default_rng(1)
    p = rng.uniform([-250, -180, 400], [250, 180, 900], size=(500, 3))
    q_cv, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    np.testing.assert_allclose(cam.project(p), q_cv[:, 0, :], atol=1e-9)


def test_rays_invert_projection(cam):
    q = cam.pixel_grid()[::7, ::7].reshape(-1, 2)
    r = cam.rays(q)
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(cam.project(r * 700.0), q, atol=1e-8)


def test_normalize_matches_opencv_undistort(cam):
    q = cam.pixel_grid()[::31, ::31].reshape(-1, 1, 2)
    ref = cv2.undistortPoints(q, cam.K, cam.dist, R=None, P=None, criteria=
                              (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14))
    np.testing.assert_allclose(cam.normalize(q[:, 0]), ref[:, 0], atol=1e-7)


def test_camera_rejects_bad_parameters():
    with pytest.raises(GBError, match="3x3"):
        Camera(640, 480, np.eye(2))
    with pytest.raises(GBError, match="5 values"):
        Camera(640, 480, np.eye(3), np.zeros(4))
    with pytest.raises(GBError, match="focal"):
        Camera(640, 480, np.diag([0.0, 1.0, 1.0]))


def test_column_planes_contain_projector_rays():
    rig = paper_rig()
    rng = np.random.default_rng(2)
    x = rng.uniform(0, 1023, 50)
    y = rng.uniform(0, 767, 50)
    depth = rng.uniform(300, 1200, 50)
    Kp = rig.projector.K
    p_proj = np.stack([(x - Kp[0, 2]) / Kp[0, 0], (y - Kp[1, 2]) / Kp[1, 1], np.ones(50)], 1) * depth[:, None]
    p_cam = p_proj @ rig.R_cam_proj.T + rig.t_cam_proj
    n, d = rig.column_planes(x)
    np.testing.assert_allclose(np.einsum("ij,ij->i", n, p_cam), d, atol=1e-9)
    np.testing.assert_allclose(rig.project_to_projector(p_cam), np.stack([x, y], 1), atol=1e-9)
    # the projector centre lies on every plane; normals are unit with positive x
    np.testing.assert_allclose(n @ rig.projector_centre, d, atol=1e-9)
    assert np.all(n[:, 0] > 0)
    # on a wall at 650 mm, the plane of a larger column meets the camera's x axis further right
    n2, d2 = column_planes(Kp, rig.R_cam_proj, rig.t_cam_proj, np.sort(x))
    x_at_wall = (d2 - n2[:, 2] * 650.0) / n2[:, 0]
    assert np.all(np.diff(x_at_wall) > 0)


def test_paper_rig_scale():
    """One projector pixel covers about 0.43 camera pixels at 650 mm (the paper's geometry)."""
    rig = paper_rig()
    p = np.array([[0.0, 0.0, 650.0]])
    n, d = rig.column_planes(np.array([511.0, 512.0]))
    x_at_wall = (d - n[:, 2] * 650.0) / n[:, 0]           # points on the wall z = 650 mm, y = 0
    q = rig.camera.project(np.stack([x_at_wall, [0.0, 0.0], [650.0, 650.0]], 1))
    assert 0.38 < abs(q[1, 0] - q[0, 0]) < 0.48
    assert rig.camera.project(p)[0, 0] == pytest.approx(319.5)


def test_pattern_layout():
    spec = PatternSpec()
    assert spec.n_stripes == 128
    img = render_pattern(spec)
    assert img.shape == (768, 1024, 3) and img.dtype == np.uint8
    assert np.all(img[:, :, 0] == 0), "red must never be projected"
    labels = spec.stripe_labels()
    markers = spec.marker_indices()
    assert np.all(labels[markers] == CYAN)
    normal = np.setdiff1d(np.arange(spec.n_stripes), markers)
    assert np.all(labels[normal] == np.where(normal % 2 == 0, GREEN, BLUE))
    # marker neighbours share a colour, so a blurred green|blue boundary never looks like a marker
    assert np.all(labels[markers - 1] == labels[markers + 1])
    assert np.all(labels[markers - 1] != CYAN)
    gaps = np.diff(markers)
    assert set(gaps) <= set(MARKER_GAPS)
    pairs = list(zip(gaps[:-1], gaps[1:]))
    assert len(set(pairs)) == len(pairs), "three consecutive markers must fix the position"
    # stripe k's pixels: columns k*w .. k*w+w-1; boundary k at k*w - 0.5
    k = spec.stripe_of_column(np.array([0, 7, 8, 15.4, 15.6]))
    np.testing.assert_array_equal(k, [0, 0, 1, 1, 2])
    assert spec.boundary_column(1) == 7.5
    col = img[0, :, 1].astype(int) * 2 + (img[0, :, 2] > 0)
    for kk in range(spec.n_stripes):
        assert len(set(col[kk * 8:(kk + 1) * 8])) == 1


def test_pure_pattern_has_no_markers():
    spec = PatternSpec(markers=False)
    assert spec.marker_indices().size == 0
    img = render_pattern(spec)
    assert not np.any((img[:, :, 1] > 0) & (img[:, :, 2] > 0))


def test_pattern_rejects_bad_sizes():
    with pytest.raises(GBError):
        PatternSpec(width=8)
    with pytest.raises(GBError):
        PatternSpec(stripe_px=1)
