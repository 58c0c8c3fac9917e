"""The decoder's per-pixel back end: final masks, stripe, column and confidence
(:func:`finish_pixels`), the regions' marker histograms and offset scores, painting regions,
the paper's step 7 check, and the rim rule (:func:`rim_mask`).

Part of :mod:`gbscan.kernels` (its docstring has the conventions)."""
from __future__ import annotations

import numpy as np
from numba import njit

from ._common import BLUE, CYAN, GREEN, NONE, contradicting_px, copy_row, ctz64, fill_row


@njit(cache=True, nogil=True)
def _minmax_nonneg(x):
    # (min over x >= 0 (2**31-1 if none), max over all) of an int32 row: for a row of regions,
    # hi < 0 when it has none, lo == hi when it has one (finish_pixels, _abs_row, paint_regions)
    lo = np.int32(2147483647)
    hi = np.int32(-2147483648)
    for u in range(x.size):
        s = x[u]
        hi = max(hi, s)
        lo = min(lo, s if s >= 0 else np.int32(2147483647))
    return lo, hi


@njit(cache=True, nogil=True)
def finish_pixels(reason, labels, region, relative, column_rel, inconsistent, reg_shift, reg_indexed, reg_margin,
                  contrast, stripe_px, n_stripes, min_contrast, n_codes, conf_floor):
    """Final masks, absolute stripe, column and confidence (see :func:`gbscan.decode.decode`).

    Reason codes as in ``gbscan.decode``: 0 ok, 4 isolated, 5 inconsistent, 6 unindexed,
    7 no boundary (other non-zero codes come from ``reason`` and are kept).  One-pixel unlabelled
    gaps between two pixels of one region join that region (``region`` is updated in place).
    A reported pixel must lie within one stripe of its colour run's stripe, inside the pattern,
    and agree within half a stripe with a reported vertical neighbour.  ``column_rel`` is set
    to NaN in place outside regions.

    One pass over the rows: row v's provisional code, column, stripe and region margin go to a
    ring of three row buffers; the vertical check and the final values of row v - 1 follow, each
    output written once.  A row whose region pixels all belong to one indexed region (most rows)
    is done branch-free (vector loops); the other rows, and the one-pixel gaps, pixel by pixel.
    Returns mask (uint8), column (float32), stripe (int32), confidence (float32) (H, W) and the
    count of each mask code (n_codes,) int64.  A reported pixel's confidence is
    ``conf_floor + (1 - conf_floor) * contrast term * its region's marker margin``.
    """
    H, W = reason.shape
    mask = np.empty((H, W), np.uint8)
    column = np.empty((H, W), np.float32)
    stripe = np.empty((H, W), np.int32)
    conf = np.empty((H, W), np.float32)
    counts = np.zeros(n_codes, np.int64)
    # row buffers (row v in v % 3): provisional code, column, stripe and region margin; row 3
    # stands for the rows above the first and below the last (no reported pixel)
    pm = np.ones((4, W), np.uint8)
    pc = np.zeros((4, W), np.float32)
    ps = np.zeros((4, W), np.int32)
    pg = np.zeros((4, W), np.float32)
    Wp = (W + 7) & ~7
    todo = np.zeros(Wp, np.uint8)     # the row's pixels for the pixel-by-pixel path
    todo64 = todo.view(np.uint64)
    ok = np.zeros(W, np.bool_)
    w = stripe_px
    half = np.float32(0.5 * w)        # (exact: it is compared with float32 differences)
    hw = 0.5 * (w - 1)
    inv_mc = 1.0 / max(min_contrast, 1e-3)
    conf_span = 1.0 - conf_floor
    for v in range(H + 1):
        if v < H:  # provisional result of row v
            i = v % 3
            lo, hi = _minmax_nonneg(region[v])
            r0 = max(hi, np.int32(-1))
            single = hi < 0 or lo == hi
            if single and (r0 < 0 or reg_indexed[r0]):
                # one indexed region (or none): branch-free with its shift and margin, the
                # pixel-by-pixel path's operations; its one-pixel gaps are left to that path
                shift = reg_shift[max(r0, 0)]
                shw = shift * w
                shf = np.float64(shift)
                shwf = np.float64(shw)
                wf = np.float64(w)
                nsf = np.float64(n_stripes)
                for u in range(W):
                    c = np.float64(column_rel[v, u]) + shwf
                    k = np.float64(relative[v, u]) + shf
                    code = np.uint8(5) if (abs(c - (k * wf + hw)) > wf) | (k < 0.0) | (k >= nsf) else np.uint8(0)
                    code = np.uint8(7) if np.isnan(column_rel[v, u]) else code
                    code = np.uint8(5) if inconsistent[v, u] else code
                    code = np.uint8(4) if region[v, u] < 0 else code
                    m = reason[v, u]
                    pm[i, u] = code if m == 0 else m
                for u in range(W):
                    pc[i, u] = column_rel[v, u] + shw
                for u in range(W):
                    ps[i, u] = relative[v, u] + shift
                mg = reg_margin[max(r0, 0)]
                for u in range(W):
                    pg[i, u] = mg
                todo[0] = 0
                todo[W - 1] = 0
                for u in range(1, W - 1):
                    todo[u] = np.uint8((region[v, u] < 0) & (region[v, u - 1] >= 0) & (region[v, u + 1] >= 0) &
                                       (reason[v, u] == 0) & (labels[v, u] == NONE))
            else:
                for u in range(W):
                    todo[u] = 1
            # pixel by pixel (8 flags at a time skipped when none is set)
            for wi in range(Wp >> 3):
                if todo64[wi] == 0:
                    continue
                for u in range(wi * 8, min(wi * 8 + 8, W)):
                    if todo[u] == 0:
                        continue
                    m = reason[v, u]
                    pm[i, u] = m
                    if m != 0:
                        continue
                    r = region[v, u]
                    gap = False
                    if r < 0 and labels[v, u] == NONE and 0 < u < W - 1:
                        rl = region[v, u - 1]
                        # (u - 1 was not joined: a joined pixel has no region on both sides)
                        if rl >= 0 and rl == region[v, u + 1]:
                            r = rl
                            region[v, u] = r
                            gap = True
                    if r < 0:
                        pm[i, u] = 4
                        continue
                    if not reg_indexed[r]:
                        pm[i, u] = 6
                        continue
                    if inconsistent[v, u]:
                        pm[i, u] = 5
                        continue
                    c = column_rel[v, u]
                    if np.isnan(c):
                        pm[i, u] = 7
                        continue
                    c = c + reg_shift[r] * w
                    if gap:
                        k = int(np.floor((c + 0.5) / w))
                    else:
                        k = relative[v, u] + reg_shift[r]
                    if abs(c - (k * w + 0.5 * (w - 1))) > w or k < 0 or k >= n_stripes:
                        pm[i, u] = 5
                        continue
                    pc[i, u] = c
                    ps[i, u] = k
                    pg[i, u] = reg_margin[r]
        f = v - 1
        if f < 0:
            continue
        # row f: vertical continuity against the provisional rows f - 1 and f + 1, then the final
        # values, branch-free (one array written per loop: they vectorise)
        i = f % 3
        iu = (f - 1) % 3 if f > 0 else 3
        idn = (f + 1) % 3 if f + 1 < H else 3
        for u in range(W):
            c = pc[i, u]
            ok[u] = (pm[i, u] == 0) & (((pm[iu, u] == 0) & (abs(pc[iu, u] - c) <= half)) |
                                       ((pm[idn, u] == 0) & (abs(pc[idn, u] - c) <= half)))
        # (the code read before its select and the confidence clamped by selects: so these two
        # loops vectorise on AVX2 too; the kernel alone 0.80x on a plane, 0.87x on a face, Zen 3)
        for u in range(W):
            p = pm[i, u]
            alt = np.uint8(5) & (np.uint8(0) - np.uint8(not ok[u]))
            mask[f, u] = p if p != 0 else alt
        for u in range(W):
            column[f, u] = pc[i, u] if ok[u] else np.float32(np.nan)
        for u in range(W):
            stripe[f, u] = ps[i, u] if ok[u] else np.int32(-1)
        for u in range(W):
            x = (contrast[f, u] - min_contrast) * inv_mc
            x = 0.0 if 0.0 > x else x      # min(max(x, 0), 1) as selects, NaN and -0.0 kept alike
            x = 1.0 if 1.0 < x else x
            val = np.float32(conf_floor + conf_span * x * pg[i, u])
            conf[f, u] = val if ok[u] else np.float32(0.0)
        for u in range(W):
            column_rel[f, u] = np.float32(np.nan) if region[f, u] < 0 else column_rel[f, u]
        # the count of each code: the row's codes as bits, then a vector count of each one there
        bits = np.uint64(0)
        for u in range(W):
            bits |= np.uint64(1) << np.uint64(mask[f, u] & 63)
        for m in range(n_codes):
            if (bits >> np.uint64(m)) & np.uint64(1):
                n = np.int32(0)
                mc = np.uint8(m)
                for u in range(W):
                    n += np.int32(mask[f, u] == mc)
                counts[m] += n
    return mask, column, stripe, conf, counts


#: region_histograms counts into this many copies of its table, by column (consecutive pixels
#: never increment the same counter: no chain of stores and loads through one memory word)
_HIST_COPIES = 8


@njit(cache=True, nogil=True)
def _region_range_row(rel, reg, lo, hi):
    # the smallest and largest relative index of the row's region pixels, folded into lo, hi
    for u in range(rel.size):
        x = np.int64(rel[u]) if reg[u] >= 0 else 2 ** 62
        y = np.int64(rel[u]) if reg[u] >= 0 else -2 ** 62
        lo = min(lo, x)
        hi = max(hi, y)
    return lo, hi


@njit(cache=True, nogil=True)
def _histogram_slots_row(lab, rel, reg, RS, lo, spare4, tsz, slot):
    # every pixel's counter: (region, relative - lo, class: 0 cyan, 1 green / blue, 2 other) in the
    # copy of its column mod _HIST_COPIES; pixels outside regions to a spare counter
    for u in range(slot.size):
        k = np.int64(reg[u])
        lb = lab[u]
        cls = 2 - np.int64((lb == GREEN) | (lb == BLUE)) - 2 * np.int64(lb == CYAN)
        base = (k * RS + (np.int64(rel[u]) - lo)) * 4 if k >= 0 else spare4
        slot[u] = base + cls + (u & (_HIST_COPIES - 1)) * tsz


@njit(cache=True, nogil=True)
def _count_slots(slot, T):
    for u in range(slot.size):
        T[slot[u]] += 1


@njit(cache=True, nogil=True)
def _region_starts(rmin, rmax):
    # where each region's counts start in the flat histograms (n_reg + 1,): its relative range
    n_reg = rmin.size
    start = np.zeros(n_reg + 1, np.int64)
    for k in range(n_reg):
        span = rmax[k] - rmin[k] + 1 if rmax[k] >= rmin[k] else 0
        start[k + 1] = start[k] + span
    return start


@njit(cache=True, nogil=True)
def region_histograms(labels, relative, region, n_reg):
    """Per region: relative index range and the pixel counts of cyan and of green/blue per
    relative index.  Returns ``rmin, rmax`` (n_reg,) and flat ``n_c, n_g`` with region ``k``'s
    counts at ``start[k] .. start[k] + rmax[k] - rmin[k]``.

    One dense table of counters (region, relative index, class) over the frame's range of relative
    indices, in ``_HIST_COPIES`` copies by column, filled row by row (every pixel's counter by a
    vector loop, then the increments); the ranges and counts are read off the summed copies
    (0.77 -> 0.42 ms on the plane's frame).  Where the table would cost more than the pixels
    (regions x range over a 32nd of the frame) or there is no region pixel, two plain passes."""
    H, W = labels.shape
    lo = 2 ** 62
    hi = -2 ** 62
    for v in range(H):
        lo, hi = _region_range_row(relative[v], region[v], lo, hi)
    if lo > hi:   # no region pixel
        return _region_histograms_loops(labels, relative, region, n_reg)
    RS = hi - lo + 1
    if n_reg * RS * 32 > H * W:
        return _region_histograms_loops(labels, relative, region, n_reg)
    spare4 = n_reg * RS * 4
    tsz = spare4 + 4
    T = np.zeros(tsz * _HIST_COPIES, np.int64)
    slot = np.empty(W, np.int64)
    for v in range(H):
        _histogram_slots_row(labels[v], relative[v], region[v], RS, lo, spare4, tsz, slot)
        _count_slots(slot, T)
    for c in range(1, _HIST_COPIES):
        for i in range(spare4):
            T[i] += T[c * tsz + i]
    rmin = np.full(n_reg, 2 ** 30, np.int64)
    rmax = np.full(n_reg, -(2 ** 30), np.int64)
    for k in range(n_reg):
        for j in range(RS):
            b = (k * RS + j) * 4
            if T[b] + T[b + 1] + T[b + 2] > 0:
                if rmin[k] > j + lo:
                    rmin[k] = j + lo
                rmax[k] = j + lo
    start = _region_starts(rmin, rmax)
    n_c = np.zeros(start[n_reg], np.int64)
    n_g = np.zeros(start[n_reg], np.int64)
    for k in range(n_reg):
        for i in range(start[k + 1] - start[k]):
            b = (k * RS + rmin[k] - lo + i) * 4
            n_c[start[k] + i] = T[b]
            n_g[start[k] + i] = T[b + 1]
    return rmin, rmax, start, n_c, n_g


@njit(cache=True, nogil=True)
def _region_histograms_loops(labels, relative, region, n_reg):
    # region_histograms by two plain passes over the pixels (its fallback)
    H, W = labels.shape
    rmin = np.full(n_reg, 2 ** 30, np.int64)
    rmax = np.full(n_reg, -(2 ** 30), np.int64)
    for v in range(H):
        for u in range(W):
            k = region[v, u]
            if k >= 0:
                r = relative[v, u]
                if r < rmin[k]:
                    rmin[k] = r
                if r > rmax[k]:
                    rmax[k] = r
    start = _region_starts(rmin, rmax)
    n_c = np.zeros(start[n_reg], np.int64)
    n_g = np.zeros(start[n_reg], np.int64)
    for v in range(H):
        for u in range(W):
            k = region[v, u]
            if k >= 0:
                i = start[k] + relative[v, u] - rmin[k]
                lab = labels[v, u]
                if lab == CYAN:
                    n_c[i] += 1
                elif lab == GREEN or lab == BLUE:
                    n_g[i] += 1
    return rmin, rmax, start, n_c, n_g


@njit(cache=True, nogil=True)
def score_offsets(rmin, rmax, start, n_c, n_g, is_marker, min_marker_px, cover, cstart, npx, frac, strengths=True):
    """The marker matched filter of :func:`gbscan.unwrap.index_regions` for every region, from
    :func:`region_histograms`: integer counts, the same sums as its ``np.correlate`` form.

    Per region ``k`` returns (all (n_reg,) int64): ``status`` 0 empty, 1 too thin (no relative
    index with ``min_marker_px`` pixels), 2 no candidate offset, 3 scored, 4 scored but the best
    candidate is outside the working volume; ``seen`` marker stripes seen; for scored regions the
    ``offset`` (absolute - relative) of the best candidate (first minimum), its ``evidence`` and
    ``mismatch`` and the ``runner_up`` (smallest mismatch of the other candidates inside the
    working volume, ``2**63 // 4`` when there is none: the prior never changes the best candidate,
    it only rules out runner-ups).  A candidate is inside when it keeps at least ``frac`` of the
    region's ``npx[k]`` bounded pixels inside their stripes (``cover``, :func:`region_offset_cover`;
    every candidate is inside when ``npx[k]`` is 0: no prior).
    Candidate absolute index ``A`` of relative ``rmin``: ``A + c0 >= -2``, ``A + c1 <= n_st + 1``
    (``c0, c1`` the core's ends), ``A - rmin`` even; positions outside the pattern mismatch every
    observation.  Also returns ``stripe_margin`` (n_reg,) int64: how many more *stripes* every
    other candidate inside the working volume contradicts than the best (``big`` when there is
    none; 0 for unscored regions).  A stripe (relative index) contradicts a candidate when it
    shows at least ``min_marker_px`` cyan pixels where the candidate puts a plain stripe, at
    least ``min_marker_px`` green/blue pixels where it puts a marker, or at least
    ``min_marker_px`` pixels outside the pattern.  And ``stripe_strength`` (n_reg,) int64, for
    the regions whose stripe margin is 1 (0 for the others): over the candidates inside the
    working volume that contradict one stripe more than the best, the fewest contradicting
    pixels of the strongest stripe that contradicts the candidate and not the best (how well
    the one stripe that tells them apart is seen; all 0 when ``strengths`` is False: a caller
    that scores many pseudo-regions and reads no strength, :func:`gbscan.unwrap.split_row`)."""
    n_reg = rmin.shape[0]
    n_st = is_marker.shape[0]
    status = np.zeros(n_reg, np.int64)
    seen = np.zeros(n_reg, np.int64)
    offset = np.zeros(n_reg, np.int64)
    evidence = np.zeros(n_reg, np.int64)
    mismatch = np.zeros(n_reg, np.int64)
    runner = np.zeros(n_reg, np.int64)
    stripes = np.zeros(n_reg, np.int64)
    strength = np.zeros(n_reg, np.int64)
    big = np.iinfo(np.int64).max // 4
    for k in range(n_reg):
        r0 = rmin[k]
        r1 = rmax[k]
        if r1 < r0:
            continue
        span = r1 - r0 + 1
        cand_A = np.empty(n_st + span + 2, np.int64)
        cand_mis = np.empty(n_st + span + 2, np.int64)
        cand_bad = np.empty(n_st + span + 2, np.int64)
        b0 = start[k]
        n_seen = 0
        c0 = -1
        c1 = -1
        sum_c = 0
        for j in range(span):
            if n_c[b0 + j] >= min_marker_px:
                n_seen += 1
            if n_c[b0 + j] + n_g[b0 + j] >= min_marker_px:
                if c0 < 0:
                    c0 = j
                c1 = j
            sum_c += n_c[b0 + j]
        seen[k] = n_seen
        if c0 < 0:
            status[k] = 1
            continue
        status[k] = 2
        best_mis = big
        best_A = 0
        best_exp = 0
        best_bad = 0
        n_cand = 0
        # A = absolute index of relative r0; the extended position i = A + span (pad = span)
        for A in range(-span, n_st + 1):
            if A + c0 < -2 or A + c1 > n_st + 1 or (A - r0) % 2 != 0:
                continue
            mis = 0
            exp = 0
            bad = 0
            for j in range(span):
                a = A + j
                c = n_c[b0 + j]
                g = n_g[b0 + j]
                # outside the pattern every observation mismatches (O = 1)
                px = contradicting_px(a, c, g, is_marker)
                mis += px
                if px >= min_marker_px:
                    bad += 1
                if 0 <= a < n_st and is_marker[a]:
                    exp += c + g
            cand_A[n_cand] = A
            cand_mis[n_cand] = mis
            cand_bad[n_cand] = bad
            n_cand += 1
            if mis < best_mis:
                best_mis = mis
                best_A = A
                best_exp = exp
                best_bad = bad
        if n_cand == 0:
            continue
        second = big
        fewest = big
        need = frac * npx[k]
        for i in range(n_cand):
            if cand_A[i] != best_A and (npx[k] == 0 or cover[cstart[k] + cand_A[i] + span] >= need):
                second = min(second, cand_mis[i])
                fewest = min(fewest, cand_bad[i])
        inside = npx[k] == 0 or cover[cstart[k] + best_A + span] >= need
        status[k] = 3 if inside else 4
        offset[k] = best_A - r0
        evidence[k] = sum_c + best_exp
        mismatch[k] = best_mis
        runner[k] = second
        stripes[k] = fewest - best_bad if fewest < big else big
        if strengths and stripes[k] == 1:
            weakest = big
            for i in range(n_cand):
                if cand_A[i] == best_A or cand_bad[i] != best_bad + 1 or \
                        not (npx[k] == 0 or cover[cstart[k] + cand_A[i] + span] >= need):
                    continue
                strongest = 0
                for j in range(span):
                    px_c = contradicting_px(cand_A[i] + j, n_c[b0 + j], n_g[b0 + j], is_marker)
                    if px_c >= min_marker_px and \
                            contradicting_px(best_A + j, n_c[b0 + j], n_g[b0 + j], is_marker) < min_marker_px:
                        strongest = max(strongest, px_c)
                weakest = min(weakest, strongest)
            strength[k] = weakest if weakest < big else 0
    return status, seen, offset, evidence, mismatch, runner, stripes, strength



@njit(cache=True, nogil=True)
def region_offset_cover(region, relative, stripe_lo, stripe_hi, rmin, rmax, n_st, step=1):
    """How many pixels of each region each candidate offset keeps inside their allowed stripes.

    ``stripe_lo, stripe_hi`` (H, W) float32: the absolute stripe indices a pixel can see (NaN: no
    bound; the pixel is not counted); ``rmin, rmax`` (n_reg,) the regions' relative index ranges
    (:func:`region_histograms`).  Candidate ``A`` is the absolute index of relative ``rmin[k]``,
    ``A`` in ``[-span, n_st]`` as in :func:`score_offsets`.  Returns flat ``cover`` (int64) with
    region ``k``'s count for ``A`` at ``cstart[k] + A + span``, ``cstart`` (n_reg + 1,) and
    ``npx`` (n_reg,) the region's pixels with bounds (every ``step``-th row and column: a sample
    is enough for a fraction)."""
    n_reg = rmin.shape[0]
    cstart = np.zeros(n_reg + 1, np.int64)
    for k in range(n_reg):
        span = rmax[k] - rmin[k] + 1 if rmax[k] >= rmin[k] else 0
        cstart[k + 1] = cstart[k] + (n_st + span + 2 if span > 0 else 0)
    diff = np.zeros(cstart[n_reg] + 1, np.int64)
    npx = np.zeros(n_reg, np.int64)
    H, W = region.shape
    for v in range(0, H, step):
        for u in range(0, W, step):
            k = region[v, u]
            if k < 0:
                continue
            lo = stripe_lo[v, u]
            hi = stripe_hi[v, u]
            if np.isnan(lo) or np.isnan(hi):
                continue
            span = rmax[k] - rmin[k] + 1
            d = relative[v, u] - rmin[k]
            a = np.int64(np.floor(lo)) - d
            b = np.int64(np.ceil(hi)) - d
            if a < -span:
                a = -span
            if b > n_st:
                b = n_st
            npx[k] += 1
            if a > b:
                continue
            diff[cstart[k] + a + span] += 1
            diff[cstart[k] + b + span + 1] -= 1
    cover = np.zeros(cstart[n_reg], np.int64)
    for k in range(n_reg):
        acc = 0
        for i in range(cstart[k], cstart[k + 1]):
            acc += diff[i]
            cover[i] = acc
    return cover, cstart, npx


@njit(cache=True, nogil=True)
def _sel_region(o, s, k):
    # a row of one segment: its region where the segment is, -1 elsewhere
    m1 = np.int32(-1)
    for u in range(o.size):
        o[u] = k if s[u] >= 0 else m1


@njit(cache=True, nogil=True)
def _sel_rel(o, s, r, p):
    # ... its relative index rel + P, 0 elsewhere
    for u in range(o.size):
        o[u] = r[u] + p if s[u] >= 0 else 0


@njit(cache=True, nogil=True)
def _sel_iso(o, s, neg):
    # ... isolated where the segment is in no region
    for u in range(o.size):
        o[u] = (s[u] >= 0) & neg


@njit(cache=True, nogil=True)
def paint_regions(seg, rel, seg_region, seg_P):
    """Per pixel: region id of its segment (-1), relative index ``rel + P[segment]`` (0 outside
    segments) and whether it is *isolated*: in a segment of no region (bool).

    Row by row, each output written once: a row without segments by constants, a row of one
    segment by three vector loops, others pixel by pixel (plane 0.24-0.29 -> 0.10-0.12 ms).
    """
    H, W = seg.shape
    region = np.empty((H, W), np.int32)
    relative = np.empty((H, W), np.int32)
    isolated = np.empty((H, W), np.bool_)
    for v in range(H):
        sr = seg[v]
        rr = rel[v]
        rg = region[v]
        rl = relative[v]
        iso = isolated[v]
        lo, hi = _minmax_nonneg(sr)
        if hi < 0:
            fill_row(rg, np.int32(-1))
            fill_row(rl, np.int32(0))
            fill_row(iso, False)
        elif lo == hi:
            k = seg_region[hi]
            _sel_region(rg, sr, k)
            _sel_rel(rl, sr, rr, seg_P[hi])
            _sel_iso(iso, sr, k < 0)
        else:
            fill_row(rg, np.int32(-1))
            fill_row(rl, np.int32(0))
            fill_row(iso, False)
            for u in range(W):
                s = sr[u]
                if s >= 0:
                    k = seg_region[s]
                    rg[u] = k
                    rl[u] = rr[u] + seg_P[s]
                    iso[u] = k < 0
    return region, relative, isolated


@njit(cache=True, nogil=True)
def repaint_segments(seg, seg_row, seg_u0, seg_u1, which, seg_region, region, isolated):
    """In place: ``region`` (H, W) int32 and ``isolated`` (H, W) bool become what
    :func:`paint_regions` makes of ``seg_region``, rewriting only the pixels of the segments
    ``which`` (int array): the others' regions are as the images were painted (the decoder's
    linking gives a few segments a region)."""
    for i in range(which.size):
        s = which[i]
        v = seg_row[s]
        k = seg_region[s]
        for u in range(seg_u0[s], seg_u1[s] + 1):
            if seg[v, u] == s:
                region[v, u] = k
                isolated[v, u] = k < 0


@njit(cache=True, nogil=True)
def check_vertical_rows(labels, relative, region, rows, bad):
    """:func:`check_vertical`'s flags of the rows ``rows`` (int array) recomputed in place in
    ``bad``: a row's flags depend on it and its two neighbours only."""
    H, W = labels.shape
    for i in range(rows.size):
        v = rows[i]
        b = bad[v]
        for u in range(W):
            b[u] = False
        la, ka, ra = labels[v], region[v], relative[v]
        for w in (v - 1, v + 1):
            if w < 0 or w >= H:
                continue
            lb, kb, rb = labels[w], region[w], relative[w]
            for u in range(W):
                b[u] = b[u] | _clash(la, ka, ra, lb, kb, rb, u)


@njit(cache=True, nogil=True)
def count_codes(mask, n_codes):
    """Histogram of a uint8 code image (n_codes bins)."""
    out = np.zeros(n_codes, np.int64)
    H, W = mask.shape
    for v in range(H):
        for u in range(W):
            c = mask[v, u]
            if c < n_codes:
                out[c] += 1
    return out


@njit(cache=True, nogil=True)
def spacing_cuts(j_x, seg_j0, seg_j1, ratio):
    """Junctions where the boundary spacing along a row jumps by more than ``ratio``.

    On one continuous surface the camera distance between consecutive stripe boundaries changes
    slowly; where a row crosses a depth edge (the colour sequence may look valid there) it jumps.
    For each segment, each interval between located boundaries is compared with the previous
    one; when their ratio leaves [1/ratio, ratio] the junction between them is cut.
    """
    cut = np.zeros(j_x.shape[0], np.uint8)
    for s in range(seg_j0.shape[0]):
        prev_x = np.nan
        prev_s = np.nan
        for j in range(seg_j0[s], seg_j1[s]):
            x = j_x[j]
            if np.isnan(x):
                prev_x = np.nan
                prev_s = np.nan
                continue
            if not np.isnan(prev_x):
                sp = x - prev_x
                if sp <= 0:
                    cut[j] = 1
                elif not np.isnan(prev_s) and (sp > ratio * prev_s or sp * ratio < prev_s):
                    cut[j - 1] = 1
                prev_s = sp
            prev_x = x
    return cut


@njit(cache=True, nogil=True)
def check_vertical(labels, relative, region):
    """Paper step 7 kernel: (H, W) bool, a pixel whose upper or lower neighbour has the same
    colour (not NONE) and region (>= 0) but another relative index."""
    H, W = labels.shape
    bad = np.zeros((H, W), np.bool_)
    for v in range(1, H):
        # branch-free along the row (vectorised): flag both pixels of every bad vertical pair
        la, lb = labels[v], labels[v - 1]
        ka, kb = region[v], region[v - 1]
        ra, rb = relative[v], relative[v - 1]
        ba, bb = bad[v], bad[v - 1]
        for u in range(W):
            c = _clash(la, ka, ra, lb, kb, rb, u)
            ba[u] = ba[u] | c
            bb[u] = bb[u] | c
    return bad


@njit(cache=True, nogil=True, error_model="numpy")
def _clash(la, ka, ra, lb, kb, rb, u):
    # step 7's test of one vertical pair at column u (rows a, b: labels, regions, relative
    # indices): the same colour (not NONE) and region (>= 0) but another index
    return (la[u] != 0) & (ka[u] >= 0) & (lb[u] == la[u]) & (kb[u] == ka[u]) & (ra[u] != rb[u])


@njit(cache=True, nogil=True, error_model="numpy")
def _abs_row(column_rel, region, off1, v, kk, tmp, out, weight):
    # absolute columns of row v into out (W,) (0 where none) and weight (W,) uint8 (1 where one): a
    # column of an indexed region; an unlabelled gap pixel inside a segment (region -1 with a
    # column) takes its left neighbour's region.  off1 = [NaN] + reg_off (indexed by region + 1);
    # kk (W,) int32 and tmp (W,) float32 scratch.  Branch-free loops, one array written per loop
    # (they vectorise; an in-place select would not).  A row of one region (the common case)
    # selects its one offset instead of looking it up per pixel (a gather), without tmp.  A row
    # with no region returns False and writes nothing (rim_mask reads nothing of it).
    W = out.shape[0]
    reg = region[v]
    crel = column_rel[v]
    mn, mx = _minmax_nonneg(reg)
    if mx < 0:   # no region in the row: no columns
        return False
    a = reg[:W - 1]
    b = reg[1:]
    if mn == mx:
        # one region: a pixel has its offset when it or its left neighbour is in the region
        o = off1[mx + 1]
        nan = off1[0]
        t = crel[0] + (o if reg[0] >= 0 else nan)
        weight[0] = np.uint8(t == t)
        out[0] = t if t == t else np.float32(0.0)
        c1 = crel[1:]
        w1 = weight[1:]
        o1 = out[1:]
        for i in range(W - 1):
            t = c1[i] + (o if max(a[i], b[i]) >= 0 else nan)
            w1[i] = np.uint8(t == t)
        for i in range(W - 1):
            t = c1[i] + (o if max(a[i], b[i]) >= 0 else nan)
            o1[i] = t if t == t else np.float32(0.0)
        return True
    else:
        kk[0] = max(reg[0], -1) + 1
        k1 = kk[1:]
        for i in range(W - 1):
            k = b[i]
            k = a[i] if k < 0 else k
            k1[i] = max(k, -1) + 1
        for u in range(W):
            tmp[u] = crel[u] + off1[kk[u]]
    for u in range(W):
        weight[u] = np.uint8(tmp[u] == tmp[u])
    for u in range(W):
        out[u] = tmp[u] if tmp[u] == tmp[u] else np.float32(0.0)
    return True


@njit(cache=True, nogil=True)
def join_transitions(reason, labels, region, gn, bn, contrast, reg_indexed, min_level, min_contrast, dark_code,
                     ok_code):
    """Give back the signal of stripe-transition pixels the classifier called dark (see
    :func:`gbscan.decode.decode`, ``DecodeParams.join_transitions``).

    A pixel is one when its ``reason`` (H, W) uint8 is ``dark_code``, its label NONE, and
    * its row neighbours are GREEN and BLUE (either order), both with reason ``ok_code``;
    * both lie in one region ``k`` of ``region`` (H, W) int32 with ``reg_indexed[k]``, and the
      pixel itself in no region or in ``k`` (the unwrapping counted it as the transition
      between them: a one-pixel gap between two colours is one, ``row_segments``);
    * its normalised channels ``gn + bn`` reach ``min_level`` (a transition's pixel has about
      half of each; the unlit side of a shadow has neither) and its ``contrast`` reaches
      ``min_contrast`` (the modulation a labelled pixel needs).
    Its reason becomes ``ok_code`` in place; the label stays NONE, so the unwrapping and indexing
    that already ran are unchanged.  One pass; a pixel's test reads only labels, regions and the
    reasons of labelled pixels, which the pass does not change, so the order does not matter.
    Returns the joined pixels' flat indices ``v * W + u`` (n,) int64, ascending.
    """
    H, W = reason.shape
    n = 0
    out = np.empty(64, np.int64)
    dc = np.uint8(dark_code)
    oc = np.uint8(ok_code)
    nb = np.uint8(NONE)
    gb = np.uint8(GREEN + BLUE)   # the only pair of labels other than NONE that sums to it (CYAN = 3 with NONE)
    flag = np.zeros(W, np.uint8)
    for v in range(H):
        rr = reason[v]
        ll = labels[v]
        rg = region[v]
        # candidates, branch-free over the row (the background is dark and NONE too): a dark NONE
        # pixel between a green and a blue one
        anyf = np.uint8(0)
        for u in range(1, W - 1):
            a = ll[u - 1]
            c = ll[u + 1]
            f = np.uint8((rr[u] == dc) & (ll[u] == nb) & (a != nb) & (c != nb) & (np.uint8(a + c) == gb))
            flag[u] = f
            anyf |= f
        if anyf == 0:
            continue
        for u in range(1, W - 1):
            if flag[u] == 0:
                continue
            if rr[u - 1] != oc or rr[u + 1] != oc:
                continue
            k = rg[u - 1]
            if k < 0 or rg[u + 1] != k or (rg[u] >= 0 and rg[u] != k) or not reg_indexed[k]:
                continue
            if gn[v, u] + bn[v, u] < min_level or contrast[v, u] < min_contrast:
                continue
            rr[u] = oc
            if n == out.size:
                grown = np.empty(2 * n, np.int64)
                grown[:n] = out
                out = grown
            out[n] = v * W + u
            n += 1
    return out[:n].copy()


@njit(cache=True, nogil=True, error_model="numpy")
def _slide_sum(acc, rin, rout):
    # acc += rin, then acc -= rout (a running sum's row in and row out, in that order)
    for u in range(acc.size):
        acc[u] = acc[u] + rin[u] - rout[u]


@njit(cache=True, nogil=True, error_model="numpy")
def _add_sum(acc, rin):
    for u in range(acc.size):
        acc[u] += rin[u]


@njit(cache=True, nogil=True, error_model="numpy")
def _sub_sum(acc, rout):
    for u in range(acc.size):
        acc[u] -= rout[u]


@njit(cache=True, nogil=True, error_model="numpy")
def _pull_flags(num, den, row, roww, max_pull_px, flag):
    # rim_mask's pull rule over a row: flag (W,) 1 where a column is pulled by more than
    # max_pull_px (den * pull, no division); returns whether any
    anyf = np.uint8(0)
    for u in range(flag.size):
        dn = np.float64(den[u])
        dev = num[u] - row[u] * dn
        x = np.uint8((roww[u] != 0) & (abs(dev) > max_pull_px * dn))
        flag[u] = x
        anyf |= x
    return anyf


@njit(cache=True, nogil=True, error_model="numpy")
def _nan_flags(crel, out):
    # out (W,) 1 where the row has no column
    for u in range(out.size):
        out[u] = np.uint8(crel[u] != crel[u])


@njit(cache=True, nogil=True, error_model="numpy")
def _end_need(gap, e, roww, flag, near, need):
    # rim_mask's end rule, the pixels to look at: need (W,) 1 where a pixel has a column, no pull
    # hit, and a pixel without one within e px (gap (W + 2 e,): 1 where none, the e px beyond
    # either side 1: the image's side); near (W,) scratch.  Returns whether any
    for u in range(near.size):
        near[u] = gap[u]
    for d in range(1, 2 * e + 1):
        g = gap[d:]
        for u in range(near.size):
            near[u] |= g[u]
    anyn = np.uint8(0)
    for u in range(need.size):
        x = np.uint8((roww[u] != 0) & (flag[u] == 0)) & near[u]
        need[u] = x
        anyn |= x
    return anyn


@njit(cache=True, nogil=True, error_model="numpy")
def rim_mask(column_rel, region, reg_off, reason, half_px, max_pull_px, end_px, rim_code, pull_out, end_isolated,
             end_overflow=False, labels=np.zeros((0, 0), np.uint8), end_reach=0):
    """Mask ``rim_code`` into ``reason`` (H, W) uint8, in place where it is 0, where a column is
    unreliable near a silhouette or bend (see :func:`gbscan.decode.rim_rule`); returns the count.

    column_rel (H, W) float32 relative columns; region (H, W) int32; reg_off (n_regions,) float32
    absolute offset (projector px) per region, NaN where the region is not indexed.
    * *pull*: ``|M[c] - c| > max_pull_px`` (0: off), M the vertical mean over rows
      ``v - half_px .. v + half_px`` of the finite absolute columns (a box with the variance of the
      decoder's along-stripe Gaussian when ``half_px ~ sqrt(3) sigma``), by running sums.
    * *end*: at most ``end_px`` (0: off) px from the end of the pixel's row stretch of columns
      and as close to a pixel whose reason is 1..3 (no signal: dark, saturated, low contrast) or
      to the image's left or right side (nothing measured beyond); with ``end_isolated`` also
      when the next pixel along the row has reason 0 but no region (a striped pixel no region
      holds: a fragment of another surface, reported "isolated" later); with ``end_overflow``
      also when the next two pixels have reason 0, a region, no column and the pixel's colour in
      ``labels`` (H, W) uint8 (its run goes on past the columns' reach: see
      :func:`gbscan.decode.rim_rule`); with ``end_reach`` > 0 (and ``end_px`` > 0), at a stretch
      end next to reason 1..3 or the image's side, the stretch's pixel with reason 1..3 farthest
      from that end within its last ``end_reach`` px counts as the end: from ``end_px`` before it
      to the end, the pixels with an absolute column and reason 0 are masked (after the other
      rules, per row).
    ``pull_out`` (H, W) float32 receives ``M[c] - c`` (pass a (0, 0) array to skip).
    Row-major with per-image-column accumulators; no image-size temporaries.  Per row: the pull
    test branch-free over the row, the end test's window only where the window is not all
    columns (a stretch end), and the few flagged pixels found through the flag rows read as
    uint64 words (ctz64 of a word: its next flagged byte), then masked in order (as one
    sequential pass would).  The row loops are functions of their own writing one array each,
    indexed from 0 (so they vectorise; inside this function the end rule's did not): plane
    0.50 -> 0.27 ms.
    """
    H, W = column_rel.shape
    want = pull_out.shape[0] == H and pull_out.shape[1] == W
    n_ring = 2 * half_px + 2
    ring = np.empty((n_ring, W), np.float32)   # absolute columns of rows v - half_px - 1 .. v + half_px
    ring_w = np.empty((n_ring, W), np.uint8)    # ... 1 where there is one
    has = np.zeros(n_ring, np.bool_)            # ... whether the row has region pixels at all
    num = np.zeros(W, np.float64)
    den = np.zeros(W, np.int32)     # the window's count of columns (exact: as float64 sums of 1.0)
    kk = np.empty(W, np.int32)
    tmp = np.empty(W, np.float32)
    Wp = (W + 7) & ~7
    flag = np.zeros(Wp, np.uint8)    # pull rule hits
    need = np.zeros(Wp, np.uint8)    # pixels whose end-rule window must be looked at
    e = max(end_px, 0)
    gap = np.ones(W + 2 * e, np.uint8)   # 1 where no column, padded by e px of 1 each side
    near = np.empty(W, np.uint8)     # 1 where a pixel without a column is within end_px
    flag64 = flag.view(np.uint64)
    need64 = need.view(np.uint64)
    off1 = np.empty(reg_off.shape[0] + 1, np.float32)
    off1[0] = np.nan
    off1[1:] = reg_off
    pull = max_pull_px > 0
    rc = np.uint8(rim_code)
    n_rim = 0
    # the running sums skip the rows without a region (adding their zeros changes nothing: the
    # sums are never -0.0)
    for v in range(min(half_px, H)):
        has[v % n_ring] = _abs_row(column_rel, region, off1, v, kk, tmp, ring[v % n_ring], ring_w[v % n_ring])
        if has[v % n_ring]:
            _add_sum(num, ring[v % n_ring])
            _add_sum(den, ring_w[v % n_ring])
    for v in range(H):
        va = v + half_px                      # row entering the window
        vb = v - half_px - 1                  # row leaving it
        if va < H:
            has[va % n_ring] = _abs_row(column_rel, region, off1, va, kk, tmp, ring[va % n_ring],
                                        ring_w[va % n_ring])
        ins = va < H and has[va % n_ring]
        outs = vb >= 0 and has[vb % n_ring]
        if pull:                              # branch-free running sums
            if ins and outs:
                _slide_sum(num, ring[va % n_ring], ring[vb % n_ring])
                _slide_sum(den, ring_w[va % n_ring], ring_w[vb % n_ring])
            elif ins:
                _add_sum(num, ring[va % n_ring])
                _add_sum(den, ring_w[va % n_ring])
            elif outs:
                _sub_sum(num, ring[vb % n_ring])
                _sub_sum(den, ring_w[vb % n_ring])
        if not has[v % n_ring]:   # no region in row v: nothing to mask
            continue
        row = ring[v % n_ring]
        roww = ring_w[v % n_ring]
        crel = column_rel[v]
        anyf = np.uint8(0)
        if pull:
            anyf = _pull_flags(num, den, row, roww, max_pull_px, flag[:W])
            if want:
                for u in range(W):
                    if roww[u] != 0:
                        dn = np.float64(den[u])
                        pull_out[v, u] = (num[u] - row[u] * dn) / dn
        if end_px > 0:
            # only a pixel with no column somewhere in its window (or whose window leaves the
            # image) can be at a stretch end: the window test runs only there (few pixels)
            _nan_flags(crel, gap[e:e + W])
            anyf |= _end_need(gap, e, roww, flag[:W], near, need[:W])
        if anyf != 0:
            # the flagged pixels, in order: the end rule reads the reasons as masked so far
            rsn = reason[v]
            rg = region[v]
            for wi in range(Wp >> 3):
                m = flag64[wi] | need64[wi]   # bytes 0 or 1: one bit per flagged pixel
                while m != np.uint64(0):
                    u = wi * 8 + (ctz64(m) >> 3)
                    m &= m - np.uint64(1)
                    rim = flag[u] != 0
                    if need[u] != 0:
                        # at the end of the row stretch and next to no signal (reason 1..3) or the
                        # image's side, both within end_px (nothing is measured beyond the side, and
                        # stage 3's windows are cut there: columns 0.3-0.9 projector px off within
                        # 2 px of it)
                        at_end = u - end_px < 0 or u + end_px >= W
                        near_dark = at_end
                        for x in range(max(u - end_px, 0), min(u + end_px, W - 1) + 1):
                            cx = rsn[x]
                            if x != u and cx >= 1 and cx <= 3:
                                near_dark = True
                            elif end_isolated and cx == 0 and rg[x] < 0 and (x == u - 1 or x == u + 1):
                                near_dark = True
                            elif end_overflow and cx == 0 and rg[x] >= 0 and crel[x] != crel[x] and \
                                    (x == u - 1 or x == u + 1):
                                # the run goes on without a column for 2 px or more, in one colour
                                # (a run wider than the stripe the columns reach: two surfaces'
                                # stripes of one colour merged across a silhouette)
                                x2 = 2 * x - u
                                if 0 <= x2 < W and rsn[x2] == 0 and rg[x2] >= 0 and crel[x2] != crel[x2] and \
                                        labels[v, x] == labels[v, u] and labels[v, x2] == labels[v, u]:
                                    near_dark = True
                            if crel[x] != crel[x]:
                                at_end = True
                        rim = at_end and near_dark
                    if rim and rsn[u] == 0:
                        rsn[u] = rc
                        n_rim += 1
        if end_px > 0 and end_reach > 0 and _dark_with_column(crel, reason[v]):
            n_rim += _reach_ends(crel, roww, reason[v], end_px, end_reach, rc)
    return n_rim


@njit(cache=True, nogil=True, error_model="numpy")
def _dark_with_column(crel, rsn):
    # rim_mask's reach rule, whether the row has work: a pixel with reason 1..3 and a column (one
    # interpolated across it), branch-free (most rows have none: the walk below then never runs)
    anyd = np.uint8(0)
    for u in range(crel.size):
        r = rsn[u]
        anyd |= np.uint8((crel[u] == crel[u]) & (r >= 1) & (r <= 3))
    return anyd != 0


@njit(cache=True, nogil=True)
def _reach_ends(crel, roww, rsn, end_px, reach, rc):
    # rim_mask's reach rule over a row (crel (W,) relative columns, roww (W,) 1 where an absolute
    # one, rsn (W,) reasons, in place): at a stretch end next to no signal (reason 1..3) or the
    # image's side, the stretch's no-signal pixel (an interpolated column) farthest from the end
    # within its last ``reach`` px counts as the end: from ``end_px`` before it on, the pixels
    # with an absolute column and reason 0 are masked ``rc``; returns their count
    W = crel.size
    n = 0
    u = 0
    while u < W:
        if crel[u] != crel[u]:
            u += 1
            continue
        a = u
        while u < W and crel[u] == crel[u]:
            u += 1
        b = u - 1                               # the stretch a..b
        # both ends' no-signal pixels first (the masking then cannot feed the other end's search,
        # whatever the code)
        lo = b + 1                              # masked from lo on (none: b + 1)
        if b + 1 >= W or (rsn[b + 1] >= 1 and rsn[b + 1] <= 3):
            for d in range(max(a, b - reach + 1), b):
                if rsn[d] >= 1 and rsn[d] <= 3:
                    lo = max(a, d - end_px)
                    break
        hi = a - 1                              # masked up to hi (none: a - 1)
        if a == 0 or (rsn[a - 1] >= 1 and rsn[a - 1] <= 3):
            for d in range(min(b, a + reach - 1), a, -1):
                if rsn[d] >= 1 and rsn[d] <= 3:
                    hi = min(b, d + end_px)
                    break
        for x in range(a, hi + 1):
            if rsn[x] == 0 and roww[x] != 0:
                rsn[x] = rc
                n += 1
        for x in range(max(lo, hi + 1), b + 1):
            if rsn[x] == 0 and roww[x] != 0:
                rsn[x] = rc
                n += 1
    return n


@njit(cache=True, nogil=True)
def index_tests(status, seen, evidence, mismatch, runner_up, min_markers, max_mismatch, margin, margin_events):
    """:func:`gbscan.unwrap._index_tests` per region (the ``np.select`` of its tests, first failed
    wins): (n,) int8, 0 indexed, 1 nothing scored (status < 3), 2 outside the working volume
    (status 4), 3 fewer than ``min_markers`` markers, 4 mismatch over ``max_mismatch`` of the
    evidence, 5 the runner-up within the margin (``margin`` of the evidence, or ``margin_events``
    marker events of ``evidence / (2 seen)`` px when that is less: ``unwrap._margin_px``)."""
    n = status.shape[0]
    out = np.zeros(n, np.int8)
    for r in range(n):
        ev = np.float64(evidence[r])
        m = margin * ev
        if margin_events > 0 and seen[r] > 0:
            by_events = margin_events * ev / (2.0 * max(seen[r], 1))
            m = min(m, by_events)
        if status[r] < 3:
            out[r] = 1
        elif status[r] == 4:
            out[r] = 2
        elif seen[r] < min_markers:
            out[r] = 3
        elif mismatch[r] > max_mismatch * evidence[r]:
            out[r] = 4
        elif runner_up[r] - mismatch[r] < m:
            out[r] = 5
    return out


@njit(cache=True, nogil=True)
def row_bands(rows, h, H):
    """The rows within ``h`` of any of ``rows`` (sorted, in ``[0, H)``) as maximal runs of
    consecutive rows: ``(first, last)`` int64 arrays (inclusive).  The same rows as
    ``np.cumsum`` of +1 at ``clip(r - h)`` and -1 at ``clip(r + h + 1)`` being positive."""
    a = np.empty(rows.shape[0], np.int64)
    b = np.empty(rows.shape[0], np.int64)
    n = 0
    for r in rows:
        lo = max(np.int64(r) - h, 0)
        hi = min(np.int64(r) + h, H - 1)
        if lo > hi:
            continue
        if n > 0 and lo <= b[n - 1] + 1:
            b[n - 1] = max(b[n - 1], hi)
        else:
            a[n] = lo
            b[n] = hi
            n += 1
    return a[:n], b[:n]


@njit(cache=True, nogil=True)
def paste_window(a, H, W, y0, x0, fill):
    """A window's map ``a`` (h, w) at ``(y0, x0)`` in a new (H, W) map filled with ``fill``
    elsewhere (``out = np.full((H, W), fill); out[y0:y0 + h, x0:x0 + w] = a``, one pass: every
    pixel written once, row by row)."""
    h, w = a.shape
    out = np.empty((H, W), a.dtype)
    for v in range(H):
        row = out[v]
        if y0 <= v < y0 + h:
            fill_row(row[:x0], fill)
            copy_row(row[x0:x0 + w], a[v - y0])
            fill_row(row[x0 + w:], fill)
        else:
            fill_row(row, fill)
    return out
