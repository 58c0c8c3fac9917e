"""The seven unwrapping steps and the marker indexing on small synthetic label images."""
import dataclasses
import re

import numpy as np
import pytest

from gbscan import unwrap as uw
from gbscan.errors import GBError
from gbscan.pattern import BLUE, CYAN, GREEN, NONE, PatternSpec

G, B, C, N = GREEN, BLUE, CYAN, NONE


def row_from_stripes(stripes, widths):
    return np.concatenate([np.full(w, s, np.uint8) for s, w in zip(stripes, widths)])


def stripe_image(spec: PatternSpec, first: int, n: int, px: int = 3, rows: int = 12) -> np.ndarray:
    """Labels of stripes first .. first+n-1, ``px`` camera px each, vertical."""
    lab = spec.stripe_labels()[first:first + n]
    row = np.repeat(lab, px).astype(np.uint8)
    return np.ascontiguousarray(np.broadcast_to(row, (rows, row.size)))


def test_unroll_rows_counts_transitions_with_colour_parity():
    lab = row_from_stripes([B, G, B, G, C, G, B], [3, 3, 3, 3, 3, 3, 3])[None]
    s = uw.unroll_rows(lab)
    assert s.n == 1 and s.parity[0] == 1
    np.testing.assert_array_equal(s.rel[0, ::3], [1, 2, 3, 4, 5, 6, 7])  # blue odd, green even
    assert s.j_rel.tolist() == [2, 3, 4, 5, 6, 7]
    assert (s.u0[0], s.u1[0]) == (0, 20)


def test_unroll_rows_spikes_gaps_and_parity_breaks():
    # a 1-px blue spike inside green is absorbed; a 1-px gap between G and B is a transition
    lab = row_from_stripes([G, B, G, N, B, G], [3, 1, 3, 1, 3, 3])[None]
    s = uw.unroll_rows(lab, max_gap_px=1, spike_px=1)
    assert s.n == 1
    assert s.rel[0, 0] == s.rel[0, 6] == 0 and s.rel[0, 8] == 1 and s.rel[0, 11] == 2
    assert s.seg[0, 7] == -1  # the gap pixel itself belongs to no run
    # G C B is impossible in the pattern (a marker is flanked by equal colours): the segment ends
    lab = row_from_stripes([G, C, B, G], [3, 3, 3, 3])[None]
    s = uw.unroll_rows(lab)
    assert s.n == 2
    # a 2-px gap ends the segment
    s = uw.unroll_rows(row_from_stripes([G, N, B], [3, 2, 3])[None], max_gap_px=1)
    assert s.n == 2



def test_unroll_rows_absorbs_mixed_pixels_beside_a_wide_marker():
    """A marker replaces one stripe, so its flanks share one colour (``B C B``).  Where stripes are
    wide, the pixels mixing a flank and the marker can come out as the other colour: ``B G C B``
    reads as a parity contradiction.  The short run is absorbed into its flank (one segment, the
    indices of the stripes after the marker unchanged); ``marker_flank_px=0`` cuts the row there."""
    lab = row_from_stripes([B, G, C, B, G], [7, 2, 7, 7, 7])[None]
    s = uw.unroll_rows(lab, marker_flank_px=2)
    assert s.n == 1
    assert s.rel[0, 0] == s.rel[0, 8] == 1 and s.rel[0, 9] == 2 and s.rel[0, 16] == 3 and s.rel[0, 23] == 4
    # the flank|marker junction spans the absorbed pixels, so its sub-pixel search covers them
    assert s.j_ua[0] == 8 and s.j_ub[0] == 9 and s.j_la[0] == B and s.j_lb[0] == C
    assert uw.unroll_rows(lab, marker_flank_px=0).n == 2
    # mirrored (a short run after the marker), and across a 1-px gap on each side
    lab = row_from_stripes([G, C, B, G], [7, 7, 1, 7])[None]
    s = uw.unroll_rows(lab, marker_flank_px=2)
    assert s.n == 1 and s.rel[0, 0] == 0 and s.rel[0, 7] == 1 and s.rel[0, 14] == s.rel[0, 21] == 2
    lab = row_from_stripes([B, G, N, C, N, B], [7, 2, 1, 7, 1, 7])[None]
    s = uw.unroll_rows(lab, max_gap_px=1, marker_flank_px=2)
    assert s.n == 1 and s.rel[0, 0] == 1 and s.rel[0, 10] == 2 and s.rel[0, 20] == 3
    # narrow stripes: the short run may be a real stripe whose twin across the marker was lost;
    # a marker of 4 px (<= 2 * marker_flank_px) is not treated as seen wide: the row is cut
    assert uw.unroll_rows(row_from_stripes([B, G, C, B], [7, 2, 4, 7])[None], marker_flank_px=2).n == 2
    # the legitimate B G C G B (narrow real stripes beside the marker) keeps its five stripes
    s = uw.unroll_rows(row_from_stripes([B, G, C, G, B], [6, 2, 7, 2, 6])[None], marker_flank_px=2)
    assert s.n == 1 and [int(s.rel[0, u]) for u in (0, 6, 8, 15, 17)] == [1, 2, 3, 4, 5]
    with pytest.raises(GBError, match="marker_flank_px"):
        uw.UnwrapParams(marker_flank_px=-1)

def test_seven_steps_give_one_consistent_region():
    spec = PatternSpec()
    lab = stripe_image(spec, 10, 40, rows=20)
    # rows start at different stripes (a ragged left edge): relative indices must still agree
    lab[5, :7] = NONE
    lab[9, :13] = NONE
    u = uw.unwrap(lab, uw.UnwrapParams(min_region_px=10))
    assert u.stats["regions_kept"] == 1
    truth = np.repeat(np.arange(10, 50), 3)[None].repeat(20, 0)
    d = (truth - u.relative)[u.region == 0]
    assert np.unique(d).size == 1 and d[0] % 2 == 0
    assert not u.inconsistent.any()


def test_inserted_stripe_is_cut_not_propagated():
    spec = PatternSpec()
    lab = stripe_image(spec, 10, 40, rows=20)
    # misread row 10: a two-pixel wrong-colour island inserts two transitions mid-row
    lab[10, 60:62] = BLUE if lab[10, 60] == GREEN else GREEN
    u = uw.unwrap(lab, uw.UnwrapParams(min_region_px=10, spike_px=0))
    truth = np.repeat(np.arange(10, 50), 3)[None].repeat(20, 0)
    d = truth - u.relative
    keep = ~u.inconsistent
    keep[10, 59:63] = False  # the island itself is not a stripe of the pattern
    for r in range(u.stats["regions_kept"]):
        vals = np.unique(d[(u.region == r) & keep])
        assert vals.size == 1, f"region {r} mixes offsets {vals}"
    # the big region holds all other rows, unharmed
    assert (u.region[[9, 11]] == u.region[0, 0]).all()


def test_link_kernel_potentials_and_conflicts():
    from gbscan import kernels

    n = 4
    parent = np.arange(n, dtype=np.int32)
    pot = np.zeros(n, np.int32)
    size = np.ones(n, np.int32)
    conf = np.zeros(n, np.int32)
    e_s = np.array([1, 2, 3, 3], np.int32)
    e_t = np.array([0, 1, 2, 0], np.int32)
    off = np.array([2, -4, 6, 5], np.int32)  # the last contradicts 2 - 4 + 6 = 4
    order = np.arange(4, dtype=np.int64)
    kernels.link_segments(parent, pot, size, conf, e_s, e_t, off, order, np.ones(4, bool), np.ones(n, bool), False)
    root, P = kernels.resolve_roots(parent, pot)
    assert len(set(root.tolist())) == 1
    assert [P[1] - P[0], P[2] - P[1], P[3] - P[2]] == [2, -4, 6]
    assert conf[3] == 1 and conf[0] == 1


def test_index_regions_recovers_offset_and_refuses_to_guess():
    spec = PatternSpec()
    lab = stripe_image(spec, 20, 30, rows=10)
    rel = np.repeat(np.arange(30), 3)[None].repeat(10, 0).astype(np.int32)  # true index = rel + 20
    reg = np.zeros(lab.shape, np.int32)
    p = uw.UnwrapParams(min_marker_px=5)
    idx = uw.index_regions(lab, rel, reg, 1, spec, p)
    assert idx.indexed[0] and idx.offset[0] == 20 and idx.mismatch[0] == 0
    # too few markers: a narrow region sees at most two
    narrow = reg.copy()
    narrow[:, 24:] = -1
    idx = uw.index_regions(lab, rel, narrow, 1, spec, p)
    assert not idx.indexed[0]
    # the pure pattern: never indexed
    idx = uw.index_regions(lab, rel, reg, 1, PatternSpec(markers=False), p)
    assert not idx.indexed[0] and "no markers" in idx.why[0]


@pytest.mark.parametrize("compiled", [True, False])
def test_index_regions_working_volume_rules_out_far_runner_ups(compiled, monkeypatch):
    """``stripe_range`` (the scanner's working volume): stripes 30-38 show two markers 7 stripes
    apart, a gap the marker code repeats (stripes 70 and 77): two offsets fit exactly, so the region
    is ambiguous.  A volume holding stripes 25-45 only rules the far one out: indexed, at the
    offset the markers chose; a volume that excludes the best one leaves the region unindexed
    ("outside the working volume") -- the prior never picks an offset.  Compiled and reference
    scoring agree."""
    monkeypatch.setattr(uw, "_SCORE_COMPILED", compiled)
    spec = PatternSpec()
    lab = stripe_image(spec, 30, 9, rows=10)
    rel = np.repeat(np.arange(9), 3)[None].repeat(10, 0).astype(np.int32)
    reg = np.zeros(lab.shape, np.int32)
    p = uw.UnwrapParams(min_marker_px=5)
    idx = uw.index_regions(lab, rel, reg, 1, spec, p)
    assert idx.why[0] == "ambiguous offset" and idx.offset[0] == 30 and idx.runner_up[0] == idx.mismatch[0] == 0
    assert idx.stripe_margin[0] == 0  # the far offset contradicts no stripe either: no stripe margin

    def volume(lo, hi):
        r = np.empty((2, *lab.shape), np.float32)
        r[0], r[1] = lo, hi
        return r

    idx = uw.index_regions(lab, rel, reg, 1, spec, p, volume(25, 45))
    assert idx.indexed[0] and idx.why[0] == "ok" and idx.offset[0] == 30
    assert idx.runner_up[0] > idx.mismatch[0]
    idx = uw.index_regions(lab, rel, reg, 1, spec, p, volume(60, 90))
    assert not idx.indexed[0] and idx.why[0] == uw.OUTSIDE and idx.offset[0] == 30
    # unbounded pixels (NaN) carry no prior
    assert uw.index_regions(lab, rel, reg, 1, spec, p, volume(np.nan, np.nan)).why[0] == "ambiguous offset"
    # an offset is inside when it keeps volume_frac of the pixels inside: 6 rows of 10 see 25-45,
    # 4 see 60-90 (stripes 30-38 inside for 60 %, 70-78 for 40 %)
    mixed = volume(25, 45)
    mixed[0, 6:], mixed[1, 6:] = 60, 90
    assert uw.index_regions(lab, rel, reg, 1, spec, p, mixed).why[0] == "ok"
    strict = uw.UnwrapParams(min_marker_px=5, volume_frac=0.7)
    assert uw.index_regions(lab, rel, reg, 1, spec, strict, mixed).why[0] == uw.OUTSIDE
    loose = uw.UnwrapParams(min_marker_px=5, volume_frac=0.4)
    assert uw.index_regions(lab, rel, reg, 1, spec, loose, mixed).why[0] == "ambiguous offset"
    with pytest.raises(GBError, match="stripe_range"):
        uw.index_regions(lab, rel, reg, 1, spec, p, volume(25, 45)[:, :5])
    with pytest.raises(GBError, match="volume_frac"):
        uw.UnwrapParams(volume_frac=0.0)


def test_unwrap_rejects_bad_labels():
    with pytest.raises(GBError, match="2-D uint8"):
        uw.unwrap(np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(GBError, match="agree_frac"):
        uw.UnwrapParams(agree_frac=0.2)


def welded_image(spec: PatternSpec, rows_clean: int = 60, rows_welded: int = 3, jump: int = 20, shift: int = 12,
                 n: int = 45, px: int = 3) -> np.ndarray:
    """Stripes 0..n-1 (``px`` camera px each); in the last ``rows_welded`` rows the stripes from
    ``jump`` on are those of another surface ``shift`` (even) stripes further: the colour sequence
    stays valid and green/blue line up vertically -- only the markers tell."""
    lab = spec.stripe_labels()
    clean = np.repeat(lab[:n], px)
    welded = np.repeat(np.concatenate([lab[:jump], lab[jump + shift:n + shift]]), px)
    return np.ascontiguousarray(np.vstack([np.broadcast_to(clean, (rows_clean, clean.size)),
                                           np.broadcast_to(welded, (rows_welded, welded.size))]).astype(np.uint8))


def test_marker_conflicts_reject_a_welded_stretch_and_nothing_else():
    spec = PatternSpec()
    lab = welded_image(spec)
    un = uw.unwrap(lab)
    n_reg = un.region_px.size
    idx = uw.index_regions(lab, un.relative, un.region, n_reg, spec)
    # the weld is invisible to the unwrapping (one region) and to the region's marker fit
    assert n_reg == 1 and idx.indexed[0] and idx.offset[0] == -un.relative[0, 0]
    bad = uw.spans_mask(uw.marker_conflicts(lab, un, idx, spec), lab.shape)
    absolute = un.relative + idx.offset[0]
    truth = np.concatenate([np.arange(20), np.arange(32, 57)]).repeat(3)
    wrong = absolute[60:] != truth[None]
    assert wrong.any() and not bad[:60].any()            # clean rows untouched
    assert bad[60:][wrong].all()                           # every wrongly indexed pixel is rejected
    # the rejected stretch starts at the last marker that agrees (stripe 16), not earlier
    assert not bad[60:, :16 * 3].any() and bad[60:, 16 * 3:20 * 3].all()
    # the pure pattern has no evidence: nothing is rejected (the decoder reports relative only)
    assert uw.marker_conflicts(lab, un, idx, PatternSpec(markers=False)).shape == (0, 3)


def test_marker_conflicts_do_not_stop_at_a_coincidental_agreement():
    """A strip 12 stripes off from stripe 30 on: its first marker (true stripe 49) lands on the
    region's marker stripe 37 and agrees; around it the strip disagrees (the region's marker 30
    shows green/blue, the strip's marker 54 sits on the region's 42).  An agreeing marker bounds
    the rejected stretch only when the next event beyond it agrees too
    (``UnwrapParams.conflict_confirm``): every wrong pixel goes, from the last marker whose
    predecessor agrees as well (stripe 26); without the rule the stretch began at the coincidence
    and 63 wrong pixels stayed.  A coincidence right after a real agreement (10 stripes off from
    stripe 17: the strip's marker 30 on the region's 20, the region's 16 confirming it) fits the
    strip's shift as well (16 + 10 = 26, a marker): ``conflict_extend`` runs the stretch on to the
    first run that fits the region and not the shift (the marker 11: 21 is none), and the
    strip's 9 px a row before the coincidence go too (27 stayed without it).  The first strip's
    stretch keeps its bound 26: its runs fit shifts 12, 28 and 40 by one agreement each, short
    of the two a shift needs (``conflict_events``; 26 + 28 = 54 is a marker)."""
    spec = PatternSpec()
    for shift, jump, kept in ((12, 30, {(True, True): 0, (True, False): 0, (False, False): 63}),
                              (10, 17, {(True, True): 0, (True, False): 27, (False, False): 27})):
        lab = welded_image(spec, jump=jump, shift=shift)
        un = uw.unwrap(lab)
        idx = uw.index_regions(lab, un.relative, un.region, un.region_px.size, spec)
        assert un.region_px.size == 1 and idx.indexed[0]
        truth = np.concatenate([np.arange(jump), np.arange(jump + shift, 45 + shift)]).repeat(3)
        wrong = (un.relative + idx.offset[0])[60:] != truth[None]
        for (confirm, extend), n_kept in kept.items():
            p = uw.UnwrapParams(conflict_confirm=confirm, conflict_extend=extend)
            bad = uw.spans_mask(uw.marker_conflicts(lab, un, idx, spec, p), lab.shape)
            assert not bad[:60].any() and int((wrong & ~bad[60:]).sum()) == n_kept, (shift, jump, confirm, extend)
    for jump, shift, first in ((30, 12, 26), (17, 10, 11)):
        lab = welded_image(spec, jump=jump, shift=shift)
        un = uw.unwrap(lab)
        idx = uw.index_regions(lab, un.relative, un.region, un.region_px.size, spec)
        bad = uw.spans_mask(uw.marker_conflicts(lab, un, idx, spec), lab.shape)
        assert not bad[60:, :first * 3].any() and bad[60:, first * 3:].all(), (jump, shift)


def test_grow_conflicts_follows_a_strip_through_rows_without_evidence():
    """kernels.grow_conflicts: a rejected row's segment passes the rejection to the segments of
    the same region above and below that hold no agreeing run, row after row; a segment with an
    agreeing run, one of another region or of an unindexed one, or one not touching a rejected
    pixel keeps its pixels."""
    from gbscan import kernels

    H, W = 7, 10
    seg_map = np.full((H, W), -1, np.int32)
    region = np.full((H, W), -1, np.int32)
    #        row  u0 u1 region agree
    table = [(0, 2, 7, 0, 0),    # 0: two rows above the rejected one, no evidence: grown (second pass)
             (1, 2, 7, 0, 0),    # 1: right above it: grown
             (2, 2, 7, 0, 0),    # 2: the rejected row
             (3, 0, 9, 0, 1),    # 3: below it, an agreeing run of its own: kept
             (4, 2, 7, 0, 0),    # 4: below that one (not touching a rejected pixel): kept
             (5, 0, 4, 1, 0),    # 5: another region's, under row 4
             (6, 0, 9, 2, 0)]    # 6: an unindexed region's
    row, u0, u1, sreg, agree = (np.array(c) for c in zip(*table))
    for k, (v, a, b, r, _) in enumerate(table):
        seg_map[v, a:b + 1] = k
        region[v, a:b + 1] = r
    indexed = np.array([True, True, False])
    rejected = np.zeros((H, W), bool)
    rejected[2, 2:8] = True
    rejected[5, 0:5] = True             # region 1's row: rejected, but row 6 is region 2's (unindexed)
    grown = kernels.grow_conflicts(rejected, seg_map, region, row.astype(np.int32), u0.astype(np.int32),
                                   u1.astype(np.int32), sreg.astype(np.int32), indexed, agree.astype(np.uint8))
    assert grown.tolist() == [1, 0]
    want = np.zeros((H, W), bool)
    want[0:3, 2:8] = True
    want[5, 0:5] = True
    np.testing.assert_array_equal(rejected, want)
    # nothing to grow from: nothing grown
    none = np.zeros((H, W), bool)
    assert kernels.grow_conflicts(none, seg_map, region, row.astype(np.int32), u0.astype(np.int32), u1.astype(np.int32),
                                  sreg.astype(np.int32), indexed, agree.astype(np.uint8)).size == 0 and not none.any()


def test_marker_conflicts_ignore_a_single_missed_marker():
    """A marker that a row fails to show (e.g. at a rim) is one disagreement, not a shifted stretch."""
    spec = PatternSpec()
    lab = stripe_image(spec, 0, 45, rows=40)
    lab[20, 16 * 3:17 * 3] = G if spec.stripe_labels()[15] == B else B  # marker 16 shown as its neighbours' colour
    un = uw.unwrap(lab)
    idx = uw.index_regions(lab, un.relative, un.region, un.region_px.size, spec)
    assert idx.indexed.all()
    assert uw.marker_conflicts(lab, un, idx, spec).shape == (0, 3)
    # with one disagreement enough, that row's stretch around it goes
    p1 = uw.UnwrapParams(conflict_events=1)
    bad = uw.spans_mask(uw.marker_conflicts(lab, un, idx, spec, p1), lab.shape)
    assert bad.any() and not np.delete(bad, 20, axis=0).any()
    with pytest.raises(GBError, match="conflict_events"):
        uw.UnwrapParams(conflict_events=0)


def test_marker_conflicts_reject_a_short_strip_by_its_persistent_marker():
    """At a horizontal contact a strip of 3 stripes of the surface above (its marker 49 between
    48 and 50) lines up with stripes 38-40 of the surface below, 10 stripes off, and ends there
    (a silhouette): one disagreement a row, too few alone (``conflict_events``).  Its marker stays
    cyan on one stripe for 6 rows, which no glint does: decisive
    (``UnwrapParams.conflict_persist_rows``), and the rows go from the last agreeing marker (37)
    to the strip's end.  Not decisive: the same strip over 2 rows, or cut after its marker (a cyan
    run without its second flank: a mixed pixel at a silhouette looks the same)."""
    spec = PatternSpec()
    lab_all = spec.stripe_labels()

    def short_weld(rows_welded: int, end: int) -> np.ndarray:
        clean = np.repeat(lab_all[:45], 3)
        welded = np.repeat(np.concatenate([lab_all[:38], lab_all[48:51]]), 3)
        img = np.zeros((60 + rows_welded, clean.size), np.uint8)
        img[:60] = clean
        img[60:, :welded.size] = welded
        img[60:, end * 3:] = NONE
        return img

    for rows_welded, end, rejected in ((6, 41, True), (2, 41, False), (6, 40, False)):
        lab = short_weld(rows_welded, end)
        un = uw.unwrap(lab)
        idx = uw.index_regions(lab, un.relative, un.region, un.region_px.size, spec)
        assert un.region_px.size == 1 and idx.indexed[0] and idx.offset[0] == 0   # the weld fools the index
        truth = np.concatenate([np.arange(38), np.arange(48, 51)]).repeat(3)[:end * 3]
        wrong = un.relative[60:, :end * 3] != truth[None]
        assert wrong.sum() == rows_welded * (end - 38) * 3
        off = uw.spans_mask(uw.marker_conflicts(lab, un, idx, spec, uw.UnwrapParams(conflict_persist_rows=0)),
                            lab.shape)
        assert not off.any()                      # one disagreement a row: kept without the rule
        bad = uw.spans_mask(uw.marker_conflicts(lab, un, idx, spec), lab.shape)
        if rejected:
            assert not bad[:60].any() and bad[60:, :end * 3][wrong].all()
            assert not bad[60:, :37 * 3].any() and bad[60:, 37 * 3:end * 3].all()
        else:
            assert not bad.any()
    with pytest.raises(GBError, match="conflict_persist_rows"):
        uw.UnwrapParams(conflict_persist_rows=1)


def patch_scene(spec: PatternSpec, shift: int = 0, first: int = 10, n: int = 40, px: int = 3):
    """Stripes ``first..first+n-1`` (``px`` camera px each, 40 rows) and their true columns; a patch
    (rows 24-28, columns 0-26) is cut off by two dark rows above and a dark gap of 3 px to its right,
    so it is a component too small to be kept (135 px).  With ``shift`` != 0 the patch shows the stripes of
    another surface, ``shift`` stripes further (a depth edge)."""
    lab = stripe_image(spec, first, n, px=px, rows=40)
    lab[24:29, :27] = stripe_image(spec, first + shift, n, px=px, rows=5)[:, :27]
    lab[22:24, :30] = NONE
    lab[24:29, 27:30] = NONE
    u = np.arange(lab.shape[1])
    col = ((first + u // px) * spec.stripe_px + ((u % px) + 0.5) * spec.stripe_px / px - 0.5).astype(np.float32)
    return np.ascontiguousarray(lab), np.broadcast_to(col, lab.shape)


def linked(spec, lab, col_true, p):
    u = uw.unwrap(lab, p)
    idx = uw.index_regions(lab, u.relative, u.region, u.region_px.size, spec, p)
    assert idx.indexed.all() and u.isolated[25, 5]
    px = lab.shape[1] // 40
    uu = np.arange(lab.shape[1])
    # columns from the relative index (exact, as the decoder's interpolation gives on clean data)
    frac = (((uu % px) + 0.5) * spec.stripe_px / px - 0.5).astype(np.float32)
    col_rel = (u.relative * spec.stripe_px + frac).astype(np.float32)
    off = np.r_[idx.offset, 0][np.where(u.region >= 0, u.region, idx.offset.size)]
    col_abs = np.where(u.region >= 0, col_rel + off * spec.stripe_px, np.nan).astype(np.float32)
    return u, idx, uw.link_components(lab, u, idx, np.where(lab > 0, col_rel, np.nan), col_abs, spec, p)


def test_link_components_indexes_a_small_patch_through_its_neighbours():
    spec = PatternSpec()
    lab, col_true = patch_scene(spec)
    p = uw.UnwrapParams(min_region_px=150, min_marker_px=5)
    u, idx, lk = linked(spec, lab, col_true, p)
    assert lk.stats["components_linked"] == 1 and lk.linked.sum() == 1
    r = lk.seg_region[u.segments.seg[25, 5]]
    assert r == idx.offset.size and lk.indexed[r]
    # the linked offset is the true one: absolute index = relative + offset everywhere in the patch
    patch = u.segments.seg >= 0
    patch &= lk.seg_region[np.maximum(u.segments.seg, 0)] == r
    truth = np.floor((col_true + 0.5) / spec.stripe_px).astype(np.int64)
    np.testing.assert_array_equal((u.relative + lk.offset[r])[patch], truth[patch])
    assert lk.votes[r] >= p.link_votes and lk.dissent[r] == 0
    # disabled: nothing linked
    off = uw.link_components(lab, u, idx, np.full(lab.shape, np.nan, np.float32), np.full(lab.shape, np.nan, np.float32),
                             spec, uw.UnwrapParams(link_votes=0))
    assert off.stats["components_linked"] == 0 and not off.linked.any()


@pytest.mark.parametrize("shift", [5, 2, 4])
def test_link_components_refuses_another_surface(shift):
    """A patch showing another surface: an odd shift leaves the votes between offsets; an even one
    lines the stripes up, and then the markers at the linked offset contradict the patch's colours."""
    spec = PatternSpec()
    lab, col_true = patch_scene(spec, shift=shift)
    p = uw.UnwrapParams(min_region_px=150, min_marker_px=5)
    u, idx, lk = linked(spec, lab, col_true, p)
    assert lk.stats["components_linked"] == 0, lk.stats
    assert lk.stats["refused_votes" if shift % 2 else "refused_markers"] >= 1


def hanging_patch(spec: PatternSpec, width: int, first: int = 10, px: int = 3):
    """Stripes ``first..`` (``px`` camera px each, 60 rows) with a patch of 10 rows (24-33) and
    ``width`` px cut off above by two dark rows and on its right by a dark gap of 3 px: a
    component tied to the rows below it alone (its votes all come from its bottom row)."""
    lab = stripe_image(spec, first, 40, px=px, rows=60)
    lab[22:24, :width + 3] = NONE
    lab[24:34, width:width + 3] = NONE
    return np.ascontiguousarray(lab)


def link_hanging(spec, lab, p, grad: float = 0.0, width: int = 0, px: int = 3, bend_rows: int = 0,
                 noise_px: float = 0.0):
    """unwrap, index and link ``lab`` (columns exact from the relative index); the patch's
    columns (rows 24-33, ``width`` px) tilt by ``grad`` projector px per row along the stripes,
    continuing the rows below at the contact row 33 -- or, with ``bend_rows``, at row
    ``33 - bend_rows``, the rows below it keeping the columns of the surface below (as the
    along-stripe blur mixes the rows next to a contact) -- and carry Gaussian noise of
    ``noise_px`` projector px (seeded)."""
    u = uw.unwrap(lab, p)
    idx = uw.index_regions(lab, u.relative, u.region, u.region_px.size, spec, p)
    uu = np.arange(lab.shape[1])
    col_rel = (u.relative * spec.stripe_px + (((uu % px) + 0.5) * spec.stripe_px / px - 0.5)).astype(np.float32)
    col_rel[24:34, :width] += (grad * np.minimum(np.arange(24, 34) - 33.0 + bend_rows, 0.0)).astype(np.float32)[:, None]
    if noise_px:
        col_rel[24:34, :width] += np.random.default_rng(5).normal(0.0, noise_px, (10, width)).astype(np.float32)
    reg = np.where(u.region >= 0, u.region, idx.offset.size)
    ind, off = np.r_[idx.indexed, False][reg], np.r_[idx.offset, 0][reg]
    col_abs = np.where(ind, col_rel + off * spec.stripe_px, np.nan).astype(np.float32)
    return u, idx, uw.link_components(lab, u, idx, np.where(lab > 0, col_rel, np.nan), col_abs, spec, p)


@pytest.mark.parametrize("width, grad, linked_px", [(15, 0.0, 150), (15, 0.05, 150), (15, 0.3, 0), (15, -0.2, 0),
                                                    (27, 0.3, 270)])
def test_component_hanging_at_a_gradient_step_is_not_linked(width, grad, linked_px):
    """The gradient test of ``link_components``: a component of 10 rows tied to the reported rows
    below by its bottom row alone (no vote along a row), its columns continuing there, is not
    linked when its column's gradient along the stripes jumps at the contact by more than
    ``link_grad_tol`` (0.1 px per row): a surface of another tilt whose stripes line up with
    these (the multi-object scene's panel at 140-160 mm baselines, -0.17 px per row against the
    wall's 0).  15 px wide it shows one marker (11): 0 and 0.05 px per row are linked, 0.3 and
    -0.2 refused.  27 px wide it shows two (11, 16), which fix the offset themselves: linked."""
    spec = PatternSpec()
    lab = hanging_patch(spec, width)
    p = uw.UnwrapParams(min_region_px=150, min_marker_px=5)
    u, idx, lk = link_hanging(spec, lab, p, grad, width)
    assert not idx.indexed[u.region[28, 5]]            # the patch alone: too few markers
    assert lk.stats["components_linked"] == (linked_px > 0) and lk.stats["pixels_linked"] == linked_px
    assert lk.stats["refused_gradient"] == (linked_px == 0)
    if linked_px:
        r = lk.seg_region[u.segments.seg[28, 5]]
        assert u.relative[28, 5] + lk.offset[r] == 10 + 5 // 3   # the true stripe
    _, _, lk0 = link_hanging(spec, lab, dataclasses.replace(p, link_grad_tol=0.0), grad, width)   # the test off
    assert lk0.stats["components_linked"] == 1 and lk0.stats["refused_gradient"] == 0
    # a component of at most link_hang_rows rows is not asked (the 5-row patch of patch_scene)
    lab5, col5 = patch_scene(spec)
    assert linked(spec, lab5, col5, p)[2].stats["components_linked"] == 1


def test_gradient_test_skips_the_rows_the_blur_mixes_at_the_contact():
    """``link_grad_skip_rows``: the patch's stripes lean 0.15 px per row against the rows below
    (0), but its 3 rows next to the contact keep the columns of the surface below (the
    along-stripe blur mixes them, as on a dim glossy panel hanging 46 rows from the wall above it,
    8 stripes off).  Measured from the contact row the change is about half of it, under
    ``link_grad_tol``, and the patch is linked; from 3 rows in it is refused."""
    spec = PatternSpec()
    lab = hanging_patch(spec, 15)
    p = uw.UnwrapParams(min_region_px=150, min_marker_px=5)
    assert p.link_grad_skip_rows == 3
    _, _, lk = link_hanging(spec, lab, p, 0.15, 15, bend_rows=3)
    assert lk.stats["components_linked"] == 0 and lk.stats["refused_gradient"] == 1
    _, _, lk0 = link_hanging(spec, lab, dataclasses.replace(p, link_grad_skip_rows=0), 0.15, 15, bend_rows=3)
    assert lk0.stats["components_linked"] == 1 and lk0.stats["refused_gradient"] == 0
    # a patch leaning with the surface below is linked either way
    _, _, lk1 = link_hanging(spec, lab, p, 0.0, 15, bend_rows=3)
    assert lk1.stats["components_linked"] == 1


def test_component_tied_through_one_contact_needs_its_gradient_seen_continuing():
    """``link_grad_z_one`` (0): the hanging patch (tied to the rows below alone, one marker of its
    own) leans 0.2 px per row against them, its columns noisy (0.5 projector px): the change is
    over ``link_grad_tol`` but at a z-score under ``link_grad_z`` (10), as the layouts set's panel
    fragment hanging 12 stripes off from a strip of the wall (-0.21 px per row at z 6.3 / 8.2).
    Judged at ``link_grad_z`` it is linked; tied through one contact, it is refused.  Leaning with
    the rows below, the same noise, it is linked either way."""

    spec = PatternSpec()
    lab = hanging_patch(spec, 15)
    p = uw.UnwrapParams(min_region_px=150, min_marker_px=5)
    assert p.link_grad_z_one == 0.0 and p.link_grad_z == 10.0
    u, idx, lk = link_hanging(spec, lab, p, 0.2, 15, noise_px=0.5)
    assert lk.stats["components_linked"] == 0 and lk.stats["refused_gradient"] == 1
    _, _, lk10 = link_hanging(spec, lab, dataclasses.replace(p, link_grad_z_one=10.0), 0.2, 15, noise_px=0.5)
    assert lk10.stats["components_linked"] == 1 and lk10.stats["refused_gradient"] == 0
    for z_one in (0.0, 10.0):
        _, _, lk0 = link_hanging(spec, lab, dataclasses.replace(p, link_grad_z_one=z_one), 0.0, 15, noise_px=0.5)
        assert lk0.stats["components_linked"] == 1, z_one


@pytest.mark.parametrize("skip", [0, 3])
def test_stripe_gradient_jumps_kernel_equals_least_squares(skip):
    """kernels.stripe_gradient_jumps against np.polyfit: random columns with a gradient step at
    contacts above and below, components cut short (fewer than 3 rows: NaN) and unlisted ones;
    the component's rows from ``skip`` rows past the contact on."""
    from gbscan import kernels

    rng = np.random.default_rng(5)
    H, W, rows = 40, 30, 6
    comp = np.full((H, W), -1, np.int32)
    comp[10:20, :] = 0            # hangs from the rows below (20..)
    comp[25:40, 10:20] = 1        # hangs from the rows above (20-24)
    comp[2:4, :] = 2              # two rows only: not measurable
    col_rel = rng.normal(0, 0.05, (H, W)).astype(np.float32) + 0.3 * np.arange(H, dtype=np.float32)[:, None]
    col_abs = np.full((H, W), np.nan, np.float32)
    col_abs[20:, :] = (rng.normal(0, 0.05, (20, W)) - 0.1 * np.arange(20)[:, None]).astype(np.float32)
    col_abs[25:, 10:20] = np.nan
    col_abs[4:6, :] = 0.0
    col_abs[:2, :] = 1.0
    vc = np.array([0, 0, 1, 1, 2, 0], np.int64)
    vl = np.array([3, 7, 12, 15, 5, -1 - 19], np.int64)    # the last: a vote along a row (not measured)
    vv = np.array([19, 19, 25, 25, 3, 19], np.int64)
    slot = np.array([0, 1, 2], np.int64)
    got, where = kernels.stripe_gradient_jumps(vc, vl, vv, comp, col_rel, col_abs, slot, rows, skip)
    np.testing.assert_array_equal(where, [1, 1, 0, 0, -1, -1])   # below, below, above, above, not measured

    def ls(y, x):
        return np.polyfit(x.astype(float), y.astype(float), 1)[0]

    for i in range(vc.size):
        c, u, v = vc[i], vl[i], vv[i]
        if u < 0 or c == 2:
            assert np.isnan(got[i])
            continue
        d = -1 if c == 1 else 1
        rin = np.array([v - d * (j + skip) for j in range(rows + 1)])
        rin = rin[(rin >= 0) & (rin < H)]
        rin = rin[np.cumprod(comp[rin, u] == c).astype(bool)]
        rout = np.array([v + d * (j + 1) for j in range(rows + 1)])
        rout = rout[(rout >= 0) & (rout < H)]
        rout = rout[np.cumprod(np.isfinite(col_abs[rout, u])).astype(bool)]
        want = ls(col_rel[rin, u], rin) - ls(col_abs[rout, u], rout)
        assert got[i] == pytest.approx(want, abs=1e-6), (i, got[i], want)
    assert not np.isnan(got[:4]).any()
    # the components' gradient (0.3 px per row) against the reported rows' (-0.1), below and above
    assert got[0] == pytest.approx(0.4, abs=0.05) and got[2] == pytest.approx(0.4, abs=0.05)
    # a component not listed (slot -1) is not measured
    assert np.isnan(kernels.stripe_gradient_jumps(vc, vl, vv, comp, col_rel, col_abs, np.array([-1, 1, 2]), rows)[0][0])


def test_gradient_jump_verdicts_equal_the_median_test_over_the_measured_votes():
    """kernels.gradient_jump_verdicts (link_components' one pass) against the votes measured by
    kernels.stripe_gradient_jumps and the median / MAD test written in numpy: random components
    between reported bands of random gradients, voted from below and sometimes from above; votes
    at another offset, not agreeing or along a row left out; too few measured votes never
    flagged; a component whose two contacts, apart, differ with opposite signs (the gradient
    changing steadily through it: one curved surface) not flagged; one tied through one contact
    alone judged at ``z_one`` (``link_grad_z_one``; negative: at ``z``)."""
    from gbscan import kernels

    rng = np.random.default_rng(11)
    H, W, rows, tol, z = 100, 60, 6, 0.1, 10.0
    verdicts = []
    for trial in range(40):
        inc = np.repeat(rng.choice([-0.2, 0.0, 0.1, 0.25], 10), 10)          # a gradient per band of 10 rows
        col_abs = (np.concatenate([[0.0], np.cumsum(inc)[:-1]])[:, None] + rng.normal(0, 0.02, (H, W))).astype(np.float32)
        comp = np.full((H, W), -1, np.int32)
        col_rel = np.full((H, W), np.nan, np.float32)
        votes = []
        for c in range(4):            # component c: rows 25c+8 .. 25c+16 over random columns
            r0, r1 = 25 * c + 8, 25 * c + 17
            u0, u1 = sorted(rng.integers(0, W, 2))
            comp[r0:r1, u0:u1 + 1] = c
            col_abs[r0:r1, u0:u1 + 1] = np.nan
            g = rng.choice([0.0, 0.05, 0.2, -0.3])
            col_rel[r0:r1, u0:u1 + 1] = (rng.normal(0, rng.choice([0.005, 0.05, 0.5]), (r1 - r0, u1 - u0 + 1))
                                         + g * np.arange(r0, r1)[:, None]).astype(np.float32)
            above = rng.random() < 0.6
            for u in range(u0, u1 + 1):
                for v in ((r0, r1 - 1) if above else (r1 - 1,)):
                    votes.append((c, rng.choice([3, 3, 3, 4]), u if rng.random() > 0.1 else -1 - v, v,
                                  rng.random() > 0.1))
        vc, vk, vl, vv, good = (np.array(x) for x in zip(*votes))
        vc, vk, vl, vv = (a.astype(np.int64) for a in (vc, vk, vl, vv))
        good = good.astype(bool)
        comps = np.array([0, 1, 3], np.int64)
        slot = np.full(4, -1, np.int64)
        slot[comps] = np.arange(3)
        skip = trial % 4              # the rows skipped past the contact (link_grad_skip_rows)
        z_one = (-1.0, 0.0, 3.0)[trial % 3]     # link_grad_z_one (negative: z, the rule before it)
        got = kernels.gradient_jump_verdicts(vc, vk, vl, vv, good, comp, col_rel, col_abs, slot,
                                             np.array([3, 3, 3], np.int64), rows, tol, z, 5, 0.005, skip, z_one)
        diff, where = kernels.stripe_gradient_jumps(vc, vl, vv, comp, col_rel, col_abs, slot, rows, skip)
        def test(d, z=z):
            med = np.median(d)
            zz = abs(med) / (1.4826 * max(np.median(np.abs(d - med)), 0.005) / np.sqrt(d.size))
            return abs(med) > tol and zz > z, med, zz

        for i, c in enumerate(comps):
            agree = (vc == c) & (vk == 3) & good & (vl >= 0)
            mine = agree & np.isfinite(diff)
            # the side of the reported pixels of every agreeing vote, measured or not
            contacts = {0 if v >= 2 and np.isfinite(col_abs[v - 1, u]) and np.isfinite(col_abs[v - 2, u]) else 1
                        for u, v in zip(vl[agree], vv[agree])}
            sides = [test(diff[mine & (where == w)]) for w in (0, 1) if (mine & (where == w)).sum() >= 5]
            if z_one >= 0 and len(contacts) == 1:
                # tied through one contact: judged at z_one, no exemption
                want = mine.sum() >= 5 and test(diff[mine], z_one)[0]
                verdicts.append((bool(want), "one contact", z_one, bool(test(diff[mine])[0]) if mine.sum() >= 5
                                 else None))
            else:
                steady = len(sides) == 2 and all(t[2] > z for t in sides) and sides[0][1] * sides[1][1] < 0
                jump = mine.sum() >= 5 and test(diff[mine])[0]
                want = jump and not steady
                verdicts.append((bool(want), len(sides), bool(jump and steady)))
            assert got[i] == want, (trial, c, sides, contacts, z_one)
    kinds = set(verdicts)
    assert {(True, 1, False), (False, 1, False), (False, 0, False)} <= kinds            # one contact
    assert (True, 2, False) in kinds and (False, 2, True) in kinds      # two: a jump; a steady change spared
    # link_grad_z_one: a one-contact component flagged under z_one that z alone would have linked
    assert (True, "one contact", 0.0, False) in kinds and (True, "one contact", 3.0, False) in kinds


def test_component_markers_seen_kernel_counts_marker_stripes_with_enough_pixels():
    """kernels.component_markers_seen against numpy on random components, labels and shifts."""
    from gbscan import kernels

    rng = np.random.default_rng(3)
    spec = PatternSpec()
    is_marker = spec.is_marker()
    H, W, n_comp = 30, 50, 6
    comp = rng.integers(-1, n_comp, (H, W)).astype(np.int32)
    rel = rng.integers(-5, 20, (H, W)).astype(np.int32)
    labels = rng.integers(0, 4, (H, W)).astype(np.uint8)
    shift = rng.integers(0, 40, n_comp).astype(np.int64)
    slot = np.array([0, -1, 1, 2, -1, 3], np.int64)
    for min_px in (1, 3, 6):
        got = kernels.component_markers_seen(comp, rel, labels, shift, slot, 4, is_marker, min_px)
        want = np.zeros(4, np.int64)
        for c in range(n_comp):
            if slot[c] < 0:
                continue
            m = (comp == c) & (labels == 3)
            st = rel[m] + shift[c]
            st = st[(st >= 0) & (st < is_marker.size)]
            vals, cnt = np.unique(st[is_marker[st]], return_counts=True)
            want[slot[c]] = int((cnt >= min_px).sum())
        np.testing.assert_array_equal(got, want)
        assert want.sum() > 0


def test_link_params_are_validated():
    with pytest.raises(GBError, match="link_tol_px"):
        uw.UnwrapParams(link_tol_px=5.0)
    with pytest.raises(GBError, match="link_votes"):
        uw.UnwrapParams(link_votes=-1)
    for bad in ({"link_grad_tol": -0.1}, {"link_grad_z": -1.0}, {"link_grad_rows": 1}, {"link_grad_skip_rows": -1},
                {"link_grad_z_one": -1.0}, {"link_grad_z_one": float("nan")}):
        with pytest.raises(GBError, match="link_grad"):
            uw.UnwrapParams(**bad)


def test_component_pixels_over_spans_equals_the_image_pass():
    """kernels.component_pixels_spans (link_components' fast form) against the whole-image pass,
    on the segments of a simulated multi-object frame with random candidate components."""
    from gbscan import kernels, sim
    from gbscan.decode import decode
    from gbscan.pattern import PatternSpec, render_pattern
    from gbscan.unwrap import unroll_rows, cut_depth_edges

    r = sim.render(sim.paper_rig(), sim.scenes.multi_object(), render_pattern(PatternSpec()), "typical", seed=0)
    sm = decode(r.image, PatternSpec())
    segs = unroll_rows(sm.labels)
    segs.j_x = np.linspace(0, 600, segs.j_seg.size).astype(np.float32) % 37  # spacing jumps: cuts
    segs = cut_depth_edges(segs, 1.35)
    rng = np.random.default_rng(0)
    col = np.where(rng.random(sm.labels.shape) < 0.9, rng.normal(300, 50, sm.labels.shape), np.nan).astype(np.float32)
    for frac in (0.0, 0.1, 1.0):
        seg_comp = np.where(rng.random(segs.n) < frac, rng.integers(0, 50, segs.n), -1).astype(np.int32)
        a = kernels.component_pixels(segs.seg, seg_comp, col)
        b = kernels.component_pixels_spans(segs.seg, seg_comp, col, segs.row, segs.u0, segs.u1)
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])
        assert a[2] == b[2] and (frac == 0 or a[2] > 0)


# -- compiled kernels against their reference forms (performance work keeps results bit-identical)
def _slope_jumps_reference(vc, vk, vl, vv, comp, col_rel, col_abs, region, comps, offsets, rows, half_px, tol, z_min):
    """The numpy form ``unwrap._slope_jumps`` had before its compiled kernels (kept as the reference)."""
    from gbscan import kernels

    out = np.zeros(comps.size, bool)
    H, W = col_rel.shape
    h = int(half_px)
    sel = vl >= 0
    if not sel.any():
        return out
    c, kk, u, v = vc[sel], vk[sel], vl[sel].astype(np.int64), vv[sel].astype(np.int64)
    up = (v >= 2) & np.isfinite(col_abs[np.clip(v - 1, 0, H - 1), u]) & np.isfinite(col_abs[np.clip(v - 2, 0, H - 1), u])
    d = np.where(up, -1, 1)
    ca = np.ascontiguousarray(col_abs, dtype=np.float32)
    cr = np.ascontiguousarray(col_rel, dtype=np.float32)
    reg = np.ascontiguousarray(region, dtype=np.int32)
    src_reg = reg[np.clip(v + d, 0, H - 1), u]

    def first_slopes(img, labels, rows_of, want, r0, r1):
        g = np.full(c.size, np.nan)
        for r in range(r0, r1):
            todo = np.isnan(g)
            if todo.any():
                g[todo] = kernels.window_slopes(img, labels, want[todo], rows_of(r)[todo], u[todo], h, h)
        return g

    g_c = first_slopes(cr, comp, lambda r: v - r * d, c.astype(np.int32), rows, 2 * rows)
    lim = np.log1p(tol)
    for s0, sides, lim_s in ((rows, (0,), lim), (3 * rows, (-1, 1), np.log1p(2 * tol))):
        g_s = first_slopes(ca, reg, lambda r: v + r * d, src_reg, s0, s0 + rows)
        fin = np.isfinite(g_c) & np.isfinite(g_s) & (g_c > 0) & (g_s > 0)
        lr = np.full(c.size, np.nan)
        lr[fin] = np.log(g_c[fin] / g_s[fin])
        for i, (cc, ko) in enumerate(zip(comps.tolist(), offsets.tolist())):
            for side in sides:
                m = (c == cc) & (kk == ko) & fin & ((d == side) | (side == 0))
                if m.sum() >= uw._SLOPE_MIN_VOTES:
                    sl = lr[m]
                    med = float(np.median(sl))
                    spread = max(1.4826 * float(np.median(np.abs(sl - med))), uw._SLOPE_NOISE_FLOOR) / np.sqrt(sl.size)
                    out[i] |= abs(med) > lim_s and abs(med) > z_min * spread
    return out


_FRAMES: dict = {}


def _sim_frame(name: str):
    """(image, StripeMap) of a small set of simulated frames (cached per test session)."""
    from gbscan import sim
    from gbscan.decode import decode
    from gbscan.pattern import render_pattern

    if name not in _FRAMES:
        import dataclasses

        scene, preset, seed = {"multi_move5": (lambda: sim.scenes.multi_object(675.0), "typical", 5),
                               "hard_plane": (lambda: sim.scenes.plane(650.0, (10.0, 20.0)), "hard", 2)}[name]
        cond = dataclasses.replace(sim.preset(preset), supersample=1)
        img = sim.render(sim.paper_rig(), scene(), render_pattern(PatternSpec()), cond, seed=seed).image
        _FRAMES[name] = (img, decode(img, PatternSpec()))
    return _FRAMES[name]


@pytest.mark.parametrize("name", ["multi_move5", "hard_plane"])
def test_slope_jumps_kernel_equals_the_numpy_reference(name, monkeypatch):
    """unwrap._slope_jumps (kernels.slope_samples + slope_verdicts) gives the old numpy form's
    verdicts on the votes of simulated frames: the components the decoder asks about, every
    voted-for (component, offset) pair, and tolerances from always to never refusing."""
    from gbscan.decode import decode

    img, _ = _sim_frame(name)
    calls = []
    real = uw._slope_jumps

    def spy(*args, **kw):
        calls.append(args)
        return real(*args, **kw)

    monkeypatch.setattr(uw, "_slope_jumps", spy)
    decode(img, PatternSpec())
    assert calls, "the frame must exercise the slope test"
    n_true = n_false = 0
    for args in calls:
        vc, vk, vl, vv, comp, cr, ca, reg, comps, offs, rows, half, tol, z = args
        np.testing.assert_array_equal(real(*args), _slope_jumps_reference(*args))
        pairs = np.unique(np.c_[vc.astype(np.int64), vk], axis=0)  # every voted (component, offset)
        for tol2, z2, rows2 in ((tol, z, rows), (0.0, 0.0, rows), (0.01, 3.0, 2), (1.0, z, rows)):
            a = real(vc, vk, vl, vv, comp, cr, ca, reg, pairs[:, 0], pairs[:, 1], rows2, half, tol2, z2)
            b = _slope_jumps_reference(vc, vk, vl, vv, comp, cr, ca, reg, pairs[:, 0], pairs[:, 1], rows2, half,
                                       tol2, z2)
            np.testing.assert_array_equal(a, b)
            n_true += int(a.sum())
            n_false += int((~a).sum())
    assert n_true > 0 and n_false > 0  # both verdicts were compared


def _channels(lab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Locally normalised green and blue of an ideal frame: each stripe lights its own channel(s)."""
    gn = ((lab == G) | (lab == C)).astype(np.float32)
    bn = ((lab == B) | (lab == C)).astype(np.float32)
    return gn, bn


@pytest.mark.parametrize("other_channel, rejected", [(0.05, True), (0.12, True), (0.2, False), (0.45, False)])
def test_marker_conflicts_a_clean_disagreement_is_decisive_a_missed_marker_is_not(other_channel, rejected):
    """A green/blue run where the region expects a marker: a marker the classifier missed still
    lights the other channel (skin, rims: min(gn, bn) >= 0.204 on the sweep), a stripe of another
    surface welded in does not.  Only the clean one rejects its stretch on its own (the row only,
    from the agreeing marker before it to the one after it)."""
    spec = PatternSpec()
    lab = stripe_image(spec, 0, 45, rows=40)
    m = slice(16 * 3, 17 * 3)                      # marker stripe 16 (neighbours 15 and 17 blue)
    lab[20, m] = G
    gn, bn = _channels(lab)
    bn[20, m] = other_channel
    un = uw.unwrap(lab)
    idx = uw.index_regions(lab, un.relative, un.region, un.region_px.size, spec)
    assert idx.indexed.all()
    bad = uw.spans_mask(uw.marker_conflicts(lab, un, idx, spec, gn=gn, bn=bn), lab.shape)
    assert not np.delete(bad, 20, axis=0).any()
    if rejected:
        assert bad[20, 11 * 3:21 * 3].all() and not bad[20, :11 * 3].any() and not bad[20, 21 * 3:].any()
    else:
        assert not bad.any()
    # without the channels, or with the rule off, one disagreement is never enough
    assert uw.marker_conflicts(lab, un, idx, spec).shape == (0, 3)
    off = uw.UnwrapParams(conflict_clean_level=0.0)
    assert uw.marker_conflicts(lab, un, idx, spec, off, gn, bn).shape == (0, 3)


@pytest.mark.parametrize("edge_px, rejected", [((0.37,), True), ((0.37, 0.4), False)])
def test_marker_conflicts_a_clean_run_stays_clean_with_a_mixed_edge_pixel(edge_px, rejected):
    """The clean test takes the run's median ``min(gn, bn)``: a lens with lateral chromatic
    aberration mixes both channels into a welded run's edge pixel (0.05 / 0.05 / 0.37 on the
    sweep through a 1-px lens: mean 0.16, over ``conflict_clean_level`` 0.15, median 0.05).  Two
    mixed pixels of three are no clean run."""
    spec = PatternSpec()
    lab = stripe_image(spec, 0, 45, rows=40)
    m = slice(16 * 3, 17 * 3)
    lab[20, m] = G
    gn, bn = _channels(lab)
    bn[20, m] = 0.05
    bn[20, 17 * 3 - len(edge_px):17 * 3] = edge_px
    un = uw.unwrap(lab)
    idx = uw.index_regions(lab, un.relative, un.region, un.region_px.size, spec)
    bad = uw.spans_mask(uw.marker_conflicts(lab, un, idx, spec, gn=gn, bn=bn), lab.shape)
    assert bad[20].any() == rejected and not np.delete(bad, 20, axis=0).any()


def test_marker_conflicts_with_channels_equal_the_two_event_rule_without_clean_runs():
    """On the welded image of the two-event test the clean rule finds the same spans (its
    disagreements are cyan-less stripes too, but two of them already reject the stretch)."""
    spec = PatternSpec()
    lab = welded_image(spec)
    gn, bn = _channels(lab)
    un = uw.unwrap(lab)
    idx = uw.index_regions(lab, un.relative, un.region, un.region_px.size, spec)
    old = uw.spans_mask(uw.marker_conflicts(lab, un, idx, spec), lab.shape)
    assert old.any()
    for g, b in ((gn, bn), (np.full_like(gn, 0.5), np.full_like(bn, 0.5))):
        np.testing.assert_array_equal(uw.spans_mask(uw.marker_conflicts(lab, un, idx, spec, gn=g, bn=b), lab.shape),
                                      old)


def test_conflict_clean_level_is_validated():
    for bad in (-0.1, 1.0):
        with pytest.raises(GBError, match="conflict_clean_level"):
            uw.UnwrapParams(conflict_clean_level=bad)


def _merge_loops_reference(rs, re, rl, nr, spike_px, max_gap_px):
    """The spike and gap cleaning of ``kernels.row_segments`` as it was: merging by shifting the
    rest of the row (quadratic), in Python."""
    rs, re, rl = list(rs[:nr]), list(re[:nr]), list(rl[:nr])

    def merge(k):
        re[k - 1] = re[k + 1]
        del rs[k:k + 2], re[k:k + 2], rl[k:k + 2]

    if spike_px > 0 and len(rs) >= 3:
        k = 1
        while k < len(rs) - 1:
            if (rl[k] != N and rl[k - 1] != N and rl[k - 1] == rl[k + 1] and re[k] - rs[k] + 1 <= spike_px
                    and re[k - 1] + 1 == rs[k] and re[k] + 1 == rs[k + 1]):
                merge(k)
            else:
                k += 1
    if max_gap_px > 0 and len(rs) >= 3:
        k = 1
        while k < len(rs) - 1:
            if rl[k] == N and re[k] - rs[k] + 1 <= max_gap_px and rl[k - 1] != N and rl[k - 1] == rl[k + 1]:
                merge(k)
            else:
                k += 1
    return rs, re, rl


def test_one_pass_run_cleaning_equals_the_merge_loops():
    """kernels._merge_runs_pass (spikes, then gaps; one pass each) leaves the runs the old merge
    loops left, on noisy rows full of spikes, gaps and spike-gap-spike chains."""
    from gbscan import kernels

    rng = np.random.default_rng(0)
    n_merged = 0
    for trial in range(400):
        W = int(rng.integers(1, 60))
        # stripes of 1-4 px with NONE gaps and wrong-colour spikes sprinkled in
        row = np.repeat(rng.choice([G, B, C, N], size=W, p=[0.35, 0.35, 0.1, 0.2]), rng.integers(1, 4, W))[:W]
        row = row.astype(np.uint8)
        starts = np.flatnonzero(np.r_[True, row[1:] != row[:-1]])
        nr = starts.size
        rs = np.zeros(W, np.int32)
        re = np.zeros(W, np.int32)
        rl = np.zeros(W, np.uint8)
        rs[:nr], re[:nr], rl[:nr] = starts, np.r_[starts[1:] - 1, W - 1], row[starts]
        for spike_px, gap_px in ((1, 1), (2, 1), (0, 2), (3, 0)):
            want = _merge_loops_reference(rs, re, rl, nr, spike_px, gap_px)
            a, b, c = rs.copy(), re.copy(), rl.copy()
            m = nr
            if spike_px > 0:
                m = kernels._merge_runs_pass(a, b, c, m, False, spike_px)
            if gap_px > 0:
                m = kernels._merge_runs_pass(a, b, c, m, True, gap_px)
            assert (a[:m].tolist(), b[:m].tolist(), c[:m].tolist()) == want, (trial, row.tolist(), spike_px, gap_px)
            n_merged += nr - m
    assert n_merged > 1000  # the rows did exercise the merging


def test_vertical_votes_without_sort_equals_the_sorted_form():
    """kernels.vertical_votes (pairs counted as they pass along the rows) against the sort of all
    keys (kernels._vertical_votes_sorted) on a simulated hard frame, before and after cuts, and on
    a shuffled numbering of the segments (the fast form must then fall back to the sort)."""
    from gbscan import kernels

    _, sm = _sim_frame("hard_plane")
    segs = uw.unroll_rows(sm.labels)
    segs.j_x = (0.5 * (segs.j_ua + segs.j_ub) + np.random.default_rng(1).normal(0, 0.4, segs.j_ua.size)).astype(
        np.float32)
    pieces = uw.cut_depth_edges(segs, 1.2)
    assert pieces.n > segs.n
    for s in (segs, pieces):
        a = kernels.vertical_votes(sm.labels, s.seg, s.rel, s.n)
        b = kernels._vertical_votes_sorted(sm.labels, s.seg, s.rel, s.n)
        assert len(a) == len(b) == 6 and a[0].size > 1000
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)
            assert x.dtype == y.dtype
    perm = np.random.default_rng(2).permutation(segs.n).astype(np.int32)
    shuffled = np.where(segs.seg >= 0, perm[np.maximum(segs.seg, 0)], -1).astype(np.int32)
    a = kernels.vertical_votes(sm.labels, shuffled, segs.rel, segs.n)
    b = kernels._vertical_votes_sorted(sm.labels, shuffled, segs.rel, segs.n)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


def test_vertical_votes_on_a_pixel_by_pixel_checkerboard_of_segments():
    """The worst case for the vote tables: every pixel its own segment, the numbering reversed
    (the fast form falls back to the sort), so that a key run ends at every pixel of every row.
    The sorted form once sized its buffer for half of that and wrote past it; now both forms give
    the edges a plain count gives: each pixel with a labelled pixel above is one pair with one vote
    (same colour) or one overlap (another colour)."""
    from gbscan import kernels

    rng = np.random.default_rng(5)
    H, W = 9, 70
    labels = rng.integers(1, 4, (H, W)).astype(np.uint8)
    labels[rng.random((H, W)) < 0.1] = 0
    seg = (H * W - 1 - np.arange(H * W)).reshape(H, W).astype(np.int32)    # reversed numbering
    rel = rng.integers(-3, 4, (H, W)).astype(np.int32)
    n = H * W
    want = {}
    for v in range(1, H):
        for u in range(W):
            if labels[v, u] == 0 or labels[v - 1, u] == 0:
                continue
            same = labels[v, u] == labels[v - 1, u]
            want[(seg[v, u], seg[v - 1, u])] = (int(rel[v - 1, u] - rel[v, u]) if same else 0, int(same), int(same), 1)
    for f in (kernels.vertical_votes, kernels._vertical_votes_sorted):
        s, t, off, agree, same, over = f(labels, seg, rel, n)
        got = {(a, b): (c, d, e, g) for a, b, c, d, e, g in zip(s, t, off, agree, same, over)}
        assert got == want


def test_check_vertical_equals_its_array_form():
    """kernels.check_vertical (branch-free rows) against the same rule in whole-array numpy, on a
    simulated frame with a tenth of the relative indices disturbed."""
    from gbscan import kernels

    _, sm = _sim_frame("multi_move5")
    rng = np.random.default_rng(3)
    rel = np.where(rng.random(sm.relative.shape) < 0.1, sm.relative + 2, sm.relative).astype(np.int32)
    lab, reg = sm.labels, sm.region.astype(np.int32)
    pair = ((lab[1:] != 0) & (reg[1:] >= 0) & (lab[:-1] == lab[1:]) & (reg[:-1] == reg[1:])
            & (rel[1:] != rel[:-1]))
    want = np.zeros(lab.shape, bool)
    want[1:] |= pair
    want[:-1] |= pair
    got = kernels.check_vertical(lab, rel, reg)
    assert want.sum() > 1000
    np.testing.assert_array_equal(got, want)


def _interpolate_columns_reference(H, W, seg_row, seg_u0, seg_u1, seg_j0, seg_j1, seg_ok, j_x, j_bnd, stripe_px,
                                   extrapolate):
    """``kernels.interpolate_columns`` as it was (the slope per pixel), in Python."""
    col = np.full((H, W), np.nan, np.float32)
    for s in np.flatnonzero(seg_ok):
        xs, cs = [], []
        for j in range(seg_j0[s], seg_j1[s]):
            x = float(j_x[j])
            if np.isnan(x) or (xs and x <= xs[-1] + 0.05):
                continue
            xs.append(x)
            cs.append(float(j_bnd[j]) * stripe_px - 0.5)
        n = len(xs)
        if n < 2:
            continue
        k = 0
        for u in range(seg_u0[s], seg_u1[s] + 1):
            while k < n - 2 and u >= xs[k + 1]:
                k += 1
            x0, x1 = xs[k], xs[k + 1]
            slope = (cs[k + 1] - cs[k]) / (x1 - x0)
            if (u < x0 and x0 - u > extrapolate * (x1 - x0)) or (u > x1 and u - x1 > extrapolate * (x1 - x0)):
                continue
            col[seg_row[s], u] = cs[k] + (u - x0) * slope
    return col


def test_interpolate_columns_equals_the_per_pixel_form():
    """kernels.interpolate_columns (the slope once per interval) against the per-pixel form, on a
    simulated frame's segments with jittered, missing and out-of-order boundaries."""
    from gbscan import kernels

    _, sm = _sim_frame("multi_move5")
    segs = uw.unroll_rows(sm.labels)
    rng = np.random.default_rng(4)
    jx = 0.5 * (segs.j_ua + segs.j_ub) + rng.normal(0, 0.6, segs.j_ua.size)
    jx[rng.random(jx.size) < 0.05] = np.nan
    jb = segs.j_rel.astype(np.float64) + 2 * rng.integers(-3, 4, jx.size)
    ok = (rng.random(segs.n) < 0.3).astype(np.uint8)
    H, W = sm.labels.shape
    args = (H, W, segs.row, segs.u0, segs.u1, segs.j0, segs.j1, ok, jx, jb, 8.0, 0.5)
    got = kernels.interpolate_columns(*args)
    want = _interpolate_columns_reference(*args)
    assert np.isfinite(want).sum() > 10000
    np.testing.assert_array_equal(got, want)


def test_unroll_rows_holds_a_junction_at_every_pixel():
    """1-px alternating stripes without spike removal: W - 1 junctions in every row (more than the
    kernel's scratch once held: it must not write past it)."""
    lab = np.tile(np.array([G, B], np.uint8), (30, 40))
    s = uw.unroll_rows(lab, max_gap_px=1, spike_px=0)
    assert s.n == 30 and s.j_seg.size == 30 * 79
    np.testing.assert_array_equal(s.rel, np.broadcast_to(np.arange(80), (30, 80)))
    e = uw.relate_rows(lab, s)
    assert e.s.size == 29 and (e.offset == 0).all() and (e.n_agree == 80).all()



# -- kernels.rim_mask (branch-free rows, flagged pixels found 8 at a time) against its old form ----
from numba import njit  # noqa: E402


@njit(nogil=True)
def _abs_row_reference(column_rel, region, reg_off, v, out, weight):
    # absolute columns of row v into out (W,) (0 where none) and weight (W,) (1 where one): a
    # column of an indexed region; an unlabelled gap pixel inside a segment (region -1 with a
    # column) takes its left neighbour's region
    W = out.shape[0]
    for u in range(W):
        k = region[v, u]
        if k < 0 and u > 0:
            k = region[v, u - 1]
        c = np.float32(np.nan)
        if k >= 0:
            c = column_rel[v, u] + reg_off[k]
        if c == c:
            out[u] = c
            weight[u] = 1.0
        else:
            out[u] = 0.0
            weight[u] = 0.0


@njit(nogil=True)
def _rim_mask_reference(column_rel, region, reg_off, reason, half_px, max_pull_px, end_px, rim_code, pull_out,
                        end_isolated, end_overflow, labels, end_reach=0):
    """``kernels.rim_mask`` as it was (per-pixel branches, in-place rows), and the reach rule
    pixel by pixel (``_reach_reference``): the reference."""
    H, W = column_rel.shape
    want = pull_out.shape[0] == H and pull_out.shape[1] == W
    n_ring = 2 * half_px + 2
    ring = np.empty((n_ring, W), np.float32)   # absolute columns of rows v - half_px - 1 .. v + half_px
    ring_w = np.empty((n_ring, W), np.float32)  # ... 1 where there is one
    num = np.zeros(W, np.float64)
    den = np.zeros(W, np.float64)
    n_rim = 0
    for v in range(min(half_px, H)):
        _abs_row_reference(column_rel, region, reg_off, v, ring[v % n_ring], ring_w[v % n_ring])
        for u in range(W):
            num[u] += ring[v % n_ring, u]
            den[u] += ring_w[v % n_ring, u]
    for v in range(H):
        va = v + half_px                      # row entering the window
        vb = v - half_px - 1                  # row leaving it
        if va < H:
            _abs_row_reference(column_rel, region, reg_off, va, ring[va % n_ring], ring_w[va % n_ring])
            if max_pull_px > 0:
                rin = ring[va % n_ring]
                win = ring_w[va % n_ring]
                for u in range(W):                # branch-free running sums
                    num[u] += rin[u]
                    den[u] += win[u]
        if vb >= 0 and max_pull_px > 0:
            rout = ring[vb % n_ring]
            wout = ring_w[vb % n_ring]
            for u in range(W):
                num[u] -= rout[u]
                den[u] -= wout[u]
        row = ring[v % n_ring]
        roww = ring_w[v % n_ring]
        for u in range(W):
            if roww[u] == 0:
                continue
            c = row[u]
            rim = False
            if max_pull_px > 0:
                dev = num[u] - c * den[u]          # den * pull, no division in the common case
                if want:
                    pull_out[v, u] = dev / den[u]
                rim = abs(dev) > max_pull_px * den[u]
            if not rim and end_px > 0:
                # at the end of the row stretch and next to no signal (reason 1..3) or the
                # image's side, both within end_px; the common case (a column on both sides)
                # exits at once
                if (u >= end_px and u + end_px < W and column_rel[v, u - 1] == column_rel[v, u - 1]
                        and column_rel[v, u + 1] == column_rel[v, u + 1] and end_px == 1):
                    pass
                else:
                    at_end = u - end_px < 0 or u + end_px >= W
                    near_dark = at_end
                    for x in range(max(u - end_px, 0), min(u + end_px, W - 1) + 1):
                        cx = reason[v, x]
                        if x != u and cx >= 1 and cx <= 3:
                            near_dark = True
                        if end_isolated and abs(x - u) == 1 and cx == 0 and region[v, x] < 0:
                            near_dark = True    # a striped pixel no region holds, next to it
                        x2 = 2 * x - u
                        if end_overflow and abs(x - u) == 1 and 0 <= x2 < W:
                            over = True         # its colour run goes on 2 px past the columns
                            for y in (x, x2):
                                if not (reason[v, y] == 0 and region[v, y] >= 0 and column_rel[v, y] != column_rel[v, y]
                                        and labels[v, y] == labels[v, u]):
                                    over = False
                            if over:
                                near_dark = True
                        if column_rel[v, x] != column_rel[v, x]:
                            at_end = True
                    rim = at_end and near_dark
            if rim and reason[v, u] == 0:
                reason[v, u] = rim_code
                n_rim += 1
        if end_px > 0 and end_reach > 0:
            n_rim += _reach_reference(column_rel[v], roww, reason[v], end_px, end_reach, rim_code)
    return n_rim


@njit(nogil=True)
def _reach_reference(crel, roww, rsn, end_px, reach, rim_code):
    # the reach rule pixel by pixel, every decision read from the reasons before it: a pixel with
    # an absolute column and reason 0 goes when its stretch ends next to no signal (or the side)
    # and a no-signal pixel d within the stretch's last `reach` px, d not the end, lies at most
    # end_px beyond it toward that end (the farthest such d from the end decides)
    W = crel.size
    snap = rsn.copy()
    n = 0
    for u in range(W):
        if snap[u] != 0 or roww[u] == 0 or crel[u] != crel[u]:
            continue
        a = u
        while a > 0 and crel[a - 1] == crel[a - 1]:
            a -= 1
        b = u
        while b < W - 1 and crel[b + 1] == crel[b + 1]:
            b += 1
        go = False
        if b == W - 1 or 1 <= snap[b + 1] <= 3:
            ds = [d for d in range(a, b) if b - d < reach and 1 <= snap[d] <= 3]
            if len(ds) > 0 and u >= min(ds) - end_px:
                go = True
        if a == 0 or 1 <= snap[a - 1] <= 3:
            ds = [d for d in range(a + 1, b + 1) if d - a < reach and 1 <= snap[d] <= 3]
            if len(ds) > 0 and u <= max(ds) + end_px:
                go = True
        if go:
            rsn[u] = rim_code
            n += 1
    return n


@pytest.mark.parametrize("name", ["multi_move5", "hard_plane"])
def test_rim_mask_equals_its_per_pixel_form(name, monkeypatch):
    """kernels.rim_mask masks the pixels, returns the count and (when asked) the pull its old
    per-pixel form gave, on the decoder's own calls for simulated frames and with other rule
    parameters: no pull, wider end windows, a rim code the end rule reads (1..3: masking in row
    order matters), a short window, the pull image requested."""
    from gbscan import kernels
    from gbscan.decode import decode

    img, _ = _sim_frame(name)
    calls = []
    real = kernels.rim_mask

    def spy(*args):
        calls.append(tuple(a.copy() if isinstance(a, np.ndarray) else a for a in args))
        return real(*args)

    monkeypatch.setattr(kernels, "rim_mask", spy)
    decode(img, PatternSpec())
    assert calls, "the decoder must call the rim rule"
    n_masked = 0
    for args in calls:
        col, reg, off, reason, half, pull, end, code, _, iso, over, labels, reach = args
        assert iso is True and over is True and labels.shape == reason.shape   # the decoder's defaults
        assert reach == 5
        H, W = reason.shape
        for half2, pull2, end2, code2, want in ((half, pull, end, code, False), (half, pull, end, code, True),
                                                (half, 0.0, end, code, False), (half, pull, 0, code, False),
                                                (half, pull, 2, code, True), (1, 0.3, 3, 2, False),
                                                (0, pull, end, 1, False)):
            for iso2, over2, reach2 in ((True, True, reach), (True, False, 0), (False, True, 3), (True, True, 0)):
                r_new, r_ref = reason.copy(), reason.copy()
                p_new = np.full((H, W) if want else (0, 0), -7.0, np.float32)
                p_ref = p_new.copy()
                n_new = real(col, reg, off, r_new, half2, pull2, end2, code2, p_new, iso2, over2, labels, reach2)
                n_ref = _rim_mask_reference(col, reg, off, r_ref, half2, pull2, end2, code2, p_ref, iso2, over2, labels,
                                            reach2)
                assert n_new == n_ref
                np.testing.assert_array_equal(r_new, r_ref)
                np.testing.assert_array_equal(p_new, p_ref)
                n_masked += n_new
    assert n_masked > 100  # the rules did mask pixels


def test_rim_mask_end_rule_masks_a_stretch_end_beside_a_striped_pixel_no_region_holds():
    """``end_isolated``: the last pixel of a row's stretch whose next pixel has signal (reason 0)
    but no region is masked, and only that one (not the second pixel within ``end_px``); a
    neighbour of another region, or none (the stretch simply ending in a dark pixel's place with
    reason 0 and a region), does not count."""
    from gbscan import kernels

    W = 12
    col = np.full((1, W), np.nan, np.float32)
    col[0, 2:8] = np.arange(6, dtype=np.float32) * 3.0
    region = np.full((1, W), -1, np.int32)
    region[0, 2:8] = 0
    none = np.zeros((0, 0), np.float32)
    for iso, other, want in ((True, -1, [7]), (False, -1, []), (True, 1, [])):
        reg = region.copy()
        reg[0, 8] = other                   # the pixel after the stretch (reason 0: it has signal)
        reason = np.zeros((1, W), np.uint8)
        reason[0, :2] = 1                   # dark before the stretch: its first two pixels go as ever
        n = kernels.rim_mask(col, reg, np.zeros(2, np.float32), reason, 1, 0.0, 2, 8, none, iso)
        assert sorted(np.flatnonzero(reason[0] == 8)) == [2, 3] + want, (iso, other)
        assert n == 2 + len(want)
        r_ref = np.zeros((1, W), np.uint8)
        r_ref[0, :2] = 1
        assert _rim_mask_reference(col, reg, np.zeros(2, np.float32), r_ref, 1, 0.0, 2, 8, none, iso, False,
                                   np.zeros((1, W), np.uint8)) == n
        np.testing.assert_array_equal(r_ref, reason)


def test_rim_mask_end_rule_masks_a_stretch_end_whose_run_overflows_its_columns():
    """``end_overflow``: the last pixel of a stretch whose colour run goes on for 2 px or more in
    a region without columns (a run wider than the stripe its end was extrapolated over: two
    surfaces' stripes of one colour merged at a silhouette) is masked; 1 px of overflow, another
    colour beyond, or no region there is not."""
    from gbscan import kernels

    W = 20
    col = np.full((1, W), np.nan, np.float32)
    col[0, 4:10] = np.arange(6, dtype=np.float32) * 3.0
    none = np.zeros((0, 0), np.float32)
    for n_over, beyond_lab, beyond_reg, on, want in ((2, 2, 0, True, [9]), (3, 2, 0, True, [9]), (1, 2, 0, True, []),
                                                     (2, 1, 0, True, []), (2, 2, -1, True, []), (2, 2, 0, False, [])):
        region = np.full((1, W), -1, np.int32)
        region[0, 4:10 + n_over] = 0
        region[0, 10:10 + n_over] = beyond_reg
        labels = np.zeros((1, W), np.uint8)
        labels[0, 4:10] = [1, 1, 2, 2, 2, 2]      # the stretch ends in a blue run ...
        labels[0, 10:10 + n_over] = beyond_lab     # ... that goes on past its columns (blue) or not
        col_row = col.copy()
        col_row[0, 10 + n_over:] = 100.0           # after it another surface's stretch (region 1)
        region[0, 10 + n_over:] = 1
        labels[0, 10 + n_over:] = 3              # (a colour neither run has)
        reason = np.zeros((1, W), np.uint8)
        reason[0, :4] = 1                          # dark before: the first two pixels go as ever
        r_ref = reason.copy()
        off = np.zeros(2, np.float32)
        n = kernels.rim_mask(col_row, region, off, reason, 1, 0.0, 2, 8, none, False, on, labels)
        # (the other stretch's first two pixels: beside the overflow's pixels without a column, but
        # no signal-less pixel or isolated one within reach: kept; its last two: the image's side)
        got = sorted(np.flatnonzero(reason[0] == 8))
        assert got == [4, 5] + want + [W - 2, W - 1], (n_over, beyond_lab, beyond_reg, on)
        assert _rim_mask_reference(col_row, region, off, r_ref, 1, 0.0, 2, 8, none, False, on, labels) == n
        np.testing.assert_array_equal(r_ref, reason)


def test_rim_mask_reach_rule_ends_a_stretch_at_its_last_dark_pixel():
    """``end_reach``: a stretch that ends next to no signal, with a dark pixel (an interpolated
    column) within its last ``end_reach`` px, ends there for the end rule: from ``end_px`` before
    it to the end everything goes (the left-hand rig's weld, ``GGG . BB . G`` then shadow).  A
    dark pixel farther in, an end beside a pixel with signal, or the rule off: only what the end
    rule masks on its own."""
    from gbscan import kernels

    W = 24
    none = np.zeros((0, 0), np.float32)

    def masked(dark_at, beyond, reach, left_dark=None):
        col = np.full((1, W), np.nan, np.float32)
        col[0, 2:18] = np.arange(16, dtype=np.float32) * 2.5
        region = np.full((1, W), -1, np.int32)
        region[0, 2:18] = 0
        reason = np.zeros((1, W), np.uint8)
        reason[0, :2] = 1                   # dark before the stretch 2..17
        reason[0, 18:] = beyond             # after it: no signal (1) or signal without a column (0)
        region[0, 18:] = 0 if beyond == 0 else -1
        for d in dark_at:
            reason[0, d] = 1                # dark inside the stretch, its column interpolated
        r_ref = reason.copy()
        args = (np.zeros(1, np.float32), reason, 1, 0.0, 2, 8, none, False, False, np.zeros((1, W), np.uint8), reach)
        n = kernels.rim_mask(col, region, *args)
        got = np.flatnonzero(reason[0] == 8).tolist()
        assert n == len(got)
        assert _rim_mask_reference(col, region, args[0], r_ref, *args[2:]) == n
        np.testing.assert_array_equal(r_ref, reason)
        return got

    assert masked([14], 1, 5) == [2, 3, 12, 13, 15, 16, 17]      # from 2 px before the dark pixel on
    assert masked([13, 15], 1, 5) == [2, 3, 11, 12, 14, 16, 17]   # the farthest within reach decides
    assert masked([14], 1, 0) == [2, 3, 16, 17]                   # off: the end rule's 2 px
    assert masked([12], 1, 5) == [2, 3, 16, 17]                   # 5 px from the end: beyond reach
    # the end beside signal: no reach (16: the end rule's own, the dark pixel 2 px from it)
    assert masked([14], 0, 5) == [2, 3, 16]
    assert masked([5], 1, 5) == [2, 3, 4, 6, 7, 16, 17]           # the left end, mirrored


def test_rim_mask_equals_its_per_pixel_form_on_random_rows():
    """The same comparison on random images: many regions (some not indexed), holes in the
    columns, no-signal reasons everywhere, narrow images (the window leaves them), pulls large
    and small."""
    from gbscan import kernels

    rng = np.random.default_rng(3)
    n_masked = n_over = n_reach = 0
    for trial in range(40):
        H, W = int(rng.integers(1, 30)), int(rng.integers(1, 50))
        n_reg = int(rng.integers(1, 6))
        region = np.repeat(rng.integers(-1, n_reg, (H, W // 3 + 1)), 3, axis=1)[:, :W].astype(np.int32)
        col = (np.arange(W, dtype=np.float32)[None, :] * 1.3 + rng.normal(0, 1.5, (H, W))).astype(np.float32)
        col[rng.random((H, W)) < 0.15] = np.nan
        col[np.repeat(rng.random((H, W // 2 + 1)) < 0.1, 2, axis=1)[:, :W]] = np.nan   # pairs: runs overflowing
        off = rng.integers(0, 50, n_reg).astype(np.float32) * 8
        off[rng.random(n_reg) < 0.2] = np.nan
        reason = rng.choice(np.array([0, 0, 0, 1, 2, 3, 5], np.uint8), size=(H, W))
        labels = np.repeat(rng.integers(1, 4, (H, W // 2 + 1)), 2, axis=1)[:, :W].astype(np.uint8)
        for half, pull, end, code, want in ((2, 0.7, 2, 8, False), (1, 0.3, 1, 8, True), (0, 2.0, 3, 2, True),
                                            (3, 0.0, 1, 1, False), (2, 0.5, 0, 8, False)):
            for iso, over, reach in ((True, False, 0), (False, False, 5), (True, True, 2), (False, True, 0),
                                     (True, True, 8)):
                r_new, r_ref = reason.copy(), reason.copy()
                p_new = np.full((H, W) if want else (0, 0), -7.0, np.float32)
                p_ref = p_new.copy()
                n_new = kernels.rim_mask(col, region, off, r_new, half, pull, end, code, p_new, iso, over, labels, reach)
                n_ref = _rim_mask_reference(col, region, off, r_ref, half, pull, end, code, p_ref, iso, over, labels,
                                            reach)
                assert n_new == n_ref, (trial, half, pull, end, code, iso, over, reach)
                np.testing.assert_array_equal(r_new, r_ref)
                np.testing.assert_array_equal(p_new, p_ref)
                n_masked += n_new
                n_over += n_new if over else -n_new
                if reach:
                    n_reach += n_new - kernels.rim_mask(col, region, off, reason.copy(), half, pull, end, code,
                                                        np.zeros((0, 0), np.float32), iso, over, labels, 0)
    assert n_masked > 200
    assert n_over > 0       # the overflow rule had pixels to mask
    assert n_reach > 0      # the reach rule masked pixels the others did not


def test_cut_unlocated_cuts_only_a_bridge_that_does_not_fit():
    """uw.cut_unlocated on one row of 4-px stripes (boundaries every 4 px, one segment): an
    unlocated boundary whose neighbours bridge it at the row's spacing stays; shifting the
    boundaries right of it by 1.5 px (bridge 1.19 x the spacing beside it: two surfaces whose
    stripes only nearly line up) cuts the row there at bridge_ratio 1.15, not at 1.35; an
    unlocated boundary at the segment's end (nothing to bridge) is cut; 0 disables the rule."""
    lab = np.tile(np.repeat(np.array([G, B], np.uint8), 4), 10)[None]   # 20 stripes, 19 boundaries
    segs = uw.unroll_rows(lab)
    assert segs.n == 1 and segs.j_seg.size == 19
    x = (segs.j_ua + 0.5).astype(np.float32)    # boundary between px 4k-1 and 4k: at 4k - 0.5
    np.testing.assert_allclose(np.diff(x), 4.0)

    def cut(jx, ratio=1.15):
        s = uw.unroll_rows(lab)
        s.j_x = jx.astype(np.float32)
        return uw.cut_unlocated(s, ratio)

    fits = x.copy()
    fits[9] = np.nan
    assert cut(fits).n == 1
    shifted = x.copy()
    shifted[10:] += 1.5
    shifted[9] = np.nan
    pieces = cut(shifted)
    assert pieces.n == 2 and cut(shifted, 1.35).n == 1 and cut(shifted, 0.0).n == 1
    # the cut is at the unlocated boundary: the pieces meet where boundary 9 was
    assert pieces.u1[0] + 1 == pieces.u0[1] == segs.j_ub[9]
    np.testing.assert_array_equal(pieces.rel, segs.rel)     # relative indices unchanged
    end = x.copy()
    end[18] = np.nan
    assert cut(end).n == 2
    two = x.copy()
    two[[8, 9]] = np.nan    # a run of two, bridged at the row's spacing
    assert cut(two).n == 1
    two[10:] += 4.0         # one stripe too many for the bridge (1.33 x)
    assert cut(two).n == 3  # cut at both: which one was the silhouette is unknown


def test_weld_rule_params_are_validated():
    for bad in (1.0, 0.5, -1.0):
        with pytest.raises(GBError, match="bridge_ratio"):
            uw.UnwrapParams(bridge_ratio=bad)
    with pytest.raises(GBError, match="link_hang_rows"):
        uw.UnwrapParams(link_hang_rows=-1)
    with pytest.raises(GBError, match="link_slope_z_near"):
        uw.UnwrapParams(link_slope_z_near=-1.0)
    uw.UnwrapParams(bridge_ratio=0.0, link_hang_rows=0)


def test_one_split_equals_cut_depth_edges_then_cut_unlocated():
    """unwrap() applies the spacing and the bridge cuts in one split (uw._spacing_cut_mask,
    uw._unlocated_cut_mask with the spacing cuts as piece ends); the pieces equal those of the two
    public cutters run one after the other, on a simulated hard frame's segments with noisy
    boundaries, 3 % of them unlocated (runs included)."""
    _, sm = _sim_frame("hard_plane")
    segs = uw.unroll_rows(sm.labels)
    rng = np.random.default_rng(4)
    jx = 0.5 * (segs.j_ua + segs.j_ub) + rng.normal(0, 0.4, segs.j_ua.size)
    lost = rng.random(jx.size) < 0.03
    lost[1:] |= lost[:-1] & (rng.random(jx.size - 1) < 0.3)
    jx[lost] = np.nan
    segs.j_x = jx.astype(np.float32)
    want = uw.cut_unlocated(uw.cut_depth_edges(segs, 1.2), 1.15)
    c_depth = uw._spacing_cut_mask(segs, 1.2)
    c_unloc = uw._unlocated_cut_mask(segs, 1.15, c_depth)
    assert c_depth.sum() > 100 and c_unloc.sum() > 100 and not (c_depth & c_unloc).any()
    got = uw._apply_cuts(segs, c_depth | c_unloc)
    assert got.n == segs.n + int(c_depth.sum() + c_unloc.sum()) == want.n
    for f in ("seg", "row", "u0", "u1", "j0", "j1", "parity", "j_seg", "j_ua", "j_ub", "j_rel", "j_x"):
        np.testing.assert_array_equal(getattr(got, f), getattr(want, f), err_msg=f)


def _two_segments(spacing_b: float, gap_px: int):
    """One row: segment A over pixels 0..29 with boundaries every 4 px from 2 to 26, segment B
    from 30 + gap_px on with boundaries every ``spacing_b`` px from 1 px after its start."""
    a_x = np.arange(2.0, 27.0, 4.0)
    b0 = 30 + gap_px
    b_x = b0 + 1.0 + spacing_b * np.arange(8)
    W = int(np.ceil(b_x[-1])) + 3
    j_x = np.r_[a_x, b_x]
    j_bnd = np.r_[np.arange(a_x.size), 100 + np.arange(b_x.size)].astype(np.float64)
    seg = (np.zeros(2, np.int32), np.array([0, b0], np.int32), np.array([29, W - 1], np.int32),
           np.array([0, a_x.size], np.int32), np.array([a_x.size, j_x.size], np.int32))
    return W, seg, j_x, j_bnd


@pytest.mark.parametrize("spacing_b, gap_px, ratio, cut", [
    (2.0, 1, 1.35, True),     # a depth edge: the spacing halves across the contact (one pixel between)
    (2.0, 0, 1.35, True),     # ... the segments side by side
    (4.2, 1, 1.35, False),    # one surface split (a misclassified pixel): the spacing goes on
    (2.0, 1, 0.0, False),     # the rule off
    (2.0, 2, 1.35, False)])   # no contact: two pixels or more between the segments
def test_interpolate_columns_does_not_extrapolate_across_a_depth_edge_contact(spacing_b, gap_px, ratio, cut):
    """DecodeParams.contact_ratio: where two segments of a row touch and the boundary spacing
    jumps across the contact, neither end is extrapolated beyond its last located boundary (the
    run the depth edge cuts may carry the other surface's colours); elsewhere ends are
    extrapolated up to ``extrapolate`` intervals, as before."""
    from gbscan import kernels

    W, seg, j_x, j_bnd = _two_segments(spacing_b, gap_px)
    col = kernels.interpolate_columns(1, W, *seg, np.ones(2, np.uint8), j_x, j_bnd, 8.0, 0.75, ratio)[0]
    ref = kernels.interpolate_columns(1, W, *seg, np.ones(2, np.uint8), j_x, j_bnd, 8.0, 0.75)[0]
    _assert_contact_ends(col, ref, seg, j_x, cut)


def _assert_contact_ends(col, ref, seg, j_x, cut: bool):
    """``col`` against the columns ``ref`` of :func:`_two_segments` extrapolated at both ends of
    the contact: equal but for A's end beyond its last boundary (26) and B's start before its
    first, which are NaN when ``cut``, else equal too."""
    a_end = np.arange(27, 30)                       # beyond A's last boundary (26)
    b_start = np.arange(seg[1][1], int(np.ceil(j_x[7])))   # before B's first boundary
    assert np.all(np.isfinite(ref[a_end])) and np.all(np.isfinite(ref[b_start]))
    inner = np.isfinite(ref)
    inner[a_end] = inner[b_start] = False
    np.testing.assert_array_equal(col[inner], ref[inner])   # the rest never changes
    if cut:
        assert np.all(np.isnan(col[a_end])) and np.all(np.isnan(col[b_start]))
    else:
        np.testing.assert_array_equal(col, ref)


@pytest.mark.parametrize("shift_b, cut", [
    ((8 - 100) * 8.0, False),          # B continues A's columns: one surface (two regions of it)
    ((8 + 12 - 100) * 8.0, True),      # 12 stripes further: another surface whose colours line up
    ((8 - 2 - 100) * 8.0, True),       # 2 stripes back
    (np.nan, False),                   # B's region not indexed: nothing to compare
    (None, False)])                    # the rule off (no shifts)
def test_interpolate_columns_does_not_extrapolate_where_the_columns_jump_at_a_contact(shift_b, cut):
    """DecodeParams.contact_regions: two touching segments of a row with the same boundary spacing
    (no spacing jump) but in regions whose offsets put B's first boundary more than a stripe from
    A's columns continued to it: two surfaces at a depth edge whose stripes line up (the layouts
    set at 620 mm: a near object's last run, the wall's stripe of its colour 12 stripes on, read
    as the object's next stripe).  Neither end is extrapolated there; where B's columns continue
    A's, or a shift is unknown, both are, as before."""
    from gbscan import kernels

    W, seg, j_x, j_bnd = _two_segments(4.2, 1)
    ones = np.ones(2, np.uint8)
    ref = kernels.interpolate_columns(1, W, *seg, ones, j_x, j_bnd, 8.0, 0.75, 1.35)[0]
    if shift_b is None:
        col = kernels.interpolate_columns(1, W, *seg, ones, j_x, j_bnd, 8.0, 0.75, 1.35, 0, 1, 0, np.zeros(0))[0]
    else:
        col = kernels.interpolate_columns(1, W, *seg, ones, j_x, j_bnd, 8.0, 0.75, 1.35, 0, 1, 0,
                                          np.array([0.0, shift_b]))[0]
    _assert_contact_ends(col, ref, seg, j_x, cut)
    # the same shifts without the contact rule (contact_ratio 0): always extrapolated
    if shift_b is not None:
        off = kernels.interpolate_columns(1, W, *seg, ones, j_x, j_bnd, 8.0, 0.75, 0.0, 0, 1, 0, np.array([0.0, shift_b]))
        np.testing.assert_array_equal(off[0], kernels.interpolate_columns(1, W, *seg, ones, j_x, j_bnd, 8.0, 0.75)[0])


def _quadratic_row(q: float, n: int = 9, x0: float = 10.5):
    """One row, one segment whose boundary k (column 8 k - 0.5) sits where the column
    c(x) = 8 (x - x0) / 4 + q (x - x0)^2 - 0.5 reaches it: stripes that narrow (q > 0) or widen
    along the row, as toward a silhouette.  Returns (W, seg, j_x, j_bnd, c) with c the exact column."""
    k = np.arange(n, dtype=np.float64)
    t = (-2.0 + np.sqrt(4.0 + 4.0 * q * 8.0 * k)) / (2.0 * q) if q else 4.0 * k
    j_x = x0 + t
    W = int(np.ceil(j_x[-1])) + 6

    def c(x):
        return 2.0 * (x - x0) + q * (x - x0) ** 2 - 0.5

    seg = (np.zeros(1, np.int32), np.array([int(x0) - 5], np.int32), np.array([W - 1], np.int32),
           np.array([0], np.int32), np.array([n], np.int32))
    return W, seg, j_x, k.copy(), c


@pytest.mark.parametrize("q", [0.05, -0.01, 0.0])
def test_interpolate_columns_extrapolates_ends_with_the_boundaries_quadratic(q):
    """DecodeParams.extrapolate_fit: beyond a segment's end boundary the column follows the
    least-squares quadratic of its last 5 boundaries -- exact on a quadratic column (stripes that
    narrow or widen steadily toward a silhouette), where the end interval's straight line errs,
    always the same way; inside the boundaries nothing changes."""
    from gbscan import kernels

    W, seg, j_x, j_bnd, c = _quadratic_row(q)
    ok = np.ones(1, np.uint8)
    fit = kernels.interpolate_columns(1, W, *seg, ok, j_x, j_bnd, 8.0, 0.75, 0.0, 5)[0]
    line = kernels.interpolate_columns(1, W, *seg, ok, j_x, j_bnd, 8.0, 0.75, 0.0, 0)[0]
    u = np.arange(W, dtype=np.float64)
    ends = np.isfinite(line) & ((u < j_x[0]) | (u > j_x[-1]))
    assert ends.sum() >= 4 and np.array_equal(np.isfinite(fit), np.isfinite(line))
    np.testing.assert_allclose(fit[ends], c(u[ends]), atol=1e-3)
    inside = np.isfinite(line) & ~ends
    np.testing.assert_array_equal(fit[inside], line[inside])
    if q:
        assert np.abs(line[ends] - c(u[ends])).max() > 0.1   # the straight line misses the bend


def test_interpolate_columns_end_fit_falls_back_to_the_straight_line():
    """A stray boundary that bends the end quadratic (its slope at the pixel more than a factor 2
    off the end interval's) leaves the straight line; segments with fewer boundaries than the fit
    use the straight line too."""
    from gbscan import kernels

    _, seg, j_x, j_bnd, c = _quadratic_row(0.0)
    j_x = j_x.copy()
    j_x[-1] += 6.0           # the end boundary located 6 px off: the fit's slope falls below half the line's
    W = int(np.ceil(j_x[-1])) + 9
    seg = (seg[0], seg[1], np.array([W - 1], np.int32), seg[3], seg[4])
    ok = np.ones(1, np.uint8)
    fit = kernels.interpolate_columns(1, W, *seg, ok, j_x, j_bnd, 8.0, 0.75, 0.0, 5)[0]
    line = kernels.interpolate_columns(1, W, *seg, ok, j_x, j_bnd, 8.0, 0.75, 0.0, 0)[0]
    right = np.arange(int(np.ceil(j_x[-1] + 1.0)), W)   # a pixel or more past it (the ratio falls with t)
    right = right[np.isfinite(line[right])]
    assert right.size >= 4
    np.testing.assert_array_equal(fit[right], line[right])
    # four boundaries, a fit of five: the straight line at both ends
    W4, seg4, j4, b4, _ = _quadratic_row(0.05, n=4)
    f4 = kernels.interpolate_columns(1, W4, *seg4, ok, j4, b4, 8.0, 0.75, 0.0, 5)[0]
    l4 = kernels.interpolate_columns(1, W4, *seg4, ok, j4, b4, 8.0, 0.75, 0.0, 0)[0]
    np.testing.assert_array_equal(f4, l4)


@pytest.mark.parametrize("gap_px, contact_gap_px, cut", [(2, 2, True), (3, 2, False), (2, 1, False), (1, 1, True)])
def test_interpolate_columns_contact_gap(gap_px, contact_gap_px, cut):
    """DecodeParams.contact_gap_px: two segments of a row with at most that many unlabelled pixels
    between them touch (a Bayer camera's demosaicing leaves such a two-pixel gap at a silhouette);
    across a spacing jump neither end is extrapolated then."""
    from gbscan import kernels

    W, seg, j_x, j_bnd = _two_segments(2.0, gap_px)
    ok = np.ones(2, np.uint8)
    col = kernels.interpolate_columns(1, W, *seg, ok, j_x, j_bnd, 8.0, 0.75, 1.35, 0, contact_gap_px)[0]
    ref = kernels.interpolate_columns(1, W, *seg, ok, j_x, j_bnd, 8.0, 0.75, 0.0, 0, contact_gap_px)[0]
    a_end = np.arange(27, 30)
    assert np.all(np.isfinite(ref[a_end]))
    assert np.all(np.isnan(col[a_end])) == cut and np.all(np.isfinite(col[a_end])) == (not cut)


def test_unroll_rows_drops_a_one_pixel_flank_between_a_marker_and_the_dark():
    """At a shadow's or silhouette's edge through a marker, the pixel mixing the marker and the
    dark can come out as the colour that contradicts the marker's other flank (``. G C B``): the
    row then splits into a fragment ``G C`` and the rest, and the marker is lost to its surface.
    ``marker_end_flank`` unlabels that pixel (1 px only, any marker width; mirrored at the
    stretch's right end, and at the image border); a 2 px run, or one that agrees with the other
    flank (``. B C B``: a real stripe), is left alone."""
    lab = row_from_stripes([N, G, C, B, G, B], [3, 1, 3, 4, 4, 4])[None]
    s = uw.unroll_rows(lab)
    assert s.n == 1 and s.u0[0] == 4 and s.u1[0] == 18
    assert s.seg[0, 3] == -1 and lab[0, 3] == G          # the dropped pixel: outside any segment
    assert s.rel[0, 4] % 2 == 0 and s.rel[0, 7] == s.rel[0, 4] + 1   # flanked by blue: a green stripe's place
    s0 = uw.unroll_rows(lab, marker_end_flank=False)
    assert s0.n == 2 and s0.u1[0] == 6                   # the fragment G C
    # mirrored, and at the image border (no dark run beyond the pixel)
    lab = row_from_stripes([B, G, B, C, G, N], [4, 4, 4, 3, 1, 3])[None]
    s = uw.unroll_rows(lab)
    assert s.n == 1 and s.u0[0] == 0 and s.u1[0] == 14
    assert uw.unroll_rows(row_from_stripes([G, C, B, G], [1, 3, 4, 4])[None]).n == 1
    assert uw.unroll_rows(row_from_stripes([G, C, B, G], [1, 3, 4, 4])[None], marker_end_flank=False).n == 2
    # left alone: two pixels; or a colour that agrees with the other flank
    assert uw.unroll_rows(row_from_stripes([N, G, C, B, G], [3, 2, 3, 4, 4])[None]).n == 2
    s = uw.unroll_rows(row_from_stripes([N, B, C, B, G], [3, 1, 3, 4, 4])[None])
    assert s.n == 1 and s.u0[0] == 3
    # and without the flank pass at all (marker_flank_px=0) nothing changes
    assert uw.unroll_rows(lab, marker_flank_px=0).n == 2


def test_partial_repaint_and_step7_rows_equal_the_full_passes():
    """After the linking gives some segments a region, the decoder repaints only those segments
    (kernels.repaint_segments) and recomputes step 7 only on their rows and the rows beside them
    (kernels.check_vertical_rows); both must equal the full passes."""
    from gbscan import kernels

    rng = np.random.default_rng(11)
    H, W = 40, 60
    labels = rng.choice(np.array([0, 1, 1, 2, 2, 3], np.uint8), size=(H, W))
    labels = np.repeat(labels[:, ::3], 3, axis=1)[:, :W].copy()          # runs a few pixels long
    labels[rng.random((H, W)) < 0.05] = 0
    segs = kernels.row_segments(labels, 1, 1, 2, True)
    seg, rel, seg_row, seg_u0, seg_u1 = segs[0], segs[1], segs[2], segs[3], segs[4]
    n = seg_row.size
    old = rng.integers(-1, 4, n).astype(np.int32)
    P = np.zeros(n, np.int32)
    region, _, isolated = kernels.paint_regions(seg, rel, old, P)
    relative = np.where(seg >= 0, rel, 0).astype(np.int32)
    relative[rng.random((H, W)) < 0.1] += 2                               # some inconsistent pixels
    bad = kernels.check_vertical(labels, relative, region)
    new = old.copy()
    moved = np.flatnonzero(rng.random(n) < 0.2)
    new[moved] = rng.integers(-1, 4, moved.size)
    kernels.repaint_segments(seg, seg_row, seg_u0, seg_u1, moved.astype(np.int64), new, region, isolated)
    want_region, _, want_isolated = kernels.paint_regions(seg, rel, new, P)
    np.testing.assert_array_equal(region, want_region)
    np.testing.assert_array_equal(isolated, want_isolated)
    rows = np.unique(np.clip(seg_row[moved][:, None] + np.arange(-1, 2), 0, H - 1)).astype(np.int64)
    before = bad.copy()
    kernels.check_vertical_rows(labels, relative, region, rows, bad)
    want = kernels.check_vertical(labels, relative, region)
    assert (want != before).any()   # the moved segments changed flags: the rows had work to do
    np.testing.assert_array_equal(bad, want)


def contact_image(spec: PatternSpec, rows_top: int = 20, rows_bottom: int = 20, first: int = 10, shift: int = 24,
                  n: int = 45, px: int = 3) -> np.ndarray:
    """Stripes ``first ..`` over ``rows_top`` rows and, below them, another surface whose stripes are
    ``shift`` (even) further over ``rows_bottom`` rows: green and blue line up at the contact, only
    the markers differ (a horizontal depth edge at the wrong distance)."""
    lab = spec.stripe_labels()
    top = np.repeat(lab[first:first + n], px)
    bottom = np.repeat(lab[first + shift:first + shift + n], px)
    return np.ascontiguousarray(np.vstack([np.broadcast_to(top, (rows_top, top.size)),
                                           np.broadcast_to(bottom, (rows_bottom, bottom.size))]).astype(np.uint8))


def welded_maps(lab: np.ndarray):
    """``relative`` and ``region`` of a label image unwrapped as one region (every pixel; stripes
    continuing down the columns): what the unwrapping gives where two surfaces weld."""
    rel = np.cumsum(np.diff(lab, axis=1, prepend=lab[:, :1]) != 0, axis=1).astype(np.int32)
    return rel, np.zeros(lab.shape, np.int32)


@pytest.mark.parametrize("rows_top, rows_bottom", [(20, 20), (25, 12), (4, 30)])
def test_split_row_finds_a_lined_up_contact(rows_top, rows_bottom):
    spec = PatternSpec()
    lab = contact_image(spec, rows_top, rows_bottom)
    rel, region = welded_maps(lab)
    idx = uw.index_regions(lab, rel, region, 1, spec)
    assert not idx.indexed[0] and idx.why[0] == uw.MISFIT      # no one offset fits both surfaces
    assert uw.split_row(lab, rel, region, 0, spec) == rows_top - 1
    # each part alone is indexed at its own offset (what the decoder's unwrap again finds)
    for part in (np.arange(lab.shape[0]) < rows_top, np.arange(lab.shape[0]) >= rows_top):
        reg = np.where(np.broadcast_to(part[:, None], lab.shape), 0, -1).astype(np.int32)
        ip = uw.index_regions(lab, rel, reg, 1, spec)
        assert ip.indexed[0] and ip.offset[0] == (10 if part[0] else 34)


def test_split_row_span_holds_the_rows_whose_markers_say_nothing():
    """``split_row(span=True)``: the cuts that tie at the fewest mismatching pixels.  At a clean
    contact one row stands out; where the rows next to it show no marker stripe of either surface
    (their marker stripes dark, under either offset) every cut among them fits as well, and the
    span runs from the last row of markers above to the last blank row below: the rows between
    may belong to either part (the decoder reports them unindexed, ``split_undecided``)."""
    spec = PatternSpec()
    lab = contact_image(spec, 20, 20)
    rel, region = welded_maps(lab)
    assert uw.split_row(lab, rel, region, 0, spec, span=True) == (19, 19)
    is_marker = spec.is_marker()
    s = rel[0].astype(np.int64)          # relative stripe per column; the top is 10 on, the bottom 34 on
    either = is_marker[np.minimum(s + 10, is_marker.size - 1)] | is_marker[np.minimum(s + 34, is_marker.size - 1)]
    blank = lab.copy()
    blank[16:24, either] = NONE
    assert uw.split_row(blank, rel, region, 0, spec) == 15                      # the first of the tie, as before
    assert uw.split_row(blank, rel, region, 0, spec, span=True) == (15, 23)
    # a blank band above the contact only: the tie ends at the contact
    above = lab.copy()
    above[16:20, either] = NONE
    assert uw.split_row(above, rel, region, 0, spec, span=True) == (15, 19)


def test_unwrap_sever_px_cuts_the_links_to_the_row_above():
    spec = PatternSpec()
    lab = stripe_image(spec, 10, 45, rows=40)
    un = uw.unwrap(lab)
    assert un.region_px.size == 1
    sever = np.zeros(lab.shape, bool)
    sever[20, :60] = True                                      # any pixel of a segment severs it
    un2 = uw.unwrap(lab, sever_px=sever)
    assert un2.region_px.size == 2 and set(un2.region_px) == {20 * 135}
    assert (un2.region[:20] == un2.region[0, 0]).all() and (un2.region[20:] == un2.region[20, 0]).all()
    idx2 = uw.index_regions(lab, un2.relative, un2.region, 2, spec)
    assert idx2.indexed.all()
    assert np.array_equal(un2.relative + idx2.offset[un2.region], un.relative - un.relative[0, 0] + 10)
    # nothing severed: the same result as without
    un3 = uw.unwrap(lab, sever_px=np.zeros(lab.shape, bool))
    assert np.array_equal(un3.region, un.region) and np.array_equal(un3.relative, un.relative)


def test_split_row_refuses_what_is_no_contact_of_two_surfaces():
    spec = PatternSpec()
    one = stripe_image(spec, 10, 45, rows=40)
    un = uw.unwrap(one)
    assert uw.split_row(one, un.relative, un.region, 0, spec) is None        # one offset fits everywhere
    lab = contact_image(spec, 20, 20)
    rel, region = welded_maps(lab)
    assert uw.split_row(lab, rel, region, 0, spec, uw.UnwrapParams(split_rows=0)) is None
    # a part thinner than split_rows rows is not split off
    assert uw.split_row(lab, rel, region, 0, spec, uw.UnwrapParams(split_rows=21)) is None
    assert uw.split_row(lab, rel, region, 0, spec, uw.UnwrapParams(split_rows=20)) == 19
    # the pure pattern has no markers to tell; a region that is not there
    assert uw.split_row(lab, rel, region, 0, PatternSpec(markers=False)) is None
    assert uw.split_row(lab, rel, region, 5, spec) is None
    # markers that fit no offset in either part (a marker stripe read green in every row): no split
    bad = lab.copy()
    bad[:, 3 * (37 - 10):3 * (38 - 10)] = G
    bad[:, 3 * (41 - 10):3 * (42 - 10)] = G
    bad[20:, 3 * (37 - 34):3 * (38 - 34)] = G
    assert uw.split_row(bad, rel, region, 0, spec) is None


@pytest.mark.parametrize("rows_welded", [10, 16])
def test_peel_conflicts_indexes_a_region_without_its_welded_in_strip(rows_welded):
    """A strip of another surface welded in beside a region along its last rows (12 stripes off
    from stripe 20 on): from 10 welded rows the region's markers mismatch more than
    ``max_mismatch`` and it is left unindexed whole (:data:`MISFIT`).  Without the stretches
    :func:`marker_conflicts` rejects at the best offset the rest fits it exactly: indexed
    (``peeled``), and every wrongly indexed pixel lies in the stretches taken out, which the
    decoder then reports unindexed."""
    spec = PatternSpec()
    lab = welded_image(spec, rows_welded=rows_welded)
    un = uw.unwrap(lab)
    idx = uw.index_regions(lab, un.relative, un.region, un.region_px.size, spec)
    assert un.region_px.size == 1 and not idx.indexed[0] and idx.why[0] == uw.MISFIT
    p = uw.UnwrapParams(retry_min_px=1000)
    new, peeled = uw.peel_conflicts(lab, un, idx, spec, p)
    assert new.indexed[0] and new.why[0] == uw.PEELED and new.offset[0] == idx.offset[0] == -un.relative[0, 0]
    assert new.mismatch[0] == 0 and new.evidence[0] < idx.evidence[0]
    assert not idx.indexed[0] and idx.why[0] == uw.MISFIT          # the input is left as it was
    bad = uw.spans_mask(uw.marker_conflicts(lab, un, new, spec, p), lab.shape)
    assert peeled[0] == bad.sum() == rows_welded * 3 * (45 - 16)  # from the last agreeing marker (16) on
    truth = np.concatenate([np.arange(20), np.arange(32, 57)]).repeat(3)
    wrong = np.zeros(lab.shape, bool)
    wrong[60:] = (un.relative + new.offset[0])[60:] != truth[None]
    assert wrong.any() and bad[wrong].all() and not bad[:60].any()


def test_peel_conflicts_refuses_what_it_should_not_index():
    spec = PatternSpec()
    lab = welded_image(spec, rows_welded=20)             # 1740 of 10 800 px (16 %) in the stretches
    un = uw.unwrap(lab)
    idx = uw.index_regions(lab, un.relative, un.region, un.region_px.size, spec)
    for p in (uw.UnwrapParams(peel_max_frac=0.0),        # off
              uw.UnwrapParams(peel_max_frac=0.15),       # more than that fraction would be taken out
              uw.UnwrapParams(retry_min_px=20000),       # a region under retry_min_px
              uw.UnwrapParams(peel_min_markers=10),      # the rest shows 9 marker stripes
              uw.UnwrapParams(peel_margin=4.7)):         # its runner-up is 4.6 margins behind
        new, peeled = uw.peel_conflicts(lab, un, idx, spec, p)
        assert new is idx and not peeled.any()
    assert uw.peel_conflicts(lab, un, idx, spec, uw.UnwrapParams(peel_max_frac=0.17))[0].indexed[0]
    new = uw.peel_conflicts(lab, un, idx, spec, uw.UnwrapParams(peel_min_markers=9, peel_margin=4.5))[0]
    assert new.indexed[0] and new.markers_seen[0] == 9 and idx.markers_seen[0] == 12
    # the pure pattern has no markers; an indexed region is left alone
    assert uw.peel_conflicts(lab, un, idx, PatternSpec(markers=False))[0] is idx
    ok = welded_image(spec, rows_welded=3)
    un3 = uw.unwrap(ok)
    idx3 = uw.index_regions(ok, un3.relative, un3.region, 1, spec)
    assert idx3.indexed[0] and uw.peel_conflicts(ok, un3, idx3, spec)[0] is idx3
    # as many welded rows as clean ones: the stretches hold 32 % of the region, more than 25 %
    half = welded_image(spec, rows_welded=60)
    un2 = uw.unwrap(half)
    idx2 = uw.index_regions(half, un2.relative, un2.region, un2.region_px.size, spec)
    assert un2.region_px.size == 1 and idx2.why[0] == uw.MISFIT
    assert uw.peel_conflicts(half, un2, idx2, spec)[0] is idx2
    assert uw.peel_conflicts(half, un2, idx2, spec, uw.UnwrapParams(peel_max_frac=0.33))[0].indexed[0]
    with pytest.raises(GBError, match="peel_max_frac"):
        uw.UnwrapParams(peel_max_frac=1.0)
    with pytest.raises(GBError, match="peel_max_frac"):
        uw.UnwrapParams(peel_max_frac=-0.1)
    with pytest.raises(GBError, match="peel_min_markers"):
        uw.UnwrapParams(peel_min_markers=0)
    with pytest.raises(GBError, match="peel_margin"):
        uw.UnwrapParams(peel_margin=0.5)


def test_split_rows_and_sever_px_are_validated():
    with pytest.raises(GBError, match="split_rows"):
        uw.UnwrapParams(split_rows=-1)
    lab = contact_image(PatternSpec())
    with pytest.raises(GBError, match="sever_px"):
        uw.unwrap(lab, sever_px=np.zeros((3, 3), bool))


def test_index_regions_and_split_row_refuse_maps_of_other_shapes():
    spec = PatternSpec()
    lab = contact_image(spec)
    rel, region = welded_maps(lab)
    with pytest.raises(GBError, match="index_regions: labels, relative, region must be 2-D arrays of one shape"):
        uw.index_regions(lab, rel, region[:, :1], 1, spec)       # (the compiled pass would read past it)
    with pytest.raises(GBError, match="split_row"):
        uw.split_row(lab, rel[:5], region, 0, spec)


def test_margin_px_of_arrays_equals_the_scalar_form():
    """index_regions' margin per region (scalars) and split_row's per pseudo-region (arrays)."""
    ev = np.array([0, 10, 300, 5000, 16280], np.int64)
    seen = np.array([0, 1, 2, 5, 27])
    for p in (uw.UnwrapParams(), uw.UnwrapParams(index_margin_events=0.0)):
        vec = uw._margin_px(p, ev[:, None], seen[None, :])
        ref = [[uw._margin_px(p, int(e), int(k)) for k in seen] for e in ev]
        assert isinstance(ref[0][0], float) and vec.shape == (5, 5)
        assert np.array_equal(vec, np.array(ref))
    assert uw._margin_px(uw.UnwrapParams(), 300, 2) == min(0.25 * 300, 1.5 * 300 / 4)


def test_run_starts_equals_the_label_changes():
    """kernels.run_starts (64 pixel pairs at a time from a bit mask of changes, the row's last block
    overlapping the one before; rows under 65 px pixel by pixel) against np.diff, on rows of every
    width around the block sizes and of long runs, noise and constant labels."""
    from gbscan import kernels

    rng = np.random.default_rng(3)
    widths = list(range(1, 140)) + [191, 192, 193, 255, 256, 257, 640, 641]
    for W in widths:
        for kind in range(3):
            if kind == 0:
                row = rng.integers(0, 4, W).astype(np.uint8)                       # noise
            elif kind == 1:
                row = np.repeat(rng.integers(0, 4, W), rng.integers(1, 9, W))[:W].astype(np.uint8)  # runs
            else:
                row = np.full(W, rng.integers(0, 4), np.uint8)                      # one label
            rs = np.full(W + 1, -7, np.int32)
            n = kernels.run_starts(row, rs)
            want = np.r_[0, np.flatnonzero(np.diff(row)) + 1]
            assert n == want.size, (W, kind)
            np.testing.assert_array_equal(rs[:n], want)
            assert rs[n] == W


# -- compiled group-bys against the numpy expressions they replaced ------------------------------
def _random_edges(rng, n_seg, n_edges):
    s = np.sort(rng.integers(1, n_seg, n_edges)).astype(np.int32)
    t = (s - rng.integers(1, 4, n_edges)).clip(0).astype(np.int32)
    n_agree = rng.integers(0, 12, n_edges).astype(np.int32)
    n_same = (n_agree + rng.integers(0, 4, n_edges)).astype(np.int32)
    off = (2 * rng.integers(-2, 3, n_edges)).astype(np.int32)
    return s, t, off, n_agree, n_same


def test_edge_order_equals_lexsort():
    from gbscan import kernels

    rng = np.random.default_rng(5)
    for n in (0, 1, 7, 300):
        _, _, _, n_agree, n_same = _random_edges(rng, 50, n)
        want = np.lexsort((n_same - n_agree, -n_agree)).astype(np.int64)
        np.testing.assert_array_equal(kernels.edge_order(n_agree, n_same), want)


def _link_believable_numpy(n, s_, t_, off_, n_agree, n_same, strong, believable, order, p):
    # the numpy form of link_believable that kernels.link_strips replaced
    from gbscan import kernels

    parent, pot = np.arange(n, dtype=np.int32), np.zeros(n, np.int32)
    size, conflicts = np.ones(n, np.int32), np.zeros(n, np.int32)
    ids = np.flatnonzero(strong)
    if ids.size == 0:
        return parent, pot, size, conflicts
    score = n_agree[ids].astype(np.int64) * 4096 - (n_same[ids] - n_agree[ids])
    best_up, best_dn = np.full(n, -1, np.int64), np.full(n, -1, np.int64)
    o = np.argsort(score, kind="stable")
    best_up[s_[ids[o]]] = ids[o]
    best_dn[t_[ids[o]]] = ids[o]
    mutual = np.zeros(s_.size, bool)
    mutual[ids] = (best_up[s_[ids]] == ids) & (best_dn[t_[ids]] == ids)
    kernels.link_segments(parent, pot, size, conflicts, s_, t_, off_, order, mutual, believable, False)
    root, P = kernels.resolve_roots(parent, pot)
    rest = ids[~mutual[ids]]
    if rest.size:
        A, B = root[s_[rest]].astype(np.int64), root[t_[rest]].astype(np.int64)
        delta = off_[rest].astype(np.int64) - P[s_[rest]] + P[t_[rest]]
        inside = A == B
        ci = rest[inside & (delta != 0)]
        np.add.at(conflicts, s_[ci], 1)
        np.add.at(conflicts, t_[ci], 1)
        A, B, delta = A[~inside], B[~inside], delta[~inside]
        swap = A > B
        A, B = np.where(swap, B, A), np.where(swap, A, B)
        delta = np.where(swap, -delta, delta)
        if A.size:
            key = (A * n + B) * 8192 + (delta + 4096)
            ukey, cnt = np.unique(key, return_counts=True)
            pair = ukey // 8192
            _, inv = np.unique(pair, return_inverse=True)
            tot = np.bincount(inv, weights=cnt)
            ok = (cnt >= p.n_ref_rows) & (cnt >= p.agree_frac * tot[inv])
            kernels.link_segments(parent, pot, size, conflicts, (pair // n).astype(np.int32),
                                  (pair % n).astype(np.int32), (ukey % 8192 - 4096).astype(np.int32),
                                  np.argsort(-cnt, kind="stable").astype(np.int64), ok, believable, False)
    return parent, pot, size, conflicts


def test_link_strips_equals_numpy_group_by():
    from gbscan import kernels

    rng = np.random.default_rng(11)
    for trial in range(60):
        n = int(rng.integers(2, 80))
        s_, t_, off_, n_agree, n_same = _random_edges(rng, n, int(rng.integers(0, 200)))
        believable = rng.random(n) < 0.8
        for p in (uw.UnwrapParams(), uw.UnwrapParams(n_ref_rows=1, agree_frac=0.5)):
            strong = (rng.random(s_.size) < 0.7) & believable[s_] & believable[t_]
            order = kernels.edge_order(n_agree, n_same)
            want = _link_believable_numpy(n, s_, t_, off_, n_agree, n_same, strong, believable, order, p)
            parent, pot = np.arange(n, dtype=np.int32), np.zeros(n, np.int32)
            size, conflicts = np.ones(n, np.int32), np.zeros(n, np.int32)
            kernels.link_strips(parent, pot, size, conflicts, s_, t_, off_, n_agree, n_same, order, strong,
                                believable, p.n_ref_rows, p.agree_frac)
            for got, ref in zip((parent, pot, size, conflicts), want):
                np.testing.assert_array_equal(got, ref, err_msg=str(trial))


def test_best_vote_offsets_equals_numpy_group_by():
    from gbscan import kernels

    rng = np.random.default_rng(7)
    H, W = 40, 60
    for trial in range(80):
        n_comp, nv = int(rng.integers(1, 30)), int(rng.integers(1, 400))
        vc = rng.integers(0, n_comp, nv).astype(np.int32)
        k = rng.integers(-3, 4, nv).astype(np.int64)
        good = rng.random(nv) < 0.8
        vv = rng.integers(0, H, nv).astype(np.int32)
        vl = np.where(rng.random(nv) < 0.5, rng.integers(0, W, nv), -1 - vv).astype(np.int32)
        n_all, tried, bc, bk, bcnt, bl, br = kernels.best_vote_offsets(vc, k, good, vl, vv, n_comp, H, W)
        # the numpy form link_components used
        assert tried == np.unique(vc).size
        np.testing.assert_array_equal(n_all, np.bincount(vc, minlength=n_comp))
        gc, gk, gl, gv = vc[good].astype(np.int64), k[good], vl[good].astype(np.int64), vv[good].astype(np.int64)
        if not gc.size:
            assert bc.size == 0
            continue
        kk0 = gk - gk.min()
        span = int(kk0.max()) + 1
        pair = gc * span + kk0
        pairs, cnt = np.unique(pair, return_counts=True)
        H1 = H + 1
        line_key = np.unique(pair * (H1 + W) + (gl + H1))
        _, n_lines = np.unique(line_key // (H1 + W), return_counts=True)
        _, n_rows = np.unique(np.unique(pair * H1 + gv) // H1, return_counts=True)
        pc, pk = pairs // span, pairs % span + gk.min()
        o = np.lexsort((-cnt, pc))
        b = o[np.r_[True, np.diff(pc[o]) != 0]]
        for got, ref in zip((bc, bk, bcnt, bl, br), (pc[b], pk[b], cnt[b], n_lines[b], n_rows[b])):
            np.testing.assert_array_equal(got, ref, err_msg=str(trial))
        # rows spanned (np.minimum.at / np.maximum.at)
        seg_comp = np.where(rng.random(3 * n_comp) < 0.3, -1, rng.integers(0, n_comp, 3 * n_comp)).astype(np.int32)
        seg_row = np.sort(rng.integers(0, H, seg_comp.size)).astype(np.int32)
        r_lo, r_hi = np.full(seg_comp.size, np.iinfo(np.int64).max, np.int64), np.full(seg_comp.size, -1, np.int64)
        cs = seg_comp >= 0
        np.minimum.at(r_lo, seg_comp[cs], seg_row[cs].astype(np.int64))
        np.maximum.at(r_hi, seg_comp[cs], seg_row[cs].astype(np.int64))
        np.testing.assert_array_equal(kernels.component_row_span(seg_comp, seg_row, bc), r_hi[bc] - r_lo[bc] + 1)


@pytest.mark.parametrize("compiled", [True, False])
def test_index_margin_stripes_indexes_a_sphere_whose_runner_up_contradicts_its_short_markers(compiled, monkeypatch):
    """UnwrapParams.index_margin_stripes (:func:`index_by_stripes`): the multi-object scene's
    lower sphere shows stripes 54-73 with markers 54, 59, 65, 70, the outer two short (its top and
    bottom) like its last stripe.  Offset +50 puts markers on 59 and 65 too (109, 115): it
    contradicts only the two short markers and the short last stripe (123 is a marker), fewer
    pixels than the pixel margin (1.5 marker events of the average marker) asks -- ambiguous.
    Counted in stripes every other offset contradicts at least 3 more than the best: indexed, at
    the right offset, up to a stripe margin of 3, not at 4.  Compiled and reference scoring agree."""
    monkeypatch.setattr(uw, "_SCORE_COMPILED", compiled)
    spec = PatternSpec()
    rows = 30
    lab = stripe_image(spec, 54, 20, rows=rows)
    rel = np.repeat(np.arange(20), 3)[None].repeat(rows, 0).astype(np.int32)  # true index = rel + 54
    reg = np.zeros(lab.shape, np.int32)
    for s in (0, 16, 19):           # markers 54 and 70 and stripe 73: 5 rows of 30
        reg[5:, 3 * s:3 * s + 3] = -1
    p = uw.UnwrapParams()
    idx = uw.index_regions(lab, rel, reg, 1, spec, p)
    assert idx.why[0] == uw.AMBIGUOUS and idx.offset[0] == 54 and idx.markers_seen[0] == 4
    assert idx.runner_up[0] - idx.mismatch[0] == 45 < uw._margin_px(p, idx.evidence[0], 4)
    assert idx.stripe_margin[0] == 3
    new = uw.index_by_stripes(idx, p)
    assert new.indexed[0] and new.why[0] == uw.STRIPE_OK and new.offset[0] == 54
    assert not idx.indexed[0] and idx.why[0] == uw.AMBIGUOUS  # a new index; the old one is kept
    assert uw.index_by_stripes(idx, uw.UnwrapParams(index_margin_stripes=3)).indexed[0]
    for q in (uw.UnwrapParams(index_margin_stripes=4), uw.UnwrapParams(index_margin_stripes=0)):
        assert uw.index_by_stripes(idx, q) is idx
    # only ambiguous regions: one whose markers do not fit, or too few, stays unindexed
    other = dataclasses.replace(idx, why=[uw.MISFIT])
    assert uw.index_by_stripes(other, p) is other
    # the stripes are counted at min_marker_px: with 16 px the short markers (15 px) are not seen,
    # nor can they contradict an offset
    idx = uw.index_regions(lab, rel, reg, 1, spec, uw.UnwrapParams(min_marker_px=16))
    assert idx.markers_seen[0] == 2 and not uw.index_by_stripes(idx, p).indexed[0]
    with pytest.raises(GBError, match="index_margin_stripes"):
        uw.UnwrapParams(index_margin_stripes=-1)


@pytest.mark.parametrize("compiled", [True, False])
def test_index_strong_stripe_px_indexes_a_region_one_stripe_apart_only_when_that_stripe_is_well_seen(compiled,
                                                                                                      monkeypatch):
    """UnwrapParams.index_strong_stripe_px (:func:`index_by_stripes`): stripes 50-60 show markers
    54 (on all 60 rows) and 59 (on its first ``vis`` rows).  The offsets that put a marker on 54
    and none elsewhere in 50-60 contradict only stripe 59's cyan: a stripe margin of 1, and 59's
    3 * ``vis`` cyan pixels are what tells them from the right offset (``stripe_strength``).  Under
    the pixel margin (1.5 marker events, 120 px here) the region is ambiguous; with 59 seen on 60
    pixels it is indexed, right, with 57 it is not.  Compiled and reference scoring agree."""
    monkeypatch.setattr(uw, "_SCORE_COMPILED", compiled)
    spec = PatternSpec()
    rows = 60
    lab = stripe_image(spec, 50, 11, rows=rows)
    rel = np.repeat(np.arange(11), 3)[None].repeat(rows, 0).astype(np.int32)   # true index = rel + 50
    p = uw.UnwrapParams()
    assert p.index_strong_stripe_px == 60
    for vis, take in ((20, True), (19, False)):
        reg = np.zeros(lab.shape, np.int32)
        reg[vis:, 27:30] = -1                 # marker 59 (relative 9) seen on its first vis rows
        idx = uw.index_regions(lab, rel, reg, 1, spec, p)
        assert idx.why[0] == uw.AMBIGUOUS and idx.offset[0] == 50 and idx.markers_seen[0] == 2
        assert idx.stripe_margin[0] == 1 and idx.stripe_strength[0] == 3 * vis
        assert idx.runner_up[0] - idx.mismatch[0] == 3 * vis < uw._margin_px(p, idx.evidence[0], 2)
        new = uw.index_by_stripes(idx, p)
        assert new.indexed[0] == take and (new.why[0] == uw.STRONG_OK) == take
        if take:
            assert new.offset[0] == 50 and not idx.indexed[0]   # a new index; the old one is kept
            # the threshold, and switched off (0): the region stays ambiguous
            assert uw.index_by_stripes(idx, uw.UnwrapParams(index_strong_stripe_px=61)) is idx
            assert uw.index_by_stripes(idx, uw.UnwrapParams(index_strong_stripe_px=0)) is idx
            # with a stripe margin of 1 asked for, the stripe margin indexes it as before
            assert uw.index_by_stripes(idx, uw.UnwrapParams(index_margin_stripes=1)).why[0] == uw.STRIPE_OK
    # marker 59 seen on every row: the pixel margin indexes the region, nothing left to do
    idx = uw.index_regions(lab, rel, np.zeros(lab.shape, np.int32), 1, spec, p)
    assert idx.why[0] == "ok" and idx.stripe_strength[0] == 3 * rows and uw.index_by_stripes(idx, p) is idx
    with pytest.raises(GBError, match="index_strong_stripe_px"):
        uw.UnwrapParams(index_strong_stripe_px=-1)


def test_index_tests_equals_np_select():
    rng = np.random.default_rng(2)
    n = 500
    status = rng.integers(0, 5, n).astype(np.int64)
    seen = rng.integers(0, 6, n).astype(np.int64)
    evidence = rng.integers(0, 3000, n).astype(np.int64)
    mismatch = rng.integers(0, 200, n).astype(np.int64)
    runner_up = mismatch + rng.integers(0, 900, n)
    for p in (uw.UnwrapParams(), uw.UnwrapParams(index_margin_events=0.0), uw.UnwrapParams(max_mismatch=0.01)):
        want = np.select([status < 3, status == 4, seen < p.min_markers, mismatch > p.max_mismatch * evidence,
                          runner_up - mismatch < uw._margin_px(p, evidence, seen)], [1, 2, 3, 4, 5], 0).astype(np.int8)
        got = uw._index_tests(p, status, seen, evidence, mismatch, runner_up)
        assert got.dtype == np.int8
        np.testing.assert_array_equal(got, want)
    assert uw._index_tests(uw.UnwrapParams(), [3], [4], [1000], [0], [900])[0] == 0


def _random_segments(seed, H=14, W=150):
    """Labels of noisy stripes (some rows shifted, a dark left part) and their row segments."""
    from gbscan import kernels

    rng = np.random.default_rng(seed)
    cols = np.array([G, B, G, B, C, G, B, G], np.uint8)
    x = (np.arange(W)[None, :] + rng.integers(0, 3, (H, 1))) // 4
    lab = cols[x % 8]
    noise = rng.random((H, W)) < 0.05
    lab[noise] = rng.integers(0, 4, int(noise.sum()))
    lab[:, :10] = N
    return rng, lab, kernels.row_segments(lab, 1, 1, 2, True)


def test_subpixel_junctions_equals_a_plain_loop():
    """kernels.subpixel_junctions (the four-pixel window unrolled) against the crossing search
    written out in Python, with the same float rounding (green|blue: a float32 difference)."""
    from gbscan import kernels

    for seed in range(4):
        rng, lab, r = _random_segments(seed)
        seg, rel, row, u0, u1, j0, j1, par, jseg, jua, jub, jla, jlb = r[:13]
        gn = rng.random(lab.shape).astype(np.float32)
        bn = rng.random(lab.shape).astype(np.float32)
        if seed % 2:
            gn, bn = (np.round(gn * 4) / 4).astype(np.float32), (np.round(bn * 4) / 4).astype(np.float32)
        ox = 7 * seed
        got = kernels.subpixel_junctions(gn, bn, row, jua, jub, jla, jlb, u0, u1, jseg, ox)
        want = np.full(jseg.size, np.nan, np.float32)
        for j in range(jseg.size):
            s, la, lb = jseg[j], jla[j], jlb[j]
            v = row[s]
            a, b = max(int(jua[j]) - 1, int(u0[s])), min(int(jub[j]) + 1, int(u1[s]))
            mid = 0.5 * ((int(jua[j]) + ox) + (int(jub[j]) + ox))
            best, bestd, f0 = np.nan, 1e9, 0.0
            for u in range(a, b + 1):
                g_, b_ = gn[v, u], bn[v, u]
                if la == C:
                    f = 0.5 - float(b_ if lb == G else g_)
                elif lb == C:
                    f = float(b_ if la == G else g_) - 0.5
                else:
                    f = float(b_ - g_) if la == G else float(g_ - b_)
                if u > a and f0 < 0.0 and f >= 0.0:
                    xx = (u - 1 + ox) + f0 / (f0 - f)
                    if abs(xx - mid) < bestd:
                        best, bestd = xx, abs(xx - mid)
                f0 = f
            want[j] = best
        assert got.tobytes() == want.tobytes()


def test_apply_cuts_equals_a_plain_split():
    """kernels.apply_cuts (the new image written row by row, the kept junctions gathered) against
    the split written out in Python, on segments in row order and on the same tables reversed (the
    general path: each piece painted over a copy in turn)."""
    from gbscan import kernels

    for seed in range(4):
        rng, lab, r = _random_segments(seed)
        seg, rel, row, u0, u1, j0, j1, par, jseg, jua, jub, jla, jlb, jrel = r[:14]
        jx = rng.random(jseg.size).astype(np.float32)
        cut = (rng.random(jseg.size) < 0.1).astype(np.uint8)
        for order in (slice(None), slice(None, None, -1)):
            tabs = [t[order].copy() for t in (row, u0, u1, j0, j1, par)]
            pieces, kept = [], []
            for s in range(tabs[0].size):
                v, a = tabs[0][s], tabs[1][s]
                first = len(kept)
                for j in range(tabs[3][s], tabs[4][s]):
                    if cut[j]:
                        pieces.append((v, a, jua[j], first, len(kept), tabs[5][s]))
                        a, first = jub[j], len(kept)
                    else:
                        kept.append((len(pieces), j))
                pieces.append((v, a, tabs[2][s], first, len(kept), tabs[5][s]))
            want_seg = seg.copy()
            for k, (v, a, b, _, _, _) in enumerate(pieces):
                want_seg[v, a:b + 1] = np.where(seg[v, a:b + 1] >= 0, k, want_seg[v, a:b + 1])
            idx = np.array([j for _, j in kept], np.int32)
            P = np.array(pieces, np.int64).T
            want = [want_seg, *[P[i].astype(np.int32) for i in range(5)], P[5].astype(np.uint8),
                    np.array([k for k, _ in kept], np.int32), jua[idx], jub[idx], jla[idx], jlb[idx], idx, jrel[idx], jx[idx]]
            args = (seg, *tabs, jseg, jua, jub, jla, jlb, cut)
            got = kernels.apply_cuts(*args, jrel, jx)
            assert len(got) == 15 and all(g.dtype == w.dtype and np.array_equal(g, w) for g, w in zip(got, want))
            got = kernels.apply_cuts(*args, jrel, np.empty(0, np.float32))      # no located boundaries
            assert got[14].size == 0 and all(np.array_equal(g, w) for g, w in zip(got[:14], want[:14]))


def test_vertical_votes_int64_keys_equal_the_sorted_form():
    """kernels.vertical_votes with more than 724 segments (keys past int32) and with few (int32
    keys) against the sort of all keys."""
    from gbscan import kernels

    for seed in range(3):
        _, lab, r = _random_segments(seed, H=40, W=200)
        seg, rel, n = r[0], r[1], r[2].size
        for n_seg in (n, n + 800):
            a = kernels.vertical_votes(lab, seg, rel, n_seg)
            b = kernels._vertical_votes_sorted(lab, seg, rel, n_seg)
            assert all(np.array_equal(x, y) for x, y in zip(a, b)) and a[0].size > 0


# -- the tilt-step cut (two surfaces welded along a row where their stripes line up) -------------
def _tilted_planes(tilt_left, tilt_right, weld_rows, seam=40, rows=60, width=88, period=8.0, noise=0.0, seed=0,
                   line_row=30):
    """Labels (rows, width) of green/blue stripes ``period`` px wide (boundaries every
    ``period / 2`` px): left of column ``seam`` leaning ``tilt_left`` camera px per row, right of
    it ``tilt_right``, lined up in row ``line_row`` (their stripes meet there at a whole stripe,
    so the spacing across the seam is the rows' own within 0.1 px a row of it).  The rows in
    ``weld_rows`` cross the seam; every other row has 3 unlabelled px there (a silhouette the row
    was parted at).  Returns the labels and a ``j_x`` function giving each junction its true
    boundary position (plus ``noise`` px, seeded) for step 1's segments."""
    half = period / 2

    def model(u, v):
        return tilt_left * v if u < seam else tilt_right * v + (tilt_left - tilt_right) * line_row

    lab = np.zeros((rows, width), np.uint8)
    for v in range(rows):
        for u in range(width):
            k = int(np.floor((u - model(u, v)) / half))
            lab[v, u] = G if k % 2 == 0 else B
        if v not in weld_rows:
            lab[v, seam - 1:seam + 2] = N

    return lab, _true_positions(model, half, noise, seed)


def _true_positions(model, half, noise, seed):
    """A ``j_x`` function for step 1's segments of labels drawn from ``model(u, v)`` (the
    stripes' offset at column u of row v, boundaries every ``half`` px): each junction's true
    boundary position, plus ``noise`` px (seeded)."""
    def jx(segs):
        rng = np.random.default_rng(seed)
        out = np.empty(segs.j_seg.size, np.float64)
        for j in range(segs.j_seg.size):
            v, a = int(segs.row[segs.j_seg[j]]), int(segs.j_ua[j])
            off = model(a + 1, v)
            out[j] = off + np.floor((a + 1 - off) / half) * half   # the boundary in (a, a + 1]
        return out + noise * rng.standard_normal(out.size)
    return jx


def _memo(n):
    # kernels.tilt_step_cuts' memo: tilts, followed, tested
    return np.full(n, np.nan), np.zeros(n, np.uint8), np.zeros(n, np.uint8)


def _tilt_cuts(lab, jx, **kw):
    from gbscan import kernels

    p = dataclasses.replace(uw.UnwrapParams(), **kw)
    segs = uw.unroll_rows(lab)
    segs.j_x = jx(segs).astype(np.float32)
    cut = uw._tilt_cut_mask(segs, lab.shape, p)
    cut = np.zeros(segs.j_seg.size, np.uint8) if cut is None else cut
    return segs, cut, kernels


def test_junction_tilts_recover_the_stripes_lean():
    """kernels.junction_tilts: each boundary followed up and down the rows; on exact positions the
    least-squares slope is the stripes' lean on either side of the seam (0.1 and 0 px per row),
    and the fit over the rows followed equals np.polyfit of the same track."""
    lab, jx = _tilted_planes(0.1, 0.0, weld_rows=range(60))
    segs = uw.unroll_rows(lab)
    x = jx(segs)
    from gbscan import kernels

    t = kernels.junction_tilts(x, segs.j_seg, segs.row, segs.j_la, segs.j_lb, lab.shape[0], 6, 1.0, 5)
    v = segs.row[segs.j_seg]
    inner = (v >= 6) & (v < 54)
    left = inner & (x < 30)
    right = inner & (x > 50)
    assert left.sum() > 300 and right.sum() > 300
    np.testing.assert_allclose(t[left], 0.1, atol=1e-9)
    np.testing.assert_allclose(t[right], 0.0, atol=1e-9)
    # near the top rows fewer rows are followed (none above row 0): the same fit, fewer points
    j = int(np.flatnonzero((v == 2) & (x > 8) & (x < 30))[0])
    track = [(2, x[j])]
    for vv in range(3, 9):
        c = np.flatnonzero((v == vv) & (segs.j_la == segs.j_la[j]) & (segs.j_lb == segs.j_lb[j]))
        k = c[np.argmin(np.abs(x[c] - track[-1][1]))]
        track.append((vv, x[k]))
    for vv in (1, 0):
        c = np.flatnonzero((v == vv) & (segs.j_la == segs.j_la[j]) & (segs.j_lb == segs.j_lb[j]))
        k = c[np.argmin(np.abs(x[c] - track[0][1]))]
        track.insert(0, (vv, x[k]))
    vv, xx = np.array(track).T
    assert t[j] == pytest.approx(np.polyfit(vv, xx, 1)[0], abs=1e-12)


def test_tilt_step_cuts_part_the_welded_rows_only():
    """uw.UnwrapParams.tilt_step: two planes, the left leaning 0.1 px per row, the right 0, their
    stripes lined up; rows 28-33 cross the seam (welded: one segment each), the others are parted
    there.  Each welded row is cut at the seam and nowhere else.  The same rows are not cut when
    both planes lean alike, when no row around is parted (one surface bending: a crease), or with
    ``tilt_step=0``; fewer parted rows than ``tilt_break_min`` leave them too."""
    weld = range(28, 34)
    lab, jx = _tilted_planes(0.1, 0.0, weld, noise=0.02)
    segs, cut, _ = _tilt_cuts(lab, jx)
    v = segs.row[segs.j_seg]
    xs = segs.j_ua.astype(float)
    assert set(v[cut == 1]) == set(weld)
    assert np.all(np.abs(xs[cut == 1] - 40) <= 5)
    for rows in weld:
        assert 1 <= cut[v == rows].sum() <= 3
    assert _tilt_cuts(lab, jx, tilt_step=0.0)[1].sum() == 0
    assert _tilt_cuts(lab, jx, tilt_break_min=17, tilt_follow_rows=0)[1].sum() == 0   # 15 parted rows around row 30
    # (the follow-on cut of a line's welded end cuts them then: rows 0-27 parted at the seam)
    assert set(v[_tilt_cuts(lab, jx, tilt_break_min=17)[1] == 1]) == set(weld)
    lab2, jx2 = _tilted_planes(0.1, 0.1, weld, noise=0.02)
    assert _tilt_cuts(lab2, jx2)[1].sum() == 0
    lab3, jx3 = _tilted_planes(0.1, 0.0, range(60), noise=0.02)
    assert _tilt_cuts(lab3, jx3)[1].sum() == 0
    # through unwrap: the welded rows' segments end at the seam (lined up there: the spacing cut
    # leaves them), the stats count the cuts
    def parted(**kw):
        un = uw.unwrap(lab, uw.UnwrapParams(**kw), locate=lambda s: jx(s).astype(np.float32))
        return [r for r in weld if (un.segments.row == r).sum() >= 2], un.stats["tilt_cuts"]

    assert parted() == (list(weld), int(cut.sum()))
    assert parted(tilt_step=0.0) == ([], 0)


def _slanted_silhouette(tilt_left, tilt_right, parted_rows, end_row=48, slant=-1.5, seam_row=44, rows=60,
                        width=120, period=8.0, noise=0.02, seed=0):
    """Labels like :func:`_tilted_planes`, the seam slanting: at column ``seam_row``'s 70 plus
    ``slant`` px a row.  The left surface ends at ``end_row`` (the right one fills the rows below
    it, as a wall below an object); the rows in ``parted_rows`` have 3 unlabelled px at the seam,
    the others above ``end_row`` cross it, the stripes lined up in row ``seam_row``."""
    half = period / 2

    def seam(v):
        return 70 + slant * (v - seam_row)

    def model(u, v):
        left = v < end_row and u < seam(v)
        return tilt_left * v if left else tilt_right * v + (tilt_left - tilt_right) * seam_row

    lab = np.zeros((rows, width), np.uint8)
    for v in range(rows):
        for u in range(width):
            k = int(np.floor((u - model(u, v)) / half))
            lab[v, u] = G if k % 2 == 0 else B
        if v in parted_rows:
            c = int(round(seam(v)))
            lab[v, c - 1:c + 2] = N

    return lab, _true_positions(model, half, noise, seed), seam


def test_tilt_follow_cuts_follow_a_slanted_silhouette_past_its_parted_rows():
    """uw.UnwrapParams.tilt_follow_rows (kernels.tilt_follow_cuts): a silhouette slanting 1.5 px a
    row, parted in rows 0-39, its last rows 40-47 welded across it (the near surface leaning 0.2
    px a row, the far one 0; the far one alone below).  tilt_step_cuts alone leaves them (the
    line leaves their column within 2 rows); the follow-on cut cuts each of them once, at the
    junction next to the seam, and nothing else (the last two may stay: their boundaries' tracks run on into
    the far surface below, which halves their lean).  Not when both sides lean alike, nor when the parted line
    above them is shorter than ``tilt_follow_rows`` (rows 36-39 only, the rows above crossing
    too: a crease); the same upwards (the frame flipped)."""
    weld = range(40, 48)
    lab, jx, seam = _slanted_silhouette(0.2, 0.0, range(0, 40))
    segs, cut, _ = _tilt_cuts(lab, jx, tilt_follow_rows=0)
    assert cut.sum() == 0
    segs, cut, _ = _tilt_cuts(lab, jx)
    v = segs.row[segs.j_seg]
    got = v[cut == 1].tolist()
    assert len(got) == len(set(got)) and set(range(40, 46)) <= set(got) <= set(weld)
    assert np.all(np.abs(segs.j_ua[cut == 1] + 0.5 - seam(v[cut == 1])) <= 4.5)   # (junctions 4 px apart)
    assert _tilt_cuts(lab, jx, tilt_step=0.0)[1].sum() == 0
    lab2, jx2, _ = _slanted_silhouette(0.2, 0.2, range(0, 40))
    assert _tilt_cuts(lab2, jx2)[1].sum() == 0
    lab3, jx3, _ = _slanted_silhouette(0.2, 0.0, range(36, 40))
    assert _tilt_cuts(lab3, jx3)[1].sum() == 0
    segs3, cut3, _ = _tilt_cuts(lab3, jx3, tilt_follow_rows=4)
    assert set(segs3.row[segs3.j_seg][cut3 == 1]) >= set(range(40, 46))
    # upwards: the frame and the positions flipped top to bottom
    flip = lab[::-1].copy()

    def jx_flip(s):
        s2 = dataclasses.replace(s, row=(lab.shape[0] - 1 - s.row).astype(s.row.dtype))
        return jx(s2)
    segs_f, cut_f, _ = _tilt_cuts(flip, jx_flip)
    vf = lab.shape[0] - 1 - segs_f.row[segs_f.j_seg]
    assert sorted(vf[cut_f == 1].tolist()) == sorted(got)
    # through unwrap: each welded row is two segments or more, the stats count the cuts
    un = uw.unwrap(lab, uw.UnwrapParams(), locate=lambda s: jx(s).astype(np.float32))
    assert all((un.segments.row == r).sum() >= 2 for r in got)
    assert un.stats["tilt_cuts"] >= len(got)
    un0 = uw.unwrap(lab, uw.UnwrapParams(tilt_follow_rows=0), locate=lambda s: jx(s).astype(np.float32))
    assert un0.stats["tilt_cuts"] == 0


def test_tilt_step_cuts_count_rows_parted_by_a_cut_where_the_tilt_steps_across_it():
    """kernels.tilt_step_cuts' ``pre``: rows parted by the spacing or bridge cut (junctions cut
    already) count as parted where the tilt steps across the cut junction too.  The two planes
    crossing the seam in every row: none cut without ``pre`` (a crease); with the seam junctions
    of the rows outside 28-33 given as cut, rows 28-33 are cut at the seam, and nothing away from
    it (a row whose given cut is a junction beside the step may be cut at the step as well);
    given where both planes lean alike (no step across those cuts), nothing."""
    from gbscan import kernels

    weld = range(28, 34)

    def cuts(tilt_right, with_pre):
        lab, jx = _tilted_planes(0.1, tilt_right, range(60), noise=0.02)
        segs = uw.unroll_rows(lab)
        x = jx(segs)
        v = segs.row[segs.j_seg]
        pre = np.zeros(x.size, np.uint8)
        if with_pre:
            for r in set(range(60)) - set(weld):
                k = np.flatnonzero(v == r)
                pre[k[np.argmin(np.abs(x[k] - 40.0))]] = 1
        H, W = lab.shape
        c = kernels.tilt_step_cuts(x, segs.j_seg, segs.row, segs.u0, segs.u1, segs.j0, segs.j1, segs.j_ua, segs.j_la,
                                   segs.j_lb, H, W, 6, 1.0, 10, 3, 10, 4, 3, 0.03, 6.0, 0.01, pre, *_memo(x.size))
        return set(v[c == 1]), segs.j_ua[c == 1]

    assert cuts(0.0, False)[0] == set()
    rows, cols = cuts(0.0, True)
    assert rows >= set(weld) and np.all(np.abs(cols - 40) <= 6)   # (boundaries 4 px apart)
    assert cuts(0.1, True)[0] == set()


def test_tilt_step_equals_the_median_test():
    """kernels._tilt_step against numpy medians and MADs: a step of 0.08 px per row between two
    flat sides is cut, a steady ramp of the same total change (a curved surface) is not, nor a
    step under ``step``, nor sides with fewer than 3 finite tilts."""
    from gbscan import kernels

    buf = np.empty(4)
    rng = np.random.default_rng(3)

    def ref(t, i, window=4, min_n=3, step=0.03, z=6.0, floor=0.01):
        L, R = t[max(0, i - window):i], t[i + 1:i + 1 + window]
        L, R = L[np.isfinite(L)], R[np.isfinite(R)]
        if L.size < min_n or R.size < min_n:
            return False
        d = abs(np.median(R) - np.median(L))
        mad = max(np.median(np.abs(L - np.median(L))), np.median(np.abs(R - np.median(R))))
        return bool(d > step and d > z * max(1.4826 * mad, floor))

    cases = {
        "step": (np.r_[np.full(5, 0.08), 0.04, np.zeros(5)] + 0.002 * rng.standard_normal(11), True),
        "ramp": (np.linspace(0.08, 0.0, 11), False),
        "small": (np.r_[np.full(5, 0.02), 0.01, np.zeros(5)], False),
        "few": (np.r_[np.full(5, 0.08), 0.04, np.zeros(2), np.full(3, np.nan)], False),
    }
    for name, (t, want) in cases.items():
        got = kernels._tilt_step(t, 0, t.size, 5, 4, 3, 0.03, 6.0, 0.01, buf)
        assert got == ref(t, 5) == want, name
    for _ in range(300):
        t = np.where(rng.random(11) < 0.15, np.nan, rng.normal(0, 0.05, 11) + np.r_[np.zeros(5), 0, np.full(5, 0.1)]
                     * rng.integers(0, 2))
        assert kernels._tilt_step(t, 0, 11, 5, 4, 3, 0.03, 6.0, 0.01, buf) == ref(t, 5)


def test_tilt_step_cuts_tracks_equal_junction_tilts():
    """kernels.tilt_step_cuts computes tilts only around candidate junctions, searching each next
    row; with every junction a candidate (``break_min`` 0) its cuts equal the step test run on
    kernels.junction_tilts (every track at once) — on noisy positions and labels."""
    from gbscan import kernels

    lab, jx = _tilted_planes(0.12, -0.03, range(20, 40), noise=0.05, seed=1)
    rng = np.random.default_rng(2)
    flip = rng.random(lab.shape) < 0.01
    lab[flip] = np.where(lab[flip] == G, B, G)
    segs = uw.unroll_rows(lab)
    x = jx(segs)
    x[rng.random(x.size) < 0.03] = np.nan
    H, W = lab.shape
    got = kernels.tilt_step_cuts(x, segs.j_seg, segs.row, segs.u0, segs.u1, segs.j0, segs.j1, segs.j_ua, segs.j_la,
                                 segs.j_lb, H, W, 6, 1.0, 10, 3, 0, 4, 3, 0.03, 6.0, 0.01, np.zeros(0, np.uint8),
                                 *_memo(x.size))
    t = kernels.junction_tilts(x, segs.j_seg, segs.row, segs.j_la, segs.j_lb, H, 6, 1.0, 5)
    want = np.zeros_like(got)
    buf = np.empty(4)
    for s in range(segs.n):
        j0, j1 = segs.j0[s], segs.j1[s]
        if j1 - j0 < 7:
            continue
        for i in range(j0 + 3, j1 - 3):
            want[i] = kernels._tilt_step(t, j0, j1, i, 4, 3, 0.03, 6.0, 0.01, buf)
    assert want.sum() >= 5
    np.testing.assert_array_equal(got, want)


def test_tilt_params_are_validated():
    for kw in (dict(tilt_step=-0.1), dict(tilt_z=-1.0), dict(tilt_rows=1), dict(tilt_window=2),
               dict(tilt_break_rows=0), dict(tilt_break_min=21), dict(tilt_break_min=-1)):
        with pytest.raises(GBError, match="tilt_"):
            uw.UnwrapParams(**kw)
    uw.UnwrapParams(tilt_step=0.0, tilt_break_min=0)


def test_index_margin_study_records_regions_against_the_truth(capsys):
    """scripts/index_margin_study.py: each scored region's true offset (the most common one of its
    pixels), its purity and stripe margin, and the table of what each stripe margin would index."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "scripts" / "index_margin_study.py"
    spec_ = importlib.util.spec_from_file_location("index_margin_study", path)
    mod = importlib.util.module_from_spec(spec_)
    spec_.loader.exec_module(mod)
    spec = PatternSpec()
    rows = 30
    lab = stripe_image(spec, 54, 20, rows=rows)
    rel = np.repeat(np.arange(20), 3)[None].repeat(rows, 0).astype(np.int32)
    reg = np.zeros(lab.shape, np.int32)
    for s in (0, 16, 19):
        reg[5:, 3 * s:3 * s + 3] = -1
    reg[:, 57:] = 1                       # a second region: the last stripes, 20 px wide columns
    idx = uw.index_regions(lab, rel, reg, 2, spec, uw.UnwrapParams())
    truth = (rel + 54) * 8.0 + 3.5        # true column: stripe (rel + 54), mid-stripe
    truth[:10, 40:57] += 12 * 8           # a third of region 0's upper rows on another surface
    recs = mod.region_records(lab, rel, reg, idx, truth, spec.stripe_px)
    assert [r["true"] for r in recs] == [54, 54] and recs[0]["best"] == idx.offset[0]
    assert recs[0]["why"] == idx.why[0] and recs[0]["stripes"] == idx.stripe_margin[0]
    m0 = (reg == 0)
    assert recs[0]["px"] == m0.sum() and recs[0]["purity"] == pytest.approx(1 - (m0[:10, 40:57]).sum() / m0.sum())
    assert [r["strength"] for r in recs] == idx.stripe_strength.tolist()
    mod.report(recs + [dict(recs[0], why="ambiguous offset", stripes=2, purity=1.0, best=60, true=54),
                       dict(recs[0], why="ambiguous offset", stripes=1, strength=70, best=60, true=54)])
    out = capsys.readouterr().out
    margin1 = out.split("ambiguous, stripe margin 1: 1 scorings")[1].split("indexed by the pixel margin")[0]
    table1 = {ln.split()[1]: re.findall(r"(\d+) \(\s*\d+\)", ln) for ln in margin1.splitlines()
              if ln.strip().startswith(">=")}   # scorings indexed, of them wrong
    assert table1["60"] == ["1", "1"] and table1["80"] == ["0", "0"]   # 60 px would index it, wrongly
    one_surface = out.split("ambiguous, one surface: 1 scorings")[1].split("ambiguous, two surfaces")[0]
    table = {ln.split()[1]: [ln.split()[2], ln.split()[5]] for ln in one_surface.splitlines()
             if ln.strip().startswith(">=")}   # scorings indexed, of them wrong
    assert table["2"] == ["1", "1"] and table["3"] == ["0", "0"]   # margin 2 would index it, wrongly
    assert mod.main(["--set", "bogus"]) == 2
