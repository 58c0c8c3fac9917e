"""Triangulation: rays x light planes, exact for a pinhole projector from the planes alone."""
import numpy as np
import pytest

from gbscan.calibfile import Calibration, calibration_from_rig
from gbscan.errors import GBError
from gbscan.pattern import PatternSpec
from gbscan.rig import paper_rig
from gbscan.triangulate import PlaneTable, ray_depths, triangulate


# -- analytic ground truth (shared with the other scan-pipeline tests) ---------------------------
def cast(rays, spheres=(), planes=()):
    """Distance along unit rays (H, W, 3) to the nearest of spheres [(centre, radius)] and planes
    [(normal, d)] (n . p = d); returns (s (H, W) with inf for no hit, object id (H, W), -1 none)."""
    s = np.full(rays.shape[:2], np.inf)
    oid = np.full(rays.shape[:2], -1)
    k = 0
    for c, R in spheres:
        c = np.asarray(c, float)
        b = rays @ c
        disc = b * b - (c @ c - R * R)
        with np.errstate(invalid="ignore"):
            hit = np.where(disc > 0, b - np.sqrt(disc), np.inf)
        hit[hit <= 0] = np.inf
        closer = hit < s
        s[closer], oid[closer] = hit[closer], k
        k += 1
    for n, d in planes:
        with np.errstate(divide="ignore"):
            hit = d / (rays @ np.asarray(n, float))
        hit[~(hit > 0)] = np.inf
        closer = hit < s
        s[closer], oid[closer] = hit[closer], k
        k += 1
    return s, oid


_RAYS = {}


def pixel_rays(camera):
    """Camera.pixel_rays() cached per camera (the distortion inversion is the slow part)."""
    if id(camera) not in _RAYS:
        _RAYS[id(camera)] = (camera, camera.pixel_rays())
    return _RAYS[id(camera)][1]


def truth(rig, spheres=(), planes=(), pattern=PatternSpec()):
    """Ground truth of an analytic scene seen by ``rig``: points (H, W, 3) float64 (NaN where no
    surface or outside the projector's image), true projector column (H, W), object id (H, W)."""
    rays = pixel_rays(rig.camera)
    s, oid = cast(rays, spheres, planes)
    p = rays * np.where(np.isfinite(s), s, np.nan)[..., None]
    xy = rig.project_to_projector(p)
    inside = (xy[..., 0] >= 0) & (xy[..., 0] <= pattern.width - 1) & (xy[..., 1] >= 0) & \
        (xy[..., 1] <= pattern.height - 1)
    p[~inside] = np.nan
    col = np.where(inside, xy[..., 0], np.nan)
    return p, col, np.where(inside, oid, -1)


def tilted_plane(distance_mm=650.0, normal=(0.3, -0.2, -1.0)):
    n = np.asarray(normal, float)
    n /= np.linalg.norm(n)
    return n, float(n @ [0.0, 0.0, distance_mm])


@pytest.fixture(scope="module")
def rig():
    return paper_rig()


@pytest.fixture(scope="module")
def calib(rig):
    return calibration_from_rig(rig, PatternSpec())


# -- exactness ----------------------------------------------------------------------------------
@pytest.mark.parametrize("compiled", [True, False])
def test_exact_on_plane_and_sphere(rig, calib, compiled):
    p, col, _ = truth(rig, spheres=[((30.0, -20.0, 600.0), 90.0)], planes=[tilted_plane(700.0)])
    xyz = triangulate(pixel_rays(rig.camera), col, PlaneTable.from_calibration(calib), compiled=compiled)
    ok = np.isfinite(col)
    assert ok.mean() > 0.3
    assert np.array_equal(np.isfinite(xyz[..., 2]), ok)
    assert np.max(np.abs(xyz[ok] - p[ok])) < 1e-6  # mm, on every pixel


def test_exact_from_sparse_planes_where_linear_interpolation_is_not(rig, calib):
    """Keep every 4th plane: the cross ratio stays exact, linear depth interpolation does not."""
    keep = slice(None, None, 4)
    table = PlaneTable.from_arrays(calib.plane_column[keep], calib.plane_normal[keep], calib.plane_d[keep])
    p, col, _ = truth(rig, planes=[tilted_plane(650.0)])
    ok = np.isfinite(col) & (col > table.column[0]) & (col < table.column[-1])
    xyz = triangulate(pixel_rays(rig.camera), np.where(ok, col, np.nan), table)
    assert np.max(np.abs(xyz[ok] - p[ok])) < 1e-6
    two = PlaneTable.from_arrays(table.column[[10, 11]], table.normal[[10, 11]], table.d[[10, 11]])
    sel = ok & (col > two.column[0]) & (col < two.column[1])
    lin = triangulate(pixel_rays(rig.camera), np.where(sel, col, np.nan), two)  # 2 planes: linear
    assert sel.sum() > 100 and np.max(np.abs(lin[sel] - p[sel])) > 1e-3


def test_compiled_matches_numpy_reference(rig, calib):
    rng = np.random.default_rng(0)
    rays = pixel_rays(rig.camera)[::7, ::5]
    col = rng.uniform(-20, 1040, rays.shape[:2])
    col[rng.random(col.shape) < 0.1] = np.nan
    table = PlaneTable.from_calibration(calib)
    a = triangulate(rays, col, table)
    b = triangulate(rays, col, table, compiled=False)
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    np.testing.assert_allclose(a[np.isfinite(a)], b[np.isfinite(b)], rtol=1e-12, atol=1e-9)


def test_float32_columns_give_the_float64_result(rig, calib):
    """The decoder's float32 columns go to the kernel as they are (promoted per pixel)."""
    rng = np.random.default_rng(1)
    rays = pixel_rays(rig.camera)[::3, ::3]
    col = rng.uniform(-20, 1040, rays.shape[:2]).astype(np.float32)
    col[rng.random(col.shape) < 0.2] = np.nan
    table = PlaneTable.from_calibration(calib)
    a = triangulate(rays, col, table)
    b = triangulate(rays, col.astype(np.float64), table)
    np.testing.assert_array_equal(a, b)
    out = np.empty(rays.shape, np.float32)
    triangulate(rays, col, table, out=out)
    np.testing.assert_array_equal(out, a.astype(np.float32))


def test_points_reproject_to_their_pixels_through_distortion(rig, calib):
    _, col, _ = truth(rig, planes=[tilted_plane(650.0)])
    xyz = triangulate(pixel_rays(rig.camera), col, PlaneTable.from_calibration(calib))
    ok = np.isfinite(xyz[..., 2])
    q = rig.camera.project(xyz[ok])
    assert np.max(np.abs(q - rig.camera.pixel_grid()[ok])) < 1e-6
    assert abs(rig.camera.dist[0]) > 0.05  # the lens really is distorted


def test_works_from_camera_and_planes_alone(rig, calib):
    bare = Calibration(calib.camera, calib.plane_index, calib.plane_column, calib.plane_normal, calib.plane_d)
    assert bare.projector is None and bare.pattern is None
    p, col, _ = truth(rig, planes=[tilted_plane(800.0, (0.0, 0.3, -1.0))])
    xyz = triangulate(pixel_rays(rig.camera), col, PlaneTable.from_calibration(bare))
    ok = np.isfinite(col)
    assert np.max(np.abs(xyz[ok] - p[ok])) < 1e-6


# -- failure modes ---------------------------------------------------------------------------------
def test_rays_parallel_to_planes_give_nan_not_huge_values(calib):
    table = PlaneTable.from_calibration(calib)
    k = 60
    n = table.normal[k]
    along = np.cross(n, [0.0, 1.0, 0.0])
    along /= np.linalg.norm(along) * np.sign(along[2])  # forward, inside plane k
    tilt = [np.radians(a) for a in (0.0, 0.5, 1.5, 5.0)]
    rays = np.array([np.cos(t) * along + np.sin(t) * n for t in tilt])
    s = ray_depths(rays, np.full(4, table.column[k] + 1.0), table, min_angle_deg=2.0)
    assert np.all(np.isnan(s[:3]))
    x = triangulate(rays, np.full(4, table.column[k] + 1.0), table, min_angle_deg=2.0)
    assert np.all(np.isnan(x[:3])) and not np.any(np.abs(x[np.isfinite(x)]) > 1e5)


def test_columns_outside_the_calibrated_range_and_nan_give_nan(rig, calib):
    table = PlaneTable.from_calibration(calib)
    rays = pixel_rays(rig.camera)[240, 300:305]
    col = np.array([np.nan, table.column[0] - 3 * table.spacing_px, table.column[-1] + 3 * table.spacing_px,
                    table.column[0] - 0.5 * table.spacing_px, 500.0])
    x = triangulate(rays, col, table)
    assert np.isnan(x[:3]).all() and np.isfinite(x[3:]).all()


def test_bad_inputs_raise_gberror(calib):
    with pytest.raises(GBError, match="at least 2 light planes"):
        PlaneTable.from_arrays(calib.plane_column[:1], calib.plane_normal[:1], calib.plane_d[:1])
    with pytest.raises(GBError, match="share one projector column"):
        PlaneTable.from_arrays([1.0, 1.0], calib.plane_normal[:2], calib.plane_d[:2])
    with pytest.raises(GBError, match="unit vectors"):
        PlaneTable.from_arrays(calib.plane_column[:2], 2 * calib.plane_normal[:2], calib.plane_d[:2])
    table = PlaneTable.from_calibration(calib)
    with pytest.raises(GBError, match="must be"):
        triangulate(np.zeros((4, 5, 3)), np.zeros((4, 4)), table)


def test_pixel_rays_invert_the_camera_model(rig):
    from gbscan.camera import Camera

    for dist in (rig.camera.dist, np.zeros(5), [-0.35, 0.15, 0.002, -0.001, -0.03]):
        cam = Camera(160, 120, rig.camera.K / [[4], [4], [1]], dist)
        rays = cam.pixel_rays()
        np.testing.assert_allclose(np.linalg.norm(rays, axis=-1), 1.0, rtol=0, atol=1e-12)
        xn = rays[..., :2] / rays[..., 2:]
        np.testing.assert_allclose(cam.distort(xn), _distorted(cam), rtol=0, atol=1e-12)


def _distorted(cam):
    """Distorted normalised coordinates of every pixel centre (the target the rays must hit)."""
    q = cam.pixel_grid()
    y = (q[..., 1] - cam.K[1, 2]) / cam.K[1, 1]
    return np.stack([(q[..., 0] - cam.K[0, 2] - cam.K[0, 1] * y) / cam.K[0, 0], y], axis=-1)
