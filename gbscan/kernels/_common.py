"""Colour classes of the decoder's label images and small row loops and helpers (least squares, a
sorted search, a colour against the markers), shared by the kernel modules."""
NONE, GREEN, BLUE, CYAN = 0, 1, 2, 3

import numpy as np
from numba import njit

#: count trailing zeros of a 64-bit word by a de Bruijn multiply (numba's own intrinsic lives in
#: an internal module): the lowest set bit times the sequence, its top 6 bits index the table
_DEBRUIJN64 = np.uint64(0x03F79D71B4CB0A89)
_CTZ_TABLE = np.array([0, 1, 48, 2, 57, 49, 28, 3, 61, 58, 50, 42, 38, 29, 17, 4,
                       62, 55, 59, 36, 53, 51, 43, 22, 45, 39, 33, 30, 24, 18, 12, 5,
                       63, 47, 56, 27, 60, 41, 37, 16, 54, 35, 52, 21, 44, 32, 23, 11,
                       46, 26, 40, 15, 34, 20, 31, 10, 25, 14, 19, 9, 13, 8, 7, 6], np.int64)


@njit(cache=True, nogil=True)
def ctz64(m):
    """The index of the lowest set bit of a uint64 ``m != 0``."""
    low = m & (~m + np.uint64(1))
    return _CTZ_TABLE[(low * _DEBRUIJN64) >> np.uint64(58)]


@njit(cache=True, nogil=True)
def contradicts(lab, marker):
    """Whether a pixel of colour class ``lab`` contradicts a stripe that is (``marker``) or is not
    a marker stripe: cyan on a plain stripe, green or blue on a marker stripe."""
    return (lab == CYAN and not marker) or ((lab == GREEN or lab == BLUE) and marker)


@njit(cache=True, nogil=True)
def contradicting_px(a, c, g, is_marker):
    """How many of a stripe's pixels (``c`` cyan, ``g`` green or blue) contradict absolute stripe
    ``a`` of a pattern whose marker stripes are ``is_marker`` (n_stripes,) bool: all of them
    outside the pattern, the green / blue ones on a marker, the cyan ones on a plain stripe."""
    if a < 0 or a >= is_marker.shape[0]:
        return c + g
    return g if is_marker[a] else c


@njit(cache=True, nogil=True)
def fill_row(o, val):
    """``o[:] = val`` as a loop numba vectorises (a row slice)."""
    for u in range(o.size):
        o[u] = val


@njit(cache=True, nogil=True)
def copy_row(o, src):
    """``o[:] = src`` as a loop numba vectorises (row slices of one length)."""
    for u in range(o.size):
        o[u] = src[u]


@njit(cache=True, nogil=True)
def run_starts(row, rs):
    """Run-length encode one row (W,) (W >= 1) of labels, or of any values: the runs' first pixels
    into ``rs[0 .. n-1]`` and ``rs[n] = W`` (rs: (W + 1,) integers); returns n.  64 pixel pairs
    at a time: a bit mask of the changes (a vector loop), then one step per change, its position
    the mask's trailing-zero count; the row's last block is the 64 pairs that end it, less those
    the block before took.  Rows under 65 px: branch-free, pixel by pixel.  The runs of a label
    row (``segments.row_segments``, ``classify``'s faint-run test) and of a row of vote keys
    (``linking.vertical_votes``)."""
    W = row.size
    rs[0] = 0
    n = np.uint64(1)
    m1 = W - 1            # pixel pairs (u, u + 1)
    a = row[:m1]
    b = row[1:]
    if m1 >= 64:
        base = 0
        while base < m1:
            lo = 0
            if base + 64 > m1:     # the last block: pairs base - lo .. base - 1 are done
                lo = base - (m1 - 64)
                base = m1 - 64
            A = a[base:base + 64]
            B = b[base:base + 64]
            m = np.uint64(0)
            for t in range(64):
                m |= np.uint64(A[t] != B[t]) << np.uint64(t)
            m = (m >> np.uint64(lo)) << np.uint64(lo)
            while m != np.uint64(0):
                rs[n] = base + ctz64(m) + 1
                n += np.uint64(1)
                m &= m - np.uint64(1)
            base += 64
    else:
        for u in range(m1):
            rs[n] = u + 1
            n += np.uint64(a[u] != b[u])
    rs[n] = W
    return np.int64(n)


@njit(cache=True, nogil=True)
def fit_add(acc, v, x):
    """One point (``v``, ``x``) into the least-squares sums ``acc`` (5,) float64: n, sum v,
    sum x, sum v^2, sum v x (start from zeros)."""
    acc[0] += 1.0
    acc[1] += v
    acc[2] += x
    acc[3] += v * v
    acc[4] += v * x


@njit(cache=True, nogil=True)
def fit_slope(acc, min_n):
    """The least-squares slope ``d x / d v`` of the sums of :func:`fit_add`; NaN with fewer than
    ``min_n`` points or all at one ``v``."""
    n = acc[0]
    den = n * acc[3] - acc[1] * acc[1]
    if n < min_n or not den > 0.0:
        return np.nan
    return (n * acc[4] - acc[1] * acc[2]) / den


@njit(cache=True, nogil=True)
def lower_bound(a, lo, hi, key):
    """The first index in ``[lo, hi)`` of the ascending ``a`` with ``a[i] >= key`` (``hi`` if none)."""
    while lo < hi:
        mid = (lo + hi) // 2
        if a[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    return lo
