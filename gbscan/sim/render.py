"""Image formation of the simulated rig: one camera frame of a scene lit by a projector frame.

Physically motivated, vectorised numpy (+ open3d for meshes):

1. Camera rays: ``ss x ss`` sub-pixel samples per pixel through the camera model *with* its
   lens distortion (``Camera.normalize`` at pixel centres, interpolated to the sub-pixel
   offsets: ~1e-6 px), plus the exact ray of every pixel centre for the ground truth.
2. First hit in the scene: point, normal (facing the camera), albedo, object id.
3. Projector light at the hit: projector pixel ``rig.project_to_projector``; a secondary ray
   from the point to the projector centre tests the projector shadow; back-facing points and
   points outside the projector frame are unlit.  Radiance is the projector frame linearised
   (``(v/255)**proj_gamma``: frame values are sRGB-ish, so 0/255 patterns are unaffected) and
   blurred by projector defocus (Gaussian, sigma in projector px, growing away from the focus
   distance, plus the object's subsurface scattering ``scatter_mm`` seen in projector px),
   sampled bilinearly.
4. Irradiance ``E = radiance * cos(incidence) / (d_proj / ref_distance_mm)**2``; the camera's
   channels see it through the spectral ``crosstalk`` matrix; ambient light adds
   ``ambient_rgb``; Lambertian reflection with the albedo RGB; ``exposure`` scales.
5. Average of the sub-samples, vignetting, camera blur (Gaussian), optional motion blur, shot
   noise (variance proportional to signal, ``full_well_e``), read noise, camera encoding
   (gamma with a small linear toe, see :func:`encode`), 8-bit rounding and saturation.

Ground truth comes from the pixel-centre rays: ``point``, ``proj_xy``, ``lit``, ``object_id``;
``depth_edge`` marks depth jumps (> ``EDGE_REL`` relative), object-id changes and silhouettes,
dilated by one pixel.
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..errors import GBError
from ..rig import Rig
from .presets import Conditions, preset
from .scenes import Scene

#: Relative depth jump between 4-neighbours that counts as a depth edge.
EDGE_REL = 0.02
#: Offset (mm) of a shadow ray's origin along the surface normal.
SHADOW_EPS_MM = 0.01
#: Largest projector blur sigma (px) the simulator models.
MAX_PROJ_SIGMA_PX = 6.0
#: Encoding toe: ``encode`` uses ((x + b)**(1/g) - b**(1/g)) / ((1 + b)**(1/g) - b**(1/g)).
ENCODE_TOE = 0.01
#: Rays per processing chunk (memory bound).
CHUNK_RAYS = 240_000


@dataclass
class Render:
    """One simulated camera frame and its ground truth (H, W = camera size).

    image : (H, W, 3) uint8 RGB camera image.
    point : (H, W, 3) float32 mm camera frame, surface point on the pixel-centre ray; NaN where none.
    lit : (H, W) bool, the centre point is seen, faces the projector, is not in its shadow and
        falls inside the projector frame.
    depth_edge : (H, W) bool, within ~1 px of a depth jump, object change or silhouette.
    proj_xy : (H, W, 2) float32 projector pixel (x, y) (centres at integers) of ``point``, for
        every hit in front of the projector (also outside its frame -- see ``lit``); NaN otherwise.
    object_id : (H, W) int16 index of the scene object hit, -1 for background.
    linear : (H, W, 3) float32 noise-free linear camera signal (before blur and noise; 1 = full scale).
    motion_edge : (H, W) bool or None: in a frame of a moving scene (:func:`render_moving`), the
        pixels whose first surface changes during the exposure (another object, none, or a depth
        jump as for ``depth_edge``), dilated by one pixel: they mix surfaces as depth-edge pixels
        do.  None for a still frame.
    """

    image: np.ndarray
    point: np.ndarray
    lit: np.ndarray
    depth_edge: np.ndarray
    proj_xy: np.ndarray
    object_id: np.ndarray
    linear: np.ndarray
    motion_edge: np.ndarray | None = None

    def save_truth(self, path) -> None:
        """Write the ground truth (and image) as a compressed .npz, atomically (with
        ``motion_edge`` when there is one)."""
        from ..io import save_npz

        extra = {} if self.motion_edge is None else {"motion_edge": self.motion_edge}
        save_npz(path, image=self.image, point=self.point, lit=self.lit, depth_edge=self.depth_edge,
                 proj_xy=self.proj_xy, object_id=self.object_id, **extra)


# -- camera rays -------------------------------------------------------------------------------
_RAY_CACHE: "OrderedDict[tuple, np.ndarray]" = OrderedDict()


def _cam_key(cam: Camera, ss: int) -> tuple:
    return (cam.width, cam.height, cam.K.tobytes(), cam.dist.tobytes(), ss)


def subpixel_offsets(ss: int) -> np.ndarray:
    """(ss*ss, 2) sample offsets (du, dv) inside a pixel, a regular grid centred on it."""
    o = (np.arange(ss) + 0.5) / ss - 0.5
    dv, du = np.meshgrid(o, o, indexing="ij")
    return np.stack([du.ravel(), dv.ravel()], axis=1)


def sample_rays(cam: Camera, ss: int) -> np.ndarray:
    """(H, W, ss*ss, 3) float32 unit rays of the sub-pixel samples (cached per camera).

    The undistorted normalised coordinates are computed exactly at the pixel centres (and a
    one-pixel border) and interpolated bilinearly to the sub-pixel offsets: the distortion map
    is so smooth that this is within ~1e-6 px of the exact inverse, at a fraction of the cost.
    """
    key = _cam_key(cam, ss)
    if key in _RAY_CACHE:
        _RAY_CACHE.move_to_end(key)
        return _RAY_CACHE[key]
    H, W = cam.height, cam.width
    v, u = np.mgrid[-1 : H + 1, -1 : W + 1].astype(np.float64)
    xn = cam.normalize(np.stack([u, v], axis=-1))  # (H+2, W+2, 2)
    offs = subpixel_offsets(ss)
    rays = np.empty((H, W, len(offs), 3), np.float32)
    for k, (du, dv) in enumerate(offs):
        iu, iv = int(np.floor(du)), int(np.floor(dv))
        fu, fv = du - iu, dv - iv
        def at(a, b):
            return xn[1 + iv + b : 1 + iv + b + H, 1 + iu + a : 1 + iu + a + W]
        x = (at(0, 0) * (1 - fu) * (1 - fv) + at(1, 0) * fu * (1 - fv)
             + at(0, 1) * (1 - fu) * fv + at(1, 1) * fu * fv)
        r = np.concatenate([x, np.ones((H, W, 1))], axis=-1)
        rays[:, :, k] = r / np.linalg.norm(r, axis=-1, keepdims=True)
    _RAY_CACHE[key] = rays
    while len(_RAY_CACHE) > 3:
        _RAY_CACHE.popitem(last=False)
    return rays


def centre_rays(cam: Camera) -> np.ndarray:
    """(H, W, 3) float64 unit rays through the pixel centres (cached per camera)."""
    key = _cam_key(cam, 0)
    if key not in _RAY_CACHE:
        _RAY_CACHE[key] = cam.pixel_rays()
        while len(_RAY_CACHE) > 3:
            _RAY_CACHE.popitem(last=False)
    return _RAY_CACHE[key]


# -- projector light ---------------------------------------------------------------------------
class ProjectorLight:
    """A projector frame as linear radiance, blurred on demand, sampled bilinearly.

    The frame is padded with black so that blur fades out past its edges, and sampling outside
    the padded frame gives 0.
    """

    STEP_PX = 0.25  # sigma grid on which blurred copies are made (linear interpolation between)

    def __init__(self, frame: np.ndarray, cond: Conditions):
        lin = (frame.astype(np.float32) / 255.0) ** np.float32(cond.proj_gamma)
        lin *= np.asarray(cond.proj_gain_rgb, np.float32)
        self.pad = p = int(np.ceil(4 * MAX_PROJ_SIGMA_PX)) + 2
        # Stripe and Gray-code frames are constant down each column: the blurred frame is then
        # exactly separable (row profile x column profile), which is much cheaper to sample.
        self.separable = bool(np.all(frame == frame[:1]))
        if self.separable:
            self.base = (np.pad(lin[0], ((p, p), (0, 0))), np.pad(np.ones(frame.shape[0], np.float32), (p, p)))
        else:
            self.base = np.pad(lin, ((p, p), (p, p), (0, 0)))
        self.cond = cond
        self._levels: dict[int, object] = {}

    def sigma_px(self, dist_mm: np.ndarray) -> np.ndarray:
        """Defocus sigma (projector px) at distances ``dist_mm`` from the projector."""
        c = self.cond
        extra = c.proj_defocus_px_per_100mm * np.abs(dist_mm - c.proj_focus_mm) / 100.0
        return np.minimum(np.sqrt(c.proj_sigma_px**2 + extra**2), MAX_PROJ_SIGMA_PX)

    def _level(self, i: int):
        if i not in self._levels:
            s = i * self.STEP_PX
            if s < 1e-3:
                self._levels[i] = self.base
            elif self.separable:
                r = int(np.ceil(4 * s))
                k = np.exp(-0.5 * (np.arange(-r, r + 1) / s) ** 2)
                k = (k / k.sum()).astype(np.float32)
                row, col = self.base
                row = np.stack([np.convolve(row[:, c], k, mode="same") for c in range(3)], axis=1)
                self._levels[i] = (row, np.convolve(col, k, mode="same"))
            else:
                import cv2

                self._levels[i] = cv2.GaussianBlur(self.base, (0, 0), s, sigmaY=s, borderType=cv2.BORDER_CONSTANT)
        return self._levels[i]

    def _bilinear(self, img, xy: np.ndarray) -> np.ndarray:
        x = xy[:, 0] + self.pad
        y = xy[:, 1] + self.pad
        if isinstance(img, tuple):  # separable: linear in x times linear in y (== bilinear)
            row, col = img
            xs = np.arange(len(row))
            out = np.stack([np.interp(x, xs, row[:, c], left=0.0, right=0.0) for c in range(3)], axis=1)
            fy = np.interp(y, np.arange(len(col)), col, left=0.0, right=0.0)
            return (out * fy[:, None]).astype(np.float32)
        h, w = img.shape[:2]
        x0 = np.floor(x).astype(np.int64)
        y0 = np.floor(y).astype(np.int64)
        fx = (x - x0).astype(np.float32)[:, None]
        fy = (y - y0).astype(np.float32)[:, None]
        inside = (x0 >= 0) & (y0 >= 0) & (x0 < w - 1) & (y0 < h - 1)
        x0 = np.clip(x0, 0, w - 2)
        y0 = np.clip(y0, 0, h - 2)
        out = (img[y0, x0] * (1 - fx) * (1 - fy) + img[y0, x0 + 1] * fx * (1 - fy)
               + img[y0 + 1, x0] * (1 - fx) * fy + img[y0 + 1, x0 + 1] * fx * fy)
        out[~inside] = 0.0
        return out

    def sample(self, xy: np.ndarray, sigma_px: np.ndarray) -> np.ndarray:
        """Radiance (N, 3) float32 at projector pixels ``xy`` (N, 2) with blur ``sigma_px`` (N,)."""
        if len(xy) == 0:
            return np.zeros((0, 3), np.float32)
        g = sigma_px / self.STEP_PX
        lo = np.floor(g).astype(np.int64)
        frac = (g - lo).astype(np.float32)
        out = np.zeros((len(xy), 3), np.float32)
        for i in np.unique(lo):
            sel = lo == i
            a = self._bilinear(self._level(int(i)), xy[sel])
            f = frac[sel]
            if np.any(f > 1e-6):
                b = self._bilinear(self._level(int(i) + 1), xy[sel])
                a = a * (1 - f[:, None]) + b * f[:, None]
            out[sel] = a
        return out


def _project_to_projector(rig: Rig, P: np.ndarray) -> np.ndarray:
    """``rig.project_to_projector`` for (N, 3) points, with einsum (same numbers, faster)."""
    pp = np.einsum("ij,jk->ik", P - rig.t_cam_proj, rig.R_cam_proj)
    return rig.projector.project(pp)


def _light_geometry(rig: Rig, scene: Scene, light: ProjectorLight, cond: Conditions, P, n, oid):
    """Frame-independent projector light at surface points P (N, 3) with normals n (facing the
    camera) on objects ``oid``: (illuminated (N,) bool, projector pixel (N, 2), irradiance
    factor cos(incidence) * (ref / distance)**2 (N,), defocus sigma (N,), lit (N,) bool)."""
    L = rig.t_cam_proj - P
    dist = np.sqrt(np.einsum("ij,ij->i", L, L))
    cos_in = np.einsum("ij,ij->i", n, L) / dist
    xy = _project_to_projector(rig, P)
    pw, ph = rig.projector.width, rig.projector.height
    m = light.pad
    with np.errstate(invalid="ignore"):
        near = (xy[:, 0] > -m) & (xy[:, 0] < pw - 1 + m) & (xy[:, 1] > -m) & (xy[:, 1] < ph - 1 + m)
        inframe = (xy[:, 0] >= -0.5) & (xy[:, 0] < pw - 0.5) & (xy[:, 1] >= -0.5) & (xy[:, 1] < ph - 0.5)
    cand = np.flatnonzero(near & (cos_in > 0))
    occ = scene.occluded(P[cand] + SHADOW_EPS_MM * n[cand], L[cand], 1.0 - 1e-7, oid[cand])
    ill = np.zeros(len(P), bool)
    ill[cand[~occ]] = True
    factor = np.where(ill, cos_in * (cond.ref_distance_mm / dist) ** 2, 0.0)
    sigma = light.sigma_px(dist)
    scatter = np.array([float(getattr(o, "scatter_mm", 0.0)) for o in scene.objects] + [0.0])[oid]
    if np.any(scatter > 0):  # subsurface spread (mm) in projector pixels at this distance
        sigma = np.minimum(np.hypot(sigma, scatter * rig.projector.K[0, 0] / dist), MAX_PROJ_SIGMA_PX)
    return ill, xy, factor, sigma, ill & inframe


def _gloss(rig: Rig, cond: Conditions, P: np.ndarray, n: np.ndarray, S: int) -> np.ndarray:
    """(N,) float32 Blinn-Phong weight of the light's own colour at lit points P (N, 3) mm with
    normals n (facing the camera): ``exposure / S * specular * (n . h)**shininess * (ref / d)**2``,
    ``h`` the unit half vector between the directions to the projector and to the camera, ``d``
    the distance to the projector (the same fall-off as the diffuse irradiance)."""
    L = rig.t_cam_proj - P
    d = np.sqrt(np.einsum("ij,ij->i", L, L))
    V = -P / np.linalg.norm(P, axis=1, keepdims=True)
    hv = L / d[:, None] + V
    hv /= np.linalg.norm(hv, axis=1, keepdims=True)
    nh = np.clip(np.einsum("ij,ij->i", n, hv), 0.0, 1.0)
    g = cond.exposure / S * cond.specular * nh ** cond.shininess * (cond.ref_distance_mm / d) ** 2
    return g.astype(np.float32)


@dataclass
class Trace:
    """Everything about one view of a scene that does not depend on the projector frame.

    Ground truth (pixel-centre rays): ``t`` (H, W) ray length mm (inf: none), ``point``,
    ``proj_xy``, ``lit``, ``object_id``, ``depth_edge`` as in :class:`Render`.
    Sub-pixel samples lit by the projector (M of them): ``pix`` (M,) flat pixel index, ``xy``
    (M, 2) projector pixel, ``sigma`` (M,) defocus px, ``weight`` (M, 3) = exposure * albedo *
    irradiance factor / samples per pixel.  ``ambient`` (H, W, 3): the frame-independent part
    of the linear signal (ambient light).
    """

    t: np.ndarray
    point: np.ndarray
    proj_xy: np.ndarray
    lit: np.ndarray
    object_id: np.ndarray
    depth_edge: np.ndarray
    pix: np.ndarray
    xy: np.ndarray
    sigma: np.ndarray
    weight: np.ndarray
    ambient: np.ndarray
    cond: Conditions


def trace(rig: Rig, scene: Scene, cond: Conditions | str | None = None) -> Trace:
    """Cast the camera rays (pixel centres and sub-pixel samples) and the shadow rays."""
    if not isinstance(rig, Rig):
        raise GBError(f"the simulator needs a gbscan.rig.Rig, got {type(rig).__name__}")
    if not isinstance(scene, Scene):
        raise GBError(f"the simulator needs a gbscan.sim.scenes.Scene, got {type(scene).__name__}")
    cond = preset("typical") if cond is None else preset(cond)
    cam = rig.camera
    H, W = cam.height, cam.width
    geo_light = ProjectorLight(np.zeros((1, 1, 3), np.uint8), cond)  # pad and sigma model only
    zero = np.zeros((1, 3))

    # Ground truth from the pixel-centre rays.
    rc = centre_rays(cam).reshape(-1, 3)
    t_c = np.full(H * W, np.inf)
    oid_c = np.full(H * W, -1, np.int16)
    lit_c = np.zeros(H * W, bool)
    xy_c = np.full((H * W, 2), np.nan)
    for s0 in range(0, H * W, CHUNK_RAYS):
        d = rc[s0 : s0 + CHUNK_RAYS]
        hit = scene.intersect(np.broadcast_to(zero, d.shape), d)
        t_c[s0 : s0 + len(d)] = hit.t
        oid_c[s0 : s0 + len(d)] = hit.object_id
        h = np.flatnonzero(np.isfinite(hit.t))
        P = d[h] * hit.t[h, None]
        _, xy, _, _, lit = _light_geometry(rig, scene, geo_light, cond, P, hit.normal[h], hit.object_id[h])
        lit_c[s0 + h] = lit
        xy_c[s0 + h] = xy
    hit_c = np.isfinite(t_c)
    point = np.where(hit_c[:, None], rc * np.where(hit_c, t_c, 0)[:, None], np.nan)

    # Sub-pixel samples.
    ss = int(cond.supersample)
    S = ss * ss
    rays = sample_rays(cam, ss)
    rows = max(1, CHUNK_RAYS // (W * S))
    amb = np.asarray(cond.ambient_rgb, np.float32)
    ambient = np.zeros((H * W, 3), np.float32)
    parts = []
    for r0 in range(0, H, rows):
        d = rays[r0 : r0 + rows].reshape(-1, 3).astype(np.float64)
        hit = scene.intersect(np.broadcast_to(zero, d.shape), d)
        h = np.flatnonzero(np.isfinite(hit.t))
        if h.size == 0:
            continue
        pix = (r0 * W + h // S).astype(np.int64)
        alb = (np.float32(cond.exposure / S) * hit.albedo[h] * np.asarray(cond.albedo_gain_rgb)).astype(np.float32)
        if np.any(amb > 0):
            for c in range(3):
                ambient[:, c] += np.bincount(pix, weights=alb[:, c] * amb[c], minlength=H * W).astype(np.float32)
        P = d[h] * hit.t[h, None]
        ill, xy, factor, sigma, _ = _light_geometry(rig, scene, geo_light, cond, P, hit.normal[h], hit.object_id[h])
        weight = alb[ill] * factor[ill, None].astype(np.float32)
        if cond.specular > 0:
            weight += _gloss(rig, cond, P[ill], hit.normal[h][ill], S)[:, None]
        parts.append((pix[ill].astype(np.int32), xy[ill].astype(np.float32), sigma[ill].astype(np.float32),
                      weight))
    cat = (lambda i, shape, dt: np.concatenate([p[i] for p in parts]) if parts else np.zeros(shape, dt))
    return Trace(
        t=t_c.reshape(H, W), point=point.reshape(H, W, 3).astype(np.float32),
        proj_xy=xy_c.reshape(H, W, 2).astype(np.float32), lit=lit_c.reshape(H, W),
        object_id=oid_c.reshape(H, W), depth_edge=_depth_edges(t_c.reshape(H, W), oid_c.reshape(H, W)),
        pix=cat(0, (0,), np.int32), xy=cat(1, (0, 2), np.float32), sigma=cat(2, (0,), np.float32),
        weight=cat(3, (0, 3), np.float32), ambient=ambient.reshape(H, W, 3), cond=cond)


# -- camera ------------------------------------------------------------------------------------
def encode(lin: np.ndarray, gamma: float) -> np.ndarray:
    """Linear signal (1 = full scale) -> output DN (float, 0..255 before rounding).

    ``255 * ((x + b)**(1/g) - b**(1/g)) / ((1 + b)**(1/g) - b**(1/g))`` with ``b = ENCODE_TOE``: a
    gamma-``g`` curve with a finite slope at black, like real cameras' sRGB/Rec.709 curves.
    ``g = 1`` is linear.
    """
    x = np.clip(lin, 0.0, None)
    if gamma == 1.0:
        return 255.0 * x
    b, e = ENCODE_TOE, 1.0 / gamma
    return 255.0 * ((x + b) ** e - b**e) / ((1 + b) ** e - b**e)


def decode_dn(dn: np.ndarray, gamma: float) -> np.ndarray:
    """Inverse of :func:`encode`: output DN -> linear signal."""
    y = np.asarray(dn, dtype=np.float64) / 255.0
    if gamma == 1.0:
        return y
    b, e = ENCODE_TOE, 1.0 / gamma
    return (y * ((1 + b) ** e - b**e) + b**e) ** gamma - b


def _motion_kernel(length_px: float, angle_deg: float) -> np.ndarray:
    k = int(np.ceil(length_px)) // 2 * 2 + 3
    ker = np.zeros((k, k), np.float32)
    c = k // 2
    a = np.radians(angle_deg)
    for s in np.linspace(-length_px / 2, length_px / 2, 64):
        x, y = c + s * np.cos(a), c + s * np.sin(a)
        x0, y0 = int(np.floor(x)), int(np.floor(y))
        fx, fy = x - x0, y - y0
        ker[y0, x0] += (1 - fx) * (1 - fy)
        ker[y0, x0 + 1] += fx * (1 - fy)
        ker[y0 + 1, x0] += (1 - fx) * fy
        ker[y0 + 1, x0 + 1] += fx * fy
    return ker / ker.sum()


def _depth_edges(t: np.ndarray, oid: np.ndarray, rel: float = EDGE_REL) -> np.ndarray:
    import cv2

    hit = np.isfinite(t)
    edge = np.zeros(t.shape, bool)
    for a, b in (((slice(None), slice(0, -1)), (slice(None), slice(1, None))),
                 ((slice(0, -1), slice(None)), (slice(1, None), slice(None)))):
        ta, tb = t[a], t[b]
        with np.errstate(invalid="ignore"):
            jump = (hit[a] != hit[b]) | (oid[a] != oid[b]) | (
                hit[a] & hit[b] & (np.abs(ta - tb) > rel * np.minimum(ta, tb)))
        edge[a] |= jump
        edge[b] |= jump
    return cv2.dilate(edge.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)


def _check_frame(rig: Rig, frame) -> np.ndarray:
    f = np.asarray(frame)
    if f.ndim == 2:
        f = np.repeat(f[:, :, None], 3, axis=2)
    pw, ph = rig.projector.width, rig.projector.height
    if f.shape != (ph, pw, 3):
        raise GBError(f"projector frame must be ({ph}, {pw}, 3) for this {pw}x{ph} projector, got {f.shape}")
    if f.dtype != np.uint8:
        raise GBError(f"projector frame must be uint8, got {f.dtype}")
    return f


def linear_signal(tr: Trace, projector_rgb: np.ndarray) -> np.ndarray:
    """Noise-free linear camera signal (H, W, 3) float32 of a traced view under a projector frame."""
    cond = tr.cond
    light = ProjectorLight(projector_rgb, cond)
    H, W = tr.t.shape
    rad = light.sample(tr.xy, tr.sigma)
    cam_rgb = (rad @ np.asarray(cond.crosstalk, np.float32).T) * tr.weight
    out = tr.ambient.reshape(-1, 3).copy()
    for c in range(3):
        out[:, c] += np.bincount(tr.pix, weights=cam_rgb[:, c], minlength=H * W).astype(np.float32)
    return out.reshape(H, W, 3)


def camera_image(linear: np.ndarray, cam: Camera, cond: Conditions, rng: np.random.Generator) -> np.ndarray:
    """Linear signal (H, W, 3) -> 8-bit camera image: lateral chromatic aberration, vignetting, blur,
    motion, noise, encoding."""
    import cv2

    H, W = linear.shape[:2]
    img = linear.astype(np.float32, copy=True)
    if cond.lateral_ca_px:
        img = lateral_ca(img, (float(cam.K[0, 2]), float(cam.K[1, 2])), cond.lateral_ca_px)
    if cond.vignetting > 0:
        q = cam.pixel_grid()
        c = np.array([cam.K[0, 2], cam.K[1, 2]])
        r2 = ((q - c) ** 2).sum(-1)
        corner = max(((np.array([[0, 0], [W - 1, 0], [0, H - 1], [W - 1, H - 1]]) - c) ** 2).sum(-1))
        img *= (1.0 - cond.vignetting * r2 / corner).astype(np.float32)[:, :, None]
    if cond.cam_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), cond.cam_sigma_px, sigmaY=cond.cam_sigma_px,
                               borderType=cv2.BORDER_REFLECT)
    if cond.motion_px > 0:
        img = cv2.filter2D(img, -1, _motion_kernel(cond.motion_px, cond.motion_deg), borderType=cv2.BORDER_REFLECT)
    if cond.bayer:
        return _yuv_round_trip(_jpeg_round_trip(_bayer_image(img, cond, rng), cond), cond)
    noisy = img
    if cond.full_well_e > 0:
        noisy = noisy + np.sqrt(np.clip(img, 0, None) / cond.full_well_e) * rng.standard_normal(img.shape, np.float32)
    if cond.read_noise_dn > 0:
        noisy = noisy + np.float32(cond.read_noise_dn / 255.0) * rng.standard_normal(img.shape, np.float32)
    return _yuv_round_trip(_jpeg_round_trip(np.clip(np.rint(encode(noisy, cond.gamma)), 0, 255).astype(np.uint8), cond),
                           cond)


def lateral_ca(img: np.ndarray, centre: tuple[float, float], corner_px: float) -> np.ndarray:
    """A lens's lateral chromatic aberration on an (H, W, 3) float image (R, G, B): the blue image
    magnified about ``centre`` (x, y, px) so that it lies ``corner_px`` further out than the green
    one at the frame's farthest corner, the red one as far in (bilinear resampling; green as it
    is).  Negative ``corner_px``: blue inward, red outward."""
    import cv2

    H, W = img.shape[:2]
    cx, cy = centre
    rc = max(np.hypot(x - cx, y - cy) for x in (0.0, W - 1.0) for y in (0.0, H - 1.0))
    m = float(corner_px) / rc
    xs = np.arange(W, dtype=np.float32)[None, :] - np.float32(cx)
    ys = np.arange(H, dtype=np.float32)[:, None] - np.float32(cy)
    out = img.copy()
    for c, mag in ((0, 1.0 - m), (2, 1.0 + m)):
        mx = np.broadcast_to(np.float32(cx) + xs / np.float32(mag), (H, W)).astype(np.float32)
        my = np.broadcast_to(np.float32(cy) + ys / np.float32(mag), (H, W)).astype(np.float32)
        out[..., c] = cv2.remap(np.ascontiguousarray(img[..., c]), mx, my, cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_REPLICATE)
    return out


_JPEG_SAMPLING_FLAGS = {"4:4:4": "IMWRITE_JPEG_SAMPLING_FACTOR_444", "4:2:2": "IMWRITE_JPEG_SAMPLING_FACTOR_422",
                        "4:2:0": "IMWRITE_JPEG_SAMPLING_FACTOR_420"}


def _jpeg_round_trip(rgb: np.ndarray, cond: Conditions) -> np.ndarray:
    """The 8-bit RGB frame as a camera storing JPEG delivers it: OpenCV's (libjpeg) encoder at
    ``cond.jpeg_quality`` with ``cond.jpeg_sampling``, decoded again; unchanged when the quality is 0."""
    if not cond.jpeg_quality:
        return rgb
    import cv2

    flag = getattr(cv2, _JPEG_SAMPLING_FLAGS[cond.jpeg_sampling])
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]),
                           [cv2.IMWRITE_JPEG_QUALITY, int(cond.jpeg_quality), cv2.IMWRITE_JPEG_SAMPLING_FACTOR, flag])
    if not ok:
        raise GBError("the simulated camera could not encode its frame as JPEG")
    return np.ascontiguousarray(cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1])


_YUV_CODES = {"yuyv": ("COLOR_RGB2YUV_YUYV", "COLOR_YUV2RGB_YUYV"), "i420": ("COLOR_RGB2YUV_I420", "COLOR_YUV2RGB_I420")}


def _yuv_round_trip(rgb: np.ndarray, cond: Conditions) -> np.ndarray:
    # the frame of a camera delivering YUV (cond.yuv), unchanged for RGB frames or a raw mosaic
    if not cond.yuv or rgb.ndim != 3:
        return rgb
    return yuv_round_trip(rgb, cond.yuv)


def yuv_round_trip(rgb: np.ndarray, fmt: str) -> np.ndarray:
    """An 8-bit RGB frame (H, W, 3) as a camera delivering YUV frames gives it after OpenCV's
    conversion back to RGB: ``fmt`` "yuyv" keeps one colour per pixel pair along the rows (4:2:2),
    "i420" one per 2x2 block (4:2:0).  H and W must be even."""
    import cv2

    if fmt not in _YUV_CODES:
        raise GBError(f"yuv format must be one of {', '.join(_YUV_CODES)}, got {fmt!r}")
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8 or rgb.shape[0] % 2 or rgb.shape[1] % 2:
        raise GBError(f"a {fmt} camera needs an (H, W, 3) uint8 frame of even size, got {rgb.dtype} {rgb.shape}")
    to, back = (getattr(cv2, c) for c in _YUV_CODES[fmt])
    return np.ascontiguousarray(cv2.cvtColor(cv2.cvtColor(np.ascontiguousarray(rgb), to), back))


def _bayer_image(img: np.ndarray, cond: Conditions, rng: np.random.Generator) -> np.ndarray:
    """Colour-filter mosaic: one channel per photosite (pattern named by its top-left 2x2, row
    by row), noise per photosite, encoding, then OpenCV's edge-aware demosaicing to RGB
    (:func:`gbscan.io.demosaic`) -- or, with ``cond.bayer_raw``, the 8-bit mosaic (H, W) itself."""
    from ..io import demosaic

    H, W = img.shape[:2]
    ch = {"R": 0, "G": 1, "B": 2}
    p = cond.bayer
    sel = np.empty((H, W), np.int64)
    sel[0::2, 0::2], sel[0::2, 1::2] = ch[p[0]], ch[p[1]]
    sel[1::2, 0::2], sel[1::2, 1::2] = ch[p[2]], ch[p[3]]
    raw = np.take_along_axis(img, sel[:, :, None], axis=2)[:, :, 0]
    noisy = raw
    if cond.full_well_e > 0:
        noisy = noisy + np.sqrt(np.clip(raw, 0, None) / cond.full_well_e) * rng.standard_normal(raw.shape, np.float32)
    if cond.read_noise_dn > 0:
        noisy = noisy + np.float32(cond.read_noise_dn / 255.0) * rng.standard_normal(raw.shape, np.float32)
    mosaic = np.clip(np.rint(encode(noisy, cond.gamma)), 0, 255).astype(np.uint8)
    return mosaic if cond.bayer_raw else demosaic(mosaic, p)


def _rng(seed) -> np.random.Generator:
    return seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)


def render_traced(rig: Rig, tr: Trace, projector_rgb: np.ndarray, seed=0) -> Render:
    """Render a view already traced with :func:`trace` under another projector frame (cheap:
    only the projector sampling and the camera run again)."""
    frame = _check_frame(rig, projector_rgb)
    lin = linear_signal(tr, frame)
    image = camera_image(lin, rig.camera, tr.cond, _rng(seed))
    return Render(image=image, point=tr.point, lit=tr.lit, depth_edge=tr.depth_edge, proj_xy=tr.proj_xy,
                  object_id=tr.object_id, linear=lin)


def render(rig: Rig, scene: Scene, projector_rgb: np.ndarray, cond: Conditions | str | None = None,
           seed: int | np.random.Generator | None = 0) -> Render:
    """Render the camera image of ``scene`` lit by ``projector_rgb`` (H_p, W_p, 3) uint8.

    ``cond`` is a :class:`Conditions` or a preset name (default ``"typical"``); ``seed`` seeds
    the noise (an int or a ``numpy.random.Generator``).  Returns a :class:`Render`.
    To render one view under many frames, :func:`trace` once and :func:`render_traced` per frame.
    """
    frame = _check_frame(rig, projector_rgb)
    return render_traced(rig, trace(rig, scene, cond), frame, seed)


def render_moving(rig: Rig, poses, projector_rgb: np.ndarray, cond: Conditions | str | None = None,
                  seed: int | np.random.Generator | None = 0) -> Render:
    """The camera frame of a scene that moves during the exposure.

    ``poses``: a sequence of :class:`Scene`, the scene at equally spaced instants of the exposure
    (an odd number, at least 1: the middle one is mid-exposure; :func:`gbscan.sim.scenes.moved`
    makes them).  The projector and the camera stand still, so the stripes stay where the
    projector's light planes meet the surface: a plane sliding along itself keeps its stripes in
    place (only its texture smears), while depth changes shift them along the rows.  The
    noise-free linear signal of every pose is averaged (float64), then the camera's blur, noise and
    encoding run once (as :func:`render`).  Ground truth (``point``, ``proj_xy``, ``lit``,
    ``depth_edge``, ``object_id``) is the middle pose's: what a scan of the frame should return;
    ``motion_edge`` marks the pixels that see another surface during the exposure.  One pose gives
    :func:`render`'s frame, bit for bit.  ``cond.motion_px`` is another thing: the whole image
    smeared, as when the camera shakes.  Costs one :func:`trace` per pose."""
    import cv2

    poses = list(poses) if not isinstance(poses, Scene) else [poses]
    if not poses or len(poses) % 2 == 0:
        raise GBError(f"render_moving needs an odd number of poses (the middle one is mid-exposure), "
                      f"got {len(poses)}")
    frame = _check_frame(rig, projector_rgb)
    cond = preset("typical") if cond is None else preset(cond)
    acc = None
    surfaces = []          # (ray length, object id) of every pose's pixel-centre rays
    mid = None
    for k, scene in enumerate(poses):
        tr = trace(rig, scene, cond)
        lin = linear_signal(tr, frame).astype(np.float64)
        acc = lin if acc is None else acc + lin
        surfaces.append((tr.t, tr.object_id))
        if k == len(poses) // 2:
            mid = tr
    lin = (acc / len(poses)).astype(np.float32)
    image = camera_image(lin, rig.camera, cond, _rng(seed))
    changed = np.zeros(mid.t.shape, bool)
    hit_mid = np.isfinite(mid.t)
    for t, oid in surfaces:
        hit = np.isfinite(t)
        with np.errstate(invalid="ignore"):
            changed |= (hit != hit_mid) | (oid != mid.object_id) | (
                hit & hit_mid & (np.abs(t - mid.t) > EDGE_REL * np.minimum(t, mid.t)))
    motion_edge = cv2.dilate(changed.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    return Render(image=image, point=mid.point, lit=mid.lit, depth_edge=mid.depth_edge, proj_xy=mid.proj_xy,
                  object_id=mid.object_id, linear=lin, motion_edge=motion_edge)


def point_errors_mm(r: Render, xyz: np.ndarray, valid: np.ndarray, footprint: bool = True) -> np.ndarray:
    """3D error (mm) of every kept point of a scan of ``r``: (H, W) float64, inf where the truth
    has no surface, 0 where ``valid`` is False.

    xyz : (H, W, 3) scanned points, camera frame, mm; valid : (H, W) bool, the points kept.
    footprint : on pixels the simulator marks as depth edges (``r.depth_edge``), the distance to
    the nearest true point of the pixel and its 8 neighbours instead of its centre's.  Such a pixel
    integrates light from both surfaces (defocus, pixel area: the simulator renders both), so a
    point on either of them is a measurement of what the pixel sees; a flying pixel between the
    surfaces, or a point on a surface the pixel does not see, is still off.  The metric of the
    issue's "no point off by more than 3 mm" (tests, ``scripts/coverage_study.py``)."""
    P = np.asarray(r.point, np.float64)
    xyz = np.asarray(xyz)
    valid = np.asarray(valid, bool)
    if xyz.shape != P.shape or valid.shape != P.shape[:2]:
        raise GBError(f"point_errors_mm: xyz {xyz.shape} and valid {valid.shape} must match the render's "
                      f"points {P.shape}")
    err = np.zeros(valid.shape)
    err[valid] = np.linalg.norm(xyz[valid] - P[valid], axis=1)
    err[valid & ~np.isfinite(P[..., 2])] = np.inf
    if footprint:
        Pp = np.pad(P, ((1, 1), (1, 1), (0, 0)), constant_values=np.nan)
        edge = valid & np.asarray(r.depth_edge, bool)
        X = xyz[edge].astype(np.float64)
        ys, xs = np.nonzero(edge)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                e = np.linalg.norm(X - Pp[ys + 1 + dy, xs + 1 + dx], axis=1)
                err[ys, xs] = np.minimum(err[ys, xs], np.where(np.isfinite(e), e, np.inf))
    return err


def column_errors(column: np.ndarray, valid: np.ndarray, truth: np.ndarray,
                  stripe_px: float) -> tuple[np.ndarray, np.ndarray]:
    """A decoder's columns against the simulator's (``r.proj_xy[..., 0]``): the error (projector
    px, (H, W) float, 0 where not compared) and the *wrong* pixels ((H, W) bool): reported, with a
    true column, at least half a stripe off -- on another stripe, not just a sub-pixel miss.  The
    decoder metric of ``scripts/sweep_decode.py`` and ``scripts/resample_study.py`` (split it by
    ``r.depth_edge``: such pixels mix two surfaces)."""
    ok = np.asarray(valid, bool) & np.isfinite(truth)
    err = np.where(ok, column - truth, 0.0)
    return err, ok & (np.abs(err) >= stripe_px / 2)


def incidence_deg(rig: Rig, r: Render) -> tuple[np.ndarray, np.ndarray]:
    """Camera and projector incidence of the true surface per pixel: angles (deg, (H, W) float64)
    between the surface normal and the directions to the camera centre and to the projector
    centre; NaN where the pixel has no surface or no finite neighbours.

    The normal is estimated from ``r.point`` by central differences along the rows and columns
    (one-sided at holes), so within ~1 px of a depth edge it mixes surfaces (``r.depth_edge``
    marks those pixels).  What coverage studies bin by: stripes arrive dim and compressed at
    grazing projector incidence and are seen edge-on at grazing camera incidence."""
    P = np.asarray(r.point, np.float64)
    if P.ndim != 3 or P.shape[2] != 3:
        raise GBError(f"incidence_deg: r.point must be (H, W, 3), got {P.shape}")

    def diff(axis):
        fwd = np.roll(P, -1, axis) - P
        bwd = P - np.roll(P, 1, axis)
        idx = [slice(None)] * 3
        idx[axis] = -1
        fwd[tuple(idx)] = np.nan
        idx[axis] = 0
        bwd[tuple(idx)] = np.nan
        with np.errstate(invalid="ignore"):
            c = 0.5 * (fwd + bwd)
        return np.where(np.isfinite(c), c, np.where(np.isfinite(fwd), fwd, bwd))

    n = np.cross(diff(1), diff(0))
    with np.errstate(invalid="ignore", divide="ignore"):
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        to_cam = -P / np.linalg.norm(P, axis=-1, keepdims=True)
        to_proj = np.asarray(rig.projector_centre, np.float64) - P
        to_proj /= np.linalg.norm(to_proj, axis=-1, keepdims=True)
        n = np.where(np.sum(n * to_cam, -1, keepdims=True) < 0, -n, n)
        cam = np.degrees(np.arccos(np.clip(np.sum(n * to_cam, -1), -1, 1)))
        proj = np.degrees(np.arccos(np.clip(np.sum(n * to_proj, -1), -1, 1)))
    return cam, proj
