"""Pinhole camera with OpenCV's five-parameter lens distortion.

Conventions (used everywhere in gbcal and gbscan):

* Camera frame: OpenCV's, x right, y down, z forward; lengths in millimetres.
* A pixel ``q = (u, v)``: ``u`` along image columns, ``v`` along rows, pixel *centres* at integer
  coordinates, so the image array is indexed ``image[v, u]`` and the top-left pixel's centre is
  ``(0, 0)``.  This is OpenCV's convention too, so ``K`` and ``distortion`` match
  ``cv2.calibrateCamera`` / ``cv2.projectPoints`` exactly.
* Distortion ``[k1, k2, p1, p2, k3]`` (OpenCV order) maps undistorted normalised coordinates to
  distorted ones; projecting a point applies it, back-projecting a pixel inverts it.
* A point ``p`` is ``(..., 3)`` mm; a ray is a unit ``(..., 3)`` direction from the camera centre.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import GBError


@dataclass(frozen=True, eq=False)
class Camera:
    """Intrinsics of one camera.

    width, height : image size in pixels.
    K : (3, 3) float64 ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels.
    dist : (5,) float64 ``[k1, k2, p1, p2, k3]``.
    """

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))

    def __post_init__(self):
        K = np.asarray(self.K, dtype=np.float64)
        dist = np.zeros(5) if self.dist is None else np.asarray(self.dist, dtype=np.float64).ravel()
        if K.shape != (3, 3):
            raise GBError(f"camera matrix must be 3x3, got shape {K.shape}")
        if dist.size != 5:
            raise GBError(f"camera distortion must have 5 values [k1,k2,p1,p2,k3], got {dist.size}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise GBError(f"camera size must be positive, got {self.width}x{self.height}")
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            raise GBError(f"camera focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels, OpenCV's order."""
        return (self.width, self.height)

    # -- forward model -------------------------------------------------------------------------
    def distort(self, xn: np.ndarray) -> np.ndarray:
        """Undistorted normalised coordinates (..., 2) -> distorted normalised (..., 2)."""
        return distort_normalized(xn, self.dist)

    def project(self, p: np.ndarray) -> np.ndarray:
        """Points (..., 3) mm in the camera frame -> pixels (..., 2).  Points with z <= 0 give NaN."""
        p = np.asarray(p, dtype=np.float64)
        z = p[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xn = p[..., :2] / np.where(z > 0, z, np.nan)[..., None]
        xd = self.distort(xn)
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        skew = self.K[0, 1]
        u = fx * xd[..., 0] + skew * xd[..., 1] + cx
        v = fy * xd[..., 1] + cy
        return np.stack([u, v], axis=-1)

    # -- backward model ------------------------------------------------------------------------
    def normalize(self, q: np.ndarray) -> np.ndarray:
        """Pixels (..., 2) -> undistorted normalised coordinates (..., 2) (rays ``[x, y, 1]``).

        Inverts the distortion by Newton's method (:func:`undistort_normalized`), which reaches
        ~1e-13 in a few steps on the distortions real lenses have; where it has not converged
        (extreme distortion far off-axis) a fixed-point warm start and Newton again.
        """
        q = np.asarray(q, dtype=np.float64)
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        skew = self.K[0, 1]
        yd = (q[..., 1] - cy) / fy
        xd = (q[..., 0] - cx - skew * yd) / fx
        target = np.stack([xd, yd], axis=-1)
        if not np.any(self.dist):
            return target
        x = undistort_normalized(target, self.dist)
        bad = ~np.all(np.abs(self.distort(x) - target) < 1e-10, axis=-1)
        if np.any(bad):
            t = target[bad]
            xb = t.copy()
            for _ in range(20):
                xb = xb + (t - self.distort(xb))
            x[bad] = undistort_normalized(t, self.dist, xb)
        return x

    def rays(self, q: np.ndarray) -> np.ndarray:
        """Pixels (..., 2) -> unit ray directions (..., 3) in the camera frame."""
        xn = self.normalize(q)
        r = np.concatenate([xn, np.ones(xn.shape[:-1] + (1,))], axis=-1)
        return r / np.linalg.norm(r, axis=-1, keepdims=True)

    def pixel_grid(self) -> np.ndarray:
        """(H, W, 2) float64 pixel centres ``(u, v)``."""
        v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        return np.stack([u, v], axis=-1)

    def pixel_rays(self) -> np.ndarray:
        """(H, W, 3) float64 unit rays of every pixel centre (compute once per calibration)."""
        return self.rays(self.pixel_grid())

    def scaled(self, s: float) -> "Camera":
        """The same lens on a sensor resampled by factor ``s`` (pixel-centre convention kept)."""
        K = self.K.copy()
        K[0, 0] *= s
        K[1, 1] *= s
        K[0, 1] *= s
        K[0, 2] = (K[0, 2] + 0.5) * s - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * s - 0.5
        return Camera(round(self.width * s), round(self.height * s), K, self.dist.copy())


def distort_normalized(xn: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """OpenCV's radial-tangential model: undistorted normalised (..., 2) -> distorted (..., 2)."""
    k1, k2, p1, p2, k3 = (float(v) for v in np.asarray(dist, dtype=np.float64).ravel()[:5])
    x = xn[..., 0]
    y = xn[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def undistort_normalized(xd: np.ndarray, dist: np.ndarray, x0: np.ndarray | None = None, *,
                         iterations: int = 12, tol: float | None = 1e-13) -> np.ndarray:
    """Invert :func:`distort_normalized`: distorted normalised (..., 2) -> undistorted (..., 2).

    Newton's method with the analytic 2x2 Jacobian of OpenCV's model, from ``x0`` (default: the
    distorted coordinates themselves).  Stops after ``iterations`` steps or once the residual is
    below ``tol`` (``None``: always take every step).  Quadratic convergence: from a start 1e-7
    away, two steps reach ~1e-15.
    """
    k1, k2, p1, p2, k3 = (float(v) for v in np.asarray(dist, dtype=np.float64).ravel()[:5])
    t = np.asarray(xd, dtype=np.float64)
    tx, ty = t[..., 0], t[..., 1]
    start = t if x0 is None else np.asarray(x0, dtype=np.float64)
    x, y = start[..., 0].copy(), start[..., 1].copy()
    for _ in range(iterations):
        xx, yy, xy = x * x, y * y, x * y
        r2 = xx + yy
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dr = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        fx = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * xx) - tx
        fy = y * radial + p1 * (r2 + 2.0 * yy) + 2.0 * p2 * xy - ty
        a = radial + 2.0 * xx * dr + 2.0 * p1 * y + 6.0 * p2 * x
        b = 2.0 * xy * dr + 2.0 * p1 * x + 2.0 * p2 * y
        d = radial + 2.0 * yy * dr + 6.0 * p1 * y + 2.0 * p2 * x
        det = a * d - b * b
        with np.errstate(divide="ignore", invalid="ignore"):
            x = x - (d * fx - b * fy) / det
            y = y - (a * fy - b * fx) / det
        if tol is not None and (fx.size == 0 or max(np.abs(fx).max(), np.abs(fy).max()) < tol):
            break
    return np.stack([x, y], axis=-1)
