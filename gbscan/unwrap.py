"""Unwrapping the green-blue stripes (the paper's seven steps) and absolute indexing by markers.

Input: a colour-class image ``labels`` (H, W) uint8 (``gbscan.pattern.NONE/GREEN/BLUE/CYAN``)
from :mod:`gbscan.decode`.  Output: for every pixel a *relative* stripe index that is consistent
inside a connected *region*, then (with cyan markers) the region's absolute offset.

Vocabulary (the paper gives only the step names; this is how each is realised):

* **run** -- a maximal horizontal stretch of one colour in a row.
* **segment** -- a maximal chain of runs along a row joined by valid stripe transitions; inside a
  segment the relative index ``rel`` counts transitions, its parity fixed by colour (green even,
  blue odd; cyan markers take the count).  A row usually holds several segments (shadows,
  occlusions, objects).  Segments, not rows, are the units related to the row above.
* **edge** -- a vote between a segment and an overlapping segment of the row above: every pixel
  whose upper neighbour has the same colour votes for ``rel_above - rel``; the winning (even)
  offset, its votes ``n_agree`` and the agreement fraction ``n_agree / n_same`` make the edge.
  *Strong* edges have ``n_agree >= n_ref_pixels`` and fraction ``>= agree_frac``.
* **region** -- segments joined by strong edges whose offsets are mutually consistent
  (union-find with potentials, strongest edges first; a contradicting edge is a *conflict*, not
  applied).  All indices inside a region share one unknown even offset.

The seven steps (paper wording -> function):

1. *unroll each row by transitions along it* -> :func:`unroll_rows` (runs -> segments; spike
   runs and small gaps cleaned, parity contradictions end a segment), then
   :func:`cut_depth_edges` (a transition where the sub-pixel boundary spacing jumps is a depth
   edge, not a stripe boundary of one surface: the segment is cut there).
2. *unroll every row by relation with the upper neighbour row* -> :func:`relate_rows` (edges;
   an edge is strong with enough agreeing votes, few dissenters, enough overlap and colours kept).
3. *determine believable rows* -> :func:`believable_segments`: a segment is believable when its
   stripes continue, through strong edges, over at least ``n_ref_rows`` rows.
4. *unroll each pixel by relation with its upper neighbour in believable rows* ->
   :func:`link_believable`: believable segments are joined (strongest edges first) into regions;
   every pixel of them gets ``rel + P[segment]``.
5. *unroll each row by transitions again* -> :func:`split_doubtful`: a segment that is not
   believable is cut where its relation to the rows above and below changes (an inserted or lost
   stripe shifts the index of the rest of the row by two): each piece is a new segment.
6. *unroll every row by relation with the upper neighbour* -> :func:`attach_doubtful`: the pieces
   are related to their neighbours again and each joins at most one region through a strong edge
   (a doubtful piece never merges two regions).
7. *unroll each pixel by relation with its upper neighbour* -> :func:`check_pixels`: a pixel whose
   upper or lower neighbour has the same colour and region but another index is flagged.

No step optimises globally; each decision uses only a pixel's own row and its neighbour rows.
Absolute indexing (beyond the paper) is :func:`index_regions`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import GBError
from .pattern import NONE, PatternSpec


@dataclass(frozen=True)
class UnwrapParams:
    """Parameters of the unwrapping and the absolute indexing.

    n_ref_pixels : votes (pixels) an edge between two segments needs to be strong.
    n_ref_rows : rows a segment's stripes must continue through to be believable (step 3).
    agree_frac : fraction of an edge's same-colour votes that must agree on its offset.
    min_overlap_frac : agreeing votes an edge needs, as a fraction of its shorter segment's length.
    same_frac : fraction of an edge's overlapping labelled pixels that must keep their colour.
    max_gap_px : unlabelled gap (px) a segment may bridge along a row.
    spacing_ratio : a row is cut where consecutive boundary spacings differ by more than this
        factor (a depth edge; 0 disables; needs sub-pixel boundaries, see :func:`unwrap`).
    spike_px : runs of at most this many px flanked by one colour are noise (0: keep all).
    min_region_px : regions smaller than this are dropped (mask "isolated").
    min_marker_px : pixels of a marker stripe a region must see for it to count as observed.
    min_markers : distinct markers a region must see to be indexed (three consecutive ones fix the
        offset by construction; two can, together with the marker-free stripes around them, when
        the margin test passes).
    index_margin : the best offset's mismatch must be lower than the runner-up's by this
        fraction of the region's marker evidence.
    max_mismatch : largest acceptable mismatch of the best offset, as a fraction of the evidence.
    """

    n_ref_pixels: int = 4
    n_ref_rows: int = 3
    agree_frac: float = 0.8
    min_overlap_frac: float = 0.3
    same_frac: float = 0.75
    spacing_ratio: float = 1.35
    max_gap_px: int = 1
    spike_px: int = 1
    min_region_px: int = 150
    min_marker_px: int = 12
    min_markers: int = 2
    index_margin: float = 0.25
    max_mismatch: float = 0.05

    def __post_init__(self):
        for name in ("n_ref_pixels", "n_ref_rows", "min_region_px", "min_markers"):
            if int(getattr(self, name)) < 1:
                raise GBError(f"UnwrapParams.{name} must be >= 1, got {getattr(self, name)}")
        if not 0.5 <= float(self.agree_frac) <= 1.0:
            raise GBError(f"UnwrapParams.agree_frac must be in [0.5, 1], got {self.agree_frac}")
        if int(self.max_gap_px) < 0 or int(self.spike_px) < 0:
            raise GBError("UnwrapParams.max_gap_px and spike_px must be >= 0")


@dataclass
class Segments:
    """Step-1 result.  Per pixel: ``seg`` (H, W) int32 (-1 none), ``rel`` (H, W) int32.
    Per segment (numbered row by row, left to right): ``row, u0, u1`` (inclusive span),
    ``j0, j1`` (junction range), ``parity`` (1 if colour fixed the parity).
    Per junction (boundary between consecutive runs): ``j_seg, j_ua, j_ub, j_la, j_lb, j_rel``
    (``j_rel`` = relative index of the stripe right of the boundary = relative boundary index),
    ``j_x`` its sub-pixel camera position (float32, NaN if not located; None if not computed).
    """

    seg: np.ndarray
    rel: np.ndarray
    row: np.ndarray
    u0: np.ndarray
    u1: np.ndarray
    j0: np.ndarray
    j1: np.ndarray
    parity: np.ndarray
    j_seg: np.ndarray
    j_ua: np.ndarray
    j_ub: np.ndarray
    j_la: np.ndarray
    j_lb: np.ndarray
    j_rel: np.ndarray
    j_x: np.ndarray | None = None  # sub-pixel camera position of each junction (when known)

    @property
    def n(self) -> int:
        return int(self.row.shape[0])


@dataclass
class Edges:
    """Step-2 result: segment ``s`` (row v) and ``t`` (row v-1), winning ``offset``
    (``rel_t - rel_s``), ``n_agree`` votes for it, ``n_same`` same-colour votes in all,
    ``n_overlap`` labelled pixel pairs, ``len_min`` the shorter segment's length."""

    s: np.ndarray
    t: np.ndarray
    offset: np.ndarray
    n_agree: np.ndarray
    n_same: np.ndarray
    n_overlap: np.ndarray
    len_min: np.ndarray | None = None

    def strong(self, p: UnwrapParams) -> np.ndarray:
        """Enough agreeing votes, a high agreeing fraction, fewer than ``n_ref_pixels`` dissenters,
        and agreeing votes over at least ``min_overlap_frac`` of the shorter segment (at a depth
        edge two surfaces overlap on a few pixels only, where stripes may line up by chance)."""
        dissent = self.n_same - self.n_agree
        ok = ((self.n_agree >= p.n_ref_pixels) & (self.n_agree >= p.agree_frac * self.n_same)
              & (dissent < p.n_ref_pixels))
        if self.len_min is not None:
            ok &= self.n_agree >= p.min_overlap_frac * self.len_min
        # colours kept from row to row: across a depth edge the stripes are shifted and many
        # vertically adjacent pixels change colour even when the votes happen to agree
        ok &= self.n_same >= p.same_frac * self.n_overlap
        return ok

    def disputed(self, p: UnwrapParams) -> np.ndarray:
        """At least ``n_ref_pixels`` same-colour votes dissent from the winning offset: part of one
        of the two segments is shifted (an inserted or lost stripe, or another surface)."""
        return (self.n_same - self.n_agree) >= p.n_ref_pixels


@dataclass
class Unwrapped:
    """Result of :func:`unwrap`.

    relative : (H, W) int32 stripe index consistent within a region (meaningless where region < 0).
    region : (H, W) int32 region id 0..n-1, -1 where the pixel is in no kept region.
    inconsistent : (H, W) bool pixels flagged by step 7.
    segments, edges : the step-1/2 tables; ``seg_region`` (n_seg,) region per segment (-1),
    ``seg_P`` (n_seg,) int32 potential (``relative = rel + seg_P[seg]``).
    stats : counts (segments, believable, regions found/kept, conflicts).
    """

    relative: np.ndarray
    region: np.ndarray
    inconsistent: np.ndarray
    segments: Segments
    edges: Edges
    seg_region: np.ndarray
    seg_P: np.ndarray
    region_px: np.ndarray
    region_conflicts: np.ndarray
    believable: np.ndarray
    isolated: np.ndarray
    stats: dict = field(default_factory=dict)


# -- step 1 -------------------------------------------------------------------------------------
def unroll_rows(labels: np.ndarray, max_gap_px: int = 1, spike_px: int = 1) -> Segments:
    """Step 1, *unroll each row by transitions along it*.

    ``labels`` (H, W) uint8.  Along each row, runs of one colour are chained while consecutive
    colours differ and are adjacent (or separated by at most ``max_gap_px`` unlabelled pixels);
    each colour change is one stripe boundary (+1 to the relative index).  Parity is fixed by
    colour: a green run must get an even index, a blue one odd; a contradiction (``G C B``: a
    marker is always flanked by equal colours) ends the segment.  Runs of at most ``spike_px``
    pixels between two runs of one colour are noise and are absorbed.
    """
    from . import kernels

    labels = np.ascontiguousarray(labels, dtype=np.uint8)
    out = kernels.row_segments(labels, int(max_gap_px), int(spike_px))
    return Segments(*out)


# -- step 2 -------------------------------------------------------------------------------------
def relate_rows(labels: np.ndarray, segs: Segments) -> Edges:
    """Step 2, *unroll every row by relation with the upper neighbour row*.

    Every pixel whose upper neighbour carries the same colour votes for the offset between the
    two segments' relative indices (stripes are near-vertical, so most same-colour vertical
    neighbours lie on the same stripe; pixels next to a boundary that shifts between rows
    differ in colour and do not vote).  Returns one edge per overlapping pair, with the winning
    offset and the vote counts (sorted by the lower segment ``s``).
    """
    from . import kernels

    n = max(segs.n, 1)
    e = kernels.vertical_votes(np.ascontiguousarray(labels, dtype=np.uint8), segs.seg, segs.rel, n)
    length = (segs.u1 - segs.u0 + 1).astype(np.int32)
    len_min = np.minimum(length[e[0]], length[e[1]]) if segs.n else np.zeros(0, np.int32)
    return Edges(*e, len_min=len_min)


# -- step 3 -------------------------------------------------------------------------------------
def believable_segments(segs: Segments, edges: Edges, p: UnwrapParams) -> np.ndarray:
    """Step 3, *determine believable rows*: (n_seg,) bool.

    A segment is believable when it is linked by strong edges (enough agreeing votes, few
    dissenting ones) into a vertical chain covering at least ``n_ref_rows`` rows, it saw a green
    or blue run (parity known), and none of its edges to the row above or below is a strong
    disagreement (an edge with many votes but a low agreement fraction means part of the segment
    is shifted: an inserted or lost stripe) -- :meth:`Edges.disputed`.
    """
    from . import kernels

    strong = edges.strong(p)
    chain = kernels.chain_lengths(segs.n, edges.s, edges.t, strong)
    ok = (chain >= p.n_ref_rows) & (segs.parity > 0)
    bad_edge = edges.disputed(p)
    disputed = np.zeros(segs.n, bool)
    disputed[edges.s[bad_edge]] = True
    disputed[edges.t[bad_edge]] = True
    return ok & ~disputed


# -- steps 4 and 6 ------------------------------------------------------------------------------
def _edge_order(edges: Edges) -> np.ndarray:
    # strongest first: most agreeing votes, then fewest dissenting ones
    return np.lexsort((edges.n_same - edges.n_agree, -edges.n_agree)).astype(np.int64)


def link_believable(segs: Segments, edges: Edges, believable: np.ndarray, p: UnwrapParams):
    """Step 4, *unroll each pixel by relation with its upper neighbour in believable rows*.

    Two stages, so that one lucky row pair never welds two surfaces together (at a horizontal
    depth edge the stripes of the far and the near surface may happen to line up):

    a. *strips*: a believable segment is linked to the one above when each is the other's best
       strong edge (mutual best match); strips are vertical chains of segments on one surface.
    b. strips are merged when at least ``n_ref_rows`` distinct edges between them agree on the
       relative offset and at least ``agree_frac`` of all their strong edges do; pairs with the
       most support first; an edge contradicting what is already fixed is a conflict.

    Every pixel of a region then gets ``rel + P[segment]``, consistent with its upper neighbour.
    Returns the union-find state ``(parent, pot, size, conflicts)``.
    """
    from . import kernels

    n = segs.n
    parent = np.arange(n, dtype=np.int32)
    pot = np.zeros(n, np.int32)
    size = np.ones(n, np.int32)
    conflicts = np.zeros(n, np.int32)
    strong = edges.strong(p) & believable[edges.s] & believable[edges.t]
    ids = np.flatnonzero(strong)
    if ids.size == 0:
        return parent, pot, size, conflicts
    # a. mutual best edges -> strips
    score = edges.n_agree[ids].astype(np.int64) * 4096 - (edges.n_same[ids] - edges.n_agree[ids])
    best_up = np.full(n, -1, np.int64)
    best_dn = np.full(n, -1, np.int64)
    o = np.argsort(score, kind="stable")  # ascending: the last write wins -> best
    best_up[edges.s[ids[o]]] = ids[o]
    best_dn[edges.t[ids[o]]] = ids[o]
    mutual = np.zeros(edges.s.size, bool)
    mutual[ids] = (best_up[edges.s[ids]] == ids) & (best_dn[edges.t[ids]] == ids)
    kernels.link_segments(parent, pot, size, conflicts, edges.s, edges.t, edges.offset, _edge_order(edges),
                          mutual, believable, False)
    root, P = kernels.resolve_roots(parent, pot)
    # b. merge strips by consensus of the other strong edges
    rest = ids[~mutual[ids]]
    if rest.size:
        A = root[edges.s[rest]].astype(np.int64)
        B = root[edges.t[rest]].astype(np.int64)
        delta = edges.offset[rest].astype(np.int64) - P[edges.s[rest]] + P[edges.t[rest]]
        inside = A == B
        conflicts_inside = rest[inside & (delta != 0)]
        np.add.at(conflicts, edges.s[conflicts_inside], 1)
        np.add.at(conflicts, edges.t[conflicts_inside], 1)
        A, B, delta = A[~inside], B[~inside], delta[~inside]
        swap = A > B
        A, B = np.where(swap, B, A), np.where(swap, A, B)
        delta = np.where(swap, -delta, delta)
        if A.size:
            key = (A * n + B) * 8192 + (delta + 4096)
            ukey, cnt = np.unique(key, return_counts=True)
            pair = ukey // 8192
            upair, inv = np.unique(pair, return_inverse=True)
            tot = np.bincount(inv, weights=cnt)
            ok = (cnt >= p.n_ref_rows) & (cnt >= p.agree_frac * tot[inv])
            pa = (pair // n).astype(np.int32)
            pb = (pair % n).astype(np.int32)
            pdelta = (ukey % 8192 - 4096).astype(np.int32)
            order = np.argsort(-cnt, kind="stable").astype(np.int64)
            kernels.link_segments(parent, pot, size, conflicts, pa, pb, pdelta, order, ok, believable, False)
    return parent, pot, size, conflicts


def split_doubtful(labels: np.ndarray, segs: Segments, believable: np.ndarray, p: UnwrapParams) -> Segments:
    """Step 5, *unroll each row by transitions again*.

    A doubtful (non-believable) segment is walked again run by run; each run's majority
    relation (segment, offset) to the row above and to the row below is compared with the
    previous run's: where it changes, the transition between the two runs is not trusted and the
    segment is cut there (an inserted or lost stripe shifts the rest of the row by two; a
    segment may also bridge two surfaces).  The pieces keep their relative indices and become
    segments of their own.  Believable segments are unchanged.
    """
    from . import kernels

    doubtful = ~believable
    if segs.n == 0 or not doubtful.any():
        return segs
    lab = np.ascontiguousarray(labels, dtype=np.uint8)
    cut = kernels.cut_junctions(lab, segs.seg, segs.rel, segs.row, segs.u0, segs.u1, segs.j0, segs.j1, segs.j_ua,
                                segs.j_ub, doubtful)
    if not cut.any():
        return segs
    return _apply_cuts(segs, cut)



def _apply_cuts(segs: Segments, cut: np.ndarray) -> Segments:
    """Split segments at the transitions flagged in ``cut`` (one kernel, shared by the cutters)."""
    from . import kernels

    (seg, row, u0, u1, j0, j1, par, j_seg, j_ua, j_ub, j_la, j_lb, j_idx) = kernels.apply_cuts(
        segs.seg, segs.row, segs.u0, segs.u1, segs.j0, segs.j1, segs.parity, segs.j_seg, segs.j_ua, segs.j_ub,
        segs.j_la, segs.j_lb, cut)
    return Segments(seg, segs.rel, row, u0, u1, j0, j1, par, j_seg, j_ua, j_ub, j_la, j_lb, segs.j_rel[j_idx],
                    None if segs.j_x is None else segs.j_x[j_idx])

def cut_depth_edges(segs: Segments, ratio: float) -> Segments:
    """Step 1 (geometry check of the transitions): cut segments where the boundary spacing jumps.

    A row crossing a depth edge may show a perfectly valid colour sequence while the stripe index
    jumps by many stripes; the spacing of the located boundaries (``segs.j_x``) changes abruptly
    there (another surface, another distance and slant).  Cutting there keeps each segment on one
    surface; the pieces are related to their neighbour rows like any segment.
    """
    from . import kernels

    if segs.j_x is None or ratio <= 0 or segs.j_seg.size == 0:
        return segs
    cut = kernels.spacing_cuts(segs.j_x.astype(np.float64), segs.j0, segs.j1, float(ratio))
    if not cut.any():
        return segs
    return _apply_cuts(segs, cut)


def attach_doubtful(segs: Segments, edges: Edges, believable: np.ndarray, state, p: UnwrapParams):
    """Step 6, *unroll every row by relation with the upper neighbour* (and the lower one).

    Each doubtful segment (piece) joins at most one region, through its strongest strong edge
    to a believable segment; further edges only check it (a disagreement is a conflict).  Two
    regions are never merged through a doubtful segment.  Updates ``state`` in place.
    """
    from . import kernels

    parent, pot, size, conflicts = state
    use = edges.strong(p) & (believable[edges.s] != believable[edges.t])
    kernels.link_segments(parent, pot, size, conflicts, edges.s, edges.t, edges.offset, _edge_order(edges), use,
                          believable, True)
    return state


# -- step 7 -------------------------------------------------------------------------------------
def check_pixels(labels: np.ndarray, relative: np.ndarray, region: np.ndarray) -> np.ndarray:
    """Step 7, *unroll each pixel by relation with its upper neighbour*: (H, W) bool flags.

    A pixel is flagged when its upper or lower neighbour has the same colour and the same
    region but a different index (stripes are continuous across rows).
    """
    H, W = labels.shape
    bad = np.zeros((H, W), bool)
    if H < 2:
        return bad
    lab_ok = (labels[1:] == labels[:-1]) & (labels[1:] != NONE)
    same = lab_ok & (region[1:] == region[:-1]) & (region[1:] >= 0)
    diff = same & (relative[1:] != relative[:-1])
    bad[1:] |= diff
    bad[:-1] |= diff
    return bad


# -- the seven steps together -------------------------------------------------------------------
def unwrap(labels: np.ndarray, params: UnwrapParams = UnwrapParams(), locate=None) -> Unwrapped:
    """The paper's seven steps on a colour-class image ``labels`` (H, W) uint8 -> :class:`Unwrapped`.

    ``locate`` (optional): a function ``Segments -> (n_junctions,) float32`` sub-pixel boundary
    positions (the decoder passes its own); with it, step 1 also cuts rows at depth edges
    (:func:`cut_depth_edges`) and the positions travel with the segments (``segments.j_x``).
    """
    labels = np.asarray(labels)
    if labels.ndim != 2 or labels.dtype != np.uint8:
        raise GBError(f"unwrap: labels must be a 2-D uint8 array, got {labels.dtype} {labels.shape}")
    p = params
    segs1 = unroll_rows(labels, p.max_gap_px, p.spike_px)                 # 1
    if locate is not None:
        segs1.j_x = np.asarray(locate(segs1), dtype=np.float32)
        n_before = segs1.n
        segs1 = cut_depth_edges(segs1, p.spacing_ratio)
        n_depth_cuts = segs1.n - n_before
    else:
        n_depth_cuts = 0
    edges1 = relate_rows(labels, segs1)                                   # 2
    bel1 = believable_segments(segs1, edges1, p)                          # 3
    segs = split_doubtful(labels, segs1, bel1, p)                         # 5 (pieces)
    edges = relate_rows(labels, segs) if segs is not segs1 else edges1
    bel = believable_segments(segs, edges, p) if segs is not segs1 else bel1
    state = link_believable(segs, edges, bel, p)                          # 4
    attach_doubtful(segs, edges, bel, state, p)                           # 6
    from . import kernels

    parent, pot, size, conflicts = state
    root, P = kernels.resolve_roots(parent, pot)
    H, W = labels.shape
    # region pixel counts: a region is a union-find root with at least one believable segment
    seg_px = (segs.u1 - segs.u0 + 1).astype(np.int64)
    root_px = np.bincount(root, weights=seg_px, minlength=segs.n) if segs.n else np.zeros(0)
    root_bel = np.bincount(root, weights=bel.astype(np.int64), minlength=segs.n) if segs.n else np.zeros(0)
    root_conf = np.bincount(root, weights=conflicts, minlength=segs.n) if segs.n else np.zeros(0)
    is_root = (np.arange(segs.n) == root)
    found = is_root & (root_bel > 0)
    kept = found & (root_px >= p.min_region_px)
    region_of_root = np.full(segs.n, -1, np.int32)
    region_of_root[kept] = np.arange(int(kept.sum()), dtype=np.int32)
    seg_region = region_of_root[root] if segs.n else np.zeros(0, np.int32)
    region, relative = kernels.paint_regions(segs.seg, segs.rel, seg_region.astype(np.int32), P.astype(np.int32))
    incons = check_pixels(labels, relative, region)                      # 7
    isolated = (segs.seg >= 0) & (region < 0)
    n_reg = int(kept.sum())
    region_px = np.bincount(seg_region[seg_region >= 0], weights=seg_px[seg_region >= 0],
                            minlength=n_reg).astype(np.int64)
    stats = {
        "segments": segs1.n,
        "depth_edge_cuts": int(n_depth_cuts),
        "segments_believable": int(bel1.sum()),
        "pieces_after_split": segs.n,
        "regions_found": int(found.sum()),
        "regions_kept": n_reg,
        "regions_too_small": int((found & ~kept).sum()),
        "conflicts": int(conflicts.sum() // 2),
        "pixels_inconsistent": int(incons.sum()),
    }
    return Unwrapped(relative, region, incons, segs, edges, seg_region, P, region_px,
                     root_conf[kept].astype(np.int64) // 2 if segs.n else np.zeros(0, np.int64), bel, isolated, stats)


# -- absolute indexing (beyond the paper) -------------------------------------------------------
@dataclass
class RegionIndex:
    """Result of :func:`index_regions` per region (arrays of length n_regions).

    offset : int absolute = relative + offset (valid where ``indexed``).
    indexed : bool, the offset is certain.
    markers_seen : distinct marker stripes observed.
    evidence : marker-related pixel votes (cyan seen + cyan expected) of the best offset.
    mismatch, runner_up : mismatching votes of the best and the second-best offset.
    why : str per region ("ok", "no markers in pattern", "too few markers", "ambiguous", ...).
    """

    offset: np.ndarray
    indexed: np.ndarray
    markers_seen: np.ndarray
    evidence: np.ndarray
    mismatch: np.ndarray
    runner_up: np.ndarray
    why: list


def index_regions(labels: np.ndarray, relative: np.ndarray, region: np.ndarray, n_regions: int,
                  pattern: PatternSpec, params: UnwrapParams = UnwrapParams()) -> RegionIndex:
    """Absolute stripe offset of every region by the cyan markers (a matched filter).

    For each region, every candidate offset ``o`` (same parity as the colours: even) is scored
    with ALL of the region's pixels: a cyan pixel at relative index ``r`` agrees if stripe
    ``r + o`` is a marker, a green/blue pixel agrees if it is not; pixels that would fall outside
    the pattern disagree.  Offsets whose placement leaves the region's stripes inside the
    pattern are candidates.  The best offset is accepted only if (a) the region saw at least
    ``min_markers`` distinct marker stripes with ``min_marker_px`` pixels each, (b) its mismatch is
    at most ``max_mismatch`` of the marker evidence and (c) the runner-up mismatches by at least
    ``index_margin`` of the evidence more.  Otherwise the region is *unindexed* -- never a guess.
    """
    n_st = pattern.n_stripes
    is_marker = np.zeros(n_st, bool)
    is_marker[pattern.marker_indices()] = True
    out = RegionIndex(np.zeros(n_regions, np.int64), np.zeros(n_regions, bool), np.zeros(n_regions, np.int64),
                      np.zeros(n_regions, np.int64), np.zeros(n_regions, np.int64), np.zeros(n_regions, np.int64),
                      ["unindexed"] * n_regions)
    if n_regions == 0:
        return out
    if not pattern.markers or not is_marker.any():
        out.why = ["no markers in the pattern (relative index only)"] * n_regions
        return out
    from . import kernels

    rmin, rmax, start, hc, hg = kernels.region_histograms(np.ascontiguousarray(labels, dtype=np.uint8),
                                                          np.ascontiguousarray(relative, dtype=np.int32),
                                                          np.ascontiguousarray(region, dtype=np.int32), n_regions)
    for k in range(n_regions):
        r0, r1 = int(rmin[k]), int(rmax[k])
        if r1 < r0:
            out.why[k] = "empty region"
            continue
        span = r1 - r0 + 1
        n_c = hc[start[k]:start[k + 1]]
        n_g = hg[start[k]:start[k + 1]]
        seen = int((n_c >= params.min_marker_px).sum())
        out.markers_seen[k] = seen
        # core: relative indices with enough pixels (stray pixels beyond it only add mismatch)
        tot = n_c + n_g
        core = np.flatnonzero(tot >= params.min_marker_px)
        if core.size == 0:
            out.why[k] = "region too thin"
            continue
        c0, c1 = int(core[0]), int(core[-1])
        # extended pattern: pad by the region's span on both sides; outside the pattern every
        # observation mismatches.  Candidate: absolute index A of relative r0 + c0 in
        # [-2, n_st - core width + 2] (stray light may extend a region past the pattern's edge
        # stripes: those pixels are mismatches), same parity as r0 (colour fixes parity).
        pad = span
        M = np.zeros(n_st + 2 * pad, np.int64)
        M[pad:pad + n_st] = is_marker
        O = np.ones(n_st + 2 * pad, np.int64)
        O[pad:pad + n_st] = 0
        notM = 1 - M  # includes outside
        mis_all = (np.correlate(notM, n_c, mode="valid") + np.correlate(M, n_g, mode="valid")
                   + np.correlate(O, n_g, mode="valid"))
        exp_all = np.correlate(M, n_c + n_g, mode="valid")
        # mis_all[i]: relative r0 sits at extended position i -> absolute A0 = i - pad
        A0 = np.arange(mis_all.size) - pad
        okA = (A0 + c0 >= -2) & (A0 + c1 <= n_st + 1) & ((A0 - r0) % 2 == 0)
        if not okA.any():
            out.why[k] = "region wider than the pattern"
            continue
        mis = mis_all[okA]
        cand = A0[okA]
        best = int(np.argmin(mis))
        b_mis = int(mis[best])
        ev = int(n_c.sum() + exp_all[okA][best])
        second = int(np.partition(mis, 1)[1]) if mis.size > 1 else np.iinfo(np.int64).max // 4
        out.offset[k] = int(cand[best]) - r0
        out.evidence[k] = ev
        out.mismatch[k] = b_mis
        out.runner_up[k] = second
        if seen < params.min_markers:
            out.why[k] = f"too few markers ({seen} < {params.min_markers})"
        elif b_mis > params.max_mismatch * ev:
            out.why[k] = "markers do not fit the pattern"
        elif second - b_mis < params.index_margin * ev:
            out.why[k] = "ambiguous offset"
        else:
            out.indexed[k] = True
            out.why[k] = "ok"
    return out
