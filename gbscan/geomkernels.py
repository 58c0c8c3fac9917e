"""Compiled (numba) kernels of the geometry stages: pixel rays, triangulation, grid mesh, file
packing.  Only :mod:`gbscan.triangulate`, :mod:`gbscan.scan` and :mod:`gbscan.mesh` import this
module (lazily), so ``gbscan --help`` never loads numba.

Conventions as everywhere (camera frame, mm, px, pixel centres at integers).  Kernels take flat,
C-contiguous arrays; the wrappers in the modules named above check shapes and dtypes.  No
``fastmath``: the results are the IEEE results of the arithmetic written here, so the compiled
paths can be compared with their numpy references to the last bit where the arithmetic is the
same.  Single-threaded (the machine's cores belong to the decoder and to other processes).
"""
from __future__ import annotations

import numpy as np
from numba import njit


# -- pixel rays ----------------------------------------------------------------------------------
@njit(cache=True, nogil=True, inline="always")
def _distort(x, y, k1, k2, p1, p2, k3):
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


@njit(cache=True, nogil=True, inline="always")
def _newton_terms(tx, ty, x, y, k1, k2, p1, p2, k3):
    """Residual ``(fx, fy)`` of the distortion model at ``(x, y)`` against the target ``(tx, ty)``
    and its Jacobian ``[[a, b], [b, d]]`` (the algebra of :func:`gbscan.camera.undistort_normalized`)."""
    xx = x * x
    yy = y * y
    xy = x * y
    r2 = xx + yy
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dr = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    fx = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * xx) - tx
    fy = y * radial + p1 * (r2 + 2.0 * yy) + 2.0 * p2 * xy - ty
    a = radial + 2.0 * xx * dr + 2.0 * p1 * y + 6.0 * p2 * x
    b = 2.0 * xy * dr + 2.0 * p1 * x + 2.0 * p2 * y
    d = radial + 2.0 * yy * dr + 6.0 * p1 * y + 2.0 * p2 * x
    return fx, fy, a, b, d


@njit(cache=True, nogil=True, inline="always")
def _newton(tx, ty, x, y, k1, k2, p1, p2, k3, iterations, tol):
    """Newton steps of :func:`gbscan.camera.undistort_normalized` for one point (same algebra);
    stops after the step whose starting residual was below ``tol``."""
    for _ in range(iterations):
        fx, fy, a, b, d = _newton_terms(tx, ty, x, y, k1, k2, p1, p2, k3)
        det = a * d - b * b
        x = x - (d * fx - b * fy) / det
        y = y - (a * fy - b * fx) / det
        if max(abs(fx), abs(fy)) < tol:
            break
    return x, y


@njit(cache=True, nogil=True, error_model="numpy")
def undistort_grid(width, height, fx, fy, cx, cy, skew, dist, mx, my):  # pragma: no cover
    """Undistorted normalised coordinates of every pixel centre into ``mx``, ``my`` (H * W,)
    float64 (raster order): the ray of pixel ``(u, v)`` is ``(mx, my, 1)``.

    :meth:`gbscan.camera.Camera.normalize` per pixel: Newton from the distorted coordinates.
    Four steps for every pixel first (no branches: vectorised; three reach 1e-16 on the paper's
    lens), then every pixel whose residual
    is not below 1e-13 is redone as ``normalize`` does (Newton to 1e-13, at most 12 steps; where
    that does not reproduce the pixel to 1e-10, 20 fixed-point steps and Newton again).
    Returns how many pixels were redone.
    """
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    for v in range(height):
        yd = (v - cy) / fy
        o = v * width
        for u in range(width):
            xd = (u - cx - skew * yd) / fx
            x = xd
            y = yd
            for _ in range(4):
                x, y = _newton_step(xd, yd, x, y, k1, k2, p1, p2, k3)
            mx[o + u] = x
            my[o + u] = y
    n_slow = 0
    for v in range(height):  # branch-free count first: the redo loop below is scalar
        yd = (v - cy) / fy
        o = v * width
        for u in range(width):
            xd = (u - cx - skew * yd) / fx
            ex, ey = _distort(mx[o + u], my[o + u], k1, k2, p1, p2, k3)
            n_slow += np.int64(not ((abs(ex - xd) < 1e-13) & (abs(ey - yd) < 1e-13)))
    if n_slow == 0:
        return 0
    for v in range(height):
        yd = (v - cy) / fy
        o = v * width
        for u in range(width):
            xd = (u - cx - skew * yd) / fx
            ex, ey = _distort(mx[o + u], my[o + u], k1, k2, p1, p2, k3)
            if abs(ex - xd) < 1e-13 and abs(ey - yd) < 1e-13:
                continue
            x, y = _newton(xd, yd, xd, yd, k1, k2, p1, p2, k3, 12, 1e-13)
            ex, ey = _distort(x, y, k1, k2, p1, p2, k3)
            if not (abs(ex - xd) < 1e-10 and abs(ey - yd) < 1e-10):
                x, y = xd, yd
                for _ in range(20):
                    ex, ey = _distort(x, y, k1, k2, p1, p2, k3)
                    x = x + (xd - ex)
                    y = y + (yd - ey)
                x, y = _newton(xd, yd, x, y, k1, k2, p1, p2, k3, 12, 1e-13)
            mx[o + u] = x
            my[o + u] = y
    return n_slow


@njit(cache=True, nogil=True, inline="always")
def _newton_step(tx, ty, x, y, k1, k2, p1, p2, k3):
    fx, fy, a, b, d = _newton_terms(tx, ty, x, y, k1, k2, p1, p2, k3)
    inv = 1.0 / (a * d - b * b)
    return x - (d * fx - b * fy) * inv, y - (a * fy - b * fx) * inv


@njit(cache=True, nogil=True, inline="always")
def _triangle_cross(v, i0, i1, i2):
    """``(v[i1] - v[i0]) x (v[i2] - v[i0])`` of vertices ``v`` (V, 3): twice the area-weighted
    normal of the triangle (right-hand rule)."""
    ex = v[i1, 0] - v[i0, 0]
    ey = v[i1, 1] - v[i0, 1]
    ez = v[i1, 2] - v[i0, 2]
    fx = v[i2, 0] - v[i0, 0]
    fy = v[i2, 1] - v[i0, 1]
    fz = v[i2, 2] - v[i0, 2]
    return ey * fz - ez * fy, ez * fx - ex * fz, ex * fy - ey * fx


# -- triangulation -------------------------------------------------------------------------------
@njit(cache=True, nogil=True, error_model="numpy")
def pencil_points(mx, my, column, xc, ax, ay, az, ad, bx, by, bz, bd, naa, nab, nbb, lo, hi, sin2_guard,
                  out):  # pragma: no cover
    """Points of pixels whose light planes form a pencil: plane of column ``x`` is
    ``N(x) . p = D(x)`` with ``N = A + (x - xc) B``, ``D = ad + (x - xc) bd`` (unnormalised).

    mx, my : (N,) float64 ray ``(mx, my, 1)`` per pixel.  column : (N,) float32/64 px, NaN = none.
    lo, hi : accepted column range.  out : (3 N,) float32, written for every pixel (NaN = none).
    The depth is ``z = D(x) / (N(x) . m)`` and the point ``z m``: exact for a pinhole projector.
    A pixel whose ray is within the guard angle (``sin2_guard`` = its squared sine) of the plane
    at ``x`` is counted, not judged: the caller re-triangulates such frames with the general
    kernel, whose angle test is on the calibrated planes.  Branch-free so that LLVM vectorises it.
    Returns the number of such pixels.
    """
    n_guard = 0
    for p in range(column.size):
        x = np.float64(column[p])
        ok = (x >= lo) & (x <= hi)  # False for NaN
        t = x - xc
        u = mx[p]
        v = my[p]
        den = (ax + t * bx) * u + (ay + t * by) * v + (az + t * bz)
        z = (ad + t * bd) / den
        nn = naa + t * (2.0 * nab + t * nbb)
        guard = ok & (den * den < sin2_guard * nn * (u * u + v * v + 1.0))
        n_guard += np.int64(guard)
        ok = ok & (z > 0.0) & (z < np.inf)
        z = z if ok else np.nan
        out[3 * p] = np.float32(z * u)
        out[3 * p + 1] = np.float32(z * v)
        out[3 * p + 2] = np.float32(z)
    return n_guard


@njit(cache=True, nogil=True)
def grid_mesh_arrays(xyz, valid, use_valid, max_jump, normals, use_normals):  # pragma: no cover
    """The organised-grid mesh of :func:`gbscan.mesh.grid_mesh` (see there for the rules).

    xyz : (H, W, 3) float32/64.  valid : (H, W) bool (read when ``use_valid``).  max_jump :
    float32.  normals : (H, W, 3) (read when ``use_normals``).
    Returns vertices (V, 3) float64, triangles (T, 3) int64, pixel (V, 2) int32, vertex normals
    (V, 3) float64 (the given normals of the vertices' pixels) and (V,) bool: that normal is
    finite and non-zero.
    """
    H, W = xyz.shape[0], xyz.shape[1]
    z = np.empty((H, W), np.float32)
    for v in range(H):
        for u in range(W):
            a = xyz[v, u, 0]
            b = xyz[v, u, 1]
            c = xyz[v, u, 2]
            zz = np.float32((a + b + c) * 0 + c)  # NaN unless all three are finite
            if use_valid and not valid[v, u]:
                zz = np.float32(np.nan)
            z[v, u] = zz
    quad = np.zeros((max(H - 1, 0), max(W - 1, 0)), np.bool_)
    index = np.full((H, W), -1, np.int64)
    n_quads = 0
    for v in range(H - 1):
        for u in range(W - 1):
            a = z[v, u]
            b = z[v + 1, u]
            c = z[v, u + 1]
            d = z[v + 1, u + 1]
            zmin = min(min(a, b), min(c, d))
            zmax = max(max(a, b), max(c, d))
            if (a == a) and (b == b) and (c == c) and (d == d) and zmax - zmin <= max_jump * zmin:
                quad[v, u] = True
                n_quads += 1
                index[v, u] = 0
                index[v + 1, u] = 0
                index[v, u + 1] = 0
                index[v + 1, u + 1] = 0
    n_v = 0
    for v in range(H):
        for u in range(W):
            if index[v, u] >= 0:
                index[v, u] = n_v
                n_v += 1
    verts = np.empty((n_v, 3), np.float64)
    pixel = np.empty((n_v, 2), np.int32)
    vn = np.empty((n_v, 3), np.float64)
    has_normal = np.zeros(n_v, np.bool_)
    k = 0
    for v in range(H):
        for u in range(W):
            if index[v, u] >= 0:
                for c in range(3):
                    verts[k, c] = np.float64(xyz[v, u, c])
                pixel[k, 0] = v
                pixel[k, 1] = u
                if use_normals:
                    s = 0.0
                    for c in range(3):
                        nc = np.float64(normals[v, u, c])
                        vn[k, c] = nc
                        s += abs(nc)
                    has_normal[k] = s > 0 and s < np.inf  # False for NaN too
                k += 1
    tris = np.empty((2 * n_quads, 3), np.int64)
    t = 0
    for v in range(H - 1):
        for u in range(W - 1):
            if quad[v, u]:
                ia = index[v, u]
                ib = index[v + 1, u]
                ic = index[v, u + 1]
                id_ = index[v + 1, u + 1]
                tris[t, 0] = ia
                tris[t, 1] = ib
                tris[t, 2] = ic
                tris[t + 1, 0] = ic
                tris[t + 1, 1] = ib
                tris[t + 1, 2] = id_
                t += 2
    return verts, tris, pixel, vn, has_normal


@njit(cache=True, nogil=True)
def area_weighted_normals(v, tris, want, out):  # pragma: no cover
    """Area-weighted unit vertex normals of the vertices ``want`` (V,) bool into their rows of
    ``out`` (V, 3) float64 (zero for vertices in no triangle; other rows untouched): bit for bit
    :func:`gbscan.mesh.vertex_normals` (the same float64 cross products, summed per corner in
    triangle order as ``np.bincount`` does, then the corner sums added)."""
    V = v.shape[0]
    acc = np.empty((V, 3), np.float64)
    for i in range(V):
        if want[i]:
            for c in range(3):
                out[i, c] = 0.0
    for corner in range(3):
        acc[:] = 0.0
        for t in range(tris.shape[0]):
            k = tris[t, corner]
            if not want[k]:
                continue
            nx, ny, nz = _triangle_cross(v, tris[t, 0], tris[t, 1], tris[t, 2])
            acc[k, 0] += nx
            acc[k, 1] += ny
            acc[k, 2] += nz
        for i in range(V):
            if want[i]:
                for c in range(3):
                    out[i, c] = out[i, c] + acc[i, c]
    for i in range(V):
        if not want[i]:
            continue
        x, y, z = out[i, 0], out[i, 1], out[i, 2]
        norm = np.sqrt(x * x + y * y + z * z)
        if norm > 0:
            out[i, 0] = x / norm
            out[i, 1] = y / norm
            out[i, 2] = z / norm
        else:
            out[i, 0] = 0.0
            out[i, 1] = 0.0
            out[i, 2] = 0.0


# -- file packing --------------------------------------------------------------------------------
@njit(cache=True, nogil=True)
def pack_ply_faces(tris, buf):  # pragma: no cover
    """PLY face records ``uchar 3, int32 a b c`` (little endian, 13 bytes each) into ``buf``."""
    for t in range(tris.shape[0]):
        o = 13 * t
        buf[o] = 3
        for c in range(3):
            val = np.uint32(np.int32(tris[t, c]))
            q = o + 1 + 4 * c
            buf[q] = np.uint8(val & 0xFF)
            buf[q + 1] = np.uint8((val >> 8) & 0xFF)
            buf[q + 2] = np.uint8((val >> 16) & 0xFF)
            buf[q + 3] = np.uint8((val >> 24) & 0xFF)


@njit(cache=True, nogil=True)
def pack_cloud(xyz, normals, confidence, reason, with_normals, with_confidence, with_pixel, out,
               out_i32):  # pragma: no cover
    """The kept pixels (``reason == 0``) of an organised scan as PLY vertex records, raster order.

    out : (N, K) float32, the 4-byte fields x y z [nx ny nz] [confidence] [row col]; out_i32 :
    an int32 view of the same memory, through which row/col are written.  Normals as
    ``np.nan_to_num``.  Returns the number of records written.
    """
    H, W = reason.shape
    k = 0
    big = np.float32(3.4028234663852886e38)
    for v in range(H):
        for u in range(W):
            if reason[v, u] != 0:
                continue
            c = 0
            for j in range(3):
                out[k, c] = xyz[v, u, j]
                c += 1
            if with_normals:
                for j in range(3):
                    n = normals[v, u, j]
                    if n != n:
                        n = np.float32(0.0)
                    elif n == np.inf:
                        n = big
                    elif n == -np.inf:
                        n = -big
                    out[k, c] = n
                    c += 1
            if with_confidence:
                out[k, c] = confidence[v, u]
                c += 1
            if with_pixel:
                out_i32[k, c] = v
                out_i32[k, c + 1] = u
            k += 1
    return k


@njit(cache=True, nogil=True)
def stl_records(v, tris, buf):  # pragma: no cover
    """Binary STL triangle records (50 bytes each) into ``buf`` (T * 50,) uint8: the unit normal
    (right-hand rule, zero when degenerate; float64 arithmetic as
    :func:`gbscan.mesh.triangle_normals`), the three corners (float32, little endian on the
    little-endian machines numba runs on) and a zero attribute."""
    rec = np.empty(12, np.float32)
    rb = rec.view(np.uint8)
    for t in range(tris.shape[0]):
        i0, i1, i2 = tris[t, 0], tris[t, 1], tris[t, 2]
        nx, ny, nz = _triangle_cross(v, i0, i1, i2)
        norm = np.sqrt(nx * nx + ny * ny + nz * nz)
        if norm > 0:
            nx, ny, nz = nx / norm, ny / norm, nz / norm
        else:
            nx, ny, nz = 0.0, 0.0, 0.0
        rec[0] = nx
        rec[1] = ny
        rec[2] = nz
        for c in range(3):
            i = tris[t, c]
            for j in range(3):
                rec[3 + 3 * c + j] = v[i, j]
        o = 50 * t
        for b in range(48):
            buf[o + b] = rb[b]
        buf[o + 48] = 0
        buf[o + 49] = 0


# -- text (OBJ) ----------------------------------------------------------------------------------
@njit(cache=True, nogil=True)
def fixed_point_digits(x, decimals, k, ambiguous):  # pragma: no cover
    """Round ``|x| * 10**decimals`` half to even into ``k`` (int64) as ``'%.Nf'`` does, for
    finite ``|x| < 1e15``.  Where the float64 product cannot decide the rounding (within two
    ulps of a half), ``ambiguous`` is set and the caller asks Python's exact formatting.
    Returns how many entries are ambiguous."""
    scale = 10.0 ** decimals
    n = 0
    for p in range(x.size):
        t = abs(x[p]) * scale
        f = np.floor(t)
        frac = t - f
        amb = abs(frac - 0.5) <= 4.5e-16 * t + 1e-300
        r = np.rint(t)
        k[p] = np.int64(r)
        ambiguous[p] = amb
        n += np.int64(amb)
    return n


@njit(cache=True, nogil=True, inline="always")
def _put_uint(buf, o, val):
    """Decimal digits of ``val`` >= 0 at ``buf[o:]``; returns the new offset."""
    if val == 0:
        buf[o] = 48
        return o + 1
    n = 0
    t = val
    while t > 0:
        t //= 10
        n += 1
    for i in range(n - 1, -1, -1):
        buf[o + i] = 48 + val % 10
        val //= 10
    return o + n


@njit(cache=True, nogil=True)
def format_rows(prefix, k, negative, decimals, buf):  # pragma: no cover
    """ASCII lines ``prefix a b c\\n`` of fixed-point numbers into ``buf`` (uint8, large enough).

    k : (R * 3,) int64 ``round(|value| * 10**decimals)``; negative : (R * 3,) bool sign bits.
    Returns the number of bytes written."""
    o = 0
    pw = 1
    for _ in range(decimals):
        pw *= 10
    n_rows = k.size // 3
    for r in range(n_rows):
        for c in range(prefix.size):
            buf[o] = prefix[c]
            o += 1
        for c in range(3):
            q = 3 * r + c
            buf[o] = 32
            o += 1
            if negative[q]:
                buf[o] = 45
                o += 1
            val = k[q]
            o = _put_uint(buf, o, val // pw)
            buf[o] = 46
            o += 1
            frac = val % pw
            for i in range(decimals - 1, -1, -1):
                buf[o + i] = 48 + frac % 10
                frac //= 10
            o += decimals
        buf[o] = 10
        o += 1
    return o


@njit(cache=True, nogil=True)
def format_obj_faces(tris, buf):  # pragma: no cover
    """OBJ face lines ``f a//a b//b c//c`` (1-based) into ``buf``; returns the bytes written."""
    o = 0
    for t in range(tris.shape[0]):
        buf[o] = 102
        o += 1
        for c in range(3):
            buf[o] = 32
            o += 1
            i = tris[t, c] + 1
            o = _put_uint(buf, o, i)
            buf[o] = 47
            buf[o + 1] = 47
            o += 2
            o = _put_uint(buf, o, i)
        buf[o] = 10
        o += 1
    return o


@njit(cache=True, nogil=True, error_model="numpy")
def ray_sigma(p_hi, p_lo, p0, sigma, h, out):  # pragma: no cover
    """:func:`gbscan.triangulate.point_sigma_mm`'s propagation in one pass: ``out = sigma *
    |p_hi - p_lo| / 2h`` (the central difference of the points at columns ``x +- h``), one-sided
    against ``p0`` (the points at ``x``) where ``p_hi`` or ``p_lo`` has none, NaN where
    ``sigma`` is NaN or no difference exists.  p_hi, p_lo, p0 : (N, 3) float32; sigma, out :
    (N,) float32."""
    n = sigma.shape[0]
    inv2h = 1.0 / (2.0 * h)
    invh = 1.0 / h
    for i in range(n):
        s = sigma[i]
        if not s == s:
            out[i] = np.nan
            continue
        hi_ok = p_hi[i, 2] == p_hi[i, 2]
        lo_ok = p_lo[i, 2] == p_lo[i, 2]
        if hi_ok and lo_ok:
            a, b, scale = p_hi[i], p_lo[i], inv2h
        elif hi_ok:
            a, b, scale = p_hi[i], p0[i], invh
        elif lo_ok:
            a, b, scale = p0[i], p_lo[i], invh
        else:
            out[i] = np.nan
            continue
        dx = np.float64(a[0]) - np.float64(b[0])
        dy = np.float64(a[1]) - np.float64(b[1])
        dz = np.float64(a[2]) - np.float64(b[2])
        out[i] = np.float32(np.sqrt(dx * dx + dy * dy + dz * dz) * scale * abs(s))
