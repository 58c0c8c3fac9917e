"""Sequential row/segment kernels of the decoder, compiled with numba (``cache=True``).

Only :mod:`gbscan.unwrap` and :mod:`gbscan.decode` import this module, so ``gbscan --help`` never
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
def _merge_runs(rs, re, rl, k, nr):
    """Merge runs k-1, k, k+1 of a row into run k-1 (in place); returns the new run count."""
    re[k - 1] = re[k + 1]
    for m in range(k + 2, nr):
        rs[m - 2] = rs[m]
        re[m - 2] = re[m]
        rl[m - 2] = rl[m]
    return nr - 2


@njit(cache=True, nogil=True)
def row_segments(labels, max_gap_px, spike_px):
    """Paper step 1 kernel: unroll each row by the transitions along it.

    Returns per pixel ``seg`` (H, W) int32 (-1 outside segments) and ``rel`` (H, W) int32;
    per segment ``seg_row, seg_u0, seg_u1`` (inclusive pixel span), ``seg_j0, seg_j1`` (its
    junctions ``j0 .. j1-1``), ``seg_parity`` (1 if a green or blue run fixed the parity);
    per junction ``j_seg, j_ua`` (last pixel of the left run), ``j_ub`` (first pixel of the right
    run), ``j_la, j_lb`` (labels), ``j_rel`` (relative index of the right run = boundary index).

    Robustness inside a row: runs of at most ``spike_px`` pixels flanked on both sides by the
    same colour are noise and are merged into their neighbours; gaps (NONE) of at most
    ``max_gap_px`` between different colours are a transition, between equal colours the same
    stripe; any other gap, or a colour whose parity contradicts the count of transitions
    (e.g. ``G C B``: a marker is always flanked by equal colours), ends the segment.
    """
    H, W = labels.shape
    seg = np.full((H, W), -1, np.int32)
    rel = np.zeros((H, W), np.int32)
    cap_s = H * (W // 2 + 1)
    seg_row = np.empty(cap_s, np.int32)
    seg_u0 = np.empty(cap_s, np.int32)
    seg_u1 = np.empty(cap_s, np.int32)
    seg_j0 = np.empty(cap_s, np.int32)
    seg_j1 = np.empty(cap_s, np.int32)
    seg_par = np.empty(cap_s, np.uint8)
    cap_j = H * W // 2 + H
    j_seg = np.empty(cap_j, np.int32)
    j_ua = np.empty(cap_j, np.int32)
    j_ub = np.empty(cap_j, np.int32)
    j_la = np.empty(cap_j, np.uint8)
    j_lb = np.empty(cap_j, np.uint8)
    j_rel = np.empty(cap_j, np.int32)
    rs = np.empty(W, np.int32)
    re = np.empty(W, np.int32)
    rl = np.empty(W, np.uint8)
    ns = 0
    nj = 0
    for v in range(H):
        # -- run-length encode the row
        nr = 0
        u = 0
        while u < W:
            lab = labels[v, u]
            e = u
            while e + 1 < W and labels[v, e + 1] == lab:
                e += 1
            rs[nr] = u
            re[nr] = e
            rl[nr] = lab
            nr += 1
            u = e + 1
        # -- spike removal: short run between two equal colours (directly adjacent) -> merge
        if spike_px > 0 and nr >= 3:
            k = 1
            while k < nr - 1:
                if (rl[k] != NONE and rl[k - 1] != NONE and rl[k - 1] == rl[k + 1]
                        and re[k] - rs[k] + 1 <= spike_px and re[k - 1] + 1 == rs[k] and re[k] + 1 == rs[k + 1]):
                    nr = _merge_runs(rs, re, rl, k, nr)  # merge k-1, k, k+1
                else:
                    k += 1
        # -- small gaps: equal colours across a small gap -> one run; else keep the gap as a gap
        if max_gap_px > 0 and nr >= 3:
            k = 1
            while k < nr - 1:
                if (rl[k] == NONE and re[k] - rs[k] + 1 <= max_gap_px and rl[k - 1] != NONE
                        and rl[k - 1] == rl[k + 1]):
                    nr = _merge_runs(rs, re, rl, k, nr)
                else:
                    k += 1
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
                seg[v, uu] = s
                rel[v, uu] = r
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
                                if seg[v, uu] == s:
                                    rel[v, uu] += 1
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
                    seg[v, uu] = s
                    rel[v, uu] = r
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
def vertical_votes(labels, seg, rel, n_seg):
    """Paper step 2 kernel: relate every segment to the overlapping segments of the row above.

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
def subpixel_junctions(gn, bn, j_row, j_ua, j_ub, j_la, j_lb, seg_u0, seg_u1, j_seg):
    """Sub-pixel position (camera px, along the row) of every junction (stripe boundary).

    ``gn, bn`` are the colour channels normalised to [0, 1] between their local minimum and
    maximum.  The boundary is the crossing of the channel(s) that change: ``gn = bn`` for green|blue
    (both channels swap: a symmetric signal, so gamma and equal blur do not bias it), ``bn = 1/2``
    for green|cyan and ``gn = 1/2`` for blue|cyan.  The crossing nearest to the runs' junction is
    searched from the last pixel of the left run - 1 to the first pixel of the right run + 1 and
    located by linear interpolation between the two samples that bracket it.  NaN if none.
    """
    nj = j_row.shape[0]
    out = np.full(nj, np.nan, np.float32)
    for j in range(nj):
        v = j_row[j]
        la = j_la[j]
        lb = j_lb[j]
        s = j_seg[j]
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
def interpolate_columns(H, W, seg_row, seg_u0, seg_u1, seg_j0, seg_j1, seg_ok, j_x, j_bnd, stripe_px,
                        extrapolate):
    """Continuous projector column of every pixel of the accepted segments.

    Between two consecutive boundaries at camera positions ``x_k < x_{k+1}`` with projector columns
    ``c_k, c_{k+1}`` (``c = index * stripe_px - 0.5``) a pixel at ``u`` gets
    ``c_k + (u - x_k) (c_{k+1} - c_k) / (x_{k+1} - x_k)``.  Pixels beyond the first/last boundary
    of a segment are extrapolated with the neighbouring interval's slope up to ``extrapolate``
    times that interval's width (else left NaN).  Boundaries out of order (non-increasing) are
    dropped.  ``j_bnd`` is the boundary index (relative or absolute: the caller shifts).
    """
    col = np.full((H, W), np.nan, np.float32)
    xs = np.empty(W + 2, np.float64)
    cs = np.empty(W + 2, np.float64)
    for s in range(seg_row.shape[0]):
        if not seg_ok[s]:
            continue
        v = seg_row[s]
        n = 0
        for j in range(seg_j0[s], seg_j1[s]):
            x = j_x[j]
            if np.isnan(x):
                continue
            if n > 0 and x <= xs[n - 1] + 0.05:
                continue
            xs[n] = x
            cs[n] = j_bnd[j] * stripe_px - 0.5
            n += 1
        if n < 2:
            continue
        k = 0
        for u in range(seg_u0[s], seg_u1[s] + 1):
            while k < n - 2 and u >= xs[k + 1]:
                k += 1
            x0 = xs[k]
            x1 = xs[k + 1]
            slope = (cs[k + 1] - cs[k]) / (x1 - x0)
            if u < x0 and x0 - u > extrapolate * (x1 - x0):
                continue
            if u > x1 and u - x1 > extrapolate * (x1 - x0):
                continue
            col[v, u] = cs[k] + (u - x0) * slope
    return col


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


@njit(cache=True, nogil=True, fastmath=True)
def classify_pixels(g, b, d, thr, lo_g, hi_g, lo_b, hi_b, raw_g, raw_b, raw_hi, raw_max, cyan_level, min_level,
                    raw_margin, min_contrast, dark_level, saturation_level):
    """Per-pixel part of :func:`gbscan.decode.classify` in one pass (see there for the rules).

    Returns labels (uint8), reason (uint8: 0 ok, 1 dark, 2 saturated, 3 low contrast), gn, bn
    (normalised channels) and contrast (float32).
    """
    H, W = g.shape
    labels = np.empty((H, W), np.uint8)
    reason = np.empty((H, W), np.uint8)
    gn = np.empty((H, W), np.float32)
    bn = np.empty((H, W), np.float32)
    contrast = np.empty((H, W), np.float32)
    for v in range(H):
        for u in range(W):
            rg = max(hi_g[v, u] - lo_g[v, u], np.float32(1e-3))
            rb = max(hi_b[v, u] - lo_b[v, u], np.float32(1e-3))
            ig = np.float32(1.0) / rg
            ib = np.float32(1.0) / rb
            x = (g[v, u] - lo_g[v, u]) * ig
            y = (b[v, u] - lo_b[v, u]) * ib
            gn[v, u] = x
            bn[v, u] = y
            c = min(rg / max(hi_g[v, u], np.float32(1e-3)), rb / max(hi_b[v, u], np.float32(1e-3)))
            contrast[v, u] = c
            lab = GREEN if d[v, u] > thr[v, u] else BLUE
            hn = max(x, y)
            ln = min(x, y)
            if x > cyan_level and y > cyan_level:
                lab = CYAN
            elif hn > cyan_level and ln > min_level:
                lab = NONE  # the edge of a cyan marker: neither colour
            diff_raw = (raw_g[v, u] - lo_g[v, u]) * ig - (raw_b[v, u] - lo_b[v, u]) * ib
            r = 0
            if c < min_contrast or (lab == GREEN and diff_raw < -raw_margin) or (lab == BLUE and diff_raw > raw_margin):
                r = 3
            mod = max(rg, rb)
            if mod < dark_level or hn < min_level or raw_hi[v, u] - min(lo_g[v, u], lo_b[v, u]) < np.float32(0.5) * mod:
                r = 1
            if raw_max[v, u] >= saturation_level:
                r = 2
            if r != 0:
                lab = NONE
            labels[v, u] = lab
            reason[v, u] = r
    return labels, reason, gn, bn, contrast


@njit(cache=True, nogil=True)
def finish_pixels(reason, labels, region_in, relative, column_rel, inconsistent, reg_shift, reg_indexed, reg_margin,
                  contrast, stripe_px, n_stripes, min_contrast):
    """Final masks, absolute stripe, column and confidence (see :func:`gbscan.decode.decode`).

    Reason codes as in ``gbscan.decode``: 0 ok, 4 isolated, 5 inconsistent, 6 unindexed,
    7 no boundary (1-3 come from ``reason``).  One-pixel unlabelled gaps between two pixels of
    one region join that region.  A reported pixel must lie within one stripe of its colour
    run's stripe, inside the pattern, and agree within half a stripe with a reported vertical
    neighbour.
    """
    H, W = reason.shape
    mask = reason.copy()
    region = region_in.copy()
    column = np.full((H, W), np.nan, np.float32)
    stripe = np.full((H, W), -1, np.int32)
    conf = np.zeros((H, W), np.float32)
    w = stripe_px
    for v in range(H):
        for u in range(W):
            if mask[v, u] != 0:
                continue
            r = region[v, u]
            gap = False
            if r < 0 and labels[v, u] == NONE and 0 < u < W - 1:
                rl = region_in[v, u - 1]
                if rl >= 0 and rl == region_in[v, u + 1]:
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
    # vertical continuity: a reported pixel needs a reported vertical neighbour within w/2
    half = 0.5 * w
    lonely = np.zeros((H, W), np.bool_)
    for v in range(H):
        for u in range(W):
            if mask[v, u] != 0:
                continue
            c = column[v, u]
            ok = False
            if v > 0 and mask[v - 1, u] == 0 and abs(column[v - 1, u] - c) <= half:
                ok = True
            if not ok and v + 1 < H and mask[v + 1, u] == 0 and abs(column[v + 1, u] - c) <= half:
                ok = True
            lonely[v, u] = not ok
    for v in range(H):
        for u in range(W):
            if lonely[v, u]:
                mask[v, u] = 5
    for v in range(H):
        for u in range(W):
            if mask[v, u] != 0:
                column[v, u] = np.nan
                stripe[v, u] = -1
                continue
            cc = min(max((contrast[v, u] - min_contrast) / max(min_contrast, 1e-3), 0.0), 1.0)
            conf[v, u] = 0.25 + 0.75 * cc * reg_margin[region[v, u]]
    return mask, column, stripe, conf, region


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
def paint_regions(seg, rel, seg_region, seg_P):
    """Per pixel: region id of its segment (-1) and relative index ``rel + P[segment]``."""
    H, W = seg.shape
    region = np.full((H, W), -1, np.int32)
    relative = np.zeros((H, W), np.int32)
    for v in range(H):
        for u in range(W):
            s = seg[v, u]
            if s >= 0:
                region[v, u] = seg_region[s]
                relative[v, u] = rel[v, u] + seg_P[s]
    return region, relative


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
