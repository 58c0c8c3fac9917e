"""Cleaning an organised range image: each filter is a pure function returning a kept mask.

Input everywhere is the organised point map ``xyz`` (H, W, 3) float mm in the camera frame with
NaN where nothing was reconstructed, and a ``valid`` (H, W) bool mask of the points still in
play.  Every filter returns ``(kept, reason)``: ``kept`` (H, W) bool is ``valid`` minus what the
filter rejects, ``reason`` the name under which the CLI counts the rejected points.  :func:`clean`
runs them in order and keeps, per pixel, the code of the first filter that rejected it
(``REASONS``), so the counts add up and the coverage picture can colour pixels by reason.

Order matters: isolated spikes are removed (``outlier``) *before* depth discontinuities, so a
spike costs one pixel instead of taking its four neighbours with it; small clusters are found
last, as 4-connected components of what is left (the discontinuity filter has already cut every
4-neighbour pair across a depth jump, so a detached blob is its own component).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from .errors import GBError

#: Per-pixel reason codes of :func:`clean` (0 = kept).
REASONS = {
    0: "ok",
    1: "not_decoded",
    2: "no_plane",
    3: "low_confidence",
    4: "depth_range",
    5: "outlier",
    6: "discontinuity",
    7: "grazing",
    8: "small_cluster",
}
CODE = {name: code for code, name in REASONS.items()}


@dataclass(frozen=True)
class CleanParams:
    """Thresholds of the cleaning filters (units in the names).

    min_confidence : decoder confidence below this is dropped (0 disables).
    min_depth_mm, max_depth_mm : accepted range of z.
    max_jump : a 4-neighbour whose depth differs by more than ``max_jump * z`` is across a depth
        discontinuity; both pixels are dropped (0.01 = 6.5 mm at 650 mm; a surface steeper than
        the grazing limit is removed anyway).
    max_angle_deg : maximum angle between the viewing ray and the surface normal.
    normal_step_px : half-width (px) of the finite differences the grid normals use.
    outlier_tol, min_pairs : a point is a spike unless at least ``min_pairs`` of its four
        opposite-neighbour pairs have a mean depth within ``outlier_tol * z`` of its own
        (0.002 = 1.3 mm at 650 mm, >10x the depth noise of the simulator's typical preset, where a
        plane's depth RMS is 0.09 mm; spikes below it stay within the 3 mm accuracy promise).
    min_cluster_px : 4-connected components smaller than this are dropped
        (None: one pixel in a thousand of the image, 307 at 640x480).
    """

    min_confidence: float = 0.2
    min_depth_mm: float = 50.0
    max_depth_mm: float = 10000.0
    max_jump: float = 0.01
    max_angle_deg: float = 80.0
    normal_step_px: int = 2
    outlier_tol: float = 0.002
    min_pairs: int = 1
    min_cluster_px: int | None = None

    def __post_init__(self):
        checks = [
            (0.0 <= self.min_confidence <= 1.0, "min_confidence must be in [0, 1]"),
            (0.0 <= self.min_depth_mm < self.max_depth_mm, "need 0 <= min_depth_mm < max_depth_mm"),
            (self.max_jump > 0, "max_jump must be > 0"),
            (0 < self.max_angle_deg <= 90, "max_angle_deg must be in (0, 90]"),
            (int(self.normal_step_px) >= 1, "normal_step_px must be >= 1"),
            (self.outlier_tol > 0, "outlier_tol must be > 0"),
            (0 <= int(self.min_pairs) <= 4, "min_pairs must be between 0 and 4"),
            (self.min_cluster_px is None or int(self.min_cluster_px) >= 0, "min_cluster_px must be >= 0"),
        ]
        for ok, msg in checks:
            if not ok:
                raise GBError(f"cleaning parameters: {msg}")

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class CleanResult:
    """kept (H, W) bool; reason (H, W) uint8 code (``REASONS``); counts: points removed per
    filter name (in order), plus ``input`` and ``kept``; normals (H, W, 3) float32 grid normals
    (towards the camera) computed for the grazing filter, NaN where none."""

    kept: np.ndarray
    reason: np.ndarray
    counts: dict = field(default_factory=dict)
    normals: np.ndarray | None = None


# -- the filters -------------------------------------------------------------------------------
def confidence_filter(confidence: np.ndarray, valid: np.ndarray, min_confidence: float):
    """Drop points whose decoder confidence (H, W) in [0, 1] is below ``min_confidence``."""
    return valid & (np.nan_to_num(confidence, nan=0.0) >= min_confidence), "low_confidence"


def depth_range_filter(xyz: np.ndarray, valid: np.ndarray, min_depth_mm: float, max_depth_mm: float):
    """Drop points whose z (mm) is outside ``[min_depth_mm, max_depth_mm]``."""
    z = xyz[..., 2]
    with np.errstate(invalid="ignore"):
        return valid & (z >= min_depth_mm) & (z <= max_depth_mm), "depth_range"


def outlier_filter(xyz: np.ndarray, valid: np.ndarray, tol: float = 0.002, min_pairs: int = 1):
    """Drop spikes: points that agree with none of their opposite-neighbour pairs.

    For each of the four pairs of opposite 8-neighbours (left/right, up/down, both diagonals)
    that are still valid, the pair *supports* the point if its depth is within ``tol * z`` of the
    pair's mean -- a second difference, which is ~0 on any smooth surface however steep (unlike a
    plain depth tolerance) and equals the spike's height for a spike.  Points with fewer than
    ``min_pairs`` supporting pairs are dropped.  The organised-grid counterpart of open3d's
    statistical outlier removal, without a k-d tree.  Points whose every pair has a missing side
    (isolated pixels, tips of one-pixel lines, some corners) are dropped too.
    """
    z = _masked_depth(xyz, valid)
    H, W = z.shape
    pad = np.full((H + 2, W + 2), np.nan, np.float32)
    pad[1:1 + H, 1:1 + W] = z
    tolz = np.float32(tol) * z
    pairs = np.zeros((H, W), np.uint8)
    dev = np.empty((H, W), np.float32)
    with np.errstate(invalid="ignore"):
        for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
            np.add(pad[1 + dy:1 + dy + H, 1 + dx:1 + dx + W], pad[1 - dy:1 - dy + H, 1 - dx:1 - dx + W], out=dev)
            dev *= np.float32(0.5)
            dev -= z
            np.abs(dev, out=dev)
            pairs += dev <= tolz  # NaN (a missing side) compares False
    return valid & (pairs >= min_pairs), "outlier"


def discontinuity_filter(xyz: np.ndarray, valid: np.ndarray, max_jump: float = 0.01):
    """Drop both pixels of every valid 4-neighbour pair whose depths differ by > ``max_jump * z``.

    ``z`` is the nearer of the two depths.  Removes flying pixels (blends of foreground and
    background) and the one-pixel rims on either side of a depth edge.
    """
    z = _masked_depth(xyz, valid)
    bad = np.zeros(z.shape, bool)
    with np.errstate(invalid="ignore"):
        for a, b in ((z[:, 1:], z[:, :-1]), (z[1:, :], z[:-1, :])):
            jump = np.abs(a - b) > max_jump * np.fmin(a, b)  # NaN pairs compare False
            if a.shape[1] != z.shape[1]:
                bad[:, 1:] |= jump
                bad[:, :-1] |= jump
            else:
                bad[1:, :] |= jump
                bad[:-1, :] |= jump
    return valid & ~bad, "discontinuity"


def grazing_filter(xyz: np.ndarray, valid: np.ndarray, max_angle_deg: float = 80.0, step_px: int = 2,
                   normals: np.ndarray | None = None):
    """Drop points seen at more than ``max_angle_deg`` between viewing ray and surface normal.

    Normals come from the grid (:func:`grid_normals`) unless given.  Points whose normal cannot
    be estimated (no valid neighbours in either direction) are kept: they are isolated and left
    to the other filters.
    """
    if normals is None:
        normals = grid_normals(xyz, valid, step_px)
    x, y, z = (np.asarray(xyz[..., c], np.float32) for c in range(3))
    with np.errstate(invalid="ignore", divide="ignore"):
        dot = normals[..., 0] * x + normals[..., 1] * y + normals[..., 2] * z
        cos = -dot / np.sqrt(x * x + y * y + z * z)
        bad = cos < np.cos(np.radians(max_angle_deg))  # NaN (no normal) compares False
    return valid & ~bad, "grazing"


def cluster_filter(valid: np.ndarray, min_cluster_px: int):
    """Drop 4-connected components of ``valid`` smaller than ``min_cluster_px`` pixels."""
    import cv2

    if min_cluster_px <= 1 or not valid.any():
        return valid.copy(), "small_cluster"
    n, labels, stats, _ = cv2.connectedComponentsWithStats(valid.view(np.uint8), connectivity=4)
    small = stats[:, cv2.CC_STAT_AREA] < min_cluster_px
    small[0] = True  # background label
    return valid & ~small[labels], "small_cluster"


# -- normals -----------------------------------------------------------------------------------
def grid_normals(xyz: np.ndarray, valid: np.ndarray | None = None, step_px: int = 2) -> np.ndarray:
    """Unit normals (H, W, 3) float32 of an organised point map, oriented towards the camera.

    Tangents are differences over ``step_px`` pixels along rows and columns (central where both
    sides are valid, one-sided otherwise); NaN where a tangent is missing.  Orientation:
    ``n . p < 0`` (the normal faces the camera at the origin).  Works on the three coordinate
    planes separately in float32 (fast, no (H, W, 3) temporaries).
    """
    xyz = np.asarray(xyz)
    comps = [np.array(xyz[..., c], dtype=np.float32) for c in range(3)]
    if valid is not None:
        for a in comps:
            a[~valid] = np.nan
    s = int(step_px)
    tu = [_tangent(a, s, axis=1) for a in comps]
    tv = [_tangent(a, s, axis=0) for a in comps]
    # n = tv x tu: (down x right) points towards -z, i.e. towards the camera
    n = np.empty(xyz.shape[:2] + (3,), np.float32)
    n[..., 0] = tv[1] * tu[2] - tv[2] * tu[1]
    n[..., 1] = tv[2] * tu[0] - tv[0] * tu[2]
    n[..., 2] = tv[0] * tu[1] - tv[1] * tu[0]
    nx, ny, nz = n[..., 0], n[..., 1], n[..., 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        norm = np.sqrt(nx * nx + ny * ny + nz * nz)
        # unit length, and the sign that makes n . p < 0
        norm = np.where(nx * comps[0] + ny * comps[1] + nz * comps[2] > 0, -norm, norm)
        n /= norm[..., None]
    return n


def _tangent(a: np.ndarray, s: int, axis: int) -> np.ndarray:
    """Finite difference of a (H, W) along ``axis`` over ``s`` px, central where possible."""
    fwd = np.full_like(a, np.nan)
    bwd = np.full_like(a, np.nan)
    if axis == 1:
        np.subtract(a[:, s:], a[:, :-s], out=fwd[:, :-s])
        bwd[:, s:] = fwd[:, :-s]
    else:
        np.subtract(a[s:], a[:-s], out=fwd[:-s])
        bwd[s:] = fwd[:-s]
    one_sided = np.where(np.isnan(fwd), bwd, fwd)
    central = fwd + bwd
    return np.where(np.isnan(central), one_sided, central)


def _finite(xyz: np.ndarray) -> np.ndarray:
    """(H, W) bool: all three coordinates finite (faster than ``isfinite(xyz).all(-1)``)."""
    return np.isfinite(xyz[..., 0] + xyz[..., 1] + xyz[..., 2])


def _masked_depth(xyz: np.ndarray, valid: np.ndarray) -> np.ndarray:
    return np.where(valid, xyz[..., 2], np.nan).astype(np.float32)


# -- the whole chain ---------------------------------------------------------------------------
def clean(xyz: np.ndarray, confidence: np.ndarray | None = None, params: CleanParams | None = None, *,
          reason: np.ndarray | None = None) -> CleanResult:
    """Run every filter in order on an organised point map.

    xyz : (H, W, 3) float mm, NaN where not reconstructed.
    confidence : (H, W) float in [0, 1] or None (no confidence filter).
    reason : optional (H, W) uint8 codes already assigned upstream (e.g. ``not_decoded``,
        ``no_plane``); pixels with a non-zero code stay rejected with that code.

    Returns a :class:`CleanResult`; ``counts``: ``no_plane`` (non-finite points), ``input``
    (points entering the filters), points removed per filter in order, ``kept``.
    """
    params = params or CleanParams()
    xyz = np.asarray(xyz)
    if xyz.ndim != 3 or xyz.shape[2] != 3:
        raise GBError(f"clean: xyz must be an organised (H, W, 3) point map, got shape {xyz.shape}")
    H, W = xyz.shape[:2]
    finite = _finite(xyz)
    reason = np.zeros((H, W), np.uint8) if reason is None else np.array(reason, dtype=np.uint8)
    if reason.shape != (H, W):
        raise GBError(f"clean: reason map {reason.shape} does not match xyz {xyz.shape[:2]}")
    no_plane = (reason == 0) & ~finite
    reason[no_plane] = CODE["no_plane"]
    valid = reason == 0
    counts = {"no_plane": int(no_plane.sum()), "input": int(valid.sum())}

    def apply(result):
        nonlocal valid
        kept, name = result
        dropped = valid & ~kept
        reason[dropped] = CODE[name]
        counts[name] = int(dropped.sum())
        valid = kept

    if confidence is not None and params.min_confidence > 0:
        apply(confidence_filter(confidence, valid, params.min_confidence))
    apply(depth_range_filter(xyz, valid, params.min_depth_mm, params.max_depth_mm))
    apply(outlier_filter(xyz, valid, params.outlier_tol, params.min_pairs))
    apply(discontinuity_filter(xyz, valid, params.max_jump))
    normals = grid_normals(xyz, valid, params.normal_step_px)
    apply(grazing_filter(xyz, valid, params.max_angle_deg, normals=normals))
    min_cluster = params.min_cluster_px if params.min_cluster_px is not None else (H * W) // 1000
    apply(cluster_filter(valid, int(min_cluster)))
    counts["kept"] = int(valid.sum())
    return CleanResult(valid, reason, counts, normals)
