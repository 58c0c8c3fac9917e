"""Camera rays x projector light planes -> 3D points (camera frame, mm).

Inputs per pixel: the unit ray of its centre through the camera model (``Camera.pixel_rays()``,
computed once per calibration) and its
continuous projector column (px, NaN where unknown) from the decoder.  The calibration gives
light planes ``n . p = d`` only at the stripe boundaries' columns (``Calibration.plane_column``);
a column in between needs the plane through that column.

Which interpolation is exact
----------------------------
For a pinhole projector the light planes of all columns form a *pencil*: they share the line
through the projector centre parallel to its pixel columns, and the unnormalised plane
coefficients are affine in the column ``x``.  Interpolating unit normals and ``d`` linearly in
``x`` is therefore not exact (the unknown per-plane scale ``sqrt(fx^2 + (x - cx)^2)`` is lost
when normals are normalised), and neither is interpolating the ray depth linearly: along a
camera ray the depth ``s`` is a *projective* (Moebius) function of the projector column.
A projective map of a line is fixed by three point pairs, and cross ratios are invariant under
it.  So we intersect the ray with three calibrated planes -- the two enclosing the column and
the next neighbour -- giving depths ``s0, s1, s2`` at columns ``x0, x1, x2``, and solve

    CR(x0, x1; x2, x) = CR(s0, s1; s2, s)

for ``s``.  This is exact for any pinhole projector, needs no projector model (``camera`` and
``planes`` alone, as the calibration-file contract says), and it stays local, so planes that
were fitted one by one and are not a perfect pencil are still interpolated sensibly.  (Linear
depth interpolation between adjacent planes errs by 0.03 mm median, 0.35 mm at the pattern's
ends, at the paper's geometry: measured on a tilted plane at 650 mm.)  With only two planes
the depth is interpolated linearly.

Rays meeting a plane at a grazing angle (``|n . r| < sin(min_angle_deg)``), negative depths
and columns beyond the calibrated range give NaN, never huge values.

Whole frames: :class:`GridTriangulator`
---------------------------------------
:func:`triangulate` is the reference (any rays, float64).  Scanning frames uses
:class:`GridTriangulator`, built once per calibration: it keeps each pixel's ray as
``(mx, my, 1)`` (undistorted normalised coordinates, two float64 arrays) and, when the planes
form a pencil (every calibration ``gbcal`` writes: its planes come from the refined pinhole
projector, :meth:`PlaneTable.pencil`), the plane of a column in closed form,
``N(x) = a + (x - xc) b``, ``D(x) = ad + (x - xc) bd``.  A pixel is then ``z = D(x) / (N(x) . m)``,
``p = z m``: no table lookup, so the kernel is branch-free and vectorised (float64 arithmetic,
float32 points: equal to the reference rounded to float32).  The angle test of the reference is
on the two calibrated planes enclosing the column; the vectorised kernel only counts pixels
whose ray comes within that angle plus four plane spacings of the plane at ``x``, and a frame
with any such pixel is redone by the reference's compiled kernel on the same rays, normalised.
Planes that are not a pencil always take that kernel.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from .errors import GBError


@dataclass(frozen=True, eq=False)
class PlaneTable:
    """Light planes sorted by projector column, ready for per-pixel lookup.

    column : (P,) float64 projector columns (px), strictly increasing, P >= 2.
    normal : (P, 3) float64 unit normals (camera frame).
    d : (P,) float64 plane offsets (mm): ``normal[i] . p = d[i]``.
    spacing_px : median column spacing between consecutive planes (px).
    lut, lut0 : lookup table for the compiled kernel: ``lut[int(x - lut0)]`` is the last plane
        whose column is <= the start of that 1-px bin (clipped to 0 .. P-2).
    """

    column: np.ndarray
    normal: np.ndarray
    d: np.ndarray
    spacing_px: float
    lut: np.ndarray = None
    lut0: float = 0.0

    def __post_init__(self):
        if self.lut is None:
            lut0 = float(np.floor(self.column[0] - 2 * self.spacing_px))
            edges = lut0 + np.arange(int(np.ceil(self.column[-1] + 2 * self.spacing_px - lut0)) + 2)
            lut = np.searchsorted(self.column, edges, side="right") - 1
            object.__setattr__(self, "lut", np.clip(lut, 0, self.column.size - 2).astype(np.int64))
            object.__setattr__(self, "lut0", lut0)

    @classmethod
    def from_arrays(cls, column, normal, d) -> "PlaneTable":
        column = np.asarray(column, dtype=np.float64).ravel()
        normal = np.asarray(normal, dtype=np.float64).reshape(-1, 3)
        d = np.asarray(d, dtype=np.float64).ravel()
        if not (column.size == normal.shape[0] == d.size):
            raise GBError("light planes: column, normal and d must have one entry per plane")
        if column.size < 2:
            raise GBError(f"triangulation needs at least 2 light planes, the calibration has {column.size} "
                          "(calibrate the projector with 'gbcal calibrate SESSION')")
        if not (np.all(np.isfinite(column)) and np.all(np.isfinite(normal)) and np.all(np.isfinite(d))):
            raise GBError("light planes hold non-finite numbers; recalibrate")
        order = np.argsort(column, kind="stable")
        column, normal, d = column[order], normal[order], d[order]
        if np.any(np.diff(column) <= 0):
            raise GBError("light planes: two planes share one projector column; recalibrate")
        norm = np.linalg.norm(normal, axis=1)
        if np.any(np.abs(norm - 1.0) > 1e-6):
            raise GBError("light planes: normals must be unit vectors")
        return cls(np.ascontiguousarray(column), np.ascontiguousarray(normal), np.ascontiguousarray(d),
                   float(np.median(np.diff(column))))

    @classmethod
    def from_calibration(cls, calib) -> "PlaneTable":
        """From a :class:`gbscan.calibfile.Calibration` (its ``plane_column/normal/d``)."""
        return cls.from_arrays(calib.plane_column, calib.plane_normal, calib.plane_d)

    @property
    def n_planes(self) -> int:
        return int(self.column.size)

    def pencil(self, tol: float = 1e-10) -> "Pencil | None":
        """The planes as one :class:`Pencil` ``(a + (x - xc) b) . p = ad + (x - xc) bd``, or None when
        they are not one (within ``tol``: unit-normal components, and ``d`` relative to the
        largest ``|d|``, at every calibrated plane).  Computed once per table."""
        key = ("_pencil", float(tol))
        cache = self.__dict__.setdefault("_cache", {})
        if key not in cache:
            cache[key] = _fit_pencil(self.column, self.normal, self.d, tol)
        return cache[key]


@dataclass(frozen=True, eq=False)
class Pencil:
    """Light planes of a pinhole projector: column ``x`` has the (unnormalised) plane
    ``(a + (x - xc) b) . p = ad + (x - xc) bd`` (camera frame, mm).

    a, b : (3,) float64; ad, bd : float (mm, mm/px); xc : column the expansion is about (px).
    fit_error : largest deviation of a calibrated plane (unit normal components, and d in mm).
    """

    xc: float
    a: np.ndarray
    b: np.ndarray
    ad: float
    bd: float
    fit_error: tuple[float, float]


def _fit_pencil(column, normal, d, tol) -> Pencil | None:
    """Fit a pencil to the planes (a rank-2 subspace of homogeneous planes, then the projective
    map from columns onto it) and check it reproduces every plane; None if it does not."""
    P = column.size
    if P < 3:
        return None
    L = max(1.0, float(np.max(np.abs(d))))
    q = np.concatenate([normal, (d / L)[:, None]], axis=1)  # (P, 4) homogeneous planes
    _, sv, vt = np.linalg.svd(q, full_matrices=False)
    if sv[2] > 1e-6 * sv[0]:
        return None
    e1, e2 = vt[0], vt[1]
    alpha, beta = q @ e1, q @ e2
    xc = 0.5 * (column[0] + column[-1])
    xs = max(0.5 * (column[-1] - column[0]), 1e-12)
    t = (column - xc) / xs
    # (alpha : beta) = (a0 + a1 t : c0 + c1 t)  ->  alpha (c0 + c1 t) - beta (a0 + a1 t) = 0
    M = np.stack([-beta, -beta * t, alpha, alpha * t], axis=1)
    _, _, vt2 = np.linalg.svd(M, full_matrices=False)
    a0, a1, c0, c1 = vt2[-1]
    A = a0 * e1 + c0 * e2
    B = (a1 * e1 + c1 * e2) / xs
    N = A[:3] + (column - xc)[:, None] * B[:3]
    D = L * (A[3] + (column - xc) * B[3])
    norm = np.linalg.norm(N, axis=1)
    if not np.all(norm > 0):
        return None
    sign = np.sign(np.einsum("ij,ij->i", N, normal))
    err_n = float(np.max(np.abs(N * (sign / norm)[:, None] - normal)))
    err_d = float(np.max(np.abs(D * sign / norm - d)))
    if not (np.all(sign != 0) and err_n <= tol and err_d <= tol * L):
        return None
    return Pencil(float(xc), A[:3].copy(), B[:3].copy(), float(L * A[3]), float(L * B[3]), (err_n, err_d))


class GridTriangulator:
    """Triangulates whole camera frames of one calibration (see the module docstring).

    camera : :class:`gbscan.camera.Camera`; planes : :class:`PlaneTable`.
    min_angle_deg, max_extrapolate_px : as :func:`triangulate`.

    Construction computes every pixel's ray (distortion inverted per pixel, as
    :meth:`Camera.normalize <gbscan.camera.Camera.normalize>`): ``mx``, ``my`` (H * W,) float64.
    Calling it with a column map (H, W) px (float32 or float64, NaN = none) returns the points
    (H, W, 3) float32 mm, NaN where nothing was reconstructed, written into ``out`` if given.
    """

    def __init__(self, camera, planes: PlaneTable, *, min_angle_deg: float = 2.0,
                 max_extrapolate_px: float | None = None):
        from . import geomkernels as gk

        self.camera = camera
        self.planes = planes
        self.shape = (camera.height, camera.width)
        H, W = self.shape
        self.mx = np.empty(H * W)
        self.my = np.empty(H * W)
        K = camera.K
        gk.undistort_grid(W, H, K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1], camera.dist, self.mx, self.my)
        self.min_angle_deg = float(min_angle_deg)
        if max_extrapolate_px is None:
            max_extrapolate_px = planes.spacing_px
        self.max_extra_px = float(min(max_extrapolate_px, 2 * planes.spacing_px))
        self.lo = float(planes.column[0] - self.max_extra_px)
        self.hi = float(planes.column[-1] + self.max_extra_px)
        self.pencil = planes.pencil()
        if self.pencil is not None:
            # the plane at x is within one plane spacing of the enclosing calibrated planes (two
            # more where extrapolating): angles to them differ by at most that dihedral angle
            cosines = np.clip(np.einsum("ij,ij->i", planes.normal[1:], planes.normal[:-1]), -1.0, 1.0)
            margin = 4.0 * float(np.max(np.arccos(np.abs(cosines))))
            guard = np.radians(self.min_angle_deg) + margin + 1e-9
            self.sin2_guard = float(np.sin(guard) ** 2) if guard < np.pi / 2 else np.inf  # inf: always general
            a, b = self.pencil.a, self.pencil.b
            self._pencil_args = (self.pencil.xc, a[0], a[1], a[2], self.pencil.ad, b[0], b[1], b[2], self.pencil.bd,
                                 float(a @ a), float(a @ b), float(b @ b))
        self._unit_rays = None  # (H * W, 3) float64, made for the first frame off the pencil path
        self.last_path = None  # "pencil", "general" or "linear": how the last frame went (tests, benches)

    def __call__(self, column: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        from . import geomkernels as gk

        column = np.asarray(column)
        H, W = self.shape
        if column.shape != (H, W):
            raise GBError(f"column map is {column.shape[::-1]} but the camera is {W}x{H}")
        if column.dtype not in (np.float32, np.float64):
            column = column.astype(np.float64)
        flat = np.ascontiguousarray(column).reshape(-1)
        if out is None:
            out = np.empty((H, W, 3), np.float32)
        elif out.shape != (H, W, 3) or out.dtype != np.float32 or not out.flags.c_contiguous:
            raise GBError(f"GridTriangulator: out must be a C-contiguous float32 array of shape {(H, W, 3)}")
        o = out.reshape(-1)
        if self.pencil is not None:
            n_guard = gk.pencil_points(self.mx, self.my, flat, *self._pencil_args, self.lo, self.hi,
                                       self.sin2_guard, o)
            if n_guard == 0:
                self.last_path = "pencil"
                return out
        # not a pencil, or a ray near the grazing angle: the reference's compiled kernel on these
        # pixels' unit rays (two planes: its linear depth interpolation)
        if self._unit_rays is None:
            m = np.stack([self.mx, self.my, np.ones_like(self.mx)], axis=1)
            self._unit_rays = m / np.linalg.norm(m, axis=1, keepdims=True)
        triangulate(self._unit_rays, flat, self.planes, min_angle_deg=self.min_angle_deg,
                    max_extrapolate_px=self.max_extra_px, out=o.reshape(-1, 3))
        self.last_path = "linear" if self.planes.n_planes < 3 else "general"
        return out


def point_sigma_mm(triangulator: "GridTriangulator", column: np.ndarray, column_sigma: np.ndarray, *,
                   step_px: float = 0.25, xyz: np.ndarray | None = None) -> np.ndarray:
    """Predicted error (one standard deviation, mm) of each pixel's point along its camera ray,
    from its projector column's predicted error: the first-order propagation
    ``|dp/dx| * column_sigma``.

    triangulator : the :class:`GridTriangulator` the points come from.
    column, column_sigma : (H, W) projector column and its predicted error (px; NaN = none), e.g.
        :class:`gbscan.decode.StripeMap`'s ``column`` and ``column_sigma``.
    step_px : half-step of the central difference ``(p(x + h) - p(x - h)) / 2h`` (along a ray
        the depth is a smooth projective function of the column, so 0.25 px is exact to far
        below the prediction's own accuracy); one-sided against ``xyz`` (the points at ``x``,
        triangulated if not given) where one side has no point (the calibrated range's ends).

    Returns (H, W) float32 mm, NaN where the column, its error or both sides are missing.  Costs
    two triangulations of the frame and one pass (1.8 ms at 640x480).  What it does not contain: the
    calibration's own error (a few hundredths of a mm in scale at 650 mm, docs/figures.md) and the chance
    that the pixel sits on a wrong stripe (the indexing's job; then the error is a whole stripe).
    """
    from . import geomkernels as gk

    column = np.asarray(column)
    sig = np.asarray(column_sigma)
    H, W = triangulator.shape
    if column.shape != (H, W) or sig.shape != (H, W):
        raise GBError(f"point_sigma_mm: column {column.shape} and column_sigma {sig.shape} must both be "
                      f"the camera's {(H, W)}")
    if not step_px > 0:
        raise GBError(f"point_sigma_mm: step_px must be > 0, got {step_px}")
    sig = np.ascontiguousarray(sig, dtype=np.float32)
    c = np.where(np.isfinite(sig), column.astype(np.float64), np.nan)
    h = float(step_px)
    p_hi = triangulator(c + h)
    p_lo = triangulator(c - h)
    if xyz is None or np.shape(xyz) != (H, W, 3):
        xyz = triangulator(c)
    out = np.empty((H, W), np.float32)
    gk.ray_sigma(p_hi.reshape(-1, 3), p_lo.reshape(-1, 3), np.ascontiguousarray(xyz, dtype=np.float32).reshape(-1, 3),
                 sig.reshape(-1), h, out.reshape(-1))
    return out


def triangulate(rays: np.ndarray, column: np.ndarray, planes: PlaneTable, *,
                min_angle_deg: float = 2.0, max_extrapolate_px: float | None = None,
                out: np.ndarray | None = None, compiled: bool = True) -> np.ndarray:
    """Points where each pixel's ray meets the light plane of its projector column.

    rays : (H, W, 3) or (N, 3) float unit ray directions (camera frame), e.g. ``Camera.pixel_rays()``.
    column : (H, W) or (N,) float continuous projector column (px); NaN = no measurement.
    planes : :class:`PlaneTable`.
    min_angle_deg : rays closer than this to a light plane give NaN (depth ill-conditioned).
    max_extrapolate_px : how far beyond the first/last calibrated plane a column may lie
        (default: one plane spacing, at most two); further gives NaN.
    out : optional C-contiguous float64 or float32 array shaped like ``rays`` to write into
        (``gbscan.scan.Scanner`` writes float32 maps directly).
    compiled : use the numba kernel (default; one pass, no temporaries) rather than the numpy
        reference :func:`ray_depths` (same arithmetic up to rounding).  With exactly two planes
        the numpy path (linear depth interpolation) is used.

    Returns ``out`` (default float64) with the points (mm), NaN where nothing was reconstructed.
    """
    rays = np.asarray(rays)
    column = np.asarray(column)
    if rays.shape[-1:] != (3,) or rays.shape[:-1] != column.shape:
        raise GBError(f"triangulate: rays {rays.shape} and column {column.shape} must be (..., 3) and (...)")
    if out is None:
        out = np.empty(rays.shape, dtype=np.float64)
    elif out.shape != rays.shape or out.dtype not in (np.float32, np.float64) or not out.flags.c_contiguous:
        raise GBError(f"triangulate: out must be a C-contiguous float array of shape {rays.shape}")
    if max_extrapolate_px is None:
        max_extrapolate_px = planes.spacing_px
    if compiled and planes.n_planes >= 3:
        # float32 columns (the decoder's) are read as they are: no float64 copy of the frame
        cdt = column.dtype if column.dtype in (np.float32, np.float64) else np.float64
        _triangulate_kernel(np.ascontiguousarray(rays.reshape(-1, 3), dtype=np.float64),
                            np.ascontiguousarray(column.reshape(-1), dtype=cdt),
                            planes.column, planes.normal, planes.d, planes.lut, planes.lut0,
                            float(np.sin(np.radians(min_angle_deg))),
                            float(min(max_extrapolate_px, 2 * planes.spacing_px)), out.reshape(-1, 3))
        return out
    out.fill(np.nan)
    flat_c = column.reshape(-1)
    sel = np.flatnonzero(np.isfinite(flat_c))
    if sel.size == 0:
        return out
    r = rays.reshape(-1, 3)[sel].astype(np.float64, copy=False)
    s = ray_depths(r, flat_c[sel].astype(np.float64, copy=False), planes,
                   min_angle_deg=min_angle_deg, max_extrapolate_px=max_extrapolate_px)
    out.reshape(-1, 3)[sel] = r * s[:, None]
    return out


def ray_depths(r: np.ndarray, x: np.ndarray, planes: PlaneTable, *, min_angle_deg: float = 2.0,
               max_extrapolate_px: float | None = None) -> np.ndarray:
    """Distance ``s`` (mm) along unit rays ``r`` (N, 3) to the plane of column ``x`` (N,) px.

    The point is ``s * r``.  NaN where the column is outside the calibrated range, the ray is
    within ``min_angle_deg`` of a light plane, or the point would lie behind the camera.
    See the module docstring for the cross-ratio interpolation (exact for a pinhole projector).
    """
    col, nor, dd = planes.column, planes.normal, planes.d
    P = col.size
    if max_extrapolate_px is None:
        max_extrapolate_px = planes.spacing_px
    max_extrapolate_px = min(max_extrapolate_px, 2 * planes.spacing_px)
    i = np.searchsorted(col, x, side="right") - 1
    np.clip(i, 0, P - 2, out=i)
    j = np.where(i + 2 < P, i + 2, i - 1) if P >= 3 else None

    min_dot = np.sin(np.radians(min_angle_deg))

    def depth(k):
        nr = np.einsum("ij,ij->i", nor[k], r)
        with np.errstate(divide="ignore", invalid="ignore"):
            s_k = dd[k] / nr
        return s_k, np.abs(nr) >= min_dot

    s0, ok0 = depth(i)
    s1, ok1 = depth(i + 1)
    x0, x1 = col[i], col[i + 1]
    ok = ok0 & ok1 & (x >= col[0] - max_extrapolate_px) & (x <= col[-1] + max_extrapolate_px)
    with np.errstate(divide="ignore", invalid="ignore"):
        lin = s0 + (x - x0) / (x1 - x0) * (s1 - s0)
        if j is None:
            s = lin
        else:
            s2, _ = depth(j)
            x2 = col[j]
            a = (x2 - x0) * (x - x1)
            b = (x2 - x1) * (x - x0)
            num = b * s1 * (s2 - s0) - a * s0 * (s2 - s1)
            den = b * (s2 - s0) - a * (s2 - s1)
            s = num / den
    s = np.where(ok & (s > 0), s, np.nan)
    return s


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _triangulate_kernel(rays, column, col, nor, dd, lut, lut0, min_dot, max_extra, out):  # pragma: no cover
    """Per-pixel version of :func:`ray_depths` (see there); writes points or NaN into ``out``.
    ``column`` float32 or float64 (promoted per pixel)."""
    P = col.size
    lo_lim = col[0] - max_extra
    hi_lim = col[P - 1] + max_extra
    n_lut = lut.size
    for p in range(column.size):
        x = np.float64(column[p])
        if not (x >= lo_lim and x <= hi_lim):  # also rejects NaN
            out[p, 0] = np.nan
            out[p, 1] = np.nan
            out[p, 2] = np.nan
            continue
        # i: last plane with col[i] <= x, clipped to [0, P-2]: table lookup, then step forward
        k = int(x - lut0)
        i = lut[min(max(k, 0), n_lut - 1)]
        while i < P - 2 and col[i + 1] <= x:
            i += 1
        rx, ry, rz = rays[p, 0], rays[p, 1], rays[p, 2]
        j = i + 2 if i + 2 < P else i - 1
        N0 = nor[i, 0] * rx + nor[i, 1] * ry + nor[i, 2] * rz
        N1 = nor[i + 1, 0] * rx + nor[i + 1, 1] * ry + nor[i + 1, 2] * rz
        N2 = nor[j, 0] * rx + nor[j, 1] * ry + nor[j, 2] * rz
        D0, D1, D2 = dd[i], dd[i + 1], dd[j]
        x0, x1, x2 = col[i], col[i + 1], col[j]
        # Cross ratio with s_k = D_k / N_k, multiplied through by N0 N1 N2 (one division).
        a = (x2 - x0) * (x - x1)
        b = (x2 - x1) * (x - x0)
        e20 = D2 * N0 - D0 * N2
        e21 = D2 * N1 - D1 * N2
        s = (b * D1 * e20 - a * D0 * e21) / (b * N1 * e20 - a * N0 * e21)
        ok = (abs(N0) >= min_dot) & (abs(N1) >= min_dot) & (s > 0.0) & (s < np.inf)
        s = s if ok else np.nan
        out[p, 0] = s * rx
        out[p, 1] = s * ry
        out[p, 2] = s * rz
