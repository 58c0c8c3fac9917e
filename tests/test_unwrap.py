"""The seven unwrapping steps and the marker indexing on small synthetic label images."""
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


def test_link_params_are_validated():
    with pytest.raises(GBError, match="link_tol_px"):
        uw.UnwrapParams(link_tol_px=5.0)
    with pytest.raises(GBError, match="link_votes"):
        uw.UnwrapParams(link_votes=-1)


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
