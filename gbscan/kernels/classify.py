"""Stages 1-3 of :mod:`gbscan.decode` (motion blur, colour balance, thresholding) as row
primitives shared by the staged whole-image path and the fused streaming pass
(:func:`stream_frame`), with the faint-run tests.

Part of :mod:`gbscan.kernels` (its docstring has the conventions)."""
from __future__ import annotations

import numpy as np
from numba import njit

from ._common import BLUE, CYAN, GREEN, NONE, run_starts


# -- decoder front end (stages 1-3): row primitives shared by the staged and the fused path -------
# Each primitive fixes the order of its floating-point operations, so a value computed by the
# staged functions (whole images, one stage after another) and by the fused streaming kernel
# (a few rows in ring buffers) is bit-identical.  No fastmath: it would let LLVM reorder them.
# What it takes for LLVM to vectorise these row loops (8 float32 lanes; measured 5-10x):
# ``error_model="numpy"`` (no zero-division branch), offsets as slices (``a = x[off:]; a[i]``,
# not ``x[i + off]``: an index that might be negative gets numba's wrap-around code), and
# scratch rows as separate arrays (not rows of one 2-D array, nor arrays swapped at run time).
# Next factor (measured per 640x480 frame, CPU ms of one thread, 1.2-1.4x): the loops are bound by
# loads and stores in L1/L2, not by memory -- the same two kernels on strips of 32 rows (0.6 MB
# working set) are no faster than on whole frames.  Streaming the blur through the classify pass
# in rings of rows (stream_frame; the colour balance from samples blurred alone first,
# balance_samples), with the min/max from quads below: stages 1-3 -12..17 % at 640x480 and
# 1280x1024 (decode's stage ms, interleaved runs, medians), and 17 bytes/px less workspace.  Per 640-px row with every input in L1
# (us; x480 = ms per frame): linearise 0.83, Gaussian 0.89 (2 channels), d + threshold 0.41,
# local min/max 0.68 (quads; 0.95 from pairs), their box means 1.3, raw maximum 0.3, per-pixel
# rule 1.5 (0.45 of it the gn/bn/contrast arithmetic with its 4 divisions, the rest the label and
# reason logic; float 0/1 masks instead of booleans were slower).  What paid: fewer passes per
# row (windows of 8..15: pair extrema / pair sums stored, the rest formed in registers; gauss_rows
# four terms per pass, two output rows per pass in blur_frame), the LUT's max loop apart from the
# gathers over a flat byte row, float32 codes in classify_row.  What did not: 13 taps in one
# pass, four output rows per Gaussian pass, int32 index gathers, the box sums inlined into
# classify_row (4x slower: not vectorised), classify_row split in two loops, column tiles for the
# Gaussian (non-contiguous slices).
_F0 = np.float32(0.0)
_F1 = np.float32(1.0)
_FHALF = np.float32(0.5)
_EPS_RATIO = np.float32(1e-6)
_EPS_RANGE = np.float32(1e-3)
_C0, _C1, _C2, _C3 = np.float32(0), np.float32(1), np.float32(2), np.float32(3)    # codes as floats
_C_NONE, _C_GREEN, _C_BLUE, _C_CYAN = (np.float32(NONE), np.float32(GREEN), np.float32(BLUE),
                                      np.float32(CYAN))


@njit(cache=True, nogil=True, error_model="numpy")
def reflect101(i, n):
    """OpenCV's ``BORDER_REFLECT_101`` index of ``i`` in ``0 .. n-1`` (n >= 2)."""
    if n == 1:
        return 0
    while i < 0 or i >= n:
        i = -i if i < 0 else 2 * (n - 1) - i
    return i


@njit(cache=True, nogil=True, error_model="numpy")
def gauss_rows(src, rows, kh, out):
    """One row of a vertical Gaussian: ``out[u] = kh[0] src[rows[r], u] + sum_j kh[j] (src[rows[r-j], u]
    + src[rows[r+j], u])``, ``r = kh.size - 1``; ``src`` (n, W) float32, ``rows`` (2r+1,) row numbers
    (border rows already reflected), ``kh`` (r+1,) float32 half kernel (centre first).  Summed in
    that order, ``((k0 x0 + k1 (a1 + b1)) + k2 (a2 + b2)) + ...``, up to four terms per pass over
    the row (``out`` is loaded and stored a third as often; same results as one term per pass)."""
    r = kh.size - 1
    W = out.size
    x0 = src[rows[r]]
    k0 = kh[0]
    if r == 0:
        for u in range(W):
            out[u] = k0 * x0[u]
        return
    a1 = src[rows[r - 1]]
    b1 = src[rows[r + 1]]
    k1 = kh[1]
    if r == 1:
        for u in range(W):
            out[u] = k0 * x0[u] + k1 * (a1[u] + b1[u])
        return
    a2 = src[rows[r - 2]]
    b2 = src[rows[r + 2]]
    k2 = kh[2]
    if r == 2:
        for u in range(W):
            out[u] = (k0 * x0[u] + k1 * (a1[u] + b1[u])) + k2 * (a2[u] + b2[u])
        return
    a3 = src[rows[r - 3]]
    b3 = src[rows[r + 3]]
    k3 = kh[3]
    for u in range(W):
        out[u] = ((k0 * x0[u] + k1 * (a1[u] + b1[u])) + k2 * (a2[u] + b2[u])) + k3 * (a3[u] + b3[u])
    j = 4
    while j + 2 <= r:
        a1 = src[rows[r - j]]
        b1 = src[rows[r + j]]
        a2 = src[rows[r - j - 1]]
        b2 = src[rows[r + j + 1]]
        a3 = src[rows[r - j - 2]]
        b3 = src[rows[r + j + 2]]
        k1 = kh[j]
        k2 = kh[j + 1]
        k3 = kh[j + 2]
        for u in range(W):
            out[u] = ((out[u] + k1 * (a1[u] + b1[u])) + k2 * (a2[u] + b2[u])) + k3 * (a3[u] + b3[u])
        j += 3
    if j + 1 == r:
        a1 = src[rows[r - j]]
        b1 = src[rows[r + j]]
        a2 = src[rows[r - j - 1]]
        b2 = src[rows[r + j + 1]]
        k1 = kh[j]
        k2 = kh[j + 1]
        for u in range(W):
            out[u] = (out[u] + k1 * (a1[u] + b1[u])) + k2 * (a2[u] + b2[u])
    elif j == r:
        a1 = src[rows[0]]
        b1 = src[rows[2 * r]]
        k1 = kh[r]
        for u in range(W):
            out[u] = out[u] + k1 * (a1[u] + b1[u])


@njit(cache=True, nogil=True, error_model="numpy")
def gauss_rows2(src, rows, kh, out0, out1):
    """:func:`gauss_rows` for two consecutive output rows y, y + 1 in the same passes (the same
    arithmetic for each), sharing the input rows they both read: ``rows`` (2r+2,) the row numbers
    of y - r .. y + r + 1 (reflected), r >= 3.  The vertical Gaussian is bound by loading input
    rows from L2 (13 rows of two channels do not stay in L1): 0.47 -> 0.37 ms at 640x480, r = 6."""
    r = kh.size - 1
    W = out0.size
    c = src[rows[r]]            # names: n<k> / p<k> the row k above / below y
    n1 = src[rows[r - 1]]
    p1 = src[rows[r + 1]]
    n2 = src[rows[r - 2]]
    p2 = src[rows[r + 2]]
    n3 = src[rows[r - 3]]
    p3 = src[rows[r + 3]]
    p4 = src[rows[r + 4]]
    k0 = kh[0]
    k1 = kh[1]
    k2 = kh[2]
    k3 = kh[3]
    for u in range(W):
        out0[u] = ((k0 * c[u] + k1 * (n1[u] + p1[u])) + k2 * (n2[u] + p2[u])) + k3 * (n3[u] + p3[u])
        out1[u] = ((k0 * p1[u] + k1 * (c[u] + p2[u])) + k2 * (n1[u] + p3[u])) + k3 * (n2[u] + p4[u])
    j = 4
    while j + 2 <= r:           # terms j, j+1, j+2 of both rows
        m0 = src[rows[r - j]]
        m1 = src[rows[r - j - 1]]
        m2 = src[rows[r - j - 2]]
        mp = src[rows[r - j + 1]]
        q0 = src[rows[r + j]]
        q1 = src[rows[r + j + 1]]
        q2 = src[rows[r + j + 2]]
        q3 = src[rows[r + j + 3]]
        ka = kh[j]
        kb = kh[j + 1]
        kc = kh[j + 2]
        for u in range(W):
            out0[u] = ((out0[u] + ka * (m0[u] + q0[u])) + kb * (m1[u] + q1[u])) + kc * (m2[u] + q2[u])
            out1[u] = ((out1[u] + ka * (mp[u] + q1[u])) + kb * (m0[u] + q2[u])) + kc * (m1[u] + q3[u])
        j += 3
    if j + 1 == r:
        m0 = src[rows[r - j]]
        m1 = src[rows[r - j - 1]]
        mp = src[rows[r - j + 1]]
        q0 = src[rows[r + j]]
        q1 = src[rows[r + j + 1]]
        q2 = src[rows[r + j + 2]]
        ka = kh[j]
        kb = kh[j + 1]
        for u in range(W):
            out0[u] = (out0[u] + ka * (m0[u] + q0[u])) + kb * (m1[u] + q1[u])
            out1[u] = (out1[u] + ka * (mp[u] + q1[u])) + kb * (m0[u] + q2[u])
    elif j == r:
        m0 = src[rows[0]]
        mp = src[rows[1]]
        q0 = src[rows[2 * r]]
        q1 = src[rows[2 * r + 1]]
        ka = kh[r]
        for u in range(W):
            out0[u] = out0[u] + ka * (m0[u] + q0[u])
            out1[u] = out1[u] + ka * (mp[u] + q1[u])


@njit(cache=True, nogil=True, error_model="numpy")
def ratio_row(g, b, sg, sb, d):
    """``d = (sg g - sb b) / max(sg g + sb b, 1e-6)`` along a row (float32)."""
    for u in range(d.size):
        x = g[u] * sg
        y = b[u] * sb
        d[u] = (x - y) / max(x + y, _EPS_RATIO)


@njit(cache=True, nogil=True, error_model="numpy")
def _ratio_update_row(g, b, sg, sb, d, old, o):
    # ratio_row into d, and in the same loop column_sums' update o = o + d - old (same arithmetic)
    for u in range(d.size):
        x = g[u] * sg
        y = b[u] * sb
        e = (x - y) / max(x + y, _EPS_RATIO)
        d[u] = e
        o[u] = o[u] + e - old[u]


@njit(cache=True, nogil=True, error_model="numpy")
def sum_rows(src, rows, out, off):
    """``out[off + u] = src[rows[0], u] + src[rows[1], u] + ...`` (float32, in that order)."""
    W = src.shape[1]
    o = out[off:off + W]     # slices, not ``out[off + u]``: an index that might be negative
    a = src[rows[0]]         # gets numba's wrap-around code, which stops LLVM vectorising
    for u in range(W):
        o[u] = a[u]
    for k in range(1, rows.size):
        a = src[rows[k]]
        for u in range(W):
            o[u] = o[u] + a[u]


@njit(cache=True, nogil=True, error_model="numpy")
def _box_8to15(p, w, a, scale, out):
    # box_row's partial sums for 8 <= w < 16 with only the pair sums stored (in a): the sums of
    # 4 and 8 samples are formed in registers, and those the bits of w name added lowest first
    # (a missing one as + 0 * sum: exact for finite sums; for w = 15 every factor is 1, so this is
    # box_row's arithmetic exactly).  2 passes instead of 8 (measured 4 rows: 0.69 -> 0.45 ms).
    n = p.size
    W = out.size
    for i in range(n - 1):
        a[i] = p[i] + p[i + 1]
    if w == 15:                     # every factor 1: without the multiplications (10 % faster)
        q1 = a[1:]
        q2 = a[3:]
        q3 = a[7:]
        for i in range(W):
            b = q2[i] + q2[i + 2]
            c = (q3[i] + q3[i + 2]) + (q3[i + 4] + q3[i + 6])
            out[i] = (((p[i] + q1[i]) + b) + c) * scale
        return
    f0 = _F1 if w & 1 else _F0
    f1 = _F1 if w & 2 else _F0
    f2 = _F1 if w & 4 else _F0
    k1 = w & 1
    k2 = k1 + (w & 2)
    k3 = k2 + (w & 4)
    q1 = a[k1:]
    q2 = a[k2:]
    q3 = a[k3:]
    for i in range(W):
        b = q2[i] + q2[i + 2]
        c = (q3[i] + q3[i + 2]) + (q3[i + 4] + q3[i + 6])
        out[i] = (((p[i] * f0 + q1[i] * f1) + b * f2) + c) * scale


@njit(cache=True, nogil=True, error_model="numpy")
def box_row(p, w, ta, tb, scale, out):
    """Sliding sum of ``w`` samples times ``scale``: ``out[i] = scale * sum(p[i : i + w])``.

    p : (W + w - 1,) float32 padded row; ta, tb : scratch of p's size (two distinct arrays);
    out : (W,).  Summed by doubling (partial sums over 1, 2, 4 ... samples, those named by the bits
    of ``w`` added lowest first), so every output has the same few-ulp rounding and every loop
    vectorises, unlike a running sum.  (Each loop names its arrays explicitly: LLVM does not
    vectorise loops over arrays chosen at run time.)  ``w = 15`` (the default windows): the same
    additions in two passes (:func:`_box_8to15`).
    """
    if w == 15:
        _box_8to15(p, w, ta, scale, out)
        return
    n = p.size
    W = out.size
    if w & 1:
        for i in range(W):
            out[i] = p[i]
    else:
        for i in range(W):
            out[i] = _F0
    off = w & 1
    span = 1
    m = n - 1
    for i in range(m):
        ta[i] = p[i] + p[i + 1]
    span = 2
    while True:
        if w & span:               # partial sums of `span` samples are in ta
            a = ta[off:]
            for i in range(W):
                out[i] = out[i] + a[i]
            off += span
        if 2 * span > w:
            break
        m -= span
        a = ta[span:]
        for i in range(m):
            tb[i] = ta[i] + a[i]
        span *= 2
        if w & span:               # ... in tb
            a = tb[off:]
            for i in range(W):
                out[i] = out[i] + a[i]
            off += span
        if 2 * span > w:
            break
        m -= span
        a = tb[span:]
        for i in range(m):
            ta[i] = tb[i] + a[i]
        span *= 2
    for i in range(W):
        out[i] = out[i] * scale


@njit(cache=True, nogil=True, error_model="numpy")
def _slide_min(p, w, ta, tb, out, off):
    # The ta/tb levels are written out rather than swapped in a loop, and min and max are two
    # functions rather than one with a flag: measured here, a swapped pair of scratch rows makes
    # LLVM give up vectorising (0.70 -> 1.24 us per 640-px row; helper functions 1.85 us).
    # 8 <= w < 16: the minimum of the 8 pairs that cover the window, in registers (min is exact
    # in any order: the same results in 2 passes instead of 4).
    n = p.size
    W = n - w + 1
    m = n - 1
    for i in range(m):
        ta[i] = min(p[i], p[i + 1])
    step = 2
    res = out[off:off + W]
    if 8 <= w < 16:
        q = ta[w - 8:]
        for i in range(W):
            res[i] = min(min(min(ta[i], ta[i + 2]), min(ta[i + 4], ta[i + 6])),
                         min(min(q[i], q[i + 2]), min(q[i + 4], q[i + 6])))
        return
    while True:                     # windows of `step` samples in ta
        if 2 * step > w:
            a = ta[w - step:]
            for i in range(W):
                res[i] = min(ta[i], a[i])
            return
        m -= step
        a = ta[step:]
        for i in range(m):
            tb[i] = min(ta[i], a[i])
        step *= 2
        if 2 * step > w:            # ... in tb
            a = tb[w - step:]
            for i in range(W):
                res[i] = min(tb[i], a[i])
            return
        m -= step
        a = tb[step:]
        for i in range(m):
            ta[i] = min(tb[i], a[i])
        step *= 2


@njit(cache=True, nogil=True, error_model="numpy")
def _slide_max(p, w, ta, tb, out, off):
    n = p.size
    W = n - w + 1
    m = n - 1
    for i in range(m):
        ta[i] = max(p[i], p[i + 1])
    step = 2
    res = out[off:off + W]
    if 8 <= w < 16:
        q = ta[w - 8:]
        for i in range(W):
            res[i] = max(max(max(ta[i], ta[i + 2]), max(ta[i + 4], ta[i + 6])),
                         max(max(q[i], q[i + 2]), max(q[i + 4], q[i + 6])))
        return
    while True:                     # windows of `step` samples in ta
        if 2 * step > w:
            a = ta[w - step:]
            for i in range(W):
                res[i] = max(ta[i], a[i])
            return
        m -= step
        a = ta[step:]
        for i in range(m):
            tb[i] = max(ta[i], a[i])
        step *= 2
        if 2 * step > w:            # ... in tb
            a = tb[w - step:]
            for i in range(W):
                res[i] = max(tb[i], a[i])
            return
        m -= step
        a = tb[step:]
        for i in range(m):
            ta[i] = max(tb[i], a[i])
        step *= 2


@njit(cache=True, nogil=True, error_model="numpy")
def minmax_row(p, w, ta, tb, lo, hi, off):
    """Sliding minimum and maximum of ``w`` samples: ``lo[off + i] = min(p[i : i + w])``, exact, by
    doubling (windows of 2, 4, 8 ... samples, then two overlapping ones).  p : (W + w - 1,) padded
    row; ta, tb : scratch of p's size (two distinct arrays)."""
    _slide_min(p, w, ta, tb, lo, off)
    _slide_max(p, w, ta, tb, hi, off)


@njit(cache=True, nogil=True, error_model="numpy")
def max_row(p, w, ta, tb, hi):
    """Sliding maximum of ``w`` samples: ``hi[i] = max(p[i : i + w])`` (see :func:`minmax_row`)."""
    _slide_max(p, w, ta, tb, hi, 0)


@njit(cache=True, nogil=True, error_model="numpy")
def pad_replicate(p, h, W):
    """Fill the ``h`` samples on each side of ``p[h : h + W]`` with its first / last sample."""
    a = p[h]
    b = p[h + W - 1]
    for k in range(h):
        p[k] = a
        p[h + W + k] = b


@njit(cache=True, nogil=True, error_model="numpy")
def pad_reflect101(p, h, W):
    """Fill the ``h`` samples on each side of ``p[h : h + W]`` by reflection about its end samples."""
    for k in range(1, h + 1):
        p[h - k] = p[h + reflect101(k, W)]
        p[h + W - 1 + k] = p[h + reflect101(W - 1 - k, W)]


@njit(cache=True, nogil=True, error_model="numpy")
def _narrow_max_row(x, n, P, M, ta, tb, out):
    # out = the box mean over n of the running maximum over n of x (both BORDER_REPLICATE), as
    # the wide envelope's maximum (_minmax_smooth_row) with the narrow window; P, M, ta, tb:
    # scratch of at least W + 2 (n // 2) samples
    W = x.size
    h = n // 2
    m = W + 2 * h
    p = P[:m]
    q = p[h:h + W]
    for u in range(W):
        q[u] = x[u]
    pad_replicate(p, h, W)
    _slide_max(p, n, ta, tb, M, h)
    pad_replicate(M[:m], h, W)
    box_row(M[:m], n, ta, tb, np.float32(1.0 / n), out)


@njit(cache=True, nogil=True, error_model="numpy")
def follow_envelope_row(g, b, n, P, M, ta, tb, ng, nb, lo_g, hi_g, lo_b, hi_b):
    """The envelope follows the pattern's brightness within a stripe period (``DecodeParams.
    envelope_follow_px``): where both channels' maxima over the narrow window ``n`` stay below
    the wide window's (a highlight, a brighter surface or the lit side of a shading gradient
    within its reach), the local ranges ``hi - lo`` of both channels shrink by the same factor
    ``k = min(1, max((ng - lo_g) / (hi_g - lo_g), (nb - lo_b) / (hi_b - lo_b)))``, ``ng, nb`` the
    narrow maxima (:func:`_narrow_max_row`).  The larger of the two ratios: a stripe wider than
    the narrow window keeps its own colour's maximum near the wide one, so k stays near 1 there;
    one common factor keeps the colour balance of the envelope.  Updates ``hi_g, hi_b`` in place
    (lo unchanged); ``ng, nb`` (W,) scratch, P, M, ta, tb of at least W + 2 (n // 2) samples."""
    _narrow_max_row(g, n, P, M, ta, tb, ng)
    _narrow_max_row(b, n, P, M, ta, tb, nb)
    for u in range(ng.size):
        lg = lo_g[u]
        lb = lo_b[u]
        rg = hi_g[u] - lg
        rb = hi_b[u] - lb
        kg = (ng[u] - lg) / max(rg, _EPS_RANGE)
        kb = (nb[u] - lb) / max(rb, _EPS_RANGE)
        k = min(max(kg, kb), _F1)
        hi_g[u] = lg + rg * k
        hi_b[u] = lb + rb * k


@njit(cache=True, nogil=True, error_model="numpy")
def classify_row(g, b, d, thr, lo_g, hi_g, lo_b, hi_b, raw_g, raw_b, raw_hi, raw_max, cyan_level, min_level,
                 raw_margin, min_contrast, dark_level, saturation_level, labels, reason, gn, bn, contrast):
    """Per-pixel rules of :func:`gbscan.decode.classify` along one row (branch-free, vectorises).

    Writes labels (NONE/GREEN/BLUE/CYAN), reason (0 ok, 1 dark, 2 saturated, 3 low contrast), gn, bn
    (channels normalised between their local min and max) and contrast.  The codes are chosen
    among float32 constants and the saturation test is a float32 comparison: every lane stays a
    32-bit float until the final store (int64 or uint8 intermediates cost packing instructions;
    measured 480 rows of 640: 0.77 -> 0.61 ms).
    """
    sat_level = np.float32(saturation_level)   # raw_max is 0..255: the comparison is exact
    neg_margin = -raw_margin
    for u in range(labels.size):
        lg = lo_g[u]
        lb = lo_b[u]
        hg = hi_g[u]
        hb = hi_b[u]
        rg = max(hg - lg, _EPS_RANGE)
        rb = max(hb - lb, _EPS_RANGE)
        ig = _F1 / rg
        ib = _F1 / rb
        x = (g[u] - lg) * ig
        y = (b[u] - lb) * ib
        gn[u] = x
        bn[u] = y
        c = min(rg / max(hg, _EPS_RANGE), rb / max(hb, _EPS_RANGE))
        contrast[u] = c
        hn = max(x, y)
        ln = min(x, y)
        cyan = (x > cyan_level) & (y > cyan_level)
        edge = (hn > cyan_level) & (ln > min_level)       # the rim of a cyan marker: neither colour
        gt = d[u] > thr[u]                                 # GREEN where d above its threshold
        diff_raw = (raw_g[u] - lg) * ig - (raw_b[u] - lb) * ib
        # a green (blue) pixel whose unblurred colour says clearly blue (green)
        wrong = (diff_raw < neg_margin) if gt else (diff_raw > raw_margin)
        low = (c < min_contrast) | (wrong & ~(cyan | edge))
        mod = max(rg, rb)
        dark = (mod < dark_level) | (hn < min_level) | (raw_hi[u] - min(lg, lb) < _FHALF * mod)
        sat = np.float32(raw_max[u]) >= sat_level
        lab = _C_CYAN if cyan else (_C_NONE if edge else (_C_GREEN if gt else _C_BLUE))
        r = _C2 if sat else (_C1 if dark else (_C3 if low else _C0))
        lab = _C_NONE if (sat | dark | low) else lab
        labels[u] = np.uint8(np.int32(lab))
        reason[u] = np.uint8(np.int32(r))


@njit(cache=True, nogil=True, error_model="numpy")
def _peak_sep(gn, bn, a, b):
    # largest |gn - bn| over pixels a .. b-1
    peak = np.float32(0.0)
    for x in range(a, b):
        peak = max(peak, abs(gn[x] - bn[x]))
    return peak


@njit(cache=True, nogil=True, error_model="numpy")
def _run_mean(x, a, b):
    # mean of x[a:b] (float64 sum)
    acc = 0.0
    for i in range(a, b):
        acc += x[i]
    return acc / (b - a)


@njit(cache=True, nogil=True, error_model="numpy")
def _swing_fails(labels, gn, bn, g, b, rs, nr, k, step, end_gap, min_swing, min_sep):
    # run k (green or blue) against the next run inward (k + step; across a gap shorter than
    # end_gap): False where there is no such run of the other colour that is itself no faint run
    # (peak separation min_sep: the mixed pixels beside a marker, X Y C X, are no reference);
    # else True where the run's own colour swings less than min_swing times the other colour
    # does.  Swings are relative (m = (x_hi - x_lo) / (x_hi + x_lo) of the two runs' means), so no
    # colour balance is needed.
    j = k + step
    if j < 0 or j >= nr:
        return False
    if labels[rs[j]] == NONE:
        if rs[j + 1] - rs[j] >= end_gap:
            return False
        j += step
        if j < 0 or j >= nr:
            return False
    lab = labels[rs[k]]
    other = labels[rs[j]]
    if not ((lab == GREEN and other == BLUE) or (lab == BLUE and other == GREEN)):
        return False
    if _peak_sep(gn, bn, rs[j], rs[j + 1]) < min_sep:
        return False
    gk = _run_mean(g, rs[k], rs[k + 1])
    gj = _run_mean(g, rs[j], rs[j + 1])
    bk = _run_mean(b, rs[k], rs[k + 1])
    bj = _run_mean(b, rs[j], rs[j + 1])
    if lab == GREEN:
        own = (gk - gj) / max(gk + gj, 1e-6)
        oth = (bj - bk) / max(bj + bk, 1e-6)
    else:
        own = (bk - bj) / max(bk + bj, 1e-6)
        oth = (gj - gk) / max(gj + gk, 1e-6)
    return oth > 0 and own < min_swing * oth


@njit(cache=True, nogil=True, error_model="numpy")
def _faint_behind(labels, gn, bn, rs, nr, k, step, end_gap, min_sep):
    # whether the first green or blue run of more than one pixel inward of run k (k + step, ...;
    # through gaps shorter than end_gap and one-pixel runs) is a faint one (peak separation below
    # min_sep): a cyan run at a stretch's end in front of it is no marker but room light with both
    # channels up
    j = k + step
    while 0 <= j < nr:
        lab = labels[rs[j]]
        n = rs[j + 1] - rs[j]
        if lab == NONE:
            if n >= end_gap:
                return False
        elif lab == GREEN or lab == BLUE:
            if n > 1:
                return _peak_sep(gn, bn, rs[j], rs[j + 1]) < min_sep
        else:
            return False
        j += step
    return False


#: faint_runs_row's swing test looks only at runs whose peak separation is below this many times
#: ``min_sep`` (a run that separates the channels clearly is a stripe, whatever its swing)
SWING_SEP = 2.0


@njit(cache=True, nogil=True, error_model="numpy")
def faint_runs_row(labels, reason, gn, bn, g, b, min_sep, min_swing, end_gap):
    """Peel runs that are no stripes off the ends of a row's stretches, in place (labels, reason
    (W,) uint8; gn, bn (W,) float32 from :func:`classify_row`; g, b (W,) float32 the blurred
    linear channels).  ``min_sep`` 0 and ``min_swing`` 0 disable the two tests.

    A green or blue run at an end of its stretch -- the row's border or at least ``end_gap``
    unlabelled pixels beyond it (a gap the unwrapping does not bridge) -- is unlabelled (labels
    NONE, reason 3: low contrast) when

    * *faint*: no pixel separates the two normalised channels by ``min_sep`` (``max |gn - bn| <
      min_sep``; gn, bn are normalised between their local min and max, so a stripe's centre
      reaches ``|gn - bn|`` near 1 however faint the stripes are), or
    * *one-sided*: against the next run inward (the other colour), its own colour swings less than
      ``min_swing`` times the other one: a green stripe is greener *and* less blue than the blue
      stripe beside it, light without the pattern is only less blue (or only less green).

    Then the run it uncovers is looked at the same way, from both ends; a one-pixel run at an end
    (the mixed pixel of the dark and a stripe) keeps the end going.  Such runs are ambient light
    with a colour cast, which the local threshold splits into "green" and "blue", beside stripes
    that fade out at a projector terminator, where the local windows still see the stripes (see
    ``DecodeParams.min_run_separation``).  Runs inside a stretch stay (they carry the row's count
    across a dim patch); cyan runs stop the peeling (a marker lights both channels)."""
    if labels.size > 0:
        _faint_runs_row(labels, reason, gn, bn, g, b, min_sep, min_swing, end_gap, np.empty(labels.size + 1, np.int32))


@njit(cache=True, nogil=True, error_model="numpy")
def _faint_runs_row(labels, reason, gn, bn, g, b, min_sep, min_swing, end_gap, rs):
    # faint_runs_row with the run starts in scratch rs ((W + 1,) int32, W >= 1: reused across rows)
    if min_sep <= 0 and min_swing <= 0:
        return
    W = labels.size
    top = labels[0]
    for u in range(W):                # a row without labels has nothing to peel (vectorised test)
        top = max(top, labels[u])
    if top == NONE:
        return
    nr = run_starts(labels, rs)       # then the runs from each end of the row
    for direction in range(2):
        none_len = end_gap            # the row's border is an end
        step = 1 if direction == 0 else -1
        for i in range(nr):
            k = i if direction == 0 else nr - 1 - i
            a = rs[k]
            e = rs[k + 1]
            lab = labels[a]           # (re-read: the first direction may have unlabelled the run)
            if lab == NONE:
                none_len += e - a
                continue
            peel = False
            if none_len >= end_gap:      # at an end of the stretch
                if lab == GREEN or lab == BLUE:
                    peak = _peak_sep(gn, bn, a, e)
                    peel = peak < min_sep or (
                        min_swing > 0 and e - a > 1 and peak < SWING_SEP * min_sep and
                        _swing_fails(labels, gn, bn, g, b, rs, nr, k, step, end_gap, min_swing, min_sep))
                    if not peel and e - a == 1:
                        none_len += 1     # one mixed pixel of the dark and the first run: still the end
                        continue
                elif lab == CYAN and min_sep > 0:
                    # light with both channels up (a cool cast) in front of faint runs: no marker
                    peel = _faint_behind(labels, gn, bn, rs, nr, k, step, end_gap, min_sep)
            if peel:
                for x in range(a, e):
                    labels[x] = np.uint8(NONE)
                    reason[x] = np.uint8(3)
                none_len += e - a
            else:
                none_len = 0


@njit(cache=True, nogil=True, error_model="numpy")
def lit_means(g, b, bright_level):
    """Means of ``g`` and ``b`` (2-D float32) over the samples where ``max(g, b) > bright_level``
    (over all samples when fewer than 16 are that bright), summed in float64 in row-major order.
    Returns ``(mean_g, mean_b, n_bright)``."""
    # the bright sums first; the plain means (a second pass) only when too few are bright.  The
    # sums with one add chain each (float64 adds in order are bound by their latency: fewer chains)
    sg = 0.0
    sb = 0.0
    n = 0
    H, W = g.shape
    for v in range(H):
        for u in range(W):
            x = g[v, u]
            y = b[v, u]
            if max(x, y) > bright_level:
                sg += x
                sb += y
                n += 1
    if n >= 16:
        return sg / n, sb / n, n
    ag = 0.0
    ab = 0.0
    for v in range(H):
        for u in range(W):
            ag += g[v, u]
            ab += b[v, u]
    return ag / max(H * W, 1), ab / max(H * W, 1), n


@njit(cache=True, nogil=True, error_model="numpy")
def gauss_image(x, kh):
    """Vertical Gaussian of (H, W) float32 ``x`` (``BORDER_REFLECT_101``), row by row with
    :func:`gauss_rows`; ``kh`` (r+1,) float32 half kernel.  Returns (H, W) float32."""
    H, W = x.shape
    r = kh.size - 1
    out = np.empty((H, W), np.float32)
    rows = np.empty(2 * r + 1, np.int64)
    for v in range(H):
        for j in range(2 * r + 1):
            rows[j] = reflect101(v - r + j, H)
        gauss_rows(x, rows, kh, out[v])
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def column_sums(src, v, H, w, mod, rows, P):
    """Sum of the ``w`` (odd) rows around row ``v`` of an H-row image (``BORDER_REFLECT_101``)
    into ``P[w//2 : w//2 + W]``, where image row ``y`` is ``src[y % mod]`` (``mod = H``: the whole
    image; smaller: a ring buffer holding rows ``v - w//2 - 1 .. v + w//2``).  Rows whose window
    crosses the border are summed afresh (:func:`sum_rows`); the others update the previous
    row's sums: ``+ new row - old row`` (call for consecutive ``v``)."""
    t = w // 2
    W = src.shape[1]
    if v - t - 1 < 0 or v + t >= H:
        for k in range(w):
            rows[k] = reflect101(v - t + k, H) % mod
        sum_rows(src, rows[:w], P, t)
        return
    o = P[t:t + W]
    a = src[(v + t) % mod]
    b = src[(v - t - 1) % mod]
    for u in range(W):
        o[u] = o[u] + a[u] - b[u]


@njit(cache=True, nogil=True, error_model="numpy")
def _box_image_row(x, v, w, rows, P, ta, tb, scale, out):
    # one output row of the w x w box mean of x (BORDER_REFLECT_101 both ways); rows in order
    H, W = x.shape
    t = w // 2
    column_sums(x, v, H, w, H, rows, P)
    pad_reflect101(P, t, W)
    box_row(P, w, ta, tb, scale, out)


@njit(cache=True, nogil=True, error_model="numpy")
def box_image(x, w):
    """``w`` x ``w`` box mean of (H, W) float32 ``x`` (odd ``w``, ``BORDER_REFLECT_101``).
    Columns of ``w`` rows are summed first (:func:`column_sums`), then :func:`box_row` along the row."""
    H, W = x.shape
    t = w // 2
    out = np.empty((H, W), np.float32)
    rows = np.empty(w, np.int64)
    P = np.empty(W + 2 * t, np.float32)
    ta = np.empty(W + 2 * t, np.float32)
    tb = np.empty(W + 2 * t, np.float32)
    scale = np.float32(1.0 / (w * w))
    for v in range(H):
        _box_image_row(x, v, w, rows, P, ta, tb, scale, out[v])
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _minmax_smooth_row(x, w, P, LO, HI, ta, tb, scale, lo, hi):
    # horizontal running min/max over w (BORDER_REPLICATE), each then box-smoothed over w
    W = x.size
    h = w // 2
    p = P[h:h + W]
    for u in range(W):
        p[u] = x[u]
    pad_replicate(P, h, W)
    minmax_row(P, w, ta, tb, LO, HI, h)
    pad_replicate(LO, h, W)
    pad_replicate(HI, h, W)
    box_row(LO, w, ta, tb, scale, lo)
    box_row(HI, w, ta, tb, scale, hi)


@njit(cache=True, nogil=True, error_model="numpy")
def _minmax4_last8(a0, a1, a2, a3, w, r0, r1, r2, r3):
    # 8 <= w < 16: r[i] = min (a0, a2) / max (a1, a3) of the 8 pair extrema a*[i + 2k], a*[i + w - 8 + 2k]
    # (k < 4), which cover the window of w samples starting at i; (W,) outputs
    W = r0.size
    e = w - 8
    q = a0[e:]
    for i in range(W):
        r0[i] = min(min(min(a0[i], a0[i + 2]), min(a0[i + 4], a0[i + 6])),
                    min(min(q[i], q[i + 2]), min(q[i + 4], q[i + 6])))
    q = a1[e:]
    for i in range(W):
        r1[i] = max(max(max(a1[i], a1[i + 2]), max(a1[i + 4], a1[i + 6])),
                    max(max(q[i], q[i + 2]), max(q[i + 4], q[i + 6])))
    q = a2[e:]
    for i in range(W):
        r2[i] = min(min(min(a2[i], a2[i + 2]), min(a2[i + 4], a2[i + 6])),
                    min(min(q[i], q[i + 2]), min(q[i + 4], q[i + 6])))
    q = a3[e:]
    for i in range(W):
        r3[i] = max(max(max(a3[i], a3[i + 2]), max(a3[i + 4], a3[i + 6])),
                    max(max(q[i], q[i + 2]), max(q[i + 4], q[i + 6])))


@njit(cache=True, nogil=True, error_model="numpy")
def _quad_minmax2(g, b, h, q0, q1, q2, q3):
    # extrema of every 4 consecutive samples of the rows g, b (W,) padded by h samples each side
    # (BORDER_REPLICATE), without forming the padded rows: q0/q1 min/max of g, q2/q3 of b at
    # j < W + 2h - 3 (samples j .. j+3 of the padded row).  With _minmax4_from_quads: windows of
    # 8..16 from 4 quads (min/max are exact in any order), 12 loads per pixel and channel pair
    # instead of 18 from the pairs (measured 640-px rows: 0.95 -> 0.68 us).
    W = g.size
    m = W - 3
    Q0, Q1, Q2, Q3 = q0[h:h + m], q1[h:h + m], q2[h:h + m], q3[h:h + m]
    g1, g2, g3 = g[1:], g[2:], g[3:]
    b1, b2, b3 = b[1:], b[2:], b[3:]
    for u in range(m):
        x0 = g[u]
        x1 = g1[u]
        x2 = g2[u]
        x3 = g3[u]
        Q0[u] = min(min(x0, x1), min(x2, x3))
        Q1[u] = max(max(x0, x1), max(x2, x3))
        x0 = b[u]
        x1 = b1[u]
        x2 = b2[u]
        x3 = b3[u]
        Q2[u] = min(min(x0, x1), min(x2, x3))
        Q3[u] = max(max(x0, x1), max(x2, x3))
    for k in range(2 * h):      # quads reaching into the padding: samples clamped to the row
        j = k if k < h else m + k
        s = min(max(j - h, 0), W - 1)
        lg = hg = g[s]
        lb = hb = b[s]
        for i in range(1, 4):
            s = min(max(j + i - h, 0), W - 1)
            lg = min(lg, g[s])
            hg = max(hg, g[s])
            lb = min(lb, b[s])
            hb = max(hb, b[s])
        q0[j] = lg
        q1[j] = hg
        q2[j] = lb
        q3[j] = hb


@njit(cache=True, nogil=True, error_model="numpy")
def _minmax4_from_quads(q0, q1, q2, q3, w, r0, r1, r2, r3):
    # 8 <= w <= 16: r[i] = min (q0, q2) / max (q1, q3) of the quads at i, i + 4, i + w - 8,
    # i + w - 4, which cover the window of w samples starting at i; (W,) outputs
    W = r0.size
    e = w - 8
    a, c, d = q0[4:], q0[e:], q0[e + 4:]
    for i in range(W):
        r0[i] = min(min(q0[i], a[i]), min(c[i], d[i]))
    a, c, d = q1[4:], q1[e:], q1[e + 4:]
    for i in range(W):
        r1[i] = max(max(q1[i], a[i]), max(c[i], d[i]))
    a, c, d = q2[4:], q2[e:], q2[e + 4:]
    for i in range(W):
        r2[i] = min(min(q2[i], a[i]), min(c[i], d[i]))
    a, c, d = q3[4:], q3[e:], q3[e + 4:]
    for i in range(W):
        r3[i] = max(max(q3[i], a[i]), max(c[i], d[i]))


@njit(cache=True, nogil=True, error_model="numpy")
def _slide_minmax2(pg, pb, w, a0, a1, a2, a3, b0, b1, b2, b3, lo_g, hi_g, lo_b, hi_b, off):
    # _slide_min/_slide_max of two channels in the same loops (same results): windows of
    # 2, 4, 8 ... samples ping-pong between the a* and b* scratch rows
    n = pg.size
    W = n - w + 1
    m = n - 1
    for i in range(m):
        x = pg[i]
        y = pg[i + 1]
        a0[i] = min(x, y)
        a1[i] = max(x, y)
        x = pb[i]
        y = pb[i + 1]
        a2[i] = min(x, y)
        a3[i] = max(x, y)
    if 8 <= w < 16:     # the 8 pairs covering the window in registers, as in _slide_min
        _minmax4_last8(a0, a1, a2, a3, w, lo_g[off:off + W], hi_g[off:off + W], lo_b[off:off + W],
                       hi_b[off:off + W])
        return
    step = 2
    while True:
        if 2 * step > w:
            o = w - step
            q0, q1, q2, q3 = a0[o:], a1[o:], a2[o:], a3[o:]
            r0, r1, r2, r3 = lo_g[off:off + W], hi_g[off:off + W], lo_b[off:off + W], hi_b[off:off + W]
            for i in range(W):
                r0[i] = min(a0[i], q0[i])
                r1[i] = max(a1[i], q1[i])
                r2[i] = min(a2[i], q2[i])
                r3[i] = max(a3[i], q3[i])
            return
        m -= step
        q0, q1, q2, q3 = a0[step:], a1[step:], a2[step:], a3[step:]
        for i in range(m):
            b0[i] = min(a0[i], q0[i])
            b1[i] = max(a1[i], q1[i])
            b2[i] = min(a2[i], q2[i])
            b3[i] = max(a3[i], q3[i])
        step *= 2
        if 2 * step > w:
            o = w - step
            q0, q1, q2, q3 = b0[o:], b1[o:], b2[o:], b3[o:]
            r0, r1, r2, r3 = lo_g[off:off + W], hi_g[off:off + W], lo_b[off:off + W], hi_b[off:off + W]
            for i in range(W):
                r0[i] = min(b0[i], q0[i])
                r1[i] = max(b1[i], q1[i])
                r2[i] = min(b2[i], q2[i])
                r3[i] = max(b3[i], q3[i])
            return
        m -= step
        q0, q1, q2, q3 = b0[step:], b1[step:], b2[step:], b3[step:]
        for i in range(m):
            a0[i] = min(b0[i], q0[i])
            a1[i] = max(b1[i], q1[i])
            a2[i] = min(b2[i], q2[i])
            a3[i] = max(b3[i], q3[i])
        step *= 2


@njit(cache=True, nogil=True, error_model="numpy")
def _box4_8to15(p0, p1, p2, p3, w, a, scale, o0, o1, o2, o3):
    # _box4 for 8 <= w < 16 (the default window 15): _box_8to15 on each row in turn (the
    # additions of box_row in its order, so the same results; one scratch row, 2 passes per row)
    _box_8to15(p0, w, a, scale, o0)
    _box_8to15(p1, w, a, scale, o1)
    _box_8to15(p2, w, a, scale, o2)
    _box_8to15(p3, w, a, scale, o3)


@njit(cache=True, nogil=True, error_model="numpy")
def _box4(p0, p1, p2, p3, w, a0, a1, a2, a3, b0, b1, b2, b3, scale, o0, o1, o2, o3):
    # box_row of four padded rows in the same loops (same arithmetic, same results)
    n = p0.size
    W = o0.size
    if w & 1:
        for i in range(W):
            o0[i] = p0[i]
            o1[i] = p1[i]
            o2[i] = p2[i]
            o3[i] = p3[i]
    else:
        for i in range(W):
            o0[i] = _F0
            o1[i] = _F0
            o2[i] = _F0
            o3[i] = _F0
    off = w & 1
    m = n - 1
    for i in range(m):
        a0[i] = p0[i] + p0[i + 1]
        a1[i] = p1[i] + p1[i + 1]
        a2[i] = p2[i] + p2[i + 1]
        a3[i] = p3[i] + p3[i + 1]
    span = 2
    while True:
        if w & span:
            q0, q1, q2, q3 = a0[off:], a1[off:], a2[off:], a3[off:]
            for i in range(W):
                o0[i] = o0[i] + q0[i]
                o1[i] = o1[i] + q1[i]
                o2[i] = o2[i] + q2[i]
                o3[i] = o3[i] + q3[i]
            off += span
        if 2 * span > w:
            break
        m -= span
        q0, q1, q2, q3 = a0[span:], a1[span:], a2[span:], a3[span:]
        for i in range(m):
            b0[i] = a0[i] + q0[i]
            b1[i] = a1[i] + q1[i]
            b2[i] = a2[i] + q2[i]
            b3[i] = a3[i] + q3[i]
        span *= 2
        if w & span:
            q0, q1, q2, q3 = b0[off:], b1[off:], b2[off:], b3[off:]
            for i in range(W):
                o0[i] = o0[i] + q0[i]
                o1[i] = o1[i] + q1[i]
                o2[i] = o2[i] + q2[i]
                o3[i] = o3[i] + q3[i]
            off += span
        if 2 * span > w:
            break
        m -= span
        q0, q1, q2, q3 = b0[span:], b1[span:], b2[span:], b3[span:]
        for i in range(m):
            a0[i] = b0[i] + q0[i]
            a1[i] = b1[i] + q1[i]
            a2[i] = b2[i] + q2[i]
            a3[i] = b3[i] + q3[i]
        span *= 2
    for i in range(W):
        o0[i] = o0[i] * scale
        o1[i] = o1[i] * scale
        o2[i] = o2[i] * scale
        o3[i] = o3[i] * scale


@njit(cache=True, nogil=True, error_model="numpy")
def local_minmax_image(x, w):
    """Horizontal running min and max of (H, W) float32 ``x`` over ``w`` (odd) samples, each then
    smoothed by a box of the same width (both ``BORDER_REPLICATE``).  Returns (lo, hi) float32."""
    H, W = x.shape
    n = W + 2 * (w // 2)
    P = np.empty(n, np.float32)
    LO = np.empty(n, np.float32)
    HI = np.empty(n, np.float32)
    ta = np.empty(n, np.float32)
    tb = np.empty(n, np.float32)
    lo = np.empty((H, W), np.float32)
    hi = np.empty((H, W), np.float32)
    scale = np.float32(1.0 / w)
    for v in range(H):
        _minmax_smooth_row(x[v], w, P, LO, HI, ta, tb, scale, lo[v], hi[v])
    return lo, hi


@njit(cache=True, nogil=True, error_model="numpy")
def _quad_max2(x, y, h, q):
    # q[j] = max(P[j .. j+3]) for the row P = max(x, y) padded by h samples each side
    # (BORDER_REPLICATE), j < W + 2h - 3, without forming P
    W = x.size
    m = W - 3
    Q = q[h:h + m]
    x1, x2, x3 = x[1:], x[2:], x[3:]
    y1, y2, y3 = y[1:], y[2:], y[3:]
    for u in range(m):
        Q[u] = max(max(max(x[u], y[u]), max(x1[u], y1[u])), max(max(x2[u], y2[u]), max(x3[u], y3[u])))
    for k in range(2 * h):
        j = k if k < h else m + k
        s = min(max(j - h, 0), W - 1)
        a = max(x[s], y[s])
        for i in range(1, 4):
            s = min(max(j + i - h, 0), W - 1)
            a = max(a, max(x[s], y[s]))
        q[j] = a


@njit(cache=True, nogil=True, error_model="numpy")
def _raw_hi_row(raw_g, raw_b, w, P, ta, tb, out):
    # running max over w (BORDER_REPLICATE) of the brighter raw channel
    W = out.size
    h = w // 2
    if 8 <= w < 16:
        # the maxima of 4 samples straight from the two rows (no padded copy), then the window
        # from 4 of them (as _minmax4_from_quads)
        _quad_max2(raw_g, raw_b, h, ta)
        e = w - 8
        a, c, d = ta[4:], ta[e:], ta[e + 4:]
        for i in range(W):
            out[i] = max(max(ta[i], a[i]), max(c[i], d[i]))
        return
    p = P[h:h + W]
    for u in range(W):
        p[u] = max(raw_g[u], raw_b[u])
    pad_replicate(P, h, W)
    max_row(P, w, ta, tb, out)


@njit(cache=True, nogil=True, error_model="numpy")
def classify_image(g, b, gbal, bbal, raw_g, raw_b, raw_max, thr_w, norm_w, cyan_level, min_level, raw_margin,
                   min_contrast, dark_level, saturation_level, min_run_sep, min_run_swing, run_end_gap, follow_w):
    """Stage 3 on whole images (the reference path of :func:`classify_frame`; see
    :func:`gbscan.decode.classify`).  g, b : blurred linear channels; gbal, bbal : balanced;
    raw_g, raw_b : linear before blurring; raw_max : uint8 max of raw green and blue (all (H, W)).
    thr_w : odd local threshold window (0: global).  follow_w : odd narrow window of
    :func:`follow_envelope_row` (0: the wide envelope alone).  Returns labels, reason, d, thr, gn,
    bn, contrast.
    """
    H, W = g.shape
    d = np.empty((H, W), np.float32)
    one = np.float32(1.0)
    for v in range(H):
        ratio_row(gbal[v], bbal[v], one, one, d[v])
    thr = box_image(d, thr_w) if thr_w > 0 else np.zeros((H, W), np.float32)
    lo_g, hi_g = local_minmax_image(g, norm_w)
    lo_b, hi_b = local_minmax_image(b, norm_w)
    labels = np.empty((H, W), np.uint8)
    reason = np.empty((H, W), np.uint8)
    gn = np.empty((H, W), np.float32)
    bn = np.empty((H, W), np.float32)
    contrast = np.empty((H, W), np.float32)
    n = W + 2 * (norm_w // 2)
    P = np.empty(n, np.float32)
    ta = np.empty(n, np.float32)
    tb = np.empty(n, np.float32)
    raw_hi = np.empty(W, np.float32)
    nf = W + 2 * (follow_w // 2)
    Pf = np.empty(nf, np.float32)
    Mf = np.empty(nf, np.float32)
    fa = np.empty(nf, np.float32)
    fb = np.empty(nf, np.float32)
    ng = np.empty(W, np.float32)
    nb = np.empty(W, np.float32)
    for v in range(H):
        if follow_w > 0:
            follow_envelope_row(g[v], b[v], follow_w, Pf, Mf, fa, fb, ng, nb, lo_g[v], hi_g[v], lo_b[v], hi_b[v])
        _raw_hi_row(raw_g[v], raw_b[v], norm_w, P, ta, tb, raw_hi)
        classify_row(g[v], b[v], d[v], thr[v], lo_g[v], hi_g[v], lo_b[v], hi_b[v], raw_g[v], raw_b[v], raw_hi,
                     raw_max[v], cyan_level, min_level, raw_margin, min_contrast, dark_level, saturation_level,
                     labels[v], reason[v], gn[v], bn[v], contrast[v])
        faint_runs_row(labels[v], reason[v], gn[v], bn[v], g[v], b[v], min_run_sep, min_run_swing, run_end_gap)
    return labels, reason, d, thr, gn, bn, contrast


@njit(cache=True, nogil=True, error_model="numpy")
def blur_frame(img, lut, kh, Lg, Lb, rmax, Bg, Bb):
    """Stages "input" and 1 of the fast path: linearise green and blue of an RGB uint8 frame with
    ``lut`` into ``Lg, Lb`` (and their raw maximum into ``rmax`` (H, W) uint8), then blur them
    vertically (:func:`gauss_rows`, ``BORDER_REFLECT_101``) into ``Bg, Bb`` ((H, W) float32),
    row by row, each row as soon as the Gaussian's support is linearised (still in cache).
    ``img`` must be C-contiguous (as :func:`gbscan.decode.validate_image` returns it).
    Returns the largest raw green or blue value (0: a black frame)."""
    H, W = img.shape[0], img.shape[1]
    r = kh.size - 1
    rows = np.empty(2 * r + 2, np.int64)
    top = np.uint8(0)
    loaded = 0
    flat = img.reshape(H, 3 * W)    # rows of bytes (see _linear_row)
    for y in range(0, H, 2):
        while loaded <= min(H - 1, y + 1 + r):
            top = _linear_row(flat[loaded], lut, Lg[loaded], Lb[loaded], rmax[loaded], top)
            loaded += 1
        for j in range(2 * r + 2):
            rows[j] = reflect101(y - r + j, H)
        if y + 1 < H and r >= 3:    # two output rows at a time: they share 2r of their input rows
            gauss_rows2(Lg, rows, kh, Bg[y], Bg[y + 1])
            gauss_rows2(Lb, rows, kh, Bb[y], Bb[y + 1])
            continue
        gauss_rows(Lg, rows[:2 * r + 1], kh, Bg[y])
        gauss_rows(Lb, rows[:2 * r + 1], kh, Bb[y])
        if y + 1 < H:
            gauss_rows(Lg, rows[1:], kh, Bg[y + 1])
            gauss_rows(Lb, rows[1:], kh, Bb[y + 1])
    return top


@njit(cache=True, nogil=True, error_model="numpy")
def classify_frame(Lg, Lb, rmax, Bg, Bb, sg, sb, thr_w, norm_w, cyan_level, min_level, raw_margin, min_contrast,
                   dark_level, saturation_level, min_run_sep, min_run_swing, run_end_gap, follow_w, labels, reason,
                   gn, bn, contrast):
    """Stages 2-3 of the fast path in one pass over the rows: colour balance with the global scales
    ``sg, sb``, ``d``, its local threshold, local min/max and the per-pixel rules.

    Bit-identical to :func:`classify_image` on ``Bg * sg, Bb * sb`` (same row primitives); only the
    ``d`` rows of the threshold window live in a ring buffer.  Lg, Lb, rmax, Bg, Bb : (H, W) from
    :func:`blur_frame` (linear, raw maximum, blurred).  thr_w : odd local
    threshold window (0: global threshold).  Writes labels, reason, gn, bn, contrast ((H, W)).
    (:func:`stream_frame` runs the same steps on rows it blurs as it goes.)
    """
    no_img = np.empty((0, 0, 3), np.uint8)
    no_kernel = np.empty(0, np.float32)
    _rows_1_3(False, no_img, no_kernel, no_kernel, Lg, Lb, rmax, Bg, Bb, sg, sb, thr_w, norm_w, cyan_level, min_level,
              raw_margin, min_contrast, dark_level, saturation_level, min_run_sep, min_run_swing, run_end_gap,
              follow_w, labels, reason, gn, bn, contrast)


@njit(cache=True, nogil=True, error_model="numpy")
def _classify_scratch(W, thr_w, norm_w, follow_w):
    # the row scratch of _rows_1_3: separate arrays (rows of one 2-D array would not vectorise)
    t = thr_w // 2
    n = W + 2 * (max(norm_w, follow_w) // 2)
    nt = W + 2 * t
    f32 = np.float32
    return (np.empty((2 * t + 2, W), f32), np.empty(2 * t + 2, np.int64),                    # Dr, rows
            np.empty(nt, f32), np.empty(nt, f32), np.empty(nt, f32), np.zeros(W, f32),         # Pd, tda, tdb, thr
            np.empty(n, f32), np.empty(n, f32),                                                 # Pg, Pb
            np.empty(n, f32), np.empty(n, f32), np.empty(n, f32), np.empty(n, f32),             # LOg, HIg, LOb, HIb
            np.empty(n, f32), np.empty(n, f32), np.empty(n, f32), np.empty(n, f32),             # s0 .. s3
            np.empty(n, f32), np.empty(n, f32), np.empty(n, f32), np.empty(n, f32),             # s4 .. s7
            np.empty(n, f32), np.empty(n, f32),                                                 # ta, tb
            np.empty(W, f32), np.empty(W, f32), np.empty(W, f32), np.empty(W, f32),             # lo_g .. hi_b
            np.empty(W, f32), np.empty(W + 1, np.int32),                                        # raw_hi, run starts
            np.empty(W, f32), np.empty(W, f32))                                                 # ng, nb


@njit(cache=True, nogil=True, error_model="numpy")
def _rows_1_3(stream, img, lut, kh, Lg, Lb, rmax, Bg, Bb, sg, sb, thr_w, norm_w, cyan_level, min_level, raw_margin,
              min_contrast, dark_level, saturation_level, min_run_sep, min_run_swing, run_end_gap, follow_w, labels,
              reason, gn, bn, contrast):
    # The row loop of classify_frame (stream False: Lg .. Bb whole images) and stream_frame (stream
    # True: rings of rows, filled from img as the loop goes; img, lut, kh unused otherwise).  Step y
    # (y = 0 .. H + thr_w//2 - 1): d of blurred row y (y < H) into the ring of the threshold window,
    # then row v = y - thr_w//2 classified (v >= 0).  Image row k of the linear (Lg, Lb, rmax) and
    # blurred (Bg, Bb) channels is row k % nL / k % nB of those arrays.  One function with the
    # scratch rows as its locals: a step function called (or inlined) per row took its scratch
    # from a tuple, whose unpacking costs reference counts on every row (-5 % with the loop here).
    # Returns the largest raw green or blue value (stream True).
    H, W = labels.shape
    nL = Lg.shape[0]
    nB = Bg.shape[0]
    t = thr_w // 2
    h = norm_w // 2
    nD = 2 * t + 2
    (Dr, rows, Pd, tda, tdb, thr, Pg, Pb, LOg, HIg, LOb, HIb, s0, s1, s2, s3, s4, s5, s6, s7, ta, tb,
     lo_g, hi_g, lo_b, hi_b, raw_hi, rs, ng, nb) = _classify_scratch(W, thr_w, norm_w, follow_w)
    flat = img.reshape(img.shape[0], 3 * img.shape[1])     # rows of bytes (see _linear_row)
    r = kh.size - 1
    grow = np.empty(2 * r + 2, np.int64)
    top = np.uint8(0)
    loaded = 0
    yb = 0                      # next blurred row
    for y in range(H + t):
        while stream and yb <= y and yb < H:
            # stages "input" and 1: rows linearised into the rings Lg, Lb, rmax as the Gaussian
            # needs them, then blurred into Bg, Bb (two rows at a time, as blur_frame)
            while loaded <= min(H - 1, yb + 1 + r):
                k = loaded % nL
                top = _linear_row(flat[loaded], lut, Lg[k], Lb[k], rmax[k], top)
                loaded += 1
            for j in range(2 * r + 2):
                grow[j] = reflect101(yb - r + j, H) % nL
            if yb + 1 < H and r >= 3:
                gauss_rows2(Lg, grow, kh, Bg[yb % nB], Bg[(yb + 1) % nB])
                gauss_rows2(Lb, grow, kh, Bb[yb % nB], Bb[(yb + 1) % nB])
                yb += 2
            else:
                gauss_rows(Lg, grow[:2 * r + 1], kh, Bg[yb % nB])
                gauss_rows(Lb, grow[:2 * r + 1], kh, Bb[yb % nB])
                yb += 1
        v = y - t
        if t > 0 and v - t - 1 >= 0 and y < H:
            # column_sums' update step with the new row's d computed in the same loop
            _ratio_update_row(Bg[y % nB], Bb[y % nB], sg, sb, Dr[y % nD], Dr[(v - t - 1) % nD], Pd[t:t + W])
        else:
            if y < H:
                ratio_row(Bg[y % nB], Bb[y % nB], sg, sb, Dr[y % nD])
            if t > 0 and v >= 0:
                column_sums(Dr, v, H, thr_w, nD, rows, Pd)
        if v < 0:
            continue
        if t > 0:
            pad_reflect101(Pd, t, W)
            box_row(Pd, thr_w, tda, tdb, np.float32(1.0 / (thr_w * thr_w)), thr)
        g = Bg[v % nB]
        b = Bb[v % nB]
        raw_g = Lg[v % nL]
        raw_b = Lb[v % nL]
        # _minmax_smooth_row of both channels, in shared loops
        if 8 <= norm_w < 16:    # (the same values without the padded copies: min/max are exact)
            _quad_minmax2(g, b, h, s0, s1, s2, s3)
            _minmax4_from_quads(s0, s1, s2, s3, norm_w, LOg[h:h + W], HIg[h:h + W], LOb[h:h + W], HIb[h:h + W])
        else:
            pg = Pg[h:h + W]
            pb = Pb[h:h + W]
            for u in range(W):
                pg[u] = g[u]
                pb[u] = b[u]
            pad_replicate(Pg, h, W)
            pad_replicate(Pb, h, W)
            _slide_minmax2(Pg, Pb, norm_w, s0, s1, s2, s3, s4, s5, s6, s7, LOg, HIg, LOb, HIb, h)
        pad_replicate(LOg, h, W)
        pad_replicate(HIg, h, W)
        pad_replicate(LOb, h, W)
        pad_replicate(HIb, h, W)
        s_norm = np.float32(1.0 / norm_w)
        if 8 <= norm_w < 16:
            _box4_8to15(LOg, HIg, LOb, HIb, norm_w, s0, s_norm, lo_g, hi_g, lo_b, hi_b)
        else:
            _box4(LOg, HIg, LOb, HIb, norm_w, s0, s1, s2, s3, s4, s5, s6, s7, s_norm, lo_g, hi_g, lo_b, hi_b)
        if follow_w > 0:
            follow_envelope_row(g, b, follow_w, Pg, LOg, ta, tb, ng, nb, lo_g, hi_g, lo_b, hi_b)
        _raw_hi_row(raw_g, raw_b, norm_w, Pg, ta, tb, raw_hi)
        classify_row(g, b, Dr[v % nD], thr, lo_g, hi_g, lo_b, hi_b, raw_g, raw_b, raw_hi, rmax[v % nL], cyan_level,
                     min_level, raw_margin, min_contrast, dark_level, saturation_level,
                     labels[v], reason[v], gn[v], bn[v], contrast[v])
        if W > 0:
            _faint_runs_row(labels[v], reason[v], gn[v], bn[v], g, b, min_run_sep, min_run_swing, run_end_gap, rs)
    return top


def stream_rows(radius: int, thr_w: int) -> tuple[int, int]:
    """Ring sizes (rows) of :func:`stream_frame` for a Gaussian of ``radius`` rows and a threshold
    window ``thr_w`` (0: global): linear rows ``nL``, blurred rows ``nB``.  When row v is classified
    the linear rows up to v + t + r + 1 are loaded (t = thr_w // 2: the blur runs t rows ahead, two
    rows at a time) and rows from min(v, v + t + 1 - r) are still to be read: at most
    r + max(r, t) + 2 rows (what :func:`stream_frame` requires); the blurred rows v .. v + t + 1:
    t + 2 rows.  One row spare in each."""
    t = thr_w // 2
    return radius + max(radius, t) + 3, t + 3


@njit(cache=True, nogil=True, error_model="numpy")
def _linear_row(px, lut, lg, lb, rm, top):
    # one row of bytes (3 W,) RGB -> linear green, blue (lut) and the raw maximum; returns the
    # running maximum ``top``.  The maximum loop apart from the gathers over a flat byte row
    # vectorises (measured: LUT stage 0.52 -> 0.24 ms at 640x480 with the two loops apart).
    W = lg.size
    for u in range(W):
        m = max(px[3 * u + 1], px[3 * u + 2])
        rm[u] = m
        top = max(top, m)
    for u in range(W):
        lg[u] = lut[px[3 * u + 1]]
        lb[u] = lut[px[3 * u + 2]]
    return top


@njit(cache=True, nogil=True, error_model="numpy")
def balance_samples(img, lut, kh, gs, bs):
    """The blurred linear green and blue of an RGB uint8 frame at every 4th row and column (what
    :func:`gbscan.decode.balance_scales` averages), without blurring the rest: ``gs[i, k]`` =
    :func:`blur_frame`'s ``Bg[4 i, 4 k]``, bit for bit (the same :func:`gauss_rows` arithmetic on
    a subset of its columns; the linear columns in a ring of 2r + 2 rows).
    gs, bs : (ceil(H/4), ceil(W/4)) float32 outputs.  ``img`` C-contiguous."""
    H = img.shape[0]
    Ws = gs.shape[1]
    r = kh.size - 1
    n = 2 * r + 2
    Sg = np.empty((n, Ws), np.float32)
    Sb = np.empty((n, Ws), np.float32)
    rows = np.empty(2 * r + 1, np.int64)
    loaded = 0
    for i in range(gs.shape[0]):
        v = 4 * i
        while loaded <= min(H - 1, v + r):
            px = img[loaded]
            lg = Sg[loaded % n]
            lb = Sb[loaded % n]
            for k in range(Ws):
                lg[k] = lut[px[4 * k, 1]]
                lb[k] = lut[px[4 * k, 2]]
            loaded += 1
        for j in range(2 * r + 1):
            rows[j] = reflect101(v - r + j, H) % n
        gauss_rows(Sg, rows, kh, gs[i])
        gauss_rows(Sb, rows, kh, bs[i])


@njit(cache=True, nogil=True, error_model="numpy")
def stream_frame(img, lut, kh, sg, sb, thr_w, norm_w, cyan_level, min_level, raw_margin, min_contrast,
                 dark_level, saturation_level, min_run_sep, min_run_swing, run_end_gap, follow_w, Rg, Rb, Rm, Qg, Qb,
                 labels, reason, gn, bn, contrast):
    """Stages "input", 1, 2 (with the global scales ``sg, sb``, from :func:`balance_samples`) and 3
    of the fast path in one pass over the rows: each image row is linearised into a ring of rows
    (Rg, Rb float32, Rm uint8 raw maximum: (nL, W)), blurred into a ring (Qg, Qb: (nB, W)) as soon
    as the Gaussian's support is there, and classified as soon as its threshold window is
    (:func:`_rows_1_3`).  Ring sizes from :func:`stream_rows`.  Bit-identical to
    :func:`blur_frame` + :func:`classify_frame`, without their full-size linear and blurred images
    (17 bytes/px written and read back).  Writes labels, reason, gn, bn, contrast ((H, W)); returns
    the largest raw green or blue value (0: a black frame)."""
    H, W = img.shape[0], img.shape[1]
    r = kh.size - 1
    t = thr_w // 2
    nL = Rg.shape[0]
    nB = Qg.shape[0]
    if nL < r + max(r, t) + 2 or nB < t + 2:
        raise ValueError("stream_frame: rings too small (see stream_rows)")
    return _rows_1_3(True, img, lut, kh, Rg, Rb, Rm, Qg, Qb, sg, sb, thr_w, norm_w, cyan_level, min_level,
                     raw_margin, min_contrast, dark_level, saturation_level, min_run_sep, min_run_swing, run_end_gap,
                     follow_w, labels, reason, gn, bn, contrast)


@njit(cache=True, nogil=True, error_model="numpy")
def bright_window(img, level):
    """The smallest window holding every pixel of an RGB uint8 frame (H, W, 3) whose green or blue
    byte is at least ``level``: (y0, y1, x0, x1), half-open; (0, 0, 0, 0) when there is none.
    The first and last bright rows from the rows' largest green/blue bytes (from each end), then
    the columns' largest byte over the rows between them (vectorised loops, no per-pixel scans;
    ``gbscan.decode`` decodes a frame's lit window)."""
    H, W = img.shape[0], img.shape[1]
    flat = img.reshape(H, 3 * W)
    y0 = 0
    while y0 < H and _row_max_gb(flat[y0]) < level:
        y0 += 1
    if y0 == H:
        return 0, 0, 0, 0
    y1 = H
    while _row_max_gb(flat[y1 - 1]) < level:
        y1 -= 1
    # column maxima over the rows y0..y1-1 (row y0 holds a bright pixel, so some column does)
    cm = np.zeros(W, np.uint8)
    for v in range(y0, y1):
        px = flat[v]
        for u in range(W):
            cm[u] = max(cm[u], max(px[3 * u + 1], px[3 * u + 2]))
    x0 = 0
    while cm[x0] < level:
        x0 += 1
    x1 = W
    while cm[x1 - 1] < level:
        x1 -= 1
    return y0, y1, x0, x1


@njit(cache=True, nogil=True, error_model="numpy")
def _row_max_gb(px):
    # the largest green or blue byte of a flat RGB row (vectorised)
    m = np.uint8(0)
    for u in range(px.size // 3):
        m = max(m, max(px[3 * u + 1], px[3 * u + 2]))
    return m
