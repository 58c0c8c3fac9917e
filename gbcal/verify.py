"""Does a calibration still hold?  Scan a flat checkerboard and measure it.

A calibration is right for one focus, zoom and mounting; after a knock, a refocus or a warm-up
the scans drift without saying so.  The board is the one known object at the rig: flat, with
squares of known size.  For a pose of it (the white frame for its corners, the scanning pattern
for its surface, as ``gbcal patterns`` / the guided capture take them), :func:`check_pose` scans
the pattern frame with the calibration and measures

* **flatness** (:func:`check_flatness`): a robust plane through the scanned board points, the
  residual RMS and 99th percentile (mm), and the *bow*: the peak-to-valley (mm) of the best
  quadratic surface left after the plane, over the board.  Noise shows in the RMS; a wrong lens
  distortion or light-plane model bends the plane, which the bow measures;
* **scale** (:func:`check_scale`): the detected corners' camera rays met with that plane give the
  corners in 3-D; their spacing against ``square_mm``.  A wrong baseline or focal length scales
  the whole scan (a 1 % baseline error: ~1 % scale, 6.5 mm at 650 mm), which a flatness check
  alone cannot see.

Pure functions over arrays (mm, camera frame); ``gbcal verify`` reads the frames and prints.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from gbscan.errors import GBError

#: the board region: the inner-corner grid grown by this many squares (to the white margin)
BOARD_GROW_SQUARES = 1.6
#: a pose's measured square size off ``square_mm`` by more than this fraction: rescale suspected.
#: A calibration estimated from a simulated typical session, checked on another session's poses:
#: 0.02-0.10 %; baseline 1 % off: ~1 %; focal length 1 % off: ~1 %.
SCALE_WARN = 0.003
#: bow (mm, peak to valley of the quadratic left after the plane) above this on a pose: the scan
#: bends.  Estimated calibration on fresh poses: 0.02-0.06 mm; camera distortion ignored: 0.6-1.9 mm.
BOW_WARN_MM = 0.12
#: residual RMS (mm) above this on a pose: noisy or partly wrong (decoding, a damaged plane table)
RMS_WARN_MM = 0.3
#: fewer scanned board points than this share of the board's image area (and 200): nothing measured (the
#: dark squares do not decode: a simulated typical pose keeps 15-40 %)
MIN_BOARD_FRAC = 0.05


@dataclass
class Flatness:
    """A plane through scanned points and how far they are from it (mm)."""

    n_points: int
    normal: tuple            # unit normal (toward the camera: its z < 0)
    offset_mm: float         # plane: normal . p + offset_mm = 0
    distance_mm: float       # distance of the camera centre to the plane
    tilt_deg: float          # angle between the plane's normal and the optical axis
    rms_mm: float            # residual RMS of the inliers
    p99_mm: float            # 99th percentile of |residual| of all points
    bow_mm: float            # peak to valley of the quadratic part of the residual over the points
    outlier_frac: float      # share of the points beyond the robust fit's cut


@dataclass
class Scale:
    """The detected corners, cast onto the scanned plane, against the board's squares."""

    n_corners: int
    square_mm: float
    measured_square_mm: float   # mean distance of neighbouring corners
    scale_error: float          # measured / square_mm - 1
    spacing_rms_mm: float       # RMS of the neighbouring distances' errors
    fit_rms_mm: float           # RMS after the best rigid fit of the board model


def fit_plane(points: np.ndarray, *, iterations: int = 4, k_sigma: float = 3.0,
              floor_mm: float = 0.05) -> tuple[np.ndarray, float, np.ndarray]:
    """Robust least-squares plane through (N, 3) points (mm): refit ``iterations`` times on the
    points within ``k_sigma`` robust sigmas (1.4826 MAD, at least ``floor_mm``) of the last fit.
    Returns the unit normal (3,) (toward the origin: ``normal . p < 0`` on the points' side), the
    offset ``d`` (``normal . p + d = 0``) and the inlier mask (N,)."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 3 or not np.isfinite(p).all():
        raise GBError(f"fit_plane: expected (N >= 3, 3) finite points, got {p.shape}")
    use = np.ones(len(p), bool)
    n = np.array([0.0, 0.0, -1.0])
    d = 0.0
    for _ in range(max(1, iterations)):
        if use.sum() < 3:
            break
        c = p[use].mean(axis=0)
        _, _, vt = np.linalg.svd(p[use] - c, full_matrices=False)
        n = vt[2]
        d = -float(n @ c)
        if d < 0:            # orient toward the camera centre
            n, d = -n, -d
        r = p @ n + d
        med = np.median(np.abs(r[use] - np.median(r[use])))
        cut = max(k_sigma * 1.4826 * med, floor_mm)
        use = np.abs(r) <= cut
    return n, d, use


def _plane_axes(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.cross(n, [0.0, 1.0, 0.0])
    if np.linalg.norm(a) < 1e-6:
        a = np.cross(n, [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    return a, np.cross(n, a)


def check_flatness(points: np.ndarray) -> Flatness:
    """Flatness of (N, 3) scanned points (mm) of a flat object (see the module docstring)."""
    p = np.asarray(points, dtype=np.float64)
    n, d, use = fit_plane(p)
    r = p @ n + d
    # the bow: quadratic in plane coordinates fitted to the inliers' residuals; its peak to valley
    # over the inliers (the plane terms are in the fit too, so only curvature remains)
    e1, e2 = _plane_axes(n)
    c = p[use].mean(axis=0)
    x, y = (p - c) @ e1, (p - c) @ e2
    A = np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], axis=1)
    coef, *_ = np.linalg.lstsq(A[use], r[use], rcond=None)
    quad = (A[use][:, :3] @ coef[:3])
    bow = float(quad.max() - quad.min()) if quad.size else float("nan")
    tilt = float(np.degrees(np.arccos(min(1.0, abs(float(n[2]))))))
    return Flatness(n_points=int(len(p)), normal=tuple(float(v) for v in n), offset_mm=float(d),
                    distance_mm=float(abs(d)), tilt_deg=tilt, rms_mm=float(np.sqrt(np.mean(r[use] ** 2))),
                    p99_mm=float(np.percentile(np.abs(r), 99)), bow_mm=bow,
                    outlier_frac=float(1.0 - use.mean()))


def corners_on_plane(rays: np.ndarray, normal, offset_mm: float) -> np.ndarray:
    """(N, 3) unit camera rays met with the plane ``normal . p + offset_mm = 0`` -> (N, 3) points
    (mm; NaN for rays parallel to the plane or meeting it behind the camera)."""
    r = np.asarray(rays, dtype=np.float64)
    n = np.asarray(normal, dtype=np.float64)
    den = r @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -float(offset_mm) / den
    t = np.where((np.abs(den) > 1e-9) & (t > 0), t, np.nan)
    return r * t[:, None]


def _rigid_fit_rms(model: np.ndarray, measured: np.ndarray) -> float:
    # Kabsch: the best rotation and translation of the board model onto the measured corners
    a = model - model.mean(axis=0)
    b = measured - measured.mean(axis=0)
    u, _, vt = np.linalg.svd(a.T @ b)
    s = np.ones(3)
    s[2] = np.sign(np.linalg.det(u @ vt))
    R = (u * s) @ vt
    return float(np.sqrt(np.mean(np.sum((a @ R - b) ** 2, axis=1))))


def check_scale(corners_3d: np.ndarray, cols: int, rows: int, square_mm: float) -> Scale:
    """The board's squares in (cols * rows, 3) corner positions (mm, row by row, x fastest: the
    order of ``gbcal.board.Board.object_points``) against ``square_mm``."""
    c = np.asarray(corners_3d, dtype=np.float64)
    if c.shape != (cols * rows, 3):
        raise GBError(f"check_scale: expected {cols * rows} corners (3-D), got {c.shape}")
    g = c.reshape(rows, cols, 3)
    dist = np.concatenate([np.linalg.norm(g[:, 1:] - g[:, :-1], axis=2).ravel(),
                           np.linalg.norm(g[1:] - g[:-1], axis=2).ravel()])
    dist = dist[np.isfinite(dist)]
    if dist.size == 0:
        raise GBError("check_scale: no pair of neighbouring corners met the plane")
    from .board import Board

    model = Board(cols, rows, square_mm).object_points()
    ok = np.isfinite(c).all(axis=1)
    m = float(dist.mean())
    return Scale(n_corners=int(ok.sum()), square_mm=float(square_mm), measured_square_mm=m,
                 scale_error=m / float(square_mm) - 1.0, spacing_rms_mm=float(np.sqrt(np.mean((dist - square_mm) ** 2))),
                 fit_rms_mm=_rigid_fit_rms(model[ok], c[ok]) if ok.sum() >= 3 else float("nan"))


def board_region(corners_px: np.ndarray, cols: int, rows: int, shape: tuple[int, int],
                 grow_squares: float = BOARD_GROW_SQUARES) -> np.ndarray:
    """(H, W) bool: the board around its detected inner corners (cols * rows, 2) px in an image of
    ``shape``: the inner-corner grid grown by ``grow_squares`` squares on every side, mapped through
    the homography of the corners (the printed grid reaches one square beyond the inner corners,
    the white margin further).  Under the stripe pattern a board scans on its white margin and
    rarely inside the grid (each white square is too small a surface to carry two markers), so
    the region must reach the margin; points beyond the board are the robust plane fit's
    outliers."""
    import cv2

    q = np.asarray(corners_px, dtype=np.float64).reshape(-1, 2)
    from .board import Board

    model = Board(cols, rows, 1.0).object_points()[:, :2]     # the grid in squares
    Hm, _ = cv2.findHomography(model, q)
    if Hm is None:
        raise GBError("board_region: the corners do not map to a grid")
    g = float(grow_squares)
    rect = np.array([[-g, -g], [cols - 1 + g, -g], [cols - 1 + g, rows - 1 + g], [-g, rows - 1 + g]], np.float64)
    quad = cv2.perspectiveTransform(rect[None], Hm)[0]
    mask = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(mask, np.round(quad).astype(np.int32), 1)
    return mask.astype(bool)


@dataclass
class PoseCheck:
    """One pose: its flatness and, with the corners, its scale (None when the board was not found)."""

    name: str
    flatness: Flatness
    scale: Scale | None
    board_px: int            # pixels of the board's region (0: no corners, the whole scan is used)
    coverage: float          # share of the board's region scanned
    residual_mm: np.ndarray | None = field(default=None, repr=False)   # (H, W) float32, NaN off the points

    def to_dict(self) -> dict:
        """The figures as plain types (without the residual map)."""
        return {"name": self.name, "flatness": asdict(self.flatness),
                "scale": None if self.scale is None else asdict(self.scale),
                "board_px": self.board_px, "coverage": self.coverage}


def check_pose(name: str, xyz: np.ndarray, valid: np.ndarray, rays_corners: np.ndarray | None,
               corners_px: np.ndarray | None, cols: int, rows: int, square_mm: float) -> PoseCheck:
    """One pose from its scan: ``xyz`` (H, W, 3) mm and ``valid`` (H, W) bool; with the detected
    corners ``corners_px`` (N, 2) px and their unit camera rays ``rays_corners`` (N, 3), the
    board's region limits the points and the corners give the scale."""
    H, W = valid.shape
    if corners_px is not None:
        region = board_region(corners_px, cols, rows, (H, W))
        use = valid & region
        n_region = int(region.sum())
    else:
        use = valid
        n_region = 0
    pts = xyz[use].reshape(-1, 3).astype(np.float64)
    need = max(200, int(MIN_BOARD_FRAC * (n_region or H * W)))
    if len(pts) < need:
        raise GBError(f"pose {name}: only {len(pts)} scanned points on the board (need {need}): the scan of "
                      "its pattern frame failed (check it with 'gbscan check')")
    flat = check_flatness(pts)
    res = np.full((H, W), np.nan, np.float32)
    res[use] = (pts @ np.asarray(flat.normal) + flat.offset_mm).astype(np.float32)
    scale = None
    if corners_px is not None and rays_corners is not None:
        c3 = corners_on_plane(rays_corners, flat.normal, flat.offset_mm)
        scale = check_scale(c3, cols, rows, square_mm)
    return PoseCheck(name, flat, scale, n_region, float(use.sum()) / n_region if n_region else float(use.mean()),
                     residual_mm=res)


def findings(poses: list) -> list:
    """Warnings over the checked poses (``gbscan.diagnose.Finding``), worst first."""
    from gbscan.diagnose import Finding

    out = []
    scales = [p.scale.scale_error for p in poses if p.scale is not None]
    if scales:
        s = float(np.median(scales))
        if abs(s) > SCALE_WARN:
            out.append(Finding("scale", "warn",
                               f"the board's squares measure {100 * s:+.2f} % off their size (median of {len(scales)} "
                               "poses): the scans are scaled; calibrate again (a moved camera or projector, a "
                               "changed zoom or focus), or check --square-mm", f"scale {100 * s:+.2f} %"))
    bows = [p.flatness.bow_mm for p in poses]
    worst = max(bows)
    if worst > BOW_WARN_MM:
        out.append(Finding("bow", "warn",
                           f"the flat board scans bent by up to {worst:.2f} mm (peak to valley): the lens "
                           "distortion or the light planes no longer fit; calibrate again", f"bow {worst:.2f} mm"))
    rms = max(p.flatness.rms_mm for p in poses)
    if rms > RMS_WARN_MM and worst <= BOW_WARN_MM:     # (a bent scan scatters too: the bow says it)
        out.append(Finding("rms", "warn",
                           f"points scatter {rms:.2f} mm RMS about the board's plane (a good rig: about 0.1 mm): "
                           "check the frames with 'gbscan check' (exposure, focus), then the calibration",
                           f"RMS {rms:.2f} mm"))
    return out
