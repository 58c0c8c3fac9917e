"""Colour classes of the decoder's label images and small row loops, shared by the kernel modules."""
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
def fill_row(o, val):
    """``o[:] = val`` as a loop numba vectorises (a row slice)."""
    for u in range(o.size):
        o[u] = val


@njit(cache=True, nogil=True)
def copy_row(o, src):
    """``o[:] = src`` as a loop numba vectorises (row slices of one length)."""
    for u in range(o.size):
        o[u] = src[u]
