"""Compiled forms of Python steps of :mod:`gbscan.unwrap` and :mod:`gbscan.decode` (same
results): the vertical votes between the segments of neighbouring rows (paper step 2), the
marker conflicts of linked rows, and the slope samples and verdicts of the components' linking.

Part of :mod:`gbscan.kernels` (its docstring has the conventions)."""
from __future__ import annotations

import numpy as np
from numba import njit

from ._common import CYAN, NONE, run_starts
from .segments import _vertical_votes_sorted


# -- decoder back end: compiled forms of Python steps (same results) -------------------------------
@njit(cache=True, nogil=True)
def _window_slope(img, comp, want, r, col, half_px, min_span_px):
    # one :func:`window_slopes` entry: the outermost finite pixels (of component ``want`` when
    # ``want >= 0``) within col +- half_px are searched from each end (same pair, fewer reads)
    H, W = img.shape
    if r < 0 or r >= H:
        return np.nan
    lo = max(col - half_px, 0)
    hi = min(col + half_px, W - 1)
    a = -1
    for x in range(lo, hi + 1):
        if not np.isnan(img[r, x]) and (want < 0 or comp[r, x] == want):
            a = x
            break
    if a < 0:
        return np.nan
    b = a
    for x in range(hi, a, -1):
        if not np.isnan(img[r, x]) and (want < 0 or comp[r, x] == want):
            b = x
            break
    if b - a >= min_span_px:
        return (img[r, b] - img[r, a]) / (b - a)
    return np.nan


@njit(cache=True, nogil=True)
def _first_slope(img, comp, want, v, d, col, r0, r1, half_px):
    # the first measurable row r0 .. r1-1 rows from v in direction d (``window_slopes`` per row)
    for r in range(r0, r1):
        g = _window_slope(img, comp, want, v + r * d, col, half_px, half_px)
        if not np.isnan(g):
            return g
    return np.nan


@njit(cache=True, nogil=True)
def slope_samples(vc, vk, vl, vv, comp, col_rel, col_abs, region, comps, offsets, rows, half_px):
    """The slopes of :func:`gbscan.unwrap._slope_jumps` for the votes that can decide: vertical
    votes (``vl >= 0``) of a component in ``comps`` (its ``vc``; the offset is checked later).

    Returns per such vote (in vote order): ``c, k`` (int64 component and offset), ``side`` (int64
    -1: the reported pair lies above, 1 below), ``g_c`` the component's slope (``rows .. 2 rows - 1``
    rows into it), ``g_near`` and ``g_deep`` the voting region's (from ``rows`` and ``3 rows`` rows
    into it), float64, NaN where no row was measurable (see ``_slope_jumps``)."""
    H, W = col_rel.shape
    n_c = 0
    for i in range(comps.shape[0]):
        if comps[i] + 1 > n_c:
            n_c = comps[i] + 1
    want_c = np.zeros(max(n_c, 1), np.bool_)
    for i in range(comps.shape[0]):
        if comps[i] >= 0:
            want_c[comps[i]] = True
    n = 0
    for i in range(vc.shape[0]):
        if vl[i] >= 0 and 0 <= vc[i] < n_c and want_c[vc[i]]:
            n += 1
    o_c = np.empty(n, np.int64)
    o_k = np.empty(n, np.int64)
    o_d = np.empty(n, np.int64)
    g_c = np.empty(n, np.float64)
    g_n = np.empty(n, np.float64)
    g_d = np.empty(n, np.float64)
    m = 0
    for i in range(vc.shape[0]):
        if not (vl[i] >= 0 and 0 <= vc[i] < n_c and want_c[vc[i]]):
            continue
        c = vc[i]
        u = vl[i]
        v = vv[i]
        up = v >= 2 and not np.isnan(col_abs[v - 1, u]) and not np.isnan(col_abs[v - 2, u])
        d = -1 if up else 1
        q = min(max(v + d, 0), H - 1)
        src = region[q, u]
        o_c[m] = c
        o_k[m] = vk[i]
        o_d[m] = d
        g_c[m] = _first_slope(col_rel, comp, np.int32(c), v, -d, u, rows, 2 * rows, half_px)
        g_n[m] = _first_slope(col_abs, region, src, v, d, u, rows, 2 * rows, half_px)
        g_d[m] = _first_slope(col_abs, region, src, v, d, u, 3 * rows, 4 * rows, half_px)
        m += 1
    return o_c, o_k, o_d, g_c, g_n, g_d


@njit(cache=True, nogil=True)
def _median_sorted(x, n):
    # numpy's median of the sorted x[:n]: the middle value, or the mean of the middle two
    h = n // 2
    if n % 2 == 1:
        return x[h]
    return (x[h - 1] + x[h]) / 2.0


@njit(cache=True, nogil=True)
def slope_verdicts(c, k, side, lr_near, lr_deep, comps, offsets, lim_near, lim_deep, z_min, min_votes, noise_floor):
    """(len(comps),) bool verdicts of :func:`gbscan.unwrap._slope_jumps` from the per-vote log slope
    ratios (NaN: not measured) of :func:`slope_samples`: for component ``comps[i]`` at offset
    ``offsets[i]``, the *near* ratios of all its votes and the *deep* ones of each side apart, with
    at least ``min_votes`` measured, flag it when ``|median| > lim`` and ``|median| > z_min *
    max(1.4826 MAD, noise_floor) / sqrt(n)`` (numpy's median: mean of the middle two when even)."""
    n_out = comps.shape[0]
    out = np.zeros(n_out, np.bool_)
    buf = np.empty(c.shape[0], np.float64)
    for i in range(n_out):
        for pas in range(3):  # 0: near, all sides; 1: deep, side -1; 2: deep, side 1
            lr = lr_near if pas == 0 else lr_deep
            want_side = 0 if pas == 0 else (-1 if pas == 1 else 1)
            lim = lim_near if pas == 0 else lim_deep
            n = 0
            for j in range(c.shape[0]):
                if c[j] == comps[i] and k[j] == offsets[i] and not np.isnan(lr[j]) and \
                        (want_side == 0 or side[j] == want_side):
                    buf[n] = lr[j]
                    n += 1
            if n < min_votes:
                continue
            s = np.sort(buf[:n])
            med = _median_sorted(s, n)
            dev = np.empty(n, np.float64)
            for j in range(n):
                dev[j] = abs(s[j] - med)
            mad = _median_sorted(np.sort(dev), n)
            spread = max(1.4826 * mad, noise_floor) / np.sqrt(np.float64(n))
            if abs(med) > lim and abs(med) > z_min * spread:
                out[i] = True
    return out


@njit(cache=True, nogil=True)
def marker_conflicts(labels, gn, bn, relative, seg_row, seg_u0, seg_u1, seg_j0, seg_j1, j_ua, j_ub,
                     seg_region, reg_offset, reg_indexed, is_marker, min_run_px, min_events, clean_level,
                     confirm, region, persist_rows, extend=False, seg_agree=np.zeros(0, np.uint8)):
    """Pixels of indexed regions whose own row contradicts the region's marker placement.

    A region's offset is fixed by all of its markers at once; a segment that crossed a depth edge
    where the stripes of two surfaces happen to line up (the colour sequence stays valid) carries
    part of the other surface with a shift of an even number of stripes.  Along each segment the
    runs are checked against the region's offset: a cyan run of at least ``min_run_px`` pixels on
    a marker stripe *agrees*, a cyan run on a non-marker stripe or a green/blue run of at least
    ``min_run_px`` pixels on a marker stripe *disagrees*.  A stretch between two agreeing runs (or
    the segment's end) holding at least ``min_events`` disagreements is rejected, the agreeing
    runs at its ends included (the jump lies somewhere in between, and the boundary next to it
    belongs to neither surface), with the unlabelled gaps between them.  An agreeing run bounds
    the stretch only if the next event beyond it (away from the stretch) agrees too: a strip of
    another surface shifted by an even number of stripes puts one of its markers on a marker
    stripe of the region now and then (the gaps between markers repeat), and the jump then lies
    beyond that marker (the clean preset's multi-object scene: a wall strip welded under the
    sphere, its first marker on one of the sphere's, 14 pixels 24 stripes off); ``confirm``
    False: any agreeing run bounds it.  A coincidental agreement right after a real one still
    bounds the stretch, and the strip's pixels between the two stay (a synthetic weld 10 stripes
    off from stripe 17: 9 px a row).  Passing one more agreeing run always would reject those
    too, but it cost 0.15 points of the 48-scene sweep's coverage (multi-object 0.3-0.7) for no
    wrong pixel fewer there: not done.  A shifted stretch shows
    two kinds of disagreement (its markers where none belong, green/blue where the region's
    markers belong); a single one is usually a marker missed at a rim.  ``is_marker``
    (n_stripes,) bool; stripes outside it are neutral.

    A *clean* disagreement is decisive on its own.  ``gn, bn`` (H, W) float32 are the green and
    blue channels normalised between their local min and max (``gbscan.decode.Classified``).
    A projected marker lights both channels, so even a
    marker pixel the classifier calls green or blue (a missed marker: skin, a rim) keeps the
    other channel well up (``min(gn, bn)`` ~0.3-0.5); on a green or blue stripe the other
    channel sits at its local minimum.  A green/blue run on a marker stripe whose median
    ``min(gn, bn)`` (robust to an edge pixel where lateral chromatic aberration mixes the
    channels) is below ``clean_level`` is therefore no missed marker but another stripe:
    it counts as ``min_events`` disagreements (``clean_level <= 0``: off; ``gn, bn`` are not read).
    Cyan on a non-marker stripe still counts one (glints, the hard preset's noise), unless it is
    a *persistent* marker of another surface: a cyan run between two runs of one colour (green or
    blue, at least ``min_run_px`` each: a marker's flanks, which a cyan fringe at a green|blue
    boundary or a mixed pixel at a silhouette, the segment's end, lacks) whose middle column is
    cyan on the same stripe of the same region (``region`` (H, W) int32) for ``persist_rows``
    consecutive rows counts as ``min_events`` (``persist_rows`` < 2: off, ``region`` is not read).

    ``extend``: a bounding agreeing run that would agree with the stretch's own shift as well
    does not bound it.  The shift is the even one (``d`` stripes) under which the stretch's runs
    agree best (cyan on a marker stripe +1, cyan off one or green/blue on one -1; its agreeing
    end runs left out; when several tie, all of them), if their sum reaches ``min_events``
    (else the bounds stay).  When the marker gaps repeat (stripes 90, 96, 102: a shift of 6
    maps the region's marker and its confirming one onto markers), an agreeing run and its
    confirmation fit both surfaces, and the jump may lie before either.  The stretch then runs
    on past such runs to the first run that fits the region and not the shift (cyan on a marker
    stripe ``A`` with ``A + d`` none, or green/blue on a stripe ``A`` that is none with
    ``A + d`` one), which it includes (the boundary beside it belongs to neither surface).
    ``seg_agree`` (n_seg,) uint8, when given, receives 1 for the segments of indexed regions with
    an agreeing run (0 elsewhere; see :func:`grow_conflicts`).
    Returns the rejected spans, (n, 3) int32 rows ``(v, u_first, u_last)``.
    """
    H, W = labels.shape
    want_agree = seg_agree.shape[0] == seg_row.shape[0]
    if want_agree:
        seg_agree[:] = 0
    spans = np.empty((16, 3), np.int32)
    n_sp = 0
    n_st = is_marker.shape[0]
    cap = W + 2
    ev = np.zeros(cap, np.int32)    # per run: +1 agree, -w disagree (w its weight), 0 neutral
    ra = np.zeros(cap, np.int32)    # run start / end pixel
    rb = np.zeros(cap, np.int32)
    rl = np.zeros(cap, np.uint8)     # per run: its colour when at least min_run_px long, else 0
    mb = np.empty(cap, np.float32)   # a run's min(gn, bn), sorted
    ar = np.zeros(cap, np.int64)     # per run: its absolute stripe in the region, -1 outside the pattern
    best = np.zeros(2 * n_st + 1, np.bool_)   # extend: the stretch's best shifts (index d + n_st)
    for s in range(seg_row.shape[0]):
        k = seg_region[s]
        if k < 0 or not reg_indexed[k]:
            continue
        v = seg_row[s]
        nr = 0
        any_bad = False
        a = seg_u0[s]
        for j in range(seg_j0[s], seg_j1[s] + 1):
            b = j_ua[j] if j < seg_j1[s] else seg_u1[s]
            ra[nr] = a
            rb[nr] = b
            e = 0
            lab = labels[v, a]        # a run starts with its colour (spikes and gaps merged inside)
            rr = relative[v, a]
            A = rr + reg_offset[k]
            ar[nr] = A if 0 <= A < n_st else -1
            if b - a + 1 >= min_run_px and lab != 0 and ar[nr] >= 0:
                e = _shift_event(lab, A, is_marker)
                if e == -1 and lab != CYAN and clean_level > 0 and _run_median_min(gn, bn, v, a, b, mb) < clean_level:
                    e = -min_events
            ev[nr] = e
            rl[nr] = lab if b - a + 1 >= min_run_px else 0
            if e < 0:
                any_bad = True
            elif e > 0 and want_agree:
                seg_agree[s] = 1
            nr += 1
            if j < seg_j1[s]:
                a = j_ub[j]
        if not any_bad:
            continue
        if persist_rows > 1:
            for i in range(1, nr - 1):
                if ev[i] == -1 and rl[i] == CYAN and rl[i - 1] == rl[i + 1] and rl[i - 1] != 0 and \
                        rl[i - 1] != CYAN and _cyan_rows(labels, relative, region, v, (ra[i] + rb[i]) // 2,
                                                         relative[v, ra[i]], k, persist_rows) >= persist_rows:
                    ev[i] = -min_events
        for i in range(nr):
            if ev[i] >= 0:
                continue
            lo = i
            while lo > 0 and not (ev[lo] == 1 and (not confirm or _confirmed(ev, lo, -1, nr))):
                lo -= 1
            hi = i
            while hi < nr - 1 and not (ev[hi] == 1 and (not confirm or _confirmed(ev, hi, 1, nr))):
                hi += 1
            n_bad = 0
            for m in range(lo, hi + 1):
                if ev[m] < 0:
                    n_bad -= ev[m]
            if n_bad < min_events:   # one odd run is noise (a marker missed at a rim, a cyan glint)
                continue
            if extend and _best_shifts(ev, rl, ar, lo, hi, is_marker, best, min_events):
                while ev[lo] == 1 and _fits_shift(lo, rl, ar, is_marker, best, True):
                    lo = _next_decisive(rl, ar, lo, -1, nr, is_marker, best)
                    if lo < 0:
                        lo = 0
                        break
                while ev[hi] == 1 and _fits_shift(hi, rl, ar, is_marker, best, True):
                    hi = _next_decisive(rl, ar, hi, 1, nr, is_marker, best)
                    if hi < 0:
                        hi = nr - 1
                        break
            if n_sp == spans.shape[0]:
                grown = np.empty((2 * n_sp, 3), np.int32)
                grown[:n_sp] = spans
                spans = grown
            spans[n_sp, 0] = v                  # unlabelled gaps too (finish_pixels may fill them)
            spans[n_sp, 1] = ra[lo]
            spans[n_sp, 2] = rb[hi]
            n_sp += 1
    return spans[:n_sp].copy()


@njit(cache=True, nogil=True)
def _run_median_min(gn, bn, v, a, b, buf):
    # marker_conflicts: the median of min(gn, bn) over pixels a..b of row v (_median_sorted of them
    # sorted by insertion in buf)
    n = 0
    for x in range(a, b + 1):
        t = min(gn[v, x], bn[v, x])
        i = n
        while i > 0 and buf[i - 1] > t:
            buf[i] = buf[i - 1]
            i -= 1
        buf[i] = t
        n += 1
    return _median_sorted(buf, n)


@njit(cache=True, nogil=True)
def _cyan_rows(labels, relative, region, v, u, rr, k, most):
    # marker_conflicts: the consecutive rows through (v, u), up to ``most``, where column u is cyan
    # on relative stripe rr of region k
    H = labels.shape[0]
    if labels[v, u] != CYAN:
        return 0
    n = 1
    q = v - 1
    while q >= 0 and n < most and labels[q, u] == CYAN and relative[q, u] == rr and region[q, u] == k:
        n += 1
        q -= 1
    q = v + 1
    while q < H and n < most and labels[q, u] == CYAN and relative[q, u] == rr and region[q, u] == k:
        n += 1
        q += 1
    return n


@njit(cache=True, nogil=True)
def grow_conflicts(rejected, seg_map, region, seg_row, seg_u0, seg_u1, seg_region, reg_indexed, seg_agree):
    """Grow rejected pixels up and down a welded strip whose rows hold no evidence of their own.

    ``rejected`` (H, W) bool, in place: the pixels :func:`marker_conflicts` rejects.  A segment of
    an indexed region (``seg_region``, ``reg_indexed``) with no agreeing run (``seg_agree`` 0) and
    no rejected pixel yet (a part rejected: its row's evidence bounds it) whose span touches a
    rejected pixel of the same region (``region`` (H, W) int32) in the row above or below is
    rejected whole; repeated until nothing changes (a strip's rows without a marker of their own
    -- segments of 3-4 stripes often have none -- go with the rows whose markers reject it).
    ``seg_map`` (H, W) int32 the segment of each pixel (-1 none).  Returns the (n,) int64
    segments rejected so.
    """
    H, W = rejected.shape
    n_seg = seg_row.shape[0]
    cand = np.zeros(n_seg, np.uint8)
    n_c = 0
    for s in range(n_seg):
        k = seg_region[s]
        if k >= 0 and reg_indexed[k] and seg_agree[s] == 0:
            v = seg_row[s]
            touched = False                 # (a segment with rejected pixels: its row's evidence bounds them)
            for u in range(seg_u0[s], seg_u1[s] + 1):
                if rejected[v, u]:
                    touched = True
                    break
            if not touched:
                cand[s] = 1
                n_c += 1
    out = np.empty(n_seg, np.int64)
    n = 0
    if n_c == 0:
        return out[:0].copy()
    changed = True
    while changed:
        changed = False
        for s in range(n_seg):
            if cand[s] == 0:
                continue
            v = seg_row[s]
            k = seg_region[s]
            hit = False
            for vv in (v - 1, v + 1):
                if vv < 0 or vv >= H:
                    continue
                for u in range(seg_u0[s], seg_u1[s] + 1):
                    if rejected[vv, u] and region[vv, u] == k:
                        hit = True
                        break
                if hit:
                    break
            if hit:
                cand[s] = 0
                for u in range(seg_u0[s], seg_u1[s] + 1):
                    if seg_map[v, u] == s:
                        rejected[v, u] = True
                out[n] = s
                n += 1
                changed = True
    return out[:n].copy()


@njit(cache=True, nogil=True)
def _shift_event(lab, B, is_marker):
    # marker_conflicts' event of a run of colour lab (0: too short) on absolute stripe B (the
    # region's, or under a shift): +1 cyan on a marker stripe, -1 cyan off one or green/blue on
    # one (or outside the pattern), 0 otherwise
    n_st = is_marker.shape[0]
    if lab == 0:
        return 0
    if B < 0 or B >= n_st:
        return -1
    if lab == CYAN:
        return 1 if is_marker[B] else -1
    return -1 if is_marker[B] else 0


@njit(cache=True, nogil=True)
def _best_shifts(ev, rl, ar, lo, hi, is_marker, best, min_events):
    # marker_conflicts' extend: best[d + n_st] True for the even shifts d != 0 under which runs
    # lo..hi agree best (their events' sum), its agreeing end runs left out (which surface they
    # fit is the question); returns whether the best sum reaches min_events (a shift as well
    # supported as a rejection must be: with one agreement to go on, shifts tie by the dozen)
    n_st = is_marker.shape[0]
    top = 0
    best[:] = False
    m0 = lo + 1 if ev[lo] == 1 else lo
    m1 = hi - 1 if ev[hi] == 1 else hi
    for i in range(-n_st // 2, n_st // 2 + 1):
        d = 2 * i
        if d == 0:
            continue
        sc = 0
        for m in range(m0, m1 + 1):
            if rl[m] != 0 and ar[m] >= 0:
                sc += _shift_event(rl[m], ar[m] + d, is_marker)
        if sc > top:
            top = sc
            best[:] = False
        if sc == top and sc > 0:
            best[d + n_st] = True
    return top >= min_events


@njit(cache=True, nogil=True)
def _fits_shift(m, rl, ar, is_marker, best, agree):
    # agree True: whether run m agrees (cyan on a marker stripe) under some best shift;
    # False: whether it disagrees under every best shift (it fits the region only)
    n_st = is_marker.shape[0]
    if rl[m] == 0 or ar[m] < 0:
        return False
    for j in range(2 * n_st + 1):
        if best[j]:
            e = _shift_event(rl[m], ar[m] + j - n_st, is_marker)
            if agree and e == 1:
                return True
            if not agree and e != -1:
                return False
    return not agree


@njit(cache=True, nogil=True)
def _next_decisive(rl, ar, p, step, nr, is_marker, best):
    # marker_conflicts' extend: the first run beyond p (direction step) that fits the region and
    # no best shift (its event under the region 0 or +1, -1 under every best shift); -1 if none
    q = p + step
    while 0 <= q < nr:
        if rl[q] != 0 and ar[q] >= 0 and _shift_event(rl[q], ar[q], is_marker) >= 0 and \
                _fits_shift(q, rl, ar, is_marker, best, False):
            return q
        q += step
    return -1


@njit(cache=True, nogil=True)
def _confirmed(ev, p, step, nr):
    # marker_conflicts: whether the first non-neutral event beyond run p (direction step) agrees
    q = p + step
    while 0 <= q < nr:
        if ev[q] != 0:
            return ev[q] == 1
        q += step
    return False


@njit(cache=True, nogil=True)
def _flush_pair(table, touched, n_t, out, ne):
    # the edge of one pair from its votes per offset (table[off + 2048], 4095: overlap only) into
    # out[2:6, ne] (offset, agree, same, overlap); the table is cleared.  The smallest offset wins ties.
    best_c = 0
    best_off = 0
    tot = 0
    over = 0
    for i in range(n_t):
        kk = touched[i]
        c = table[kk]
        table[kk] = 0
        over += c
        if kk == 4095:
            continue
        tot += c
        if c > best_c or (c == best_c and kk - 2048 < best_off):
            best_c = c
            best_off = kk - 2048
    out[2, ne] = best_off
    out[3, ne] = best_c
    out[4, ne] = tot
    out[5, ne] = over


@njit(cache=True, nogil=True)
def _row_keys(sr, tr, lr, lu, rr, ru, n_seg, key):
    # per pixel of a row: vertical_votes' key (pair * 4096 + offset + 2048), -1 where it has none
    # (branch-free, vectorised)
    for u in range(key.shape[0]):
        s = sr[u]
        t = tr[u]
        lab = lr[u]
        labu = lu[u]
        d = min(max(ru[u] - rr[u], -2047), 2046)
        off = 2047 if lab != labu else d
        k = (np.int64(s) * n_seg + t) * 4096 + (off + 2048)
        valid = (s >= 0) & (t >= 0) & (lab != NONE) & (labu != NONE)
        key[u] = k if valid else np.int64(-1)   # (an int32 key: vertical_votes checked k fits)


@njit(cache=True, nogil=True)
def vertical_votes(labels, seg, rel, n_seg):
    """Paper step 2 kernel: relate every segment to the overlapping segments of the row above.

    For each pixel whose upper neighbour has the same colour label, the pair (segment, segment
    above) votes for the offset ``rel_above - rel``.  Returns edges ``(s, t, offset, n_agree,
    n_same, n_overlap)``: for each overlapping pair the winning offset (the smallest among equal
    counts), its votes, all same-label votes and all labelled pixel pairs, in the order of the pairs.

    Segments numbered row by row, left to right, with disjoint spans (as :func:`row_segments` and
    :func:`apply_cuts` make them) meet the pairs in that order along the rows: each pair's votes
    are counted as it passes (a table per offset), no sort.  Otherwise (a pair seen again after
    another) :func:`_vertical_votes_sorted` gives the same edges by sorting.

    Per row, every pixel's key (pair, offset) by a vector loop, then the runs of equal keys found
    64 pixels at a time (a bit mask of the changes) and counted per run, not per pixel (plane
    0.73 -> 0.30 ms, head 0.19 -> 0.12; the same edges, bit for bit).  The keys are int32 where
    they fit (fewer than 725 segments; plane 0.20 -> 0.19 ms, head 0.144 -> 0.130 for two calls).
    """
    H, W = labels.shape
    if np.int64(n_seg) * n_seg * 4096 <= 2**31 - 1:   # every key fits int32: twice the pixels per vector
        return _votes_counted(labels, seg, rel, n_seg, np.empty(W, np.int32))
    return _votes_counted(labels, seg, rel, n_seg, np.empty(W, np.int64))


@njit(cache=True, nogil=True)
def _votes_counted(labels, seg, rel, n_seg, key):
    # vertical_votes with a row's keys in ``key`` (W,) (int32 or int64)
    H, W = labels.shape
    # s, t, offset, agree, same, overlap (a pair per pixel at most)
    out = np.empty((6, max(H - 1, 0) * W + 1), np.int32)
    table = np.zeros(4096, np.int32)     # votes per offset + 2048 of the current pair (4095: overlap only)
    touched = np.empty(4096, np.int32)
    st = np.empty(W + 1, np.int64)
    n_t = 0
    ne = 0
    pair = np.int64(-1)   # current pair s * n_seg + t
    cur = np.int64(-1)    # current key pair * 4096 + offset + 2048 and its count since the last change
    cnt = 0
    for v in range(1, H):
        if W == 0:
            continue
        _row_keys(seg[v], seg[v - 1], labels[v], labels[v - 1], rel[v], rel[v - 1], n_seg, key)
        nk = run_starts(key, st)
        for i in range(nk):
            kk0 = np.int64(key[st[i]])
            if kk0 < 0:    # no vote (a pixel without a segment or a label, or above one)
                continue
            ln = st[i + 1] - st[i]
            if kk0 == cur:
                cnt += ln
                continue
            if cnt > 0:   # the run of one key ends: into the pair's table
                kk = cur & 4095
                if table[kk] == 0:
                    touched[n_t] = kk
                    n_t += 1
                table[kk] += cnt
            p = kk0 >> 12
            if p != pair:
                if pair >= 0:
                    _flush_pair(table, touched, n_t, out, ne)
                    out[0, ne] = pair // n_seg
                    out[1, ne] = pair % n_seg
                    ne += 1
                    n_t = 0
                if p < pair:
                    # pairs out of order (another numbering of the segments): sort instead
                    return _vertical_votes_sorted(labels, seg, rel, n_seg)
                pair = p
            cur = kk0
            cnt = ln
    if cnt > 0:
        kk = cur & 4095
        if table[kk] == 0:
            touched[n_t] = kk
            n_t += 1
        table[kk] += cnt
    if pair >= 0:
        _flush_pair(table, touched, n_t, out, ne)
        out[0, ne] = pair // n_seg
        out[1, ne] = pair % n_seg
        ne += 1
    return (out[0, :ne].copy(), out[1, :ne].copy(), out[2, :ne].copy(), out[3, :ne].copy(), out[4, :ne].copy(),
            out[5, :ne].copy())


# -- the votes of unwrap.link_components grouped (was numpy group-by glue) --------------------------
@njit(cache=True, nogil=True)
def best_vote_offsets(vc, k, good, vl, vv, n_comp, H, W):
    """Group the column-continuity votes of :func:`gbscan.unwrap.link_components` per component.

    ``vc`` (n,) component of each vote, ``k`` its offset (periods of two stripes), ``good`` whether
    it agrees with that offset within the tolerance, ``vl`` its line (column ``>= 0`` or
    ``-1 - row``), ``vv`` its candidate pixel's row; components are ``0 .. n_comp - 1``, lines in
    ``[-H, W)``, rows in ``[0, H)``.  Returns ``n_all`` (n_comp,) int64 votes per component, the
    number of components with votes, and, per component with agreeing votes (ascending), its best
    offset: ``c, k, cnt`` (most agreeing votes; ties: the smallest offset) and that offset's
    distinct lines ``n_lines`` and candidate rows ``n_rows`` (all int64)."""
    n_all = np.zeros(n_comp, np.int64)
    for i in range(vc.shape[0]):
        n_all[vc[i]] += 1
    tried = 0
    for c in range(n_comp):
        tried += n_all[c] > 0
    # agreeing votes sorted by (component, offset)
    ng = 0
    for i in range(vc.shape[0]):
        ng += good[i]
    gi = np.empty(ng, np.int64)
    ng = 0
    for i in range(vc.shape[0]):
        if good[i]:
            gi[ng] = i
            ng += 1
    kmin = 0
    kmax = 0
    for q in range(ng):
        x = k[gi[q]]
        if q == 0 or x < kmin:
            kmin = x
        if q == 0 or x > kmax:
            kmax = x
    span = kmax - kmin + 1
    pair = np.empty(ng, np.int64)
    for q in range(ng):
        pair[q] = np.int64(vc[gi[q]]) * span + (k[gi[q]] - kmin)
    o = np.argsort(pair)
    # per (component, offset) group: votes, distinct lines and rows (marks hold the group number)
    line_mark = np.full(H + W, -1, np.int64)
    row_mark = np.full(H, -1, np.int64)
    bc = np.empty(ng, np.int64)
    bk = np.empty(ng, np.int64)
    bcnt = np.empty(ng, np.int64)
    blines = np.empty(ng, np.int64)
    brows = np.empty(ng, np.int64)
    nb = 0
    g = 0
    a = 0
    while a < ng:
        key = pair[o[a]]
        cnt = 0
        nl = 0
        nr = 0
        b = a
        while b < ng and pair[o[b]] == key:
            i = gi[o[b]]
            cnt += 1
            li = vl[i] + H
            if line_mark[li] != g:
                line_mark[li] = g
                nl += 1
            if row_mark[vv[i]] != g:
                row_mark[vv[i]] = g
                nr += 1
            b += 1
        c = key // span
        # groups come by ascending (component, offset): the first of the most votes wins
        if nb == 0 or bc[nb - 1] != c:
            bc[nb] = c
            bk[nb] = key % span + kmin
            bcnt[nb] = cnt
            blines[nb] = nl
            brows[nb] = nr
            nb += 1
        elif cnt > bcnt[nb - 1]:
            bk[nb - 1] = key % span + kmin
            bcnt[nb - 1] = cnt
            blines[nb - 1] = nl
            brows[nb - 1] = nr
        g += 1
        a = b
    return n_all, tried, bc[:nb], bk[:nb], bcnt[:nb], blines[:nb], brows[:nb]


@njit(cache=True, nogil=True)
def component_row_span(seg_comp, seg_row, comps):
    """Rows spanned by each of ``comps``: ``max - min + 1`` of the rows of the segments whose
    ``seg_comp`` is it (int64; as ``np.minimum.at`` / ``np.maximum.at`` into int64 max / -1)."""
    n = seg_comp.shape[0]
    lo = np.full(n, np.iinfo(np.int64).max, np.int64)
    hi = np.full(n, -1, np.int64)
    for s in range(n):
        c = seg_comp[s]
        if c >= 0:
            r = np.int64(seg_row[s])
            if r < lo[c]:
                lo[c] = r
            if r > hi[c]:
                hi[c] = r
    out = np.empty(comps.shape[0], np.int64)
    for q in range(comps.shape[0]):
        out[q] = hi[comps[q]] - lo[comps[q]] + 1
    return out
