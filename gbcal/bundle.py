"""Joint refinement of the whole rig: ONE robust nonlinear least squares.

Unknowns (``theta``, in this order):

* camera: ``fx, fy, cx, cy`` (px) and the free distortion terms of the chosen model
  (:data:`DIST_MODELS`; the others stay at their initial values, normally 0);
* per board pose ``i``: Rodrigues vector ``rvec_i`` (rad) and ``t_i`` (mm), ``p_cam = R_i p_board + t_i``;
* projector: Rodrigues vector of ``R_cam_proj``, the centre's coordinates ``s_x, s_z`` (mm) along
  the projector's own x and z axes (``t_cam_proj = R_cam_proj @ [s_x, s_y, s_z]``), ``fx_p`` and
  ``cx_p`` (projector px).  Vertical stripes only observe the projector's columns: every column
  plane contains the projector's y axis through its centre, so ``s_y`` (sliding along that
  axis), ``fy_p`` and ``cy_p`` are unobservable and stay fixed (gauge).

Residuals, all in **camera pixels** so that the two kinds weigh comparably:

* corner ``j`` of pose ``i``: ``project(R_i X_j + t_i) - q_j`` (2 per corner, px);
* stripe-boundary sample ``(u, v)`` of boundary column ``x_k`` on pose ``i``: its camera ray
  meets board plane ``i`` at ``P``; the residual is ``(x_proj(P) - x_k) / s`` where
  ``s = |d x_proj / d u|`` (projector px per camera px along the row, fixed at the start), i.e.
  the boundary's horizontal misplacement expressed in camera px.  ``stripe_weight`` scales
  these residuals (1 = a boundary sample is trusted like one corner coordinate).

With a *camera prior* (a camera calibrated on its own, ``gbcal camera``: mean ``mu`` and standard
deviations ``sigma`` of the camera unknowns) one more residual per camera unknown,
``prior_scale_px * (theta - mu) / sigma``, appended after the stripes: with ``prior_scale_px`` the
corners' noise (px), a prior parameter weighs as its variance says against the corners.

The robust loss (``soft_l1`` by default, scale ``f_scale_px``) is scipy's.  The Jacobian is
*structured*: every residual depends on the camera, on its own pose only, and (stripes) on the
projector, so finite differences need only ``n_camera + 6 + 7`` residual evaluations (forward;
twice that central) whatever the number of poses, the rays of the stripe samples are reused when
the camera is unchanged and re-solved by two Newton steps from the current ones when it is not; it is returned as a sparse matrix (``tests/test_bundle.py`` checks it against plain
finite differences).  Parameter standard deviations come from ``(J^T W J)^-1`` with ``W`` the
inverse variance of each residual kind estimated from the inlier residuals.
"""
from __future__ import annotations

import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from gbscan.camera import Camera, distort_normalized, undistort_normalized
from gbscan.errors import GBError
from gbscan.rig import Projector, Rig

#: Distortion models (names as in :mod:`gbcal.intrinsics`): name -> indices of
#: ``[k1, k2, p1, p2, k3]`` that are refined (the others stay at their initial values).
DIST_MODELS = {"k1k2p1p2k3": (0, 1, 2, 3, 4), "k1k2p1p2": (0, 1, 2, 3), "k1k2": (0, 1), "k1": (0,), "none": ()}
#: Below this many unknowns the trust-region step is solved exactly on the dense Jacobian.
DENSE_MAX_UNKNOWNS = 400
CAMERA_NAMES = ("fx", "fy", "cx", "cy")
DIST_NAMES = ("k1", "k2", "p1", "p2", "k3")
POSE_NAMES = ("rx", "ry", "rz", "tx", "ty", "tz")
PROJ_NAMES = ("proj_rx", "proj_ry", "proj_rz", "proj_sx", "proj_sz", "proj_fx", "proj_cx")


def camera_unknowns(camera: Camera, dist_model: str) -> tuple[list[str], np.ndarray]:
    """The bundle's camera unknowns under ``dist_model``: their names and ``camera``'s values
    (``fx, fy, cx, cy`` px, then the model's free distortion terms), in ``theta``'s order."""
    free = DIST_MODELS[dist_model]
    K = camera.K
    return (_camera_unknown_names(dist_model),
            np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], np.asarray(camera.dist, np.float64)[list(free)]])


def _camera_unknown_names(dist_model: str) -> list[str]:
    return list(CAMERA_NAMES) + [DIST_NAMES[i] for i in DIST_MODELS[dist_model]]


# -- rotations ---------------------------------------------------------------------------------
def rodrigues(rvec: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) rad -> rotation matrices (..., 3, 3) (exact for small angles)."""
    r = np.asarray(rvec, np.float64)
    th = np.linalg.norm(r, axis=-1)[..., None, None]
    k = np.zeros(r.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2] = -r[..., 2], r[..., 1]
    k[..., 1, 0], k[..., 1, 2] = r[..., 2], -r[..., 0]
    k[..., 2, 0], k[..., 2, 1] = -r[..., 1], r[..., 0]
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th ** 2 / 6.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th ** 2 / 24.0, (1.0 - np.cos(ths)) / ths ** 2)
    return np.eye(3) + a * k + b * (k @ k)


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) -> rotation vector (3,) rad."""
    import cv2

    return cv2.Rodrigues(np.asarray(R, np.float64))[0].ravel()


# -- data --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class BundleData:
    """Observations, concatenated over poses.

    corner_pose (Nc,) int64, corner_uv (Nc, 2) px, corner_xyz (Nc, 3) board frame mm;
    stripe_pose (Ns,) int64, stripe_uv (Ns, 2) px, stripe_column (Ns,) projector px (boundary
    column ``k * stripe_px - 0.5``); n_poses.
    """

    corner_pose: np.ndarray
    corner_uv: np.ndarray
    corner_xyz: np.ndarray
    stripe_pose: np.ndarray
    stripe_uv: np.ndarray
    stripe_column: np.ndarray
    n_poses: int

    def __post_init__(self):
        Nc, Ns = len(self.corner_pose), len(self.stripe_pose)
        if self.corner_uv.shape != (Nc, 2) or self.corner_xyz.shape != (Nc, 3):
            raise GBError("bundle data: corner arrays must be (Nc,), (Nc, 2), (Nc, 3)")
        if self.stripe_uv.shape != (Ns, 2) or self.stripe_column.shape != (Ns,):
            raise GBError("bundle data: stripe arrays must be (Ns,), (Ns, 2), (Ns,)")
        for name, pose in (("corner", self.corner_pose), ("stripe", self.stripe_pose)):
            if pose.size and (pose.min() < 0 or pose.max() >= self.n_poses):
                raise GBError(f"bundle data: {name} pose index outside 0..{self.n_poses - 1}")


@dataclass
class BundleResult:
    """The refined rig and what the refinement says about it.

    rig : camera + projector + ``T_cam_proj``; rvecs, tvecs : (P, 3) board poses.
    corner_residual_px : (Nc, 2) projected - observed; stripe_residual_px : (Ns,) camera px
    (see module docstring); stripe_residual_proj_px : (Ns,) projector px; stripe_inlier : (Ns,)
    bool, False for samples dropped as outliers (their residuals are still reported).
    std : parameter name -> standard deviation (px, mm, rad), ``pose_std`` (P, 6).
    """

    rig: Rig
    rvecs: np.ndarray
    tvecs: np.ndarray
    corner_residual_px: np.ndarray
    stripe_residual_px: np.ndarray
    stripe_residual_proj_px: np.ndarray
    stripe_inlier: np.ndarray
    std: dict
    pose_std: np.ndarray
    sigma: dict
    info: dict = field(default_factory=dict)
    theta: np.ndarray | None = None
    cov: np.ndarray | None = None           # (n, n) parameter covariance (None if singular)
    problem: "BundleProblem | None" = None

    def depth_std(self, pixels: np.ndarray, distance_mm: float) -> np.ndarray:
        """1-sigma uncertainty (mm) of the depth a scan gives for a point at ``distance_mm`` (z,
        camera frame) on the rays of camera ``pixels`` (N, 2), propagated from the camera's and
        the projector's parameter covariance (board poses do not enter a scan).

        The point is placed with the refined rig; its projector column is then triangulated
        again under each perturbed parameter (the pixel's ray met with that column's plane), so
        the figure is what an error of the calibration does to a scanned depth -- mostly a scale:
        ``distance_mm * std(fx) / fx`` when fx dominates.  NaN for pixels whose point falls
        outside the projector frame (not lit), and everywhere when the covariance is unknown.
        """
        q = np.asarray(pixels, np.float64).reshape(-1, 2)
        out = np.full(len(q), np.nan)
        if self.cov is None or self.problem is None or not len(q):
            return out
        prob, th = self.problem, self.theta
        rig0 = prob.rig(th)
        xn = rig0.camera.normalize(q)
        p0 = np.concatenate([xn, np.ones((len(q), 1))], axis=1) * float(distance_mm)
        xy = rig0.project_to_projector(p0)
        col = xy[:, 0]
        ok = (np.all(np.isfinite(xy), axis=1) & (col >= -0.5) & (col <= rig0.projector.width - 0.5)
              & (xy[:, 1] >= -0.5) & (xy[:, 1] <= rig0.projector.height - 0.5))
        if not ok.any():
            return out
        q, col = q[ok], col[ok]

        def depth(t):
            rig = prob.rig(t)
            r = np.concatenate([rig.camera.normalize(q), np.ones((len(q), 1))], axis=1)
            n, d = rig.column_planes(col)
            return d / np.einsum("ij,ij->i", n, r)  # z of the ray [x, y, 1] scaled to the plane

        z0 = depth(th)
        idx = np.r_[0:prob.n_cam, prob.i_proj:prob.n]
        J = np.empty((len(q), idx.size))
        for k, j in enumerate(idx):
            h = 1e-6 * max(abs(th[j]), 1.0)
            t = th.copy()
            t[j] += h
            J[:, k] = (depth(t) - z0) / h
        C = self.cov[np.ix_(idx, idx)]
        out[ok] = np.sqrt(np.maximum(np.einsum("pk,kl,pl->p", J, C, J), 0.0))
        return out

    def plane_std(self, columns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """1-sigma uncertainty of the light planes of projector ``columns`` (P,): (normal
        direction (P,) deg, offset d (P,) mm), propagated from the projector parameters'
        covariance (the planes depend on nothing else).  NaN when the covariance is unknown."""
        cols = np.asarray(columns, np.float64)
        if self.cov is None or self.problem is None:
            return np.full(cols.size, np.nan), np.full(cols.size, np.nan)
        prob, th = self.problem, self.theta
        sl = slice(prob.i_proj, prob.n)
        n0, d0 = prob.rig(th).column_planes(cols)
        Jn, Jd = [], []
        for j in range(sl.start, sl.stop):
            h = 1e-6 * max(abs(th[j]), 1.0)
            t = th.copy()
            t[j] += h
            n1, d1 = prob.rig(t).column_planes(cols)
            Jn.append((n1 - n0) / h)
            Jd.append((d1 - d0) / h)
        Jn = np.stack(Jn, axis=-1)  # (P, 3, 7)
        Jd = np.stack(Jd, axis=-1)  # (P, 7)
        C = self.cov[sl, sl]
        var_n = np.einsum("pik,kl,pil->p", Jn, C, Jn)  # n is unit: its change is a rotation (rad^2)
        var_d = np.einsum("pk,kl,pl->p", Jd, C, Jd)
        return np.degrees(np.sqrt(np.maximum(var_n, 0))), np.sqrt(np.maximum(var_d, 0))


class BundleProblem:
    """Residuals and structured Jacobian of the joint refinement (see the module docstring)."""

    def __init__(self, data: BundleData, camera: Camera, rvecs: np.ndarray, tvecs: np.ndarray,
                 rig: Rig, *, dist_model: str = "k1k2p1p2", stripe_weight: float = 1.0,
                 camera_prior: "tuple[np.ndarray, np.ndarray] | None" = None, prior_scale_px: float = 0.05):
        if dist_model not in DIST_MODELS:
            raise GBError(f"unknown distortion model '{dist_model}'; choose one of {', '.join(DIST_MODELS)}")
        self.data = data
        self.width, self.height = camera.width, camera.height
        self.dist0 = camera.dist.copy()
        self.skew = float(camera.K[0, 1])
        self.dist_model = dist_model
        self.free_dist = np.array(DIST_MODELS[dist_model], np.int64)
        self.P = int(data.n_poses)
        self.proj_size = (rig.projector.width, rig.projector.height)
        self.proj_fy_cy = (float(rig.projector.K[1, 1]), float(rig.projector.K[1, 2]))
        s = rig.R_cam_proj.T @ rig.t_cam_proj
        self.sy = float(s[1])
        self.n_cam = 4 + self.free_dist.size
        self.i_pose = self.n_cam
        self.i_proj = self.n_cam + 6 * self.P
        self.n = self.i_proj + 7
        self.Nc, self.Ns = len(data.corner_pose), len(data.stripe_pose)
        self.m_data = 2 * self.Nc + self.Ns       # corner and stripe rows; prior rows after them
        self.prior_mu = self.prior_w = None
        if camera_prior is not None:
            mu, sd = (np.asarray(a, np.float64).ravel() for a in camera_prior)
            if mu.shape != (self.n_cam,) or sd.shape != (self.n_cam,) or not np.all(np.isfinite(mu)) \
                    or not np.all(sd > 0):
                raise GBError(f"bundle: a camera prior needs {self.n_cam} finite means and positive standard "
                              f"deviations ({', '.join(_camera_unknown_names(dist_model))})")
            if not prior_scale_px > 0:
                raise GBError(f"bundle: prior_scale_px must be positive, got {prior_scale_px!r}")
            self.prior_mu, self.prior_w = mu, float(prior_scale_px) / sd
        self.n_prior = 0 if self.prior_mu is None else self.n_cam
        self.prior_scale_px = float(prior_scale_px)
        self.m = self.m_data + self.n_prior
        self.row_pose = np.concatenate([np.repeat(data.corner_pose, 2), data.stripe_pose]).astype(np.int64)
        self.stripe_weight = float(stripe_weight)
        theta = np.empty(self.n)
        theta[:self.n_cam] = camera_unknowns(camera, dist_model)[1]
        poses = np.concatenate([np.asarray(rvecs, np.float64).reshape(-1, 3),
                                np.asarray(tvecs, np.float64).reshape(-1, 3)], axis=1)
        if poses.shape[0] != self.P:
            raise GBError(f"bundle: {poses.shape[0]} initial poses for {self.P} poses of data")
        theta[self.i_pose:self.i_proj] = poses.ravel()
        theta[self.i_proj:] = [*rotation_vector(rig.R_cam_proj), s[0], s[2],
                               rig.projector.K[0, 0], rig.projector.K[0, 2]]
        self.theta0 = theta
        self.inv_scale = np.ones(self.Ns)
        if self.Ns:  # projector px per camera px along the row, at the start
            rays = self.rays(theta)
            x0 = self._stripe_columns(theta, rays)
            q = data.stripe_uv + [0.05, 0.0]
            x1 = self._stripe_columns(theta, self._rays_of(theta, q))
            s_row = np.abs(x1 - x0) / 0.05
            ok = np.isfinite(s_row) & (s_row > 1e-6)
            med = np.median(s_row[ok]) if ok.any() else 1.0
            self.inv_scale = 1.0 / np.where(ok, s_row, med)

    # -- unpacking -----------------------------------------------------------------------------
    def camera(self, theta) -> Camera:
        fx, fy, cx, cy = theta[:4]
        dist = self.dist0.copy()
        dist[self.free_dist] = theta[4:self.n_cam]
        return Camera(self.width, self.height, np.array([[fx, self.skew, cx], [0, fy, cy], [0, 0, 1.0]]), dist)

    def poses(self, theta):
        p = theta[self.i_pose:self.i_proj].reshape(self.P, 6)
        return p[:, :3], p[:, 3:]

    def projector(self, theta):
        q = theta[self.i_proj:]
        R = rodrigues(q[:3])
        t = R @ np.array([q[3], self.sy, q[4]])
        return R, t, float(q[5]), float(q[6])

    def rig(self, theta) -> Rig:
        R, t, fx_p, cx_p = self.projector(theta)
        fy_p, cy_p = self.proj_fy_cy
        K = np.array([[fx_p, 0.0, cx_p], [0.0, fy_p, cy_p], [0.0, 0.0, 1.0]])
        return Rig(self.camera(theta), Projector(*self.proj_size, K), R, t)

    # -- model ---------------------------------------------------------------------------------
    def _rays_of(self, theta, uv, x0=None):
        if x0 is None:
            xn = self.camera(theta).normalize(uv)
        else:  # warm start (a camera slightly different from the one x0 came from)
            fx, fy, cx, cy = theta[:4]
            yd = (uv[:, 1] - cy) / fy
            target = np.stack([(uv[:, 0] - cx - self.skew * yd) / fx, yd], axis=1)
            dist = self.dist0.copy()
            dist[self.free_dist] = theta[4:self.n_cam]
            xn = undistort_normalized(target, dist, x0[:, :2], iterations=2, tol=None)
        return np.concatenate([xn, np.ones((xn.shape[0], 1))], axis=1)

    def rays(self, theta) -> np.ndarray:
        """(Ns, 3) rays ``[x, y, 1]`` of the stripe samples under the camera of ``theta``."""
        return self._rays_of(theta, self.data.stripe_uv)

    def _stripe_columns(self, theta, rays):
        d = self.data
        rv, tv = self.poses(theta)
        Rb = rodrigues(rv)
        n = Rb[d.stripe_pose, :, 2]
        t = tv[d.stripe_pose]
        lam = np.einsum("ij,ij->i", n, t) / np.einsum("ij,ij->i", n, rays)
        P = rays * lam[:, None]
        R, tp, fx_p, cx_p = self.projector(theta)
        pp = (P - tp) @ R
        return fx_p * pp[:, 0] / pp[:, 2] + cx_p

    def corner_projection(self, theta) -> np.ndarray:
        d = self.data
        rv, tv = self.poses(theta)
        Rb = rodrigues(rv)
        p = np.einsum("nij,nj->ni", Rb[d.corner_pose], d.corner_xyz) + tv[d.corner_pose]
        xn = p[:, :2] / p[:, 2:3]
        dist = self.dist0.copy()
        dist[self.free_dist] = theta[4:self.n_cam]
        xd = distort_normalized(xn, dist)
        fx, fy, cx, cy = theta[:4]
        return np.stack([fx * xd[:, 0] + self.skew * xd[:, 1] + cx, fy * xd[:, 1] + cy], axis=1)

    def residuals(self, theta, rays=None) -> np.ndarray:
        """(m,) = [corner (Nc*2) px, stripe (Ns) camera px * stripe_weight, camera prior (n_prior)]."""
        rc = (self.corner_projection(theta) - self.data.corner_uv).ravel() if self.Nc else np.zeros(0)
        parts = [rc]
        if self.Ns:
            if rays is None:
                rays = self.rays(theta)
            rs = (self._stripe_columns(theta, rays) - self.data.stripe_column) * self.inv_scale
            parts.append(rs * self.stripe_weight)
        if self.n_prior:
            parts.append((theta[:self.n_cam] - self.prior_mu) * self.prior_w)
        return np.concatenate(parts) if len(parts) > 1 else rc

    # -- Jacobian ------------------------------------------------------------------------------
    def _steps(self, theta):
        h = 1e-6 * np.maximum(np.abs(theta), 1.0)
        h[:4] = 1e-4                           # px
        h[4:self.n_cam] = 1e-6                 # distortion
        return h

    def jacobian(self, theta, central: bool = False):
        """Sparse (m, n) Jacobian by block-structured finite differences (forward by default:
        half the evaluations, ~1e-6 relative accuracy -- plenty for Gauss-Newton steps; central
        differences with ``central=True``)."""
        from scipy.sparse import coo_matrix

        h = self._steps(theta)
        rows_all = np.arange(self.m)
        rr, cc, vv = [], [], []
        rays = self.rays(theta) if self.Ns else None
        uv = self.data.stripe_uv
        r0 = None if central else self.residuals(theta, rays)

        def warm(t):
            return self._rays_of(t, uv, rays) if self.Ns else None

        def diff(idx, rays_of, rows=slice(None)):
            tp = theta.copy()
            tp[idx] += h[idx]
            rp = self.residuals(tp, rays_of(tp))[rows]
            if central:
                tm = theta.copy()
                tm[idx] -= h[idx]
                return (rp - self.residuals(tm, rays_of(tm))[rows]), 2.0
            return rp - r0[rows], 1.0

        # camera block: every residual (rays re-solved by Newton from the current ones)
        for j in range(self.n_cam):
            dr, f = diff(j, warm)
            rr.append(rows_all), cc.append(np.full(self.m, j)), vv.append(dr / (f * h[j]))
        # pose block: component c of every pose at once (a residual sees only its own pose)
        data_rows = slice(0, self.m_data)
        for c in range(6):
            idx = self.i_pose + 6 * np.arange(self.P) + c
            dr, f = diff(idx, lambda t: rays, data_rows)
            rr.append(rows_all[data_rows]), cc.append(self.i_pose + 6 * self.row_pose + c)
            vv.append(dr / (f * h[idx][self.row_pose]))
        # projector block: stripe residuals only
        if self.Ns:
            srows = np.arange(2 * self.Nc, self.m_data)
            for j in range(self.i_proj, self.n):
                dr, f = diff(j, lambda t: rays, slice(2 * self.Nc, self.m_data))
                rr.append(srows), cc.append(np.full(self.Ns, j)), vv.append(dr / (f * h[j]))
        J = coo_matrix((np.concatenate(vv), (np.concatenate(rr), np.concatenate(cc))), shape=(self.m, self.n))
        return J.tocsr()

    def param_names(self) -> list[str]:
        names = _camera_unknown_names(self.dist_model)
        names += [f"pose{i}_{c}" for i in range(self.P) for c in POSE_NAMES]
        return names + list(PROJ_NAMES)


@contextmanager
def _blas_threads(n: int = 1):
    """Run the block with ``n`` OpenBLAS threads (what threadpoolctl does, without the dependency).

    The trust-region step's SVD of a tall (thousands x ~100) Jacobian is memory-bound: one thread
    does it in ~30 ms, while OpenBLAS's thread pool on a loaded machine can take seconds (measured
    70x slower on the 2-core build machine).  Linux only; elsewhere a no-op.
    """
    import ctypes

    handles = []
    try:
        with open("/proc/self/maps", encoding="utf-8") as fh:
            paths = {line.split()[-1] for line in fh if "openblas" in line.lower() and ".so" in line.split()[-1]}
    except OSError:
        paths = set()
    for p in sorted(paths):
        try:
            lib = ctypes.CDLL(p)
        except OSError:
            continue
        for prefix in ("scipy_openblas", "openblas"):
            for suffix in ("64_", ""):
                get = getattr(lib, f"{prefix}_get_num_threads{suffix}", None)
                put = getattr(lib, f"{prefix}_set_num_threads{suffix}", None)
                if get is not None and put is not None:
                    handles.append((put, int(get())))
                    put(int(n))
                    break
            else:
                continue
            break
    try:
        yield
    finally:
        for put, old in handles:
            put(old)


def refine(data: BundleData, camera: Camera, rvecs: np.ndarray, tvecs: np.ndarray, rig: Rig, *,
           dist_model: str = "k1k2p1p2", loss: str = "soft_l1", f_scale_px: float = 0.5,
           stripe_weight: float = 1.0, reject_sigma: float = 5.0, max_nfev: int = 60, log=None,
           camera_prior: "tuple[np.ndarray, np.ndarray] | None" = None, prior_scale_px: float = 0.05) -> BundleResult:
    """Refine camera, board poses and projector together (see the module docstring).

    camera : initial intrinsics; rvecs, tvecs : (P, 3) initial board poses; rig : initial
    projector model and ``T_cam_proj`` (its camera is ignored).
    reject_sigma : after the robust solve, stripe samples farther than this many robust sigmas
        (1.4826 MAD) are dropped and the problem is solved again from there (0: keep all), so
        gross outliers (a wrong Gray-code index) end with no influence at all rather than the
        robust loss's bounded one.
    log : callable(str) for progress lines (default: stderr).
    camera_prior : ``(mu, sigma)`` of the camera unknowns (fx, fy, cx, cy, then the model's free
        distortion terms), e.g. from a camera calibrated on its own; ``prior_scale_px`` the corners'
        noise per coordinate (px) that puts the prior on the residuals' scale (module docstring).
    """
    from scipy.optimize import least_squares

    log = log or (lambda s: print(s, file=sys.stderr))
    if loss not in ("linear", "soft_l1", "huber", "cauchy", "arctan"):
        raise GBError(f"unknown robust loss '{loss}'")
    prob = BundleProblem(data, camera, rvecs, tvecs, rig, dist_model=dist_model, stripe_weight=stripe_weight,
                         camera_prior=camera_prior, prior_scale_px=prior_scale_px)
    if prob.m < prob.n:
        raise GBError(f"bundle: {prob.m} residuals cannot determine {prob.n} unknowns; capture more poses")
    t0 = time.perf_counter()
    r0 = prob.residuals(prob.theta0)
    log(f"  bundle: {prob.n} unknowns, {prob.Nc} corners, {prob.Ns} stripe samples, "
        f"start RMS {np.sqrt(np.mean(r0[:prob.m_data] ** 2)):.3f} px")
    nc2 = 2 * prob.Nc
    srow = slice(nc2, prob.m_data)  # the stripe rows
    rows = np.ones(prob.m, bool)

    # the prior's rows (last) are not measurements that can be outliers: quadratic whatever the loss
    loss_fn = loss if not prob.n_prior or loss == "linear" else _loss_with_quadratic_tail(loss, prob.n_prior)

    def solve(theta, rows):
        # the Jacobian is built sparse; with few unknowns (< DENSE_MAX_UNKNOWNS: ~60 poses) the
        # trust-region step is solved exactly on its dense form: far fewer iterations than LSMR
        dense = prob.n < DENSE_MAX_UNKNOWNS
        sel = np.flatnonzero(rows)
        jac = (lambda th: prob.jacobian(th)[sel].toarray()) if dense else (lambda th: prob.jacobian(th)[sel])
        with np.errstate(all="ignore"), _blas_threads(1):  # trial steps may overshoot; trf shrinks them
            return least_squares(lambda th: prob.residuals(th)[sel], theta, jac=jac, method="trf", loss=loss_fn,
                                 f_scale=f_scale_px, x_scale="jac", max_nfev=max_nfev,
                                 tr_solver="exact" if dense else "lsmr", xtol=1e-10, ftol=1e-10)

    sol = solve(prob.theta0, rows)
    nfev = int(sol.nfev)
    n_rejected = 0
    if reject_sigma > 0 and prob.Ns:
        rs = prob.residuals(sol.x)[srow]
        thr = reject_sigma * max(_robust_sigma(rs), 1e-6)
        bad = np.abs(rs) > thr
        if bad.any():
            n_rejected = int(bad.sum())
            rows[srow] = ~bad
            log(f"  bundle: {n_rejected} stripe samples beyond {reject_sigma:g} sigma ({thr:.3f} px) dropped; "
                "solving again")
            sol = solve(sol.x, rows)
            nfev += int(sol.nfev)
    theta = sol.x
    r = prob.residuals(theta)
    dt = time.perf_counter() - t0
    rc = r[:nc2].reshape(-1, 2)
    rs = r[srow] / prob.stripe_weight
    rs_proj = rs / prob.inv_scale
    inl = rows[srow].copy()
    std, pose_std, sigma, cov = _uncertainty(prob, theta, r, rows)
    log(f"  bundle: {nfev} evaluations, {dt:.1f} s, corner RMS {_rms(np.linalg.norm(rc, axis=1)):.3f} px, stripe RMS "
        f"{_rms(rs[inl]):.3f} px ({_rms(rs_proj[inl]):.3f} projector px) over inliers; {sol.message}")
    info = {"nfev": nfev, "status": int(sol.status), "message": str(sol.message), "seconds": dt,
            "loss": loss, "f_scale_px": f_scale_px, "dist_model": dist_model, "stripe_weight": stripe_weight,
            "reject_sigma": reject_sigma, "stripe_rejected": n_rejected,
            "start_rms_px": float(np.sqrt(np.mean(r0[:prob.m_data] ** 2)))}
    if prob.n_prior:
        z = (theta[:prob.n_cam] - prob.prior_mu) * prob.prior_w / prob.prior_scale_px
        info["camera_prior_z"] = dict(zip(prob.param_names()[:prob.n_cam], z.tolist()))
    rv, tv = prob.poses(theta)
    return BundleResult(prob.rig(theta), rv.copy(), tv.copy(), rc, rs, rs_proj, inl, std, pose_std, sigma, info,
                        theta=theta, cov=cov, problem=prob)


def _robust_rho(name: str, z: np.ndarray) -> np.ndarray:
    """scipy's robust losses: (3, n) ``[rho, rho', rho'']`` of ``z = (r / f_scale)^2``."""
    out = np.empty((3, z.size))
    if name == "soft_l1":
        t = 1.0 + z
        out[0], out[1], out[2] = 2.0 * (np.sqrt(t) - 1.0), t ** -0.5, -0.5 * t ** -1.5
    elif name == "huber":
        big = z > 1.0
        sq = np.sqrt(np.where(big, z, 1.0))
        out[0] = np.where(big, 2.0 * sq - 1.0, z)
        out[1] = np.where(big, 1.0 / sq, 1.0)
        out[2] = np.where(big, -0.5 / (sq * np.where(big, z, 1.0)), 0.0)
    elif name == "cauchy":
        t = 1.0 + z
        out[0], out[1], out[2] = np.log1p(z), 1.0 / t, -1.0 / t ** 2
    elif name == "arctan":
        t = 1.0 + z ** 2
        out[0], out[1], out[2] = np.arctan(z), 1.0 / t, -2.0 * z / t ** 2
    else:  # linear
        out[0], out[1], out[2] = z, 1.0, 0.0
    return out


def _loss_with_quadratic_tail(name: str, n_tail: int):
    """A loss for ``least_squares``: ``name`` on every residual but the last ``n_tail``, which
    stay quadratic (the camera prior's rows)."""
    def rho(z):
        out = _robust_rho(name, z)
        out[0, -n_tail:], out[1, -n_tail:], out[2, -n_tail:] = z[-n_tail:], 1.0, 0.0
        return out
    return rho


def _rms(a) -> float:
    a = np.asarray(a)
    return float(np.sqrt(np.mean(a ** 2))) if a.size else float("nan")


def _robust_sigma(a: np.ndarray) -> float:
    a = np.abs(np.asarray(a).ravel())
    return float(1.4826 * np.median(a)) if a.size else float("nan")


def _uncertainty(prob: BundleProblem, theta: np.ndarray, r: np.ndarray, rows: np.ndarray):
    """Standard deviations from ``(J^T W J)^-1``; W = 1/sigma^2 per residual kind over the rows
    used (``rows``) within 3 robust sigmas."""
    J = prob.jacobian(theta)
    nc2 = 2 * prob.Nc
    w = np.zeros(prob.m)
    sigma = {}
    for name, sl in (("corner_px", slice(0, nc2)), ("stripe_px", slice(nc2, prob.m_data))):
        part = r[sl]
        if not part.size:
            continue
        rs = max(_robust_sigma(part[rows[sl]]), 1e-9)
        inl = (np.abs(part) <= 3.0 * rs) & rows[sl]
        s = float(np.sqrt(np.sum(part[inl] ** 2) / max(inl.sum() - 1, 1))) if inl.any() else rs
        s = max(s, 1e-9)
        sigma[name] = s
        w[sl] = np.where(inl, 1.0 / s, 0.0)
    if prob.n_prior:  # (theta - mu) / sigma exactly: its rows carry prior_scale_px
        w[prob.m_data:] = 1.0 / prob.prior_scale_px
    from scipy.sparse import diags

    Jw = diags(w) @ J
    JTJ = (Jw.T @ Jw).toarray()
    try:
        cov = np.linalg.inv(JTJ)
        var = np.diag(cov)
    except np.linalg.LinAlgError:
        var = np.full(prob.n, np.inf)
    sd = np.sqrt(np.where(var >= 0, var, np.inf))
    names = prob.param_names()
    std = {}
    for i, nme in enumerate(names):
        if not nme.startswith("pose"):
            std[nme] = float(sd[i])
    q = theta[prob.i_proj:]
    s_vec = np.array([q[3], prob.sy, q[4]])
    base = float(np.linalg.norm(s_vec))
    g = np.zeros(prob.n)
    g[prob.i_proj + 3] = q[3] / base
    g[prob.i_proj + 4] = q[4] / base
    if np.all(np.isfinite(var)):
        std["baseline_mm"] = float(np.sqrt(max(g @ cov @ g, 0.0)))
    pose_std = sd[prob.i_pose:prob.i_proj].reshape(prob.P, 6)
    return std, pose_std, sigma, cov if np.all(np.isfinite(var)) else None


# -- synthetic observations (tests, benchmarks) ------------------------------------------------
def synthetic_data(rig: Rig, rvecs: np.ndarray, tvecs: np.ndarray, *, cols: int, rows: int,
                   square_mm: float, columns: np.ndarray, samples_per_line: int = 40,
                   corner_noise_px: float = 0.0, stripe_noise_px: float = 0.0, seed: int = 0) -> BundleData:
    """Exact (plus optional Gaussian noise) observations of a rig looking at boards at poses.

    Corners: every inner corner projected through ``rig.camera``.  Stripes: for every projector
    column in ``columns``, ``samples_per_line`` points of its light plane's intersection with the
    board's printed area, projected into the camera (noise added along u).
    """
    rng = np.random.default_rng(seed)
    cam = rig.camera
    jj, ii = np.mgrid[0:rows, 0:cols]
    X = np.stack([ii.ravel() * square_mm, jj.ravel() * square_mm, np.zeros(ii.size)], axis=1)
    cp, cu, cx_, sp, su, sc = [], [], [], [], [], []
    n_pl, d_pl = rig.column_planes(np.asarray(columns, np.float64))
    for i, (rv, tv) in enumerate(zip(rvecs, tvecs)):
        R = rodrigues(rv)
        t = np.asarray(tv, np.float64)
        uv = cam.project(X @ R.T + t)
        cp.append(np.full(len(X), i)), cu.append(uv + rng.normal(0, corner_noise_px, uv.shape) if corner_noise_px else uv)
        cx_.append(X)
        # board line y = const: plane n.(R p + t) = d, p = (x, y, 0) -> solve for x at sampled y
        ys = np.linspace(-0.8 * square_mm, (rows - 0.2) * square_mm, samples_per_line)
        for col, n, d in zip(columns, n_pl, d_pl):
            a = n @ R  # coefficients on board coords
            if abs(a[0]) < 1e-9:
                continue
            xs = (d - n @ t - a[1] * ys) / a[0]
            ok = (xs > -0.8 * square_mm) & (xs < (cols - 0.2) * square_mm)
            if not ok.any():
                continue
            pb = np.stack([xs[ok], ys[ok], np.zeros(ok.sum())], axis=1)
            q = cam.project(pb @ R.T + t)
            if stripe_noise_px:
                q = q + np.stack([rng.normal(0, stripe_noise_px, len(q)), np.zeros(len(q))], axis=1)
            sp.append(np.full(len(q), i)), su.append(q), sc.append(np.full(len(q), col, np.float64))
    return BundleData(np.concatenate(cp).astype(np.int64), np.concatenate(cu), np.concatenate(cx_),
                      np.concatenate(sp).astype(np.int64), np.concatenate(su), np.concatenate(sc),
                      len(rvecs))
