"""Camera-only calibration from checkerboard captures (Zhang's method via OpenCV).

Conventions: pixels ``(u, v)`` with pixel centres at integers, camera frame OpenCV's (x right, y
down, z forward), mm.  Board poses ``p_cam = R_cam_board @ p_board + t_cam_board`` (board frame:
:mod:`gbcal.board`).  Distortion is OpenCV's ``[k1, k2, p1, p2, k3]`` (``gbscan.camera``).

Distortion models (``model=``):

==============  =========================================================================
``k1k2p1p2k3``  OpenCV's full five-parameter model
``k1k2p1p2``    k3 fixed at zero -- Bouguet's toolbox default, steadier with few captures
``k1k2``        radial only (p1 = p2 = k3 = 0)
``k1``          one radial term
``none``        pinhole without distortion
==============  =========================================================================

``calibrate_camera`` checks the capture set first (at least 3 captures, one image size, board
orientations that make the intrinsics observable), then calibrates with OpenCV
(``calibrateCameraExtended``), drops -- one at a time, worst first -- captures whose reprojection
RMS is far above the others and recalibrates, and finally polishes intrinsics and poses together
in float64 (OpenCV takes float32 corners, ~1e-5 px) by Levenberg-Marquardt on OpenCV's analytic
``projectPoints`` Jacobian, which also gives the parameter covariance.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from gbscan.camera import Camera
from gbscan.errors import GBError

from .board import Board, Detection

MODELS = ("k1k2p1p2k3", "k1k2p1p2", "k1k2", "k1", "none")
PARAM_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
#: Orientation spread (deg) below which the boards count as parallel (intrinsics unobservable).
MIN_TILT_SPREAD_DEG = 5.0
MIN_VIEWS = 3


@dataclass(eq=False)
class ViewResult:
    """One input capture.

    used : it took part in the final calibration.
    reason : why not ("" when used): not detected, too few corners, or an outlier.
    rms_px : reprojection RMS with the final camera (NaN without corners); for a rejected
        capture, measured after fitting its pose alone (``board_pose``).
    R, t : board pose (3, 3), (3,) mm (None without corners).
    residuals_px : (N, 2) observed minus projected corners (None without corners).
    """

    index: int
    used: bool
    reason: str = ""
    rms_px: float = float("nan")
    R: np.ndarray | None = None
    t: np.ndarray | None = None
    residuals_px: np.ndarray | None = None
    name: str = ""


@dataclass(eq=False)
class CameraResult:
    """Calibrated camera, per-capture poses and residuals, parameter uncertainties.

    rms_px : overall reprojection RMS (px) over the used captures' corners.
    std : 1-sigma standard deviation of each *estimated* parameter (fx, fy, cx, cy in px;
        k's unitless): ``sqrt(diag((J^T J)^-1) * rms^2)`` of the final float64 fit, the same
        estimate as OpenCV's ``stdDeviationsIntrinsics``.
    views : one :class:`ViewResult` per input, in input order.
    warnings : non-fatal doubts about the result (weakly observed parameters, ...).
    orientation_spread_deg : largest angle between the used boards' normals (fitted poses); the
        intrinsics are well observed from about 20 deg on.
    """

    camera: Camera
    rms_px: float
    std: dict[str, float]
    views: list[ViewResult]
    model: str
    warnings: list[str] = field(default_factory=list)
    orientation_spread_deg: float = float("nan")

    @property
    def used(self) -> np.ndarray:
        """(V,) bool: which inputs took part."""
        return np.array([v.used for v in self.views], dtype=bool)

    @property
    def R_cam_board(self) -> np.ndarray:
        """(V, 3, 3) board rotations by input index; NaN where a capture has no corners."""
        return np.stack([v.R if v.R is not None else np.full((3, 3), np.nan) for v in self.views])

    @property
    def t_cam_board(self) -> np.ndarray:
        """(V, 3) board translations (mm) by input index; NaN where a capture has no corners."""
        return np.stack([v.t if v.t is not None else np.full(3, np.nan) for v in self.views])

    def residuals_dict(self) -> dict:
        """Plain dict for the calibration file's ``residuals`` field."""
        per = []
        for v in self.views:
            e = {"capture": v.name or str(v.index), "used": v.used}
            if np.isfinite(v.rms_px):
                err = np.linalg.norm(v.residuals_px, axis=1)
                e.update(rms_px=round(float(v.rms_px), 5), max_px=round(float(err.max()), 5),
                         corners=int(err.size))
            if v.reason:
                e["reason"] = v.reason
            per.append(e)
        return {"camera_rms_px": round(float(self.rms_px), 5), "model": self.model,
                "captures_used": int(self.used.sum()),
                "orientation_spread_deg": round(float(self.orientation_spread_deg), 2), "captures": per}

    def uncertainty_dict(self) -> dict:
        """Plain dict for the calibration file's ``uncertainty`` field (1-sigma)."""
        return {"camera_std": {k: float(f"{v:.6g}") for k, v in self.std.items()}}

    def calibration(self, board: Board, corner_refiner: str):
        """The camera-only :class:`gbscan.calibfile.Calibration` ``gbcal camera`` writes (no planes;
        ``created.board``, ``residuals`` with ``corner_refiner``, ``uncertainty``): a file that
        ``gbcal calibrate --camera`` can hold a rig's camera to."""
        from gbscan.calibfile import Calibration

        return Calibration(self.camera, np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)), np.zeros(0),
                           created={"board": {"cols": board.cols, "rows": board.rows, "square_mm": board.square_mm}},
                           residuals={**self.residuals_dict(), "corner_refiner": corner_refiner},
                           uncertainty=self.uncertainty_dict())


# -- inputs ------------------------------------------------------------------------------------
def _as_points(item, board: Board, i: int) -> tuple[np.ndarray | None, tuple[int, int] | None]:
    if item is None:
        return None, None
    if isinstance(item, Detection):
        return np.asarray(item.corners, dtype=np.float64), tuple(item.image_size)
    a = np.asarray(item, dtype=np.float64)
    if a.shape != (board.n_corners, 2):
        raise GBError(f"capture {i}: expected ({board.n_corners}, 2) corner pixels for a {board}, got shape "
                      f"{a.shape}")
    if not np.all(np.isfinite(a)):
        raise GBError(f"capture {i}: corner pixels hold NaN or infinity")
    return a, None


def _flags(model: str, fix_aspect: bool, zero_tangent: bool) -> int:
    import cv2

    if model not in MODELS:
        raise GBError(f"unknown distortion model '{model}'; choose one of {', '.join(MODELS)}")
    f = 0
    if model in ("k1k2p1p2", "k1k2", "k1", "none"):
        f |= cv2.CALIB_FIX_K3
    if model in ("k1k2", "k1", "none") or zero_tangent:
        f |= cv2.CALIB_ZERO_TANGENT_DIST
    if model in ("k1", "none"):
        f |= cv2.CALIB_FIX_K2
    if model == "none":
        f |= cv2.CALIB_FIX_K1
    if fix_aspect:
        f |= cv2.CALIB_FIX_ASPECT_RATIO
    return f


def _estimated(flags: int) -> list[str]:
    import cv2

    names = ["fx", "fy", "cx", "cy"]
    for k, fl in (("k1", cv2.CALIB_FIX_K1), ("k2", cv2.CALIB_FIX_K2)):
        if not flags & fl:
            names.append(k)
    if not flags & cv2.CALIB_ZERO_TANGENT_DIST:
        names += ["p1", "p2"]
    if not flags & cv2.CALIB_FIX_K3:
        names.append("k3")
    return names


# -- observability -----------------------------------------------------------------------------
def _homography(obj_xy: np.ndarray, img: np.ndarray) -> np.ndarray:
    """Normalised DLT homography board (x, y) mm -> pixels (no outlier handling: corners are clean)."""
    def norm(p):
        m = p.mean(axis=0)
        s = np.sqrt(2) / np.mean(np.linalg.norm(p - m, axis=1))
        return np.array([[s, 0, -s * m[0]], [0, s, -s * m[1]], [0, 0, 1.0]])

    T1, T2 = norm(obj_xy), norm(img)
    a = np.c_[obj_xy, np.ones(len(obj_xy))] @ T1.T
    b = np.c_[img, np.ones(len(img))] @ T2.T
    rows = []
    for (x, y, _), (u, v, _) in zip(a, b):
        rows.append([-x, -y, -1, 0, 0, 0, u * x, u * y, u])
        rows.append([0, 0, 0, -x, -y, -1, v * x, v * y, v])
    _, _, vt = np.linalg.svd(np.asarray(rows), full_matrices=False)
    H = vt[-1].reshape(3, 3)
    H = np.linalg.inv(T2) @ H @ T1
    return H / H[2, 2]


def board_normals(points: Sequence[np.ndarray], board: Board, image_size: tuple[int, int],
                  focal_px: float | None = None) -> np.ndarray:
    """(V, 3) unit board normals (camera frame, pointing away from the camera) from the corners alone.

    The focal length, when not given, comes from Zhang's closed form with the principal point
    at the image centre and square pixels (median over the captures; 0.9 x image width if that
    fails).  Enough to tell whether the orientations differ; not a calibration.
    """
    obj = board.object_points()[:, :2]
    Hs = [_homography(obj, p) for p in points]
    cx, cy = (image_size[0] - 1) / 2.0, (image_size[1] - 1) / 2.0
    C = np.array([[1.0, 0, -cx], [0, 1.0, -cy], [0, 0, 1.0]])
    if focal_px is None:
        f2 = []
        for H in Hs:
            h = C @ H
            h1, h2 = h[:, 0], h[:, 1]
            # h1^T w h2 = 0 and h1^T w h1 = h2^T w h2 with w = diag(1/f^2, 1/f^2, 1)
            den = -(h1[0] * h2[0] + h1[1] * h2[1])
            if abs(h1[2] * h2[2]) > 1e-12 and den / (h1[2] * h2[2]) > 0:
                f2.append(den / (h1[2] * h2[2]))
            dd = (h2[2] ** 2 - h1[2] ** 2)
            num = (h1[0] ** 2 + h1[1] ** 2 - h2[0] ** 2 - h2[1] ** 2)
            if abs(dd) > 1e-12 and num / dd > 0:
                f2.append(num / dd)
        focal_px = float(np.sqrt(np.median(f2))) if f2 else 0.9 * image_size[0]
        if not np.isfinite(focal_px) or not (0.1 * image_size[0] < focal_px < 50 * image_size[0]):
            focal_px = 0.9 * image_size[0]
    Kinv = np.linalg.inv(np.array([[focal_px, 0, cx], [0, focal_px, cy], [0, 0, 1.0]]))
    normals = []
    for H in Hs:
        M = Kinv @ H
        r1, r2 = M[:, 0] / np.linalg.norm(M[:, 0]), M[:, 1] / np.linalg.norm(M[:, 1])
        n = np.cross(r1, r2)
        n /= np.linalg.norm(n)
        normals.append(n if n[2] > 0 else -n)
    return np.array(normals)


def check_observability(points: Sequence[np.ndarray], board: Board, image_size: tuple[int, int],
                        min_spread_deg: float = MIN_TILT_SPREAD_DEG) -> tuple[float, float]:
    """Raise GBError when the boards' orientations leave the intrinsics unobservable.

    Returns ``(spread_deg, max_tilt_deg)``: the largest angle between two board normals and the
    largest angle between a board normal and the optical axis.
    """
    n = board_normals(points, board, image_size)
    cosang = np.clip(n @ n.T, -1, 1)
    spread = float(np.degrees(np.arccos(cosang.min())))
    tilt = float(np.degrees(np.arccos(np.clip(n[:, 2], -1, 1))).max())
    if spread < min_spread_deg:
        if tilt < min_spread_deg:
            what = ("the boards all face the camera squarely, so the focal lengths fx, fy cannot be told "
                    "from the board distance, nor the principal point cx, cy from the board position")
        else:
            what = ("the boards all share one orientation (tilted %.0f deg), which constrains only two of "
                    "fx, fy, cx, cy; fx, fy and cx, cy are not separately observable" % tilt)
        raise GBError(f"degenerate capture set: board orientations differ by at most {spread:.1f} deg "
                      f"(need {min_spread_deg:.0f}+): {what}. Add captures with the board tilted 20-45 deg "
                      "about different axes")
    return spread, tilt


# -- calibration -------------------------------------------------------------------------------
def calibrate_camera(detections_or_points: Sequence, board: Board, image_size: tuple[int, int] | None = None, *,
                     model: str = "k1k2p1p2k3", fix_aspect: bool = False, zero_tangent: bool = False,
                     names: Sequence[str] | None = None, reject_outliers: bool = True,
                     outlier_factor: float = 3.0, outlier_floor_px: float = 0.3,
                     check_orientations: bool = True) -> CameraResult:
    """Calibrate one camera from checkerboard corners.

    detections_or_points : per capture a :class:`~gbcal.board.Detection`, an (N, 2) array of
        corner pixels in the board's order, or None (capture without a board; reported, skipped).
    image_size : (width, height) px; required when no Detection is given, else checked against
        every Detection's size.
    model : distortion model (module docstring).  fix_aspect: fx/fy held at 1.  zero_tangent:
        p1 = p2 = 0 in any model.
    names : labels of the captures for messages and the ``residuals`` field (default indices).
    reject_outliers : drop, one at a time worst first, a capture whose RMS exceeds both
        ``outlier_factor`` x the median RMS of the others and ``outlier_floor_px``.

    Raises GBError for fewer than 3 usable captures, mixed image sizes, parallel boards.
    """
    import cv2

    items = list(detections_or_points)
    n_in = len(items)
    names = [str(x) for x in names] if names is not None else [str(i) for i in range(n_in)]
    if len(names) != n_in:
        raise GBError(f"calibrate_camera: {len(names)} names for {n_in} captures")
    flags = _flags(model, fix_aspect, zero_tangent)
    pts, sizes = [], []
    for i, it in enumerate(items):
        p, s = _as_points(it, board, i)
        pts.append(p)
        sizes.append(s)
    known = {s for s in sizes if s is not None}
    if image_size is not None:
        image_size = (int(image_size[0]), int(image_size[1]))
        if image_size[0] <= 0 or image_size[1] <= 0:
            raise GBError(f"image_size must be positive (width, height), got {image_size}")
        known.add(image_size)
    if len(known) > 1:
        by = {}
        for nm, s in zip(names, sizes):
            if s is not None:
                by.setdefault(s, []).append(nm)
        desc = "; ".join(f"{w}x{h}: {', '.join(v[:4])}{' ...' if len(v) > 4 else ''}" for (w, h), v in by.items())
        raise GBError(f"captures have mixed image sizes ({desc}); calibrate each camera/resolution separately")
    if not known:
        raise GBError("calibrate_camera: image_size (width, height) is required when corners are given as arrays")
    size = known.pop()
    views = [ViewResult(i, False, "", name=names[i]) for i in range(n_in)]
    for i, p in enumerate(pts):
        if p is None:
            views[i].reason = "no board detected"
        elif np.any(p < -0.5) or np.any(p[:, 0] > size[0] - 0.5) or np.any(p[:, 1] > size[1] - 0.5):
            raise GBError(f"capture {names[i]}: corners lie outside the {size[0]}x{size[1]} image")
    active = [i for i, p in enumerate(pts) if p is not None]
    if len(active) < MIN_VIEWS:
        raise GBError(f"too few captures with a detected board: {len(active)} of {n_in} (need at least "
                      f"{MIN_VIEWS}, 10-20 recommended, with the board at different tilts and distances)")
    if check_orientations:
        check_observability([pts[i] for i in active], board, size)

    obj = board.object_points().astype(np.float32)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)

    def run(idx):
        K0 = np.eye(3)
        if fix_aspect:
            K0[0, 0] = K0[1, 1] = 1.0
        try:
            out = cv2.calibrateCameraExtended([obj] * len(idx), [pts[i].astype(np.float32) for i in idx], size,
                                              K0, np.zeros(5), flags=flags, criteria=crit)
        except cv2.error as e:
            raise GBError(f"OpenCV calibration failed on {len(idx)} captures ({str(e).strip().splitlines()[-1]}); "
                          "add captures with more varied board tilts") from None
        return out

    dropped: dict[int, str] = {}
    while True:
        rms, K, dist, rvecs, tvecs, _std_int, _std_ext, per_view = run(active)
        per_view = np.asarray(per_view, dtype=np.float64).ravel()
        if not reject_outliers or len(active) <= MIN_VIEWS:
            break
        worst = int(np.argmax(per_view))
        others = np.delete(per_view, worst)
        med = float(np.median(others))
        if per_view[worst] > max(outlier_factor * med, outlier_floor_px):
            i = active[worst]
            ratio = per_view[worst] / max(med, 1e-12)
            dropped[i] = (f"outlier: reprojection RMS {per_view[worst]:.3f} px is {ratio:.1f}x "
                          f"the median {med:.3f} px of the other captures (board moved, blurred, or bent?)")
            active = active[:worst] + active[worst + 1:]
            continue
        break

    dist = np.asarray(dist, dtype=np.float64).ravel()[:5]
    if dist.size < 5:
        dist = np.r_[dist, np.zeros(5 - dist.size)]
    est = _estimated(flags)
    aspect = None
    if fix_aspect:
        est = [n for n in est if n != "fx"]
        aspect = float(K[0, 0] / K[1, 1])
    obj64 = board.object_points()
    K, dist, rvecs, tvecs, std, _ = _polish(obj64, [pts[i] for i in active], np.asarray(K, dtype=np.float64), dist,
                                            [np.ravel(r) for r in rvecs], [np.ravel(t) for t in tvecs], est, aspect)
    std = {k: std[k] for k in PARAM_NAMES if k in std}
    camera = Camera(size[0], size[1], K, dist)
    for j, i in enumerate(active):
        R, _ = cv2.Rodrigues(np.asarray(rvecs[j], dtype=np.float64))
        t = np.asarray(tvecs[j], dtype=np.float64).ravel()
        res = pts[i] - camera.project(obj64 @ R.T + t)
        views[i] = ViewResult(i, True, "", float(np.sqrt(np.mean(np.sum(res**2, axis=1)))), R, t, res, names[i])
    for i, why in dropped.items():
        R, t = board_pose(camera, pts[i], board)
        res = pts[i] - camera.project(obj64 @ R.T + t)
        views[i] = ViewResult(i, False, why, float(np.sqrt(np.mean(np.sum(res**2, axis=1)))), R, t, res, names[i])

    all_res = np.concatenate([views[i].residuals_px for i in active])
    rms_px = float(np.sqrt(np.mean(np.sum(all_res**2, axis=1))))
    warnings = []
    for k, s in std.items():
        ref = {"fx": camera.K[0, 0], "fy": camera.K[1, 1], "cx": camera.width, "cy": camera.height}.get(k)
        if ref is not None and s > 0.02 * ref:
            warnings.append(f"{k} is weakly determined (1-sigma {s:.2f} px); add captures with more varied tilts")
    normals = np.array([views[i].R[:, 2] for i in active])
    spread = float(np.degrees(np.arccos(np.clip(normals @ normals.T, -1, 1))).max())
    if spread < 15.0:
        warnings.append(f"board orientations span only {spread:.1f} deg; tilt the board more (20-45 deg) for "
                        "well-determined focal lengths and principal point")
    return CameraResult(camera, rms_px, std, views, model, warnings, spread)


def _projection_jacobian(camera_K: np.ndarray, dist: np.ndarray, rvec: np.ndarray, tvec: np.ndarray,
                         obj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Projected pixels (N, 2) and the analytic Jacobian (2N, 15) of ``cv2.projectPoints`` in float64.

    Columns: rvec (3), tvec (3), fx, fy, cx, cy, k1, k2, p1, p2, k3; rows u0, v0, u1, v1, ...
    """
    import cv2

    q, J = cv2.projectPoints(np.ascontiguousarray(obj, dtype=np.float64), np.asarray(rvec, dtype=np.float64),
                             np.asarray(tvec, dtype=np.float64), camera_K, dist)
    return q.reshape(-1, 2), J


def _polish(obj: np.ndarray, pts: list[np.ndarray], K: np.ndarray, dist: np.ndarray, rvecs: list[np.ndarray],
            tvecs: list[np.ndarray], free: list[str], aspect: float | None, max_iter: int = 60):
    """Levenberg-Marquardt in float64 over the free intrinsics and every pose (dense normal equations).

    OpenCV's calibrateCamera takes float32 points, which caps its accuracy near 1e-5 px; this
    polish reaches the float64 optimum (exact recovery on clean data) and yields the covariance.
    ``free`` names the free intrinsics among PARAM_NAMES; with ``aspect`` (fx/fy held), fx
    follows fy and is not in ``free``.  Returns (K, dist, rvecs, tvecs, std dict, rms_px).
    """
    V = len(pts)
    ni = len(free)
    col = [PARAM_NAMES.index(n) for n in free]  # position in the 9 intrinsics
    x_int = np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], dist[:5]].astype(np.float64)
    poses = np.concatenate([np.r_[np.ravel(r), np.ravel(t)] for r, t in zip(rvecs, tvecs)]).astype(np.float64)

    def unpack(xi):
        Kc = np.array([[xi[0], 0.0, xi[2]], [0.0, xi[1], xi[3]], [0.0, 0.0, 1.0]])
        return Kc, xi[4:9].copy()

    def evaluate(xi, ps):
        Kc, dc = unpack(xi)
        n = ni + 6 * V
        JTJ = np.zeros((n, n))
        JTr = np.zeros(n)
        cost = 0.0
        for v in range(V):
            q, J = _projection_jacobian(Kc, dc, ps[6 * v:6 * v + 3], ps[6 * v + 3:6 * v + 6], obj)
            r = (pts[v] - q).reshape(-1)  # observed - projected
            Ji = J[:, 6:][:, col].copy()
            if aspect is not None:  # fx = aspect * fy: d/dfy gains aspect * d/dfx
                Ji[:, free.index("fy")] += aspect * J[:, 6]
            Jp = J[:, :6]
            sl = slice(ni + 6 * v, ni + 6 * v + 6)
            JTJ[:ni, :ni] += Ji.T @ Ji
            JTJ[:ni, sl] += Ji.T @ Jp
            JTJ[sl, :ni] += Jp.T @ Ji
            JTJ[sl, sl] += Jp.T @ Jp
            JTr[:ni] += Ji.T @ r
            JTr[sl] += Jp.T @ r
            cost += float(r @ r)
        return cost, JTJ, JTr

    def step(xi, ps, delta):
        xi = xi.copy()
        xi[col] += delta[:ni]
        if aspect is not None:
            xi[0] = aspect * xi[1]
        return xi, ps + delta[ni:]

    if aspect is not None:
        x_int[0] = aspect * x_int[1]
    cost, JTJ, JTr = evaluate(x_int, poses)
    lam = 1e-6
    for _ in range(max_iter):
        A = JTJ + lam * np.diag(np.diag(JTJ))
        try:
            delta = np.linalg.solve(A, JTr)
        except np.linalg.LinAlgError:
            lam *= 10
            continue
        xi2, ps2 = step(x_int, poses, delta)
        cost2, JTJ2, JTr2 = evaluate(xi2, ps2)
        if cost2 <= cost:
            small = np.max(np.abs(delta[:ni]) / np.maximum(np.abs(x_int[col]), 1e-3)) < 1e-13
            x_int, poses, cost, JTJ, JTr = xi2, ps2, cost2, JTJ2, JTr2
            lam = max(lam / 10, 1e-12)
            if small or cost < 1e-24:
                break
        else:
            lam *= 10
            if lam > 1e8:
                break
    n_res = 2 * sum(p.shape[0] for p in pts)
    dof = max(n_res - (ni + 6 * V), 1)
    sigma2 = cost / dof
    try:
        cov = np.linalg.inv(JTJ)[:ni, :ni] * sigma2
        sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    except np.linalg.LinAlgError:
        sd = np.full(ni, np.inf)
    std = {n: float(v) for n, v in zip(free, sd)}
    if aspect is not None:
        std = {"fx": aspect * std["fy"], **std}
    Kc, dc = unpack(x_int)
    rv = [poses[6 * v:6 * v + 3].copy() for v in range(V)]
    tv = [poses[6 * v + 3:6 * v + 6].copy() for v in range(V)]
    return Kc, dc, rv, tv, std, float(np.sqrt(cost / (n_res / 2)))


def board_pose(camera: Camera, detection_or_corners, board: Board) -> tuple[np.ndarray, np.ndarray]:
    """Board pose ``(R (3, 3), t (3,) mm)`` with ``p_cam = R @ p_board + t`` from one capture's corners.

    IPPE (planar PnP) for the start, then Levenberg-Marquardt refinement of the reprojection error.
    """
    import cv2

    c = detection_or_corners.corners if isinstance(detection_or_corners, Detection) else detection_or_corners
    c = np.asarray(c, dtype=np.float64).reshape(-1, 2)
    if c.shape[0] != board.n_corners:
        raise GBError(f"board_pose: expected {board.n_corners} corners for a {board}, got {c.shape[0]}")
    obj = board.object_points()
    ok, rvec, tvec = cv2.solvePnP(obj, c, camera.K, camera.dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        ok, rvec, tvec = cv2.solvePnP(obj, c, camera.K, camera.dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise GBError("board_pose: PnP failed for this capture (corners inconsistent with a planar board?)")
    rvec, tvec = cv2.solvePnPRefineLM(obj, c, camera.K, camera.dist, rvec, tvec,
                                      (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14))
    R, _ = cv2.Rodrigues(rvec)
    return R, np.asarray(tvec, dtype=np.float64).ravel()
