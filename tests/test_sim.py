"""The simulated rig: ground-truth self-consistency, image formation, presets, scenes."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from gbscan import sim
from gbscan.errors import GBError
from gbscan.io import write_png
from gbscan.pattern import BLUE, CYAN, GREEN, PatternSpec, render_pattern
from gbscan.rig import Rig

SPEC = PatternSpec()
PATTERN = render_pattern(SPEC)
WHITE = np.full((768, 1024, 3), 255, np.uint8)
SHARED = Path(__file__).resolve().parents[2] / "shared"


@pytest.fixture(scope="module")
def rig():
    return sim.paper_rig()


@pytest.fixture(scope="module")
def small_rig():
    r = sim.paper_rig()
    return Rig(r.camera.scaled(0.5), r.projector, r.R_cam_proj, r.t_cam_proj)


@pytest.fixture(scope="module")
def plane_clean(rig):
    scene = sim.scenes.plane(650, tilt_deg=(10, 25), albedo=0.6)
    return scene, sim.render(rig, scene, PATTERN, "clean", seed=1)


@pytest.fixture(scope="module")
def sphere_clean(rig):
    scene = sim.scenes.sphere((20, -10, 640), 110, albedo=(0.7, 0.6, 0.5), wall_mm=820)
    return scene, sim.render(rig, scene, PATTERN, "clean", seed=2)


def _camera_labels(img: np.ndarray) -> np.ndarray:
    g = img[..., 1].astype(float)
    b = img[..., 2].astype(float)
    lab = np.where(g > b, GREEN, BLUE)
    return np.where(np.minimum(g, b) > 0.6 * np.maximum(g, b), CYAN, lab)


def _stripe_consistency(r: sim.Render, margin_px: float = 2.0):
    x = r.proj_xy[..., 0].astype(np.float64)
    ok = r.lit & ~r.depth_edge & np.isfinite(x)
    # away from stripe boundaries (projector columns k*w - 0.5) and from the frame's sides
    frac = np.mod(x + 0.5, SPEC.stripe_px)
    ok &= (frac > margin_px) & (frac < SPEC.stripe_px - margin_px) & (x > 4) & (x < SPEC.width - 5)
    # the image must be bright enough to have a colour at all
    ok &= r.image[..., 1:].max(axis=-1) > 40
    truth = SPEC.stripe_labels()[np.clip(SPEC.stripe_of_column(x[ok]), 0, SPEC.n_stripes - 1)]
    return ok.sum(), np.mean(truth == _camera_labels(r.image)[ok])


def test_stripe_colour_matches_projector_pixel_plane(plane_clean, tmp_path):
    _, r = plane_clean
    write_png(tmp_path / "plane_clean.png", r.image)
    n, agree = _stripe_consistency(r)
    assert n > 50_000
    assert agree > 0.99


def test_stripe_colour_matches_projector_pixel_sphere(sphere_clean, tmp_path):
    _, r = sphere_clean
    write_png(tmp_path / "sphere_clean.png", r.image)
    n, agree = _stripe_consistency(r)
    assert n > 30_000
    assert agree > 0.99


def test_points_lie_on_the_surface_and_project_to_pixel_centres(rig, plane_clean, sphere_clean):
    cam = rig.camera
    q = cam.pixel_grid()
    scene, r = plane_clean
    pl = scene.objects[0]
    ok = np.isfinite(r.point[..., 0])
    assert ok.all()  # an unbounded plane fills the view
    p = r.point[ok].astype(np.float64)
    assert np.abs((p - pl.t) @ pl.n).max() < 1e-3  # mm (float32 storage)
    err = np.linalg.norm(cam.project(p) - q[ok], axis=-1)
    assert err.max() < 1e-3

    scene, r = sphere_clean
    sph = scene.objects[0]
    on = r.object_id == 0
    assert on.sum() > 20_000
    p = r.point[on].astype(np.float64)
    assert np.abs(np.linalg.norm(p - sph.t, axis=1) - sph.radius).max() < 1e-3
    err = np.linalg.norm(cam.project(p) - q[on], axis=-1)
    assert err.max() < 1e-3
    # the projector pixel is the true projection of the point
    xy = rig.project_to_projector(p)
    assert np.nanmax(np.abs(xy - r.proj_xy[on])) < 1e-2


def test_sphere_casts_projector_shadow_on_wall(rig, sphere_clean):
    scene, r = sphere_clean
    wall = r.object_id == 1
    inframe = np.all((r.proj_xy >= 0) & (r.proj_xy <= [1023, 767]), axis=-1)
    shadow = wall & inframe & ~r.lit
    assert shadow.sum() > 2000
    # every shadowed wall point's segment to the projector really crosses the sphere
    p = r.point[shadow].astype(np.float64)
    sph = scene.objects[0]
    d = rig.t_cam_proj - p
    t, _ = sph.intersect(p, d)
    assert np.mean(t < 1.0) > 0.99
    # the shadow is dark in the image, the lit wall is not
    grey = r.image.astype(float).mean(axis=-1)
    lit_wall = wall & r.lit & ~r.depth_edge
    assert np.median(grey[shadow & ~r.depth_edge]) < 0.3 * np.median(grey[lit_wall])
    # silhouette marked as depth edge, interior of the sphere not
    assert r.depth_edge[(r.object_id == 0)].mean() < 0.1
    assert r.depth_edge.sum() > 500


def test_step_has_depth_edge_and_shadow(small_rig):
    scene = sim.scenes.step(650, 60)
    r = sim.render(small_rig, scene, WHITE, "clean", seed=0)
    z = r.point[..., 2]
    assert np.nanmin(z) == pytest.approx(590, abs=1e-3) and np.nanmax(z) == pytest.approx(650, abs=1e-3)
    assert r.depth_edge.any()
    assert (np.isfinite(z) & ~r.lit).sum() > 50  # a shadow strip beside the step


def test_board_corners_where_the_camera_model_puts_them(rig, tmp_path):
    import cv2

    cols, rows, s = 9, 7, 20.0
    R = sim.scenes._rot_xy(-20, 25)
    t = np.array([-75.0, -50.0, 640.0])
    scene = sim.scenes.board(cols, rows, s, R, t)
    r = sim.render(rig, scene, WHITE, "typical", seed=4)
    write_png(tmp_path / "board_white.png", r.image)
    assert r.lit[r.object_id == 0].mean() > 0.999  # the whole board is inside the projector frame
    grey = cv2.cvtColor(r.image, cv2.COLOR_RGB2GRAY)
    found, corners = cv2.findChessboardCornersSB(grey, (cols, rows), flags=cv2.CALIB_CB_ACCURACY)
    assert found
    obj = sim.scenes.board_corners(cols, rows, s)
    truth = rig.camera.project(obj @ R.T + t)
    got = corners.reshape(-1, 2)
    if np.linalg.norm(got[0] - truth[0]) > np.linalg.norm(got[0] - truth[-1]):
        got = got[::-1]  # OpenCV may report the grid from the other end
    err = np.linalg.norm(got - truth, axis=1)
    assert np.mean(err) < 0.1
    assert np.max(err) < 0.25


def test_board_albedo_follows_the_convention():
    scene = sim.scenes.board(4, 3, 20.0)
    pl = scene.objects[0]
    # square [0,s]x[0,s] white, its neighbours black, margin white, outside the board nothing
    pts_local = np.array([[10, 10, 0], [30, 10, 0], [10, 30, 0], [-10, -10, 0], [-30, 10, 0], [90, 70, 0]], float)
    alb = pl.albedo_fn(pts_local)[:, 0]
    np.testing.assert_allclose(alb, [0.85, 0.05, 0.05, 0.85, 0.85, 0.85])
    o = np.zeros((2, 3))
    far = pl.R @ np.array([4 * 20 + 20 + 1.0, 0, 0]) + pl.t  # just beyond the margin
    near = pl.R @ np.array([4 * 20 + 20 - 1.0, 0, 0]) + pl.t
    d = np.stack([far, near]) / np.linalg.norm(np.stack([far, near]), axis=1, keepdims=True)
    hit = scene.intersect(o, d)
    assert not np.isfinite(hit.t[0]) and np.isfinite(hit.t[1])


def test_seeding_is_reproducible(small_rig):
    scene = sim.scenes.plane(600, (0, 10))
    a = sim.render(small_rig, scene, PATTERN, "typical", seed=7)
    b = sim.render(small_rig, scene, PATTERN, "typical", seed=7)
    c = sim.render(small_rig, scene, PATTERN, "typical", seed=8)
    np.testing.assert_array_equal(a.image, b.image)
    assert np.any(a.image != c.image)
    np.testing.assert_array_equal(a.point, c.point)  # ground truth does not depend on noise


@pytest.mark.parametrize("name, lo, hi", [("clean", 0.0, 0.6), ("typical", 1.0, 2.0), ("hard", 2.5, 6.0)])
def test_noise_statistics_match_the_documented_presets(small_rig, name, lo, hi):
    cond = dataclasses.replace(sim.preset(name), supersample=1, cam_sigma_px=0.0, motion_px=0.0)
    scene = sim.scenes.plane(650, albedo=0.5)
    a = sim.render(small_rig, scene, WHITE, cond, seed=1).image.astype(float)
    b = sim.render(small_rig, scene, WHITE, cond, seed=2).image.astype(float)
    patch = (slice(80, 160), slice(100, 220))
    sd = np.std(a[patch] - b[patch]) / np.sqrt(2)
    assert lo <= sd <= hi, f"{name}: noise {sd:.2f} DN"
    assert 80 < a[patch].mean() < 230


def test_crosstalk_and_inverse_square_are_exact_without_noise(small_rig):
    cond = dataclasses.replace(sim.preset("typical"), supersample=1, cam_sigma_px=0.0, full_well_e=0.0,
                               read_noise_dn=0.0, vignetting=0.0, ambient_rgb=(0, 0, 0), gamma=1.0)
    green = np.zeros((768, 1024, 3), np.uint8)
    green[..., 1] = 255
    r = sim.render(small_rig, sim.scenes.plane(650, albedo=0.5), green, cond, seed=0)
    c = np.asarray(cond.crosstalk)
    lin = r.linear[100:140, 140:180].reshape(-1, 3)
    np.testing.assert_allclose(lin[:, 2] / lin[:, 1], c[2, 1] / c[1, 1], rtol=1e-5)
    np.testing.assert_allclose(lin[:, 0] / lin[:, 1], c[0, 1] / c[1, 1], rtol=1e-5)
    # irradiance ~ cos(incidence) / distance^2 : compare with the exact value at each pixel
    p = r.point[100:140, 140:180].reshape(-1, 3).astype(np.float64)
    L = small_rig.t_cam_proj - p
    dist = np.linalg.norm(L, axis=1)
    expect = cond.exposure * 0.5 * c[1, 1] * (-L[:, 2] / dist) * (cond.ref_distance_mm / dist) ** 2
    np.testing.assert_allclose(lin[:, 1], expect, rtol=2e-3)


def test_encode_decode_roundtrip():
    x = np.linspace(0, 1, 101)
    np.testing.assert_allclose(sim.decode_dn(sim.encode(x, 2.2), 2.2), x, atol=1e-12)
    assert sim.encode(np.array([1.0]), 2.2)[0] == pytest.approx(255)


def test_head_scene_has_facial_relief(small_rig, tmp_path):
    scene = sim.scenes.head(650)
    r = sim.render(small_rig, scene, PATTERN, "typical", seed=0)
    write_png(tmp_path / "head.png", r.image)
    z = r.point[..., 2]
    ok = np.isfinite(z)
    assert z[ok].min() == pytest.approx(650, abs=2)
    assert 60 < np.ptp(z[ok]) < 200
    assert r.lit.sum() > 3000
    # the nose shadows part of the face from a projector on the right
    assert (ok & ~r.lit & (r.object_id == 0)).sum() > 100


def test_mesh_sphere_agrees_with_analytic_sphere():
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_sphere(radius=100.0, resolution=80)
    v = np.asarray(m.vertices) + [0, 0, 600]
    scene_m = sim.scenes.mesh(v, np.asarray(m.triangles), 0.5)
    scene_a = sim.scenes.sphere((0, 0, 600), 100, 0.5)
    d = np.random.default_rng(0).normal(size=(2000, 3)) * [0.08, 0.08, 0] + [0, 0, 1]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    hm = scene_m.intersect(np.zeros_like(d), d)
    ha = scene_a.intersect(np.zeros_like(d), d)
    both = np.isfinite(hm.t) & np.isfinite(ha.t)
    assert both.mean() > 0.8
    both &= np.arccos(d[:, 2]) < 0.9 * np.arcsin(100 / 600)  # away from the silhouette
    assert np.abs(hm.t[both] - ha.t[both]).max() < 0.1  # mm: chord error of the tessellation
    assert np.degrees(np.arccos(np.clip((hm.normal[both] * ha.normal[both]).sum(1), -1, 1))).max() < 3


def test_multi_object_and_combine(small_rig):
    scene = sim.scenes.multi_object() + sim.scenes.sphere((0, 0, 400), 10)
    r = sim.render(small_rig, scene, PATTERN, "hard", seed=0)
    ids = set(np.unique(r.object_id).tolist())
    assert {0, 1, 2, 3, 4, 5} <= ids
    assert r.image.shape == (240, 320, 3) and r.image.dtype == np.uint8


def test_bad_inputs_raise_gberror(small_rig):
    scene = sim.scenes.plane()
    with pytest.raises(GBError, match="projector frame"):
        sim.render(small_rig, scene, np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(GBError, match="preset"):
        sim.preset("sunny")
    with pytest.raises(GBError, match="albedo"):
        sim.scenes.plane(albedo=1.5)
    with pytest.raises(GBError, match="distance_mm"):
        sim.scenes.plane(distance_mm=-1)


def test_conditions_roundtrip():
    c = sim.preset("hard")
    assert sim.Conditions.from_dict(c.to_dict()) == c


def test_fran_face_renders_when_available(small_rig):
    path = SHARED / "data" / "fran_face" / "fran_cut_derived.obj"
    if not path.is_file():
        pytest.skip("../shared/data/fran_face not available")
    scene = sim.scenes.fran_face(path, distance_mm=600, subdivide=1)
    r = sim.render(small_rig, scene, PATTERN, "typical", seed=0)
    z = r.point[..., 2]
    assert np.nanmin(z) == pytest.approx(600, abs=1)
    assert r.lit.sum() > 2000


@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG", "GBRG"])
def test_bayer_mosaic_keeps_flat_colours(pattern):
    from gbscan.sim.render import camera_image

    cam = sim.paper_rig().camera.scaled(0.25)
    cond = dataclasses.replace(sim.preset("clean"), bayer=pattern, vignetting=0.0, cam_sigma_px=0.0)
    for c in range(3):
        lin = np.zeros((cam.height, cam.width, 3), np.float32)
        lin[..., c] = 0.6
        img = camera_image(lin, cam, cond, np.random.default_rng(0))[10:-10, 10:-10].reshape(-1, 3).astype(float)
        expect = np.zeros(3)
        expect[c] = sim.encode(np.array([0.6]), cond.gamma)[0]
        np.testing.assert_allclose(img.mean(axis=0), expect, atol=1.5)
    with pytest.raises(GBError, match="bayer"):
        dataclasses.replace(cond, bayer="RGBW")


def test_bayer_raw_is_the_mosaic_the_bayer_camera_demosaics():
    from gbscan.io import demosaic
    from gbscan.sim.render import camera_image

    cam = sim.paper_rig().camera.scaled(0.25)
    lin = np.random.default_rng(5).uniform(0.05, 0.9, (cam.height, cam.width, 3)).astype(np.float32)
    cond = dataclasses.replace(sim.preset("typical"), bayer="GRBG")
    rgb = camera_image(lin, cam, cond, np.random.default_rng(2))
    raw = camera_image(lin, cam, dataclasses.replace(cond, bayer_raw=True), np.random.default_rng(2))
    assert raw.shape == (cam.height, cam.width) and raw.dtype == np.uint8
    np.testing.assert_array_equal(demosaic(raw, "GRBG"), rgb)
    with pytest.raises(GBError, match="bayer_raw needs"):
        dataclasses.replace(sim.preset("typical"), bayer_raw=True)
    with pytest.raises(GBError, match="not stored as JPEG"):
        dataclasses.replace(cond, bayer_raw=True, jpeg_quality=90)


def test_jpeg_camera_is_the_lossless_frame_through_opencvs_encoder():
    """Conditions.jpeg_quality: the frame the same render gives losslessly, JPEG-encoded and decoded."""
    import cv2

    from gbscan.sim.render import camera_image

    cam = sim.paper_rig().camera.scaled(0.25)
    rng = np.random.default_rng(4)
    lin = rng.uniform(0.05, 0.9, (cam.height, cam.width, 3)).astype(np.float32)
    base = sim.preset("typical")
    lossless = camera_image(lin, cam, base, np.random.default_rng(1))
    for q, sampling, flag in ((90, "4:2:0", cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420),
                              (70, "4:4:4", cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444)):
        got = camera_image(lin, cam, dataclasses.replace(base, jpeg_quality=q, jpeg_sampling=sampling),
                           np.random.default_rng(1))
        ok, buf = cv2.imencode(".jpg", lossless[..., ::-1].copy(),
                               [cv2.IMWRITE_JPEG_QUALITY, q, cv2.IMWRITE_JPEG_SAMPLING_FACTOR, flag])
        np.testing.assert_array_equal(got, cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1])
        assert not np.array_equal(got, lossless)
    for bad in ({"jpeg_quality": 101}, {"jpeg_quality": -1}, {"jpeg_quality": 90.5}, {"jpeg_sampling": "4:1:1"}):
        with pytest.raises(GBError, match="jpeg"):
            dataclasses.replace(base, **bad)


def test_albedo_gain_scales_the_signal(small_rig):
    base = dataclasses.replace(sim.preset("clean"), supersample=1, full_well_e=0.0, read_noise_dn=0.0)
    dark = dataclasses.replace(base, albedo_gain_rgb=(0.8, 0.5, 0.25))
    scene = sim.scenes.plane(650, albedo=0.6)
    a = sim.render(small_rig, scene, WHITE, base).linear[100:140, 140:180]
    b = sim.render(small_rig, scene, WHITE, dark).linear[100:140, 140:180]
    np.testing.assert_allclose((b / a).reshape(-1, 3).mean(0), [0.8, 0.5, 0.25], rtol=1e-5)


def test_stripe_boundaries_are_unbiased(rig):
    """Where camera green = blue (noise-free, symmetric crosstalk) the true projector column is
    the boundary k*w - 0.5: the projector and camera pixel-centre conventions agree."""
    spec = PatternSpec(markers=False)
    cond = dataclasses.replace(sim.preset("clean"), full_well_e=0.0, read_noise_dn=0.0)
    r = sim.render(rig, sim.scenes.plane(650, (15, -25), albedo=0.6), render_pattern(spec), cond, seed=0)
    d = r.linear[..., 1] - r.linear[..., 2]
    x = r.proj_xy[..., 0].astype(np.float64)
    errs = []
    for v in range(100, 380, 5):
        row, xr = d[v], x[v]
        for u in np.flatnonzero((np.sign(row[:-1]) != np.sign(row[1:])) & r.lit[v, :-1] & r.lit[v, 1:]):
            f = row[u] / (row[u] - row[u + 1])
            xc = xr[u] + (xr[u + 1] - xr[u]) * f
            errs.append(xc - (np.round((xc + 0.5) / spec.stripe_px) * spec.stripe_px - 0.5))
    errs = np.array(errs)
    assert len(errs) > 3000
    assert abs(errs.mean()) < 0.03            # projector px: no convention offset
    assert np.sqrt(np.mean(errs**2)) < 0.25   # linear-crossing estimator on ~3.4 px stripes


def test_subsurface_scattering_lowers_stripe_contrast(small_rig):
    cond = dataclasses.replace(sim.preset("clean"), full_well_e=0.0, read_noise_dn=0.0)
    contrast = []
    for scatter in (0.0, 1.0):
        scene = sim.scenes.plane(650, albedo=0.6)
        scene.objects[0].scatter_mm = scatter
        r = sim.render(small_rig, scene, PATTERN, cond, seed=0)
        d = (r.linear[..., 1] - r.linear[..., 2])[r.lit & ~r.depth_edge]
        contrast.append(np.std(d))
    assert contrast[1] < 0.8 * contrast[0]


def test_incidence_deg_on_a_tilted_plane_and_a_sphere():
    """sim.incidence_deg against closed forms: a tilted plane (its normal from a least-squares fit
    of the true points) and a sphere (normal = radial direction), camera and projector angles to
    a hundredth of a degree (plane) away from the silhouette; NaN off the surface."""
    from gbscan import sim
    from gbscan.pattern import PatternSpec, render_pattern

    rig = sim.paper_rig()
    frame = render_pattern(PatternSpec())
    cond = sim.preset("clean")
    for scene, centre in ((sim.scenes.plane(650.0, (20.0, -35.0)), None),
                          (sim.scenes.sphere((10.0, -5.0, 640.0), 90.0), np.array([10.0, -5.0, 640.0]))):
        r = sim.render(rig, scene, frame, cond, seed=0)
        cam, proj = sim.incidence_deg(rig, r)
        P = r.point.astype(np.float64)
        has = np.isfinite(P[..., 2])
        if centre is None:
            X = P[has]
            n = np.linalg.svd(X - X.mean(0), full_matrices=False)[2][2]
            N = np.broadcast_to(n, P.shape)
        else:
            N = (P - centre) / np.linalg.norm(P - centre, axis=-1, keepdims=True)
        to_cam = -P / np.linalg.norm(P, axis=-1, keepdims=True)
        to_proj = rig.projector_centre - P
        to_proj /= np.linalg.norm(to_proj, axis=-1, keepdims=True)
        N = np.where(np.sum(N * to_cam, -1, keepdims=True) < 0, -N, N)
        want_c = np.degrees(np.arccos(np.clip(np.sum(N * to_cam, -1), -1, 1)))
        want_p = np.degrees(np.arccos(np.clip(np.sum(N * to_proj, -1), -1, 1)))
        inner = has & ~r.depth_edge & (want_c < 80)
        tol = 0.01 if centre is None else 0.5   # (float32 points; the sphere: differences of a curved surface)
        assert np.abs(cam - want_c)[inner].max() < tol and np.abs(proj - want_p)[inner].max() < tol
        assert np.isnan(cam[~has]).all() and np.isnan(proj[~has]).all()
        if centre is not None:
            assert np.nanmax(cam[inner]) > 70 and np.nanmin(cam[inner]) < 5


def test_column_errors_counts_half_a_stripe_or_more_as_wrong():
    """sim.column_errors, the decoder metric of the study scripts: reported pixels with a true
    column, wrong from half a stripe off; unreported or truthless pixels neither compared nor wrong."""
    truth = np.array([[100.0, 100.0, 100.0, np.nan, 100.0]])
    column = np.array([[100.5, 103.99, 96.0, 100.0, 140.0]], np.float32)
    valid = np.array([[True, True, True, True, False]])
    err, wrong = sim.column_errors(column, valid, truth, 8)
    np.testing.assert_allclose(err, [[0.5, 3.99, -4.0, 0.0, 0.0]], atol=1e-5)
    assert wrong.tolist() == [[False, False, True, False, False]]


# -- objects moving during the exposure ------------------------------------------------------------
FAST = dataclasses.replace(sim.preset("typical"), supersample=1)


def test_moved_scene_is_the_same_scene_moved(rig):
    """``scenes.moved``: the identity renders the frame bit for bit; a translated sphere is the
    sphere built at the shifted centre; a turned box is the box built turned; a texture moves with
    its object (a checker plane slid by one period looks the same, by half a period it does not)."""
    S = sim.scenes
    ball = S.sphere((0.0, 0.0, 650.0), 100.0, wall_mm=900.0)
    still = sim.render(rig, ball, PATTERN, FAST, seed=3)
    assert np.array_equal(sim.render(rig, S.moved(ball), PATTERN, FAST, seed=3).image, still.image)
    shifted = sim.render(rig, S.moved(ball, t_mm=(10.0, -5.0, 20.0)), PATTERN, FAST, seed=3)
    built = sim.render(rig, S.sphere((10.0, -5.0, 670.0), 100.0, wall_mm=920.0), PATTERN, FAST, seed=3)
    np.testing.assert_allclose(shifted.linear, built.linear, atol=1e-6)
    assert np.array_equal(shifted.lit, built.lit)

    box = S.Scene([S.Box(np.eye(3), [0.0, 0.0, 650.0], [60.0, 40.0, 30.0])])
    R = S.rotation_deg(about_x=10.0, about_y=25.0, about_z=-5.0)
    centre = np.array([20.0, 0.0, 640.0])
    turned = S.moved(box, R, t_mm=(5.0, 0.0, 0.0), about_mm=centre)
    ref = S.Scene([S.Box(R, R @ (np.array([0.0, 0.0, 650.0]) - centre) + centre + [5.0, 0.0, 0.0],
                         [60.0, 40.0, 30.0])])
    d = sim.render(rig, turned, PATTERN, FAST).point
    e = sim.render(rig, ref, PATTERN, FAST).point
    assert np.array_equal(np.isfinite(d[..., 2]), np.isfinite(e[..., 2]))
    np.testing.assert_allclose(d[np.isfinite(d)], e[np.isfinite(e)], atol=1e-3)

    chk = S.plane(650.0, albedo=S.checker(10.0))
    a = sim.render(rig, chk, PATTERN, FAST, seed=4).linear
    assert np.abs(sim.render(rig, S.moved(chk, t_mm=(20.0, 0.0, 0.0)), PATTERN, FAST, seed=4).linear - a).max() < 1e-6
    assert np.abs(sim.render(rig, S.moved(chk, t_mm=(10.0, 0.0, 0.0)), PATTERN, FAST, seed=4).linear - a).max() > 0.3


def test_moved_mesh_keeps_its_self_shadows(small_rig):
    """A moved mesh casts its shadows through the mesh's own occlusion test, as before moving."""
    S = sim.scenes
    head = S.head(650.0, resolution=120)
    still = sim.render(small_rig, head, PATTERN, FAST, seed=1)
    mesh = S.Scene([S.Mesh(head.objects[0].vertices, head.objects[0].triangles)]) \
        if isinstance(head.objects[0], S.Mesh) else head
    moved = sim.render(small_rig, S.moved(mesh), PATTERN, FAST, seed=1)
    ref = sim.render(small_rig, mesh, PATTERN, FAST, seed=1)
    assert np.array_equal(moved.lit, ref.lit) and np.array_equal(moved.image, ref.image)
    assert still.lit.sum() > 0 and (~still.lit & np.isfinite(still.point[..., 2])).sum() > 0   # shadows exist


def test_render_moving_one_pose_is_render_and_sliding_plane_keeps_its_stripes(rig):
    """One pose is :func:`sim.render`'s frame bit for bit.  The projector and the camera stand
    still, so a uniform plane sliding along itself keeps its stripes exactly where they were (and
    no pixel changes surface), while the same plane moving in depth shifts them."""
    S = sim.scenes
    plane = S.plane(650.0, tilt_deg=(0.0, 20.0))
    still = sim.render(rig, plane, PATTERN, FAST, seed=2)
    one = sim.render_moving(rig, [plane], PATTERN, FAST, seed=2)
    assert np.array_equal(one.image, still.image) and np.array_equal(one.linear, still.linear)
    assert still.motion_edge is None and not one.motion_edge.any()
    along = S.rotation_deg(about_y=20.0) @ [1.0, 0.0, 0.0]       # a direction in the tilted plane
    slide = [S.moved(plane, t_mm=along * s) for s in np.linspace(-4.0, 4.0, 5)]
    moving = sim.render_moving(rig, slide, PATTERN, FAST, seed=2)
    assert np.abs(moving.linear - still.linear).max() < 1e-6
    assert not moving.motion_edge.any()
    depth = sim.render_moving(rig, [S.moved(plane, t_mm=(0.0, 0.0, z)) for z in np.linspace(-3.0, 3.0, 5)],
                              PATTERN, FAST, seed=2)
    assert np.abs(depth.linear - still.linear).max() > 0.05
    np.testing.assert_array_equal(depth.proj_xy, still.proj_xy)   # the truth is mid-exposure


def test_decoder_on_a_plane_moving_in_depth_reads_the_mid_exposure_columns(rig):
    """A plane moving 6 mm toward the camera during the exposure: every reported pixel on its
    stripe, the columns those of mid-exposure (RMS under 0.1 projector px; the still frame's is
    0.05); 12 mm smears the stripes so far that a third of the plane is dropped, none wrong."""
    from gbscan.decode import decode

    S = sim.scenes
    plane = S.plane(650.0, tilt_deg=(0.0, 20.0))
    for travel, lo, hi in ((6.0, 0.97, 1.0), (12.0, 0.4, 0.85)):
        poses = [S.moved(plane, t_mm=(0.0, 0.0, z)) for z in np.linspace(-travel / 2, travel / 2, 5)]
        r = sim.render_moving(rig, poses, PATTERN, FAST, seed=2)
        sm = decode(r.image, SPEC)
        err, bad = sim.column_errors(sm.column, sm.valid, r.proj_xy[..., 0], SPEC.stripe_px)
        good = r.lit & ~r.depth_edge
        assert not (bad & good).any()
        assert lo <= (sm.valid & good).sum() / good.sum() <= hi
        if travel == 6.0:
            assert np.sqrt(np.mean(err[sm.valid & good] ** 2)) < 0.1


def test_motion_edge_marks_what_a_moving_silhouette_sweeps(small_rig):
    """A sphere sliding 8 mm sideways before a wall: ``motion_edge`` holds the band its silhouette
    sweeps (both sides, a few pixels wide) and nothing inside the sphere or on the far wall."""
    S = sim.scenes
    ball = S.sphere((0.0, 0.0, 650.0), 80.0)
    wall = S.plane(900.0)
    r = sim.render_moving(small_rig, [S.combine(S.moved(ball, t_mm=(x, 0.0, 0.0)), wall)
                                      for x in np.linspace(-4.0, 4.0, 5)], PATTERN, FAST, seed=0)
    H, W = r.object_id.shape
    row = r.motion_edge[H // 2]
    on_ball = np.flatnonzero(r.object_id[H // 2] == 0)
    assert row[on_ball[0]] and row[on_ball[-1]]                      # both silhouettes
    assert not row[on_ball[len(on_ball) // 2]] and not row[5] and not row[-5]
    assert 4 <= row[:W // 2].sum() <= 12     # the silhouette's sweep (8 mm: ~6 px here) and the dilation


def test_render_moving_refuses_bad_poses(small_rig):
    S = sim.scenes
    p = S.plane(650.0)
    for poses in ([], [p, p]):
        with pytest.raises(GBError, match="odd number of poses"):
            sim.render_moving(small_rig, poses, PATTERN, FAST)
    with pytest.raises(GBError, match="rotation"):
        S.moved(p, np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(GBError, match="translation"):
        S.moved(p, t_mm=(0.0, np.nan, 0.0))
    with pytest.raises(GBError, match="Scene"):
        S.moved("plane")
    with pytest.raises(GBError, match="odd number"):
        S.exposure_poses(p, (1.0, 0.0, 0.0), steps=4)
    assert len(S.exposure_poses(p, steps=1)) == 1


def test_gloss_reflects_the_light_colour_where_the_normal_bisects_camera_and_projector(small_rig):
    """``Conditions.specular`` / ``shininess`` (Blinn-Phong): without noise a glossy sphere is the
    matte one plus a highlight of the projector's own colour -- a red-tinted sphere under white
    light brightens all three channels alike in linear units -- strongest where the true normal
    bisects the directions to the camera and to the projector; gloss 0 is the matte render bit
    for bit."""
    cond = dataclasses.replace(sim.preset("typical"), supersample=1, cam_sigma_px=0.0, full_well_e=0.0,
                               read_noise_dn=0.0, vignetting=0.0, ambient_rgb=(0, 0, 0), gamma=1.0, exposure=0.3,
                               crosstalk=((1, 0, 0), (0, 1, 0), (0, 0, 1)))
    scene = sim.scenes.sphere((0.0, 0.0, 650.0), 100.0, albedo=(0.6, 0.2, 0.2))
    matte = sim.render(small_rig, scene, WHITE, cond, seed=0)
    np.testing.assert_array_equal(matte.image, sim.render(small_rig, scene, WHITE, dataclasses.replace(
        cond, specular=0.0, shininess=5.0), seed=0).image)
    gloss = sim.render(small_rig, scene, WHITE, dataclasses.replace(cond, specular=0.5, shininess=40.0), seed=0)
    add = gloss.image.astype(float) - matte.image.astype(float)
    assert add.min() >= 0 and add.max() > 30
    peak = add[..., 1] > 0.5 * add[..., 1].max()
    assert np.abs(add[peak][:, 0] - add[peak][:, 1]).max() <= 2 and np.abs(add[peak][:, 2] - add[peak][:, 1]).max() <= 2
    y, x = np.unravel_index(np.argmax(add[..., 1]), add.shape[:2])
    p = matte.point[y, x].astype(float)
    n = (p - np.array([0.0, 0.0, 650.0])) / 100.0
    to_proj = small_rig.t_cam_proj - p
    h = to_proj / np.linalg.norm(to_proj) - p / np.linalg.norm(p)
    assert np.dot(n, h / np.linalg.norm(h)) > 0.995
    with pytest.raises(GBError, match="specular"):
        sim.Conditions(specular=-0.1)
