"""Scenes for the simulated rig: surfaces in the camera frame (mm) that rays can hit.

A :class:`Scene` is a list of objects (primitives).  For a batch of rays ``o + t d`` it returns
the first hit: distance ``t`` (in units of ``|d|``; mm for unit directions), the unit surface
normal facing the ray, the albedo RGB in [0, 1] and the object id (index in the scene, ``-1``
for no hit).  It also answers shadow queries (:meth:`Scene.occluded`).

Primitives (all exact except meshes, which are exact for their triangles):

* :class:`Plane` -- a plane patch ``z = 0`` of a local frame, bounded by a rectangle (or not).
* :class:`Sphere`.
* :class:`Box` -- an oriented box.
* :class:`Mesh` -- any triangle mesh (open3d's ``RaycastingScene``), smooth-shaded normals,
  per-vertex or procedural albedo.

Albedo specs (argument ``albedo`` everywhere): a float (grey), an RGB triple, or a callable
``f(p_local (N, 3) mm) -> (N, 3)`` evaluated in the object's local frame; ready-made ones:
:func:`skin`, :func:`colour_patches`, :func:`checker`.

Scene builders: :func:`plane`, :func:`sphere`, :func:`head`, :func:`step`, :func:`board`,
:func:`multi_object`, :func:`mesh`, :func:`fran_face`; combine scenes with :func:`combine`
(or ``scene_a + scene_b``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import GBError

#: A surface hit must lie at least this far along the ray (in units of |d|) to count.
T_MIN = 1e-6

#: Skin-like base albedo (linear RGB): reflects red best, blue least -- blue stripes on skin are
#: darker than green ones, as in the paper.
SKIN_RGB = (0.72, 0.52, 0.42)


# -- albedo ------------------------------------------------------------------------------------
def _albedo_fn(spec) -> Callable[[np.ndarray], np.ndarray]:
    """Albedo spec -> function of local points (N, 3) -> (N, 3) float64 in [0, 1]."""
    if callable(spec):
        return spec
    a = np.asarray(spec, dtype=np.float64).ravel()
    if a.size == 1:
        a = np.repeat(a, 3)
    if a.size != 3 or not np.all(np.isfinite(a)) or np.any(a < 0) or np.any(a > 1):
        raise GBError(f"albedo must be a grey value or an RGB triple in [0, 1], got {spec!r}")
    return lambda p: np.broadcast_to(a, (len(p), 3))


def _smooth_noise(p_xy: np.ndarray, scale_mm: float, seed: int, n_waves: int = 12) -> np.ndarray:
    """Smooth deterministic noise in about [-1, 1] of 2D points (N, 2): a sum of random waves."""
    rng = np.random.default_rng(seed)
    ang = rng.uniform(0, np.pi, n_waves)
    freq = rng.uniform(0.5, 1.5, n_waves) * 2 * np.pi / scale_mm
    phase = rng.uniform(0, 2 * np.pi, n_waves)
    k = np.stack([np.cos(ang), np.sin(ang)], axis=1) * freq[:, None]
    return np.sin(p_xy @ k.T + phase).sum(axis=1) / np.sqrt(n_waves / 2.0) / 2.0


def skin(base_rgb=SKIN_RGB, variation: float = 0.08, scale_mm: float = 25.0, seed: int = 3):
    """Skin-like albedo varying smoothly (``variation`` relative) over ``scale_mm`` patches."""
    base = np.asarray(base_rgb, dtype=np.float64)

    def f(p):
        n = _smooth_noise(p[:, :2], scale_mm, seed)
        return np.clip(base[None] * (1.0 + variation * n[:, None]), 0.0, 1.0)

    return f


def colour_patches(size_mm: float = 40.0, seed: int = 5, low: float = 0.1, high: float = 0.9):
    """A colourful texture: square patches of ``size_mm`` with random RGB albedo in [low, high]."""
    rng = np.random.default_rng(seed)
    table = rng.uniform(low, high, (64, 64, 3))

    def f(p):
        i = np.floor(p[:, 0] / size_mm).astype(np.int64) % 64
        j = np.floor(p[:, 1] / size_mm).astype(np.int64) % 64
        return table[j, i]

    return f


def checker(square_mm: float, dark: float = 0.05, light: float = 0.85, extent=None, margin: float | None = None):
    """Printed checkerboard albedo on local (x, y): the square ``[0,s] x [0,s]`` is light.

    ``extent = (xmin, xmax, ymin, ymax)`` limits the printed squares; outside it (the paper's
    margin) the albedo is ``light`` (white paper).
    """

    def f(p):
        i = np.floor(p[:, 0] / square_mm).astype(np.int64)
        j = np.floor(p[:, 1] / square_mm).astype(np.int64)
        white = (i + j) % 2 == 0
        if extent is not None:
            xmin, xmax, ymin, ymax = extent
            inside = (p[:, 0] >= xmin) & (p[:, 0] < xmax) & (p[:, 1] >= ymin) & (p[:, 1] < ymax)
            white = white | ~inside
        return np.repeat(np.where(white, light, dark)[:, None], 3, axis=1)

    return f


# -- primitives --------------------------------------------------------------------------------
def _rot_xy(about_x_deg: float, about_y_deg: float) -> np.ndarray:
    ax, ay = np.radians(about_x_deg), np.radians(about_y_deg)
    Rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    Ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    return Ry @ Rx


def _mul(p: np.ndarray, M: np.ndarray) -> np.ndarray:
    """``p @ M`` for (N, 3) x (3, k) (einsum: faster than BLAS for this shape)."""
    return np.einsum("ij,jk->ik", p, M)


def _dot(p: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``p @ v`` for (N, 3) x (3,)."""
    return np.einsum("ij,j->i", p, v)


class Primitive:
    """One object.  Subclasses implement ``intersect`` and ``surface``.

    ``R``, ``t``: local frame, ``p_cam = R @ p_local + t``; albedo is evaluated on local points.
    """

    R: np.ndarray
    t: np.ndarray
    albedo_fn: Callable
    #: A convex object cannot shadow its own front-facing points (shadow rays skip it).
    convex: bool = False
    #: Subsurface scattering: projected light spreads under the surface with this Gaussian
    #: sigma (mm) before it is reflected (skin: ~0.3-1 mm), blurring fine stripes.
    scatter_mm: float = 0.0

    def intersect(self, o: np.ndarray, d: np.ndarray):
        """Rays (N, 3), (N, 3) -> (t (N,) float64, ``inf`` where missed, aux or None)."""
        raise NotImplementedError

    def surface(self, p: np.ndarray, aux) -> tuple[np.ndarray, np.ndarray]:
        """Hit points (N, 3) (and this primitive's aux for them) -> (unit normals, albedo RGB)."""
        raise NotImplementedError

    def local(self, p: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) -> local points (N, 3)."""
        return _mul(p - self.t, self.R)

    def bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Axis-aligned (min, max) bounds in the camera frame, or None when unbounded."""
        return None


class Plane(Primitive):
    """The plane ``z_local = 0`` clipped to ``extent = (xmin, xmax, ymin, ymax)`` (mm, local)."""

    convex = True

    def __init__(self, R, t, albedo=0.7, extent=None):
        self.R = np.asarray(R, dtype=np.float64)
        self.t = np.asarray(t, dtype=np.float64).ravel()
        self.extent = None if extent is None else tuple(float(v) for v in extent)
        self.albedo_fn = _albedo_fn(albedo)
        self.n = self.R[:, 2].copy()

    def intersect(self, o, d):
        den = _dot(d, self.n)
        num = _dot(self.t - o, self.n)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = num / den
        t = np.where(np.isfinite(t) & (t > T_MIN), t, np.inf)
        if self.extent is not None:
            ok = np.isfinite(t)
            pl = self.local(o[ok] + t[ok, None] * d[ok])
            xmin, xmax, ymin, ymax = self.extent
            inside = (pl[:, 0] >= xmin) & (pl[:, 0] <= xmax) & (pl[:, 1] >= ymin) & (pl[:, 1] <= ymax)
            tt = t[ok]
            tt[~inside] = np.inf
            t[ok] = tt
        return t, None

    def surface(self, p, aux):
        return np.broadcast_to(self.n, p.shape), self.albedo_fn(self.local(p))

    def bounds(self):
        if self.extent is None:
            return None
        xmin, xmax, ymin, ymax = self.extent
        c = np.array([[x, y, 0.0] for x in (xmin, xmax) for y in (ymin, ymax)]) @ self.R.T + self.t
        return c.min(axis=0), c.max(axis=0)


class Sphere(Primitive):
    convex = True

    def __init__(self, centre_mm, radius_mm: float, albedo=0.7):
        self.R = np.eye(3)
        self.t = np.asarray(centre_mm, dtype=np.float64).ravel()
        self.radius = float(radius_mm)
        if not self.radius > 0:
            raise GBError(f"sphere radius must be positive, got {radius_mm}")
        self.albedo_fn = _albedo_fn(albedo)

    def intersect(self, o, d):
        oc = o - self.t
        a = np.einsum("ij,ij->i", d, d)
        b = np.einsum("ij,ij->i", oc, d)
        c = np.einsum("ij,ij->i", oc, oc) - self.radius**2
        disc = b * b - a * c
        with np.errstate(invalid="ignore"):
            s = np.sqrt(disc)
            t0 = (-b - s) / a
            t1 = (-b + s) / a
        t = np.where(t0 > T_MIN, t0, np.where(t1 > T_MIN, t1, np.inf))
        t = np.where(disc >= 0, t, np.inf)
        return t, None

    def surface(self, p, aux):
        return (p - self.t) / self.radius, self.albedo_fn(self.local(p))

    def bounds(self):
        return self.t - self.radius, self.t + self.radius


class Box(Primitive):
    """Oriented box: local ``|x| <= hx, |y| <= hy, |z| <= hz`` (``half_mm = (hx, hy, hz)``)."""

    convex = True

    def __init__(self, R, t, half_mm, albedo=0.7):
        self.R = np.asarray(R, dtype=np.float64)
        self.t = np.asarray(t, dtype=np.float64).ravel()
        self.half = np.asarray(half_mm, dtype=np.float64).ravel()
        self.albedo_fn = _albedo_fn(albedo)

    def intersect(self, o, d):
        ol = self.local(o)
        dl = _mul(d, self.R)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / dl
            ta = (-self.half - ol) * inv
            tb = (self.half - ol) * inv
        ta = np.where(np.isnan(ta), -np.inf, ta)
        tb = np.where(np.isnan(tb), np.inf, tb)
        tn = np.minimum(ta, tb).max(axis=1)
        tf = np.maximum(ta, tb).min(axis=1)
        t = np.where(tn > T_MIN, tn, tf)
        ok = (tf >= tn) & (t > T_MIN)
        return np.where(ok, t, np.inf), None

    def surface(self, p, aux):
        pl = self.local(p)
        r = np.abs(pl) / self.half
        axis = np.argmax(r, axis=1)
        nl = np.zeros_like(pl)
        nl[np.arange(len(pl)), axis] = np.sign(pl[np.arange(len(pl)), axis])
        return _mul(nl, self.R.T), self.albedo_fn(pl)

    def bounds(self):
        c = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * self.half
        c = c @ self.R.T + self.t
        return c.min(axis=0), c.max(axis=0)


class Mesh(Primitive):
    """A triangle mesh (camera frame, mm), ray cast with open3d.

    vertices_mm (V, 3), triangles (T, 3) int; albedo: a spec (evaluated on camera-frame points,
    the local frame being the camera's) or a (V, 3) per-vertex array interpolated over triangles.
    Normals are interpolated vertex normals (smooth shading) unless ``smooth=False``.
    """

    def __init__(self, vertices_mm, triangles, albedo=0.7, smooth: bool = True):
        v = np.asarray(vertices_mm, dtype=np.float64)
        f = np.asarray(triangles, dtype=np.int64)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise GBError(f"mesh needs vertices (V, 3) and triangles (T, 3), got {v.shape} and {f.shape}")
        if f.min() < 0 or f.max() >= len(v):
            raise GBError("mesh triangles index vertices out of range")
        self.R = np.eye(3)
        self.t = np.zeros(3)
        self.vertices = v
        self.triangles = f
        self.smooth = smooth
        a = albedo
        if isinstance(a, np.ndarray) and a.ndim == 2 and a.shape == v.shape:
            self.vertex_albedo = np.clip(a.astype(np.float64), 0, 1)
            self.albedo_fn = None
        else:
            self.vertex_albedo = None
            self.albedo_fn = _albedo_fn(a)
        e1 = v[f[:, 1]] - v[f[:, 0]]
        e2 = v[f[:, 2]] - v[f[:, 0]]
        fn = np.cross(e1, e2)  # area-weighted face normals
        vn = np.zeros_like(v)
        for k in range(3):
            np.add.at(vn, f[:, k], fn)
        self.face_normals = fn / np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
        self.vertex_normals = vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)
        self._scene = None

    def _rc(self):
        if self._scene is None:
            import open3d as o3d

            sc = o3d.t.geometry.RaycastingScene()
            sc.add_triangles(o3d.core.Tensor(self.vertices.astype(np.float32)),
                             o3d.core.Tensor(self.triangles.astype(np.uint32)))
            self._scene = sc
        return self._scene

    def _rays(self, o, d):
        import open3d as o3d

        return o3d.core.Tensor(np.ascontiguousarray(np.concatenate([o, d], axis=1), dtype=np.float32))

    def intersect(self, o, d):
        if len(o) == 0:
            return np.zeros(0), (np.zeros(0, np.int64), np.zeros((0, 2)))
        ans = self._rc().cast_rays(self._rays(o, d))
        t = ans["t_hit"].numpy().astype(np.float64)
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        uv = ans["primitive_uvs"].numpy().astype(np.float64)
        t = np.where(np.isfinite(t) & (t > T_MIN), t, np.inf)
        # Refine t in float64 against the hit triangle's plane (open3d works in float32).
        ok = np.isfinite(t)
        if np.any(ok):
            fi = prim[ok]
            n = self.face_normals[fi]
            p0 = self.vertices[self.triangles[fi, 0]]
            den = np.einsum("ij,ij->i", d[ok], n)
            with np.errstate(divide="ignore", invalid="ignore"):
                tr = np.einsum("ij,ij->i", p0 - o[ok], n) / den
            good = np.isfinite(tr) & (np.abs(tr - t[ok]) < 1e-3 * np.maximum(1.0, t[ok]))
            t[ok] = np.where(good, tr, t[ok])
        return t, (prim, uv)

    def occluded(self, o, d, t_max: float):
        if len(o) == 0:
            return np.zeros(0, bool)
        return self._rc().test_occlusions(self._rays(o, d), tnear=1e-4, tfar=float(t_max)).numpy().astype(bool)

    def surface(self, p, aux):
        prim, uv = aux
        tri = self.triangles[prim]
        w = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
        if self.smooth:
            n = np.einsum("nk,nkj->nj", w, self.vertex_normals[tri])
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        else:
            n = self.face_normals[prim]
        if self.vertex_albedo is not None:
            alb = np.einsum("nk,nkj->nj", w, self.vertex_albedo[tri])
        else:
            alb = self.albedo_fn(p)
        return n, alb

    def bounds(self):
        return self.vertices.min(axis=0), self.vertices.max(axis=0)


# -- scene -------------------------------------------------------------------------------------
class Moved(Primitive):
    """Another primitive moved rigidly: a point ``q`` of ``inner`` is at ``R @ q + t`` (camera
    frame, mm).  Rays are taken into the inner primitive's frame and its normals brought back,
    so its albedo (a texture) moves with it and ray lengths are unchanged.  Build with
    :func:`moved`."""

    def __init__(self, inner: Primitive, R, t):
        R = np.asarray(R, dtype=np.float64)
        t = np.asarray(t, dtype=np.float64).ravel()
        if R.shape != (3, 3) or not np.all(np.isfinite(R)) or \
                not np.allclose(R @ R.T, np.eye(3), atol=1e-9) or np.linalg.det(R) < 0:
            raise GBError("a rigid motion needs R a (3, 3) rotation matrix (orthonormal, determinant +1)")
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            raise GBError(f"a rigid motion needs t a finite (3,) translation in mm, got {t}")
        self.inner = inner
        self.R = R
        self.t = t
        self.albedo_fn = inner.albedo_fn
        self.convex = inner.convex
        self.scatter_mm = getattr(inner, "scatter_mm", 0.0)

    def intersect(self, o, d):
        return self.inner.intersect(self.local(o), _mul(d, self.R))

    def surface(self, p, aux):
        n, a = self.inner.surface(self.local(p), aux)
        return _mul(n, self.R.T), a

    def occluded(self, o, d, t_max: float):
        if isinstance(self.inner, (Mesh, Moved)):
            return self.inner.occluded(self.local(o), _mul(d, self.R), t_max)
        t, _ = self.intersect(o, d)
        return t < t_max

    def bounds(self):
        b = self.inner.bounds()
        if b is None:
            return None
        lo, hi = b
        c = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        c = c @ self.R.T + self.t
        return c.min(axis=0), c.max(axis=0)


@dataclass
class Hit:
    """First hits of N rays: ``t`` (N,) (inf: none), ``normal`` (N, 3) unit, facing the ray
    (zero where none), ``albedo`` (N, 3), ``object_id`` (N,) int16 (-1: none)."""

    t: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray
    object_id: np.ndarray


@dataclass
class Scene:
    """Objects in the camera frame; ``object_id`` of a hit is the index in ``objects``."""

    objects: list = field(default_factory=list)
    name: str = "scene"

    def __add__(self, other: "Scene") -> "Scene":
        return combine(self, other)

    def intersect(self, o: np.ndarray, d: np.ndarray) -> Hit:
        """First hit of rays ``o + t d`` (o, d (N, 3) float64)."""
        o = np.asarray(o, dtype=np.float64)
        d = np.asarray(d, dtype=np.float64)
        n = len(d)
        if o.shape != d.shape:
            o = np.broadcast_to(o, d.shape)
        best = np.full(n, np.inf)
        oid = np.full(n, -1, np.int16)
        auxes = []
        for i, obj in enumerate(self.objects):
            t, aux = obj.intersect(o, d)
            closer = t < best
            best = np.where(closer, t, best)
            oid[closer] = i
            auxes.append(aux)
        normal = np.zeros((n, 3))
        albedo = np.zeros((n, 3))
        p = o + np.where(np.isfinite(best), best, 0.0)[:, None] * d
        for i, obj in enumerate(self.objects):
            sel = np.flatnonzero(oid == i)
            if sel.size == 0:
                continue
            aux = auxes[i]
            if aux is not None:
                aux = tuple(a[sel] for a in aux)
            nn, aa = obj.surface(p[sel], aux)
            normal[sel] = nn
            albedo[sel] = aa
        # Two-sided surfaces: the normal faces the incoming ray.
        flip = np.einsum("ij,ij->i", normal, d) > 0
        normal[flip] *= -1
        return Hit(best, normal, albedo, oid)

    def occluded(self, o: np.ndarray, d: np.ndarray, t_max: float = 1.0, source_id=None) -> np.ndarray:
        """(N,) bool: does segment ``o + t d``, ``T_MIN < t < t_max``, hit anything?

        ``source_id`` (N,) gives the object each ray starts on (front-facing to ``d``); convex
        objects are not tested against their own rays.
        """
        o = np.asarray(o, dtype=np.float64)
        d = np.asarray(d, dtype=np.float64)
        occ = np.zeros(len(d), bool)
        for i, obj in enumerate(self.objects):
            todo = ~occ
            if source_id is not None and obj.convex:
                todo &= source_id != i
            if not np.any(todo):
                continue
            if isinstance(obj, (Mesh, Moved)):
                occ[todo] = obj.occluded(o[todo], d[todo], t_max)
            else:
                t, _ = obj.intersect(o[todo], d[todo])
                occ[todo] = t < t_max
        return occ


def combine(*scenes: Scene, name: str | None = None) -> Scene:
    """One scene holding every object of ``scenes`` (ids renumbered in order)."""
    objs = []
    for s in scenes:
        if isinstance(s, Primitive):
            objs.append(s)
        elif isinstance(s, Scene):
            objs.extend(s.objects)
        else:
            raise GBError(f"combine() takes scenes or primitives, got {type(s).__name__}")
    return Scene(objs, name or "+".join(getattr(s, "name", type(s).__name__) for s in scenes))


# -- builders ----------------------------------------------------------------------------------
def rotation_deg(about_x: float = 0.0, about_y: float = 0.0, about_z: float = 0.0) -> np.ndarray:
    """(3, 3) rotation by ``about_x``, then ``about_y``, then ``about_z`` degrees: ``Rz @ Ry @ Rx``
    (camera frame: x right, y down, z forward; ``about_y`` turns a face left or right, a yaw)."""
    az = np.radians(float(about_z))
    Rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return Rz @ _rot_xy(float(about_x), float(about_y))


def moved(scene: Scene, R=None, t_mm=(0.0, 0.0, 0.0), about_mm=(0.0, 0.0, 0.0)) -> Scene:
    """``scene`` moved rigidly: turned by the rotation ``R`` (default none) about the point
    ``about_mm``, then shifted by ``t_mm`` -- a point ``p`` goes to ``R (p - c) + c + t``.  Every
    object keeps its texture and its id.  The poses of a moving object during one exposure
    (:func:`gbscan.sim.render_moving`) are scenes made by this."""
    if not isinstance(scene, Scene):
        raise GBError(f"moved() takes a Scene, got {type(scene).__name__}")
    R = np.eye(3) if R is None else np.asarray(R, dtype=np.float64)
    c = np.asarray(about_mm, dtype=np.float64).ravel()
    t = np.asarray(t_mm, dtype=np.float64).ravel()
    if c.shape != (3,) or t.shape != (3,):
        raise GBError(f"moved(): t_mm and about_mm must be 3 numbers (mm), got {t_mm!r}, {about_mm!r}")
    shift = t + c - R @ c if R.shape == (3, 3) else t
    return Scene([Moved(o, R, shift) for o in scene.objects], scene.name)


def exposure_poses(scene: Scene, move_mm=(0.0, 0.0, 0.0), turn_deg: float = 0.0, steps: int = 9,
                   about_mm=None) -> list:
    """The scene at ``steps`` (odd) equally spaced instants of an exposure during which its objects
    move ``move_mm`` (camera frame) and turn ``turn_deg`` about the vertical axis through
    ``about_mm`` (default: the middle of the moving objects' bounds), centred on mid-exposure: at
    instant ``f`` in -1/2 .. 1/2 a pose is moved ``f move_mm`` and turned ``f turn_deg`` (no turn at
    all when ``turn_deg`` is 0: a pure shift).  An unbounded plane (a wall behind the object) stays,
    unless the scene is nothing else; the objects keep their order, so their ids.  The poses of
    :func:`gbscan.sim.render_moving`."""
    if not isinstance(scene, Scene):
        raise GBError(f"exposure_poses() takes a Scene, got {type(scene).__name__}")
    if int(steps) < 1 or int(steps) % 2 == 0:
        raise GBError(f"exposure_poses(): steps must be an odd number >= 1 (the middle instant is mid-exposure), "
                      f"got {steps}")
    moves = [o.bounds() is not None for o in scene.objects]
    if not any(moves):
        moves = [True] * len(scene.objects)
    if about_mm is None:
        b = [o.bounds() for o, m in zip(scene.objects, moves) if m and o.bounds() is not None]
        about_mm = (np.min([x[0] for x in b], axis=0) + np.max([x[1] for x in b], axis=0)) / 2 if b else np.zeros(3)
    move = np.asarray(move_mm, dtype=np.float64)
    out = []
    for f in np.linspace(-0.5, 0.5, int(steps)) if int(steps) > 1 else [0.0]:
        R = None if turn_deg == 0 else rotation_deg(about_y=f * turn_deg)
        sc = moved(scene, R, move * f, about_mm if R is not None else (0.0, 0.0, 0.0))
        out.append(Scene([mo if m else o for o, mo, m in zip(scene.objects, sc.objects, moves)], scene.name))
    return out


def _pos(name, v):
    v = float(v)
    if not np.isfinite(v) or v <= 0:
        raise GBError(f"{name} must be a positive number of mm, got {v!r}")
    return v


def plane(distance_mm: float = 650.0, tilt_deg=(0.0, 0.0), albedo=0.7, extent=None) -> Scene:
    """A plane crossing the optical axis at ``distance_mm``, tilted ``(about_x, about_y)``
    degrees from fronto-parallel; ``extent = (xmin, xmax, ymin, ymax)`` mm in its own frame bounds it."""
    d = _pos("plane distance_mm", distance_mm)
    R = _rot_xy(*tilt_deg)
    return Scene([Plane(R, [0.0, 0.0, d], albedo, extent)], "plane")


def sphere(centre_mm=(0.0, 0.0, 650.0), radius_mm: float = 100.0, albedo=0.7, wall_mm: float | None = None,
           wall_albedo=0.6) -> Scene:
    """A sphere, optionally in front of a fronto-parallel wall at ``wall_mm`` (casts a shadow)."""
    objs = [Sphere(centre_mm, radius_mm, albedo)]
    if wall_mm is not None:
        objs.append(Plane(np.eye(3), [0.0, 0.0, _pos("wall_mm", wall_mm)], wall_albedo))
    return Scene(objs, "sphere")


def step(distance_mm: float = 650.0, height_mm: float = 40.0, albedo=0.7, edge_x_mm: float = 0.0) -> Scene:
    """A depth discontinuity: a wall at ``distance_mm`` and, right of ``x = edge_x_mm``, a block
    whose front face stands ``height_mm`` nearer the camera.  With the paper rig's projector on
    the right, the block's edge casts a projector shadow on the wall just left of the edge."""
    d = _pos("step distance_mm", distance_mm)
    h = _pos("step height_mm", height_mm)
    big = 4.0 * d
    wall = Plane(np.eye(3), [0.0, 0.0, d], albedo)
    block = Box(np.eye(3), [edge_x_mm + big, 0.0, d - h / 2.0], [big, big, h / 2.0], albedo)
    return Scene([wall, block], "step")


def board(cols: int = 9, rows: int = 7, square_mm: float = 30.0, R_cam_board=None, t_cam_board=None,
          margin_mm: float | None = None, dark: float = 0.05, light: float = 0.85) -> Scene:
    """A printed checkerboard (the convention of docs/design.md, "Checkerboard convention").

    Board frame: origin at inner corner (0, 0), x along cols, y along rows, +z into the board;
    inner corner (i, j) at ``(i*s, j*s, 0)``; the square ``[0,s] x [0,s]`` is white; the printed
    grid covers ``(cols+1) x (rows+1)`` squares, plus a white margin (default one square).
    ``p_cam = R_cam_board @ p_board + t_cam_board`` (default: fronto-parallel, centred, 650 mm).
    """
    cols, rows = int(cols), int(rows)
    if cols < 2 or rows < 2:
        raise GBError(f"board needs at least 2x2 inner corners, got {cols}x{rows}")
    s = _pos("board square_mm", square_mm)
    m = s if margin_mm is None else float(margin_mm)
    R = np.eye(3) if R_cam_board is None else np.asarray(R_cam_board, dtype=np.float64)
    if t_cam_board is None:
        t = np.array([-(cols - 1) * s / 2.0, -(rows - 1) * s / 2.0, 650.0])
    else:
        t = np.asarray(t_cam_board, dtype=np.float64).ravel()
    if R.shape != (3, 3) or abs(np.linalg.det(R) - 1) > 1e-6 or t.shape != (3,):
        raise GBError("board pose must be a 3x3 rotation R_cam_board and a 3-vector t_cam_board")
    printed = (-s, cols * s, -s, rows * s)
    extent = (-s - m, cols * s + m, -s - m, rows * s + m)
    return Scene([Plane(R, t, checker(s, dark, light, printed), extent)], "board")


def board_corners(cols: int, rows: int, square_mm: float) -> np.ndarray:
    """(cols*rows, 3) inner corners in the board frame, row by row, x fastest (OpenCV's order)."""
    j, i = np.mgrid[0:rows, 0:cols]
    return np.stack([i.ravel() * square_mm, j.ravel() * square_mm, np.zeros(i.size)], axis=1).astype(np.float64)


def mesh(vertices_mm, triangles, albedo=0.7, smooth: bool = True) -> Scene:
    """Any triangle mesh in the camera frame (mm)."""
    return Scene([Mesh(vertices_mm, triangles, albedo, smooth)], "mesh")


def _grid_triangles(nu: int, nv: int, wrap_u: bool = False) -> np.ndarray:
    """Triangles of a (nv, nu) vertex grid, row-major."""
    cu = nu if wrap_u else nu - 1
    j, i = np.mgrid[0 : nv - 1, 0:cu]
    a = j * nu + i
    b = j * nu + (i + 1) % nu
    c = (j + 1) * nu + i
    d = (j + 1) * nu + (i + 1) % nu
    return np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])


def _bump(x, y, x0, y0, sx, sy, amp):
    return amp * np.exp(-0.5 * (((x - x0) / sx) ** 2 + ((y - y0) / sy) ** 2))


def _smoothstep(a, b, x):
    u = np.clip((x - a) / (b - a), 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def head_relief(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Facial relief (mm, towards the camera) over face coordinates x right, y down (mm, origin
    between the eyes' level and the nose's root).  Nose up to ~28 mm, sockets ~-12 mm."""
    r = np.zeros_like(x)
    # nose: a ridge from the root (y ~ -25) growing to the tip (y ~ 14), then the underside
    # curving back to the upper lip by y ~ 30
    t = np.clip((y + 25.0) / 40.0, 0.0, 1.0)
    ridge = (6.0 + 16.0 * t**1.3) * np.exp(-0.5 * (x / (5.0 + 5.0 * t)) ** 2)
    r += ridge * (1.0 - _smoothstep(12.0, 30.0, y)) * _smoothstep(-38.0, -22.0, y)
    r += _bump(x, y, 0, 13, 7, 6, 5.0)                  # nose tip lobe
    for sx in (-1.0, 1.0):
        r += _bump(x, y, sx * 32, -22, 16, 11, -12.0)   # eye sockets
        r += _bump(x, y, sx * 32, -40, 20, 6, 6.0)      # brow ridges
        r += _bump(x, y, sx * 42, 18, 20, 18, 7.0)      # cheeks
        r += _bump(x, y, sx * 12, 30, 6, 4, 3.0)        # nostril wings
    r += _bump(x, y, 0, 46, 20, 5, 6.0)                 # upper lip
    r += _bump(x, y, 0, 56, 18, 5, 5.0)                 # lower lip
    r += _bump(x, y, 0, 50, 26, 4, -2.0)                # mouth line
    r += _bump(x, y, 0, 80, 20, 10, 8.0)                # chin
    r += _bump(x, y, 0, -70, 50, 25, 3.0)               # forehead
    return r


def head_albedo(skin_rgb=SKIN_RGB, seed: int = 3):
    """Skin with darker eyebrows and reddish lips, on head-local points (x right, y down, z back)."""
    base = skin(skin_rgb, 0.08, 25.0, seed)
    brow = np.array([0.22, 0.15, 0.11])
    lips = np.array([0.62, 0.30, 0.30])

    def f(p):
        a = base(p)
        x, y = p[:, 0], p[:, 1]
        front = p[:, 2] < 0
        wb = sum(_bump(x, y, sx * 32, -40, 15, 3.5, 1.0) for sx in (-1.0, 1.0)) * front
        wl = (_bump(x, y, 0, 46, 17, 3.5, 1.0) + _bump(x, y, 0, 56, 15, 3.5, 1.0)) * front
        wb = np.clip(wb, 0, 1)[:, None]
        wl = np.clip(wl, 0, 1)[:, None]
        return a * (1 - wb) * (1 - wl) + brow * wb + lips * wl * (1 - wb)

    return f


def head(distance_mm: float = 650.0, yaw_deg: float = 0.0, pitch_deg: float = 0.0, albedo=None,
         resolution: int = 320, wall_mm: float | None = None, wall_albedo=0.5, scatter_mm: float = 0.0) -> Scene:
    """A face-like head: an ellipsoidal skull (half-axes 78 x 105 x 95 mm) with nose, brow
    ridges, eye sockets, cheeks, lips and chin (relief of tens of mm); skin-like albedo with
    darker eyebrows and lips.  The nose tip is about ``distance_mm`` from the camera.
    ``yaw_deg``/``pitch_deg`` turn the head about its centre; ``wall_mm`` adds a background wall;
    ``scatter_mm`` gives the skin subsurface scattering (default 0: off).
    """
    d = _pos("head distance_mm", distance_mm)
    n = max(64, int(resolution))
    ax, ay, az = 78.0, 105.0, 95.0
    theta = np.linspace(0.0, np.pi, n)            # from the crown (top, -y) to the neck
    phi = np.linspace(-np.pi, np.pi, 2 * n, endpoint=False)  # 0 = facing the camera
    TH, PH = np.meshgrid(theta, phi, indexing="ij")
    ux = np.sin(TH) * np.sin(PH)
    uy = -np.cos(TH)
    uz = -np.sin(TH) * np.cos(PH)                 # front = -z (towards the camera)
    x, y, z = ax * ux, ay * uy, az * uz
    # face coordinates: frontal projection; relief fades out towards the sides
    fy = y + 5.0
    front = np.clip(-uz, 0, 1) ** 2
    rel = head_relief(x, fy) * front
    nrm = np.stack([x / ax**2, y / ay**2, z / az**2], -1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    P = np.stack([x, y, z], -1) + rel[..., None] * nrm   # outward = towards the camera in front
    P = P.reshape(-1, 3)
    tri = _grid_triangles(2 * n, n, wrap_u=True)  # rows: theta, columns: phi (wrapping)
    V = P @ _rot_xy(pitch_deg, yaw_deg).T
    V[:, 2] += d - V[:, 2].min()  # the nearest point (the nose tip when frontal) at distance_mm
    alb_fn = head_albedo() if albedo is None else _albedo_fn(albedo)
    vert_albedo = np.asarray(alb_fn(P), dtype=np.float64)
    face = Mesh(V, tri, vert_albedo)
    face.scatter_mm = float(scatter_mm)
    objs: list = [face]
    if wall_mm is not None:
        objs.append(Plane(np.eye(3), [0.0, 0.0, _pos("wall_mm", wall_mm)], wall_albedo))
    return Scene(objs, "head")


def multi_object(distance_mm: float = 650.0, wall_mm: float = 900.0, albedo=None, panel_albedo=None) -> Scene:
    """Several separate objects at different depths with gaps, in front of a wall: a sphere
    (left, ~600 mm), a turned box (right, ~690 mm), a small tilted colourful panel (top,
    ~760 mm; ``panel_albedo``: of that albedo instead), a small skin-coloured sphere (bottom,
    ~560 mm) and a grey wall at ``wall_mm``; all objects inside the paper rig's projector frame
    (``distance_mm`` scales the layout)."""
    d = _pos("multi_object distance_mm", distance_mm)
    s = d / 650.0
    a = 0.7 if albedo is None else albedo
    objs = [
        Sphere([-80 * s, -10 * s, 600 * s], 60 * s, a),
        Box(_rot_xy(10, -25), [95 * s, 25 * s, 690 * s], [40 * s, 55 * s, 30 * s], a),
        Plane(_rot_xy(-20, 15), [-5 * s, -100 * s, 760 * s],
              colour_patches(25 * s) if panel_albedo is None else panel_albedo, (-55 * s, 55 * s, -25 * s, 25 * s)),
        Sphere([30 * s, 78 * s, 560 * s], 28 * s, (0.75, 0.55, 0.45)),
        Plane(np.eye(3), [0.0, 0.0, _pos("wall_mm", wall_mm)], 0.55),
    ]
    return Scene(objs, "multi")


FRAN_PATH = Path(__file__).resolve().parents[3] / "shared" / "data" / "fran_face" / "fran_cut_derived.obj"


#: Yaw (deg) that turns the converted scan to face the camera (its gaze is not exactly +X).
FRAN_FRONTAL_YAW_DEG = 25.0


def fran_face(path=None, distance_mm: float = 650.0, subdivide: int = 2, albedo=None, yaw_deg: float = 0.0,
              scatter_mm: float = 0.0) -> Scene:
    """The real face mesh "fran_cut" (metres, looking along +X, up +Y), turned to face the camera
    with the nose tip at ``distance_mm`` (``yaw_deg`` turns it from frontal), Loop-subdivided ``subdivide`` times, skin albedo.
    ``scatter_mm``: skin subsurface scattering (default 0: off).  The file is not part of the
    project (default: ``../shared/data/fran_face/``)."""
    import open3d as o3d

    path = Path(FRAN_PATH if path is None else path)
    if not path.is_file():
        raise GBError(f"face mesh {path} does not exist (it lives in ../shared/data/fran_face/)")
    m = o3d.io.read_triangle_mesh(str(path))
    if len(m.triangles) == 0:
        raise GBError(f"face mesh {path} holds no triangles")
    m.remove_duplicated_vertices()
    m.triangle_uvs = o3d.utility.Vector2dVector()  # texture coordinates are not used (and subdivision warns)
    if subdivide > 0:
        m = m.subdivide_loop(number_of_iterations=int(subdivide))
    v = np.asarray(m.vertices, dtype=np.float64) * 1000.0
    f = np.asarray(m.triangles, dtype=np.int64)
    # object +X (gaze) -> camera -z, object +Y (up) -> camera -y, object +Z -> camera -x
    R0 = np.array([[0.0, 0.0, -1.0], [0.0, -1.0, 0.0], [-1.0, 0.0, 0.0]])
    v = v @ R0.T
    c = 0.5 * (v.min(axis=0) + v.max(axis=0))
    v = (v - c) @ _rot_xy(0.0, FRAN_FRONTAL_YAW_DEG + yaw_deg).T
    v[:, 2] += distance_mm - v[:, 2].min()
    v[:, 0] -= 0.5 * (v[:, 0].min() + v[:, 0].max())
    v[:, 1] -= 0.5 * (v[:, 1].min() + v[:, 1].max())
    local = v - np.array([0.0, 0.0, v[:, 2].min()])
    alb = np.asarray((skin() if albedo is None else _albedo_fn(albedo))(local), dtype=np.float64)
    face = Mesh(v, f, alb)
    face.scatter_mm = float(scatter_mm)
    return Scene([face], "fran")
