"""Paper steps 1-2 and the segment bookkeeping of :mod:`gbscan.unwrap`: runs and segments along
the rows (:func:`row_segments`), the vertical votes between segments, union-find links, the
junctions' sub-pixel positions and fits, the columns interpolated between them, cuts.

Part of :mod:`gbscan.kernels` (its docstring has the conventions)."""
from __future__ import annotations

import numpy as np
from numba import njit

from ._common import BLUE, CYAN, GREEN, NONE, contradicts, copy_row, fill_row, fit_add, fit_slope, run_starts


@njit(cache=True, nogil=True)
def _merges(rs, re, rl, left, i, gaps, limit_px):
    # _merge_runs_pass' test: candidate run i merges with its left neighbour (run ``left``, final
    # so far) and run i + 1 (branch-free: the operands are all in hand)
    if gaps:
        merge = rl[i] == NONE
    else:
        merge = (rl[i] != NONE) & (re[left] + 1 == rs[i]) & (re[i] + 1 == rs[i + 1])
    return merge & (re[i] - rs[i] + 1 <= limit_px) & (rl[left] != NONE) & (rl[left] == rl[i + 1])


@njit(cache=True, nogil=True)
def _merge_runs_pass(rs, re, rl, nr, gaps, limit_px):
    """One left-to-right merging pass of :func:`row_segments` over the runs ``0 .. nr-1`` of a row
    (in place; returns the new count).  ``gaps`` False (spikes): a coloured run of at most
    ``limit_px`` px directly between two runs of one colour is merged with both into the left
    one; True (gaps): a NONE run of at most ``limit_px`` px between two runs of one colour joins
    them.  The merged run is then the left neighbour of the next candidate.  One pass (merging by
    shifting the rest of the row was quadratic).  The runs before the first merge are final as
    they are: the pass starts there (most rows have none: both passes 0.21 -> 0.08 ms over a 640x480
    plane)."""
    if nr < 3:
        return nr
    # the first candidate that merges with its untouched neighbours (none: nothing to do)
    i = 1
    while i < nr - 1 and not _merges(rs, re, rl, i - 1, i, gaps, limit_px):
        i += 1
    if i >= nr - 1:
        return nr
    m = i          # runs 0 .. m-1 are final; run i is the candidate, i + 1 its right neighbour
    while i < nr - 1:
        if _merges(rs, re, rl, m - 1, i, gaps, limit_px):
            re[m - 1] = re[i + 1]      # merge m-1, i, i+1
            i += 2
        else:
            rs[m] = rs[i]
            re[m] = re[i]
            rl[m] = rl[i]
            m += 1
            i += 1
    while i < nr:
        rs[m] = rs[i]
        re[m] = re[i]
        rl[m] = rl[i]
        m += 1
        i += 1
    return m


@njit(cache=True, nogil=True)
def _end_pixel(rl, rs, re, k, beyond, other):
    # _marker_flank_pass's end_flank test: run k is one green or blue pixel whose neighbour away
    # from the marker (run ``beyond``; -1: the image side) is unlabelled, and whose colour
    # contradicts ``other``, the marker's other flank (green or blue)
    return ((rl[k] == GREEN or rl[k] == BLUE) and re[k] == rs[k] and (beyond < 0 or rl[beyond] == NONE)
            and (other == GREEN or other == BLUE) and other != rl[k])


@njit(cache=True, nogil=True)
def _lone_pixels(rs, re, rl, nr, i):
    # a necessary condition of _end_pixel beside marker run i (1 <= i <= nr - 2): run i - 1 or
    # i - 2 (i + 1 or i + 2) is one pixel with the image side or an unlabelled run beyond it.
    # Branch-free over clamped indices (branches here cost more than the test saves).
    a1 = i - 1
    a2 = max(i - 2, 0)
    a3 = max(i - 3, 0)
    b1 = i + 1
    b2 = min(i + 2, nr - 1)
    b3 = min(i + 3, nr - 1)
    left1 = (re[a1] == rs[a1]) & ((i - 2 < 0) | (rl[a2] == NONE))
    left2 = (i - 2 >= 0) & (re[a2] == rs[a2]) & ((i - 3 < 0) | (rl[a3] == NONE))
    right1 = (re[b1] == rs[b1]) & ((i + 2 >= nr) | (rl[b2] == NONE))
    right2 = (i + 2 < nr) & (re[b2] == rs[b2]) & ((i + 3 >= nr) | (rl[b3] == NONE))
    return left1 | left2 | right1 | right2


@njit(cache=True, nogil=True)
def _marker_flank_pass(rs, re, rl, nr, limit_px, max_gap_px, end_flank=False):
    """Absorb the mixed-pixel runs beside a marker (in place; returns the new run count).

    A cyan marker replaces one stripe, so its flanks always carry one colour (``X C X``).  Where a
    stripe is wide in the camera, the pixels mixing a flank with the marker can be classified as
    the *other* colour (``X Y C X``, ``Y`` 1-2 px: the local threshold sees only ``X`` and ``C``),
    which reads as a parity contradiction and would end the segment.  A coloured run of at most
    ``limit_px`` px, directly between a longer run of the other colour and a cyan run of more than
    ``2 limit_px`` px, whose
    colour differs from the marker's other flank (the first coloured run across the marker,
    through a gap of at most ``max_gap_px``) is merged into its longer neighbour; on both sides of
    each marker (a gap of at most ``max_gap_px`` between the short run and the marker stays a gap,
    which the walk bridges).  The legitimate ``X Y C Y X`` (narrow stripes) is left alone: there
    the flanks agree.  Where stripes are narrow and noisy, a short run beside a marker is often a
    real stripe whose twin across the marker was lost (``X Y C X`` with ``Y`` real): on the 35
    scenes of ``scripts/sweep_decode.py`` (left flanks) 362 of the 367 short runs beside a cyan run
    of 5 px or more were mixed pixels, but only 98 of 255 beside narrower ones; hence the marker's
    width test.

    ``end_flank``: also at a row stretch's end (``. Y C X``: the run before ``Y`` unlabelled, or
    ``Y`` the row's first run; mirrored after the marker), a *one*-pixel run ``Y`` whose colour
    differs from the marker's other flank ``X`` is unlabelled, whatever the marker's width: the
    mixed pixel of a marker and the dark beyond (a shadow's or a silhouette's edge, where stripes
    are seen wide).  Otherwise ``Y C`` ends up a fragment of its own and the marker, the
    strongest evidence for the absolute index, is lost to its surface.  Two-pixel runs are left
    alone: dropping them put real markers a stripe off their surface (the real face turned 30
    degrees lost a 2800 px region to an ambiguous index)."""
    if nr < 2 or limit_px <= 0:
        return nr
    DEL = np.uint8(255)
    n_del = 0
    for i in range(1, nr - 1):
        if rl[i] != CYAN:
            continue
        wide = re[i] - rs[i] + 1 > 2 * limit_px   # (beside a narrow marker a short run may be a real stripe)
        if not wide:
            if not end_flank:
                continue
            # the end test needs a one-pixel run l (i - 1 or i - 2) or r (i + 1 or i + 2) with
            # nothing or an unlabelled run beyond it: most markers have none (0.34 -> 0.07 ms on a
            # 640x480 plane)
            if not _lone_pixels(rs, re, rl, nr, i):
                continue
        # the first coloured run right of the marker (through a small gap)
        r = i + 1
        if rl[r] == NONE and re[r] - rs[r] + 1 <= max_gap_px and r + 1 < nr:
            r += 1
        # left flank: run l short, next to the marker (or across a small gap) and adjacent to a
        # longer run ll of the other colour
        l = i - 1
        if rl[l] == NONE and re[l] - rs[l] + 1 <= max_gap_px and l >= 1:
            l -= 1
        left_col = rl[l]
        if l >= 1 and (rl[l] == GREEN or rl[l] == BLUE) and re[l] - rs[l] + 1 <= limit_px:
            ll = l - 1
            if wide and (rl[ll] == GREEN or rl[ll] == BLUE) and rl[ll] != rl[l] and re[ll] + 1 == rs[l] \
                    and re[ll] - rs[ll] + 1 > limit_px and rl[r] == rl[ll]:
                re[ll] = re[l]
                rl[l] = DEL
                n_del += 1
                left_col = rl[ll]
        if end_flank and _end_pixel(rl, rs, re, l, l - 1, rl[r]):
            rl[l] = NONE   # the stretch's first run: one pixel against the marker's other flank
            left_col = NONE
        # right flank: the same, mirrored, against the (repaired) left flank's colour
        r = i + 1
        if rl[r] == NONE and re[r] - rs[r] + 1 <= max_gap_px and r + 1 < nr:
            r += 1
        if r + 1 < nr and (rl[r] == GREEN or rl[r] == BLUE) and re[r] - rs[r] + 1 <= limit_px:
            rr = r + 1
            if wide and (rl[rr] == GREEN or rl[rr] == BLUE) and rl[rr] != rl[r] and rs[rr] == re[r] + 1 \
                    and re[rr] - rs[rr] + 1 > limit_px and left_col == rl[rr]:
                rs[rr] = rs[r]
                rl[r] = DEL
                n_del += 1
        if end_flank and _end_pixel(rl, rs, re, r, r + 1 if r + 1 < nr else -1, left_col):
            rl[r] = NONE   # the stretch's last run: one pixel against the marker's other flank
    if n_del == 0:
        return nr
    m = 0
    for i in range(nr):
        if rl[i] != DEL:
            rs[m] = rs[i]
            re[m] = re[i]
            rl[m] = rl[i]
            m += 1
    return m


@njit(cache=True, nogil=True)
def _fill_runs(sr, rr, re, nr, run_s, run_r):
    # every pixel of the row gets its run's segment and index, run by run in order (the runs
    # partition the row).  8 pixels at a time (a vector store each; the last 8 reach into the runs
    # after, which overwrite them), pixel by pixel within 8 px of the row's end
    W = np.uint64(sr.size)
    a = np.uint64(0)
    for k in range(nr):
        s = run_s[k]
        r = run_r[k]
        b = np.uint64(re[k]) + np.uint64(1)
        if b + np.uint64(8) <= W:
            u = a
            while True:
                for t in range(8):   # (two loops: one vector store each)
                    sr[u + np.uint64(t)] = s
                for t in range(8):
                    rr[u + np.uint64(t)] = r
                u += np.uint64(8)
                if u >= b:
                    break
        else:
            for u in range(a, b):
                sr[u] = s
                rr[u] = r
        a = b


@njit(cache=True, nogil=True)
def row_segments(labels, max_gap_px, spike_px, marker_flank_px=0, end_flank=False):
    """Paper step 1 kernel: unroll each row by the transitions along it.

    Returns per pixel ``seg`` (H, W) int32 (-1 outside segments) and ``rel`` (H, W) int32;
    per segment ``seg_row, seg_u0, seg_u1`` (inclusive pixel span), ``seg_j0, seg_j1`` (its
    junctions ``j0 .. j1-1``), ``seg_parity`` (1 if a green or blue run fixed the parity);
    per junction ``j_seg, j_ua`` (last pixel of the left run), ``j_ub`` (first pixel of the right
    run), ``j_la, j_lb`` (labels), ``j_rel`` (relative index of the right run = boundary index).

    Robustness inside a row: runs of at most ``spike_px`` pixels flanked on both sides by the
    same colour are noise and are merged into their neighbours; gaps (NONE) of at most
    ``max_gap_px`` between different colours are a transition, between equal colours the same
    stripe; with ``marker_flank_px`` > 0 a run of at most that many px between a marker and a
    longer run of the other colour, against the marker's other flank, is a mixed-pixel artefact
    and is absorbed (:func:`_marker_flank_pass`; with ``end_flank`` a 1 px run between a marker
    and the end of the stretch too); any other gap, or a colour whose parity
    contradicts the count of transitions (e.g. ``G C B``: a marker is always flanked by equal
    colours), ends the segment.
    """
    H, W = labels.shape
    seg = np.empty((H, W), np.int32)   # filled row by row, just before the row is walked
    rel = np.empty((H, W), np.int32)
    cap_s = H * (W // 2 + 1)
    seg_row = np.empty(cap_s, np.int32)
    seg_u0 = np.empty(cap_s, np.int32)
    seg_u1 = np.empty(cap_s, np.int32)
    seg_j0 = np.empty(cap_s, np.int32)
    seg_j1 = np.empty(cap_s, np.int32)
    seg_par = np.empty(cap_s, np.uint8)
    cap_j = H * W + 1   # at most W - 1 per row (1-px runs with spike_px=0; H * W // 2 + H could overflow)
    j_seg = np.empty(cap_j, np.int32)
    j_ua = np.empty(cap_j, np.int32)
    j_ub = np.empty(cap_j, np.int32)
    j_la = np.empty(cap_j, np.uint8)
    j_lb = np.empty(cap_j, np.uint8)
    j_rel = np.empty(cap_j, np.int32)
    rs = np.empty(W + 1, np.int32)
    re = np.empty(W, np.int32)
    rl = np.empty(W, np.uint8)
    run_s = np.empty(W, np.int32)   # per run of the row: its segment (-1 none) and relative index
    run_r = np.empty(W, np.int32)
    ns = 0
    nj = 0
    for v in range(H):
        if W == 0:
            continue
        # -- run-length encode the row (64 pixels at a time)
        lrow = labels[v]
        nr = run_starts(lrow, rs)
        for k in range(nr - 1):
            re[k] = rs[k + 1] - 1
            rl[k] = lrow[rs[k]]
        re[nr - 1] = W - 1
        rl[nr - 1] = lrow[rs[nr - 1]]
        # -- spike removal: short run between two equal colours (directly adjacent) -> merge
        if spike_px > 0:
            nr = _merge_runs_pass(rs, re, rl, nr, False, spike_px)
        # -- small gaps: equal colours across a small gap -> one run; else keep the gap as a gap
        if max_gap_px > 0:
            nr = _merge_runs_pass(rs, re, rl, nr, True, max_gap_px)
        # -- mixed pixels beside a marker classified as the other colour (X Y C X -> X C X)
        if marker_flank_px > 0:
            nr = _marker_flank_pass(rs, re, rl, nr, marker_flank_px, max_gap_px, end_flank)
        # -- walk runs into segments (each run's segment and index; its pixels after the walk)
        for k in range(nr):
            run_s[k] = -1
            run_r[k] = 0
        k = 0
        while k < nr:
            if rl[k] == NONE:
                k += 1
                continue
            # start a segment at run k
            s = ns
            ns += 1
            seg_row[s] = v
            seg_u0[s] = rs[k]
            seg_j0[s] = nj
            k0 = k
            # relative index of the first run: parity from its colour (cyan: from the next run)
            lab0 = rl[k]
            par_known = 0
            if lab0 == GREEN:
                r = 0
                par_known = 1
            elif lab0 == BLUE:
                r = 1
                par_known = 1
            else:
                r = 0
                # look ahead for the colour after the cyan run (through a small gap)
                kk = k + 1
                if kk < nr and rl[kk] == NONE and re[kk] - rs[kk] + 1 <= max_gap_px:
                    kk += 1
                if kk < nr and (rl[kk] == GREEN or rl[kk] == BLUE) and rs[kk] - re[kk - 1] == 1:
                    if rl[kk] == GREEN:
                        r = 1  # cyan at odd, next green at even
                    else:
                        r = 0
            run_s[k] = s
            run_r[k] = r
            last = k
            k += 1
            while k < nr:
                gap_end = last  # index of the run before the candidate
                cand = k
                if rl[cand] == NONE:
                    if re[cand] - rs[cand] + 1 > max_gap_px or cand + 1 >= nr:
                        break
                    cand = k + 1
                    if rl[cand] == NONE:
                        break
                lab = rl[cand]
                if lab == rl[gap_end]:
                    break  # same colour across a gap the cleaning did not merge
                r_new = r + 1
                if lab == GREEN or lab == BLUE:
                    want = 0 if lab == GREEN else 1
                    if (r_new & 1) != want:
                        if par_known == 0:
                            # only cyan so far: shift the segment's indices by one
                            for kk in range(k0, gap_end + 1):
                                if run_s[kk] == s:
                                    run_r[kk] += 1
                            for jj in range(seg_j0[s], nj):
                                j_rel[jj] += 1
                            r += 1
                            r_new += 1
                        else:
                            break  # parity contradiction (e.g. G C B): end the segment here
                    par_known = 1
                # record the junction between run gap_end and run cand
                j_seg[nj] = s
                j_ua[nj] = re[gap_end]
                j_ub[nj] = rs[cand]
                j_la[nj] = rl[gap_end]
                j_lb[nj] = lab
                j_rel[nj] = r_new
                nj += 1
                r = r_new
                run_s[cand] = s
                run_r[cand] = r
                last = cand
                k = cand + 1
            seg_u1[s] = re[last]
            seg_j1[s] = nj
            seg_par[s] = par_known
            k = last + 1
        _fill_runs(seg[v], rel[v], re, nr, run_s, run_r)
    return (seg, rel, seg_row[:ns].copy(), seg_u0[:ns].copy(), seg_u1[:ns].copy(), seg_j0[:ns].copy(),
            seg_j1[:ns].copy(), seg_par[:ns].copy(), j_seg[:nj].copy(), j_ua[:nj].copy(), j_ub[:nj].copy(),
            j_la[:nj].copy(), j_lb[:nj].copy(), j_rel[:nj].copy())


@njit(cache=True, nogil=True)
def _vertical_votes_sorted(labels, seg, rel, n_seg):
    """:func:`vertical_votes` by one sort of all the (pair, offset) keys: for any numbering of the
    segments (the fast form needs the pairs in order along the rows and falls back to this one).

    For each pixel whose upper neighbour has the same colour label, the pair (segment, segment
    above) votes for the offset ``rel_above - rel``.  Returns edges ``(s, t, offset, n_agree,
    n_same)``: for each overlapping pair the winning offset, its votes and all same-label votes.
    """
    H, W = labels.shape
    cap = max(H - 1, 0) * W + 16   # a key run per pixel of every row below the first at most
    ks = np.empty(cap, np.int64)
    kn = np.empty(cap, np.int32)
    n = 0
    for v in range(1, H):
        cur = np.int64(-1)
        cnt = 0
        for u in range(W):
            s = seg[v, u]
            t = seg[v - 1, u]
            if s < 0 or t < 0:
                continue
            lab = labels[v, u]
            if lab == NONE or labels[v - 1, u] == NONE:
                continue
            if lab != labels[v - 1, u]:
                off = 2047  # overlap without a vote (colours differ): counted, not voted
            else:
                off = rel[v - 1, u] - rel[v, u]
                if off < -2047:
                    off = -2047
                elif off > 2046:
                    off = 2046
            key = (np.int64(s) * n_seg + t) * 4096 + (off + 2048)
            if key == cur:
                cnt += 1
            else:
                if cnt > 0:
                    ks[n] = cur
                    kn[n] = cnt
                    n += 1
                cur = key
                cnt = 1
        if cnt > 0:
            ks[n] = cur
            kn[n] = cnt
            n += 1
    ks = ks[:n]
    kn = kn[:n]
    order = np.argsort(ks, kind="mergesort")
    # aggregate equal keys, then keep the best offset per (s, t) pair
    e_s = np.empty(n, np.int32)
    e_t = np.empty(n, np.int32)
    e_off = np.empty(n, np.int32)
    e_agree = np.empty(n, np.int32)
    e_same = np.empty(n, np.int32)
    e_over = np.empty(n, np.int32)
    ne = 0
    i = 0
    while i < n:
        pair = ks[order[i]] // 4096
        best_c = 0
        best_off = 0
        tot = 0
        over = 0
        while i < n and ks[order[i]] // 4096 == pair:
            key = ks[order[i]]
            c = 0
            while i < n and ks[order[i]] == key:
                c += kn[order[i]]
                i += 1
            over += c
            if key % 4096 == 4095:
                continue
            tot += c
            if c > best_c:
                best_c = c
                best_off = np.int32(key % 4096 - 2048)
        e_s[ne] = np.int32(pair // n_seg)
        e_t[ne] = np.int32(pair % n_seg)
        e_off[ne] = best_off
        e_agree[ne] = best_c
        e_same[ne] = tot
        e_over[ne] = over
        ne += 1
    return (e_s[:ne].copy(), e_t[:ne].copy(), e_off[:ne].copy(), e_agree[:ne].copy(), e_same[:ne].copy(),
            e_over[:ne].copy())


@njit(cache=True, nogil=True)
def chain_lengths(n_seg, e_s, e_t, strong):
    """Paper step 3 kernel: length of the vertical chain of strong edges through each segment.

    Edges are sorted by ``s`` (segments are numbered row by row, ``t`` lies in the row above).
    Returns ``up + down - 1``: the number of rows the segment's stripes continue through.
    """
    up = np.ones(n_seg, np.int32)
    down = np.ones(n_seg, np.int32)
    for i in range(e_s.shape[0]):
        if strong[i]:
            c = up[e_t[i]] + 1
            if c > up[e_s[i]]:
                up[e_s[i]] = c
    for i in range(e_s.shape[0] - 1, -1, -1):
        if strong[i]:
            c = down[e_s[i]] + 1
            if c > down[e_t[i]]:
                down[e_t[i]] = c
    return up + down - 1


@njit(cache=True, nogil=True)
def _find(parent, pot, x):
    # returns root and P[x] - P[root], compressing the path
    root = x
    acc = 0
    while parent[root] != root:
        acc += pot[root]
        root = parent[root]
    # compress
    cur = x
    rem = acc
    while parent[cur] != cur:
        nxt = parent[cur]
        p = pot[cur]
        parent[cur] = root
        pot[cur] = rem
        rem -= p
        cur = nxt
    return root, acc


@njit(cache=True, nogil=True)
def link_segments(parent, pot, size, conflicts, e_s, e_t, e_off, order, use, believable, restrict):
    """Paper steps 4 and 6 kernel: join segments into regions of mutually consistent indices.

    Union-find with potentials (``parent``, ``pot``, ``size`` updated in place): ``P[s] - P[t] = offset``
    for an edge (s below t).  Edges are taken in ``order`` (strongest first) where ``use`` is set.
    An edge that contradicts the potentials already fixed is a *conflict*: it is not applied and
    is counted on both segments (``conflicts``).  With ``restrict`` a non-believable segment joins
    at most one region and two regions are never merged through a doubtful segment.
    """
    for ii in range(order.shape[0]):
        i = order[ii]
        if not use[i]:
            continue
        s = e_s[i]
        t = e_t[i]
        rs, ps = _find(parent, pot, s)
        rt, pt = _find(parent, pot, t)
        if rs == rt:
            if ps - pt != e_off[i]:
                conflicts[s] += 1
                conflicts[t] += 1
            continue
        if restrict:
            # the doubtful side must still be alone; it is attached under the other's root
            if believable[s] == believable[t]:
                continue
            if not believable[s]:
                if size[rs] != 1:
                    continue
                parent[s] = rt
                pot[s] = e_off[i] + pt
                size[rt] += 1
            else:
                if size[rt] != 1:
                    continue
                parent[t] = rs
                pot[t] = ps - e_off[i]
                size[rs] += 1
            continue
        parent[rs] = rt
        pot[rs] = e_off[i] - ps + pt
        size[rt] += size[rs]


@njit(cache=True, nogil=True)
def resolve_roots(parent, pot):
    """Root and potential ``P[s] - P[root]`` of every segment (after linking)."""
    n = parent.shape[0]
    P = np.zeros(n, np.int32)
    root = np.zeros(n, np.int32)
    for s in range(n):
        r, p = _find(parent, pot, s)
        root[s] = r
        P[s] = p
    return root, P


@njit(cache=True, nogil=True)
def _sj_f(la, lb, g, b):
    # subpixel_junctions' signal at a pixel of channels g, b for the colours la | lb: it crosses
    # zero upwards at the boundary
    if la == CYAN:
        if lb == GREEN:
            f = 0.5 - b
        else:
            f = 0.5 - g
    elif lb == CYAN:
        if la == GREEN:
            f = b - 0.5
        else:
            f = g - 0.5
    elif la == GREEN:
        f = b - g
    else:
        f = g - b
    return f


@njit(cache=True, nogil=True)
def _sj_cross(u, f0, f, ox, mid, best, bestd):
    # subpixel_junctions: the crossing between pixels u - 1 and u (signal f0, f), if there is one
    # nearer to mid than the best so far, and its distance; else the best so far
    if f0 < 0.0 and f >= 0.0:
        x = (u - 1 + ox) + f0 / (f0 - f)
        d = abs(x - mid)
        if d < bestd:
            return x, d
    return best, bestd


@njit(cache=True, nogil=True)
def subpixel_junctions(gn, bn, seg_row, j_ua, j_ub, j_la, j_lb, seg_u0, seg_u1, j_seg, ox=0):
    """Sub-pixel position (camera px, along the row) of every junction (stripe boundary); ``ox``
    the column of the frame where the arrays start (a decoded window): the positions are the
    frame's, computed as the whole frame's decode computes them (the same float rounding).

    ``gn, bn`` are the colour channels normalised to [0, 1] between their local minimum and
    maximum.  The boundary is the crossing of the channel(s) that change: ``gn = bn`` for green|blue
    (both channels swap: a symmetric signal, so gamma and equal blur do not bias it), ``bn = 1/2``
    for green|cyan and ``gn = 1/2`` for blue|cyan.  The crossing nearest to the runs' junction is
    searched from the last pixel of the left run - 1 to the first pixel of the right run + 1 and
    located by linear interpolation between the two samples that bracket it.  NaN if none.
    Junction ``j`` lies in segment ``j_seg[j]``, on row ``seg_row`` of it.

    Per junction, its segment's row and span are read only where the segment changes, and the
    usual window of four pixels (``a .. a + 3``) is unrolled (plane 0.44 -> 0.31 ms).
    """
    nj = j_seg.shape[0]
    out = np.empty(nj, np.float32)
    s = -1
    grow = gn[0]
    brow = bn[0]
    u0 = 0
    u1 = 0
    for j in range(nj):
        if j_seg[j] != s:     # a new segment: its row and span
            s = j_seg[j]
            v = seg_row[s]
            grow = gn[v]
            brow = bn[v]
            u0 = seg_u0[s]
            u1 = seg_u1[s]
        la = j_la[j]
        lb = j_lb[j]
        a = max(j_ua[j] - 1, u0)
        b = min(j_ub[j] + 1, u1)
        mid = 0.5 * ((j_ua[j] + ox) + (j_ub[j] + ox))
        best = np.nan
        bestd = 1e9
        if b - a == 3:    # adjacent runs away from the span's ends: the pairs (a, a+1) .. (a+2, a+3)
            fa = _sj_f(la, lb, grow[a], brow[a])
            fb = _sj_f(la, lb, grow[a + 1], brow[a + 1])
            fc = _sj_f(la, lb, grow[a + 2], brow[a + 2])
            fd = _sj_f(la, lb, grow[a + 3], brow[a + 3])
            best, bestd = _sj_cross(a + 1, fa, fb, ox, mid, best, bestd)
            best, bestd = _sj_cross(a + 2, fb, fc, ox, mid, best, bestd)
            best, bestd = _sj_cross(a + 3, fc, fd, ox, mid, best, bestd)
        else:
            f0 = 0.0
            for u in range(a, b + 1):
                f = _sj_f(la, lb, grow[u], brow[u])
                if u > a:
                    best, bestd = _sj_cross(u, f0, f, ox, mid, best, bestd)
                f0 = f
        out[j] = best
    return out


@njit(cache=True, nogil=True)
def channel_edge_offsets(gn, bn, seg_row, j_ua, j_ub, j_la, seg_u0, seg_u1, j_seg, sel, jx, ox, max_px):
    """The blue edge's offset from the green edge at the green|blue junctions ``sel`` (int64):
    each channel's own crossing of 1/2, found as :func:`subpixel_junctions` finds a green|cyan
    (``bn``) and a blue|cyan (``gn``) boundary, nearest the runs' junction.  Returns ``x`` (the
    junctions' columns ``jx``) and ``d = x_blue - x_green`` (float64, camera px) of those where
    both were found and ``|d| < max_px`` (``gbscan.decode.lateral_chromatic_aberration``)."""
    n = sel.shape[0]
    xs = np.empty(n, np.float64)
    ds = np.empty(n, np.float64)
    m = 0
    for i in range(n):
        j = sel[i]
        s = j_seg[j]
        v = seg_row[s]
        a = max(j_ua[j] - 1, seg_u0[s])
        b = min(j_ub[j] + 1, seg_u1[s])
        mid = 0.5 * ((j_ua[j] + ox) + (j_ub[j] + ox))
        sg = 1.0 if j_la[j] == GREEN else -1.0     # green left of blue: blue rises, green falls
        xb = np.nan
        db = 1e9
        xg = np.nan
        dg = 1e9
        fb0 = 0.0
        fg0 = 0.0
        for u in range(a, b + 1):
            fb = sg * (bn[v, u] - 0.5)
            fg = -sg * (gn[v, u] - 0.5)
            if u > a:
                xb, db = _sj_cross(u, fb0, fb, ox, mid, xb, db)
                xg, dg = _sj_cross(u, fg0, fg, ox, mid, xg, dg)
            fb0 = fb
            fg0 = fg
        d = xb - xg
        if np.isfinite(d) and abs(d) < max_px and np.isfinite(jx[j]):
            xs[m] = jx[j]
            ds[m] = d
            m += 1
    return xs[:m], ds[:m]


@njit(cache=True, nogil=True)
def robust_line(x, y, trims):
    """``y = a + k x`` by least squares (the sums of ``_common.fit_add`` / ``fit_slope``), refitted
    ``trims`` times on the points within 3 robust sigmas (1.4826 median absolute residual, over
    about 1024 evenly spaced points) of the last fit.  Returns (a, k, sigma, points, std of x) of
    the last fit (sigma: the robust sigma of its points' residuals)."""
    n = x.shape[0]
    keep = np.ones(n, np.bool_)
    a = 0.0
    k = 0.0
    r = np.empty(n, np.float64)
    acc = np.zeros(5, np.float64)
    step = max(n // 1024, 1)    # the medians on every step-th residual (about 1024 of them)
    for it in range(trims + 1):
        acc[:] = 0.0
        for i in range(n):
            if keep[i]:
                fit_add(acc, x[i], y[i])
        k = fit_slope(acc, 2)
        if k != k:
            return np.nan, np.nan, np.nan, int(acc[0]), 0.0
        a = (acc[2] - k * acc[1]) / acc[0]
        for i in range(n):
            r[i] = abs(y[i] - (a + k * x[i]))
        if it < trims:
            lim = 3.0 * 1.4826 * np.median(r[::step]) + 1e-9
            for i in range(n):
                keep[i] = r[i] <= lim
    c = int(acc[0])
    kept = np.empty(c, np.float64)
    q = 0
    for i in range(n):
        if keep[i]:
            kept[q] = r[i]
            q += 1
    xm = acc[1] / c
    return a, k, 1.4826 * np.median(kept[::max(c // 1024, 1)]), c, np.sqrt(max(acc[3] / c - xm * xm, 0.0))


@njit(cache=True, nogil=True)
def junction_index(j_rel, j_seg, seg_P):
    """Boundary index of every junction (float64, as :func:`interpolate_columns` takes it): its
    relative index within its segment ``j_rel`` plus the segment's offset ``seg_P[j_seg]``."""
    out = np.empty(j_rel.shape[0], np.float64)
    for j in range(j_rel.shape[0]):
        out[j] = np.float64(np.int64(j_rel[j]) + np.int64(seg_P[j_seg[j]]))
    return out


@njit(cache=True, nogil=True)
def _fj_pass0(acc, xs, c):
    # the first term of every window's fit (0.0 + c x, as the plain loop starts)
    for i in range(acc.size):
        acc[i] = 0.0 + c * xs[i]


@njit(cache=True, nogil=True)
def _fj_pass(acc, xs, c):
    # one more term of every window's fit
    for i in range(acc.size):
        acc[i] += c * xs[i]


@njit(cache=True, nogil=True)
def _fj_sel2(o, x, acc):
    # the fit where it is a number, the junction's own position where its window held a NaN
    for i in range(o.size):
        a = acc[i]
        o[i] = x[i] if np.isnan(a) else a


@njit(cache=True, nogil=True)
def _n_nan(x):
    # how many NaN
    c = 0
    for i in range(x.size):
        c += np.int64(np.isnan(x[i]))
    return c


@njit(cache=True, nogil=True)
def fit_choice_sums(j_x, fit_a, fit_b, seg_j0, seg_j1, seg_bin, k_a, k_b, n_bins):
    """The scores of two boundary fits (:func:`gbscan.decode.choose_fit`), summed per bin.

    ``j_x`` (n_j,) float64 located positions; ``fit_a``, ``fit_b`` (n_j,) their two fits
    (:func:`fit_junctions`: a position the fit left as located, or a fit that is not finite, is
    not scored); ``seg_bin``
    (n_segments,) int the bin of each segment's junctions, in [0, n_bins); ``k_a``, ``k_b`` the
    factors that turn a fit's residual into its leave-one-out residual.  Returns (count, sum_a,
    sum_b), each (n_bins,): the junctions both fits fitted and the sums of their squared
    leave-one-out residuals."""
    count = np.zeros(n_bins, np.int64)
    sum_a = np.zeros(n_bins, np.float64)
    sum_b = np.zeros(n_bins, np.float64)
    for s in range(seg_j0.shape[0]):
        r = seg_bin[s]
        c = 0
        sa = 0.0
        sb = 0.0
        for j in range(seg_j0[s], seg_j1[s]):
            x = j_x[j]
            a = fit_a[j]
            b = fit_b[j]
            if a != x and b != x and np.isfinite(x) and np.isfinite(a) and np.isfinite(b):
                ea = (x - a) * k_a
                eb = (x - b) * k_b
                c += 1
                sa += ea * ea
                sb += eb * eb
        count[r] += c
        sum_a[r] += sa
        sum_b[r] += sb
    return count, sum_a, sum_b


@njit(cache=True, nogil=True)
def take_fit(fit_a, fit_b, seg_j0, seg_j1, seg_take_b):
    """(n_j,) float64: each segment's junctions from ``fit_b`` where ``seg_take_b`` (n_segments,)
    bool says so, else from ``fit_a`` (junctions of no segment: ``fit_a``)."""
    out = fit_a.copy()
    for s in range(seg_j0.shape[0]):
        if seg_take_b[s]:
            for j in range(seg_j0[s], seg_j1[s]):
                out[j] = fit_b[j]
    return out


@njit(cache=True, nogil=True)
def fit_junctions(j_x, seg_j0, seg_j1, coef):
    """Boundary positions refined by a local polynomial fit along each segment.

    ``j_x`` (n_j,) float64 sub-pixel positions (NaN: not located); ``coef`` (2 h + 1,) float64 the
    weights that evaluate, at the centre, the least-squares polynomial through ``2 h + 1``
    equally spaced samples (Savitzky-Golay).  Consecutive junctions of a segment are consecutive
    stripe boundaries, so position against boundary index is a smooth curve on one surface; the
    fit averages the locator's noise over ``2 h + 1`` boundaries.  A junction keeps its own
    position where its window leaves the segment or holds an unlocated boundary.  Returns a new
    (n_j,) float64 array.

    Every window's fit over the whole array first, term by term in vector passes (the same sum in
    the same order per junction), then each segment's interior takes it (plane 0.25-0.35 -> 0.08-0.10
    ms, bit for bit the same).
    """
    out = j_x.copy()
    h = (coef.shape[0] - 1) // 2
    nk = 2 * h + 1
    n = j_x.shape[0]
    m = n - 2 * h
    if m <= 0:
        return out
    acc = np.empty(m, np.float64)          # acc[i]: the fit of the window centred at junction i + h
    _fj_pass0(acc, j_x[0:m], coef[0])
    for k in range(1, nk):
        _fj_pass(acc, j_x[k:k + m], coef[k])
    # a NaN in the window makes the fit NaN: keep the junction's own position there; a NaN fit of
    # a window without one (infinities) is the fit (checked one by one, rare)
    for s in range(seg_j0.shape[0]):
        a = seg_j0[s]
        b = seg_j1[s]
        if b - h > a + h:
            _fj_sel2(out[a + h:b - h], j_x[a + h:b - h], acc[a:b - 2 * h])
    if _n_nan(acc) > 0:
        for s in range(seg_j0.shape[0]):
            for j in range(seg_j0[s] + h, seg_j1[s] - h):
                if np.isnan(acc[j - h]):
                    ok = True
                    for k in range(-h, h + 1):
                        if np.isnan(j_x[j + k]):
                            ok = False
                            break
                    if ok:
                        out[j] = acc[j - h]
    return out


@njit(cache=True, nogil=True)
def locking_table(j_x, j_fit, j_la, j_lb, seg_j0, seg_j1, half, nb, min_count, table):
    """The frame's pixel-locking curve: the sub-pixel locator's mean error by junction type and
    sub-pixel phase, estimated from the boundary fit's residuals (:func:`fit_junctions`).

    ``j_x`` (n_j,) float64 located positions (camera px, the grid the locator sampled; NaN: not
    located), ``j_fit`` the same fitted by :func:`fit_junctions` with ``2 half + 1`` boundaries.
    Only junctions whose whole window lies in their segment count (``seg_j0[s] + half <= j <
    seg_j1[s] - half``), with a residual ``j_x - j_fit`` non-zero (a window holding an unlocated
    boundary keeps the located position) and under half a camera pixel.  The residual of junction
    ``j`` goes to type ``t = 4 j_la[j] + j_lb[j]`` (the colours left | right: green|blue and
    blue|green differ where the channels' blur or gain differ) and phase bin
    ``floor(frac(j_x) nb)``; ``table`` (16, nb) float64 receives each bin's mean residual, or 0
    for every bin of a type with fewer than ``min_count`` residuals in any of its bins.  Returns
    the number of types filled.

    Why it works: the fit's window spans 2 half + 1 boundaries whose phases differ (a boundary
    every few pixels), so the fit averages the locking away where the residual keeps it; a frame
    holds thousands of boundaries, so each bin's mean is the locking at that phase and the fit's
    own noise and misfit average out.  Where the phases barely change along a row (spacing near
    a whole number of pixels) the bins stay empty or their residuals near zero: no correction.
    """
    ntype = table.shape[0]
    sums = np.zeros((ntype, nb), np.float64)
    cnt = np.zeros((ntype, nb), np.int64)
    for s in range(seg_j0.shape[0]):
        for j in range(seg_j0[s] + half, seg_j1[s] - half):
            x = j_x[j]
            r = x - j_fit[j]
            if r != 0.0 and abs(r) < 0.5:         # NaN fails both
                t = 4 * np.int64(j_la[j]) + np.int64(j_lb[j])
                k = np.int64((x - np.floor(x)) * nb)
                if k >= nb:
                    k = nb - 1
                sums[t, k] += r
                cnt[t, k] += 1
    filled = 0
    for t in range(ntype):
        ok = True
        for k in range(nb):
            if cnt[t, k] < min_count:
                ok = False
        for k in range(nb):
            table[t, k] = sums[t, k] / cnt[t, k] if ok else 0.0
        if ok:
            filled += 1
    return filled


@njit(cache=True, nogil=True)
def apply_locking(j_x, j_la, j_lb, table):
    """``j_x`` (n_j,) float64 minus the locking curve ``table`` (16, nb) (:func:`locking_table`) at
    each junction's type and phase, interpolated linearly between the bins' centres
    (``(k + 1/2) / nb``, periodic).  NaN stays NaN.  Returns a new array.

    Branch-free, one pass: the curve padded with its last bin before the first and its first
    after the last (the phase is periodic), so the bin below a junction's phase is a truncation
    and no modulo is needed; an unlocated junction reads bin 0 and stays NaN (plane 0.47 -> 0.1 ms)."""
    nt = table.shape[0]
    nb = table.shape[1]
    ext = np.empty(nt * (nb + 2), np.float64)
    for t in range(nt):
        ext[t * (nb + 2)] = table[t, nb - 1]
        for k in range(nb):
            ext[t * (nb + 2) + 1 + k] = table[t, k]
        ext[t * (nb + 2) + nb + 1] = table[t, 0]
    n = j_x.shape[0]
    out = np.empty(n, np.float64)
    for j in range(n):
        x = j_x[j]
        xs = x if np.isfinite(x) else 0.0
        q = (xs - np.floor(xs)) * nb + 0.5        # in [0.5, nb + 0.5); ext[i] holds bin i - 1, centred at q = i
        i = np.int64(q)
        w = q - i
        o = (4 * np.int64(j_la[j]) + np.int64(j_lb[j])) * (nb + 2) + i
        out[j] = x - ((1.0 - w) * ext[o] + w * ext[o + 1])
    return out


@njit(cache=True, nogil=True)
def _located_cs(j_x, j_bnd, stripe_px, j0, j1, xs, cs):
    # the located boundaries j0 .. j1-1 of a segment in increasing order (a boundary not at least
    # 0.05 px right of the last one kept is dropped) into xs, their columns into cs; returns their count
    n = 0
    last = 0.0
    for j in range(j0, j1):
        x = j_x[j]
        if np.isnan(x):
            continue
        if n > 0 and x <= last + 0.05:
            continue
        xs[n] = x
        cs[n] = j_bnd[j] * stripe_px - 0.5
        last = x
        n += 1
    return n


@njit(cache=True, nogil=True)
def _n_bad(x, m):
    # count of i < m - 1 where x[i + 1] is not more than 0.05 right of x[i] (or either is NaN)
    a = x[:m - 1]
    b = x[1:m]
    bad = 0
    for i in range(m - 1):
        bad += np.int64(not (b[i] > a[i] + 0.05))
    return bad


@njit(cache=True, nogil=True)
def _copy_cs(x, jb, stripe_px, xs, cs, m):
    for i in range(m):
        xs[i] = x[i]
    for i in range(m):
        cs[i] = jb[i] * stripe_px - 0.5


@njit(cache=True, nogil=True)
def _located_fast(j_x, j_bnd, stripe_px, j0, j1, xs, cs):
    # _located_cs; by vector loops when every boundary is located and in order (the common case)
    m = j1 - j0
    if m >= 1 and not np.isnan(j_x[j0]):
        x = j_x[j0:j1]
        if _n_bad(x, m) == 0:
            _copy_cs(x, j_bnd[j0:j1], stripe_px, xs, cs, m)
            return m
    return _located_cs(j_x, j_bnd, stripe_px, j0, j1, xs, cs)


@njit(cache=True, nogil=True, error_model='numpy')
def _slopes(XS, CS, SL, m):
    # every interval's slope, across the flat arrays of all segments: the entries that straddle two
    # segments are never read, and may divide by zero (the numpy error model lets them)
    a = XS[:m - 1]
    b = XS[1:m]
    ca = CS[:m - 1]
    cb = CS[1:m]
    o = SL[:m - 1]
    for k in range(m - 1):
        o[k] = (cb[k] - ca[k]) / (b[k] - a[k])


@njit(cache=True, nogil=True)
def _ceils(XS, CI, m):
    # the first pixel at or right of every boundary
    a = XS[:m]
    o = CI[:m]
    for k in range(m):
        o[k] = np.int64(np.ceil(a[k]))


@njit(cache=True, nogil=True)
def _span(dst, q, m, c0, x0, slope):
    # pixels q .. q + m - 1 of one interval (the expression of a plain per-pixel loop)
    for i in range(m):
        dst[i] = c0 + ((q + i) - x0) * slope


@njit(cache=True, nogil=True)
def interpolate_columns(H, W, seg_row, seg_u0, seg_u1, seg_j0, seg_j1, seg_ok, j_x, j_bnd, stripe_px,
                        extrapolate, contact_ratio=0.0, end_fit=0, contact_gap_px=1, ox=0,
                        seg_shift=np.zeros(0)):
    """Continuous projector column of every pixel of the accepted segments.  ``ox``: the frame's
    column where the (H, W) arrays start (a decoded window); ``j_x`` are the frame's positions
    (:func:`subpixel_junctions` with the same ``ox``) and a pixel's position is ``u + ox``.

    Between two consecutive boundaries at camera positions ``x_k < x_{k+1}`` with projector columns
    ``c_k, c_{k+1}`` (``c = index * stripe_px - 0.5``) a pixel at ``u`` gets
    ``c_k + (u - x_k) (c_{k+1} - c_k) / (x_{k+1} - x_k)``.  Pixels beyond the first/last boundary
    of a segment are extrapolated with the neighbouring interval's slope up to ``extrapolate``
    times that interval's width (else left NaN).  Boundaries out of order (non-increasing) are
    dropped.  ``j_bnd`` is the boundary index (relative or absolute: the caller shifts).

    ``contact_ratio`` > 0: an end of a segment that touches the next segment of its row (at most
    ``contact_gap_px`` pixels between their spans) is not extrapolated when the boundary spacing across the
    contact jumps by more than this factor (last interval of one, first of the other; or either
    has fewer than two located boundaries): the two touch across a depth edge, where the run the
    edge cuts may carry the other surface's colours (mixed pixels, aliased stripes of a surface
    seen at grazing incidence, a colour camera's demosaicing).  Segments split on one surface
    (a misclassified pixel) keep their spacing and are extrapolated as before.

    ``end_fit`` >= 3: the pixels beyond an end of a segment with at least that many located
    boundaries are extrapolated with the least-squares quadratic of column against camera position
    through its ``end_fit`` boundaries at that end (:func:`_end_quadratic`) instead of the end
    interval's straight line: near a silhouette the stripes widen or narrow from boundary to
    boundary, which the straight line misses (it always errs the same way), and one located
    position is noisier than the fit.  Where the quadratic's slope at the pixel leaves
    [1/2, 2] times the straight line's (a fit bent by a stray boundary) the straight line is used.

    The located boundaries, their columns, the intervals' slopes and first pixels are computed once
    per segment into flat arrays (by vector loops when a segment's boundaries are all located and in
    order, the usual case), and an interval's pixels are written in 8-wide vector chunks; a chunk
    may run past its interval, but only inside the segment's interior, which the later intervals
    write again.  Every pixel gets the same expression as a plain loop would give it (0.74 -> 0.34
    ms on the plane's frame, 0.17 -> 0.11 in the head's lit window, bit for bit the same).
    """
    col = np.full((H, W), np.nan, np.float32)
    ns = seg_row.shape[0]
    # 8 (W >= 0) in a form the compiler cannot fold: with a constant trip count LLVM unrolls the
    # chunk loop into scalar code (numba runs no SLP vectoriser); a runtime one it vectorises
    CH = min(8, W + 8)
    off = np.zeros(ns + 1, np.int64)
    for s in range(ns):
        m = seg_j1[s] - seg_j0[s]
        if m < 0 or not (contact_ratio > 0 or seg_ok[s]):
            m = 0
        off[s + 1] = off[s] + m
    tot = off[ns]
    XS = np.empty(tot + 1, np.float64)
    CS = np.empty(tot + 1, np.float64)
    cnt = np.zeros(ns, np.int64)
    for s in range(ns):
        if off[s + 1] > off[s]:
            cnt[s] = _located_fast(j_x, j_bnd, stripe_px, seg_j0[s], seg_j1[s], XS[off[s]:off[s + 1]],
                                   CS[off[s]:off[s + 1]])
    SL = np.empty(tot + 1, np.float64)
    CI = np.empty(tot + 1, np.int64)
    if tot > 0:
        _slopes(XS, CS, SL, tot)
        _ceils(XS, CI, tot)
    sp_first = np.full(ns, np.nan)
    sp_last = np.full(ns, np.nan)
    if contact_ratio > 0:
        for s in range(ns):
            n = cnt[s]
            if n >= 2:
                o = off[s]
                sp_first[s] = XS[o + 1] - XS[o]
                sp_last[s] = XS[o + n - 1] - XS[o + n - 2]
    for s in range(ns):
        if not seg_ok[s]:
            continue
        v = seg_row[s]
        n = cnt[s]
        if n < 2:
            continue
        o = off[s]
        xs = XS[o:o + n]
        cs = CS[o:o + n]
        sl = SL[o:o + n]
        ci = CI[o:o + n]
        fl_ok, fl_a, fl_b, fl_q = 0, 0.0, 0.0, 0.0
        fr_ok, fr_a, fr_b, fr_q = 0, 0.0, 0.0, 0.0
        if end_fit >= 3 and n >= end_fit:
            fl_ok, fl_a, fl_b, fl_q = _end_quadratic(xs, cs, 0, end_fit, xs[0])
            fr_ok, fr_a, fr_b, fr_q = _end_quadratic(xs, cs, n - end_fit, end_fit, xs[n - 1])
        crow = col[v]
        u = seg_u0[s]
        u_end = seg_u1[s]
        p = u + ox
        p_end = u_end + ox
        if contact_ratio > 0:
            if s > 0 and seg_row[s - 1] == v and seg_u1[s - 1] >= u - 1 - contact_gap_px and \
                    (_spacing_jump(sp_last[s - 1], sp_first[s], contact_ratio) or
                     _column_jump(seg_shift, XS, CS, off, cnt, s - 1, s, stripe_px)):
                p = max(p, np.int64(np.ceil(xs[0])))
            if s + 1 < ns and seg_row[s + 1] == v and seg_u0[s + 1] <= u_end + 1 + contact_gap_px and \
                    (_spacing_jump(sp_last[s], sp_first[s + 1], contact_ratio) or
                     _column_jump(seg_shift, XS, CS, off, cnt, s, s + 1, stripe_px)):
                p_end = min(p_end, np.int64(np.floor(xs[n - 1])))
        if p > p_end:
            continue
        # left of xs[0]: interval 0 extrapolated
        x0 = xs[0]
        x1 = xs[1]
        reach = extrapolate * (x1 - x0)
        slope = sl[0]
        c0 = cs[0]
        lim = min(p_end, ci[0] - 1)
        while p <= lim:
            if not (x0 - p > reach):
                crow[p - ox] = _end_value(fl_ok, fl_a, fl_b, fl_q, p - x0, c0 + (p - x0) * slope, slope)
            p += 1
        # interior: pixels [ci[k], ci[k+1] - 1] of interval k, the last one up to floor(xs[n-1])
        hi = min(p_end, np.int64(np.floor(xs[n - 1])))
        for k in range(n - 1):
            q = max(p, ci[k])
            e = hi if k == n - 2 else min(hi, ci[k + 1] - 1)
            if q > e:
                continue
            c0 = cs[k]
            x0 = xs[k]
            slope = sl[k]
            while q + 8 <= hi + 1:
                _span(crow[q - ox:q - ox + 8], q, CH, c0, x0, slope)
                q += 8
                if q > e:
                    break
            if q <= e:
                _span(crow[q - ox:e + 1 - ox], q, e + 1 - q, c0, x0, slope)
            p = e + 1
        # right of xs[n-1]: interval n-2 extrapolated
        x0 = xs[n - 2]
        x1 = xs[n - 1]
        reach = extrapolate * (x1 - x0)
        slope = sl[n - 2]
        c0 = cs[n - 2]
        p = max(p, hi + 1)
        while p <= p_end:
            if not (p - x1 > reach):
                crow[p - ox] = _end_value(fr_ok, fr_a, fr_b, fr_q, p - x1, c0 + (p - x0) * slope, slope)
            p += 1
    return col


@njit(cache=True, nogil=True)
def _column_jump(seg_shift, XS, CS, off, cnt, a, b, stripe_px):
    # segment a (left) and b (right) of one row, both with an absolute shift (seg_shift finite;
    # empty: never) and two located boundaries: b's first boundary's absolute column is more than
    # a stripe from a's last interval continued to it (two surfaces whose colours line up)
    if seg_shift.shape[0] == 0 or cnt[a] < 2 or cnt[b] < 2:
        return False
    sa = seg_shift[a]
    sb = seg_shift[b]
    if np.isnan(sa) or np.isnan(sb):
        return False
    i = off[a] + cnt[a] - 1
    x0 = XS[i - 1]
    x1 = XS[i]
    c0 = CS[i - 1]
    c1 = CS[i]
    xb = XS[off[b]]
    pred = c1 + sa + (xb - x1) * (c1 - c0) / (x1 - x0)
    return abs(CS[off[b]] + sb - pred) > stripe_px


@njit(cache=True, nogil=True)
def _end_quadratic(xs, cs, i0, m, x_ref):
    # least-squares c = a + b t + q t^2, t = x - x_ref, through the m points xs/cs[i0 : i0 + m]
    # (normal equations, Cramer's rule); returns (ok, a, b, q), ok 0 when singular
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    s3 = 0.0
    s4 = 0.0
    y0 = 0.0
    y1 = 0.0
    y2 = 0.0
    for i in range(i0, i0 + m):
        t = xs[i] - x_ref
        t2 = t * t
        c = cs[i]
        s0 += 1.0
        s1 += t
        s2 += t2
        s3 += t2 * t
        s4 += t2 * t2
        y0 += c
        y1 += c * t
        y2 += c * t2
    det = s0 * (s2 * s4 - s3 * s3) - s1 * (s1 * s4 - s3 * s2) + s2 * (s1 * s3 - s2 * s2)
    if not (abs(det) > 1e-9 * max(s4 * s4, 1.0)):
        return 0, 0.0, 0.0, 0.0
    a = (y0 * (s2 * s4 - s3 * s3) - s1 * (y1 * s4 - s3 * y2) + s2 * (y1 * s3 - s2 * y2)) / det
    b = (s0 * (y1 * s4 - y2 * s3) - y0 * (s1 * s4 - s3 * s2) + s2 * (s1 * y2 - y1 * s2)) / det
    q = (s0 * (s2 * y2 - s3 * y1) - s1 * (s1 * y2 - s2 * y1) + y0 * (s1 * s3 - s2 * s2)) / det
    return 1, a, b, q


@njit(cache=True, nogil=True)
def _end_value(ok, a, b, q, t, lin, slope):
    # an extrapolated column from an end quadratic at t px past the end boundary, or ``lin`` (the
    # straight line of slope ``slope``) when there is none or its slope at t is not within a
    # factor 2 of the straight line's
    if ok == 0:
        return lin
    d = b + 2.0 * q * t
    if not (d >= 0.5 * slope and d <= 2.0 * slope):
        return lin
    return a + (b + q * t) * t


@njit(cache=True, nogil=True)
def _spacing_jump(a, b, ratio):
    # two boundary spacings (camera px) differ by more than ``ratio`` (False if one is unknown)
    return a > ratio * b or b > ratio * a


@njit(cache=True, nogil=True)
def select_columns(col_all, seg_row, seg_u0, seg_u1, seg_ok):
    """The columns :func:`interpolate_columns` gives for the segments ``seg_ok`` (n_seg,) uint8,
    taken from ``col_all`` (H, W) float32, its result for every segment: NaN outside the spans of
    the accepted segments, a copy inside.  Exact when no two segment spans share a pixel, which is
    checked (segments numbered row by row, left to right, spans disjoint); returns
    ``(columns, True)``, or ``(empty, False)`` when the check fails (the caller interpolates).
    Saves the interpolation's per-pixel work when both results are needed (the decoder's linking).

    Each row written once: NaN between the accepted spans, copies inside (plane 0.17 -> 0.03 ms).
    """
    n = seg_row.shape[0]
    for s in range(1, n):
        if seg_row[s] < seg_row[s - 1] or (seg_row[s] == seg_row[s - 1] and seg_u0[s] <= seg_u1[s - 1]):
            return np.empty((0, 0), np.float32), False
    H, W = col_all.shape
    col = np.empty((H, W), np.float32)
    nan = np.float32(np.nan)
    s = 0
    for v in range(H):
        crow = col[v]
        arow = col_all[v]
        while s < n and seg_row[s] < v:
            s += 1
        u = 0
        while s < n and seg_row[s] == v:
            if seg_ok[s]:
                a = np.int64(seg_u0[s])
                b = np.int64(seg_u1[s]) + 1
                if a > u:
                    fill_row(crow[u:a], nan)
                if b > a:
                    copy_row(crow[a:b], arow[a:b])
                u = max(u, b)
            s += 1
        if u < W:
            fill_row(crow[u:W], nan)
    return col, True


@njit(cache=True, nogil=True)
def link_votes(comp, col_rel, col_abs, max_gap_px):
    """Column-continuity votes of reported pixels for the offset of unindexed components.

    comp (H, W) int32 component id of a candidate pixel (-1 none); col_rel (H, W) float32 its
    column relative to its component (NaN none); col_abs (H, W) float32 absolute column of the
    reported pixels (NaN none; disjoint from the candidates).  A candidate pixel whose vertical
    neighbours (v +- 1, v +- 2) or, along its row past at most ``max_gap_px`` pixels of neither,
    two horizontal neighbours are reported predicts its absolute column by linear extrapolation
    of theirs; each prediction is one vote ``pred - col_rel`` (px).  Returns (comp, residual,
    line, row) with ``line`` = column (vertical votes) or ``-1 - row`` (horizontal votes) and
    ``row`` the candidate pixel's row.
    """
    H, W = comp.shape
    n = 0
    for v in range(H):
        for u in range(W):
            if comp[v, u] >= 0:
                n += 1
    out_c = np.empty(4 * n, np.int32)
    out_r = np.empty(4 * n, np.float64)
    out_l = np.empty(4 * n, np.int32)
    out_v = np.empty(4 * n, np.int32)
    m = 0
    for v in range(H):
        for u in range(W):
            c = comp[v, u]
            if c < 0 or np.isnan(col_rel[v, u]):
                continue
            x = col_rel[v, u]
            for d in (-1, 1):
                q, q2 = v + d, v + 2 * d
                if 0 <= q2 < H and not np.isnan(col_abs[q, u]) and not np.isnan(col_abs[q2, u]):
                    out_c[m] = c
                    out_r[m] = 2.0 * col_abs[q, u] - col_abs[q2, u] - x
                    out_l[m] = u
                    out_v[m] = v
                    m += 1
                for k in range(1, max_gap_px + 2):
                    q = u + d * k
                    q2 = q + 2 * d
                    if q < 0 or q >= W or comp[v, q] >= 0:
                        break
                    if not np.isnan(col_abs[v, q]):
                        if 0 <= q2 < W and not np.isnan(col_abs[v, q2]):
                            slope = (col_abs[v, q2] - col_abs[v, q]) / (2.0 * d)
                            out_c[m] = c
                            out_r[m] = col_abs[v, q] + slope * (u - q) - x
                            out_l[m] = -1 - v
                            out_v[m] = v
                            m += 1
                        break
    return out_c[:m], out_r[:m], out_l[:m], out_v[:m]


@njit(cache=True, nogil=True)
def component_pixels(seg, seg_comp, col):
    """(H, W) int32 component of each pixel (``seg_comp[seg]``, -1 none) and (H, W) float32 its
    column ``col`` there (NaN elsewhere); also the number of such pixels with a finite column."""
    H, W = seg.shape
    comp = np.full((H, W), -1, np.int32)
    out = np.full((H, W), np.nan, np.float32)
    n = 0
    for v in range(H):
        for u in range(W):
            s = seg[v, u]
            if s >= 0 and seg_comp[s] >= 0:
                comp[v, u] = seg_comp[s]
                out[v, u] = col[v, u]
                if not np.isnan(col[v, u]):
                    n += 1
    return comp, out, n


@njit(cache=True, nogil=True)
def component_pixels_spans(seg, seg_comp, col, seg_row, seg_u0, seg_u1):
    """:func:`component_pixels` visiting only the spans of the segments with ``seg_comp >= 0``
    (a segment's pixels lie in its span ``seg_row, seg_u0 .. seg_u1``): the same three results,
    without a pass over the whole image when few segments are candidates."""
    H, W = seg.shape
    comp = np.full((H, W), -1, np.int32)
    out = np.full((H, W), np.nan, np.float32)
    n = 0
    for s in range(seg_row.shape[0]):
        c = seg_comp[s]
        if c < 0:
            continue
        v = seg_row[s]
        for u in range(seg_u0[s], seg_u1[s] + 1):
            if seg[v, u] == s:
                comp[v, u] = c
                out[v, u] = col[v, u]
                if not np.isnan(col[v, u]):
                    n += 1
    return comp, out, n


@njit(cache=True, nogil=True)
def reported_columns(region, reason, inconsistent, labels, column_rel, reg_off_px):
    """(H, W) float32 absolute column ``column_rel + reg_off_px[region]`` of the pixels that are
    reported so far (region indexed -- finite offset --, reason 0, consistent, labelled), NaN
    elsewhere."""
    H, W = region.shape
    out = np.full((H, W), np.nan, np.float32)
    for v in range(H):
        for u in range(W):
            r = region[v, u]
            if r >= 0 and reason[v, u] == 0 and not inconsistent[v, u] and labels[v, u] != NONE:
                o = reg_off_px[r]
                if not np.isnan(o):
                    out[v, u] = column_rel[v, u] + o
    return out


@njit(cache=True, nogil=True)
def component_marker_counts(comp, relative, labels, comp_shift, take, is_marker):
    """Per component (``take[c]``): its pixels and those whose stripe ``relative + comp_shift[c]``
    is outside the pattern or whose colour contradicts the markers there (cyan on a non-marker
    stripe, green/blue on a marker stripe).  Returns (n_px, n_bad) int64 arrays like ``take``."""
    H, W = comp.shape
    n_st = is_marker.shape[0]
    n_px = np.zeros(take.shape[0], np.int64)
    n_bad = np.zeros(take.shape[0], np.int64)
    for v in range(H):
        for u in range(W):
            c = comp[v, u]
            if c < 0 or not take[c]:
                continue
            n_px[c] += 1
            st = relative[v, u] + comp_shift[c]
            lb = labels[v, u]
            if st < 0 or st >= n_st or contradicts(lb, is_marker[st]):
                n_bad[c] += 1
    return n_px, n_bad


@njit(cache=True, nogil=True)
def _gradient_step(comp, col_rel, col_abs, c, u, v, rows, skip, acc):
    # (d column / d v in the component minus in the reported pixels at the vote (v, u) of
    # component c, the side of the reported pixels: 0 above, 1 below); see stripe_gradient_jumps.
    # The component's rows are taken from ``skip`` rows past the contact row on.
    # The difference is NaN where either side has fewer than 3 rows.  acc: (5,) float64 scratch
    H = comp.shape[0]
    d = 1
    if v >= 2 and not np.isnan(col_abs[v - 1, u]) and not np.isnan(col_abs[v - 2, u]):
        d = -1
    where = 0 if d < 0 else 1
    g0 = 0.0
    for side in range(2):
        acc[:] = 0.0
        for j in range(rows + 1):
            q = v - d * (j + skip) if side == 0 else v + d * (j + 1)
            if q < 0 or q >= H:
                break
            if side == 0:
                if comp[q, u] != c:
                    break
                y = col_rel[q, u]
            else:
                y = col_abs[q, u]
            if np.isnan(y):
                break
            fit_add(acc, float(q), y)
        g = fit_slope(acc, 3)
        if np.isnan(g):
            return np.nan, where
        if side == 0:
            g0 = g
        else:
            return g0 - g, where
    return np.nan, where


@njit(cache=True, nogil=True)
def stripe_gradient_jumps(vc, vl, vv, comp, col_rel, col_abs, slot, rows, skip=0):
    """Per vertical link vote: how the column's gradient along the stripes changes at the contact.

    ``vc, vl, vv`` (n,) a component's votes as :func:`link_votes` returns them (component, line:
    the column for a vertical vote, row of the candidate pixel); only vertical votes of
    components with ``slot[c] >= 0`` are measured.  The reported pixels the vote came from lie
    above the candidate when its two pixels above are reported (``col_abs`` finite), else below.
    The gradient ``d column / d v`` (projector px per camera row, least squares) is taken over
    the candidate's column from ``skip`` rows past the contact row into the component (``comp ==
    c``, ``col_rel`` finite, up to ``rows + 1`` rows, contiguous; the rows skipped are those the
    along-stripe blur mixes with the other side) and from the first reported row beyond the
    contact into the reported pixels (``col_abs`` finite, up to ``rows + 1`` rows).  Returns
    (n,) float64 component minus reported gradient, NaN where either side has fewer than 3 rows,
    and (n,) int8 the side of the reported pixels (0 above, 1 below; -1 not measured).
    """
    n = vc.shape[0]
    out = np.full(n, np.nan)
    where = np.full(n, -1, np.int8)
    acc = np.zeros(5)
    for i in range(n):
        if vl[i] >= 0 and slot[vc[i]] >= 0:
            g, w = _gradient_step(comp, col_rel, col_abs, vc[i], vl[i], vv[i], rows, skip, acc)
            out[i] = g
            if not np.isnan(g):
                where[i] = w
    return out, where


@njit(cache=True, nogil=True)
def _median_test(d, tol, z, floor):
    # (|median| > tol and > z standard errors, the median, its z-score) of the differences d
    med = np.median(d)
    mad = np.median(np.abs(d - med))
    se = 1.4826 * max(mad, floor) / np.sqrt(d.shape[0])
    zz = abs(med) / se
    return abs(med) > tol and zz > z, med, zz


@njit(cache=True, nogil=True)
def gradient_jump_verdicts(vc, vk, vl, vv, good, comp, col_rel, col_abs, slot, offset, rows, tol, z, min_votes,
                           floor, skip=0, z_one=-1.0):
    """Per slot: does the column's gradient along the stripes jump where the component meets the
    reported pixels?  The agreeing (``good``) vertical votes of each component ``c`` with
    ``slot[c] >= 0`` at its offset ``offset[slot[c]]`` (``vk``, periods of two stripes) are
    measured as :func:`stripe_gradient_jumps` does.  With at least ``min_votes`` measured, the
    component is flagged when the median difference ``m`` of all of them has ``|m| > tol`` and
    ``|m| > z * se``, ``se = 1.4826 * max(MAD, floor) / sqrt(n)`` -- unless its contacts above and
    below (each with ``min_votes`` measured) have medians of opposite signs, each at a z-score
    over ``z``: then the gradient grows (or falls) steadily from the surface above through the
    component to the one below, the curvature of one surface, where a surface of another tilt
    would differ from both the same way.  A component whose agreeing votes (measured or not) all
    have the reported pixels on one side -- tied through one contact alone -- is judged at the
    z-score ``z_one`` instead (0: by the median's size alone; negative: at ``z``, the rule before
    the twenty-ninth session), with no exemption.  Returns (n_slot,) bool."""
    n_slot = offset.shape[0]
    n = vc.shape[0]
    diff = np.full(n, np.nan)
    key = np.full(n, -1, np.int64)
    cnt = np.zeros(2 * n_slot + 1, np.int64)
    sides = np.zeros(n_slot, np.int64)     # bit w: an agreeing vote with the reported pixels on side w
    acc = np.zeros(5)
    for i in range(n):
        c = vc[i]
        if not good[i] or vl[i] < 0:
            continue
        k = slot[c]
        if k < 0 or vk[i] != offset[k]:
            continue
        g, w = _gradient_step(comp, col_rel, col_abs, c, vl[i], vv[i], rows, skip, acc)
        sides[k] |= 1 << w
        if not np.isnan(g):
            diff[i] = g
            key[i] = 2 * k + w
            cnt[key[i] + 1] += 1
    for k in range(2 * n_slot):
        cnt[k + 1] += cnt[k]
    vals = np.empty(cnt[2 * n_slot])
    fill = cnt[:2 * n_slot].copy()
    for i in range(n):
        if key[i] >= 0:
            vals[fill[key[i]]] = diff[i]
            fill[key[i]] += 1
    out = np.zeros(n_slot, np.bool_)
    for k in range(n_slot):
        a, b = cnt[2 * k], cnt[2 * k + 2]       # both contacts' votes (the buckets are adjacent)
        if b - a < min_votes:
            continue
        if z_one >= 0.0 and sides[k] != 3:
            # tied through one contact alone: the gradient must be seen to continue
            jump, _, _ = _median_test(vals[a:b], tol, z_one, floor)
            out[k] = jump
            continue
        jump, _, _ = _median_test(vals[a:b], tol, z, floor)
        if not jump:
            continue
        med = np.zeros(2)
        zz = np.zeros(2)
        for w in range(2):
            a, b = cnt[2 * k + w], cnt[2 * k + w + 1]
            if b - a >= min_votes:
                _, med[w], zz[w] = _median_test(vals[a:b], tol, z, floor)
        out[k] = not (zz[0] > z and zz[1] > z and med[0] * med[1] < 0)
    return out


@njit(cache=True, nogil=True)
def component_markers_seen(comp, relative, labels, comp_shift, slot, n_slot, is_marker, min_px):
    """Per slot: the marker stripes a component shows at its linked offset.

    ``slot`` (n_comp,) int64 maps a component to its slot (-1: not counted); a pixel of component
    ``c`` counts for stripe ``relative + comp_shift[c]`` when it is cyan and that stripe is a
    marker.  Returns (n_slot,) int64: per slot the marker stripes with at least ``min_px`` such
    pixels (the indexing's ``min_marker_px``)."""
    H, W = comp.shape
    n_st = is_marker.shape[0]
    cnt = np.zeros((max(n_slot, 1), n_st), np.int64)
    for v in range(H):
        for u in range(W):
            c = comp[v, u]
            if c < 0 or labels[v, u] != CYAN:
                continue
            k = slot[c]
            if k < 0:
                continue
            st = relative[v, u] + comp_shift[c]
            if 0 <= st < n_st and is_marker[st]:
                cnt[k, st] += 1
    out = np.zeros(n_slot, np.int64)
    for k in range(n_slot):
        for st in range(n_st):
            if cnt[k, st] >= min_px:
                out[k] += 1
    return out


@njit(cache=True, nogil=True)
def _run_key(labels, seg, rel, v, vn, a, b):
    # majority (segment, offset) key of the pixels a..b of row v against row vn (-1: no vote)
    best = np.int64(-1)
    best_c = 0
    for u in range(a, b + 1):
        t = seg[vn, u]
        if t < 0 or labels[vn, u] != labels[v, u] or labels[v, u] == NONE:
            continue
        key = np.int64(t) * 8192 + (rel[vn, u] - rel[v, u] + 4096)
        c = 0
        for w in range(a, b + 1):
            t2 = seg[vn, w]
            if t2 >= 0 and labels[vn, w] == labels[v, w] and np.int64(t2) * 8192 + (rel[vn, w] - rel[v, w] + 4096) == key:
                c += 1
        if c > best_c:
            best_c = c
            best = key
    return best


@njit(cache=True, nogil=True)
def cut_junctions(labels, seg, rel, seg_row, seg_u0, seg_u1, seg_j0, seg_j1, j_ua, j_ub, doubtful):
    """Paper step 5 kernel: where to cut doubtful segments.

    For each run of a doubtful segment, the majority (segment, offset) relation of its pixels
    to the row above and to the row below is found; a junction is cut when the relation on
    either side changes between its two runs (an inserted or lost stripe, or a segment bridging
    two surfaces).  Returns (n_junctions,) uint8 cut flags.
    """
    H, W = labels.shape
    cut = np.zeros(j_ua.shape[0], np.uint8)
    for s in range(seg_row.shape[0]):
        if not doubtful[s]:
            continue
        v = seg_row[s]
        prev_up = np.int64(-1)
        prev_dn = np.int64(-1)
        a = seg_u0[s]
        for j in range(seg_j0[s], seg_j1[s] + 1):
            b = j_ua[j] if j < seg_j1[s] else seg_u1[s]
            up = _run_key(labels, seg, rel, v, v - 1, a, b) if v > 0 else np.int64(-1)
            dn = _run_key(labels, seg, rel, v, v + 1, a, b) if v + 1 < H else np.int64(-1)
            if j > seg_j0[s]:
                if (up >= 0 and prev_up >= 0 and up != prev_up) or (dn >= 0 and prev_dn >= 0 and dn != prev_dn):
                    cut[j - 1] = 1
            if up >= 0:
                prev_up = up
            if dn >= 0:
                prev_dn = dn
            if j < seg_j1[s]:
                a = j_ub[j]
    return cut


@njit(cache=True, nogil=True)
def _sel_piece(o, sr, k):
    # apply_cuts: a piece's pixels are k where the old image has a segment, else as they were
    for u in range(o.size):
        x = sr[u]
        o[u] = k if x >= 0 else x


@njit(cache=True, nogil=True)
def apply_cuts(seg, seg_row, seg_u0, seg_u1, seg_j0, seg_j1, seg_par, j_seg, j_ua, j_ub, j_la, j_lb, cut, j_rel, j_x):
    """Split segments at the cut junctions (the cut junction is dropped); rel is unchanged.

    Returns the new per-pixel ``seg``, the new segment/junction tables (same layout as
    :func:`row_segments`; pieces keep row order), each kept junction's old index, and the kept
    junctions' ``j_rel`` and ``j_x`` (``j_x`` empty in, empty out: segments without located
    boundaries) -- 15 arrays.  A piece's parity flag is inherited.  The gathers are done as the
    junctions are kept (as numpy gathers after the kernel they took as long as the kernel on a head).

    The new ``seg`` is written once, row by row, where the pieces are in row order with disjoint
    spans inside the image (as :func:`row_segments` makes them): a piece's span by a vector
    select, the rest copied (head 0.19 -> 0.10 ms for two calls, the gathers included);
    otherwise the old image is copied and each piece painted over it in turn.
    """
    H, W = seg.shape
    n_cut = 0
    for j in range(cut.shape[0]):
        n_cut += cut[j]
    ns = seg_row.shape[0] + n_cut
    nj = j_seg.shape[0] - n_cut
    gx = j_x.shape[0] == j_seg.shape[0]
    o_row = np.empty(ns, np.int32)
    o_u0 = np.empty(ns, np.int32)
    o_u1 = np.empty(ns, np.int32)
    o_j0 = np.empty(ns, np.int32)
    o_j1 = np.empty(ns, np.int32)
    o_par = np.empty(ns, np.uint8)
    o_jseg = np.empty(nj, np.int32)
    o_jua = np.empty(nj, np.int32)
    o_jub = np.empty(nj, np.int32)
    o_jla = np.empty(nj, np.uint8)
    o_jlb = np.empty(nj, np.uint8)
    o_jidx = np.empty(nj, np.int32)
    o_jrel = np.empty(nj, j_rel.dtype)
    o_jx = np.empty(nj if gx else 0, j_x.dtype)
    k = 0
    m = 0
    for s in range(seg_row.shape[0]):
        v = seg_row[s]
        o_row[k] = v
        o_u0[k] = seg_u0[s]
        o_j0[k] = m
        o_par[k] = seg_par[s]
        for j in range(seg_j0[s], seg_j1[s]):
            if cut[j]:
                o_u1[k] = j_ua[j]
                o_j1[k] = m
                k += 1
                o_row[k] = v
                o_u0[k] = j_ub[j]
                o_j0[k] = m
                o_par[k] = seg_par[s]
            else:
                o_jseg[m] = k
                o_jua[m] = j_ua[j]
                o_jub[m] = j_ub[j]
                o_jla[m] = j_la[j]
                o_jlb[m] = j_lb[j]
                o_jidx[m] = j
                o_jrel[m] = j_rel[j]
                if gx:
                    o_jx[m] = j_x[j]
                m += 1
        o_u1[k] = seg_u1[s]
        o_j1[k] = m
        k += 1
    # the pieces in row order, each span inside the image and after the row's pieces before it
    ok = True
    vp = 0
    e = 0
    for s in range(ns):
        if o_row[s] != vp:
            ok = ok & (o_row[s] > vp)
            vp = o_row[s]
            e = 0
        ok = ok & (o_u0[s] >= e) & (o_u1[s] < W)
        e = max(e, o_u1[s] + 1)
    ok = ok & (vp < H)
    if ok:
        nseg = np.empty((H, W), np.int32)
        s = 0
        for v in range(H):
            o = nseg[v]
            sr = seg[v]
            u = 0
            while s < ns and o_row[s] == v:
                a = np.int64(o_u0[s])
                b = np.int64(o_u1[s]) + 1
                if a > u:
                    copy_row(o[u:a], sr[u:a])
                if b > a:
                    _sel_piece(o[a:b], sr[a:b], np.int32(s))
                u = max(u, b)
                s += 1
            if u < W:
                copy_row(o[u:W], sr[u:W])
    else:
        nseg = seg.copy()
        for s in range(ns):
            v = o_row[s]
            for u in range(o_u0[s], o_u1[s] + 1):
                if seg[v, u] >= 0:
                    nseg[v, u] = s
    return nseg, o_row, o_u0, o_u1, o_j0, o_j1, o_par, o_jseg, o_jua, o_jub, o_jla, o_jlb, o_jidx, o_jrel, o_jx


# -- paper step 4 in one pass (was numpy group-by glue in unwrap.link_believable) -----------------
@njit(cache=True, nogil=True)
def edge_order(n_agree, n_same):
    """Edges strongest first, ``np.lexsort((n_same - n_agree, -n_agree))``: most agreeing votes,
    then fewest dissenting ones, ties in edge order (one stable sort of a combined int64 key;
    the dissent, a difference of two int32, is shifted to be non-negative under 2**34)."""
    key = np.empty(n_agree.shape[0], np.int64)
    for i in range(key.shape[0]):
        key[i] = -np.int64(n_agree[i]) * (np.int64(1) << 34) + (np.int64(n_same[i]) - n_agree[i] + (np.int64(1) << 32))
    return np.argsort(key, kind="mergesort").astype(np.int64)


@njit(cache=True, nogil=True)
def link_strips(parent, pot, size, conflicts, e_s, e_t, e_off, n_agree, n_same, order, strong, believable,
                n_ref_rows, agree_frac):
    """Paper step 4 kernel (:func:`gbscan.unwrap.link_believable`; union-find state in place).

    ``strong`` (n_edges,) bool: strong edges between believable segments.  a. Each such edge that
    is the best of its lower segment upwards and of its upper one downwards (score ``n_agree *
    4096 - dissent``, ties to the later edge) links its two segments (``link_segments`` in
    ``order``): strips.  b. The other strong edges, by the pair of strips they join (smaller root
    first) and the offset between them: an edge inside one strip contradicting it is a conflict;
    a (pair, offset) with ``n_ref_rows`` edges or more that are ``agree_frac`` of the pair's edges
    links the strips, pairs with more edges first (ties in (pair, offset) order)."""
    n = parent.shape[0]
    ne = e_s.shape[0]
    m = 0
    for i in range(ne):
        m += strong[i]
    if m == 0:
        return
    ids = np.empty(m, np.int64)
    score = np.empty(m, np.int64)
    m = 0
    for i in range(ne):
        if strong[i]:
            ids[m] = i
            score[m] = np.int64(n_agree[i]) * 4096 - (n_same[i] - n_agree[i])
            m += 1
    # a. mutual best edges (ascending stable score order: the last write wins)
    best_up = np.full(n, -1, np.int64)
    best_dn = np.full(n, -1, np.int64)
    for q in np.argsort(score, kind="mergesort"):
        i = ids[q]
        best_up[e_s[i]] = i
        best_dn[e_t[i]] = i
    mutual = np.zeros(ne, np.bool_)
    n_rest = 0
    for i in ids:
        mutual[i] = best_up[e_s[i]] == i and best_dn[e_t[i]] == i
        n_rest += not mutual[i]
    link_segments(parent, pot, size, conflicts, e_s, e_t, e_off, order, mutual, believable, False)
    root, P = resolve_roots(parent, pot)   # (compresses every path, as the numpy form did)
    if n_rest == 0:
        return
    # b. the other strong edges keyed by (strip pair, offset): key (A n + B) 8192 + delta + 4096
    key = np.empty(n_rest, np.int64)
    nk = 0
    for i in ids:
        if mutual[i]:
            continue
        A = np.int64(root[e_s[i]])
        B = np.int64(root[e_t[i]])
        delta = np.int64(e_off[i]) - P[e_s[i]] + P[e_t[i]]
        if A == B:
            if delta != 0:
                conflicts[e_s[i]] += 1
                conflicts[e_t[i]] += 1
            continue
        if A > B:
            A, B, delta = B, A, -delta
        key[nk] = (A * n + B) * 8192 + (delta + 4096)
        nk += 1
    if nk == 0:
        return
    key = np.sort(key[:nk])
    # distinct keys and their counts; each pair's total over its offsets
    ukey = np.empty(nk, np.int64)
    cnt = np.zeros(nk, np.int64)
    nu = 0
    for x in key:
        if nu == 0 or ukey[nu - 1] != x:
            ukey[nu] = x
            nu += 1
        cnt[nu - 1] += 1
    ok = np.zeros(nu, np.bool_)
    pa = np.empty(nu, np.int32)
    pb = np.empty(nu, np.int32)
    pdelta = np.empty(nu, np.int32)
    g = 0
    while g < nu:
        pair = ukey[g] // 8192
        h = g
        tot = 0
        while h < nu and ukey[h] // 8192 == pair:
            tot += cnt[h]
            h += 1
        for q in range(g, h):
            ok[q] = cnt[q] >= n_ref_rows and cnt[q] >= agree_frac * np.float64(tot)
            pa[q] = pair // n
            pb[q] = pair % n
            pdelta[q] = ukey[q] % 8192 - 4096
        g = h
    order_b = np.argsort(-cnt[:nu], kind="mergesort").astype(np.int64)
    link_segments(parent, pot, size, conflicts, pa, pb, pdelta, order_b, ok, believable, False)
