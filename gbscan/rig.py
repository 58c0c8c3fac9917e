"""Projector model, camera-projector pose, and the stripe light planes they define.

Conventions:

* ``T_cam_proj`` maps projector-frame points to camera-frame points:
  ``p_cam = R_cam_proj @ p_proj + t_cam_proj``.  The projector frame is OpenCV-like (x right,
  y down, z along the projection axis), so a projector is a camera with the light going out.
* The projector is a distortion-free pinhole ``K_proj`` with pixel centres at integers.  Stripes
  are vertical (constant projector column ``x``), the baseline horizontal.
* A light plane is ``n . p = d`` in the camera frame, ``n`` a unit (3,) vector and ``d`` in mm.
  The plane of projector column ``x`` contains the projector centre and every projector pixel of
  that column.  Its normal is chosen with a positive camera-frame x component so that ``d``
  grows with the column (for the usual projector-right-of-camera rig).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import Camera
from .errors import GBError


@dataclass(frozen=True, eq=False)
class Projector:
    """A projector as a pinhole: ``width`` x ``height`` pixels, (3, 3) ``K`` in pixels."""

    width: int
    height: int
    K: np.ndarray

    def __post_init__(self):
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3):
            raise GBError(f"projector matrix must be 3x3, got shape {K.shape}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    def project(self, p_proj: np.ndarray) -> np.ndarray:
        """Points (..., 3) in the projector frame -> projector pixels (..., 2); NaN behind it."""
        p = np.asarray(p_proj, dtype=np.float64)
        z = p[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            zz = np.where(z > 0, z, np.nan)
            x = p[..., 0] / zz
            y = p[..., 1] / zz
        K = self.K
        return np.stack([K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2]], axis=-1)


@dataclass(frozen=True, eq=False)
class Rig:
    """Camera, projector and the pose ``T_cam_proj`` between them."""

    camera: Camera
    projector: Projector
    R_cam_proj: np.ndarray
    t_cam_proj: np.ndarray

    def __post_init__(self):
        R = np.asarray(self.R_cam_proj, dtype=np.float64)
        t = np.asarray(self.t_cam_proj, dtype=np.float64).ravel()
        if R.shape != (3, 3) or t.shape != (3,):
            raise GBError("rig pose must be a 3x3 rotation and a 3-vector translation")
        object.__setattr__(self, "R_cam_proj", R)
        object.__setattr__(self, "t_cam_proj", t)

    @property
    def projector_centre(self) -> np.ndarray:
        """(3,) projector centre in the camera frame, mm."""
        return self.t_cam_proj.copy()

    def to_projector(self, p_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points (..., 3) -> projector-frame points (..., 3)."""
        return (np.asarray(p_cam, dtype=np.float64) - self.t_cam_proj) @ self.R_cam_proj

    def project_to_projector(self, p_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points (..., 3) -> projector pixels (..., 2)."""
        return self.projector.project(self.to_projector(p_cam))

    def column_planes(self, x_proj) -> tuple[np.ndarray, np.ndarray]:
        """Light planes of projector columns ``x_proj`` (...,) -> (normals (..., 3), d (...)).

        Exact for the pinhole projector (zero skew assumed for the plane to be a plane).
        """
        return column_planes(self.projector.K, self.R_cam_proj, self.t_cam_proj, x_proj)


def column_planes(K_proj, R_cam_proj, t_cam_proj, x_proj):
    """Plane ``n . p = d`` (camera frame, mm) of each projector column ``x_proj`` (...,).

    In the projector frame column ``x`` is ``fx * X - (x - cx) * Z = 0``; rotate and translate.
    Returns unit normals (..., 3) with positive camera-x component, and d (...) in mm.
    """
    x = np.asarray(x_proj, dtype=np.float64)
    fx, cx = float(K_proj[0, 0]), float(K_proj[0, 2])
    n_proj = np.stack([np.full_like(x, fx), np.zeros_like(x), -(x - cx)], axis=-1)
    n = n_proj @ np.asarray(R_cam_proj, dtype=np.float64).T
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.where(n[..., :1] < 0, -n, n)
    d = n @ np.asarray(t_cam_proj, dtype=np.float64)
    return n, d


def rotation_y(angle_rad: float) -> np.ndarray:
    """Rotation about the camera y axis (down) by ``angle_rad``, right-handed."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """Rotation whose z axis points from ``eye`` to ``target`` (OpenCV frame, y roughly down).

    Returns R such that a device at ``eye`` with orientation R has ``p_world = R @ p_dev + eye``.
    """
    z = np.asarray(target, float) - np.asarray(eye, float)
    z = z / np.linalg.norm(z)
    upv = np.asarray(up, float)
    x = np.cross(-upv, z)  # OpenCV: y down, so "up" is -y
    if np.linalg.norm(x) < 1e-9:
        x = np.cross([0.0, 0.0, 1.0] if abs(z[2]) < 0.9 else [1.0, 0.0, 0.0], z)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


#: the camera (and projector) sizes :func:`paper_rig` builds (pixels a side, inclusive)
CAMERA_SIDE_PX = (64, 16384)


def paper_rig(baseline_mm: float = 200.0, distance_mm: float = 650.0, *, distortion=True,
              camera_px: tuple[int, int] = (640, 480), projector_px: tuple[int, int] = (1024, 768)) -> Rig:
    """The paper's geometry: a 640x480 camera and a 1024x768 DLP projector.

    The camera (fx = fy = 800 px) sits at the origin; the projector (fx = fy = 1860 px, so one
    projector pixel covers about 0.43 camera pixels) sits ``baseline_mm`` to the right and is
    toed in so its axis crosses the camera axis at ``distance_mm``.  A shorter baseline sees less
    grazing light and shadow (more of a curved object is decoded) at a higher depth noise, which
    grows as 1 / baseline: ``scripts/coverage_study.py --baseline-mm`` measures both.  A negative
    ``baseline_mm`` puts the projector on the camera's left (the rig mirrored; the decoder's rules
    were tuned with it on the right: docs/method.md, "Known limits").
    ``camera_px`` (W, H): a sensor of that many pixels behind the same lens (square pixels, their
    pitch scaled by 640 / W: fx = fy = 800 W / 640, the principal point at the centre, the same
    distortion), e.g. (1280, 960) for twice the paper camera's pixels over its field of view;
    stripes then span W / 640 times as many camera pixels.
    ``projector_px`` (W, H): a projector of that many pixels behind the paper projector's lens (fx
    = fy = 1860 W / 1024, the principal point at the centre), e.g. (1920, 1080), today's common
    projector: stripes of a given width in projector px are then 1024 / W times as wide in the
    camera (pair it with a larger camera or wider stripes), and a pattern of 8-px stripes has 240
    of them (see :mod:`gbscan.pattern`, the marker code).
    """
    if not (np.isfinite(baseline_mm) and baseline_mm != 0 and np.isfinite(distance_mm) and distance_mm > 0):
        raise GBError(f"paper_rig: baseline_mm must be a non-zero length in mm (the projector that far right of the "
                      f"camera; negative: left) and distance_mm a positive one (toed in to that distance in front "
                      f"of the camera), got {baseline_mm}, {distance_mm}")
    W, H = _size_px(camera_px, "camera_px")
    PW, PH = _size_px(projector_px, "projector_px")
    f = 800.0 * W / 640.0
    cam = Camera(
        W,
        H,
        np.array([[f, 0.0, (W - 1) / 2.0], [0.0, f, (H - 1) / 2.0], [0.0, 0.0, 1.0]]),
        np.array([-0.12, 0.09, 0.0005, -0.0003, 0.0]) if distortion else np.zeros(5),
    )
    fp = 1860.0 * PW / 1024.0
    proj = Projector(PW, PH, np.array([[fp, 0.0, (PW - 1) / 2.0], [0.0, fp, (PH - 1) / 2.0], [0.0, 0.0, 1.0]]))
    eye = np.array([baseline_mm, 0.0, 0.0])
    R = look_at(eye, np.array([0.0, 0.0, distance_mm]))
    return Rig(cam, proj, R, eye)


def _size_px(size, name: str) -> tuple[int, int]:
    # paper_rig's (width, height) argument ``name`` as whole pixels in CAMERA_SIDE_PX, else GBError
    try:
        w, h = (int(x) for x in size)
    except (TypeError, ValueError):
        raise GBError(f"paper_rig: {name} must be (width, height) in pixels, got {size!r}") from None
    lo, hi = CAMERA_SIDE_PX
    if not (lo <= w <= hi and lo <= h <= hi) or (w, h) != tuple(size):
        raise GBError(f"paper_rig: {name} must be whole numbers of pixels in [{lo}, {hi}], got {size!r}")
    return w, h
