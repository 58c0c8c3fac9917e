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
