"""Cleaning an organised point map (:mod:`gbscan.clean`): point-wise limits, spikes, depth
jumps, gap edges, grid normals and the grazing filter, small components.

Part of :mod:`gbscan.kernels` (its docstring has the conventions)."""
from __future__ import annotations

import numpy as np
from numba import njit


# -- cleaning an organised point map (gbscan.clean) ---------------------------------------------
# Conventions of gbscan.clean: ``xyz`` (H, W, 3) float mm; ``reason`` (H, W) uint8 per-pixel code,
# 0 = still in play.  A filter writes its ``code`` on the pixels it rejects (in place) and returns
# how many; its decisions are all made on the pixels in play when it starts, never on its own
# partial result, so the order of the loops is irrelevant.

@njit(cache=True, nogil=True)
def clean_pointwise(xyz, confidence, use_confidence, min_confidence, min_z, max_z, reason,
                    code_no_plane, code_confidence, code_depth):
    """Non-finite points, low confidence, z outside ``[min_z, max_z]``; counts (3,) in that order.

    A NaN confidence counts as 0; ``use_confidence`` False skips the confidence test.
    """
    H, W = reason.shape
    n = np.zeros(3, np.int64)
    for v in range(H):
        for u in range(W):
            if reason[v, u] != 0:
                continue
            x = xyz[v, u, 0]
            y = xyz[v, u, 1]
            z = xyz[v, u, 2]
            if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
                reason[v, u] = code_no_plane
                n[0] += 1
            elif use_confidence and not (confidence[v, u] >= min_confidence):
                reason[v, u] = code_confidence
                n[1] += 1
            elif not (min_z <= z <= max_z):
                reason[v, u] = code_depth
                n[2] += 1
    return n


@njit(cache=True, nogil=True)
def _padded_depth(xyz, reason):
    """(H + 2, W + 2) float64 depth of the in-play pixels, NaN elsewhere and on the border."""
    H, W = reason.shape
    zp = np.full((H + 2, W + 2), np.nan)
    for v in range(H):
        for u in range(W):
            if reason[v, u] == 0:
                zp[v + 1, u + 1] = xyz[v, u, 2]
    return zp


@njit(cache=True, nogil=True)
def _reject(drop, n_drop, reason, zp, code):
    """Write ``code`` on the ``n_drop`` flat pixel indices ``drop`` and take them out of ``zp``."""
    W = reason.shape[1]
    for i in range(n_drop):
        v, u = divmod(drop[i], W)
        reason[v, u] = code
        zp[v + 1, u + 1] = np.nan
    return n_drop


@njit(cache=True, nogil=True)
def _spike_pass(zp, reason, tol, min_pairs, code):
    """Drop points supported by fewer than ``min_pairs`` of their four opposite 8-neighbour pairs
    (a pair supports when both are in play and ``|mean depth - z| <= tol * z``; NaN never does)."""
    H, W = reason.shape
    drop = np.empty(H * W, np.int64)
    n = 0
    for v in range(H):
        a = zp[v]
        b = zp[v + 1]
        c = zp[v + 2]
        for u in range(W):
            z = b[u + 1]
            if reason[v, u] != 0:
                continue
            lim = tol * z
            pairs = 0
            if abs(0.5 * (b[u] + b[u + 2]) - z) <= lim:
                pairs += 1
            if abs(0.5 * (a[u + 1] + c[u + 1]) - z) <= lim:
                pairs += 1
            if abs(0.5 * (a[u] + c[u + 2]) - z) <= lim:
                pairs += 1
            if abs(0.5 * (a[u + 2] + c[u]) - z) <= lim:
                pairs += 1
            if pairs < min_pairs:
                drop[n] = v * W + u
                n += 1
    return _reject(drop, n, reason, zp, code)


@njit(cache=True, nogil=True)
def _jump_pass(zp, reason, max_jump, code):
    """Drop both pixels of every in-play 4-neighbour pair whose depths differ by more than
    ``max_jump`` times the nearer depth (pairs with a NaN never do)."""
    H, W = reason.shape
    mark = np.zeros((H + 2, W + 2), np.bool_)
    for v in range(H):
        b = zp[v + 1]
        c = zp[v + 2]
        for u in range(W):
            z = b[u + 1]
            r = b[u + 2]
            if abs(z - r) > max_jump * min(z, r):
                mark[v + 1, u + 1] = True
                mark[v + 1, u + 2] = True
            d = c[u + 1]
            if abs(z - d) > max_jump * min(z, d):
                mark[v + 1, u + 1] = True
                mark[v + 2, u + 1] = True
    drop = np.empty(H * W, np.int64)
    n = 0
    for v in range(H):
        for u in range(W):
            if mark[v + 1, u + 1] and reason[v, u] == 0:
                drop[n] = v * W + u
                n += 1
    return _reject(drop, n, reason, zp, code)


@njit(cache=True, nogil=True)
def clean_spikes(xyz, reason, tol, min_pairs, code):
    """The spike filter alone (see :func:`_spike_pass`); returns how many it rejected."""
    return _spike_pass(_padded_depth(xyz, reason), reason, tol, min_pairs, code)


@njit(cache=True, nogil=True)
def clean_jumps(xyz, reason, max_jump, code):
    """The depth-discontinuity filter alone (see :func:`_jump_pass`)."""
    return _jump_pass(_padded_depth(xyz, reason), reason, max_jump, code)


@njit(cache=True, nogil=True)
def _gap_pass(zp, reason, max_jump, max_gap_px, far_px, near_px, code):
    """Depth edges across holes: the depth-jump test between the ends of runs a hole separates.

    For every in-play pixel whose 4-neighbour in a direction is not in play, the first in-play
    pixel ``k`` px away in that direction (``2 <= k <= max_gap_px + 1``) is compared with it:
    when their depths differ by more than ``max_jump * k`` times the nearer one (the jump test's
    slope, kept over the hole), the pixel and the in-play pixels behind it (back along the run,
    stopping at the first hole) are rejected: ``far_px`` of them if the pixel is the farther of
    the two, ``near_px`` if it is the nearer.  The other side is handled by its own scan in the
    opposite direction.  Every decision reads ``zp`` only (the pixels in play at the start; it
    is updated at the end), so the order of the loops is irrelevant.  Returns how many it rejected.
    """
    H, W = reason.shape
    n = 0
    for v in range(H):
        a = zp[v]
        b = zp[v + 1]
        c = zp[v + 2]
        for u in range(W):
            z = b[u + 1]
            if not z == z:
                continue
            if a[u + 1] == a[u + 1] and c[u + 1] == c[u + 1] and b[u] == b[u] and b[u + 2] == b[u + 2]:
                continue  # inside a run both ways: the plain jump test's business
            for d in range(4):
                dv = 1 if d == 0 else (-1 if d == 1 else 0)
                du = 1 if d == 2 else (-1 if d == 3 else 0)
                zn = zp[v + 1 + dv, u + 1 + du]
                if zn == zn:
                    continue  # neighbour in play
                for k in range(2, max_gap_px + 2):
                    vk = v + k * dv
                    uk = u + k * du
                    if vk < 0 or vk >= H or uk < 0 or uk >= W:
                        break
                    zk = zp[vk + 1, uk + 1]
                    if zk == zk:
                        if abs(zk - z) > max_jump * k * min(z, zk):
                            for j in range(far_px if z > zk else near_px):
                                vj = v - j * dv
                                uj = u - j * du
                                zj = zp[vj + 1, uj + 1]  # NaN on the padding border
                                if not zj == zj:
                                    break
                                if reason[vj, uj] == 0:
                                    reason[vj, uj] = code
                                    n += 1
                        break
    for v in range(H):
        for u in range(W):
            if reason[v, u] == code:
                zp[v + 1, u + 1] = np.nan
    return n


@njit(cache=True, nogil=True)
def clean_gap_edges(xyz, reason, max_jump, max_gap_px, far_px, near_px, code):
    """The gap-edge filter alone (see :func:`_gap_pass`)."""
    return _gap_pass(_padded_depth(xyz, reason), reason, max_jump, max_gap_px, far_px, near_px, code)


@njit(cache=True, nogil=True)
def clean_spikes_jumps(xyz, reason, tol, min_pairs, code_spike, max_jump, code_jump, max_gap_px, far_px, near_px,
                       code_gap):
    """Spikes, then depth discontinuities, then depth edges across holes (``max_gap_px`` 0:
    none) on what is left, sharing one depth map; (n_spike, n_jump, n_gap)."""
    zp = _padded_depth(xyz, reason)
    n_spike = _spike_pass(zp, reason, tol, min_pairs, code_spike)
    n_jump = _jump_pass(zp, reason, max_jump, code_jump)
    n_gap = _gap_pass(zp, reason, max_jump, max_gap_px, far_px, near_px, code_gap) if max_gap_px > 0 else 0
    return n_spike, n_jump, n_gap


@njit(cache=True, nogil=True)
def grid_normals_into(xyz, reason, step, out, min_cos, code):
    """Unit normals of the in-play pixels into ``out`` (H, W, 3) float32, NaN elsewhere.

    Tangents over ``step`` px along rows and columns, central where both sides are in play,
    one-sided otherwise; n = t_v x t_u, oriented so that n . p < 0 (towards the camera).
    A pixel is usable when in play and its three coordinates are finite.  With ``code`` != 0,
    also the grazing filter: pixels whose normal makes ``cos < min_cos`` with the ray towards
    the camera get ``code`` (the normals of all pixels use the in-play set of the start).
    Returns how many pixels it rejected.
    """
    H, W = reason.shape
    s = step
    ok = np.empty((H, W), np.bool_)
    for v in range(H):
        for u in range(W):
            ok[v, u] = (reason[v, u] == 0 and np.isfinite(xyz[v, u, 0]) and np.isfinite(xyz[v, u, 1])
                        and np.isfinite(xyz[v, u, 2]))
    n_bad = 0
    for v in range(H):
        for u in range(W):
            good = ok[v, u]
            if good:
                f = u + s < W and ok[v, u + s]
                b = u - s >= 0 and ok[v, u - s]
                fv = v + s < H and ok[v + s, u]
                bv = v - s >= 0 and ok[v - s, u]
                good = (f or b) and (fv or bv)
            if not good:
                out[v, u, 0] = np.nan
                out[v, u, 1] = np.nan
                out[v, u, 2] = np.nan
                continue
            ua = u + s if f else u
            ub = u - s if b else u
            va = v + s if fv else v
            vb = v - s if bv else v
            tux = np.float64(xyz[v, ua, 0]) - np.float64(xyz[v, ub, 0])
            tuy = np.float64(xyz[v, ua, 1]) - np.float64(xyz[v, ub, 1])
            tuz = np.float64(xyz[v, ua, 2]) - np.float64(xyz[v, ub, 2])
            tvx = np.float64(xyz[va, u, 0]) - np.float64(xyz[vb, u, 0])
            tvy = np.float64(xyz[va, u, 1]) - np.float64(xyz[vb, u, 1])
            tvz = np.float64(xyz[va, u, 2]) - np.float64(xyz[vb, u, 2])
            nx = tvy * tuz - tvz * tuy
            ny = tvz * tux - tvx * tuz
            nz = tvx * tuy - tvy * tux
            norm = np.sqrt(nx * nx + ny * ny + nz * nz)
            if not norm > 0.0:
                out[v, u, 0] = np.nan
                out[v, u, 1] = np.nan
                out[v, u, 2] = np.nan
                continue
            px = np.float64(xyz[v, u, 0])
            py = np.float64(xyz[v, u, 1])
            pz = np.float64(xyz[v, u, 2])
            inv = 1.0 / norm if nx * px + ny * py + nz * pz <= 0 else -1.0 / norm
            out[v, u, 0] = nx * inv
            out[v, u, 1] = ny * inv
            out[v, u, 2] = nz * inv
            if code != 0 and _grazing(out[v, u, 0], out[v, u, 1], out[v, u, 2], px, py, pz, min_cos):
                reason[v, u] = code
                n_bad += 1
    return n_bad


@njit(cache=True, nogil=True, inline="always")
def _grazing(nx, ny, nz, px, py, pz, min_cos):
    """cos(normal, ray to the camera) = -n.p / |p| < min_cos, without a square root or a division;
    False for a NaN normal."""
    c = -(nx * px + ny * py + nz * pz)  # cos * |p| (unit normal)
    if not c == c:
        return False
    if min_cos <= 0.0:
        return c < 0.0 and c * c > min_cos * min_cos * (px * px + py * py + pz * pz)
    return c < 0.0 or c * c < min_cos * min_cos * (px * px + py * py + pz * pz)


@njit(cache=True, nogil=True)
def clean_grazing(xyz, normals, reason, min_cos, code):
    """Drop in-play points whose given normal makes ``cos < min_cos`` with the ray towards the
    camera (points without a normal are kept)."""
    H, W = reason.shape
    n = 0
    for v in range(H):
        for u in range(W):
            if reason[v, u] != 0:
                continue
            if _grazing(np.float64(normals[v, u, 0]), np.float64(normals[v, u, 1]), np.float64(normals[v, u, 2]),
                        np.float64(xyz[v, u, 0]), np.float64(xyz[v, u, 1]), np.float64(xyz[v, u, 2]), min_cos):
                reason[v, u] = code
                n += 1
    return n


@njit(cache=True, nogil=True)
def clean_small_labels(labels, n_labels, reason, min_px, code):
    """Drop in-play pixels whose component (``labels`` (H, W) int32, 0 = background, as
    ``cv2.connectedComponents`` gives) has fewer than ``min_px`` pixels."""
    H, W = reason.shape
    area = np.zeros(n_labels, np.int64)
    for v in range(H):
        for u in range(W):
            area[labels[v, u]] += 1
    n = 0
    for v in range(H):
        for u in range(W):
            k = labels[v, u]
            if reason[v, u] == 0 and k > 0 and area[k] < min_px:
                reason[v, u] = code
                n += 1
    return n


@njit(cache=True, nogil=True)
def mask_rejected(reason, xyz, normals):
    """NaN into ``xyz`` and ``normals`` (H, W, 3) wherever ``reason`` != 0 (in place)."""
    H, W = reason.shape
    for v in range(H):
        for u in range(W):
            if reason[v, u] != 0:
                for c in range(3):
                    xyz[v, u, c] = np.nan
                    normals[v, u, c] = np.nan


@njit(cache=True, nogil=True)
def window_slopes(img, comp, want, rows, cols, half_px, min_span_px):
    """(n,) float64 slope of ``img`` (H, W) float32 along row ``rows[i]`` between the outermost
    finite pixels within ``cols[i] +- half_px`` (those of component ``want[i]`` in ``comp`` when
    ``want[i] >= 0``), NaN when the row is outside the image or they span fewer than
    ``min_span_px`` px."""
    H, W = img.shape
    n = rows.shape[0]
    out = np.full(n, np.nan, np.float64)
    for i in range(n):
        r = rows[i]
        if r < 0 or r >= H:
            continue
        a = -1
        b = -1
        for x in range(max(cols[i] - half_px, 0), min(cols[i] + half_px, W - 1) + 1):
            if np.isnan(img[r, x]) or (want[i] >= 0 and comp[r, x] != want[i]):
                continue
            if a < 0:
                a = x
            b = x
        if a >= 0 and b - a >= min_span_px:
            out[i] = (img[r, b] - img[r, a]) / (b - a)
    return out
