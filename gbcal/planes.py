"""Stripe boundaries on the calibration board -> 3D points -> light planes -> projector model.

Pipeline for one pose (all pure functions over numpy arrays):

1. :func:`gray_decode` -- every pixel's absolute stripe index from the Gray-code frames
   (bit = ``gray_b > gray_b_inv``), albedo-free: the per-bit difference is divided by the
   ``white - black`` range, and pixels with too little range (black squares, shadow) or too
   little contrast on any bit are reported as -1.
2. :func:`gray_boundaries` -- sub-pixel boundary samples ``(u, v, k)``.  In a binary-reflected
   Gray code exactly one bit flips at every stripe boundary ``k`` (bit ``ctz(k)``), so the
   boundary is where that bit's frame crosses its inverse -- the classic complementary-pattern
   crossing, unbiased by albedo, blur and colour crosstalk.  It is located by linear
   interpolation of ``(gray - gray_inv) / (white - black)`` between the two straddling pixels of
   each image row.  A sample is kept only if the step is clean (two confident pixels each side,
   every other bit confident and unchanged, no albedo edge within the 4 pixels).  The boundary
   lies at projector column ``k * stripe_px - 0.5``, the light plane ``index = k``.
3. :func:`backproject_to_board` -- camera ray x board plane (board pose) -> 3D points, mm.
4. :func:`fit_plane` / :func:`fit_planes` -- robust SVD plane per boundary index.
5. :func:`projector_from_planes` -- the pinhole projector (centre, orientation, fx, cx) whose
   column planes (:func:`gbscan.rig.column_planes`) best match the fitted planes: all column
   planes share one line (the projector's y axis through its centre), and the normal of column
   ``x`` is parallel to ``fx * X_p - (x - cx) * Z_p``.

Conventions: pixels ``(u, v)`` with centres at integers, camera frame mm (OpenCV), planes
``n . p = d`` with unit ``n`` (positive camera-x component).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gbscan.camera import Camera
from gbscan.errors import GBError
from gbscan.pattern import PatternSpec
from gbscan.rig import Projector, Rig

from .patterns import gray_decode as _gray_decode
from .patterns import n_gray_bits


# -- 1. Gray code ------------------------------------------------------------------------------
@dataclass(frozen=True)
class GrayDecoding:
    """Per-pixel Gray-code decoding of one pose.

    index : (H, W) int64 absolute stripe index, -1 where unreliable.
    raw_index : (H, W) int64 stripe index decoded without any contrast test (for boundaries).
    diff : (B, H, W) float32 ``(gray_b - gray_b_inv) / (white - black)`` per bit, MSB first.
    range : (H, W) float32 ``white - black`` grey levels (the pixel's usable signal).
    lit : (H, W) bool ``range >= min_range``.
    """

    index: np.ndarray
    raw_index: np.ndarray
    diff: np.ndarray
    range: np.ndarray
    lit: np.ndarray


def to_gray_f32(image: np.ndarray) -> np.ndarray:
    """RGB (H, W, 3) or grey (H, W) uint8 -> grey float32 (H, W), mean of the channels."""
    a = np.asarray(image)
    if a.ndim == 3:
        if a.dtype == np.uint8:  # integer sum first: 3x faster than a float mean
            return (a[..., 0].astype(np.uint16) + a[..., 1] + a[..., 2]).astype(np.float32) * np.float32(1.0 / 3.0)
        return a.astype(np.float32).mean(axis=2)
    return a.astype(np.float32)


def gray_decode(frames: dict, spec: PatternSpec, *, min_range: float = 12.0,
                min_contrast: float = 0.15) -> GrayDecoding:
    """Decode the Gray-code frames of one pose.

    frames : name -> image (H, W) or (H, W, 3) uint8/float; needs ``white``, ``black`` and every
        ``gray_NN`` / ``gray_NN_inv`` of :func:`gbcal.patterns.frame_names`.
    min_range : grey levels ``white - black`` below which a pixel is unlit/too dark (black squares
        of the board reflect little of the projector's light and are masked here).
    min_contrast : ``|gray - gray_inv| / (white - black)`` every bit must reach for ``index``.
    """
    nb = n_gray_bits(spec)
    need = ["white", "black"] + [f"gray_{b:02d}{s}" for b in range(nb) for s in ("", "_inv")]
    missing = [n for n in need if n not in frames]
    if missing:
        raise GBError(f"Gray-code decoding needs frames {', '.join(missing)}; capture every frame "
                      "listed by 'gbcal patterns'")
    white = to_gray_f32(frames["white"])
    black = to_gray_f32(frames["black"])
    rng = white - black
    lit = rng >= float(min_range)
    safe = np.where(lit, rng, np.inf).astype(np.float32)
    diff = np.empty((nb,) + white.shape, np.float32)
    code = np.zeros(white.shape, np.int64)
    confident = lit.copy()
    for b in range(nb):
        d = (to_gray_f32(frames[f"gray_{b:02d}"]) - to_gray_f32(frames[f"gray_{b:02d}_inv"])) / safe
        diff[b] = d
        code = (code << 1) | (d > 0)
        confident &= np.abs(d) >= min_contrast
    raw = _gray_decode(code)
    raw = np.where(lit & (raw < spec.n_stripes), raw, -1)
    index = np.where(confident, raw, -1)
    return GrayDecoding(index, raw, diff, rng.astype(np.float32), lit)


# -- 2. sub-pixel boundaries -------------------------------------------------------------------
@dataclass(frozen=True)
class BoundarySamples:
    """Sub-pixel samples of stripe boundaries in one image.

    uv : (N, 2) float64 pixel ``(u, v)`` of the boundary on row ``v``.
    index : (N,) int64 boundary index ``k`` (between stripes k-1 and k).
    step : (N,) float32 normalised height of the crossing step (quality, ~2 for a sharp edge).
    """

    uv: np.ndarray
    index: np.ndarray
    step: np.ndarray

    def __len__(self) -> int:
        return int(self.index.size)

    def subset(self, keep: np.ndarray) -> "BoundarySamples":
        return BoundarySamples(self.uv[keep], self.index[keep], self.step[keep])


def _ctz(k: np.ndarray) -> np.ndarray:
    """Count of trailing zero bits of positive ints."""
    k = np.asarray(k, dtype=np.int64)
    low = k & -k
    return np.round(np.log2(low.astype(np.float64))).astype(np.int64)


def gray_boundaries(dec: GrayDecoding, spec: PatternSpec, *, min_contrast: float = 0.15,
                    max_albedo_change: float = 0.25, row_step: int = 1) -> BoundarySamples:
    """Sub-pixel stripe-boundary samples along image rows from a :class:`GrayDecoding`.

    For boundary ``k`` the flipping bit ``b = B - 1 - ctz(k)`` (MSB-first frame order) changes
    sign between pixels ``u`` and ``u + 1``; the zero of its normalised difference is
    ``u + D(u) / (D(u) - D(u+1))``.  Kept only where pixels ``u-1, u`` decode to ``k-1`` and
    ``u+1, u+2`` to ``k``, every non-flipping bit is confident at ``u`` and ``u+1``, the flipping
    bit is confident at ``u-1`` and ``u+2``, and ``white - black`` varies by less than
    ``max_albedo_change`` (relative) over the four pixels.  ``row_step`` thins rows.
    """
    nb, H, W = dec.diff.shape
    if W < 4:
        return BoundarySamples(np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros(0, np.float32))
    raw = dec.raw_index[::row_step]
    D = dec.diff[:, ::row_step]
    rng = dec.range[::row_step]
    rows = np.arange(0, H, row_step)
    a, b0, c, d = raw[:, :-3], raw[:, 1:-2], raw[:, 2:-1], raw[:, 3:]
    cand = (b0 >= 0) & (a == b0) & (c == b0 + 1) & (d == c) & (c >= 1) & (c < spec.n_stripes)
    vi, ui = np.nonzero(cand)
    u = ui + 1  # left straddling pixel
    k = raw[vi, u + 1]
    bit = nb - 1 - _ctz(k)
    dl, dr = D[bit, vi, u], D[bit, vi, u + 1]
    dl2, dr2 = D[bit, vi, u - 1], D[bit, vi, u + 2]
    ok = (np.abs(dl2) >= min_contrast) & (np.abs(dr2) >= min_contrast) & (dl * dr < 0)
    ok &= (np.sign(dl2) == np.sign(dl)) & (np.sign(dr2) == np.sign(dr))
    # every other bit confident at u and u+1
    conf = np.abs(D[:, vi, u]) >= min_contrast
    conf &= np.abs(D[:, vi, u + 1]) >= min_contrast
    conf[bit, np.arange(bit.size)] = True
    ok &= conf.all(axis=0)
    r4 = np.stack([rng[vi, u - 1], rng[vi, u], rng[vi, u + 1], rng[vi, u + 2]])
    ok &= r4.min(axis=0) >= (1.0 - max_albedo_change) * r4.max(axis=0)
    vi, u, k, dl, dr = vi[ok], u[ok], k[ok], dl[ok], dr[ok]
    t = dl / (dl - dr)
    uv = np.stack([u + t.astype(np.float64), rows[vi].astype(np.float64)], axis=-1)
    return BoundarySamples(uv, k.astype(np.int64), np.abs(dl - dr).astype(np.float32))


# -- 3. back-projection ------------------------------------------------------------------------
def backproject_to_board(camera: Camera, uv: np.ndarray, R_cam_board: np.ndarray,
                         t_cam_board: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) -> their points on the board plane z = 0: (camera frame (N, 3) mm,
    board frame (N, 3) mm).  Rays nearly parallel to the board give NaN."""
    R = np.asarray(R_cam_board, np.float64)
    t = np.asarray(t_cam_board, np.float64).ravel()
    xn = camera.normalize(np.asarray(uv, np.float64).reshape(-1, 2))
    ray = np.concatenate([xn, np.ones((xn.shape[0], 1))], axis=1)
    n = R[:, 2]
    den = ray @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = np.where(np.abs(den) > 1e-9, (n @ t) / den, np.nan)
    p_cam = ray * lam[:, None]
    p_board = (p_cam - t) @ R
    return p_cam, p_board


def on_board(p_board: np.ndarray, cols: int, rows: int, square_mm: float,
             inset_squares: float = 0.1) -> np.ndarray:
    """(N,) bool: board-frame points inside the printed checker area (one square beyond the
    outer inner corners), shrunk by ``inset_squares``."""
    lo = -(1.0 - inset_squares) * square_mm
    hx = (cols - 1 + 1.0 - inset_squares) * square_mm
    hy = (rows - 1 + 1.0 - inset_squares) * square_mm
    x, y = p_board[:, 0], p_board[:, 1]
    return (x >= lo) & (x <= hx) & (y >= lo) & (y <= hy)


# -- 4. plane fits -----------------------------------------------------------------------------
@dataclass(frozen=True)
class PlaneFit:
    """Planes fitted per boundary index (camera frame).

    index : (P,) int64; normal : (P, 3) unit, positive x; d : (P,) mm;
    rms_mm : (P,) inlier RMS distance; n_points, n_inliers : (P,) int64.
    sample_inlier : (N,) bool per input sample: used by (an inlier of) its index's plane.
    """

    index: np.ndarray
    normal: np.ndarray
    d: np.ndarray
    rms_mm: np.ndarray
    n_points: np.ndarray
    n_inliers: np.ndarray
    sample_inlier: np.ndarray


def fit_plane(points: np.ndarray, *, iterations: int = 3, k_sigma: float = 3.5,
              min_sigma_mm: float = 1e-3):
    """Robust plane through points (N, 3) mm: SVD, then iteratively drop points farther than
    ``k_sigma`` robust sigmas (1.4826 MAD).  Returns (unit normal (3,), d, inlier mask (N,),
    singular values (3,)); the normal has a positive x component."""
    p = np.asarray(points, np.float64)
    keep = np.all(np.isfinite(p), axis=1)
    if keep.sum() < 3:
        raise GBError(f"a plane needs at least 3 points, got {int(keep.sum())}")
    s = np.zeros(3)
    for _ in range(iterations + 1):
        c = p[keep].mean(axis=0)
        _, s, vt = np.linalg.svd(p[keep] - c, full_matrices=False)
        n = vt[2]
        res = (p - c) @ n
        sigma = max(1.4826 * np.median(np.abs(res[keep])), min_sigma_mm)
        new = np.isfinite(res) & (np.abs(res) <= k_sigma * sigma)
        if new.sum() < 3 or np.array_equal(new, keep):
            break
        keep = new
    if n[0] < 0:
        n = -n
    return n, float(n @ c), keep, s


def fit_planes(points: np.ndarray, index: np.ndarray, *, min_points: int = 30,
               min_spread: float = 0.02) -> PlaneFit:
    """One robust plane per boundary index from 3D samples (N, 3) mm with indices (N,).

    Indices with fewer than ``min_points`` samples, or whose samples are nearly collinear (second
    singular value below ``min_spread`` times the first: seen on one board pose only), are left
    out.
    """
    index = np.asarray(index, np.int64)
    out = {k: [] for k in ("index", "normal", "d", "rms_mm", "n_points", "n_inliers")}
    sample_inlier = np.zeros(index.size, bool)
    order = np.argsort(index, kind="stable")
    idx_sorted = index[order]
    uniq, starts = np.unique(idx_sorted, return_index=True)
    ends = np.append(starts[1:], idx_sorted.size)
    for k, s0, s1 in zip(uniq, starts, ends):
        sel = order[s0:s1]
        if sel.size < min_points:
            continue
        n, d, keep, sv = fit_plane(points[sel])
        if sv[1] < min_spread * sv[0]:
            continue
        res = points[sel][keep] @ n - d
        sample_inlier[sel[keep]] = True
        out["index"].append(k)
        out["normal"].append(n)
        out["d"].append(d)
        out["rms_mm"].append(float(np.sqrt(np.mean(res ** 2))))
        out["n_points"].append(sel.size)
        out["n_inliers"].append(int(keep.sum()))
    return PlaneFit(np.array(out["index"], np.int64), np.array(out["normal"], np.float64).reshape(-1, 3),
                    np.array(out["d"], np.float64), np.array(out["rms_mm"], np.float64),
                    np.array(out["n_points"], np.int64), np.array(out["n_inliers"], np.int64), sample_inlier)


# -- 5. projector from planes ------------------------------------------------------------------
def projector_from_planes(columns: np.ndarray, normals: np.ndarray, d: np.ndarray, *,
                          projector_size: tuple[int, int], scene_point: np.ndarray,
                          camera: Camera) -> Rig:
    """The pinhole projector whose column planes best match planes ``normals . p = d``.

    columns : (P,) projector columns (px) of the planes; normals (P, 3) unit; d (P,) mm.
    scene_point : (3,) a point the projector lights (e.g. the mean board point), which fixes
        the projector's viewing direction.  The centre's position along the projector's y axis
        is unobservable from column planes (gauge): it is put at camera height y = 0.
    Returns a :class:`gbscan.rig.Rig` (projector fy = fx, cy at the image centre: the stripes
    do not observe them).  Needs >= 3 planes spread over the projector width.
    """
    x = np.asarray(columns, np.float64)
    N = np.asarray(normals, np.float64)
    d = np.asarray(d, np.float64)
    if x.size < 3 or np.ptp(x) < 1e-6:
        raise GBError(f"estimating the projector needs at least 3 light planes spread across the "
                      f"projector, got {x.size}; the board must catch more stripes")
    # common line: direction = null vector of the normals, point = least squares solution
    _, sv, vt = np.linalg.svd(N, full_matrices=False)
    ell = vt[2]
    p0, *_ = np.linalg.lstsq(N, d, rcond=None)
    # 2D basis of the plane orthogonal to the line
    e1 = np.cross(ell, [0.0, 0.0, 1.0])
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross(ell, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(ell, e1)
    n2 = np.stack([N @ e1, N @ e2], axis=1)
    n2 /= np.linalg.norm(n2, axis=1, keepdims=True)
    # n_k parallel to a + x_k b:  n1 (a2 + x b2) - n2 (a1 + x b1) = 0, linear in (a1, a2, b1, b2)
    A = np.stack([-n2[:, 1], n2[:, 0], -n2[:, 1] * x, n2[:, 0] * x], axis=1)
    _, _, vt2 = np.linalg.svd(A, full_matrices=False)
    a1, a2, b1, b2 = vt2[-1]
    a3 = a1 * e1 + a2 * e2
    b3 = b1 * e1 + b2 * e2
    scale = np.linalg.norm(b3)
    if scale < 1e-12:
        raise GBError("the light planes do not fit a pinhole projector (degenerate plane set)")
    a3, b3 = a3 / scale, b3 / scale
    Z = -b3
    sp = np.asarray(scene_point, np.float64)
    # centre: any point of the common line gives the same planes (gauge); take the one at the
    # camera's y = 0 height when the line is roughly vertical (the usual rig), else the one
    # nearest the scene point
    if abs(ell[1]) > 0.5:
        centre = p0 + ell * (-p0[1] / ell[1])
    else:
        centre = p0 + ell * (ell @ (sp - p0))
    # choose the overall sign so that the projector looks at the scene
    if Z @ (sp - centre) < 0:
        Z, a3 = -Z, -a3
    cx = float(a3 @ Z)
    xv = a3 - cx * Z
    fx = float(np.linalg.norm(xv))
    X = xv / fx
    Y = np.cross(Z, X)
    R = np.stack([X, Y, Z], axis=1)
    W, H = projector_size
    K = np.array([[fx, 0.0, cx], [0.0, fx, (H - 1) / 2.0], [0.0, 0.0, 1.0]])
    return Rig(camera, Projector(W, H, K), R, centre)
