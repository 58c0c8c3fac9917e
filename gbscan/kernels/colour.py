"""The frame's colour resolution (:mod:`gbscan.chroma`): second moments of chroma windows."""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["chroma_window_moments"]


@njit(cache=True, nogil=True)
def chroma_window_moments(img, rows, level, L):
    """Second-moment matrices of the Cb and Cr (BT.601) windows of ``L`` consecutive pixels along
    rows ``rows`` of ``img`` (H, W, 3) uint8 RGB whose every pixel is striped (green or blue byte
    at least ``level``), one matrix per start-column parity.

    Returns ``(sums, count)``: ``sums`` (2, L, L) float64 the sums of ``w w^T`` over both channels'
    windows starting on even / odd columns, ``count`` (2,) int64 the windows per parity and channel.
    Each window's products are not summed one by one: along a row the products of pixels ``d``
    apart are summed with a stride of 2 (prefix sums), and every maximal striped run adds the
    windows inside it in O(L^2) (0.34 ms for 16 rows of 640 px; gathering the windows in numpy and
    multiplying them took ~1 ms with the calls around).
    """
    W = img.shape[1]
    sums = np.zeros((2, L, L))
    count = np.zeros(2, np.int64)
    ch = np.empty((2, W), np.float64)
    pre = np.empty((L, W + 2), np.float64)     # pre[d, t + 2] = sum of q_d[t'] for t' = t, t - 2, ...
    striped = np.empty(W, np.bool_)
    for r in rows:
        for x in range(W):
            red = np.float32(img[r, x, 0])
            grn = np.float32(img[r, x, 1])
            blu = np.float32(img[r, x, 2])
            ch[0, x] = np.float32(-0.168736) * red - np.float32(0.331264) * grn + np.float32(0.5) * blu
            ch[1, x] = np.float32(0.5) * red - np.float32(0.418688) * grn - np.float32(0.081312) * blu
            striped[x] = max(img[r, x, 1], img[r, x, 2]) >= level
        # the maximal striped runs holding a window
        a = 0
        while a < W:
            if not striped[a]:
                a += 1
                continue
            b = a
            while b + 1 < W and striped[b + 1]:
                b += 1
            last = b - L + 1                   # the last window start inside [a, b]
            if last >= a:
                for c in range(2):
                    c_ = ch[c]
                    for d in range(L):
                        pre[d, 0] = 0.0
                        pre[d, 1] = 0.0
                        for t in range(a, b + 1 - d):
                            pre[d, t - a + 2] = pre[d, t - a] + c_[t] * c_[t + d]
                    for p in range(2):
                        s0 = a + ((p - a) & 1)
                        s1 = last - ((last - p) & 1)
                        if s1 < s0:
                            continue
                        if c == 0:
                            count[p] += (s1 - s0) // 2 + 1
                        for i in range(L):
                            for d in range(L - i):
                                # windows s = s0, s0 + 2, ..., s1: pixels s + i and s + i + d
                                v = pre[d, s1 + i - a + 2] - pre[d, s0 + i - a]
                                sums[p, i, i + d] += v
            a = b + 1
    for p in range(2):
        for i in range(L):
            for j in range(i):
                sums[p, i, j] = sums[p, j, i]
    return sums, count
