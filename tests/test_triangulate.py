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


# -- whole frames: GridTriangulator (vectorised pencil kernel, general compiled kernel) -----------
def _random_rig(rng, width=160, height=120):
    """A random camera (distorted) and pinhole projector looking at a point 400-1500 mm away."""
    from gbscan.camera import Camera
    from gbscan.rig import Projector, Rig, look_at

    f = 200 * rng.uniform(0.8, 1.2)
    cam = Camera(width, height, [[f, 0, (width - 1) / 2 + rng.normal(0, 3)], [0, f * rng.uniform(0.95, 1.05),
                                                                              (height - 1) / 2], [0, 0, 1]],
                 [rng.normal(0, 0.1), rng.normal(0, 0.05), rng.normal(0, 1e-3), rng.normal(0, 1e-3), 0.0])
    dist = rng.uniform(400, 1500)
    eye = np.array([rng.uniform(100, 400) * rng.choice([-1, 1]), rng.normal(0, 20), rng.normal(0, 20)])
    proj = Projector(1024, 768, [[rng.uniform(1200, 2500), 0, 511.5], [0, 1800, 383.5], [0, 0, 1]])
    return Rig(cam, proj, look_at(eye, np.array([0.0, 0.0, dist])), eye), dist


def _f32_close(out, ref):
    """Points equal to the float64 reference rounded to float32: within one float32 rounding
    (2**-24 relative; 3e-5 mm at 650 mm, 1.2e-4 mm at 2 m), and NaN exactly where it is NaN."""
    fin = np.isfinite(ref[..., 2])
    assert np.array_equal(np.isfinite(out).all(-1), fin) and np.array_equal(np.isnan(out).any(-1), ~fin)
    err = np.abs(out[fin].astype(np.float64) - ref[fin])
    assert np.all(err <= 2.0 ** -24 * np.abs(ref[fin]) + 1e-9), err.max()
    return fin


@pytest.mark.parametrize("seed", range(4))
def test_grid_triangulator_matches_the_float64_reference(seed):
    """Random rigs and surfaces: the pencil kernel on consistent columns, the general kernel on
    columns drawn at random (some rays graze their planes there), both the float64 reference
    rounded to float32."""
    from gbscan.triangulate import GridTriangulator

    rng = np.random.default_rng(seed)
    rig, dist = _random_rig(rng)
    table = PlaneTable.from_calibration(calibration_from_rig(rig, PatternSpec()))
    g = GridTriangulator(rig.camera, table)
    assert g.pencil is not None
    rays = rig.camera.pixel_rays()
    # a random depth per pixel, and the true projector column of that point
    depth = rng.uniform(0.7, 1.3, rays.shape[:2]) * dist
    col = rig.project_to_projector(rays / rays[..., 2:] * depth[..., None])[..., 0].astype(np.float32)
    col[rng.random(col.shape) < 0.1] = np.nan
    out = g(col)
    assert g.last_path == "pencil"
    fin = _f32_close(out, triangulate(rays, col, table))
    assert fin.mean() > 0.5
    np.testing.assert_allclose(out[fin, 2], depth[fin], rtol=1e-5)  # and the surface comes back
    wild = rng.uniform(table.column[0] - 12, table.column[-1] + 12, col.shape)  # float64 columns
    wild[rng.random(col.shape) < 0.1] = np.nan
    buf = np.full(out.shape, 7.0, np.float32)
    assert g(wild, out=buf) is buf
    assert g.last_path == "general"
    _f32_close(buf, triangulate(rays, wild, table))


def test_grid_triangulator_on_planes_that_are_not_a_pencil(rig, calib):
    """Planes fitted one by one (perturbed): no pencil, the general kernel, still the reference."""
    from gbscan.triangulate import GridTriangulator

    rng = np.random.default_rng(5)
    n = calib.plane_normal + rng.normal(0, 1e-4, calib.plane_normal.shape)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    table = PlaneTable.from_arrays(calib.plane_column, n, calib.plane_d + rng.normal(0, 0.01, calib.plane_d.shape))
    assert table.pencil() is None
    assert PlaneTable.from_calibration(calib).pencil().fit_error[0] < 1e-12
    _, col, _ = truth(rig, spheres=[((30.0, -20.0, 600.0), 90.0)], planes=[tilted_plane(700.0)])
    g = GridTriangulator(rig.camera, table)
    out = g(col)
    assert g.last_path == "general"
    _f32_close(out, triangulate(pixel_rays(rig.camera), col, table))
    with pytest.raises(GBError, match="column map"):
        g(col[:, :-1])
    with pytest.raises(GBError, match="out must be"):
        g(col, out=np.empty(out.shape, np.float64))


def test_grid_triangulator_with_two_planes_interpolates_linearly_as_the_reference(rig, calib):
    from gbscan.triangulate import GridTriangulator

    two = PlaneTable.from_arrays(calib.plane_column[60:62], calib.plane_normal[60:62], calib.plane_d[60:62])
    _, col, _ = truth(rig, planes=[tilted_plane(650.0)])
    g = GridTriangulator(rig.camera, two)
    out = g(col)
    assert g.last_path == "linear"
    fin = _f32_close(out, triangulate(pixel_rays(rig.camera), col, two))
    assert fin.sum() > 100


def test_pencil_fit_needs_three_planes_and_rejects_small_departures(calib):
    two = PlaneTable.from_arrays(calib.plane_column[:2], calib.plane_normal[:2], calib.plane_d[:2])
    assert two.pencil() is None
    d = calib.plane_d.copy()
    d[40] += 1e-6  # mm: a plane a micrometre off the pencil is not the pencil's
    assert PlaneTable.from_arrays(calib.plane_column, calib.plane_normal, d).pencil() is None
    p = PlaneTable.from_calibration(calib).pencil()
    x = calib.plane_column[[3, 50, 90]]
    N = p.a + (x - p.xc)[:, None] * p.b
    scale = np.linalg.norm(N, axis=1)
    np.testing.assert_allclose(N / scale[:, None], calib.plane_normal[[3, 50, 90]], atol=1e-12)
    np.testing.assert_allclose((p.ad + (x - p.xc) * p.bd) / scale, calib.plane_d[[3, 50, 90]], atol=1e-9)


@pytest.mark.parametrize("dist", [(-0.12, 0.09, 0.0005, -0.0003, 0.0), (0.0,) * 5,
                                  (-0.35, 0.15, 0.002, -0.001, -0.03), (-0.6, 0.9, 0.01, -0.01, -1.5)])
def test_per_pixel_rays_are_the_camera_models(rig, dist):
    """GridTriangulator's rays (mx, my, 1) are Camera.normalize of the pixel centres."""
    from gbscan import geomkernels as gk
    from gbscan.camera import Camera

    cam = Camera(200, 150, rig.camera.K * [[0.3125], [0.3125], [1]], dist)
    mx, my = np.empty(200 * 150), np.empty(200 * 150)
    n_slow = gk.undistort_grid(200, 150, cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2], cam.K[0, 1],
                               cam.dist, mx, my)
    ref = cam.normalize(cam.pixel_grid()).reshape(-1, 2)
    np.testing.assert_allclose(mx, ref[:, 0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(my, ref[:, 1], rtol=0, atol=1e-12)
    assert (n_slow > 0) == (dist[0] == -0.6)  # only the extreme lens takes the redo path (per-pixel Newton)


# -- a point's predicted error from its column's (point_sigma_mm) -------------------------------------
def test_point_sigma_is_the_pencils_closed_form_derivative_times_the_column_error(rig, calib):
    """Along a ray ``p = z m`` the pencil's plane of column x holds ``z = (ad + t bd) / (a.m + t b.m)``
    (t = x - xc), so ``|dp/dx| = |m| |bd a.m - ad b.m| / (a.m + t b.m)^2``: the central difference
    agrees to 1e-3 (the float32 points' rounding, ~6e-5 mm at 650 mm, over a 0.5 px step that moves
    them ~0.4 mm), the one-sided one at the calibrated range's end to 1e-2 (its error is first order
    in the step), and the error scales with the column's."""
    from gbscan.triangulate import GridTriangulator, point_sigma_mm

    table = PlaneTable.from_calibration(calib)
    g = GridTriangulator(rig.camera, table)
    pen = g.pencil
    _, col, _ = truth(rig, spheres=[((30.0, -20.0, 600.0), 90.0)], planes=[tilted_plane(700.0)])
    H, W = col.shape
    m = np.stack([g.mx, g.my, np.ones_like(g.mx)], axis=1).reshape(H, W, 3)
    am, bm = m @ pen.a, m @ pen.b

    def closed_form(x):
        return np.linalg.norm(m, axis=2) * np.abs(pen.bd * am - pen.ad * bm) / (am + (x - pen.xc) * bm) ** 2

    rng = np.random.default_rng(0)
    sig = np.where(np.isfinite(col), rng.uniform(0.02, 0.5, col.shape), np.nan).astype(np.float32)
    out = point_sigma_mm(g, col, sig)
    fin = np.isfinite(col)
    assert fin.sum() > 50000 and np.array_equal(np.isfinite(out), fin)
    want = closed_form(col.astype(np.float64)) * sig
    np.testing.assert_allclose(out[fin], want[fin], rtol=1e-3)
    assert 0.2 < float(np.median(out[fin] / sig[fin])) < 2.0    # mm per projector px at ~650 mm: sane scale
    # twice the column error, twice the point's; NaN error -> NaN
    sig2 = sig.copy()
    sig2[100, 300] = np.nan
    out2 = point_sigma_mm(g, col, 2 * sig2)
    both = fin & np.isfinite(sig2)
    np.testing.assert_allclose(out2[both], 2 * out[both], rtol=1e-6)
    assert np.isnan(out2[100, 300])
    # at the last calibrated plane the step beyond the extrapolation limit has no point: one-sided
    x_end = np.float32(table.column[-1] + g.max_extra_px - 0.1)
    near = np.isfinite(col) & (np.abs(col - x_end) < 4)       # pixels that see the pattern's end
    edge = np.where(near, x_end, np.float32(np.nan)).astype(np.float32)
    one = point_sigma_mm(g, edge, np.where(near, np.float32(1.0), np.nan).astype(np.float32))
    assert near.sum() > 100 and np.isnan(g(edge + 0.25)[near, 2]).all()   # the upper step has no point
    np.testing.assert_allclose(one[near], closed_form(np.float64(x_end))[near], rtol=1e-2)
    with pytest.raises(GBError, match="column_sigma"):
        point_sigma_mm(g, col, sig[:, :-1])
    with pytest.raises(GBError, match="step_px"):
        point_sigma_mm(g, col, sig, step_px=0)
