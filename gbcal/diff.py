"""How far two calibrations disagree, in the units that matter: mm in the working volume.

Pure computations (arrays and :class:`gbscan.camera.Camera` in, numbers out); ``gbcal diff``
reads the files and prints.

* Light planes: for camera pixels on a grid and every plane index both calibrations hold, the
  scanner would report the point where the pixel's ray meets that plane.  Triangulate with A
  (A's ray x A's plane) and with B; where A's point lies in the working depth range, the
  distance between the two points is the disagreement a scan would show.
* Camera only: back-project grid pixels with A to several depths, project the 3D points with B;
  the pixel distance is the disagreement.

Conventions: camera frame OpenCV's (x right, y down, z forward), mm; pixels with centres at
integers; planes ``n . p = d`` with unit ``n``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gbscan.camera import Camera
from gbscan.errors import GBError

DEFAULT_DEPTH_MM = (400.0, 1000.0)
DEFAULT_STEP_PX = 8.0
#: Rays meeting a plane at a grazing angle below this are skipped (ill-conditioned, as in the scanner).
MIN_ANGLE_DEG = 2.0


@dataclass(frozen=True)
class Stats:
    """Summary of a set of distances (mm or px as named by the caller); NaN when ``count == 0``."""

    count: int
    median: float
    p95: float
    max: float
    mean: float

    @classmethod
    def of(cls, x: np.ndarray) -> "Stats":
        x = np.asarray(x, dtype=np.float64).ravel()
        x = x[np.isfinite(x)]
        if x.size == 0:
            nan = float("nan")
            return cls(0, nan, nan, nan, nan)
        return cls(int(x.size), float(np.median(x)), float(np.percentile(x, 95)), float(x.max()), float(x.mean()))


def ray_plane(rays: np.ndarray, normal: np.ndarray, d: np.ndarray, min_angle_deg: float = MIN_ANGLE_DEG) -> np.ndarray:
    """Points where unit rays from the camera centre meet planes ``n . p = d``, camera frame mm.

    rays (..., 3), normal (..., 3), d (...) broadcast together -> (..., 3); NaN where the ray is
    within ``min_angle_deg`` of parallel to the plane or meets it behind the camera.
    """
    rays = np.asarray(rays, dtype=np.float64)
    normal = np.asarray(normal, dtype=np.float64)
    d = np.asarray(d, dtype=np.float64)
    dot = np.sum(rays * normal, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = d / dot
    bad = (np.abs(dot) < np.sin(np.radians(min_angle_deg))) | ~(s > 0)
    s = np.where(bad, np.nan, s)
    return rays * s[..., None]


def pixel_grid(camera: Camera, step_px: float = DEFAULT_STEP_PX) -> np.ndarray:
    """(M, 2) pixel centres on a regular grid covering the image (border pixels included)."""
    if not step_px > 0:
        raise GBError(f"grid step must be a positive number of pixels, got {step_px}")
    u = np.unique(np.r_[np.arange(0.0, camera.width - 1, step_px), camera.width - 1.0])
    v = np.unique(np.r_[np.arange(0.0, camera.height - 1, step_px), camera.height - 1.0])
    uu, vv = np.meshgrid(u, v)
    return np.stack([uu.ravel(), vv.ravel()], axis=1)


def intrinsic_differences(a: Camera, b: Camera) -> dict[str, float]:
    """B minus A for fx, fy, cx, cy (px) and k1, k2, p1, p2, k3."""
    names = ("fx", "fy", "cx", "cy")
    va = (a.K[0, 0], a.K[1, 1], a.K[0, 2], a.K[1, 2])
    vb = (b.K[0, 0], b.K[1, 1], b.K[0, 2], b.K[1, 2])
    out = {n: float(y - x) for n, x, y in zip(names, va, vb)}
    out.update({n: float(y - x) for n, x, y in zip(("k1", "k2", "p1", "p2", "k3"), a.dist, b.dist)})
    return out


def _check_depth(depth_mm) -> tuple[float, float]:
    lo, hi = (float(x) for x in depth_mm)
    if not (0 < lo < hi and np.isfinite(hi)):
        raise GBError(f"working depth range must be 0 < MIN < MAX mm, got {lo:g}..{hi:g}")
    return lo, hi


def plane_distances_mm(cam_a: Camera, normal_a: np.ndarray, d_a: np.ndarray, cam_b: Camera, normal_b: np.ndarray,
                       d_b: np.ndarray, *, depth_mm=DEFAULT_DEPTH_MM, step_px: float = DEFAULT_STEP_PX,
                       q: np.ndarray | None = None) -> np.ndarray:
    """Distances (mm) between the points A and B triangulate for the same pixel and plane.

    normal_a, normal_b : (P, 3) unit normals of the *common* planes, matched row by row.
    d_a, d_b : (P,) offsets (mm).
    q : (M, 2) pixels to sample (default :func:`pixel_grid` of A with ``step_px``).
    Returns (K,) distances for the (pixel, plane) pairs whose A point has depth z within
    ``depth_mm`` = (min, max) and whose B point exists; empty if none.
    """
    lo, hi = _check_depth(depth_mm)
    normal_a = np.asarray(normal_a, dtype=np.float64).reshape(-1, 3)
    normal_b = np.asarray(normal_b, dtype=np.float64).reshape(-1, 3)
    d_a = np.asarray(d_a, dtype=np.float64).ravel()
    d_b = np.asarray(d_b, dtype=np.float64).ravel()
    if not (normal_a.shape == normal_b.shape and d_a.size == d_b.size == normal_a.shape[0]):
        raise GBError("plane_distances_mm: A and B need the same number of matched planes")
    if (cam_a.width, cam_a.height) != (cam_b.width, cam_b.height):
        raise GBError(f"the two calibrations are for different image sizes ({cam_a.width}x{cam_a.height} vs "
                      f"{cam_b.width}x{cam_b.height}); they cannot be compared pixel by pixel")
    q = pixel_grid(cam_a, step_px) if q is None else np.asarray(q, dtype=np.float64).reshape(-1, 2)
    ra, rb = cam_a.rays(q), cam_b.rays(q)
    out = []
    for k in range(normal_a.shape[0]):  # one plane at a time keeps memory at (M, 3)
        pa = ray_plane(ra, normal_a[k], d_a[k])
        keep = (pa[:, 2] >= lo) & (pa[:, 2] <= hi)
        if not np.any(keep):
            continue
        pb = ray_plane(rb[keep], normal_b[k], d_b[k])
        dist = np.linalg.norm(pb - pa[keep], axis=1)
        out.append(dist[np.isfinite(dist)])
    return np.concatenate(out) if out else np.zeros(0)


def reprojection_distances_px(cam_a: Camera, cam_b: Camera, *, depth_mm=DEFAULT_DEPTH_MM, n_depths: int = 5,
                              step_px: float = DEFAULT_STEP_PX, q: np.ndarray | None = None) -> np.ndarray:
    """Pixel distances between grid pixels and their A-back-projected, B-projected images.

    Each pixel's ray under A is sampled at ``n_depths`` depths (z, mm) spread over ``depth_mm``
    and projected with B.  Returns (M * n_depths,) px.  Zero for identical cameras.
    """
    lo, hi = _check_depth(depth_mm)
    if (cam_a.width, cam_a.height) != (cam_b.width, cam_b.height):
        raise GBError(f"the two calibrations are for different image sizes ({cam_a.width}x{cam_a.height} vs "
                      f"{cam_b.width}x{cam_b.height}); they cannot be compared pixel by pixel")
    q = pixel_grid(cam_a, step_px) if q is None else np.asarray(q, dtype=np.float64).reshape(-1, 2)
    xn = cam_a.normalize(q)
    rays = np.concatenate([xn, np.ones((xn.shape[0], 1))], axis=1)  # z = 1
    z = np.linspace(lo, hi, max(int(n_depths), 1))
    p = rays[None, :, :] * z[:, None, None]
    qb = cam_b.project(p)
    return np.linalg.norm(qb - q[None], axis=-1).ravel()


def common_planes(index_a: np.ndarray, index_b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plane indices present in both (sorted) and their positions in A and in B."""
    index_a = np.asarray(index_a).ravel()
    index_b = np.asarray(index_b).ravel()
    common, ia, ib = np.intersect1d(index_a, index_b, assume_unique=True, return_indices=True)
    return common, ia, ib


def compare(a, b, *, depth_mm=DEFAULT_DEPTH_MM, step_px: float = DEFAULT_STEP_PX) -> dict:
    """Compare two :class:`gbscan.calibfile.Calibration` objects.

    Returns a dict: ``intrinsics`` (B - A differences), ``reprojection_px`` (:class:`Stats`),
    ``planes`` {``common``, ``only_a``, ``only_b`` counts} and ``distance_mm`` (:class:`Stats`,
    None when the files share no plane).
    """
    out = {"intrinsics": intrinsic_differences(a.camera, b.camera),
           "reprojection_px": Stats.of(reprojection_distances_px(a.camera, b.camera, depth_mm=depth_mm,
                                                                step_px=step_px))}
    common, ia, ib = common_planes(a.plane_index, b.plane_index)
    out["planes"] = {"common": int(common.size), "only_a": int(a.n_planes - common.size),
                     "only_b": int(b.n_planes - common.size)}
    out["distance_mm"] = None
    if common.size:
        dist = plane_distances_mm(a.camera, a.plane_normal[ia], a.plane_d[ia], b.camera, b.plane_normal[ib],
                                  b.plane_d[ib], depth_mm=depth_mm, step_px=step_px)
        out["distance_mm"] = Stats.of(dist)
    return out
