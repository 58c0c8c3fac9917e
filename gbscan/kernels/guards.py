"""The decoder's guards after the masks: the rim guard rows, stripe SNR, orphans, the
brightness-step guard, bridge cuts.

Part of :mod:`gbscan.kernels` (its docstring has the conventions)."""
from __future__ import annotations

import numpy as np
from numba import njit

from ._common import BLUE, CYAN, GREEN, contradicting_px, contradicts, ctz64, fill_row, fit_add, fit_slope, lower_bound


# -- decoder: rim guard (gbscan.decode.rim_guard) --------------------------------------------------
@njit(cache=True, nogil=True, error_model="numpy")
def rim_guard_rows(mask, column, stripe, conf, a1, a2, b_lo, b_hi, b_extra, rows_a, rows_b, ok_code, rim_code,
                   flags, a3, img, lut, box, dim_ratio, ref_rows, walk_rows, dark_ratio, same_ratio, c1, c2,
                   rows_c, c3):
    """Mask ``rim_code`` the ``ok_code`` pixels within ``rows_a`` rows (same column) of a pixel
    whose code is ``a1`` or ``a2`` (or ``a3`` when >= 0), or within ``rows_b`` rows of one whose code is in
    ``[b_lo, b_hi]`` or equals ``b_extra``; sets column NaN, stripe -1, conf 0 there and returns
    their count (a negative row count disables its class); and within ``rows_c`` rows of one whose
    code is ``c1``, ``c2`` or ``c3`` (when >= 0) (class c: a lit pixel the decoder could not use;
    its codes may be in class a or b as well, whose reach then also holds).  The codes are read from the mask as
    given (pixels masked here do not extend the guard).  ``flags`` (H, W) uint8 scratch: bit 1
    class a, bit 2 class b in ``[b_lo, b_hi]``, bit 4 class b ``b_extra``, bit 8 ``ok_code``, bit
    16 class c (one pass); then per row the OR of the flags of the rows in reach (byte-wide loops
    that vectorise) decides, and the few hits are written.

    ``dim_ratio`` > 0 (``img`` (H, W, 3) uint8, ``lut`` (256,) float32 linearisation; else unread):
    a pixel that only class b or c pixels put in reach is kept when :func:`_dim_end` finds darkness
    beyond them (``dark_ratio``, within ``walk_rows`` rows; or one signal-less pixel as bright as
    it, ``same_ratio``, then a reported one) and the pixel not dim against the one
    ``ref_rows`` rows the other way (``dim_ratio``; brightness: :func:`_brightness` over ``box``
    px of the row)."""
    H, W = mask.shape
    ua1, ua2 = np.uint8(a1), np.uint8(a2)
    ua3 = np.uint8(a3) if a3 >= 0 else ua1   # an optional third code of class a (-1: none)
    ulo, uhi, uex = np.uint8(b_lo), np.uint8(b_hi), np.uint8(b_extra)
    uok = np.uint8(ok_code)
    uc1, uc2 = np.uint8(c1), np.uint8(c2)
    uc3 = np.uint8(c3) if c3 >= 0 else uc1   # an optional third code of class c (-1: none)
    if rows_c < 0:
        uc1 = uc2 = uc3 = np.uint8(255)   # (no code is 255: class c empty)
    one, two, six = np.uint8(1), np.uint8(2), np.uint8(6)
    for v in range(H):
        mrow = mask[v]
        frow = flags[v]
        for u in range(W):
            m = mrow[u]
            fa = np.uint8((m == ua1) | (m == ua2) | (m == ua3))
            fb = np.uint8((m >= ulo) & (m <= uhi))
            fx = np.uint8(m == uex)
            fo = np.uint8(m == uok)
            fc = np.uint8((m == uc1) | (m == uc2) | (m == uc3))
            frow[u] = fa | (fb << one) | (fx << two) | (fo << np.uint8(3)) | (fc << np.uint8(4))   # 1, 2, 4, 8, 16
    reach = max(rows_a, rows_b, rows_c, 0)
    acc = np.empty(W, np.uint8)
    hitrow = np.empty(W, np.uint8)
    dim_test = dim_ratio > 0.0
    box_h = box // 2
    n = 0
    # every decision reads ``flags`` (made from the mask as given), never the rows written here
    for v in range(H):
        acc[:] = 0
        for vv in range(max(v - reach, 0), min(v + reach, H - 1) + 1):
            d = abs(vv - v)
            bits = np.uint8((one if d <= rows_a else 0) | (six if d <= rows_b else 0) | (16 if d <= rows_c else 0))
            if bits == 0:
                continue
            frow = flags[vv]
            for u in range(W):
                acc[u] |= frow[u] & bits
        mrow = mask[v]
        any_hit = np.uint8(0)
        for u in range(W):
            h = np.uint8((acc[u] != 0) & (mrow[u] == uok))
            hitrow[u] = h
            any_hit |= h
        if any_hit and dim_test:
            for u in range(W):
                if hitrow[u] and (acc[u] & one) == 0 and not _dim_end(img, lut, box_h, flags, v, u, rows_b, dim_ratio,
                                                                       ref_rows, walk_rows, dark_ratio,
                                                                       same_ratio, rows_c):
                    hitrow[u] = 0
        if any_hit:
            n += _unreport_row(hitrow, mrow, column[v], stripe[v], conf[v], rim_code)
    return n


@njit(cache=True, nogil=True, error_model="numpy")
def _as_bright(x, b, ratio):
    # x and b within ``ratio`` (< 1) of each other, either way
    return ratio * b <= x and ratio * x <= b


@njit(cache=True, nogil=True, error_model="numpy")
def _dim_end(img, lut, box_h, flags, v, u, rows_b, dim_ratio, ref_rows, walk_rows, dark_ratio, same_ratio, rows_c):
    # rim_guard_rows' end-row test of pixel (v, u), True: mask it.  B: the phase-blind brightness.
    # On each side s with a class b pixel (flags bits 2 or 4) within rows_b rows, walking on from
    # (v, u) that way past the pixels that are not reported (bit 8; RIM-coded, dropped striped,
    # signal-less) -- or, when the nearest is a class c pixel (bit 16, within rows_c rows), from
    # that pixel on, past the reported rows before it (a class c DARK pixel over darkness is thus
    # no trigger) -- darkness must come within walk_rows rows, before any reported pixel: two
    # signal-less pixels (bit 2) in a row below dark_ratio B(v, u), or one at the image's edge
    # (nothing there for the blur to carry; a reported pixel first is another surface, or the
    # same after a dropout, which this test cannot tell apart).  And B(v, u) must be at least
    # dim_ratio B at the pixel ref_rows rows the other way (v - s ref_rows), which must be
    # reported (else masked: no surface to compare with): not a penumbra.  A side whose next
    # pixel is signal-less (not "rim") and the one after reported, both within same_ratio of
    # B(v, u) either way, is clear: a stripe transition the classifier found neither green nor
    # blue enough, inside the surface (the real face's green-blue boundary pixels); for a class c
    # pixel alone in reach the same test at it and the pixel beyond.
    H = flags.shape[0]
    b = _brightness(img, lut, v, u, box_h)
    dark_b = np.float32(dark_ratio) * b
    for s in (-1, 1):
        start = 0              # where the walk starts (0: nothing in reach on this side)
        for k in range(1, max(rows_b, rows_c) + 1):
            w = v + s * k
            want = (6 if k <= rows_b else 0) | (16 if k <= rows_c else 0)
            if 0 <= w < H and (flags[w, u] & want) != 0:
                # a class b pixel: from the next row; class c alone: from itself (a lit pixel the
                # decoder could not use, past reported rows: is darkness beyond it?)
                start = 1 if (flags[w, u] & want & 6) != 0 else k
                break
        if start == 0:
            continue
        dark = False
        w1, w2 = v + s * start, v + s * (start + 1)
        if (0 <= w2 < H and (flags[w1, u] & 6) == 2 and (flags[w2, u] & 8) != 0
                and _as_bright(_brightness(img, lut, w1, u, box_h), b, same_ratio)
                and _as_bright(_brightness(img, lut, w2, u, box_h), b, same_ratio)):
            continue   # one signal-less pixel as bright as its neighbours: a stripe transition
        for k in range(start, start + walk_rows):
            w = v + s * k
            if w < 0 or w >= H:
                dark = True
                break
            f = flags[w, u]
            if (f & 8) != 0:
                break
            if (f & 2) != 0 and _brightness(img, lut, w, u, box_h) < dark_b:
                w2 = w + s
                if w2 < 0 or w2 >= H or ((flags[w2, u] & 2) != 0 and _brightness(img, lut, w2, u, box_h) < dark_b):
                    dark = True
                    break
        if not dark:
            return True
        r = v - s * ref_rows
        if r < 0 or r >= H or (flags[r, u] & 8) == 0:
            return True
        if b < dim_ratio * _brightness(img, lut, r, u, box_h):
            return True
    return False


@njit(cache=True, nogil=True)
def _unreport_row(hit, mrow, col, stripe, conf, code):
    """Mask ``code`` the pixels of one row where ``hit`` is set: column NaN, stripe -1,
    confidence 0 (the final outputs of :func:`finish_pixels`); returns their count."""
    n = 0
    for u in range(hit.shape[0]):
        if hit[u]:
            mrow[u] = code
            col[u] = np.nan
            stripe[u] = -1
            conf[u] = 0.0
            n += 1
    return n


@njit(cache=True, nogil=True)
def stripe_snr(img, lut, row_step, col_step, lit_dn):
    """Stripe signal-to-noise ratio of a frame, from every ``col_step``-th pixel of every
    ``row_step``-th row (cheap: 1/(row_step col_step) of the pixels, three rows read for each).

    img (H, W, 3) uint8 RGB; lut (256,) float32 encoded -> linear DN (``decode.gamma_lut``);
    lit_dn: samples whose linear green or blue reaches this count.  On ``d = g - b`` (linear):

    * noise (DN): robust standard deviation of the vertical second difference
      ``d[v-1] - 2 d[v] + d[v+1]`` (variance ``6 sigma^2`` for white noise), ``1.4826 * MAD``;
      the stripes run along the columns, so the difference removes them and leaves the noise
      (bends and silhouettes add a few large values, which the median ignores);
    * modulation (DN): the 80th percentile of ``|d|`` (the stripe's swing, away from its
      boundaries).

    Returns (noise_dn, modulation_dn, n_samples); histograms of 0.05 DN (noise) and 0.25 DN
    (modulation) bins give the quantiles in one pass."""
    H, W = img.shape[0], img.shape[1]
    nb_n = 2048
    nb_m = 1024
    hn = np.zeros(nb_n, np.int64)
    hm = np.zeros(nb_m, np.int64)
    inv6 = 1.0 / np.sqrt(6.0)
    n = 0
    for v in range(1, H - 1, row_step):
        for u in range(0, W, col_step):
            g1 = lut[img[v, u, 1]]
            b1 = lut[img[v, u, 2]]
            if g1 < lit_dn and b1 < lit_dn:
                continue
            d0 = lut[img[v - 1, u, 1]] - lut[img[v - 1, u, 2]]
            d1 = g1 - b1
            d2 = lut[img[v + 1, u, 1]] - lut[img[v + 1, u, 2]]
            e = abs(d0 - 2.0 * d1 + d2) * inv6
            k = int(e * 20.0)
            hn[min(k, nb_n - 1)] += 1
            k = int(abs(d1) * 4.0)
            hm[min(k, nb_m - 1)] += 1
            n += 1
    if n == 0:
        return 0.0, 0.0, 0
    # median of the noise histogram, 80th percentile of the modulation one (bin centres)
    med = _hist_quantile(hn, (n + 1) // 2) / 20.0
    mod = _hist_quantile(hm, int(np.ceil(0.8 * n))) / 4.0
    return 1.4826 * med, mod, n


@njit(cache=True, nogil=True)
def _hist_quantile(hist, count):
    """Centre (in bins, ``k + 0.5``) of the first bin where the cumulative count reaches ``count``."""
    c = 0
    for k in range(hist.shape[0]):
        c += hist[k]
        if c >= count:
            return k + 0.5
    return hist.shape[0] - 0.5


@njit(cache=True, nogil=True, error_model="numpy")
def drop_orphans(mask, column, stripe, conf, ok_code, code):
    """Mask ``code`` every reported pixel (``mask == ok_code``) none of whose 8 neighbours is
    reported: a lone pixel left between masked ones has no neighbour to be checked against (the
    vertical check ran before the rim masks).  column/stripe/conf set to NaN/-1/0; in place;
    returns the count.  Per row, branch-free: ``vert[u]`` = reported in rows v-1..v+1 at u, a pixel
    is alone when ``vert`` is clear at u-1 and u+1 and its own column has only itself."""
    H, W = mask.shape
    vert = np.zeros(W + 2, np.uint8)   # padded by one column each side
    other = np.zeros(W, np.uint8)
    alone = np.zeros(W, np.uint8)
    n = 0
    for v in range(H):
        cur = mask[v]
        up = mask[v - 1] if v > 0 else mask[v]
        dn = mask[v + 1] if v + 1 < H else mask[v]
        has_up = np.uint8(1 if v > 0 else 0)
        has_dn = np.uint8(1 if v + 1 < H else 0)
        for u in range(W):
            a = np.uint8(up[u] == ok_code) & has_up
            b = np.uint8(dn[u] == ok_code) & has_dn
            c = np.uint8(cur[u] == ok_code)
            vert[u + 1] = a | b | c
            other[u] = a | b
        for u in range(W):
            alone[u] = np.uint8(cur[u] == ok_code) & ~(vert[u] | vert[u + 2] | other[u]) & np.uint8(1)
        hit = np.uint8(0)   # (its own loop: with the OR above, the loop above vectorised 4 bytes wide)
        for u in range(W):
            hit |= alone[u]
        if hit:
            n += _unreport_row(alone, cur, column[v], stripe[v], conf[v], code)
    return n


@njit(cache=True, nogil=True, error_model="numpy")
def _brightness(img, lut, v, u, h):
    # phase-blind brightness of pixel (v, u): the mean of lut[G] + lut[B] over columns u - h .. u + h
    # (clipped at the image sides); a window of about one green-blue period sums a green and a
    # blue stripe whatever the phase, so its steps are the surface's irradiance and albedo
    W = img.shape[1]
    lo = max(u - h, 0)
    hi = min(u + h, W - 1)
    px = img[v]
    s = np.float32(0.0)
    for x in range(lo, hi + 1):
        s += lut[px[x, 1]] + lut[px[x, 2]]
    return s / np.float32(hi - lo + 1)


@njit(cache=True, nogil=True, error_model="numpy")
def _brightness_rows(img, lut, u, h, k0, out):
    # out[i] = _brightness(img, lut, k0 + i, u, h): the same sums, the window's columns in the
    # outer loop so the rows' sums run side by side (30% faster than one row after the other)
    W = img.shape[1]
    lo = max(u - h, 0)
    hi = min(u + h, W - 1)
    for i in range(out.size):
        out[i] = np.float32(0.0)
    for x in range(lo, hi + 1):
        for i in range(out.size):
            out[i] += lut[img[k0 + i, x, 1]] + lut[img[k0 + i, x, 2]]
    c = np.float32(hi - lo + 1)
    for i in range(out.size):
        out[i] = out[i] / c


@njit(cache=True, nogil=True, error_model="numpy")
def _step_at(buf, i_bright, i_dim, half, ratio, flat):
    # the step test on buf[i_bright : i_bright + half] (the bright side's rows) against
    # buf[i_dim : i_dim + half] (the dim side's): brighter by more than ``ratio`` in the mean, the
    # dim side flat (max <= ``flat`` min)
    sa = np.float32(0.0)
    for k in range(i_bright, i_bright + half):
        sa += buf[k]
    sb = np.float32(0.0)
    lo = np.float32(np.inf)
    hi = np.float32(0.0)
    for k in range(i_dim, i_dim + half):
        x = buf[k]
        sb += x
        lo = min(lo, x)
        hi = max(hi, x)
    return sa > ratio * sb and hi <= flat * lo


@njit(cache=True, nogil=True, error_model="numpy")
def _step_below(img, lut, box_h, u, a, b, reach, ratio, half, flat, buf):
    # step_guard's test for a dim side below a step in the stretch a..b of column u: the lowest
    # boundary t (between rows t - 1 and t) that qualifies, rows t - 1 .. b to mask; b + 2: none.
    # Reads rows max(a, b - reach - half) .. b (buf[k - a]: row k's brightness)
    t0 = max(a + half + 1, b - reach + 1)
    if t0 > b - half:
        return b + 2
    _brightness_rows(img, lut, u, box_h, t0 - 1 - half, buf[t0 - 1 - half - a:b + 1 - a])
    for t in range(t0, b - half + 1):
        if _step_at(buf, t - 1 - half - a, t + 1 - a, half, ratio, flat):
            return t
    return b + 2


@njit(cache=True, nogil=True, error_model="numpy")
def _step_above(img, lut, box_h, u, a, b, reach, ratio, half, flat, buf):
    # mirrored: a dim side above a step, the highest t that qualifies, rows a .. t to mask; a - 1:
    # none.  Reads rows a .. min(b, a + reach + half): the same answer for any b past that row
    t1 = min(b - half, a + reach)
    if t1 < a + half + 1:
        return a - 1
    _brightness_rows(img, lut, u, box_h, a, buf[:t1 + half + 1 - a])
    for t in range(t1, a + half, -1):
        if _step_at(buf, t + 1 - a, t - 1 - half - a, half, ratio, flat):
            return t
    return a - 1


@njit(cache=True, nogil=True)
def _unreport_rows(mask, column, stripe, conf, u, x0, x1, ok_code, code):
    # rows x0 .. x1 of column u: reported pixels -> ``code`` (NaN / -1 / 0); returns the count
    n = 0
    for x in range(x0, x1 + 1):
        if mask[x, u] == ok_code:
            mask[x, u] = code
            column[x, u] = np.nan
            stripe[x, u] = -1
            conf[x, u] = 0.0
            n += 1
    return n


@njit(cache=True, nogil=True)
def _sg_mask_n(rrow, cur, due, v):
    # bit t: rrow[t] != cur[t] or due[t] == v (rrow.size <= 64 pixels)
    m = np.uint64(0)
    for t in range(rrow.size):
        m |= np.uint64((rrow[t] != cur[t]) | (due[t] == v)) << np.uint64(t)
    return m


@njit(cache=True, nogil=True, error_model="numpy")
def step_guard(img, lut, box, region, mask, column, stripe, conf, reach, ratio, half, flat, ok_code, code):
    """Mask ``code`` the reported pixels (``mask == ok_code``) on the dim side of a brightness
    step inside their region's stretch along an image column, near that stretch's end: the
    stripes the along-stripe blur carried from a brighter surface across a horizontal depth edge.
    Returns the count; column/stripe/conf set to NaN/-1/0 there; in place.

    img (H, W, 3) uint8 RGB, lut (256,) float32 linearisation: the brightness of a pixel is the
    mean of ``lut[G] + lut[B]`` over the ``box`` (odd) px of its row around it (clipped at the
    sides; about one green-blue period: phase-blind).  region (H, W) int32 (-1 none).  For each
    column, each maximal run of rows ``a .. b`` of one region and each boundary ``t`` between rows
    ``t - 1`` and ``t`` with ``half`` rows of the run beyond a transition row on either side:
    ``A`` = mean brightness over rows ``t - 1 - half .. t - 2``, ``B`` over ``t + 1 .. t + half``
    (rows ``t - 1`` and ``t`` skipped: the camera's defocus blends them).  If ``A > ratio B``, the
    ``B`` rows are flat (max <= ``flat`` min: a surface, not the ramp of a light field's or
    shadow's edge) and the run ends within ``reach`` rows past the transition pair (``b - t + 1 <=
    reach``), rows ``t - 1 .. b`` are masked; mirrored for a brighter side below (``t - a <= reach``:
    rows ``a .. t``).  Row-major: the runs are found by comparing each row with the run each
    column is in, and only their ends are looked at, each while its rows are recent (the top
    ``reach + half + 1`` rows after them, the bottom when the run ends); the brightness is
    computed there alone.

    Each row is scanned 64 columns at a time for the columns whose region changes or whose top test
    is due (a bit mask), and only those are visited (plane 0.36-0.50 -> 0.23-0.26 ms).  The
    brightness (most of the time left) of a column's rows is summed side by side
    (:func:`_brightness_rows`; plane 0.18 -> 0.145 ms, head 0.17 -> 0.13).
    """
    H, W = region.shape
    cur = np.full(W, -1, np.int32)
    start = np.zeros(W, np.int64)
    due = np.full(W, H + 1, np.int32)
    buf = np.empty(H, np.float32)
    negrow = np.full(W, -1, np.int32)
    n = 0
    box_h = box // 2
    top_rows = reach + half + 1
    for v in range(H + 1):
        rrow = region[v] if v < H else negrow
        v32 = np.int32(v)
        base = 0
        while base < W:
            e = min(base + 64, W)
            m = _sg_mask_n(rrow[base:e], cur[base:e], due[base:e], v32)
            while m != np.uint64(0):
                u = base + ctz64(m)
                m &= m - np.uint64(1)
                r = rrow[u]
                if r == cur[u]:
                    if v == due[u]:
                        a = start[u]
                        hi_t = _step_above(img, lut, box_h, u, a, v - 1, reach, ratio, half, flat, buf)
                        n += _unreport_rows(mask, column, stripe, conf, u, a, hi_t, ok_code, code)
                        due[u] = H + 1
                    continue
                if cur[u] >= 0:
                    a = start[u]
                    b = v - 1
                    if due[u] <= H:
                        hi_t = _step_above(img, lut, box_h, u, a, b, reach, ratio, half, flat, buf)
                        n += _unreport_rows(mask, column, stripe, conf, u, a, hi_t, ok_code, code)
                    lo_t = _step_below(img, lut, box_h, u, a, b, reach, ratio, half, flat, buf)
                    n += _unreport_rows(mask, column, stripe, conf, u, lo_t - 1, b, ok_code, code)
                cur[u] = r
                start[u] = v
                # (a run starting within top_rows of the bottom is tested when it ends, at H at the
                # latest: H + 1 means "tested")
                due[u] = min(v + top_rows, H) if r >= 0 else H + 1
            base = e
    return n


@njit(cache=True, nogil=True)
def bridge_cuts(j_x, seg_j0, seg_j1, ratio, pre):
    """Junctions of unlocated boundaries whose bridge does not fit the spacing on both sides.

    ``j_x`` (n_j,) float64 sub-pixel boundary positions (NaN: not located), ``seg_j0, seg_j1``
    each segment's junction range, ``pre`` (n_j,) uint8 junctions cut already (by
    :func:`spacing_cuts`: they end a piece, as :func:`apply_cuts` will make them).  Inside each
    piece, a run of unlocated junctions ``a..b`` is bridged by the located boundaries ``a - 1``
    and ``b + 1``: its mean spacing ``(x[b+1] - x[a-1]) / (b - a + 2)`` must lie within
    ``[1/ratio, ratio]`` of the located spacing just left of it and of the one just right of it
    (those measurable; at least one).  Otherwise (no bridge: the run ends the piece, nothing to
    compare with, or a misfit) every junction of the run is cut.  Returns (n_j,) uint8 (the new
    cuts only).
    """
    nj = j_x.shape[0]
    cut = np.zeros(nj, np.uint8)
    for s in range(seg_j0.shape[0]):
        p0 = seg_j0[s]
        while p0 < seg_j1[s]:
            p1 = p0  # the piece [p0, p1) ends at the next junction cut already
            while p1 < seg_j1[s] and pre[p1] == 0:
                p1 += 1
            _bridge_piece(j_x, p0, p1, ratio, cut)
            p0 = p1 + 1
    return cut


@njit(cache=True, nogil=True)
def _bridge_piece(j_x, j0, j1, ratio, cut):
    j = j0
    while j < j1:
        if not np.isnan(j_x[j]):
            j += 1
            continue
        a = j
        while j < j1 and np.isnan(j_x[j]):
            j += 1
        b = j - 1
        ja = a - 1
        jb = b + 1
        ok = ja >= j0 and jb < j1
        if ok:
            sp = (j_x[jb] - j_x[ja]) / (jb - ja)
            n_nb = 0
            if sp <= 0.0:
                ok = False
            if ok and ja - 1 >= j0 and not np.isnan(j_x[ja - 1]):
                q = j_x[ja] - j_x[ja - 1]
                n_nb += 1
                if q <= 0.0 or sp > ratio * q or sp * ratio < q:
                    ok = False
            if ok and jb + 1 < j1 and not np.isnan(j_x[jb + 1]):
                q = j_x[jb + 1] - j_x[jb]
                n_nb += 1
                if q <= 0.0 or sp > ratio * q or sp * ratio < q:
                    ok = False
            if n_nb == 0:
                ok = False
        if not ok:
            for k in range(a, b + 1):
                cut[k] = 1


# column_spread's row loops: each a function of its own writing one array, indexed from 0 (see
# column_spread's docstring)
@njit(cache=True, nogil=True, error_model="numpy")
def _spread_flags_row(m, ok_code, out):
    # 1 where the pixel is not reported, else 0
    for u in range(out.size):
        out[u] = np.uint8(m[u] != ok_code)


@njit(cache=True, nogil=True, error_model="numpy")
def _reported_span(m, ok_code):
    # first and one-past-last reported pixel of the row (W, 0 if none)
    W = m.size
    lo = W
    hi = 0
    for u in range(W):
        r = m[u] == ok_code
        lo = min(lo, u if r else W)
        hi = max(hi, u + 1 if r else 0)
    return lo, hi


@njit(cache=True, nogil=True, error_model="numpy")
def _rough_add(ca, cb, cc, d2k, n2k, s, sn):
    # one row's |c(v-1) - 2 c(v) + c(v+1)| (0 where a column is NaN) into d2k and its defined
    # flag into n2k, both added to the window sums s, sn
    zero = np.float32(0.0)
    one = np.float32(1.0)
    for u in range(s.size):
        a = ca[u]
        b = cb[u]
        c = cc[u]
        d = abs(a - np.float32(2.0) * b + c)
        d = d if d == d else zero
        e = a + b + c
        n = one if e == e else zero
        d2k[u] = d
        n2k[u] = n
        s[u] += d
        sn[u] += n


@njit(cache=True, nogil=True, error_model="numpy")
def _sub2(s, sn, d2o, n2o):
    # the row leaving the window subtracted from the sums
    m1 = np.float32(-1.0)
    for u in range(s.size):
        s[u] += m1 * d2o[u]
    for u in range(sn.size):
        sn[u] += m1 * n2o[u]


@njit(cache=True, nogil=True, error_model="numpy")
def _edge_dists(F, v, cap, lo, nb, dr, dv):
    # dr, dv [0:64 nb] for columns lo .. lo + 64 nb - 1 of row v (F padded past the last column):
    # nearest k in 1..cap with a flag k px along the row / k rows along the column either way, 0: none
    H = F.shape[0]
    fr = F[v]
    c0 = lo + cap
    for b in range(nb):
        o = b * 64
        for j in range(64):
            dr[o + j] = 0
            dv[o + j] = 0
    for kk in range(cap, 0, -1):
        k8 = np.uint8(kk)
        a = fr[c0 - kk:]
        c = fr[c0 + kk:]
        for b in range(nb):
            o = b * 64
            for j in range(64):
                old = dr[o + j]   # read first: a read only on the else branch keeps AVX2 scalar
                dr[o + j] = k8 if (a[o + j] | c[o + j]) != 0 else old
    for kk in range(cap, 0, -1):
        k8 = np.uint8(kk)
        va = v - kk
        vb = v + kk
        if va >= 0 and vb < H:
            a = F[va, c0:]
            c = F[vb, c0:]
            for b in range(nb):
                o = b * 64
                for j in range(64):
                    old = dv[o + j]
                    dv[o + j] = k8 if (a[o + j] | c[o + j]) != 0 else old
        elif va >= 0 or vb < H:
            x = F[va if va >= 0 else vb, c0:]
            for b in range(nb):
                o = b * 64
                for j in range(64):
                    old = dv[o + j]
                    dv[o + j] = k8 if x[o + j] != 0 else old


@njit(cache=True, nogil=True, error_model="numpy")
def _spread2_row(s, sn, dr, dv, rs, floor2, edge2, edge_v2, out):
    one = np.float32(1.0)
    inf = np.float32(np.inf)
    for u in range(out.size):
        r = rs * s[u] / max(sn[u], one)
        a = dr[u]
        b = dv[u]
        fa = np.float32(a) if a != 0 else inf
        fb = np.float32(b) if b != 0 else inf
        out[u] = floor2 + r * r + edge2 / fa + edge_v2 / fb


@njit(cache=True, nogil=True, error_model="numpy")
def _conf_row(cf, sp2, m, ok_code, inv_s02, cfl):
    one = np.float32(1.0)
    for u in range(cf.size):
        q = one / (one + sp2[u] * inv_s02)
        c = cf[u]
        new = cfl + (c - cfl) * q
        cf[u] = new if m[u] == ok_code else c


@njit(cache=True, nogil=True, error_model="numpy")
def _spread_out(sp2, m, ok_code, out):
    nan = np.float32(np.nan)
    for u in range(out.size):
        out[u] = np.sqrt(sp2[u]) if m[u] == ok_code else nan


@njit(cache=True, nogil=True, error_model="numpy")
def column_spread(column, mask, conf, ok_code, rough_rows, rough_scale, edge_px, edge_cap, floor_px, sigma0,
                  conf_floor, spread, edge_rows_px, sources):
    """Predicted error (projector px) of every reported pixel's column (``mask == ok_code``), and the
    pixel's confidence ``conf`` (H, W) float32 scaled by it in place:
    ``conf_floor + (conf - conf_floor) / (1 + (s / sigma0)^2)`` (``sigma0 <= 0``: untouched).
    ``spread`` (H, W) float32 receives ``s`` (NaN where not reported), or is skipped when it has
    size 0.  The prediction rests on what the column map itself shows:

    * the local roughness along the stripes: ``rough_scale`` times the mean of
      ``|c(v-1) - 2 c(v) + c(v+1)|`` over the rows ``v - rough_rows .. v + rough_rows`` of the
      pixel's camera column where it is defined (the three pixels reported; none: 0).  A
      surface's column is smooth along the stripes; the boundaries' noise is not.  Near the top
      or bottom end of a surface's stretch the mean over the rows left measures how fast the
      column bends there, which the end rows miss by (the along-stripe blur is one-sided there);
    * the distance to the nearest unreported pixel within ``edge_cap`` px, ``d`` along the row
      and ``e`` along the column: ``edge_px / sqrt(d)`` and ``edge_rows_px / sqrt(e)`` (0 beyond
      the reach): the boundaries next to the edge of what was decoded rest on fewer, dimmer,
      more compressed samples, are extrapolated, and may be pulled across a depth edge.

    ``s = sqrt(floor_px^2 + roughness^2 + edge_px^2 / d + edge_rows_px^2 / e)`` (``floor_px``:
    the locator's noise on a smooth surface far from any edge, which no other term sees).
    ``sources`` (n,) int64 ascending flat indices ``v * W + u`` of reported pixels that count as
    unreported for the distances all the same (the stripe transitions the decoder joined,
    ``kernels.join_transitions``: the columns around a pixel both of whose colours the local
    normalisation puts under ``min_level`` are as poor as next to a dropped one); a source's own
    distances are to the nearest flagged pixel other than itself.  The image border counts as
    reported.  ``column`` must be NaN exactly where the pixel is not
    reported (as the decoder makes it).

    One pass down the rows.  Both distances come from one uint8 flag image (unreported or a
    source, padded by ``edge_cap`` columns): the nearest flag 1 .. ``edge_cap`` px away either way
    along the row, and rows away along the column, by shifted ORs over 64-pixel blocks.  The
    roughness sums run over the columns that hold a reported pixel, and each row is computed over
    its span of reported pixels only (NaN in ``spread`` outside it).  Every row loop is a function
    of its own writing one array and indexing from 0: so LLVM vectorises it (inside one large
    function it vectorised none, 1.75 ms at 640x480; with the loops apart and two passes, up then
    down, 0.8-1.0 ms; this way 0.5-0.7 ms, the head's lit window 0.25 -> 0.11 ms, the same values
    bit for bit).  On an AVX2 machine the distance loops stayed scalar until each read its byte
    before the select (see the package docstring): the distances 1.2-1.8 -> 0.2-0.3 ms.  float32
    throughout, the sums in the same order as a plain loop would add them."""
    H, W = mask.shape
    cap = max(min(edge_cap, 254), 0)
    h = rough_rows
    Wp = cap + ((W + 63) & ~63) + cap + 64   # padded: 64-px blocks read past the last column
    # flags (unreported or a source), padded by cap zero columns each side; each row's span of
    # reported pixels [lo, hi)
    F = np.zeros((H, Wp), np.uint8)
    span_lo = np.empty(H, np.int64)
    span_hi = np.empty(H, np.int64)
    U0 = W
    U1 = 0
    for v in range(H):
        _spread_flags_row(mask[v], ok_code, F[v, cap:cap + W])
        lo, hi = _reported_span(mask[v], ok_code)
        span_lo[v] = lo
        span_hi[v] = hi
        if hi > lo:
            U0 = min(U0, lo)
            U1 = max(U1, hi)
    ns = sources.shape[0]
    for i in range(ns):
        F[sources[i] // W, cap + sources[i] % W] = np.uint8(1)
    has_out = spread.size > 0
    if U1 <= U0:   # nothing reported
        if has_out:
            for v in range(H):
                fill_row(spread[v], np.float32(np.nan))
        return
    nr = 2 * h + 2
    NU = U1 - U0                              # the columns whose roughness is ever read
    d2 = np.zeros((nr, NU), np.float32)
    n2 = np.zeros((nr, NU), np.float32)
    s = np.zeros(NU, np.float32)
    sn = np.zeros(NU, np.float32)
    sp2 = np.empty(W, np.float32)
    dr = np.empty(W + 64, np.uint8)
    dv = np.empty(W + 64, np.uint8)
    floor2 = np.float32(floor_px * floor_px)
    edge2 = np.float32(edge_px * edge_px)
    edge_v2 = np.float32(edge_rows_px * edge_rows_px)
    rs = np.float32(rough_scale)
    inv_s02 = np.float32(1.0 / (sigma0 * sigma0)) if sigma0 > 0 else np.float32(0.0)
    cfl = np.float32(conf_floor)
    added = -1
    for v in range(H - 1, -1, -1):
        # window rows v - h .. v + h: add the rows down to v - h, then drop v + h + 1
        top = max(v - h, 0)
        sub = v + h + 1 <= H - 1
        ko = (v + h + 1) % nr
        while added > top or added == -1:
            w = min(v + h, H - 1) if added == -1 else added - 1
            k = w % nr
            if 1 <= w <= H - 2:
                ca = column[w - 1, U0:U1]
                cb = column[w, U0:U1]
                cc = column[w + 1, U0:U1]
                _rough_add(ca, cb, cc, d2[k], n2[k], s, sn)
            else:
                d2[k, :] = 0
                n2[k, :] = 0
            added = w
        if sub:
            _sub2(s, sn, d2[ko], n2[ko])
        lo = span_lo[v]
        hi = span_hi[v]
        if hi <= lo:
            if has_out:
                fill_row(spread[v], np.float32(np.nan))
            continue
        n = hi - lo
        _edge_dists(F, v, cap, lo, (n + 63) >> 6, dr, dv)
        mr = mask[v, lo:hi]
        _spread2_row(s[lo - U0:hi - U0], sn[lo - U0:hi - U0], dr[:n], dv[:n], rs, floor2, edge2, edge_v2, sp2[:n])
        if sigma0 > 0:
            _conf_row(conf[v, lo:hi], sp2[:n], mr, ok_code, inv_s02, cfl)
        if has_out:
            _spread_out(sp2[:n], mr, ok_code, spread[v, lo:hi])
            fill_row(spread[v, :lo], np.float32(np.nan))
            fill_row(spread[v, hi:], np.float32(np.nan))


@njit(cache=True, nogil=True)
def _row_junction_starts(j_seg, seg_row, H):
    # (H + 1,) first junction of each row (junctions are numbered row by row, left to right)
    start = np.zeros(H + 1, np.int64)
    for j in range(j_seg.shape[0]):
        start[seg_row[j_seg[j]] + 1] += 1
    for v in range(H):
        start[v + 1] += start[v]
    return start


@njit(cache=True, nogil=True)
def _next_row_matches(j_x, j_la, j_lb, a, b, c, e, tol_px, out):
    # for each junction of row range [a, b): the located junction of row range [c, e) between
    # the same two colours nearest it, within tol_px (-1: none).  Both rows are in order along
    # the row, so one pointer walks the next row.
    k0 = c
    for j in range(a, b):
        x = j_x[j]
        if np.isnan(x):
            continue
        while k0 < e and not j_x[k0] >= x - tol_px:   # (NaN: never a match, passed)
            k0 += 1
        best = -1
        bestd = tol_px
        k = k0
        while k < e and not j_x[k] > x + tol_px:
            xk = j_x[k]
            if j_la[k] == j_la[j] and j_lb[k] == j_lb[j] and not np.isnan(xk):
                d = abs(xk - x)
                if d <= bestd:
                    best = k
                    bestd = d
            k += 1
        out[j] = best


@njit(cache=True, nogil=True)
def junction_tilts(j_x, j_seg, seg_row, j_la, j_lb, H, rows, tol_px, min_rows):
    """The tilt of each located stripe boundary in the camera, ``d x / d v`` (camera px per row).

    ``j_x`` (n_j,) float64 sub-pixel positions (NaN: not located) and the junction tables of
    :func:`gbscan.kernels.row_segments` (``seg_row`` per segment, ``H`` rows; junctions numbered
    row by row, left to right).  Each boundary is followed up to ``rows`` rows up and down: in
    each next row, the located boundary between the same two colours nearest the last position,
    within ``tol_px`` (none: the track ends there).  The tilt is the least-squares slope of the
    positions over the rows followed; NaN where fewer than ``min_rows`` rows (the boundary's own
    included) were followed.  Returns (n_j,) float64.
    """
    nj = j_x.shape[0]
    out = np.full(nj, np.nan)
    start = _row_junction_starts(j_seg, seg_row, H)
    down = np.full(nj, -1, np.int64)
    up = np.full(nj, -1, np.int64)
    acc = np.zeros(5)
    for v in range(H - 1):
        _next_row_matches(j_x, j_la, j_lb, start[v], start[v + 1], start[v + 1], start[v + 2], tol_px, down)
        _next_row_matches(j_x, j_la, j_lb, start[v + 1], start[v + 2], start[v], start[v + 1], tol_px, up)
    for j in range(nj):
        x0 = j_x[j]
        if np.isnan(x0):
            continue
        acc[:] = 0.0
        acc[0] = 1.0   # the boundary itself, at (0, 0)
        for d in (-1, 1):
            nxt = up if d < 0 else down
            m = j
            for k in range(1, rows + 1):
                m = nxt[m]
                if m < 0:
                    break
                fit_add(acc, float(d * k), j_x[m] - x0)
        out[j] = fit_slope(acc, min_rows)
    return out


@njit(cache=True, nogil=True)
def _sort_few(a, n):
    # sort a[:n] in place (insertion sort: n is a handful)
    for i in range(1, n):
        t = a[i]
        k = i - 1
        while k >= 0 and a[k] > t:
            a[k + 1] = a[k]
            k -= 1
        a[k + 1] = t


@njit(cache=True, nogil=True)
def _median_sorted(a, n):
    # median of a[:n], sorting it in place
    _sort_few(a, n)
    return 0.5 * (a[(n - 1) // 2] + a[n // 2])


@njit(cache=True, nogil=True)
def _side_stats(tilt, a, b, buf):
    # median and MAD of the finite tilts in [a, b); n = how many
    n = 0
    for k in range(a, b):
        t = tilt[k]
        if not np.isnan(t):
            buf[n] = t
            n += 1
    if n == 0:
        return np.nan, np.nan, 0
    med = _median_sorted(buf, n)
    for k in range(n):
        buf[k] = abs(buf[k] - med)
    return med, _median_sorted(buf, n), n


@njit(cache=True, nogil=True)
def _tilt_step(tilt, j0, j1, i, window, min_n, step, z, floor, buf):
    # the test of tilt_step_cuts at junction i of the segment's junctions [j0, j1)
    # (medians more than step apart need a range of more than step: most junctions stop there)
    lo = np.inf
    hi = -np.inf
    for k in range(max(j0, i - window), min(j1, i + 1 + window)):
        t = tilt[k]
        if k != i and not np.isnan(t):
            lo = min(lo, t)
            hi = max(hi, t)
    if not hi - lo > step:
        return False
    ml, dl, nl = _side_stats(tilt, max(j0, i - window), i, buf)
    if nl < min_n:
        return False
    mr, dr, nr = _side_stats(tilt, i + 1, min(j1, i + 1 + window), buf)
    if nr < min_n:
        return False
    d = abs(mr - ml)
    return d > step and d > z * max(1.4826 * max(dl, dr), floor)


@njit(cache=True, nogil=True)
def _match_in_row(j_x, j_ua, j_la, j_lb, a, b, x, uw, la, lb, tol_px):
    # the located junction of row range [a, b) with labels (la, lb) nearest the position x, within
    # tol_px; -1 if none.  uw: x in the tables' pixel columns (a decoded window's j_x are the
    # frame's), found +-2 px (a junction lies between its runs' pixels j_ua and j_ub <= j_ua + 2)
    lo = lower_bound(j_ua, a, b, uw - tol_px - 2.0)
    best = -1
    bestd = tol_px
    k = lo
    while k < b and j_ua[k] <= uw + tol_px + 2.0:
        xk = j_x[k]
        if j_la[k] == la and j_lb[k] == lb and not np.isnan(xk):
            d = abs(xk - x)
            if d <= bestd:
                best = k
                bestd = d
        k += 1
    return best


@njit(cache=True, nogil=True)
def _track_tilt(j, j_x, j_seg, seg_row, j_ua, j_la, j_lb, start, H, rows, tol_px, min_rows):
    # junction_tilts for one junction (the same tracks and fit, searched row by row)
    x0 = j_x[j]
    if np.isnan(x0):
        return np.nan
    v0 = seg_row[j_seg[j]]
    acc = np.zeros(5)
    acc[0] = 1.0   # the boundary itself, at (0, 0)
    for d in (-1, 1):
        x = x0
        for k in range(1, rows + 1):
            v = v0 + d * k
            if v < 0 or v >= H:
                break
            m = _match_in_row(j_x, j_ua, j_la, j_lb, start[v], start[v + 1], x, j_ua[j] + (x - x0), j_la[j],
                              j_lb[j], tol_px)
            if m < 0:
                break
            x = j_x[m]
            fit_add(acc, float(d * k), x - x0)
    return fit_slope(acc, min_rows)


@njit(cache=True, nogil=True, error_model="numpy")
def _add_row2(a, r, q, out):
    # out = a + (r | q) (a column's running count, one row down)
    for u in range(out.size):
        out[u] = a[u] + (r[u] | q[u])


@njit(cache=True, nogil=True)
def _tilts_around(i, j0, j1, window, tilt, done, j_x, j_seg, seg_row, j_ua, j_la, j_lb, start, H, rows, tol_px):
    # the tilts of junction i's test window (its segment's junctions [j0, j1)), each followed once
    for k in range(max(j0, i - window), min(j1, i + 1 + window)):
        if done[k] == 0:
            tilt[k] = _track_tilt(k, j_x, j_seg, seg_row, j_ua, j_la, j_lb, start, H, rows, tol_px, rows - 1)
            done[k] = 1


@njit(cache=True, nogil=True)
def _mark_end(near, other, col_rows, v, e, W, break_px):
    # the pixels of row v within break_px of column e into near; col_rows counts each pixel once
    # over near and other
    for u in range(max(0, e - break_px), min(W, e + break_px + 1)):
        if near[v, u] == 0:
            near[v, u] = 1
            if other[v, u] == 0:
                col_rows[u] += 1


@njit(cache=True, nogil=True)
def _steps(j, stepped, window, min_n, step, z, floor, buf, tilt, done, j_x, j_seg, seg_row, seg_j0, seg_j1, j_ua,
           j_la, j_lb, start, H, rows, tol_px):
    # junction j's test (_tilt_step over its segment), run once: stepped[j] 1 steps, 2 does not
    if stepped[j] == 0:
        s = j_seg[j]
        _tilts_around(j, seg_j0[s], seg_j1[s], window, tilt, done, j_x, j_seg, seg_row, j_ua, j_la, j_lb, start, H,
                      rows, tol_px)
        stepped[j] = 1 if _tilt_step(tilt, seg_j0[s], seg_j1[s], j, window, min_n, step, z, floor, buf) else 2
    return stepped[j] == 1


@njit(cache=True, nogil=True)
def _pre_parts(r, u, pre, stepped, start, break_px, window, min_n, step, z, floor, buf, tilt, done, j_x, j_seg,
               seg_row, seg_j0, seg_j1, j_ua, j_la, j_lb, H, rows, tol_px):
    # does a junction of row r cut already, within break_px of column u, part its row: the tilt
    # steps across it (each tested once)
    b = start[r + 1]
    for j in range(lower_bound(j_ua, start[r], b, u - break_px), b):   # (at or right of u - break_px)
        if j_ua[j] > u + break_px:
            break
        if pre[j] != 0 and _steps(j, stepped, window, min_n, step, z, floor, buf, tilt, done, j_x, j_seg, seg_row,
                                  seg_j0, seg_j1, j_ua, j_la, j_lb, start, H, rows, tol_px):
            return True
    return False


@njit(cache=True, nogil=True)
def tilt_step_cuts(j_x, j_seg, seg_row, seg_u0, seg_u1, seg_j0, seg_j1, j_ua, j_la, j_lb, H, W, rows, tol_px,
                   break_rows, break_px, break_min, window, min_n, step, z, floor, pre, tilt, done, stepped):
    """Junctions where a row crosses the depth-edge line of the rows around it with the boundaries'
    tilt stepping there (two surfaces welded in one segment where their stripes line up).

    Step 1's tables (:func:`gbscan.kernels.row_segments`; ``j_x`` (n_j,) float32 or float64 the
    located positions, NaN where none).  A junction ``i`` of a segment, with at least ``min_n`` junctions
    either side of it in the segment, is a candidate when at least ``break_min`` of the
    ``2 * break_rows`` rows around have a segment end within ``break_px`` px of its column and
    its own row has none (the rows there were parted: a silhouette that this row crossed; ``pre``
    (n_j,) uint8, or empty: junctions cut already, by the spacing and bridge cuts, that count as
    segment ends where the tilt steps across them by the test below).  It is cut
    when the tilts (:func:`junction_tilts` with ``rows``, ``tol_px`` and ``min_rows = rows - 1``;
    computed only where needed) of
    the ``window`` junctions left of it and of the ``window`` right of it (``i`` left out: it may
    be the mixed boundary at the contact), at least ``min_n`` finite on each side, have medians
    more than ``step`` px per row apart and more than ``z`` times the sides' spread (1.4826 x the
    larger MAD, at least ``floor``): a tilt changing steadily along the row (a curved surface)
    spreads each side as much as it moves the medians.  ``tilt`` (n_j,) float64, ``done`` and
    ``stepped`` (n_j,) uint8: the caller's memo of the tilts followed (``done`` 1) and of each
    junction's test (``stepped`` 0 not yet, 1 steps, 2 does not), kept over calls on the same
    junctions and parameters (start with ``done`` and ``stepped`` 0).  Returns (n_j,) uint8.
    """
    nj = j_x.shape[0]
    cut = np.zeros(nj, np.uint8)
    # the pixels within break_px of a segment end (near_end) or of a junction cut already
    # (near_pre: it parts its row there only where the tilt steps across it, tested when a
    # candidate asks), and how many rows have either in each column (an upper bound of the parted
    # rows: a column with fewer than break_min has no candidate, nor a segment spanning none)
    near_end = np.zeros((H, W), np.uint8)
    near_pre = np.zeros((H, W), np.uint8)
    col_rows = np.zeros(W, np.int32)
    for s in range(seg_row.shape[0]):
        _mark_end(near_end, near_pre, col_rows, seg_row[s], seg_u0[s], W, break_px)
        _mark_end(near_end, near_pre, col_rows, seg_row[s], seg_u1[s], W, break_px)
    for j in range(pre.shape[0]):
        if pre[j] != 0:
            _mark_end(near_pre, near_end, col_rows, seg_row[j_seg[j]], j_ua[j], W, break_px)
    col_ok = np.zeros(W + 1, np.int32)
    for u in range(W):
        col_ok[u + 1] = col_ok[u] + (1 if col_rows[u] >= break_min else 0)
    # (int16 running sums down each column wrap on frames of over 32767 rows; the differences
    # below, at most 2 * break_rows + 1, are taken modulo 2**16 and stay exact)
    csum = np.empty((H + 1, W), np.int16)
    csum[0] = 0
    for v in range(H):
        _add_row2(csum[v], near_end[v], near_pre[v], csum[v + 1])
    start = np.empty(0, np.int64)   # the rows' first junctions, made at the first junction tested
    buf = np.empty(max(window, 1), np.float64)
    for s in range(seg_j0.shape[0]):
        j0 = seg_j0[s]
        j1 = seg_j1[s]
        if j1 - j0 < 2 * min_n + 1:
            continue
        if col_ok[j_ua[j1 - min_n - 1] + 1] - col_ok[j_ua[j0 + min_n]] == 0:
            continue
        v = seg_row[s]
        r0 = max(0, v - break_rows)
        r1 = min(H, v + break_rows + 1)
        for i in range(j0 + min_n, j1 - min_n):
            u = j_ua[i]
            if col_rows[u] < break_min or near_end[v, u] != 0:   # (a row parted here already: no weld)
                continue
            if (np.int64(csum[r1, u]) - np.int64(csum[r0, u])) & 0xFFFF < break_min:
                continue
            if start.shape[0] == 0:
                start = _row_junction_starts(j_seg, seg_row, H)
            if not _steps(i, stepped, window, min_n, step, z, floor, buf, tilt, done, j_x, j_seg, seg_row, seg_j0,
                          seg_j1, j_ua, j_la, j_lb, start, H, rows, tol_px):
                continue
            if near_pre[v, u] != 0 and _pre_parts(v, u, pre, stepped, start, break_px, window, min_n, step, z,
                                                  floor, buf, tilt, done, j_x, j_seg, seg_row, seg_j0, seg_j1, j_ua,
                                                  j_la, j_lb, H, rows, tol_px):
                continue
            n = 0
            for r in range(r0, r1):
                if r == v:
                    continue
                if near_end[r, u] != 0:
                    n += 1
                elif near_pre[r, u] != 0 and _pre_parts(r, u, pre, stepped, start, break_px, window, min_n, step,
                                                        z, floor, buf, tilt, done, j_x, j_seg, seg_row, seg_j0,
                                                        seg_j1, j_ua, j_la, j_lb, H, rows, tol_px):
                    n += 1
            if n >= break_min:
                cut[i] = 1
    return cut


@njit(cache=True, nogil=True)
def _parting_near(ends, v, c, reach, W):
    # the column of row v's parting (ends[v, u] != 0) nearest column c within reach px; -1 if none
    for d in range(reach + 1):
        if c - d >= 0 and ends[v, c - d] != 0:
            return c - d
        if c + d < W and ends[v, c + d] != 0:
            return c + d
    return -1


@njit(cache=True, nogil=True)
def _line_rows(ends, v, c, step, need, reach, H, W):
    # how many rows (v's included) a line of partings runs from (v, c) in direction step, each
    # row's parting within reach px of the last one's (slanted silhouettes), counted up to need,
    # and the column of the last one counted
    n = 0
    last = c
    while 0 <= v < H and n < need:
        c = _parting_near(ends, v, c, reach, W)
        if c < 0:
            break
        last = c
        n += 1
        v += step
    return n, last


@njit(cache=True, nogil=True)
def tilt_follow_cuts(j_x, j_seg, seg_row, seg_u0, seg_u1, seg_j0, seg_j1, j_ua, j_la, j_lb, H, W, rows, tol_px,
                     break_px, window, min_n, step, z, floor, line_rows, cut, pre, tilt, done, stepped):
    """Junctions where a welded row carries on a line of parted rows, the boundaries' tilt
    stepping there: the silhouette of :func:`tilt_step_cuts` followed past the rows that end it.

    That test asks for ``break_min`` of the rows around a junction parted within ``break_px`` of
    its column, so it cannot see a slanted silhouette whose last rows are welded: the line leaves
    the column within a few rows, and at its end only one side of it is parted.  Same tables,
    tests and memo as :func:`tilt_step_cuts`; ``cut`` (n_j,) uint8 its result and ``pre`` (n_j,)
    uint8 the spacing and bridge cuts (or empty) count as partings, as do segment ends (the
    middle of a gap of at most ``2 break_px + 1`` px; not the frame's sides).

    A pass down the frame (then one up): at each parting of row ``v - 1`` with none within
    ``break_px`` in row ``v`` (the line ends there), whose line runs on upwards for at least
    ``line_rows`` rows (each row's parting within ``break_px + 1`` px of the last one's: the cuts
    sit on junctions, 3-4 px apart), the line is carried on one row at its slant over those rows.
    Of row ``v``'s junctions within ``break_px + 2`` px of there, with ``min_n`` junctions either
    side in their segment, whose tilt steps by :func:`tilt_step_cuts`' test, the one whose two
    neighbours' tilts differ most (the seam lies between them: near a slanted seam the
    boundaries' tracks cross it, so the test passes over several junctions) is cut, and parts row
    ``v`` for the next: a welded run of rows is followed while the tilt steps.  Returns (n_j,)
    uint8, the junctions this adds.
    """
    nj = j_x.shape[0]
    out = np.zeros(nj, np.uint8)
    if line_rows <= 0 or nj == 0:
        return out
    ends = np.zeros((H, W), np.uint8)      # the partings: segment ends (not the frame's sides) and cuts
    ns = seg_row.shape[0]
    part = np.full((ns, 2), -1, np.int64)  # each segment's partings at its start and its end (-1 none)
    for s in range(ns):
        # a parting: the middle of the gap to the next segment of the row when it is near, else
        # each end that is not the frame's side
        v = seg_row[s]
        if 0 < seg_u0[s] and (s == 0 or seg_row[s - 1] != v or seg_u0[s] - seg_u1[s - 1] > 2 * break_px + 1):
            part[s, 0] = seg_u0[s]
        if s + 1 < ns and seg_row[s + 1] == v and seg_u0[s + 1] - seg_u1[s] <= 2 * break_px + 1:
            part[s, 1] = (seg_u1[s] + seg_u0[s + 1]) // 2
        elif seg_u1[s] < W - 1:
            part[s, 1] = seg_u1[s]
        for e in part[s]:
            if e >= 0:
                ends[v, e] = 1
    for j in range(nj):
        if cut[j] != 0 or (pre.shape[0] != 0 and pre[j] != 0):
            ends[seg_row[j_seg[j]], j_ua[j]] = 1
    start = _row_junction_starts(j_seg, seg_row, H)
    sstart = np.zeros(H + 1, np.int64)     # each row's first segment (segments are in row order)
    for t in range(ns):
        sstart[seg_row[t] + 1] += 1
    for v in range(H):
        sstart[v + 1] += sstart[v]
    cols = np.empty(W + 2 * ns + 8, np.int64)   # one row's partings (segment ends, gaps' middles, cuts)
    flagged = np.zeros(H, np.int64)        # each row's junctions cut (by either kernel or this one)
    for j in range(nj):
        if cut[j] != 0 or (pre.shape[0] != 0 and pre[j] != 0):
            flagged[seg_row[j_seg[j]]] += 1
    buf = np.empty(max(window, 1), np.float64)
    for d in (1, -1):
        v = 1 if d == 1 else H - 2
        while 0 <= v < H and 0 <= v - d < H:
            if start[v + 1] > start[v]:
                # row v - d's partings, from its segments and its junctions cut (by either kernel
                # or this pass: ends holds them all; listed from the tables, not by a scan of W)
                r = v - d
                m = 0
                for t in range(sstart[r], sstart[r + 1]):
                    for e in part[t]:
                        if e >= 0:
                            cols[m] = e
                            m += 1
                if flagged[r] != 0:
                    for j in range(start[r], start[r + 1]):
                        if cut[j] != 0 or out[j] != 0 or (pre.shape[0] != 0 and pre[j] != 0):
                            cols[m] = j_ua[j]
                            m += 1
                _sort_few(cols, m)   # (a handful a row)
                last = -1
                for q in range(m):
                    c = cols[q]
                    if c == last:
                        continue
                    last = c
                    if _parting_near(ends, v, c, break_px, W) >= 0:
                        continue   # (the line goes on in this row)
                    n, far = _line_rows(ends, v - d, c, -d, line_rows, break_px + 1, H, W)
                    if n < line_rows:
                        continue
                    # the line carried on one row at its slant over the rows counted; of the
                    # junctions within break_px + 2 of there whose tilt steps, the one whose two
                    # neighbours' tilts differ most (the seam lies between them)
                    at = c + (c - far) / max(n - 1, 1)
                    reach = break_px + 2.0   # (a stripe's junctions either side: 3-4 px apart)
                    best = -1
                    jump = -1.0
                    for i in range(lower_bound(j_ua, start[v], start[v + 1], at - reach - 1.0), start[v + 1]):
                        if j_ua[i] + 0.5 > at + reach:
                            break
                        sg = j_seg[i]
                        if abs(j_ua[i] + 0.5 - at) > reach or i - seg_j0[sg] < min_n or seg_j1[sg] - 1 - i < min_n:
                            continue
                        if _steps(i, stepped, window, min_n, step, z, floor, buf, tilt, done, j_x, j_seg, seg_row,
                                  seg_j0, seg_j1, j_ua, j_la, j_lb, start, H, rows, tol_px):
                            g = abs(tilt[i + 1] - tilt[i - 1])
                            g = 0.0 if np.isnan(g) else g
                            if g > jump:
                                best = i
                                jump = g
                    if best >= 0:   # (a parting for the next row)
                        out[best] = 1
                        ends[v, j_ua[best]] = 1
                        flagged[v] += 1
            v += d
    return out


# -- decoder: a short run sandwiched in a surface it continues (gbscan.decode.sandwich_guard) -------
@njit(cache=True, nogil=True)
def _median_diff(col, a, b, u, buf):
    # median of the per-row changes of col[:, u] over rows [a, b] (0.0 with fewer than two rows)
    n = 0
    for v in range(a, b):
        buf[n] = col[v + 1, u] - col[v, u]
        n += 1
    if n == 0:
        return 0.0
    return _median_sorted(buf, n)


@njit(cache=True, nogil=True)
def _sandwiched(column, u, ga, a0, a1, gr, r0, r1, gb, b0, period, max_rows, gap_rows, tol_px, line_px, buf):
    # the test of sandwich_guard on column u's runs A = [a0, a1] (region ga), R = [r0, r1] (gr) and
    # B from row b0 (gb)
    if gr == ga or gr == gb or r1 - r0 + 1 > max_rows:
        return False
    ga_rows = r0 - a1
    gb_rows = b0 - r1
    if ga_rows > gap_rows or gb_rows > gap_rows:
        return False
    ca = column[a1, u]
    cr1 = column[r0, u]
    cr2 = column[r1, u]
    cb = column[b0, u]
    sa = _median_diff(column, max(a0, a1 - 4), a1, u, buf)
    pa = ca + sa * ga_rows
    k = np.round((cr1 - pa) / period)
    if k == 0 or abs(cr1 - pa - k * period) >= tol_px:
        return False
    sr = _median_diff(column, r0, r1, u, buf)
    if abs(cb - (cr2 + sr * gb_rows) + k * period) >= tol_px:
        return False
    span = b0 - a1
    if abs(cb - (ca + sa * span)) >= tol_px + 0.05 * span:
        return False
    for w in range(r0, r1 + 1):
        if not abs(column[w, u] - k * period - (ca + (cb - ca) * (w - a1) / span)) < line_px:
            return False
    return True


@njit(cache=True, nogil=True)
def sandwich_guard(mask, column, stripe, conf, region, period, max_rows, gap_rows, tol_px, line_px, ok_code,
                   code):
    """Mask ``code`` the short runs of one region along a column that the surface around them, in
    other regions, continues to the sub-pixel a whole number of periods away: a strip of a far
    surface welded along its rows into a near one's region across a silhouette, where their stripes
    line up.

    mask (H, W) uint8, column (H, W) float32 absolute projector columns (px), stripe (H, W) int32,
    conf (H, W) float32: updated in place; region (H, W) int32.  Along each column the reported
    pixels form runs of one region; a run ``R`` of at most ``max_rows`` rows whose neighbour runs
    ``A`` above and ``B`` below (at most ``gap_rows`` rows away) are of other regions is masked when
    ``A``'s columns carried on at its slope (the median change of its last 5 rows) reach ``R``'s
    first row ``k`` periods off (``k`` != 0) within ``tol_px``, ``R``'s carried on at its own slope
    reach ``B``'s first row ``-k`` periods off within ``tol_px``, ``A`` carried on reaches ``B``
    within ``tol_px`` + 0.05 px a row (one surface behind), and every row of ``R``, ``k`` periods
    back, lies within ``line_px`` of the straight line from ``A``'s last row to ``B``'s first (it is
    that surface).  Returns how many pixels it masked.
    """
    H, W = mask.shape
    if H == 0 or W == 0:
        return 0
    uok = np.uint8(ok_code)
    ucode = np.uint8(code)
    # row by row (the maps are row-major), each column's state: its current run (in_run, its
    # region and first row) and the last two runs it completed (A above R); a run starting in a
    # column with two completed runs is the B of their triple.  Hits are applied at the end, so
    # every triple sees the columns as they came in
    in_run = np.zeros(W, np.uint8)
    cur_g = np.zeros(W, np.int32)
    cur_s = np.zeros(W, np.int64)
    nh = np.zeros(W, np.int64)
    ag = np.zeros(W, np.int32)
    a0 = np.zeros(W, np.int64)
    a1 = np.zeros(W, np.int64)
    rgn = np.zeros(W, np.int32)
    r0 = np.zeros(W, np.int64)
    r1 = np.zeros(W, np.int64)
    hit_u = np.empty(16, np.int64)
    hit_a = np.empty(16, np.int64)
    hit_b = np.empty(16, np.int64)
    nhit = 0
    buf = np.empty(max(H, 8), np.float64)
    # the columns with three runs or more (a byte-wide pass the compiler vectorises): only they
    # can hold a triple
    starts = np.zeros(W, np.int32)
    for u in range(W):
        starts[u] = 1 if mask[0, u] == uok else 0
    for v in range(1, H):
        for u in range(W):
            starts[u] += (mask[v, u] == uok) & ((mask[v - 1, u] != uok) | (region[v, u] != region[v - 1, u]))
    cand = np.empty(W, np.int64)
    nc = 0
    for u in range(W):
        if starts[u] >= 3:
            cand[nc] = u
            nc += 1
    for v in range(H + 1):
        for q in range(nc):
            u = cand[q]
            ok = v < H and mask[v, u] == uok
            g = region[v, u] if ok else -1
            if in_run[u] != 0:
                if ok and g == cur_g[u]:
                    continue
                # the current run ends at v - 1: it becomes R, R becomes A
                ag[u], a0[u], a1[u] = rgn[u], r0[u], r1[u]
                rgn[u], r0[u], r1[u] = cur_g[u], cur_s[u], v - 1
                nh[u] = min(nh[u] + 1, 2)
                in_run[u] = 0
            if not ok:
                continue
            if nh[u] == 2 and _sandwiched(column, u, ag[u], a0[u], a1[u], rgn[u], r0[u], r1[u], g, v, period,
                                          max_rows, gap_rows, tol_px, line_px, buf):
                if nhit == hit_u.shape[0]:
                    hit_u = np.concatenate((hit_u, np.empty(nhit, np.int64)))
                    hit_a = np.concatenate((hit_a, np.empty(nhit, np.int64)))
                    hit_b = np.concatenate((hit_b, np.empty(nhit, np.int64)))
                hit_u[nhit], hit_a[nhit], hit_b[nhit] = u, r0[u], r1[u]
                nhit += 1
            in_run[u] = 1
            cur_g[u] = g
            cur_s[u] = v
    total = 0
    for h in range(nhit):
        total += _unreport_rows(mask, column, stripe, conf, hit_u[h], hit_a[h], hit_b[h], uok, ucode)
    return total


# -- decoder: pieces of a region cut off from its body (gbscan.decode.piece_check) ------------------

@njit(cache=True, nogil=True)
def _find(parent, a):
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


@njit(cache=True, nogil=True)
def _join_runs(rr, r0, r1, rg, row_start, H):
    # the pieces of :func:`_piece_runs`' runs: (n,) int64, each run's root, its piece's first run
    # (unions keep the smaller index).  Runs of rows v - 1 and v of one region that share a column
    # (4 neighbours) are one piece.  Pixels touching at a corner only are no evidence for each
    # other (the continuity votes, like the unwrapping's links, are along rows and columns): a
    # wall band below a sphere's slanted silhouette hung from it by one diagonal step at 725-755 mm
    n = rr.shape[0]
    parent = np.arange(n).astype(np.int64)
    for v in range(1, H):
        i = row_start[v - 1]
        ie = row_start[v]
        for j in range(row_start[v], row_start[v + 1]):
            while i < ie and r1[i] < r0[j]:
                i += 1
            k = i
            while k < ie and r0[k] <= r1[j]:
                if rg[k] == rg[j]:
                    a = _find(parent, k)
                    b = _find(parent, j)
                    if a != b:
                        if a < b:
                            parent[b] = a
                        else:
                            parent[a] = b
                k += 1
    root = np.empty(n, np.int64)
    for j in range(n):
        root[j] = _find(parent, j)
    return root


@njit(cache=True, nogil=True)
def _piece_runs(mask, region, ok_code, n_regions):
    # the reported pixels' runs of one region along each row: (row, u0, u1, region) per run (row
    # order) and row_start (H + 1,) into them.  Per row a branch-free pass writes each pixel's key
    # (its region where reported, else -1; padded by -1 both sides), then the runs are read off
    # it (0.13 against 0.18 ms a 640x480 plane reading the maps directly).  Sized for the most
    # runs a row can hold (untouched pages cost nothing): arrays grown inside the loop made numba
    # count references at every pixel (5.4 ms)
    H, W = mask.shape
    cap = H * ((W + 1) // 2) + 1
    rr = np.empty(cap, np.int32)
    r0 = np.empty(cap, np.int32)
    r1 = np.empty(cap, np.int32)
    rg = np.empty(cap, np.int32)
    row_start = np.empty(H + 1, np.int64)
    key = np.empty(W + 2, np.int32)
    key[0] = -1
    key[W + 1] = -1
    n = 0
    for v in range(H):
        row_start[v] = n
        mrow = mask[v]
        grow = region[v]
        cnt = 0
        for u in range(W):
            g = grow[u]
            ok = (mrow[u] == ok_code) & (g >= 0) & (g < n_regions)
            key[u + 1] = g if ok else np.int32(-1)
            cnt += ok
        if cnt == 0:
            continue
        u = 1
        while u <= W:
            k = key[u]
            if k < 0:
                u += 1
                continue
            a = u
            while key[u + 1] == k:
                u += 1
            rr[n] = v
            r0[n] = a - 1
            r1[n] = u - 1
            rg[n] = k
            n += 1
            u += 1
    row_start[H] = n
    return rr[:n], r0[:n], r1[:n], rg[:n], row_start


@njit(cache=True, nogil=True)
def _has_vote(cls, v, a, b, max_gap_px, want=1):
    # whether a reported pixel outside every piece (cls 1; or of class ``want``) continues the
    # piece run (v, a .. b) as kernels.link_votes reads continuity: two such pixels in line above
    # or below one of its pixels (rows v -+ 1, v -+ 2), or along the row past at most max_gap_px
    # unreported pixels beyond either end (the nearest such pixel q and q + 2 outward)
    H, W = cls.shape
    for u in range(a, b + 1):
        for d in (-1, 1):
            q, q2 = v + d, v + 2 * d
            if 0 <= q2 < H and cls[q, u] == want and cls[q2, u] == want:
                return True
    for d in (-1, 1):
        u = a if d < 0 else b
        for k in range(1, max_gap_px + 2):
            q = u + d * k
            if q < 0 or q >= W or cls[v, q] == 2:
                break
            if cls[v, q] == want:
                q2 = q + 2 * d
                if 0 <= q2 < W and cls[v, q2] == want:
                    return True
                break
            if cls[v, q] != 0:
                break
    return False


@njit(cache=True, nogil=True)
def piece_check(mask, column, stripe, conf, labels, region, is_marker, n_regions, min_px, alone_fix_px, max_gap_px,
                ok_code, code, vouch):
    """Mask ``code`` the pieces of a region that its reported pixels leave apart from its body
    and whose index nothing but the region's other pixels supports.

    mask (H, W) uint8, column (H, W) float32, stripe (H, W) int32 absolute stripe, conf (H, W)
    float32: updated in place (NaN / -1 / 0 where masked); labels (H, W) uint8 colour classes;
    region (H, W) int32; is_marker (n_stripes,) bool, the pattern's marker stripes; n_regions:
    more than the largest region id.  A region's reported pixels form *pieces*, joined along rows
    and columns (4-connected: a corner is no contact); the largest is its body (of two as large,
    the first in row order).  A reported pixel
    *contradicts* its stripe when it is cyan on a plain stripe or green / blue on a marker
    stripe; a piece's *margin* is how many fewer of its pixels contradict their stripes at its
    index than at the best other (every even shift of its stripes that keeps them within 2 of
    the pattern; a pixel beyond the pattern contradicts).  A piece other than the body is masked
    when (a) ``min_px`` > 0, at least ``min_px`` of its pixels contradict and its margin is at
    most ``-min_px`` (another index fits it better), or (b) ``alone_fix_px`` > 0, no reported
    pixel outside every piece continues it (:func:`_has_vote`, the column-continuity votes of
    :func:`gbscan.kernels.link_votes` with ``max_gap_px``) and its margin is under
    ``alone_fix_px`` (its own markers do not fix its index).  ``vouch`` (n_regions,) bool: False
    for a region whose index is its neighbours' word (linked by column continuity): its body
    continues a piece only where pixels outside every piece continue the body itself; such a
    body that nothing outside every piece continues is tested as a piece after the pieces, by
    both tests, where a piece they masked continued it (the two may have stood on each other
    alone), and kept otherwise.  Returns (masked by (a), by (b)).
    """
    H, W = mask.shape
    if H == 0 or W == 0 or n_regions <= 0 or (min_px <= 0 and alone_fix_px <= 0):
        return 0, 0
    n_st = is_marker.shape[0]
    uok = np.uint8(ok_code)
    rr, r0, r1, rg, row_start = _piece_runs(mask, region, uok, n_regions)
    n = rr.shape[0]
    root = _join_runs(rr, r0, r1, rg, row_start, H)
    size = np.zeros(n, np.int64)
    for j in range(n):
        size[root[j]] += r1[j] - r0[j] + 1
    # a root is its piece's first run (unions keep the smaller index): the body of each region
    # is its largest piece, the first in row order among equals
    body = np.full(n_regions, -1, np.int64)
    pieces = 0
    for j in range(n):
        if root[j] != j:
            continue
        g = rg[j]
        if body[g] < 0:
            body[g] = j
            pieces += not vouch[g]   # a linked region's body is a piece to the look
        else:
            pieces += 1
            if size[j] > size[body[g]]:
                body[g] = j
    if pieces == 0:
        return 0, 0
    # pixel classes for the continuity test: 1 reported outside every piece, 2 in a piece (a
    # linked region's body too) and the piece runs, grouped by piece
    cls = np.zeros((H, W), np.uint8)
    pr = np.empty(n, np.int64)
    n_piece_runs = 0
    for j in range(n):
        piece = root[j] != body[rg[j]] or not vouch[rg[j]]
        if piece:
            pr[n_piece_runs] = j
            n_piece_runs += 1
        c = np.uint8(2) if piece else np.uint8(1)
        for u in range(r0[j], r1[j] + 1):
            cls[rr[j], u] = c
    pr = pr[:n_piece_runs]
    pr = pr[np.argsort(root[pr], kind="mergesort")]
    # the pieces as ranges [first, end) of pr
    n_pieces = 0
    first = np.empty(n_piece_runs + 1, np.int64)
    for t in range(n_piece_runs):
        if t == 0 or root[pr[t]] != root[pr[t - 1]]:
            first[n_pieces] = t
            n_pieces += 1
    first[n_pieces] = n_piece_runs
    # a linked region's body that reported pixels outside every piece continue vouches, as they
    # do, for the pieces beside it (its index has support besides them); the others vouch for
    # no piece (nor do pieces, a linked region's as any other's)
    later = np.zeros(n_pieces, np.bool_)
    for p in range(n_pieces):
        s, e = first[p], first[p + 1]
        g = rg[pr[s]]
        later[p] = not vouch[g] and root[pr[s]] == body[g] and \
            not _runs_have_vote(pr, s, e, rr, r0, r1, cls, max_gap_px)
    for p in range(n_pieces):
        s, e = first[p], first[p + 1]
        g = rg[pr[s]]
        if not vouch[g] and root[pr[s]] == body[g] and not later[p]:
            _set_cls(pr, s, e, rr, r0, r1, cls, 1)
    # the pieces (not bodies), each tested as they all stand (a verdict waits for the loop's end
    # to change a class); then the bodies of linked regions that nothing outside every piece
    # continues, where a piece just masked continued them (the two stood on each other alone),
    # beside what stands then; the other linked bodies are kept, as linked (the pixels that
    # voted for them masked by other rules since)
    verdict = np.zeros(n_pieces, np.int64)
    n_a = 0
    n_b = 0
    for phase in range(2):
        for p in range(n_pieces):
            s, e = first[p], first[p + 1]
            is_body = root[pr[s]] == body[rg[pr[s]]]
            if (phase == 0 and is_body) or (phase == 1 and not later[p]):
                continue
            verdict[p] = _piece_verdict(pr, s, e, rr, r0, r1, stripe, labels, is_marker, min_px, alone_fix_px,
                                        cls, max_gap_px)
            if verdict[p] == 0:
                continue
            k = 0
            for t in range(s, e):
                j = pr[t]
                v = rr[j]
                for u in range(r0[j], r1[j] + 1):
                    mask[v, u] = np.uint8(code)
                    column[v, u] = np.nan
                    stripe[v, u] = -1
                    conf[v, u] = 0.0
                    k += 1
            if verdict[p] == 1:
                n_a += k
            else:
                n_b += k
        if phase == 0:
            if not later.any():
                break
            # the look: the pieces just masked as class 3
            for p in range(n_pieces):
                if verdict[p] != 0:
                    _set_cls(pr, first[p], first[p + 1], rr, r0, r1, cls, 3)
            for p in range(n_pieces):
                if later[p]:
                    later[p] = _runs_have_vote(pr, first[p], first[p + 1], rr, r0, r1, cls, max_gap_px, 3)
            for p in range(n_pieces):
                s, e = first[p], first[p + 1]
                if verdict[p] != 0:
                    _set_cls(pr, s, e, rr, r0, r1, cls, 0)         # masked: a gap
                elif vouch[rg[pr[s]]]:
                    _set_cls(pr, s, e, rr, r0, r1, cls, 1)         # kept: vouches for the bodies next
    return n_a, n_b


@njit(cache=True, nogil=True)
def _set_cls(pr, s, e, rr, r0, r1, cls, c):
    # the class of the piece runs pr[s:e]
    for t in range(s, e):
        j = pr[t]
        for u in range(r0[j], r1[j] + 1):
            cls[rr[j], u] = c


@njit(cache=True, nogil=True)
def _runs_have_vote(pr, s, e, rr, r0, r1, cls, max_gap_px, want=1):
    # whether pixels of class ``want`` continue one of the piece runs pr[s:e] (_has_vote)
    for t in range(s, e):
        j = pr[t]
        if _has_vote(cls, rr[j], r0[j], r1[j], max_gap_px, want):
            return True
    return False


@njit(cache=True, nogil=True)
def _piece_verdict(pr, s, e, rr, r0, r1, stripe, labels, is_marker, min_px, alone_fix_px, cls, max_gap_px):
    # piece_check's tests on the piece of runs pr[s:e]: 0 kept, 1 masked by its own markers (a),
    # 2 masked for nothing continuing it (b)
    n_st = is_marker.shape[0]
    s0 = n_st
    s1 = -1
    own = 0
    for t in range(s, e):
        j = pr[t]
        for u in range(r0[j], r1[j] + 1):
            st = stripe[rr[j], u]
            s0 = min(s0, st)
            s1 = max(s1, st)
            if 0 <= st < n_st and contradicts(labels[rr[j], u], is_marker[st]):
                own += 1
    contra = min_px > 0 and own >= min_px
    alone = alone_fix_px > 0 and not _runs_have_vote(pr, s, e, rr, r0, r1, cls, max_gap_px)
    if not (contra or alone) or s1 < 0:
        return 0
    span = s1 - s0 + 1
    n_c = np.zeros(span, np.int64)    # cyan pixels per stripe of the piece
    n_p = np.zeros(span, np.int64)    # green / blue pixels per stripe
    for t in range(s, e):
        j = pr[t]
        for u in range(r0[j], r1[j] + 1):
            lab = labels[rr[j], u]
            if lab == CYAN:
                n_c[stripe[rr[j], u] - s0] += 1
            elif lab == GREEN or lab == BLUE:
                n_p[stripe[rr[j], u] - s0] += 1
    best = np.iinfo(np.int64).max // 4
    # shifts keeping the piece's stripes no further than 2 beyond the pattern's ends (the
    # indexing's candidates), the colours' parity kept
    for shift in range(-s1 - 2, n_st + 2 - s0 + 1):
        if shift == 0 or shift % 2 != 0:
            continue
        mis = 0
        for jj in range(span):
            mis += contradicting_px(s0 + jj + shift, n_c[jj], n_p[jj], is_marker)
        best = min(best, mis)
    margin = best - own
    if contra and margin <= -min_px:
        return 1
    if alone and margin < alone_fix_px:
        return 2
    return 0


@njit(cache=True, nogil=True, error_model="numpy")
def jump_flags(mask, column, column_rel, region, reg_shift, reg_indexed, stripe_px, gap_rows, fit_rows, tol_px,
               ok_code, rim_code):
    """(H, W) bool: reported pixels where their region's projector column jumps along the
    stripes (down the image column), seen past the along-stripe blur; and (H,) int32, the flags
    per row.

    mask (H, W) uint8 reasons, column (H, W) float32 (projector px; NaN where masked),
    column_rel (H, W) float32 the columns relative to their region, region (H, W) int32,
    reg_shift (n_regions,) int64 and reg_indexed (n_regions,) bool the regions' offsets (stripes)
    and whether they are indexed, stripe_px the stripe width (px).  A pixel can be fitted when it
    is reported (its column) or masked ``rim_code`` in an indexed region (``column_rel + shift *
    stripe_px``: the rim rules mask the rows the blur may pull, but their columns still follow
    the surface, and at a depth edge they are often all there is below the line).  For a
    reported pixel (v, u) whose row neighbours are reported too, with ``fit_rows`` fitted pixels
    of its region at rows ``v - gap_rows - fit_rows + 1 .. v - gap_rows`` (above) and at
    ``v + gap_rows .. v + gap_rows + fit_rows - 1`` (below), a line is fitted (least squares) to
    each side's columns; the pixel is flagged when the two lines do not meet between the sides
    (rows ``v - gap_rows .. v + gap_rows``) and stay more than ``tol_px`` apart there.  A smooth
    surface's column is continuous: a kink (a crease, the stripes' lean changing) or a curve
    makes the lines meet between the sides; where two surfaces meet at a horizontal depth edge
    the column jumps by the two surfaces' disparity, which the unwrapping sees modulo two stripes
    when their stripes line up.  A row at a time, its columns in vectorisable loops (float32):
    ~0.3 ms a 640x480 frame."""
    H, W = mask.shape
    out = np.zeros((H, W), np.bool_)
    row_n = np.zeros(H, np.int32)
    L = fit_rows
    k = gap_rows
    if L < 2 or k < 0 or H < 2 * (k + L) - 1 or W < 3:
        return out, row_n
    xm = (L - 1) / 2.0
    sxx = 0.0
    for i in range(L):
        sxx += (i - xm) * (i - xm)
    inv_l = np.float32(1.0 / L)
    inv_s = np.float32(1.0 / sxx)
    xm32 = np.float32(xm)
    far = np.float32(xm + 2 * k)
    tol32 = np.float32(tol_px)
    uok = np.uint8(ok_code)
    urim = np.uint8(rim_code)
    n_reg = reg_shift.shape[0]
    # fcol: the column of every pixel a side may fit (NaN elsewhere); run[v, u]: such pixels of
    # one region ending at row v, counted up the column
    nan32 = np.float32(np.nan)
    # each region's offset in px, NaN where it is not indexed
    shw = np.full(n_reg, nan32, np.float32)
    for g in range(n_reg):
        if reg_indexed[g]:
            shw[g] = np.float32(reg_shift[g] * stripe_px)
    fcol = np.empty((H, W), np.float32)
    run = np.zeros((H, W), np.int16)
    for v in range(H):
        frow = fcol[v]
        mrow = mask[v]
        crow = column[v]
        rrow = column_rel[v]
        grow = region[v]
        for u in range(W):
            m = mrow[u]
            c = crow[u]
            frow[u] = c if m == uok else nan32
        for u in range(W):
            # (rarely taken: the rim rules' pixels, from their region's index)
            if mrow[u] == urim:
                g = grow[u]
                if 0 <= g < n_reg:
                    frow[u] = rrow[u] + shw[g]
        if v == 0:
            for u in range(W):
                c0 = frow[u]
                run[0, u] = np.int16(1) if c0 == c0 else np.int16(0)
            continue
        prow = fcol[v - 1]
        gprev = region[v - 1]
        rprev = run[v - 1]
        rcur = run[v]
        for u in range(W):
            c0 = frow[u]
            c1 = prow[u]
            fin = c0 == c0
            same = fin & (c1 == c1) & (grow[u] == gprev[u])
            prev = rprev[u]
            rcur[u] = np.int16(prev + 1) if same else (np.int16(1) if fin else np.int16(0))
    ma = np.empty(W, np.float32)
    ba = np.empty(W, np.float32)
    mb = np.empty(W, np.float32)
    bb = np.empty(W, np.float32)
    ok = np.zeros(W, np.bool_)
    for v in range(k + L - 1, H - k - L + 1):
        va = v - k           # the above side's last row
        vb = v + k + L - 1   # the below side's last row
        any_ok = False
        for u in range(1, W - 1):
            m = mask[v, u]
            ml = mask[v, u - 1]
            mr = mask[v, u + 1]
            g = region[v, u]
            o = (m == uok) & (ml == uok) & (mr == uok) & (run[va, u] >= L) & (run[vb, u] >= L) \
                & (region[va, u] == g) & (region[v + k, u] == g)
            ok[u] = o
            any_ok |= o
        if not any_ok:
            continue
        for u in range(W):
            ma[u] = np.float32(0.0)
            ba[u] = np.float32(0.0)
            mb[u] = np.float32(0.0)
            bb[u] = np.float32(0.0)
        for i in range(L):
            w = np.float32(i - xm)
            ra = fcol[v - k - L + 1 + i]
            rb = fcol[v + k + i]
            for u in range(W):
                ya = ra[u]
                yb = rb[u]
                ma[u] += ya
                ba[u] += w * ya
                mb[u] += yb
                bb[u] += w * yb
        orow = out[v]
        n = 0
        for u in range(1, W - 1):
            # both lines at the sides' inner rows v - k and v + k (above's centre row is
            # v - k - xm, below's v + k + xm)
            a_m = ma[u] * inv_l
            a_b = ba[u] * inv_s
            b_m = mb[u] * inv_l
            b_b = bb[u] * inv_s
            r0 = (a_m + a_b * xm32) - (b_m - b_b * far)
            r1 = (a_m + a_b * far) - (b_m - b_b * xm32)
            f = ok[u] & (r0 * r1 > 0) & (min(abs(r0), abs(r1)) > tol32)
            orow[u] = f
            n += f
        row_n[v] = n
    return out, row_n


@njit(cache=True, nogil=True)
def jump_band(mask, region, flags, row_n, min_cols, reach_px, ok_code):
    """(H, W) bool, the pixels a cut along a jump line takes out of the pieces, and their count.

    A flagged pixel (:func:`jump_flags`) counts when flagged pixels lie in at least ``min_cols``
    distinct columns within 4 px of its column (rows within 2 of its row): a line along the row,
    not one column's noise.  Its row's stretch of reported pixels of its region is cut from it to
    either end, or ``reach_px`` px when the end lies more than ``2 * reach_px`` px away.
    ``row_n`` (H,) the flags per row (rows without any are skipped)."""
    H, W = mask.shape
    band = np.zeros((H, W), np.bool_)
    uok = np.uint8(ok_code)
    n = 0
    for v in range(H):
        if row_n[v] == 0:
            continue
        for u in range(W):
            if not flags[v, u]:
                continue
            c = 0
            for du in range(-4, 5):
                q = u + du
                if q < 0 or q >= W:
                    continue
                for dv in range(-2, 3):
                    p = v + dv
                    if 0 <= p < H and flags[p, q]:
                        c += 1
                        break
            if c < min_cols:
                continue
            g = region[v, u]
            a = u
            while a > 0 and mask[v, a - 1] == uok and region[v, a - 1] == g:
                a -= 1
            b = u
            while b < W - 1 and mask[v, b + 1] == uok and region[v, b + 1] == g:
                b += 1
            if u - a > 2 * reach_px:
                a = u - reach_px
            if b - u > 2 * reach_px:
                b = u + reach_px
            for x in range(a, b + 1):
                if not band[v, x]:
                    band[v, x] = True
                    n += 1
    return band, n


@njit(cache=True, nogil=True)
def jump_pieces(mask, column, stripe, conf, failed, band, region, near_rows, ok_code, code, band_code):
    """Mask what the pieces cut along jump lines lost: ``failed`` (H, W) bool, reported pixels
    the piece tests masked with the cut (:func:`jump_band`'s ``band`` taken out) and not without
    it, joined into pieces as the piece tests join them (:func:`_piece_runs`, :func:`_join_runs`:
    one region's, along rows and columns; ``region`` (H, W) int32).  A piece with a cut pixel
    right above one of its pixels and one right below another hangs between two jump lines
    inside its surface (a face's eyelid, its lips) and is kept; the others are masked ``code``,
    and the band pixels of their region within ``near_rows`` rows and 1 column of them
    ``band_code`` (the rows the blur mixed).  mask, column, stripe, conf: updated in place
    (:func:`_unreport_row`).  Returns (piece pixels, band pixels) masked."""
    H, W = mask.shape
    n_reg = 0
    for v in range(H):
        for u in range(W):
            if failed[v, u]:
                n_reg = max(n_reg, region[v, u] + 1)
    if n_reg == 0:
        return 0, 0
    # what the cut lost as pieces: runs of one region joined along rows and columns, as the
    # piece tests join them
    rr, r0, r1, rg, row_start = _piece_runs(failed.view(np.uint8), region, 1, n_reg)
    n = rr.shape[0]
    root = _join_runs(rr, r0, r1, rg, row_start, H)
    up = np.zeros(n, np.bool_)
    down = np.zeros(n, np.bool_)
    for j in range(n):
        v = rr[j]
        t = root[j]
        for u in range(r0[j], r1[j] + 1):
            up[t] |= v > 0 and band[v - 1, u]
            down[t] |= v < H - 1 and band[v + 1, u]
    uok = np.uint8(ok_code)
    drop = np.zeros((H, W), np.bool_)
    for j in range(n):
        t = root[j]
        if up[t] and down[t]:
            continue
        v = rr[j]
        for u in range(r0[j], r1[j] + 1):
            drop[v, u] = mask[v, u] == uok
    n_piece = 0
    for v in range(H):
        n_piece += _unreport_row(drop[v], mask[v], column[v], stripe[v], conf[v], np.uint8(code))
    if n_piece == 0:
        return 0, 0
    n_band = 0
    hit = np.zeros(W, np.bool_)
    for v in range(H):
        for u in range(W):
            hit[u] = False
            if not band[v, u] or mask[v, u] != uok:
                continue
            g = region[v, u]
            for p in range(max(v - near_rows, 0), min(v + near_rows + 1, H)):
                for q in range(max(u - 1, 0), min(u + 2, W)):
                    if drop[p, q] and region[p, q] == g:
                        hit[u] = True
        n_band += _unreport_row(hit, mask[v], column[v], stripe[v], conf[v], np.uint8(band_code))
    return n_piece, n_band
