"""gbcal.bundle: rotations, undistortion, the structured Jacobian, recovery of a known rig."""
import numpy as np
import pytest

from gbcal.bundle import BundleData, BundleProblem, refine, rodrigues, rotation_vector, synthetic_data
from gbscan.camera import Camera, undistort_normalized
from gbscan.errors import GBError
from gbscan.rig import Projector, Rig, paper_rig

COLS, ROWS, SQ = 9, 7, 30.0


def _poses(n, seed=1):
    rng = np.random.default_rng(seed)
    rv, tv = [], []
    for _ in range(n):
        R = rodrigues(np.deg2rad([rng.uniform(-30, 30), rng.uniform(-30, 30), rng.uniform(-10, 10)]))
        c = np.array([rng.uniform(-50, 50), rng.uniform(-40, 40), rng.uniform(550, 750)])
        rv.append(rotation_vector(R))
        tv.append(c - R @ np.array([(COLS - 1) * SQ / 2, (ROWS - 1) * SQ / 2, 0]))
    return np.array(rv), np.array(tv)


def _perturbed(rig, seed=3):
    """A start like the real one: camera a little off, projector a few mm / mrad / px off."""
    rng = np.random.default_rng(seed)
    K = rig.camera.K.copy()
    K[0, 0] *= 1.005
    K[1, 1] *= 0.996
    K[0, 2] += 2.0
    K[1, 2] -= 1.5
    cam0 = Camera(rig.camera.width, rig.camera.height, K, rig.camera.dist * 0.9)
    Kp = rig.projector.K.copy()
    Kp[0, 0] *= 1.01
    Kp[0, 2] += 4.0
    R0 = rodrigues(rotation_vector(rig.R_cam_proj) + rng.normal(0, 0.005, 3))
    return cam0, Rig(cam0, Projector(rig.projector.width, rig.projector.height, Kp), R0,
                     rig.t_cam_proj + rng.normal(0, 3, 3))


def _normal_error_deg(a: Rig, b: Rig, cols):
    n1, _ = a.column_planes(cols)
    n2, _ = b.column_planes(cols)
    return float(np.degrees(np.arccos(np.clip(np.sum(n1 * n2, axis=1), -1, 1))).max())


def test_rodrigues_matches_opencv():
    import cv2

    rng = np.random.default_rng(0)
    for r in [np.zeros(3), np.array([1e-10, 0, 0]), *rng.normal(0, 1, (5, 3))]:
        np.testing.assert_allclose(rodrigues(r), cv2.Rodrigues(r)[0], atol=1e-9)  # OpenCV rounds tiny angles to 0
        np.testing.assert_allclose(rodrigues(rotation_vector(rodrigues(r))), rodrigues(r), atol=1e-9)


def test_warm_started_newton_inverts_distortion():
    cam = paper_rig().camera
    q = cam.pixel_grid()[::37, ::41].reshape(-1, 2)
    x_ref = cam.normalize(q)
    target = (q - cam.K[:2, 2]) / np.diag(cam.K)[:2]
    x = undistort_normalized(target, cam.dist, x_ref + 1e-6, iterations=2, tol=None)
    np.testing.assert_allclose(x, x_ref, atol=1e-13)


@pytest.mark.parametrize("with_prior", [False, True])
def test_structured_jacobian_matches_finite_differences(with_prior):
    from scipy.optimize._numdiff import approx_derivative

    rig = paper_rig()
    rv, tv = _poses(3)
    cols = np.arange(5, 125, 12) * 8 - 0.5
    data = synthetic_data(rig, rv, tv, cols=COLS, rows=ROWS, square_mm=SQ, columns=cols, samples_per_line=4)
    cam0, rig0 = _perturbed(rig)
    K = rig.camera.K
    prior = (np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], rig.camera.dist], np.r_[0.1, 0.1, 0.2, 0.2, [1e-3] * 5])
    prob = BundleProblem(data, cam0, rv + 0.01, tv + 1.0, rig0, dist_model="k1k2p1p2k3",
                         camera_prior=prior if with_prior else None, prior_scale_px=0.04)
    assert prob.m == 2 * prob.Nc + prob.Ns + (prob.n_cam if with_prior else 0)
    th = prob.theta0
    J_fd = approx_derivative(prob.residuals, th, method="3-point")
    scale = np.abs(J_fd).max(axis=0) + 1e-12
    Jc = prob.jacobian(th, central=True).toarray()
    assert np.max(np.abs(Jc - J_fd) / scale) < 1e-6
    J = prob.jacobian(th).toarray()  # forward differences: what the solver uses
    assert np.max(np.abs(J - J_fd) / scale) < 1e-4
    # the structure: a residual never depends on another pose's parameters
    pose_cols = J[:prob.m_data, prob.i_pose:prob.i_proj].reshape(prob.m_data, prob.P, 6)
    other = np.ones((prob.m_data, prob.P), bool)
    other[np.arange(prob.m_data), prob.row_pose] = False
    assert np.all(pose_cols[other] == 0)
    assert np.all(J[:2 * prob.Nc, prob.i_proj:] == 0)  # corners do not see the projector
    if with_prior:  # a prior row sees its own camera unknown only, by prior_scale_px / sigma
        np.testing.assert_allclose(J[prob.m_data:], np.c_[np.diag(0.04 / prior[1]), np.zeros((9, prob.n - 9))],
                                   rtol=1e-6, atol=1e-9)


def test_exact_recovery_on_clean_observations():
    rig = paper_rig()
    rv, tv = _poses(6)
    cols = np.arange(2, 127, 3) * 8 - 0.5
    data = synthetic_data(rig, rv, tv, cols=COLS, rows=ROWS, square_mm=SQ, columns=cols, samples_per_line=10)
    cam0, rig0 = _perturbed(rig)
    res = refine(data, cam0, rv + 0.005, tv + 2.0, rig0, loss="linear", log=lambda s: None)
    np.testing.assert_allclose(res.rig.camera.K, rig.camera.K, atol=1e-5)
    np.testing.assert_allclose(res.rig.camera.dist, rig.camera.dist, atol=1e-8)
    assert _normal_error_deg(res.rig, rig, cols) < 1e-5
    _, d1 = res.rig.column_planes(cols)
    _, d2 = rig.column_planes(cols)
    np.testing.assert_allclose(d1, d2, atol=1e-5)
    np.testing.assert_allclose(res.tvecs, tv, atol=1e-5)
    assert np.sqrt(np.mean(res.corner_residual_px ** 2)) < 1e-7
    assert np.sqrt(np.mean(res.stripe_residual_px ** 2)) < 1e-7


def _noisy_refinement():
    """The paper rig refined from 8 poses with 0.1 px corner and 0.05 px stripe noise: (true rig,
    stripe columns, result)."""
    rig = paper_rig()
    rv, tv = _poses(8, seed=5)
    cols = np.arange(2, 127, 2) * 8 - 0.5
    data = synthetic_data(rig, rv, tv, cols=COLS, rows=ROWS, square_mm=SQ, columns=cols, samples_per_line=12,
                          corner_noise_px=0.1, stripe_noise_px=0.05, seed=7)
    cam0, rig0 = _perturbed(rig)
    return rig, cols, refine(data, cam0, rv, tv, rig0, log=lambda s: None)


def test_noisy_recovery_is_consistent_with_the_reported_uncertainty():
    rig, cols, res = _noisy_refinement()
    K, K0 = res.rig.camera.K, rig.camera.K
    for name, est, true in (("fx", K[0, 0], K0[0, 0]), ("fy", K[1, 1], K0[1, 1]), ("cx", K[0, 2], K0[0, 2]),
                            ("cy", K[1, 2], K0[1, 2]), ("proj_fx", res.rig.projector.K[0, 0], 1860.0)):
        assert 0 < res.std[name] < 2.0
        assert abs(est - true) < 4.5 * res.std[name], (name, est, true, res.std[name])
    assert res.sigma["corner_px"] == pytest.approx(0.1, rel=0.15)
    assert res.sigma["stripe_px"] == pytest.approx(0.05, rel=0.15)
    assert _normal_error_deg(res.rig, rig, cols) < 0.05
    assert abs(np.linalg.norm(res.rig.t_cam_proj) - 200.0) < 4.5 * res.std["baseline_mm"] + 1e-3
    n_std, d_std = res.plane_std(cols)
    n1, d1 = res.rig.column_planes(cols)
    n2, d2 = rig.column_planes(cols)
    err = np.degrees(np.arccos(np.clip(np.sum(n1 * n2, axis=1), -1, 1)))
    assert np.all(n_std > 0) and np.all(err < 4.5 * n_std)
    assert np.all(np.abs(d1 - d2) < 4.5 * d_std)


def test_robust_loss_shrugs_off_gross_stripe_outliers():
    rig = paper_rig()
    rv, tv = _poses(5, seed=9)
    cols = np.arange(2, 127, 4) * 8 - 0.5
    clean = synthetic_data(rig, rv, tv, cols=COLS, rows=ROWS, square_mm=SQ, columns=cols, samples_per_line=8,
                           corner_noise_px=0.05, stripe_noise_px=0.05, seed=2)
    rng = np.random.default_rng(4)
    bad = rng.choice(len(clean.stripe_pose), len(clean.stripe_pose) // 30, replace=False)
    uv = clean.stripe_uv.copy()
    uv[bad, 0] += rng.choice([-1, 1], bad.size) * rng.uniform(3, 8, bad.size)  # wrong stripe, 3-8 px off
    dirty = BundleData(clean.corner_pose, clean.corner_uv, clean.corner_xyz, clean.stripe_pose, uv,
                       clean.stripe_column, clean.n_poses)
    good = np.setdiff1d(np.arange(len(clean.stripe_pose)), bad)
    subset = BundleData(clean.corner_pose, clean.corner_uv, clean.corner_xyz, clean.stripe_pose[good],
                        clean.stripe_uv[good], clean.stripe_column[good], clean.n_poses)
    cam0, rig0 = _perturbed(rig)
    ref = refine(subset, cam0, rv, tv, rig0, log=lambda s: None)           # without the outliers
    res = refine(dirty, cam0, rv, tv, rig0, log=lambda s: None)            # robust + rejection
    lin = refine(dirty, cam0, rv, tv, rig0, loss="linear", reject_sigma=0, log=lambda s: None)
    # every outlier is found, and the solution is the one without them
    assert not res.stripe_inlier[bad].any() and res.stripe_inlier[good].mean() > 0.995
    assert _normal_error_deg(res.rig, ref.rig, cols) < 2e-3
    assert abs(res.rig.camera.K[0, 0] - ref.rig.camera.K[0, 0]) < 0.02
    # plain least squares is pulled away by them
    assert _normal_error_deg(lin.rig, ref.rig, cols) > 0.02
    assert np.median(np.abs(res.stripe_residual_px[bad])) > 2.0


def test_bad_inputs_are_named():
    with pytest.raises(GBError, match="corner arrays"):
        BundleData(np.zeros(3, int), np.zeros((2, 2)), np.zeros((3, 3)), np.zeros(0, int), np.zeros((0, 2)),
                   np.zeros(0), 1)
    rig = paper_rig()
    rv, tv = _poses(2)
    data = synthetic_data(rig, rv, tv, cols=COLS, rows=ROWS, square_mm=SQ, columns=np.array([500.5]))
    with pytest.raises(GBError, match="distortion model"):
        BundleProblem(data, rig.camera, rv, tv, rig, dist_model="fisheye")


def test_depth_std_bounds_the_scanned_depth_error_and_matches_a_direct_perturbation():
    import dataclasses

    rig, _, res = _noisy_refinement()
    q = np.array([[319.5, 239.5], [120.0, 110.0], [500.0, 350.0]])
    s = res.depth_std(q, 650.0)
    assert np.all(np.isfinite(s)) and np.all(s > 0) and np.all(s < 1.0), s

    def scanned_depth(scan_rig, true_rig, q, z):
        """Depth that ``scan_rig`` gives for pixel ``q`` lit by the column the true point at ``z`` sees."""
        p = np.concatenate([true_rig.camera.normalize(q), np.ones((len(q), 1))], axis=1) * z
        col = true_rig.project_to_projector(p)[:, 0]
        n, d = scan_rig.column_planes(col)
        r = np.concatenate([scan_rig.camera.normalize(q), np.ones((len(q), 1))], axis=1)
        return d / np.sum(n * r, axis=1)

    err = scanned_depth(res.rig, rig, q, 650.0) - 650.0
    assert np.all(np.abs(err) < 4.5 * s), (err, s)
    # one parameter's variance alone: the propagated figure is the depth change of a 1-sigma step
    prob = res.problem
    for j in (0, prob.i_proj + 5, prob.i_proj + 3):  # fx, the projector's fx, its centre along x
        sig = 0.3 if j == 0 else (0.5 if j == prob.i_proj + 5 else 0.05)
        cov = np.zeros_like(res.cov)
        cov[j, j] = sig ** 2
        one = dataclasses.replace(res, cov=cov).depth_std(q, 650.0)
        th = res.theta.copy()
        th[j] += sig
        direct = np.abs(scanned_depth(prob.rig(th), res.rig, q, 650.0) - 650.0)
        np.testing.assert_allclose(one, direct, rtol=0.02, atol=1e-6)
    # a point outside the projector's frame has no depth to be uncertain about
    assert np.isnan(res.depth_std(np.array([[0.0, 0.0]]), 5000.0)[0])  # above the frame
    out = res.depth_std(np.array([[0.0, 239.5], [639.0, 239.5]]), 300.0)
    assert np.isnan(out[0]) and np.isfinite(out[1])  # left of it; inside
    assert np.all(np.isnan(dataclasses.replace(res, cov=None).depth_std(q, 650.0)))


def test_a_camera_prior_pins_the_camera_and_is_reported():
    rig, cols, free = _noisy_refinement()
    rv, tv = _poses(8, seed=5)
    data = synthetic_data(rig, rv, tv, cols=COLS, rows=ROWS, square_mm=SQ, columns=cols, samples_per_line=12,
                          corner_noise_px=0.1, stripe_noise_px=0.05, seed=7)
    cam0, rig0 = _perturbed(rig)
    K0 = rig.camera.K
    names = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")
    sd = np.array([free.std[n] for n in names]) / 10.0  # a camera known ten times better
    for shift in (0.0, 1.0):  # the prior at the truth; then one of its sigmas off in fx
        mu = np.r_[K0[0, 0] + shift * sd[0], K0[1, 1], K0[0, 2], K0[1, 2], rig.camera.dist[:4]]
        res = refine(data, cam0, rv, tv, rig0, log=lambda s: None, camera_prior=(mu, sd), prior_scale_px=0.1)
        K = res.rig.camera.K
        assert res.std["fx"] < 0.2 * free.std["fx"] and res.std["cx"] < 0.2 * free.std["cx"], (res.std, free.std)
        assert abs(K[0, 0] - mu[0]) < 2.5 * sd[0] and abs(K[0, 2] - mu[2]) < 2.5 * sd[2]
        z = res.info["camera_prior_z"]
        assert set(z) == set(names) and abs(z["fx"]) < 2.5
        # the rows the summaries read are still the data's
        assert res.corner_residual_px.shape == (free.corner_residual_px.shape[0], 2)
        assert res.stripe_residual_px.shape == free.stripe_residual_px.shape
        assert res.sigma["corner_px"] == pytest.approx(0.1, rel=0.15)
    # the depth a scan inherits is known better too
    q = np.array([[319.5, 239.5]])
    assert res.depth_std(q, 650.0)[0] < 0.7 * free.depth_std(q, 650.0)[0]
    with pytest.raises(GBError, match="camera prior needs 8 finite means"):
        refine(data, cam0, rv, tv, rig0, log=lambda s: None, camera_prior=(mu[:4], sd[:4]))


@pytest.mark.parametrize("name", ["soft_l1", "huber", "cauchy", "arctan", "linear"])
def test_the_losses_match_scipys_and_the_prior_rows_stay_quadratic(name):
    from scipy.optimize import least_squares

    from gbcal.bundle import _loss_with_quadratic_tail, _robust_rho

    rng = np.random.default_rng(0)
    x = np.linspace(0, 1, 40)
    y = 2.0 * x + 1.0 + rng.normal(0, 0.05, x.size)
    y[::7] += 3.0  # outliers

    def fun(p):
        return np.r_[p[0] * x + p[1] - y, 3.0 * (p[0] - 2.5)]  # last: a "prior" 0.5 off the data's slope

    ours = least_squares(fun, [1.0, 0.0], loss=lambda z: _robust_rho(name, z), f_scale=0.1).x
    ref = least_squares(fun, [1.0, 0.0], loss=name, f_scale=0.1).x
    np.testing.assert_allclose(ours, ref, atol=1e-7)
    tail = least_squares(fun, [1.0, 0.0], loss=_loss_with_quadratic_tail(name, 1), f_scale=0.1).x
    # quadratic, the prior row pulls the slope well towards 2.5 (a robust loss caps its pull)
    assert tail[0] > 2.1 and (name == "linear" or tail[0] > ref[0] + 0.05), (tail, ref)
