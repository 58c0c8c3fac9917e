"""Frames whose stripes are wide in the camera (``DecodeParams.resample``): stripe width from
colour runs, linear-light shrinking, and expanding a coarse decode back to every pixel.

Part of :mod:`gbscan.kernels` (its docstring has the conventions)."""
from __future__ import annotations

import numpy as np
from numba import njit


# -- resampling: frames whose stripes are wide in the camera ----------------------------------------
@njit(cache=True, nogil=True, error_model="numpy")
def stripe_run_px(img, lut, row_step, level, floor, max_run, quantile=0.5):
    """Camera pixels per stripe of an RGB uint8 frame, from its colour runs alone (no decoding).

    Every ``row_step``-th row is walked with the linear green and blue (``lut``) scaled to equal
    means over the bright pixels (sum above ``floor``); a pixel is green where ``(g - b) / (g + b)``
    exceeds ``level``, blue below ``-level``, and keeps the colour before it in between (cyan
    markers, the mixed pixels of a boundary), so each run spans one stripe (three around a marker:
    ``G C G``) and its length is counted from one colour change to the next; a pixel darker than
    ``floor`` ends the run uncounted.  Returns ``(run length px, runs counted)``: the ``quantile``
    of the runs of at most ``max_run`` px, each length spread over its pixel (grouped data), 0.0
    when none.
    """
    H, W = img.shape[0], img.shape[1]
    # both passes walk a row from its first to its last pixel that may be lit (lo, hi): a pixel
    # whose green and blue bytes are below ``c`` is dark for sure (any two LUT values below c sum
    # to at most floor), and a dark pixel ends a run anyway
    c = _dark_below(lut, floor)
    flat = img.reshape(H, 3 * W)
    nr = (H + row_step - 1) // row_step
    lo = np.empty(nr, np.int64)
    hi = np.empty(nr, np.int64)
    sg = 0.0
    sb = 0.0
    n = 0
    for i in range(nr):
        px = flat[i * row_step]
        a = 0
        while a < W and max(px[3 * a + 1], px[3 * a + 2]) < c:
            a += 1
        e = W
        while e > a and max(px[3 * e - 2], px[3 * e - 1]) < c:
            e -= 1
        lo[i] = a
        hi[i] = e
        for u in range(a, e):
            g = lut[px[3 * u + 1]]
            b = lut[px[3 * u + 2]]
            if g + b > floor:
                sg += g
                sb += b
                n += 1
    if n == 0 or sg <= 0.0 or sb <= 0.0:
        return 0.0, 0
    kg = n / sg
    kb = n / sb
    hist = np.zeros(max_run + 1, np.int64)
    total = 0
    for i in range(nr):
        px = flat[i * row_step]
        state = 0
        start = -1
        for u in range(lo[i], hi[i]):
            g = lut[px[3 * u + 1]]
            b = lut[px[3 * u + 2]]
            if g + b <= floor:
                state = 0
                start = -1
                continue
            g *= kg
            b *= kb
            d = g - b
            cur = state
            if d > level * (g + b):
                cur = 1
            elif d < -level * (g + b):
                cur = -1
            if cur != state:
                if state != 0 and start >= 0:
                    r = u - start
                    if r <= max_run:
                        hist[r] += 1
                        total += 1
                start = u if state != 0 else -1
                state = cur
    if total == 0:
        return 0.0, 0
    # the quantile of the lengths taken as spread evenly over [r - 1/2, r + 1/2) (grouped data)
    half = quantile * total
    acc = 0
    for r in range(max_run + 1):
        if acc + hist[r] >= half:
            return r - 0.5 + (half - acc) / hist[r], total
        acc += hist[r]
    return float(max_run), total


@njit(cache=True, nogil=True, error_model="numpy")
def _dark_below(lut, floor):
    """The count ``c`` of leading bytes whose LUT values, any two summed (float32), are at most
    ``floor``: twice the largest of lut[0..c-1] is (a float32 sum is monotone in each term)."""
    m = lut[0]
    c = 0
    while c < lut.size:
        m = max(m, lut[c])
        if not m + m <= floor:
            break
        c += 1
    return c


@njit(cache=True, nogil=True, error_model="numpy")
def linear_rgb(img, lut, first):
    """(H, W, 3 - first) float32: channels ``first`` .. 2 of an RGB uint8 frame through ``lut``
    (linear light; ``first`` 1: green and blue only, all the decoder reads)."""
    H, W = img.shape[0], img.shape[1]
    n = 3 - first
    out = np.empty((H, W, n), np.float32)
    for v in range(H):
        px = img[v]
        o = out[v]
        if n == 2:   # the channels spelt out (against a loop over them: 2.2 -> 0.9 ms at 1280x1024)
            for u in range(W):
                o[u, 0] = lut[px[u, 1]]
                o[u, 1] = lut[px[u, 2]]
        else:
            for u in range(W):
                for c in range(n):
                    o[u, c] = lut[px[u, first + c]]
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _encoded(x, enc, scale, top):
    # the encoded value of linear x through the table of encode_rgb (scale = (enc.size - 1) / 255)
    return enc[min(max(int(x * scale + 0.5), 0), top)]


@njit(cache=True, nogil=True, error_model="numpy")
def shrink2_rgb(img, lut, enc, first):
    """:func:`linear_rgb`, ``cv2.resize(..., INTER_AREA)`` to exactly half the size and
    :func:`encode_rgb` in one pass: (H/2, W/2, 3) uint8 (H, W even; channels before ``first`` 0).
    The mean of a 2x2 block is OpenCV's, value for value: ``(((a + b) + c) + d) * 0.25`` in
    float32, ``a b`` the block's upper pixels (its fast path for an exact half; checked against
    cv2 by the tests).  2.9 -> 1.0 ms at 1280x960 against the three steps."""
    H, W = img.shape[0], img.shape[1]
    h = H // 2
    w = W // 2
    out = np.zeros((h, w, 3), np.uint8)
    scale = (enc.size - 1) / 255.0
    top = enc.size - 1
    q = np.float32(0.25)
    for i in range(h):
        p0 = img[2 * i]
        p1 = img[2 * i + 1]
        o = out[i]
        for c in range(first, 3):   # a channel at a time (the loop over j then has no inner loop)
            for j in range(w):
                m = (((lut[p0[2 * j, c]] + lut[p0[2 * j + 1, c]]) + lut[p1[2 * j, c]]) + lut[p1[2 * j + 1, c]]) * q
                o[j, c] = _encoded(m, enc, scale, top)
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def encode_rgb(lin, enc):
    """(H, W, 3) uint8 RGB of (H, W, n) linear values in [0, 255] (the last n channels; the others
    0) through ``enc``, the table of the encoded value of linear ``255 i / (enc.size - 1)``."""
    H, W, n = lin.shape
    out = np.zeros((H, W, 3), np.uint8)
    scale = (enc.size - 1) / 255.0
    top = enc.size - 1
    for v in range(H):
        li = lin[v]
        o = out[v]
        if n == 2:   # green and blue spelt out (as linear_rgb)
            for u in range(W):
                o[u, 1] = _encoded(li[u, 0], enc, scale, top)
                o[u, 2] = _encoded(li[u, 1], enc, scale, top)
        else:
            for u in range(W):
                for c in range(n):
                    o[u, 3 - n + c] = _encoded(li[u, c], enc, scale, top)
    return out


@njit(cache=True, nogil=True)
def _pairs(c0, c1, r0, r1, limit, F, D):
    # the pairs (c0[j], c1[j]) (neighbours along a row or across rows): F[j] 1 where both are on
    # one surface (same region, columns within limit; NaN: 0), D[j] = c1[j] - c0[j]
    for j in range(c0.size):
        D[j] = c1[j] - c0[j]
    for j in range(c0.size):
        F[j] = np.uint8((r0[j] == r1[j]) & (abs(c1[j] - c0[j]) < limit))


@njit(cache=True, nogil=True)
def _gx_row(P, D, out):
    # slope along the row: central where both pairs are on the surface, else one-sided, else 0
    z = np.float32(0.0)
    for j in range(out.size):
        r = P[j + 1]
        l = P[j]
        dr = D[j + 1]
        dl = D[j]
        both = np.float32(0.5 * (dr + dl))
        one = dr if r != 0 else (dl if l != 0 else z)
        out[j] = both if (r & l) != 0 else one


@njit(cache=True, nogil=True)
def _nb_row(P, Fu, Fd, out):
    # the neighbour bits: 1 right, 2 left, 4 below, 8 above
    for j in range(out.size):
        out[j] = P[j + 1] | (P[j] << np.uint8(1)) | (Fd[j] << np.uint8(2)) | (Fu[j] << np.uint8(3))


@njit(cache=True, nogil=True)
def _gy_row(Fu, Du, Fd, Dd, out):
    # slope across the rows: (0 + above) + below, halved where both (the additions in pair order)
    z = np.float32(0.0)
    for j in range(out.size):
        fu = Fu[j]
        fd = Fd[j]
        du = Du[j]
        dd = Dd[j]
        acc = z + (du if fu != 0 else z)
        acc = acc + (dd if fd != 0 else z)
        half = np.float32(acc * 0.5)
        out[j] = half if (fu & fd) != 0 else acc


@njit(cache=True, nogil=True)
def _slopes(col, region, limit):
    # per coarse pixel with a finite column: the column's change per pixel along the rows (gx) and
    # across them (gy) from its neighbours on the same surface (same region, both columns finite
    # and within ``limit``; central, else one-sided, else 0), and which of the four neighbours are
    # on it (bits 1 right, 2 left, 4 below, 8 above).  Each pair of neighbours is tested once.
    # Row by row, each output from the row's pair flags and differences by selects, one array
    # written per loop (they vectorise; with branches per pixel, 1.32 -> 0.50 ms at 640x512 on
    # AVX2).  The same values bit for bit as adding the differences into zeros in pair order:
    # gy = (0 + the one above) + the one below, halved where both.
    h, w = col.shape
    gx = np.empty((h, w), np.float32)
    gy = np.empty((h, w), np.float32)
    nb = np.empty((h, w), np.uint8)
    P = np.zeros(w + 1, np.uint8)        # P[0] = P[w] = 0: no pair past the row's ends
    D = np.zeros(w + 1, np.float32)
    F = np.zeros((2, w), np.uint8)       # vertical pairs above / below the row (ring of two)
    Dv = np.zeros((2, w), np.float32)
    Fz = np.zeros(w, np.uint8)
    Dz = np.zeros(w, np.float32)
    for i in range(h):
        up = (i + 1) % 2
        dn = i % 2
        if i + 1 < h:
            _pairs(col[i], col[i + 1], region[i], region[i + 1], limit, F[dn], Dv[dn])
        Fu = F[up] if i > 0 else Fz
        Du = Dv[up] if i > 0 else Dz
        Fd = F[dn] if i + 1 < h else Fz
        Dd = Dv[dn] if i + 1 < h else Dz
        c, r = col[i], region[i]
        _pairs(c[:w - 1], c[1:], r[:w - 1], r[1:], limit, P[1:w], D[1:w])   # pair (j, j + 1) at j + 1
        _gx_row(P, D, gx[i])
        _nb_row(P, Fu, Fd, nb[i])
        _gy_row(Fu, Du, Fd, Dd, gy[i])
    return gx, gy, nb


@njit(cache=True, nogil=True)
def _coarse_columns(w, W, centre_tol):
    # per full column u of a frame resampled to w columns: its coarse column jidx[u], its offset
    # dxs[u] from that column's centre (coarse px) and the neighbour the offset points to (xbit[u],
    # a bit of _slopes; 0 near the centre)
    dxs = np.empty(W, np.float64)
    xbit = np.empty(W, np.uint8)
    jidx = np.empty(W, np.int64)
    fx = w / W
    for u in range(W):
        x = (u + 0.5) * fx - 0.5
        j = min(max(int(np.floor(x + 0.5)), 0), w - 1)
        jidx[u] = j
        dxs[u] = x - j
        xbit[u] = 1 if x - j > centre_tol else (2 if x - j < -centre_tol else 0)
    return dxs, xbit, jidx


@njit(cache=True, nogil=True)
def _coarse_row(v, h, H, centre_tol):
    # full row v of a frame resampled to h rows: its coarse row i, offset dy from that row's
    # centre (coarse px) and the neighbour the offset points to (bit of _slopes, 0 near the centre)
    y = (v + 0.5) * (h / H) - 0.5
    i = min(max(int(np.floor(y + 0.5)), 0), h - 1)
    dy = y - i
    return i, dy, (4 if dy > centre_tol else (8 if dy < -centre_tol else 0))


@njit(cache=True, nogil=True, error_model="numpy")
def _expanded(m0, bits, need, cj, gxj, gyj, dx, dy, stripe_px, no_boundary, edge_code):
    # one full pixel of a coarse pixel (mask m0, neighbour bits, column cj and slopes): its mask,
    # column (NaN unless reported) and the stripe of that column (-1 unless reported)
    if m0 != 0:
        return m0, np.float32(np.nan), -1
    if bits & need != need:
        return np.uint8(edge_code), np.float32(np.nan), -1   # towards an edge of the decoded area
    if bits & 3 == 0:
        return np.uint8(no_boundary), np.float32(np.nan), -1
    x = np.float32(cj + gxj * dx + gyj * dy)
    return np.uint8(0), x, int(np.floor((np.float64(x) + 0.5) / stripe_px))   # the stripe of the stored column


@njit(cache=True, nogil=True, error_model="numpy")
def upsample_stripes(H, W, column, stripe, conf, mask, region, stripe_px, no_boundary, edge_code, centre_tol=0.2):
    """A decoder result on a frame resampled to (h, w) (``cv2.INTER_AREA``: the coarse pixel ``i``
    covers the full rows ``[i H / h, (i + 1) H / h)``), back at the full frame's (H, W) pixels:
    the maps a scan needs (:func:`upsample_maps` expands the others).

    Each pixel takes the coarse pixel nearest to it and, for the columns, the first-order
    expansion from that pixel's centre: ``c + gx dx + gy dy`` (dx, dy its offset in coarse pixels,
    at most 1/2), the slopes from the coarse neighbours on the same surface (same region, column
    within one stripe; central, else one-sided; along the rows one is required, else the pixel is
    masked ``no_boundary``; across them none gives 0).  A pixel more than ``centre_tol`` coarse
    pixels from its coarse pixel's centre towards a neighbour that is not reported on the same
    surface is masked ``edge_code``: the coarse pixel spans a silhouette or depth edge there,
    decoded for the surface that filled most of it, and the pixel may lie on the other (expansion
    only between decoded centres, never past the last).  ``stripe`` is the stripe of the expanded
    column.  Returns column (float32), stripe (int32), conf (float32), mask (uint8) (H, W) and the
    count of each mask code (16,) int64.
    """
    h, w = column.shape
    gx, gy, nb = _slopes(column, region, float(stripe_px))
    if H == 2 * h and W == 2 * w and centre_tol < 0.25:
        return _upsample_x2(column, conf, mask, gx, gy, nb, stripe_px, no_boundary, edge_code)
    return _upsample_any(H, W, column, conf, mask, gx, gy, nb, stripe_px, no_boundary, edge_code, centre_tol)


@njit(cache=True, nogil=True, error_model="numpy")
def _new_maps(H, W):
    # upsample_stripes' outputs: column, stripe, confidence, mask (H, W) and the count of each mask
    # code (16,)
    return (np.empty((H, W), np.float32), np.empty((H, W), np.int32), np.empty((H, W), np.float32),
            np.empty((H, W), np.uint8), np.zeros(16, np.int64))


@njit(cache=True, nogil=True, error_model="numpy")
def _upsample_any(H, W, column, conf, mask, gx, gy, nb, stripe_px, no_boundary, edge_code, centre_tol):
    # upsample_stripes' loop for any factor: each full row's coarse values gathered along the row
    # by their coarse column (once per coarse row), then the row computed by selects, one array per
    # loop, as _upsample_x2 does; the same values bit for bit (head at 1280x1024 shrunk by 1.75: a
    # loop per coarse pixel counting per pixel 4.2 ms; counting per row 3.3; one loop calling
    # _expanded per pixel 2.5-2.7 on an AVX-512 host; on a Zen 3 the upsample stage 3.64 -> 3.50 ms
    # this way, within the noise).
    h, w = column.shape
    col_o, stripe_o, conf_o, mask_o, counts = _new_maps(H, W)
    dxs, xbit, jidx = _coarse_columns(w, W, centre_tol)
    E = _expand_scratch(W)
    last = -1
    for v in range(H):
        i, dy, ybit = _coarse_row(v, h, H, centre_tol)
        if i != last:
            _load_coarse(E, i, mask, nb, column, gx, gy, conf, jidx)
            last = i
        _expand_row(E, xbit, np.uint8(ybit), dxs, dy, stripe_px, no_boundary, edge_code, col_o[v], stripe_o[v],
                    conf_o[v], mask_o[v], counts)
    return col_o, stripe_o, conf_o, mask_o, counts


@njit(cache=True, nogil=True, error_model="numpy")
def _expand_scratch(W):
    # the row scratch of the expansion loops: need, then one coarse row at the full row's pixels:
    # mask, neighbour bits, column, gx, gy, confidence
    return (np.empty(W, np.uint8), np.empty(W, np.uint8), np.empty(W, np.uint8), np.empty(W, np.float32),
            np.empty(W, np.float32), np.empty(W, np.float32), np.empty(W, np.float32))


@njit(cache=True, nogil=True, error_model="numpy")
def _load_coarse(E, i, mask, nb, column, gx, gy, conf, jidx):
    # coarse row i at the full row's pixels: by the coarse column jidx of each, or (jidx empty)
    # each value twice
    _, em, enb, ec, egx, egy, ecf = E
    if jidx.size == 0:
        _twice(mask[i], em)
        _twice(nb[i], enb)
        _twice(column[i], ec)
        _twice(gx[i], egx)
        _twice(gy[i], egy)
        _twice(conf[i], ecf)
    else:
        _gather(mask[i], jidx, em)
        _gather(nb[i], jidx, enb)
        _gather(column[i], jidx, ec)
        _gather(gx[i], jidx, egx)
        _gather(gy[i], jidx, egy)
        _gather(conf[i], jidx, ecf)


@njit(cache=True, nogil=True, error_model="numpy")
def _expand_row(E, xbit, ybit, dxs, dy, stripe_px, no_boundary, edge_code, co, so, fo, mo, counts):
    # one full row from the coarse row in E (_load_coarse): mask, column, stripe, confidence (each
    # loop writes one array), its codes counted into counts
    need, em, enb, ec, egx, egy, ecf = E
    for u in range(need.size):
        need[u] = xbit[u] | ybit
    _exp_mask(em, enb, need, np.uint8(no_boundary), np.uint8(edge_code), mo)
    _exp_column(ec, egx, egy, dxs, dy, mo, co)
    _exp_stripe(co, mo, stripe_px, so)
    _exp_conf(ecf, mo, fo)
    _count_codes(mo, counts)


@njit(cache=True, nogil=True, error_model="numpy")
def _gather(src, jidx, out):
    # out[u] = src[jidx[u]] (a coarse row at the full row's pixels)
    for u in range(out.size):
        out[u] = src[jidx[u]]


@njit(cache=True, nogil=True, error_model="numpy")
def _twice(src, out):
    # each value of a coarse row twice: out[2 j] = out[2 j + 1] = src[j]
    for j in range(src.size):
        x = src[j]
        out[2 * j] = x
        out[2 * j + 1] = x


@njit(cache=True, nogil=True, error_model="numpy")
def _exp_mask(em, enb, need, no_boundary, edge_code, mo):
    # _expanded's mask code: the coarse one, else edge_code where a needed neighbour is missing,
    # else no_boundary where neither neighbour along the row is on the surface, else 0
    z = np.uint8(0)
    for u in range(mo.size):
        m0 = em[u]
        bits = enb[u]
        nd = need[u]
        c = no_boundary if (bits & np.uint8(3)) == z else z
        c = edge_code if (bits & nd) != nd else c
        mo[u] = m0 if m0 != z else c


@njit(cache=True, nogil=True, error_model="numpy")
def _exp_column(ec, egx, egy, dxs, dy, mo, co):
    # _expanded's column where reported (mo 0), else NaN
    nan = np.float32(np.nan)
    for u in range(co.size):
        x = np.float32(ec[u] + egx[u] * dxs[u] + egy[u] * dy)
        co[u] = x if mo[u] == 0 else nan


@njit(cache=True, nogil=True, error_model="numpy")
def _exp_stripe(co, mo, stripe_px, so):
    # the stripe of the stored column where reported, else -1 (int32 straight from the floor: the
    # same value as _expanded's int64 stored into int32, columns are far inside int32)
    m1 = np.int32(-1)
    for u in range(so.size):
        s = np.int32(np.floor((np.float64(co[u]) + 0.5) / stripe_px))
        so[u] = s if mo[u] == 0 else m1


@njit(cache=True, nogil=True, error_model="numpy")
def _exp_conf(ecf, mo, fo):
    # the coarse confidence where reported, else 0
    z = np.float32(0.0)
    for u in range(fo.size):
        c = ecf[u]
        fo[u] = c if mo[u] == 0 else z


@njit(cache=True, nogil=True, error_model="numpy")
def _count_codes(mo, counts):
    # counts[c] += the row's pixels of code c (0..15): the codes present as bits, then a vector
    # count of each one present
    bits = np.uint32(0)
    for u in range(mo.size):
        bits |= np.uint32(1) << np.uint32(mo[u] & 15)
    for c in range(16):
        if (bits >> np.uint32(c)) & np.uint32(1):
            n = np.int32(0)
            cc = np.uint8(c)
            for u in range(mo.size):
                n += np.int32((mo[u] & np.uint8(15)) == cc)
            counts[c] += n


@njit(cache=True, nogil=True, error_model="numpy")
def _upsample_x2(column, conf, mask, gx, gy, nb, stripe_px, no_boundary, edge_code):
    # upsample_stripes' loop for an exact half (H = 2 h, W = 2 w): the full pixel (2 i + a, 2 j + b)
    # of coarse pixel (i, j) sits at dy, dx = -1/4 (a, b = 0) or +1/4 (1) coarse px -- the same
    # values as the general loop computes -- and always needs the neighbour bit its offset points to
    # (8 / 4 across the rows, 2 / 1 along them).  Each coarse row is first doubled along the row
    # (each value twice), then every output row is computed by selects, one array per loop, so the
    # loops vectorise: 4.2-4.9 -> 3.5-3.8 ms at 1280x1024 on AVX2 (with a branchy _expanded per
    # pixel and a per-pixel count; the four outputs' 17 MB of writes now bound it), the same values
    # bit for bit.
    h, w = column.shape
    W = 2 * w
    col_o, stripe_o, conf_o, mask_o, counts = _new_maps(2 * h, W)
    q = 0.25
    dxs = np.empty(W, np.float64)
    xb = np.empty(W, np.uint8)
    for j in range(w):
        dxs[2 * j] = -q
        dxs[2 * j + 1] = q
        xb[2 * j] = np.uint8(2)
        xb[2 * j + 1] = np.uint8(1)
    E = _expand_scratch(W)
    twice = np.empty(0, np.int64)
    for i in range(h):
        _load_coarse(E, i, mask, nb, column, gx, gy, conf, twice)
        for a in range(2):
            v = 2 * i + a
            _expand_row(E, xb, np.uint8(4) if a == 1 else np.uint8(8), dxs, q if a == 1 else -q, stripe_px, no_boundary,
                        edge_code, col_o[v], stripe_o[v], conf_o[v], mask_o[v], counts)
    return col_o, stripe_o, conf_o, mask_o, counts


@njit(cache=True, nogil=True, error_model="numpy")
def upsample_maps(H, W, column, stripe, mask, relative, region, labels, column_rel, stripe_px, no_boundary,
                  edge_code, centre_tol=0.2):
    """The other maps of :func:`upsample_stripes`' expansion, from the same coarse (h, w) arrays:
    ``region`` and ``labels`` of the nearest coarse pixel; ``relative`` moved with the expanded
    column's stripe (where :func:`upsample_stripes` reports the pixel); ``column_rel`` expanded as
    the column is, where finite (its own slopes; NaN where they are missing along the row).
    Returns relative (int32), region (int32), labels (uint8), column_rel (float32) (H, W).
    """
    h, w = column.shape
    gx, gy, nb = _slopes(column, region, float(stripe_px))
    rgx, rgy, rnb = _slopes(column_rel, region, float(stripe_px))
    rel_o = np.empty((H, W), np.int32)
    reg_o = np.empty((H, W), np.int32)
    lab_o = np.empty((H, W), np.uint8)
    crel_o = np.empty((H, W), np.float32)
    dxs, xbit, jidx = _coarse_columns(w, W, centre_tol)
    nan = np.float32(np.nan)
    for v in range(H):
        i, dy, ybit = _coarse_row(v, h, H, centre_tol)
        m_r, c_r, gx_r, gy_r, nb_r, s_r = mask[i], column[i], gx[i], gy[i], nb[i], stripe[i]
        r_r, l_r, rel_r, cr_r, rgx_r, rgy_r, rnb_r = region[i], labels[i], relative[i], column_rel[i], rgx[i], \
            rgy[i], rnb[i]
        relo, rego, labo, cro = rel_o[v], reg_o[v], lab_o[v], crel_o[v]
        for u in range(W):
            j = jidx[u]
            rego[u] = r_r[j]
            labo[u] = l_r[j]
            cro[u] = cr_r[j] + rgx_r[j] * dxs[u] + rgy_r[j] * dy if (rnb_r[j] & 3) != 0 else nan
            rel = rel_r[j]
            if m_r[j] == 0:
                m, x, s = _expanded(m_r[j], nb_r[j], xbit[u] | ybit, c_r[j], gx_r[j], gy_r[j], dxs[u], dy, stripe_px,
                                    no_boundary, edge_code)
                if m == 0:
                    rel = rel + (s - s_r[j])
            relo[u] = rel
    return rel_o, reg_o, lab_o, crel_o
