"""Cleaning an organised range image: each filter is a pure function returning a kept mask.

Input everywhere is the organised point map ``xyz`` (H, W, 3) float mm in the camera frame with
NaN where nothing was reconstructed, and a ``valid`` (H, W) bool mask of the points still in
play.  Every filter returns ``(kept, reason)``: ``kept`` (H, W) bool is ``valid`` minus what the
filter rejects, ``reason`` the name under which the CLI counts the rejected points.  :func:`clean`
runs them in order and keeps, per pixel, the code of the first filter that rejected it
(``REASONS``), so the counts add up and the coverage picture can colour pixels by reason.

Order matters: isolated spikes are removed (``outlier``) *before* depth discontinuities, so a
spike costs one pixel instead of taking its four neighbours with it; the same jump test is then
made across holes (``gap_edge``: a run end next to a missing pixel against the first point
beyond it, so an edge whose far-side neighbours were never decoded, or were just dropped, still
loses its rim); small clusters are found last, as 4-connected components of what is left (the
discontinuity filter has already cut every 4-neighbour pair across a depth jump, so a detached
blob is its own component).

What no filter here can see: points the decoder extended from one surface into another that it
reported nothing for (no point of the far surface within ``max_gap_px``): they lie exactly on
the surface they were extended from.
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
    9: "gap_edge",
    10: "high_sigma",
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
    max_sigma_mm : drop points whose predicted error along the camera ray
        (:attr:`gbscan.scan.Scan.sigma_mm`, one standard deviation) is above this or unknown
        (None, the default: off).  Unlike ``min_confidence`` it means the same on every scene and
        rig: millimetres.
    max_gap_px, gap_far_px, gap_near_px : the depth-jump test across holes
        (:func:`gap_edge_filter`): a run end whose depth differs by more than ``max_jump`` per px
        of distance from the first in-play pixel beyond a hole of at most ``max_gap_px`` px loses
        ``gap_far_px`` pixels if it is the farther of the two, ``gap_near_px`` if the nearer
        (``max_gap_px`` 0 disables).  On the simulator every wrong point this test can reach is
        on the farther side (the far surface's stripes spilled 1-2 px over the near object's
        silhouette) and the nearer run ends are good points, hence 2 and 0.
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
    max_gap_px: int = 8
    gap_far_px: int = 2
    gap_near_px: int = 0
    max_sigma_mm: float | None = None

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
            (int(self.max_gap_px) >= 0, "max_gap_px must be >= 0"),
            (int(self.gap_far_px) >= 0 and int(self.gap_near_px) >= 0, "gap_far_px and gap_near_px must be >= 0"),
            (self.max_sigma_mm is None or float(self.max_sigma_mm) > 0, "max_sigma_mm must be > 0 (or None: off)"),
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
# Each public filter is a thin wrapper around one compiled kernel of ``gbscan.kernels`` (which
# works on a per-pixel reason map in place); :func:`clean` runs the same kernels on one shared
# reason map, so a filter and the chain cannot disagree.
def confidence_filter(confidence: np.ndarray, valid: np.ndarray, min_confidence: float):
    """Drop points whose decoder confidence (H, W) in [0, 1] is below ``min_confidence``."""
    return valid & (np.nan_to_num(confidence, nan=0.0) >= min_confidence), "low_confidence"


def sigma_filter(sigma_mm: np.ndarray, valid: np.ndarray, max_sigma_mm: float):
    """Drop points whose predicted error (H, W) mm (:attr:`gbscan.scan.Scan.sigma_mm`) is above
    ``max_sigma_mm`` or unknown (NaN)."""
    with np.errstate(invalid="ignore"):
        return valid & (np.asarray(sigma_mm) <= max_sigma_mm), "high_sigma"


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
    from . import kernels

    xyz, reason = _points(xyz), _reason_map(valid, xyz)
    kernels.clean_spikes(xyz, reason, float(tol), int(min_pairs), 1)
    return reason == 0, "outlier"


def discontinuity_filter(xyz: np.ndarray, valid: np.ndarray, max_jump: float = 0.01):
    """Drop both pixels of every valid 4-neighbour pair whose depths differ by > ``max_jump * z``.

    ``z`` is the nearer of the two depths.  Removes flying pixels (blends of foreground and
    background) and the one-pixel rims on either side of a depth edge.
    """
    from . import kernels

    xyz, reason = _points(xyz), _reason_map(valid, xyz)
    kernels.clean_jumps(xyz, reason, float(max_jump), 1)
    return reason == 0, "discontinuity"


def gap_edge_filter(xyz: np.ndarray, valid: np.ndarray, max_jump: float = 0.01, max_gap_px: int = 8,
                    far_px: int = 2, near_px: int = 0):
    """Drop the ends of runs that a hole of at most ``max_gap_px`` px separates from a surface
    at another depth: the depth-jump test when the neighbour across the edge is *missing*.

    At a silhouette the decoder often reports nothing for a few pixels (blur, shadow, a column
    it could not index) and extends the other surface's stripes by a pixel or two into the
    object: those points sit exactly on the wrong surface, so no local test sees them, and the
    plain jump test has no neighbour to compare with.  For every valid pixel whose 4-neighbour
    in a direction is missing, the first valid pixel ``k`` px further that way (``k <=
    max_gap_px + 1``) is compared with it; if their depths differ by more than
    ``max_jump * k * z`` (``z`` the nearer; the jump test's per-pixel slope, so a steep but
    smooth surface with a hole in it passes), the pixel and the valid pixels behind it along
    its run are dropped: ``far_px`` in all if it is the farther of the two, ``near_px`` if the
    nearer (each side of the hole is tested from its own side).  ``max_gap_px`` 0 keeps
    everything.
    """
    from . import kernels

    if int(max_gap_px) < 0 or int(far_px) < 0 or int(near_px) < 0:
        raise GBError("gap_edge_filter: max_gap_px, far_px and near_px must be >= 0, "
                      f"got {max_gap_px}, {far_px}, {near_px}")
    xyz, reason = _points(xyz), _reason_map(valid, xyz)
    if int(max_gap_px) > 0:
        kernels.clean_gap_edges(xyz, reason, float(max_jump), int(max_gap_px), int(far_px), int(near_px), 1)
    return reason == 0, "gap_edge"


def grazing_filter(xyz: np.ndarray, valid: np.ndarray, max_angle_deg: float = 80.0, step_px: int = 2,
                   normals: np.ndarray | None = None):
    """Drop points seen at more than ``max_angle_deg`` between viewing ray and surface normal.

    Normals come from the grid (:func:`grid_normals`) unless given ((H, W, 3), towards the
    camera).  Points whose normal cannot be estimated (no valid neighbours in either direction)
    are kept: they are isolated and left to the other filters.
    """
    from . import kernels

    xyz, reason = _points(xyz), _reason_map(valid, xyz)
    normals = grid_normals(xyz, valid, step_px) if normals is None else _points(normals, "normals")
    if normals.shape != xyz.shape:
        raise GBError(f"grazing_filter: normals {normals.shape} do not match xyz {xyz.shape}")
    kernels.clean_grazing(xyz, normals, reason, float(np.cos(np.radians(max_angle_deg))), 1)
    return reason == 0, "grazing"


def cluster_filter(valid: np.ndarray, min_cluster_px: int):
    """Drop 4-connected components of ``valid`` smaller than ``min_cluster_px`` pixels."""
    reason = (~np.asarray(valid, bool)).view(np.uint8)
    _drop_small_components(reason, int(min_cluster_px), 1)
    return reason == 0, "small_cluster"


def _drop_small_components(reason: np.ndarray, min_px: int, code: int) -> int:
    """Write ``code`` on the in-play pixels (``reason == 0``) of 4-connected components smaller
    than ``min_px``; returns how many.  Labels by OpenCV (a few ms at 640x480 without the
    statistics of ``connectedComponentsWithStats``), areas and marking in one compiled pass."""
    import cv2

    from . import kernels

    if min_px <= 1:
        return 0
    inplay = (reason == 0).view(np.uint8)
    n, labels = cv2.connectedComponents(inplay, connectivity=4, ltype=cv2.CV_32S)
    if n <= 1:
        return 0
    return int(kernels.clean_small_labels(labels, n, reason, min_px, code))


# -- normals -----------------------------------------------------------------------------------
def grid_normals(xyz: np.ndarray, valid: np.ndarray | None = None, step_px: int = 2) -> np.ndarray:
    """Unit normals (H, W, 3) float32 of an organised point map, oriented towards the camera.

    Tangents are differences over ``step_px`` pixels along rows and columns (central where both
    sides are valid, one-sided otherwise); NaN where a tangent is missing or the point is not
    valid/finite.  Orientation: ``n . p < 0`` (the normal faces the camera at the origin).
    One compiled pass (:func:`gbscan.kernels.grid_normals_into`), float64 arithmetic.
    """
    from . import kernels

    xyz = _points(xyz)
    if int(step_px) < 1:
        raise GBError(f"grid_normals: step_px must be >= 1, got {step_px}")
    n = np.empty(xyz.shape, np.float32)
    kernels.grid_normals_into(xyz, _reason_map(valid, xyz), int(step_px), n, -np.inf, 0)
    return n


def _points(xyz, what: str = "xyz") -> np.ndarray:
    """An organised (H, W, 3) float32/float64 map (other dtypes become float64)."""
    xyz = np.asarray(xyz)
    if xyz.ndim != 3 or xyz.shape[2] != 3:
        raise GBError(f"clean: {what} must be an organised (H, W, 3) point map, got shape {xyz.shape}")
    if xyz.dtype not in (np.float32, np.float64):
        xyz = xyz.astype(np.float64)
    return xyz


def _reason_map(valid, xyz) -> np.ndarray:
    """(H, W) uint8, 0 where ``valid`` (all pixels when None), 1 elsewhere: a fresh array."""
    if valid is None:
        return np.zeros(xyz.shape[:2], np.uint8)
    valid = np.asarray(valid, bool)
    if valid.shape != xyz.shape[:2]:
        raise GBError(f"clean: valid mask {valid.shape} does not match xyz {xyz.shape[:2]}")
    return (~valid).view(np.uint8)


# -- the whole chain ---------------------------------------------------------------------------
def clean(xyz: np.ndarray, confidence: np.ndarray | None = None, params: CleanParams | None = None, *,
          reason: np.ndarray | None = None, sigma_mm: np.ndarray | None = None) -> CleanResult:
    """Run every filter in order on an organised point map.

    xyz : (H, W, 3) float mm, NaN where not reconstructed.
    confidence : (H, W) float in [0, 1] or None (no confidence filter).
    reason : optional (H, W) uint8 codes already assigned upstream (e.g. ``not_decoded``,
        ``no_plane``); pixels with a non-zero code stay rejected with that code.
    sigma_mm : (H, W) predicted error of each point (mm, :func:`gbscan.triangulate.point_sigma_mm`);
        required when ``params.max_sigma_mm`` is set (the ``high_sigma`` filter, after the
        confidence and depth range), ignored otherwise.

    Returns a :class:`CleanResult`; ``counts``: ``no_plane`` (non-finite points), ``input``
    (points entering the filters), points removed per filter in order, ``kept``.  Every filter
    is one compiled pass over the grid on a shared reason map: a few ms per 640x480 frame.
    """
    from . import kernels

    params = params or CleanParams()
    if not isinstance(params, CleanParams):
        raise GBError(f"clean: params must be a CleanParams, got {type(params).__name__}")
    xyz = _points(xyz)
    H, W = xyz.shape[:2]
    reason = np.zeros((H, W), np.uint8) if reason is None else np.array(reason, dtype=np.uint8)
    if reason.shape != (H, W):
        raise GBError(f"clean: reason map {reason.shape} does not match xyz {xyz.shape[:2]}")
    use_conf = confidence is not None and params.min_confidence > 0
    if use_conf:
        conf = np.asarray(confidence, dtype=np.float32)
        if conf.shape != (H, W):
            raise GBError(f"clean: confidence {conf.shape} does not match xyz {xyz.shape[:2]}")
    else:
        conf = np.zeros((1, 1), np.float32)
    n_in = int(np.count_nonzero(reason == 0))
    n_plane, n_conf, n_depth = (int(c) for c in kernels.clean_pointwise(
        xyz, conf, use_conf, float(params.min_confidence), float(params.min_depth_mm),
        float(params.max_depth_mm), reason, CODE["no_plane"], CODE["low_confidence"], CODE["depth_range"]))
    counts = {"no_plane": n_plane, "input": n_in - n_plane}
    if use_conf:
        counts["low_confidence"] = n_conf
    counts["depth_range"] = n_depth
    if params.max_sigma_mm is not None:
        if sigma_mm is None:
            raise GBError("clean: max_sigma_mm is set but no sigma_mm map was given (Scanner passes the "
                          "decoder's column errors through the triangulation)")
        sig = np.asarray(sigma_mm)
        if sig.shape != (H, W):
            raise GBError(f"clean: sigma_mm {sig.shape} does not match xyz {xyz.shape[:2]}")
        in_play = reason == 0
        kept, name = sigma_filter(sig, in_play, params.max_sigma_mm)   # the public filter, on the chain's map
        high = in_play & ~kept
        reason[high] = CODE[name]
        counts["high_sigma"] = int(np.count_nonzero(high))
    n_spike, n_jump, n_gap = kernels.clean_spikes_jumps(
        xyz, reason, float(params.outlier_tol), int(params.min_pairs), CODE["outlier"], float(params.max_jump),
        CODE["discontinuity"], int(params.max_gap_px), int(params.gap_far_px), int(params.gap_near_px),
        CODE["gap_edge"])
    counts["outlier"], counts["discontinuity"], counts["gap_edge"] = int(n_spike), int(n_jump), int(n_gap)
    normals = np.empty((H, W, 3), np.float32)  # normals of what is left, and the grazing filter with them
    counts["grazing"] = int(kernels.grid_normals_into(xyz, reason, int(params.normal_step_px), normals,
                                                      float(np.cos(np.radians(params.max_angle_deg))), CODE["grazing"]))
    min_cluster = params.min_cluster_px if params.min_cluster_px is not None else (H * W) // 1000
    counts["small_cluster"] = _drop_small_components(reason, int(min_cluster), CODE["small_cluster"])
    kept = reason == 0
    counts["kept"] = int(np.count_nonzero(kept))
    return CleanResult(kept, reason, counts, normals)
