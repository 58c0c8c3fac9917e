"""Sequential row/segment kernels of the decoder, compiled with numba (``cache=True``).

Only :mod:`gbscan.unwrap`, :mod:`gbscan.decode` and (inside its functions) :mod:`gbscan.clean`
import this module, so ``gbscan --help`` never
pays for numba.  Every kernel works on plain numpy arrays; the conventions are those of
:mod:`gbscan.unwrap`:

* ``labels`` (H, W) uint8 colour class per pixel (``NONE=0, GREEN=1, BLUE=2, CYAN=3``).
* A *run* is a maximal horizontal stretch of one label; a *segment* is a maximal chain of runs
  along a row whose consecutive labels form valid stripe transitions; ``rel`` is the relative
  stripe index of a pixel inside its segment, with parity fixed by colour (green even, blue odd).
* A *junction* is the place between two consecutive runs of a segment (one stripe boundary).

The first call compiles (a few seconds, cached on disk afterwards); tests and benchmarks warm up.
"""
from __future__ import annotations

import numpy as np
from numba import njit

NONE, GREEN, BLUE, CYAN = 0, 1, 2, 3


@njit(cache=True, nogil=True)
def run_starts(row, rs):
    """Run-length encode one row of labels (W,) (W >= 1): the runs' first pixels into ``rs[0 ..
    n-1]`` and ``rs[n] = W`` (rs: (W + 1,) int32); returns n.  Branch-free: every pixel stores its
    position as the next run's start, and the count advances only where the label changes (noisy
    rows cost no mispredicted branches)."""
    W = row.size
    rs[0] = 0
    nr = 1
    a = row[:W - 1]
    b = row[1:]
    for u in range(W - 1):
        rs[nr] = u + 1
        nr += np.int64(a[u] != b[u])
    rs[nr] = W
    return nr


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
    ns = 0
    nj = 0
    for v in range(H):
        sr = seg[v]
        rr = rel[v]
        sr[:] = -1
        rr[:] = 0
        if W == 0:
            continue
        # -- run-length encode the row (branch-free)
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
        # -- walk runs into segments
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
            for uu in range(rs[k], re[k] + 1):
                sr[uu] = s
                rr[uu] = r
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
                            for uu in range(seg_u0[s], re[gap_end] + 1):
                                if sr[uu] == s:
                                    rr[uu] += 1
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
                for uu in range(rs[cand], re[cand] + 1):
                    sr[uu] = s
                    rr[uu] = r
                last = cand
                k = cand + 1
            seg_u1[s] = re[last]
            seg_j1[s] = nj
            seg_par[s] = par_known
            k = last + 1
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
    cap = H * W // 2 + 16
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
def subpixel_junctions(gn, bn, seg_row, j_ua, j_ub, j_la, j_lb, seg_u0, seg_u1, j_seg):
    """Sub-pixel position (camera px, along the row) of every junction (stripe boundary).

    ``gn, bn`` are the colour channels normalised to [0, 1] between their local minimum and
    maximum.  The boundary is the crossing of the channel(s) that change: ``gn = bn`` for green|blue
    (both channels swap: a symmetric signal, so gamma and equal blur do not bias it), ``bn = 1/2``
    for green|cyan and ``gn = 1/2`` for blue|cyan.  The crossing nearest to the runs' junction is
    searched from the last pixel of the left run - 1 to the first pixel of the right run + 1 and
    located by linear interpolation between the two samples that bracket it.  NaN if none.
    Junction ``j`` lies in segment ``j_seg[j]``, on row ``seg_row`` of it.
    """
    nj = j_seg.shape[0]
    out = np.full(nj, np.nan, np.float32)
    for j in range(nj):
        s = j_seg[j]
        v = seg_row[s]
        la = j_la[j]
        lb = j_lb[j]
        a = max(j_ua[j] - 1, seg_u0[s])
        b = min(j_ub[j] + 1, seg_u1[s])
        mid = 0.5 * (j_ua[j] + j_ub[j])
        best = np.nan
        bestd = 1e9
        f0 = 0.0
        for u in range(a, b + 1):
            if la == CYAN:
                if lb == GREEN:
                    f = 0.5 - bn[v, u]
                else:
                    f = 0.5 - gn[v, u]
            elif lb == CYAN:
                if la == GREEN:
                    f = bn[v, u] - 0.5
                else:
                    f = gn[v, u] - 0.5
            elif la == GREEN:
                f = bn[v, u] - gn[v, u]
            else:
                f = gn[v, u] - bn[v, u]
            if u > a and f0 < 0.0 and f >= 0.0:
                x = (u - 1) + f0 / (f0 - f)
                d = abs(x - mid)
                if d < bestd:
                    bestd = d
                    best = x
            f0 = f
        out[j] = best
    return out


@njit(cache=True, nogil=True)
def junction_index(j_rel, j_seg, seg_P):
    """Boundary index of every junction (float64, as :func:`interpolate_columns` takes it): its
    relative index within its segment ``j_rel`` plus the segment's offset ``seg_P[j_seg]``."""
    out = np.empty(j_rel.shape[0], np.float64)
    for j in range(j_rel.shape[0]):
        out[j] = np.float64(np.int64(j_rel[j]) + np.int64(seg_P[j_seg[j]]))
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
    """
    out = j_x.copy()
    h = (coef.shape[0] - 1) // 2
    for s in range(seg_j0.shape[0]):
        a = seg_j0[s]
        b = seg_j1[s]
        for j in range(a + h, b - h):
            acc = 0.0
            ok = True
            for k in range(-h, h + 1):
                x = j_x[j + k]
                if np.isnan(x):
                    ok = False
                    break
                acc += coef[k + h] * x
            if ok:
                out[j] = acc
    return out


@njit(cache=True, nogil=True)
def interpolate_columns(H, W, seg_row, seg_u0, seg_u1, seg_j0, seg_j1, seg_ok, j_x, j_bnd, stripe_px,
                        extrapolate, contact_ratio=0.0, end_fit=0, contact_gap_px=1):
    """Continuous projector column of every pixel of the accepted segments.

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
    """
    col = np.full((H, W), np.nan, np.float32)
    xs = np.empty(W + 2, np.float64)
    cs = np.empty(W + 2, np.float64)
    js = np.empty(W + 2, np.int64)
    ns = seg_row.shape[0]
    # first and last located interval of every segment (NaN: fewer than two located boundaries)
    sp_first = np.full(ns, np.nan)
    sp_last = np.full(ns, np.nan)
    if contact_ratio > 0:
        for s in range(ns):
            n = _located(j_x, seg_j0[s], seg_j1[s], xs, js)
            if n >= 2:
                sp_first[s] = xs[1] - xs[0]
                sp_last[s] = xs[n - 1] - xs[n - 2]
    for s in range(ns):
        if not seg_ok[s]:
            continue
        v = seg_row[s]
        n = _located(j_x, seg_j0[s], seg_j1[s], xs, js)
        if n < 2:
            continue
        for i in range(n):
            cs[i] = j_bnd[js[i]] * stripe_px - 0.5
        # least-squares quadratics of the end boundaries (ok flag 0: the straight line)
        fl_ok, fl_a, fl_b, fl_q = 0, 0.0, 0.0, 0.0
        fr_ok, fr_a, fr_b, fr_q = 0, 0.0, 0.0, 0.0
        if end_fit >= 3 and n >= end_fit:
            fl_ok, fl_a, fl_b, fl_q = _end_quadratic(xs, cs, 0, end_fit, xs[0])
            fr_ok, fr_a, fr_b, fr_q = _end_quadratic(xs, cs, n - end_fit, end_fit, xs[n - 1])
        crow = col[v]
        u = seg_u0[s]
        u_end = seg_u1[s]
        if contact_ratio > 0:
            if s > 0 and seg_row[s - 1] == v and seg_u1[s - 1] >= u - 1 - contact_gap_px and \
                    _spacing_jump(sp_last[s - 1], sp_first[s], contact_ratio):
                u = max(u, np.int64(np.ceil(xs[0])))
            if s + 1 < ns and seg_row[s + 1] == v and seg_u0[s + 1] <= u_end + 1 + contact_gap_px and \
                    _spacing_jump(sp_last[s], sp_first[s + 1], contact_ratio):
                u_end = min(u_end, np.int64(np.floor(xs[n - 1])))
        # per interval k: its pixels are those the per-pixel rule gives it (the largest k <= n-2
        # with u >= xs[k], the first interval also left of xs[0]); only pixels outside
        # [xs[k], xs[k+1]] (extrapolated: first and last interval) need the reach test, the rest
        # is one branch-free loop with the interval's slope (the same expression per pixel)
        k = 0
        while u <= u_end:
            while k < n - 2 and u >= xs[k + 1]:
                k += 1
            x0 = xs[k]
            x1 = xs[k + 1]
            slope = (cs[k + 1] - cs[k]) / (x1 - x0)
            reach = extrapolate * (x1 - x0)
            c0 = cs[k]
            last = u_end if k == n - 2 else min(u_end, np.int64(np.ceil(xs[k + 1])) - 1)
            # pixels left of x0 (first interval only), then inside [x0, x1], then right of x1
            while u <= last and u < x0:
                if not (x0 - u > reach):
                    crow[u] = _end_value(fl_ok, fl_a, fl_b, fl_q, u - x0, c0 + (u - x0) * slope, slope)
                u += 1
            mid = min(last, np.int64(np.floor(x1)))
            if u <= mid:
                seg_row_out = crow[u:mid + 1]
                for i in range(mid + 1 - u):
                    seg_row_out[i] = c0 + ((u + i) - x0) * slope
                u = mid + 1
            while u <= last:
                if not (u - x1 > reach):
                    lin = c0 + (u - x0) * slope
                    crow[u] = _end_value(fr_ok, fr_a, fr_b, fr_q, u - x1, lin, slope) if k == n - 2 else lin
                u += 1
    return col


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
def _located(j_x, j0, j1, xs, js):
    # the located boundaries j0 .. j1-1 of a segment in increasing order (a boundary not at least
    # 0.05 px right of the last one kept is dropped) into xs, their junction indices into js;
    # returns their count
    n = 0
    for j in range(j0, j1):
        x = j_x[j]
        if np.isnan(x):
            continue
        if n > 0 and x <= xs[n - 1] + 0.05:
            continue
        xs[n] = x
        js[n] = j
        n += 1
    return n


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
    Saves the interpolation's per-pixel work when both results are needed (the decoder's linking)."""
    n = seg_row.shape[0]
    for s in range(1, n):
        if seg_row[s] < seg_row[s - 1] or (seg_row[s] == seg_row[s - 1] and seg_u0[s] <= seg_u1[s - 1]):
            return np.empty((0, 0), np.float32), False
    H, W = col_all.shape
    col = np.full((H, W), np.nan, np.float32)
    for s in range(n):
        if seg_ok[s]:
            v = seg_row[s]
            for u in range(seg_u0[s], seg_u1[s] + 1):
                col[v, u] = col_all[v, u]
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
            if st < 0 or st >= n_st:
                n_bad[c] += 1
            elif lb == CYAN and not is_marker[st]:
                n_bad[c] += 1
            elif (lb == GREEN or lb == BLUE) and is_marker[st]:
                n_bad[c] += 1
    return n_px, n_bad


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
def apply_cuts(seg, seg_row, seg_u0, seg_u1, seg_j0, seg_j1, seg_par, j_seg, j_ua, j_ub, j_la, j_lb, cut):
    """Split segments at the cut junctions (the cut junction is dropped); rel is unchanged.

    Returns new per-pixel ``seg`` and the new segment/junction tables (same layout as
    :func:`row_segments`; pieces keep row order).  A piece's parity flag is inherited.
    """
    H, W = seg.shape
    n_cut = 0
    for j in range(cut.shape[0]):
        n_cut += cut[j]
    ns = seg_row.shape[0] + n_cut
    nj = j_seg.shape[0] - n_cut
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
    nseg = seg.copy()
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
                m += 1
        o_u1[k] = seg_u1[s]
        o_j1[k] = m
        k += 1
    for s in range(ns):
        v = o_row[s]
        for u in range(o_u0[s], o_u1[s] + 1):
            if seg[v, u] >= 0:
                nseg[v, u] = s
    return nseg, o_row, o_u0, o_u1, o_j0, o_j1, o_par, o_jseg, o_jua, o_jub, o_jla, o_jlb, o_jidx


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
    if min_sep <= 0 and min_swing <= 0:
        return
    W = labels.size
    if W == 0:
        return
    rs = np.empty(W + 1, np.int32)
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
    sg = 0.0
    sb = 0.0
    ag = 0.0
    ab = 0.0
    n = 0
    H, W = g.shape
    for v in range(H):
        for u in range(W):
            x = g[v, u]
            y = b[v, u]
            ag += x
            ab += y
            if max(x, y) > bright_level:
                sg += x
                sb += y
                n += 1
    if n < 16:
        return ag / max(H * W, 1), ab / max(H * W, 1), n
    return sg / n, sb / n, n


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
                   min_contrast, dark_level, saturation_level, min_run_sep, min_run_swing, run_end_gap):
    """Stage 3 on whole images (the reference path of :func:`classify_frame`; see
    :func:`gbscan.decode.classify`).  g, b : blurred linear channels; gbal, bbal : balanced;
    raw_g, raw_b : linear before blurring; raw_max : uint8 max of raw green and blue (all (H, W)).
    thr_w : odd local threshold window (0: global).  Returns labels, reason, d, thr, gn, bn, contrast.
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
    for v in range(H):
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
                   dark_level, saturation_level, min_run_sep, min_run_swing, run_end_gap, labels, reason, gn, bn,
                   contrast):
    """Stages 2-3 of the fast path in one pass over the rows: colour balance with the global scales
    ``sg, sb``, ``d``, its local threshold, local min/max and the per-pixel rules.

    Bit-identical to :func:`classify_image` on ``Bg * sg, Bb * sb`` (same row primitives); only the
    ``d`` rows of the threshold window live in a ring buffer.  Lg, Lb, rmax, Bg, Bb : (H, W) from
    :func:`blur_frame` (linear, raw maximum, blurred).  thr_w : odd local
    threshold window (0: global threshold).  Writes labels, reason, gn, bn, contrast ((H, W)).
    (:func:`stream_frame` runs the same steps on rows it blurs as it goes.)
    """
    H, W = Bg.shape
    sc = _classify_scratch(W, thr_w, norm_w)
    for y in range(H + thr_w // 2):
        _classify_step(y, H, Lg, Lb, rmax, H, Bg, Bb, H, sg, sb, thr_w, norm_w, cyan_level, min_level, raw_margin,
                       min_contrast, dark_level, saturation_level, min_run_sep, min_run_swing, run_end_gap, sc,
                       labels, reason, gn, bn, contrast)


@njit(cache=True, nogil=True, error_model="numpy")
def _classify_scratch(W, thr_w, norm_w):
    # the row scratch of _classify_step: separate arrays (rows of one 2-D array would not vectorise)
    t = thr_w // 2
    n = W + 2 * (norm_w // 2)
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
            np.empty(W, f32))                                                                   # raw_hi


@njit(cache=True, nogil=True, error_model="numpy")
def _classify_step(y, H, Lg, Lb, rmax, nL, Bg, Bb, nB, sg, sb, thr_w, norm_w, cyan_level, min_level, raw_margin,
                   min_contrast, dark_level, saturation_level, min_run_sep, min_run_swing, run_end_gap, sc, labels,
                   reason, gn, bn, contrast):
    # Step y of stages 2-3 (y = 0 .. H + thr_w//2 - 1): d of blurred row y (y < H) into the ring of
    # the threshold window, then row v = y - thr_w//2 classified (v >= 0).  Image row k of the
    # linear (Lg, Lb, rmax) and blurred (Bg, Bb) channels is row k % nL / k % nB of those arrays
    # (whole images: nL = nB = H; rings: the rows these two steps read must still be there).
    (Dr, rows, Pd, tda, tdb, thr, Pg, Pb, LOg, HIg, LOb, HIb, s0, s1, s2, s3, s4, s5, s6, s7, ta, tb,
     lo_g, hi_g, lo_b, hi_b, raw_hi) = sc
    W = Bg.shape[1]
    t = thr_w // 2
    h = norm_w // 2
    nD = 2 * t + 2
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
        return
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
    _raw_hi_row(raw_g, raw_b, norm_w, Pg, ta, tb, raw_hi)
    classify_row(g, b, Dr[v % nD], thr, lo_g, hi_g, lo_b, hi_b, raw_g, raw_b, raw_hi, rmax[v % nL], cyan_level,
                 min_level, raw_margin, min_contrast, dark_level, saturation_level,
                 labels[v], reason[v], gn[v], bn[v], contrast[v])
    faint_runs_row(labels[v], reason[v], gn[v], bn[v], g, b, min_run_sep, min_run_swing, run_end_gap)


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
                 dark_level, saturation_level, min_run_sep, min_run_swing, run_end_gap, Rg, Rb, Rm, Qg, Qb, labels,
                 reason, gn, bn, contrast):
    """Stages "input", 1, 2 (with the global scales ``sg, sb``, from :func:`balance_samples`) and 3
    of the fast path in one pass over the rows: each image row is linearised into a ring of rows
    (Rg, Rb float32, Rm uint8 raw maximum: (nL, W)), blurred into a ring (Qg, Qb: (nB, W)) as soon
    as the Gaussian's support is there, and classified as soon as its threshold window is
    (:func:`_classify_step`).  Ring sizes from :func:`stream_rows`.  Bit-identical to
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
    grow = np.empty(2 * r + 2, np.int64)
    flat = img.reshape(H, 3 * W)
    top = np.uint8(0)
    loaded = 0
    yb = 0                      # next blurred row
    sc = _classify_scratch(W, thr_w, norm_w)
    for y in range(H + t):
        while yb <= y and yb < H:
            while loaded <= min(H - 1, yb + 1 + r):
                k = loaded % nL
                top = _linear_row(flat[loaded], lut, Rg[k], Rb[k], Rm[k], top)
                loaded += 1
            for j in range(2 * r + 2):
                grow[j] = reflect101(yb - r + j, H) % nL
            if yb + 1 < H and r >= 3:    # two rows at a time, as blur_frame
                gauss_rows2(Rg, grow, kh, Qg[yb % nB], Qg[(yb + 1) % nB])
                gauss_rows2(Rb, grow, kh, Qb[yb % nB], Qb[(yb + 1) % nB])
                yb += 2
            else:
                gauss_rows(Rg, grow[:2 * r + 1], kh, Qg[yb % nB])
                gauss_rows(Rb, grow[:2 * r + 1], kh, Qb[yb % nB])
                yb += 1
        _classify_step(y, H, Rg, Rb, Rm, nL, Qg, Qb, nB, sg, sb, thr_w, norm_w, cyan_level, min_level, raw_margin,
                       min_contrast, dark_level, saturation_level, min_run_sep, min_run_swing, run_end_gap, sc,
                       labels, reason, gn, bn, contrast)
    return top


@njit(cache=True, nogil=True)
def finish_pixels(reason, labels, region, relative, column_rel, inconsistent, reg_shift, reg_indexed, reg_margin,
                  contrast, stripe_px, n_stripes, min_contrast, n_codes):
    """Final masks, absolute stripe, column and confidence (see :func:`gbscan.decode.decode`).

    Reason codes as in ``gbscan.decode``: 0 ok, 4 isolated, 5 inconsistent, 6 unindexed,
    7 no boundary (other non-zero codes come from ``reason`` and are kept).  One-pixel unlabelled
    gaps between two pixels of one region join that region (``region`` is updated in place).
    A reported pixel must lie within one stripe of its colour run's stripe, inside the pattern,
    and agree within half a stripe with a reported vertical neighbour.  ``column_rel`` is set
    to NaN in place outside regions.

    One pass over the rows (the vertical check lags one row behind, with the previous row's
    provisional result kept in a row buffer).  Returns mask (uint8), column (float32), stripe
    (int32), confidence (float32) (H, W) and the count of each mask code (n_codes,) int64.
    """
    H, W = reason.shape
    mask = np.empty((H, W), np.uint8)
    column = np.empty((H, W), np.float32)
    stripe = np.empty((H, W), np.int32)
    conf = np.empty((H, W), np.float32)
    counts = np.zeros(n_codes, np.int64)
    prev_ok = np.zeros(W, np.bool_)
    prev_col = np.zeros(W, np.float32)
    cur_ok = np.zeros(W, np.bool_)
    cur_col = np.zeros(W, np.float32)
    w = stripe_px
    half = 0.5 * w
    inv_mc = 1.0 / max(min_contrast, 1e-3)
    for v in range(H + 1):
        if v < H:  # provisional result of row v
            for u in range(W):
                m = reason[v, u]
                mask[v, u] = m
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
                    mask[v, u] = 4
                    continue
                if not reg_indexed[r]:
                    mask[v, u] = 6
                    continue
                if inconsistent[v, u]:
                    mask[v, u] = 5
                    continue
                c = column_rel[v, u]
                if np.isnan(c):
                    mask[v, u] = 7
                    continue
                c = c + reg_shift[r] * w
                if gap:
                    k = int(np.floor((c + 0.5) / w))
                else:
                    k = relative[v, u] + reg_shift[r]
                if abs(c - (k * w + 0.5 * (w - 1))) > w or k < 0 or k >= n_stripes:
                    mask[v, u] = 5
                    continue
                column[v, u] = c
                stripe[v, u] = k
        f = v - 1
        if f < 0:
            continue
        # row f: vertical continuity against the provisional rows f - 1 and f + 1, then final values
        for u in range(W):
            cur_ok[u] = mask[f, u] == 0
            cur_col[u] = column[f, u]
        for u in range(W):
            m = mask[f, u]
            if m == 0:
                c = cur_col[u]
                ok = f > 0 and prev_ok[u] and abs(prev_col[u] - c) <= half
                if not ok and f + 1 < H and mask[f + 1, u] == 0 and abs(column[f + 1, u] - c) <= half:
                    ok = True
                if not ok:
                    m = 5
                    mask[f, u] = 5
            if m != 0:
                column[f, u] = np.nan
                stripe[f, u] = -1
                conf[f, u] = 0.0
            else:
                cc = min(max((contrast[f, u] - min_contrast) * inv_mc, 0.0), 1.0)
                conf[f, u] = 0.25 + 0.75 * cc * reg_margin[region[f, u]]
            if m < n_codes:
                counts[m] += 1
            if region[f, u] < 0:
                column_rel[f, u] = np.nan
        for u in range(W):
            prev_ok[u] = cur_ok[u]
            prev_col[u] = cur_col[u]
    return mask, column, stripe, conf, counts


@njit(cache=True, nogil=True)
def region_histograms(labels, relative, region, n_reg):
    """Per region: relative index range and the pixel counts of cyan and of green/blue per
    relative index.  Returns ``rmin, rmax`` (n_reg,) and flat ``n_c, n_g`` with region ``k``'s
    counts at ``start[k] .. start[k] + rmax[k] - rmin[k]``."""
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
    start = np.zeros(n_reg + 1, np.int64)
    for k in range(n_reg):
        span = rmax[k] - rmin[k] + 1 if rmax[k] >= rmin[k] else 0
        start[k + 1] = start[k] + span
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
def score_offsets(rmin, rmax, start, n_c, n_g, is_marker, min_marker_px, cover, cstart, npx, frac):
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
    observation."""
    n_reg = rmin.shape[0]
    n_st = is_marker.shape[0]
    status = np.zeros(n_reg, np.int64)
    seen = np.zeros(n_reg, np.int64)
    offset = np.zeros(n_reg, np.int64)
    evidence = np.zeros(n_reg, np.int64)
    mismatch = np.zeros(n_reg, np.int64)
    runner = np.zeros(n_reg, np.int64)
    big = np.iinfo(np.int64).max // 4
    for k in range(n_reg):
        r0 = rmin[k]
        r1 = rmax[k]
        if r1 < r0:
            continue
        span = r1 - r0 + 1
        cand_A = np.empty(n_st + span + 2, np.int64)
        cand_mis = np.empty(n_st + span + 2, np.int64)
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
        n_cand = 0
        # A = absolute index of relative r0; the extended position i = A + span (pad = span)
        for A in range(-span, n_st + 1):
            if A + c0 < -2 or A + c1 > n_st + 1 or (A - r0) % 2 != 0:
                continue
            mis = 0
            exp = 0
            for j in range(span):
                a = A + j
                c = n_c[b0 + j]
                g = n_g[b0 + j]
                if a < 0 or a >= n_st:      # outside: not a marker (cyan mismatches), O = 1
                    mis += c + g
                elif is_marker[a]:
                    mis += g
                    exp += c + g
                else:
                    mis += c
            cand_A[n_cand] = A
            cand_mis[n_cand] = mis
            n_cand += 1
            if mis < best_mis:
                best_mis = mis
                best_A = A
                best_exp = exp
        if n_cand == 0:
            continue
        second = big
        need = frac * npx[k]
        for i in range(n_cand):
            if cand_A[i] != best_A and cand_mis[i] < second and \
                    (npx[k] == 0 or cover[cstart[k] + cand_A[i] + span] >= need):
                second = cand_mis[i]
        inside = npx[k] == 0 or cover[cstart[k] + best_A + span] >= need
        status[k] = 3 if inside else 4
        offset[k] = best_A - r0
        evidence[k] = sum_c + best_exp
        mismatch[k] = best_mis
        runner[k] = second
    return status, seen, offset, evidence, mismatch, runner


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
def paint_regions(seg, rel, seg_region, seg_P):
    """Per pixel: region id of its segment (-1), relative index ``rel + P[segment]`` (0 outside
    segments) and whether it is *isolated*: in a segment of no region (bool)."""
    H, W = seg.shape
    region = np.full((H, W), -1, np.int32)
    relative = np.zeros((H, W), np.int32)
    isolated = np.zeros((H, W), np.bool_)
    for v in range(H):
        for u in range(W):
            s = seg[v, u]
            if s >= 0:
                k = seg_region[s]
                region[v, u] = k
                relative[v, u] = rel[v, u] + seg_P[s]
                isolated[v, u] = k < 0
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
    # absolute columns of row v into out (W,) (0 where none) and weight (W,) (1 where one): a
    # column of an indexed region; an unlabelled gap pixel inside a segment (region -1 with a
    # column) takes its left neighbour's region.  off1 = [NaN] + reg_off (indexed by region + 1);
    # kk (W,) int32 and tmp (W,) float32 scratch.  Branch-free loops, one array written per loop
    # (they vectorise; an in-place select would not), dark rows skipped.
    W = out.shape[0]
    reg = region[v]
    crel = column_rel[v]
    mx = np.int32(-1)
    for u in range(W):
        mx = max(mx, reg[u])
    if mx < 0:   # no region in the row: no columns
        for u in range(W):
            out[u] = 0.0
        for u in range(W):
            weight[u] = 0.0
        return False
    kk[0] = max(reg[0], -1) + 1
    a = reg[:W - 1]
    b = reg[1:]
    k1 = kk[1:]
    for i in range(W - 1):
        k = b[i]
        k = a[i] if k < 0 else k
        k1[i] = max(k, -1) + 1
    for u in range(W):
        tmp[u] = crel[u] + off1[kk[u]]
    for u in range(W):
        weight[u] = np.float32(1.0) if tmp[u] == tmp[u] else np.float32(0.0)
    for u in range(W):
        out[u] = tmp[u] if tmp[u] == tmp[u] else np.float32(0.0)
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def rim_mask(column_rel, region, reg_off, reason, half_px, max_pull_px, end_px, rim_code, pull_out):
    """Mask ``rim_code`` into ``reason`` (H, W) uint8, in place where it is 0, where a column is
    unreliable near a silhouette or bend (see :func:`gbscan.decode.rim_rule`); returns the count.

    column_rel (H, W) float32 relative columns; region (H, W) int32; reg_off (n_regions,) float32
    absolute offset (projector px) per region, NaN where the region is not indexed.
    * *pull*: ``|M[c] - c| > max_pull_px`` (0: off), M the vertical mean over rows
      ``v - half_px .. v + half_px`` of the finite absolute columns (a box with the variance of the
      decoder's along-stripe Gaussian when ``half_px ~ sqrt(3) sigma``), by running sums.
    * *end*: at most ``end_px`` (0: off) px from the end of the pixel's row stretch of columns
      and as close to a pixel whose reason is 1..3 (no signal: dark, saturated, low contrast).
    ``pull_out`` (H, W) float32 receives ``M[c] - c`` (pass a (0, 0) array to skip).
    Row-major with per-image-column accumulators; no image-size temporaries.  Per row: the pull
    test branch-free over the row, the end test's window only where the window is not all
    columns (a stretch end), and the few flagged pixels found 8 at a time (the flag rows read as
    uint64 words), then masked in order (as one sequential pass would).
    """
    H, W = column_rel.shape
    want = pull_out.shape[0] == H and pull_out.shape[1] == W
    n_ring = 2 * half_px + 2
    ring = np.empty((n_ring, W), np.float32)   # absolute columns of rows v - half_px - 1 .. v + half_px
    ring_w = np.empty((n_ring, W), np.float32)  # ... 1 where there is one
    has = np.zeros(n_ring, np.bool_)            # ... whether the row has region pixels at all
    num = np.zeros(W, np.float64)
    den = np.zeros(W, np.float64)
    kk = np.empty(W, np.int32)
    tmp = np.empty(W, np.float32)
    Wp = (W + 7) & ~7
    flag = np.zeros(Wp, np.uint8)    # pull rule hits
    need = np.zeros(Wp, np.uint8)    # pixels whose end-rule window must be looked at
    fin = np.zeros(W, np.uint8)      # 1 where a relative column
    ok = np.zeros(W, np.uint8)       # 1 where the end rule's window is all columns, inside the image
    flag64 = flag.view(np.uint64)
    need64 = need.view(np.uint64)
    off1 = np.empty(reg_off.shape[0] + 1, np.float32)
    off1[0] = np.nan
    off1[1:] = reg_off
    pull = max_pull_px > 0
    rc = np.uint8(rim_code)
    n_rim = 0
    for v in range(min(half_px, H)):
        has[v % n_ring] = _abs_row(column_rel, region, off1, v, kk, tmp, ring[v % n_ring], ring_w[v % n_ring])
        for u in range(W):
            num[u] += ring[v % n_ring, u]
            den[u] += ring_w[v % n_ring, u]
    for v in range(H):
        va = v + half_px                      # row entering the window
        vb = v - half_px - 1                  # row leaving it
        if va < H:
            rin = ring[va % n_ring]
            win = ring_w[va % n_ring]
            has[va % n_ring] = _abs_row(column_rel, region, off1, va, kk, tmp, rin, win)
            if pull:
                for u in range(W):                # branch-free running sums
                    num[u] += rin[u]
                for u in range(W):
                    den[u] += win[u]
        if vb >= 0 and pull:
            rout = ring[vb % n_ring]
            wout = ring_w[vb % n_ring]
            for u in range(W):
                num[u] -= rout[u]
            for u in range(W):
                den[u] -= wout[u]
        if not has[v % n_ring]:   # no region in row v: nothing to mask
            continue
        row = ring[v % n_ring]
        roww = ring_w[v % n_ring]
        crel = column_rel[v]
        anyf = np.uint8(0)
        if pull:
            for u in range(W):
                dev = num[u] - row[u] * den[u]          # den * pull, no division
                x = np.uint8((roww[u] != 0) & (abs(dev) > max_pull_px * den[u]))
                flag[u] = x
                anyf |= x
            if want:
                for u in range(W):
                    if roww[u] != 0:
                        pull_out[v, u] = (num[u] - row[u] * den[u]) / den[u]
        else:
            for u in range(W):
                flag[u] = 0
        if end_px > 0:
            # only a pixel with no column somewhere in its window (or whose window leaves the
            # image) can be at a stretch end: the window test runs only there (few pixels)
            for u in range(W):
                fin[u] = np.uint8(crel[u] == crel[u])
            for u in range(W):
                ok[u] = 0
            if W > 2 * end_px:
                n_in = W - 2 * end_px
                oi = ok[end_px:W - end_px]
                c0 = fin[end_px:W - end_px]
                for i in range(n_in):
                    oi[i] = c0[i]
                for d in range(1, end_px + 1):
                    lo = fin[end_px - d:W - end_px - d]
                    hi = fin[end_px + d:W - end_px + d]
                    for i in range(n_in):
                        oi[i] &= lo[i] & hi[i]
            for u in range(W):
                x = np.uint8((roww[u] != 0) & (flag[u] == 0) & (ok[u] == 0))
                need[u] = x
                anyf |= x
        else:
            for u in range(W):
                need[u] = 0
        if anyf == 0:
            continue
        # the flagged pixels, in order: the end rule reads the reasons as masked so far
        rsn = reason[v]
        for wi in range(Wp >> 3):
            if (flag64[wi] | need64[wi]) == 0:
                continue
            for u in range(wi * 8, min(wi * 8 + 8, W)):
                rim = flag[u] != 0
                if need[u] != 0:
                    # at the end of the row stretch and next to no signal (reason 1..3), both
                    # within end_px
                    at_end = u - end_px < 0 or u + end_px >= W
                    near_dark = False
                    for x in range(max(u - end_px, 0), min(u + end_px, W - 1) + 1):
                        cx = rsn[x]
                        if x != u and cx >= 1 and cx <= 3:
                            near_dark = True
                        if crel[x] != crel[x]:
                            at_end = True
                    rim = at_end and near_dark
                if rim and rsn[u] == 0:
                    rsn[u] = rc
                    n_rim += 1
    return n_rim


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
                     seg_region, reg_offset, reg_indexed, is_marker, min_run_px, min_events, clean_level):
    """Pixels of indexed regions whose own row contradicts the region's marker placement.

    A region's offset is fixed by all of its markers at once; a segment that crossed a depth edge
    where the stripes of two surfaces happen to line up (the colour sequence stays valid) carries
    part of the other surface with a shift of an even number of stripes.  Along each segment the
    runs are checked against the region's offset: a cyan run of at least ``min_run_px`` pixels on
    a marker stripe *agrees*, a cyan run on a non-marker stripe or a green/blue run of at least
    ``min_run_px`` pixels on a marker stripe *disagrees*.  A stretch between two agreeing runs (or
    the segment's end) holding at least ``min_events`` disagreements is rejected, the agreeing
    runs at its ends included (the jump lies somewhere in between, and the boundary next to it
    belongs to neither surface), with the unlabelled gaps between them.  A shifted stretch shows
    two kinds of disagreement (its markers where none belong, green/blue where the region's
    markers belong); a single one is usually a marker missed at a rim.  ``is_marker``
    (n_stripes,) bool; stripes outside it are neutral.

    A *clean* disagreement is decisive on its own.  ``gn, bn`` (H, W) float32 are the green and
    blue channels normalised between their local min and max (``gbscan.decode.Classified``).
    A projected marker lights both channels, so even a
    marker pixel the classifier calls green or blue (a missed marker: skin, a rim) keeps the
    other channel well up (``min(gn, bn)`` ~0.3-0.5); on a green or blue stripe the other
    channel sits at its local minimum.  A green/blue run on a marker stripe whose mean
    ``min(gn, bn)`` is below ``clean_level`` is therefore no missed marker but another stripe:
    it counts as ``min_events`` disagreements (``clean_level <= 0``: off; ``gn, bn`` are not read).
    Cyan on a non-marker stripe still counts one (glints, the hard preset's noise).
    Returns the rejected spans, (n, 3) int32 rows ``(v, u_first, u_last)``.
    """
    H, W = labels.shape
    spans = np.empty((16, 3), np.int32)
    n_sp = 0
    n_st = is_marker.shape[0]
    cap = W + 2
    ev = np.zeros(cap, np.int32)    # per run: +1 agree, -w disagree (w its weight), 0 neutral
    ra = np.zeros(cap, np.int32)    # run start / end pixel
    rb = np.zeros(cap, np.int32)
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
            if b - a + 1 >= min_run_px and lab != 0:
                A = rr + reg_offset[k]
                if 0 <= A < n_st:
                    if lab == CYAN:
                        e = 1 if is_marker[A] else -1
                    elif is_marker[A]:
                        e = -1
                        if clean_level > 0:
                            acc = 0.0
                            for x in range(a, b + 1):
                                acc += min(gn[v, x], bn[v, x])
                            if acc < clean_level * (b - a + 1):
                                e = -min_events
            ev[nr] = e
            if e < 0:
                any_bad = True
            nr += 1
            if j < seg_j1[s]:
                a = j_ub[j]
        if not any_bad:
            continue
        for i in range(nr):
            if ev[i] >= 0:
                continue
            lo = i
            while lo > 0 and ev[lo] != 1:
                lo -= 1
            hi = i
            while hi < nr - 1 and ev[hi] != 1:
                hi += 1
            n_bad = 0
            for m in range(lo, hi + 1):
                if ev[m] < 0:
                    n_bad -= ev[m]
            if n_bad < min_events:   # one odd run is noise (a marker missed at a rim, a cyan glint)
                continue
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
    """
    H, W = labels.shape
    out = np.empty((6, max(H - 1, 0) * W + 1), np.int32)   # s, t, offset, agree, same, overlap (a pair per pixel at most)
    table = np.zeros(4096, np.int32)     # votes per offset + 2048 of the current pair (4095: overlap only)
    touched = np.empty(4096, np.int32)
    n_t = 0
    ne = 0
    pair = np.int64(-1)   # current pair s * n_seg + t
    cur = np.int64(-1)    # current key pair * 4096 + offset + 2048 and its count since the last change
    cnt = 0
    for v in range(1, H):
        sr = seg[v]
        tr = seg[v - 1]
        lr = labels[v]
        lu = labels[v - 1]
        rr = rel[v]
        ru = rel[v - 1]
        for u in range(W):
            s = sr[u]
            t = tr[u]
            if s < 0 or t < 0:
                continue
            lab = lr[u]
            labu = lu[u]
            if lab == NONE or labu == NONE:
                continue
            if lab != labu:
                off = 2047  # overlap without a vote (colours differ): counted, not voted
            else:
                off = ru[u] - rr[u]
                if off < -2047:
                    off = -2047
                elif off > 2046:
                    off = 2046
            key = (np.int64(s) * n_seg + t) * 4096 + (off + 2048)
            if key == cur:
                cnt += 1
                continue
            if cnt > 0:   # the run of one key ends: into the pair's table
                kk = cur & 4095
                if table[kk] == 0:
                    touched[n_t] = kk
                    n_t += 1
                table[kk] += cnt
            p = key >> 12
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
            cur = key
            cnt = 1
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


# -- decoder: rim guard (gbscan.decode.rim_guard) --------------------------------------------------
@njit(cache=True, nogil=True, error_model="numpy")
def rim_guard_rows(mask, column, stripe, conf, a1, a2, b_lo, b_hi, b_extra, rows_a, rows_b, ok_code, rim_code,
                   flags, a3=-1):
    """Mask ``rim_code`` the ``ok_code`` pixels within ``rows_a`` rows (same column) of a pixel
    whose code is ``a1`` or ``a2`` (or ``a3`` when >= 0), or within ``rows_b`` rows of one whose code is in
    ``[b_lo, b_hi]`` or equals ``b_extra``; sets column NaN, stripe -1, conf 0 there and returns
    their count (a negative row count disables its class).  The codes are read from the mask as
    given (pixels masked here do not extend the guard).  ``flags`` (H, W) uint8 scratch: bit 1
    class a, bit 2 class b (one pass); then per row the OR of the flags of the rows in reach
    (byte-wide loops that vectorise) decides, and the few hits are written."""
    H, W = mask.shape
    ua1, ua2 = np.uint8(a1), np.uint8(a2)
    ua3 = np.uint8(a3) if a3 >= 0 else ua1   # an optional third code of class a
    ulo, uhi, uex = np.uint8(b_lo), np.uint8(b_hi), np.uint8(b_extra)
    uok = np.uint8(ok_code)
    one, two = np.uint8(1), np.uint8(2)
    for v in range(H):
        mrow = mask[v]
        frow = flags[v]
        for u in range(W):
            m = mrow[u]
            fa = np.uint8((m == ua1) | (m == ua2) | (m == ua3))
            fb = np.uint8(((m >= ulo) & (m <= uhi)) | (m == uex))
            frow[u] = fa | (fb << one)
    reach = max(rows_a, rows_b, 0)
    acc = np.empty(W, np.uint8)
    hitrow = np.empty(W, np.uint8)
    n = 0
    # every decision reads ``flags`` (made from the mask as given), never the rows written here
    for v in range(H):
        acc[:] = 0
        for vv in range(max(v - reach, 0), min(v + reach, H - 1) + 1):
            d = abs(vv - v)
            bits = np.uint8((one if d <= rows_a else 0) | (two if d <= rows_b else 0))
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
        if any_hit:
            n += _unreport_row(hitrow, mrow, column[v], stripe[v], conf[v], rim_code)
    return n


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
        hit = np.uint8(0)
        for u in range(W):
            x = np.uint8(cur[u] == ok_code) & ~(vert[u] | vert[u + 2] | other[u]) & np.uint8(1)
            alone[u] = x
            hit |= x
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
    for k in range(t0 - 1 - half, b + 1):
        buf[k - a] = _brightness(img, lut, k, u, box_h)
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
    for k in range(a, t1 + half + 1):
        buf[k - a] = _brightness(img, lut, k, u, box_h)
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
    """
    H, W = region.shape
    cur = np.full(W, -1, np.int32)
    start = np.zeros(W, np.int64)
    due = np.full(W, H + 1, np.int64)   # row at which the stretch's top test can run (H + 1: done)
    buf = np.empty(H, np.float32)
    n = 0
    box_h = box // 2
    top_rows = reach + half + 1         # the rows the top test reads
    for v in range(H + 1):
        for u in range(W):
            r = region[v, u] if v < H else np.int32(-1)
            if r == cur[u]:
                if v == due[u]:
                    # the top test, while its rows are recent (they are the same for any end below)
                    a = start[u]
                    hi_t = _step_above(img, lut, box_h, u, a, v - 1, reach, ratio, half, flat, buf)
                    n += _unreport_rows(mask, column, stripe, conf, u, a, hi_t, ok_code, code)
                    due[u] = H + 1
                continue
            if cur[u] >= 0:
                a = start[u]
                b = v - 1
                if due[u] <= H:   # a short stretch: its top test now
                    hi_t = _step_above(img, lut, box_h, u, a, b, reach, ratio, half, flat, buf)
                    n += _unreport_rows(mask, column, stripe, conf, u, a, hi_t, ok_code, code)
                lo_t = _step_below(img, lut, box_h, u, a, b, reach, ratio, half, flat, buf)
                n += _unreport_rows(mask, column, stripe, conf, u, lo_t - 1, b, ok_code, code)
            cur[u] = r
            start[u] = v
            due[u] = v + top_rows if r >= 0 else H + 1
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
    sg = 0.0
    sb = 0.0
    n = 0
    for v in range(0, H, row_step):
        for u in range(W):
            g = lut[img[v, u, 1]]
            b = lut[img[v, u, 2]]
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
    for v in range(0, H, row_step):
        state = 0
        start = -1
        for u in range(W):
            g = lut[img[v, u, 1]]
            b = lut[img[v, u, 2]]
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
def _slopes(col, region, limit):
    # per coarse pixel with a finite column: the column's change per pixel along the rows (gx) and
    # across them (gy) from its neighbours on the same surface (same region, both columns finite
    # and within ``limit``; central, else one-sided, else 0), and which of the four neighbours are
    # on it (bits 1 right, 2 left, 4 below, 8 above).  Each pair of neighbours is tested once.
    h, w = col.shape
    gx = np.zeros((h, w), np.float32)
    gy = np.zeros((h, w), np.float32)
    nb = np.zeros((h, w), np.uint8)
    pair = np.zeros(w, np.bool_)       # pair (j, j + 1) of the row, or (i, j) - (i + 1, j)
    diff = np.zeros(w, np.float32)
    for i in range(h):
        c = col[i]
        r = region[i]
        for j in range(w - 1):
            d = c[j + 1] - c[j]
            diff[j] = d
            pair[j] = (r[j] == r[j + 1]) & (abs(d) < limit)       # NaN: False
        nbi = nb[i]
        gxi = gx[i]
        for j in range(w):
            right = j < w - 1 and pair[j]
            left = j > 0 and pair[j - 1]
            nbi[j] = (1 if right else 0) | (2 if left else 0)
            if right and left:
                gxi[j] = 0.5 * (diff[j] + diff[j - 1])
            elif right:
                gxi[j] = diff[j]
            elif left:
                gxi[j] = diff[j - 1]
    for i in range(h - 1):
        c0, c1 = col[i], col[i + 1]
        r0, r1 = region[i], region[i + 1]
        for j in range(w):
            d = c1[j] - c0[j]
            if (r0[j] == r1[j]) & (abs(d) < limit):
                nb[i, j] |= 4
                nb[i + 1, j] |= 8
                gy[i, j] += d        # below (halved below where both)
                gy[i + 1, j] += d    # above
    for i in range(h):
        for j in range(w):
            if nb[i, j] & 12 == 12:
                gy[i, j] *= 0.5
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
def _put_expanded(co, so, fo, mo, u, m0, bits, need, cj, gxj, gyj, cfj, dx, dy, stripe_px, no_boundary, edge_code):
    # _expanded's full pixel stored at u of the output rows (column, stripe, confidence, mask);
    # returns its mask code
    m, x, s = _expanded(m0, bits, need, cj, gxj, gyj, dx, dy, stripe_px, no_boundary, edge_code)
    co[u] = x
    so[u] = s
    fo[u] = cfj if m == 0 else np.float32(0.0)
    mo[u] = m
    return m


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
        col_o, stripe_o, conf_o, mask_o, counts4 = _upsample_x2(column, conf, mask, gx, gy, nb, stripe_px, no_boundary,
                                                                edge_code)
    else:
        col_o, stripe_o, conf_o, mask_o, counts4 = _upsample_any(H, W, column, conf, mask, gx, gy, nb, stripe_px,
                                                                 no_boundary, edge_code, centre_tol)
    counts = counts4[0] + counts4[1] + counts4[2] + counts4[3]
    return col_o, stripe_o, conf_o, mask_o, counts


@njit(cache=True, nogil=True, error_model="numpy")
def _new_maps(H, W):
    # upsample_stripes' outputs: column, stripe, confidence, mask (H, W) and four interleaved
    # histograms of the mask codes (4, 16) (no chain of increments)
    return (np.empty((H, W), np.float32), np.empty((H, W), np.int32), np.empty((H, W), np.float32),
            np.empty((H, W), np.uint8), np.zeros((4, 16), np.int64))


@njit(cache=True, nogil=True, error_model="numpy")
def _upsample_any(H, W, column, conf, mask, gx, gy, nb, stripe_px, no_boundary, edge_code, centre_tol):
    # upsample_stripes' loop for any factor: one loop over the full pixels with their coarse column
    # looked up, each row's codes counted after the row (head at 1280x1024 shrunk by 1.75: a loop
    # per coarse pixel counting per pixel 4.2 ms; counting per row 3.3; one loop 2.5-2.7)
    h, w = column.shape
    col_o, stripe_o, conf_o, mask_o, counts4 = _new_maps(H, W)
    dxs, xbit, jidx = _coarse_columns(w, W, centre_tol)
    for v in range(H):
        i, dy, ybit = _coarse_row(v, h, H, centre_tol)
        m_r, c_r, gx_r, gy_r, nb_r, cf_r = mask[i], column[i], gx[i], gy[i], nb[i], conf[i]
        co, so, fo, mo = col_o[v], stripe_o[v], conf_o[v], mask_o[v]
        for u in range(W):
            j = jidx[u]
            _put_expanded(co, so, fo, mo, u, m_r[j], nb_r[j], xbit[u] | ybit, c_r[j], gx_r[j], gy_r[j], cf_r[j], dxs[u],
                          dy, stripe_px, no_boundary, edge_code)
        for u in range(W):
            counts4[u & 3, mo[u] & 15] += 1
    return col_o, stripe_o, conf_o, mask_o, counts4


@njit(cache=True, nogil=True, error_model="numpy")
def _upsample_x2(column, conf, mask, gx, gy, nb, stripe_px, no_boundary, edge_code):
    # upsample_stripes' loop for an exact half (H = 2 h, W = 2 w): the full pixel (2 i + a, 2 j + b)
    # of coarse pixel (i, j) sits at dy, dx = -1/4 (a, b = 0) or +1/4 (1) coarse px -- the same
    # values as the general loop computes -- and always needs the neighbour bit its offset points to
    # (8 / 4 across the rows, 2 / 1 along them).  Two full pixels per coarse pixel and row with the
    # offsets as constants: 1.6 ms at 1280x1024 where the general loop takes 4.3.
    h, w = column.shape
    W = 2 * w
    col_o, stripe_o, conf_o, mask_o, counts4 = _new_maps(2 * h, W)
    q = 0.25
    for i in range(h):
        m_r, c_r, gx_r, gy_r, nb_r, cf_r = mask[i], column[i], gx[i], gy[i], nb[i], conf[i]
        for a in range(2):
            v = 2 * i + a
            dy = q if a == 1 else -q
            ybit = np.uint8(4) if a == 1 else np.uint8(8)
            co, so, fo, mo = col_o[v], stripe_o[v], conf_o[v], mask_o[v]
            for j in range(w):
                m0, bits, cj, gxj, gyj, cfj = m_r[j], nb_r[j], c_r[j], gx_r[j], gy_r[j], cf_r[j]
                for b in range(2):
                    _put_expanded(co, so, fo, mo, 2 * j + b, m0, bits, ybit | (np.uint8(1) if b == 1 else np.uint8(2)),
                                  cj, gxj, gyj, cfj, q if b == 1 else -q, dy, stripe_px, no_boundary, edge_code)
            for u in range(W):
                counts4[u & 3, mo[u] & 15] += 1
    return col_o, stripe_o, conf_o, mask_o, counts4


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
