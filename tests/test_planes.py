"""gbcal.planes: Gray-code boundaries, back-projection, plane fits, projector from planes."""
import numpy as np
import pytest

from gbcal import planes as pl
from gbcal.bundle import rodrigues
from gbcal.patterns import calibration_frames
from gbscan.errors import GBError
from gbscan.pattern import PatternSpec
from gbscan.rig import Projector, Rig, look_at, paper_rig

SPEC = PatternSpec(256, 64, 8, True)


def _frames_linear(spec, H=48, W=100, slope=2.3, x0=7.0, shear=0.05, albedo=None, ambient=10.0):
    """Camera images of a scene whose projector column is x(u, v) = x0 + slope*u + shear*v.

    Each camera pixel integrates a (defocused) footprint [x(u-1.25), x(u+1.25)] of the projector
    row, so near an edge a complementary pair's difference is linear in u over +-1.25 px and
    crosses zero exactly at the true boundary column: linear interpolation must be exact.
    """
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    lo = x0 + slope * (u - 1.25) + shear * v
    hi = lo + 2.5 * slope
    a = np.ones((H, W)) if albedo is None else albedo
    out = {}

    def integral(F, x):  # exact integral of the piecewise-constant row from -0.5 to x
        x = np.clip(x + 0.5, 0, spec.width - 1e-9)
        i = np.floor(x).astype(int)
        return F[i] + (F[i + 1] - F[i]) * (x - i)

    for name, f in calibration_frames(spec).items():
        row = f[0, :, :].astype(np.float64).mean(axis=1)     # (W_p,) grey of each projector column
        F = np.r_[0.0, np.cumsum(row)]
        img = (integral(F, hi) - integral(F, lo)) / (hi - lo) * 0.8 * a + ambient
        out[name] = img.astype(np.float32)
    return out, (lambda uu, vv: x0 + slope * uu + shear * vv)


def test_gray_boundaries_are_exact_on_box_filtered_frames():
    albedo = np.full((48, 100), 0.9)
    albedo[:, 60:] = 0.5                                     # an albedo step (kept away by the check)
    frames, x_of = _frames_linear(SPEC, albedo=albedo)
    dec = pl.gray_decode(frames, SPEC)
    v, u = np.mgrid[0:48, 0:100]
    truth = SPEC.stripe_of_column(x_of(u, v))
    ok = dec.index >= 0
    assert ok.mean() > 0.6
    np.testing.assert_array_equal(dec.index[ok], truth[ok])
    bs = pl.gray_boundaries(dec, SPEC)
    assert len(bs) > 48 * 24
    x = x_of(bs.uv[:, 0], bs.uv[:, 1])
    np.testing.assert_allclose(x, SPEC.boundary_column(bs.index), atol=1e-4)
    # no sample straddles the albedo step at u = 59.5
    assert not np.any((bs.uv[:, 0] > 58) & (bs.uv[:, 0] < 61))


def test_dark_pixels_are_masked_not_decoded():
    albedo = np.full((48, 100), 0.9)
    albedo[10:20, 30:50] = 0.01                              # a black square: almost no signal
    frames, _ = _frames_linear(SPEC, albedo=albedo)
    dec = pl.gray_decode(frames, SPEC)
    assert np.all(dec.index[10:20, 30:50] == -1)
    bs = pl.gray_boundaries(dec, SPEC)
    inside = (bs.uv[:, 1] >= 10) & (bs.uv[:, 1] < 20) & (bs.uv[:, 0] > 29) & (bs.uv[:, 0] < 50)
    assert not inside.any()


def test_gray_decode_names_missing_frames():
    frames, _ = _frames_linear(SPEC)
    del frames["gray_03_inv"]
    with pytest.raises(GBError, match="gray_03_inv"):
        pl.gray_decode(frames, SPEC)


def test_backproject_to_board_inverts_projection():
    rig = paper_rig()
    R = rodrigues(np.array([0.3, -0.2, 0.1]))
    t = np.array([-100.0, -60.0, 640.0])
    rng = np.random.default_rng(0)
    pb = np.c_[rng.uniform(-30, 270, 50), rng.uniform(-30, 180, 50), np.zeros(50)]
    q = rig.camera.project(pb @ R.T + t)
    pc, pb2 = pl.backproject_to_board(rig.camera, q, R, t)
    np.testing.assert_allclose(pb2, pb, atol=1e-6)
    np.testing.assert_allclose(pc, pb @ R.T + t, atol=1e-6)
    assert pl.on_board(pb2, 9, 7, 30.0).sum() == pl.on_board(pb, 9, 7, 30.0).sum()


def test_fit_plane_rejects_outliers():
    rng = np.random.default_rng(1)
    n_true = np.array([0.9, 0.1, -0.3])
    n_true /= np.linalg.norm(n_true)
    a = np.cross(n_true, [0, 1, 0]); a /= np.linalg.norm(a)
    b = np.cross(n_true, a)
    p = 150.0 * n_true + rng.uniform(-200, 200, (400, 1)) * a + rng.uniform(-200, 200, (400, 1)) * b
    p += rng.normal(0, 0.05, (400, 1)) * n_true
    bad = rng.choice(400, 40, replace=False)
    p[bad] += rng.uniform(5, 30, (40, 1)) * n_true
    n, d, keep, _ = pl.fit_plane(p)
    assert np.degrees(np.arccos(min(1.0, n @ n_true))) < 0.02
    assert abs(d - 150.0) < 0.02
    assert not keep[bad].any() and keep.sum() >= 355


def test_fit_planes_skips_collinear_and_sparse_indices():
    rng = np.random.default_rng(2)
    line = np.c_[np.linspace(0, 100, 50), np.zeros(50), np.full(50, 600.0)]
    plane = np.c_[rng.uniform(0, 100, 60), rng.uniform(0, 100, 60), np.full(60, 600.0)] @ rodrigues([0, 0.4, 0]).T
    pts = np.r_[line, plane, plane[:5]]
    idx = np.r_[np.full(50, 3), np.full(60, 4), np.full(5, 9)]
    fit = pl.fit_planes(pts, idx)
    assert list(fit.index) == [4]
    assert fit.sample_inlier[50:110].all() and not fit.sample_inlier[:50].any()


@pytest.mark.parametrize("rig", [paper_rig(), Rig(paper_rig().camera,
                                                   Projector(800, 600, [[1500.0, 0, 390.0], [0, 1500.0, 300.0], [0, 0, 1]]),
                                                   look_at(np.array([-150.0, 30.0, 20.0]), np.array([20.0, -10.0, 700.0])),
                                                   np.array([-150.0, 30.0, 20.0]))])
def test_projector_from_planes_recovers_the_planes_exactly(rig):
    W = rig.projector.width
    x = np.arange(1, W // 8) * 8 - 0.5
    n, d = rig.column_planes(x)
    est = pl.projector_from_planes(x, n, d, projector_size=(W, rig.projector.height),
                                   scene_point=np.array([0.0, 0.0, 650.0]), camera=rig.camera)
    n2, d2 = est.column_planes(x)
    np.testing.assert_allclose(n2, n, atol=1e-9)
    np.testing.assert_allclose(d2, d, atol=1e-7)
    assert est.projector.K[0, 0] == pytest.approx(rig.projector.K[0, 0], rel=1e-9)
    assert est.projector.K[0, 2] == pytest.approx(rig.projector.K[0, 2], abs=1e-6)
    # the centre lies on the true projector's y axis (its position along it is a gauge)
    off = rig.to_projector(est.t_cam_proj)
    assert abs(off[0]) < 1e-6 and abs(off[2]) < 1e-6


def test_projector_from_planes_needs_planes():
    rig = paper_rig()
    n, d = rig.column_planes(np.array([7.5, 15.5]))
    with pytest.raises(GBError, match="at least 3 light planes"):
        pl.projector_from_planes(np.array([7.5, 15.5]), n, d, projector_size=(1024, 768),
                                 scene_point=np.array([0, 0, 650.0]), camera=rig.camera)
