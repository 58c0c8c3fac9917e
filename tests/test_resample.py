"""Frames whose stripes are wide in the camera (a camera with more pixels than the paper's):
the decoder measures the stripe width from the colour runs, decodes the frame shrunk to the
width its rules are validated at, and expands the result back to every pixel."""
from __future__ import annotations

import dataclasses
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from gbscan import kernels, sim
from gbscan.decode import (NO_BOUNDARY, RIM, DecodeParams, choose_resample, decode, frame_stripe_px, gamma_lut,
                           resample_size, shrink_frame)
from gbscan.errors import GBError
from gbscan.pattern import PatternSpec, render_pattern

SPEC = PatternSpec()
_path = Path(__file__).resolve().parents[1] / "scripts" / "resample_study.py"
_spec = importlib.util.spec_from_file_location("resample_study", _path)
study = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(study)


def render(scene: str, scale: float, seed: int = 0):
    """A frame of the paper rig whose camera has ``scale`` times its pixels (same field of view)."""
    cond = dataclasses.replace(sim.preset("typical"), supersample=1 if scale > 1 else 3)
    rig = study.scaled_rig(scale) if scale != 1 else sim.paper_rig()
    return sim.render(rig, getattr(sim.scenes, scene)(), render_pattern(SPEC), cond, seed=seed)


@pytest.fixture(scope="module")
def wide():
    """The multi-object scene through a 1280x960 camera: 7.2-7.9 camera px per stripe."""
    return render("multi_object", 2.0)


def true_stripe_px(r) -> float:
    return SPEC.stripe_px / float(np.nanmedian(np.abs(np.diff(r.proj_xy[..., 0], axis=1))))


def scores(sm, r) -> tuple[float, int]:
    """Reported % of the lit non-edge pixels; pixels half a stripe or more off, off depth edges."""
    truth = r.proj_xy[..., 0]
    cand = r.lit & ~r.depth_edge
    ok = sm.valid & np.isfinite(truth) & ~r.depth_edge
    wrong = int((np.abs(sm.column - truth)[ok] >= SPEC.stripe_px / 2).sum())
    return 100.0 * float((sm.valid & cand).sum()) / float(cand.sum()), wrong


def test_stripe_width_from_the_colour_runs(wide):
    """frame_stripe_px reads the camera px per stripe from the colour runs alone, within 10 % of
    the truth's median, at the paper's camera and at twice its pixels."""
    for r in (render("plane", 1.0), render("sphere", 1.0), wide):
        px, n = frame_stripe_px(r.image)
        assert n >= 200
        assert px == pytest.approx(true_stripe_px(r), rel=0.10)
    # no stripes, no measure: a uniform frame and a black one
    assert frame_stripe_px(np.full((64, 64, 3), 120, np.uint8)) == (0.0, 0)
    assert frame_stripe_px(np.zeros((64, 64, 3), np.uint8)) == (0.0, 0)


def _stripe_run_px_plain(img, lut, step, level, floor, max_run, quantile):
    # kernels.stripe_run_px written out pixel by pixel over every row (no skipping of dark ends)
    rows = img[::step]
    lit = [(float(lut[p[1]]), float(lut[p[2]])) for row in rows for p in row]
    s = [(g, b) for g, b in lit if np.float32(g) + np.float32(b) > floor]
    sg, sb = 0.0, 0.0
    for g, b in s:
        sg += g
        sb += b
    if not s or sg <= 0 or sb <= 0:
        return 0.0, 0
    kg, kb = len(s) / sg, len(s) / sb
    hist = [0] * (max_run + 1)
    for row in rows:
        state, start = 0, -1
        for u, p in enumerate(row):
            g, b = lut[p[1]], lut[p[2]]
            if g + b <= floor:
                state, start = 0, -1
                continue
            g, b = g * kg, b * kb
            cur = 1 if g - b > level * (g + b) else -1 if g - b < -level * (g + b) else state
            if cur != state:
                if state != 0 and start >= 0 and u - start <= max_run:
                    hist[u - start] += 1
                start, state = (u if state != 0 else -1), cur
    total = sum(hist)
    if total == 0:
        return 0.0, 0
    half, acc = quantile * total, 0
    for r in range(max_run + 1):
        if acc + hist[r] >= half:
            return r - 0.5 + (half - acc) / hist[r], total
        acc += hist[r]
    return float(max_run), total


def test_stripe_run_px_kernel_matches_a_plain_walk():
    """kernels.stripe_run_px (rows walked between their first and last pixel that may be lit) gives
    the plain walk's result bit for bit: stripes of green and blue in a dark frame, with dark
    ends of different lengths, random widths and noise."""
    rng = np.random.default_rng(5)
    lut = gamma_lut(2.2)
    for _ in range(12):
        H, W = int(rng.integers(5, 40)), int(rng.integers(7, 90))
        img = rng.integers(0, 25, (H, W, 3), dtype=np.uint8)
        x0, x1 = sorted(rng.integers(0, W + 1, 2))
        green = (np.arange(W) // int(rng.integers(1, 8))) % 2 == 0
        lvl = rng.integers(20, 256, (H, W))
        box = np.zeros(W, bool)
        box[x0:x1] = True
        img[:, box & green, 1] = lvl[:, box & green]
        img[:, box & ~green, 2] = lvl[:, box & ~green]
        step = int(rng.integers(1, 4))
        got = kernels.stripe_run_px(img, lut, step, 0.1, 8.0, 255, 0.4)
        assert got == _stripe_run_px_plain(img, lut, step, 0.1, 8.0, 255, 0.4)


def test_paper_frames_are_decoded_as_they_are():
    """At the paper's 3.5-4 px per stripe nothing is resampled: the automatic decode equals the
    decode with resampling off, array for array."""
    for scene in ("head", "multi_object"):
        r = render(scene, 1.0)
        f, px = choose_resample(r.image)
        assert f == 1.0 and 3.0 < px < 5.0
        a = decode(r.image, SPEC)
        b = decode(r.image, SPEC, DecodeParams(resample=1.0))
        assert "resample" not in a.stats and a.stats["stripe_camera_px"] == pytest.approx(px, abs=0.01)
        for name in ("column", "stripe", "confidence", "mask", "relative", "region", "labels", "column_relative"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def test_wide_stripes_are_decoded_shrunk(wide):
    """Through a camera with twice the paper's pixels the decoder as it is loses part of the scene
    (the multi-object scene, seed 0: 77.1 % reported, 67.1 % before misfit regions were split at
    a contact row, ``UnwrapParams.split_rows``, against 80.5 % shrunk) and, without the confirmed
    marker bound of its row check (``UnwrapParams.conflict_confirm``, which now rejects them, as
    does ``conflict_extend`` alone, and without the piece rules, ``piece_check_px`` and
    ``piece_alone``, which mask most of them too), put 97 pixels on wrong stripes; shrunk to the
    validated width it reports more of the scene and none wrong, at every pixel of the frame."""
    from gbscan.unwrap import UnwrapParams

    auto = decode(wide.image, SPEC)
    never = decode(wide.image, SPEC, DecodeParams(resample=1.0, piece_check_px=0, piece_alone=False,
                                                  unwrap=UnwrapParams(conflict_confirm=False, conflict_extend=False)))
    assert scores(decode(wide.image, SPEC, DecodeParams(resample=1.0)), wide)[1] == 0
    assert auto.column.shape == wide.image.shape[:2]
    assert 1.8 < auto.stats["resample"] < 2.3 and auto.stats["decoded_size"] == list(
        resample_size(wide.image.shape, auto.stats["resample"]))[::-1]
    cover_auto, wrong_auto = scores(auto, wide)
    cover_never, wrong_never = scores(never, wide)
    assert wrong_never > 20 and cover_never < cover_auto - 2          # the failure this guards against
    assert wrong_auto == 0 and cover_auto > 78
    # the outputs agree with each other at every pixel
    v = auto.valid
    assert np.isfinite(auto.column[v]).all() and (auto.stripe[v] >= 0).all() and (auto.confidence[v] > 0).all()
    assert (auto.stripe[v] == np.floor((auto.column[v] + 0.5) / SPEC.stripe_px)).all()
    assert np.isnan(auto.column[~v]).all() and (auto.stripe[~v] == -1).all() and (auto.confidence[~v] == 0).all()
    assert (auto.region[v] >= 0).all()
    assert auto.stats["pixels"] == v.size and auto.stats["reported"] == int(v.sum())
    # a fixed factor is taken as given; the same for the CLI's spelling
    fixed = decode(wide.image, SPEC, DecodeParams(resample=2.0))
    assert fixed.stats["resample"] == 2.0 and "stripe_camera_px" not in fixed.stats
    from gbscan.commands.decode import resample_value

    assert (resample_value("auto"), resample_value("never"), resample_value("2.5")) == (0.0, 1.0, 2.5)



def test_a_stream_reuses_the_resampling_factor(wide):
    """Frames of one stream (``StreamMemo``) measure the stripes' width once: the next frame takes
    the factor (and the shrunk frame's aberration fit) from the first -- the sphere at its distance
    would choose 1.75 alone, it takes the multi-object scene's 2 -- and decodes to the same maps
    bit for bit as with that factor given; a fixed ``resample`` measures nothing."""
    from gbscan.decode import StreamMemo

    other = render("sphere", 2.0)
    memo = StreamMemo()
    a = decode(wide.image, SPEC, memo=memo)
    b = decode(other.image, SPEC, memo=memo)
    assert a.stats["stream"] == {"lateral_ca": "measured", "resample": "measured"}
    assert b.stats["stream"] == {"lateral_ca": "reused (measured 1 frame before)",
                                 "resample": "reused (measured 1 frame before)"}
    assert decode(other.image, SPEC).stats["resample"] == 1.75
    ref = decode(other.image, SPEC, DecodeParams(resample=a.stats["resample"]))
    assert b.stats["resample"] == a.stats["resample"] == 2.0
    assert not ref.stats["lateral_ca"]["corrected"] and not a.stats["lateral_ca"]["corrected"]
    for f in ("column", "stripe", "confidence", "mask"):
        assert np.array_equal(getattr(b, f), getattr(ref, f), equal_nan=True), f
    fixed = decode(other.image, SPEC, DecodeParams(resample=2.0), memo=StreamMemo())
    assert "resample" not in fixed.stats["stream"]



def test_a_stream_keeps_the_aberration_fit_in_the_full_frames_pixels():
    """A shrunk decode of a lit window keeps its aberration fit in the full frame's px (the window
    and the ratio taken out) and reads it back in its own: the blue offset a full pixel x gets is
    the same whichever window stored and read it (shrunk px: ratio times smaller), and the sphere
    of a 1280x960 camera whose blue image is 2 px larger at the corners decoded twice through one
    memo corrects the second time with the first fit, to the same columns within 1e-3 px."""
    from gbscan.decode import StreamMemo, _ShrunkMemo

    memo = StreamMemo()
    key = ((10, 20), 5.0, 0.1)
    _ShrunkMemo(memo, (960, 1280), 2.0, 300, 2.0).put("lateral_ca", key, ({"k": 1}, (0.05, 4e-4)))
    (_, (a2, k2)), _ = _ShrunkMemo(memo, (960, 1280), 2.0, 100, 1.98).get("lateral_ca", key)
    for x in (120.0, 700.0, 1200.0):
        xs1, xs2 = (x - 300 - 0.5) / 2.0, (x - 100 - 0.49) / 1.98
        assert 1.98 * (a2 + k2 * xs2) == pytest.approx(2.0 * (0.05 + 4e-4 * xs1), abs=1e-12)
    assert _ShrunkMemo(memo, (960, 1280), 1.75, 0, 1.75).get("lateral_ca", key) == (None, 0)   # another factor
    cond = dataclasses.replace(sim.preset("typical"), supersample=1, lateral_ca_px=2.0)
    r = sim.render(study.scaled_rig(2.0), sim.scenes.sphere(), render_pattern(SPEC), cond, seed=0)
    memo = StreamMemo()
    a = decode(r.image, SPEC, memo=memo)
    b = decode(r.image, SPEC, memo=memo)
    assert a.stats["lateral_ca"]["corrected"] and a.stats["decoded_window"] is not None
    assert b.stats["stream"]["lateral_ca"].startswith("reused") and a.stats["resample"] == b.stats["resample"]
    assert np.array_equal(a.valid, b.valid) and scores(b, r)[1] == 0
    assert float(np.nanmax(np.abs(a.column - b.column))) < 1e-3


def test_working_volume_follows_the_shrunk_frame(wide):
    """A working volume (stripe bounds per frame pixel) is carried to the shrunk frame: bounds
    that rule nothing out change nothing; bounds that exclude every stripe drop every region."""
    H, W = wide.image.shape[:2]
    free = np.full((2, H, W), np.nan, np.float32)
    a = decode(wide.image, SPEC)
    b = decode(wide.image, SPEC, stripe_range=free)
    np.testing.assert_array_equal(a.mask, b.mask)
    np.testing.assert_array_equal(a.column, b.column)
    none = np.stack([np.full((H, W), 500.0, np.float32), np.full((H, W), 501.0, np.float32)])
    c = decode(wide.image, SPEC, stripe_range=none)
    assert c.stats["reported"] == 0


def test_working_volume_bounds_follow_the_nearest_full_pixel():
    """The stripe bounds of a shrunk frame's pixel are those of the full pixel under its centre
    (the one nearest to it), for exact and non-integer factors."""
    from gbscan.decode import _shrink_range

    rng = np.random.default_rng(3)
    H, W = 96, 128
    sr = rng.random((2, H, W)).astype(np.float32)
    sr[0, 5, 7] = np.nan
    for factor in (1.75, 2.0, 2.5):
        h, w = resample_size((H, W), factor)
        out = _shrink_range(sr, h, w)
        assert out.shape == (2, h, w) and out.dtype == np.float32 and out.flags.c_contiguous
        for i, j in ((0, 0), (h - 1, w - 1), (h // 2, w // 3), (3, 4)):
            v, u = min(int((i + 0.5) * H / h), H - 1), min(int((j + 0.5) * W / w), W - 1)
            np.testing.assert_array_equal(out[:, i, j], sr[:, v, u])


def test_upsample_exact_on_a_linear_column():
    """The expansion is exact for a column linear in the pixel position, between decoded coarse
    pixels; past the last one towards an undecoded neighbour the pixel is masked (rim), and a
    coarse pixel without a neighbour along its row gives no column (no_boundary)."""
    h, w, H, W = 20, 30, 47, 71          # a non-integer factor, different along the two axes
    ii, jj = np.mgrid[0:h, 0:w].astype(np.float64)
    # the coarse pixel (i, j) sits at full-frame position ((i + 0.5) H / h - 0.5, ...)
    Y = (ii + 0.5) * H / h - 0.5
    X = (jj + 0.5) * W / w - 0.5
    col = (100.0 + 0.9 * X + 0.05 * Y).astype(np.float32)
    mask = np.zeros((h, w), np.uint8)
    mask[:, 25:] = 1                      # dark on the right
    mask[10, 0] = 0
    region = np.where(mask == 0, 0, -1).astype(np.int32)
    col[mask != 0] = np.nan
    stripe = np.where(mask == 0, np.floor((col + 0.5) / 8.0), -1).astype(np.int32)
    ones = np.ones((h, w), np.float32)
    c_full, s_full, conf, m_full, counts = kernels.upsample_stripes(H, W, col, stripe, ones, mask, region, 8.0,
                                                                   NO_BOUNDARY, RIM)
    rel_full, reg_full, lab_full, crel_full = kernels.upsample_maps(H, W, col, stripe, mask, stripe.copy(), region,
                                                                    np.ones((h, w), np.uint8), col.copy(), 8.0,
                                                                    NO_BOUNDARY, RIM)
    vv, uu = np.mgrid[0:H, 0:W].astype(np.float64)
    want = 100.0 + 0.9 * uu + 0.05 * vv
    ok = m_full == 0
    assert ok.sum() > 0.75 * H * W * 25 / 30
    np.testing.assert_allclose(c_full[ok], want[ok], atol=2e-4)
    np.testing.assert_allclose(crel_full[ok], want[ok], atol=2e-4)    # column_relative alike
    assert (rel_full[ok] == s_full[ok]).all()                          # relative moves with the stripe
    assert (reg_full[ok] == 0).all() and (lab_full == 1).all()
    assert (s_full[ok] == np.floor((c_full[ok] + 0.5) / 8.0)).all() and (conf[ok] == 1).all()
    # towards the dark columns: the pixels past the last decoded centre are masked rim
    x_last = (24 + 0.5) * W / w - 0.5
    right = (uu > x_last + 0.2 * W / w) & (uu < (24.5 + 0.5) * W / w - 0.5)
    assert right.any() and (m_full[right] == RIM).all()
    assert (m_full[uu > (25 + 0.5) * W / w - 0.5 + 1] == 1).all()     # the dark keeps its reason
    assert counts.sum() == H * W and counts[0] == ok.sum()


@pytest.mark.parametrize("stripe_px", [8.0, 6.0])
def test_exact_half_expansion_equals_the_general_loop(stripe_px):
    """The loop for an exact half (2x2 full pixels per coarse pixel) gives what the loop for any
    factor gives, bit for bit: random columns, masks and regions with holes, so that every
    neighbour bit and mask branch occurs."""
    rng = np.random.default_rng(7)
    h, w = 23, 31
    col = (50 + 0.9 * np.arange(w)[None, :] + 0.2 * np.arange(h)[:, None] + rng.normal(0, 0.3, (h, w))).astype(np.float32)
    mask = np.where(rng.random((h, w)) < 0.2, rng.integers(1, 8, (h, w)), 0).astype(np.uint8)
    region = np.where(rng.random((h, w)) < 0.1, 1, 0).astype(np.int32)
    region[mask != 0] = -1
    col[mask != 0] = np.nan
    conf = rng.random((h, w)).astype(np.float32)
    gx, gy, nb = kernels._slopes(col, region, 8.0)
    assert {0, 1, 2, 3} <= set(np.unique(nb & 3)) and {0, 4, 8, 12} <= set(np.unique(nb & 12))
    outs = []
    for o in (kernels._upsample_x2(col, conf, mask, gx, gy, nb, stripe_px, NO_BOUNDARY, RIM),
              kernels._upsample_any(2 * h, 2 * w, col, conf, mask, gx, gy, nb, stripe_px, NO_BOUNDARY, RIM, 0.2)):
        outs.append(list(o[:5]))
    for a, b in zip(*outs):
        assert a.tobytes() == b.tobytes()
    m = outs[0][3]
    assert {0, RIM, NO_BOUNDARY} <= set(np.unique(m)) and outs[0][4].sum() == 4 * h * w
    # and upsample_stripes takes the exact-half loop for these sizes
    got = kernels.upsample_stripes(2 * h, 2 * w, col, np.zeros((h, w), np.int32), conf, mask, region, stripe_px,
                                   NO_BOUNDARY, RIM)
    for a, b in zip(got, outs[0]):
        assert a.tobytes() == b.tobytes()


def test_other_maps_are_expanded_when_first_read(wide):
    """A resampled decode expands relative / region / labels / column_relative only when one is
    read (a scan reads none): the nearest coarse pixel's region and label, its relative index moved
    with the expanded stripe where reported; the same after the StripeMap's own arrays were
    edited, and through a pickle (batch workers send StripeMaps)."""
    import pickle

    from gbscan.decode import _Deferred

    sm = decode(wide.image, SPEC)
    assert sm.stats["resample"] == 2.0
    lazy = ("relative", "region", "labels", "column_relative")
    assert all(isinstance(sm.__dict__[k], _Deferred) for k in lazy)
    twin = pickle.loads(pickle.dumps(sm))
    fresh = decode(wide.image, SPEC)
    sm.mask[:] = 0                      # edits before the first read change nothing
    sm.stripe[:] = -7
    H, W = sm.column.shape
    small = decode(shrink_frame(wide.image, 2.0, red=False), SPEC, DecodeParams(resample=1.0))
    h, w = small.column.shape
    # nearest coarse pixel of each full pixel (an exact half: full pixel u -> u // 2)
    near = (np.arange(H)[:, None] * h // H, np.arange(W)[None, :] * w // W)
    np.testing.assert_array_equal(sm.region, small.region[near])
    np.testing.assert_array_equal(sm.labels, small.labels[near])
    ok = fresh.valid
    moved = fresh.stripe - small.stripe[near]
    np.testing.assert_array_equal(sm.relative[ok], (small.relative[near] + moved)[ok])
    np.testing.assert_array_equal(sm.relative[~ok], small.relative[near][~ok])
    crel = sm.column_relative
    assert np.isfinite(crel[ok]).mean() > 0.99
    # column_relative is the column less the region's offset (a multiple of two stripes), to the
    # last bits but where its own slopes differ (neighbours reported or not): within 0.8 px
    off = (fresh.column - crel)[ok & np.isfinite(crel)] / (2 * SPEC.stripe_px)
    assert (np.abs(off - np.round(off)) < 1e-3).mean() > 0.99
    np.testing.assert_allclose(off, np.round(off), atol=0.05)
    assert all(not isinstance(sm.__dict__[k], _Deferred) for k in lazy)
    for k in lazy:
        np.testing.assert_array_equal(getattr(twin, k), getattr(sm, k))
        np.testing.assert_array_equal(getattr(fresh, k), getattr(sm, k))
    # column_sigma likewise, on its own: the nearest coarse pixel's predicted column error (projector px:
    # the same units at both sizes), NaN exactly where the expanded map reports nothing as decoded
    assert isinstance(fresh.__dict__["column_sigma"], _Deferred) and isinstance(sm.__dict__["column_sigma"], _Deferred)
    cs = sm.column_sigma
    assert cs.shape == (H, W) and cs.dtype == np.float32
    assert np.array_equal(np.isfinite(cs), ok) and ok.mean() > 0.3
    np.testing.assert_array_equal(cs[ok], small.column_sigma[near][ok])
    np.testing.assert_array_equal(twin.column_sigma, cs)
    assert not isinstance(fresh.__dict__["relative"], _Deferred)   # (fresh's four maps were read above)


def test_shrink_frame_is_a_linear_light_mean():
    """Shrinking averages linear light: a uniform frame stays as it is; a 2 x 2 checker of 0 and
    255 becomes the encoding of half the linear white (186 at gamma 2.2), not 128."""
    flat = np.full((40, 60, 3), 77, np.uint8)
    np.testing.assert_array_equal(shrink_frame(flat, 2.0), np.full((20, 30, 3), 77, np.uint8))
    checker = np.zeros((40, 60, 3), np.uint8)
    checker[0::2, 0::2] = 255
    checker[1::2, 1::2] = 255
    out = shrink_frame(checker, 2.0)
    assert out.shape == (20, 30, 3)
    assert (np.abs(out.astype(int) - round(255 * 0.5 ** (1 / 2.2))) <= 1).all()
    gb = shrink_frame(checker, 2.0, red=False)
    assert (gb[..., 0] == 0).all() and (gb[..., 1:] == out[..., 1:]).all()
    lut = gamma_lut(2.2)
    assert lut.dtype == np.float32
    with pytest.raises(GBError, match="factor"):
        shrink_frame(flat, 0.5)


@pytest.mark.parametrize("gamma", [1.0, 2.2])
@pytest.mark.parametrize("red", [True, False])
def test_halving_in_one_pass_equals_opencv_area_mean(gamma, red):
    """An exact half (even sides) is shrunk by one fused kernel (kernels.shrink2_rgb); it must
    give what the three steps give (linearise, cv2.INTER_AREA, encode), value for value -- also
    on the sides that are not even, which take the three steps themselves."""
    import cv2

    from gbscan import kernels
    from gbscan.decode import _encode_table, _lut

    rng = np.random.default_rng(7)
    for H, W in ((48, 64), (50, 70), (51, 70)):
        img = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        h, w = resample_size(img.shape, 2.0)
        lin = kernels.linear_rgb(img, _lut(gamma), 0 if red else 1)
        small = cv2.resize(lin, (w, h), interpolation=cv2.INTER_AREA).reshape(h, w, lin.shape[2])
        want = kernels.encode_rgb(np.ascontiguousarray(small, dtype=np.float32), _encode_table(gamma))
        np.testing.assert_array_equal(shrink_frame(img, 2.0, gamma, red=red), want)
    assert kernels.shrink2_rgb(img[:50, :70], _lut(gamma), _encode_table(gamma), 0 if red else 1).shape == (25, 35, 3)


@pytest.mark.parametrize("bad", [-1.0, 0.5, 9.0, True, "2"])
def test_resample_parameter_is_checked(bad):
    with pytest.raises(GBError, match="resample"):
        DecodeParams(resample=bad)


def test_cli_resample_flag(tmp_path, capsys):
    """gbscan decode --resample: a bad factor is one line and exit 1; a good one is used."""
    from gbscan.cli import main
    from gbscan.io import write_png

    r = render("plane", 1.0)
    png = write_png(tmp_path / "plane.png", r.image)
    assert main(["decode", str(png), "-o", str(tmp_path / "a.npz"), "--resample", "0.5"]) == 1
    assert "resample" in capsys.readouterr().err
    assert not (tmp_path / "a.npz").exists()
    assert main(["decode", str(png), "-o", str(tmp_path / "b.npz"), "--resample", "2"]) == 0
    assert "decoded shrunk by 2 to 320x240" in capsys.readouterr().out
    z = np.load(tmp_path / "b.npz")
    assert z["column"].shape == (480, 640)
    import json

    assert json.loads(str(z["stats"]))["resample"] == 2.0


@pytest.mark.parametrize("shape, coarse", [((960, 1280), (480, 640)), ((1024, 1280), (585, 731)), ((9, 12), (5, 7))])
def test_column_sigma_expands_from_the_coarse_pixel_the_columns_come_from(shape, coarse):
    """A resampled decode's column_sigma takes, at each full pixel, the coarse pixel whose column the
    expansion used (the kernels' nearest-pixel rule, ``_coarse_row`` / ``_coarse_columns``), for
    exact halves and for other factors (1.75: the head's), NaN where the full pixel is not
    reported."""
    from gbscan.decode import _expand_sigma
    from gbscan.kernels.resample import _coarse_columns, _coarse_row

    H, W = shape
    h, w = coarse
    rng = np.random.default_rng(3)
    sigma = rng.uniform(0.04, 0.5, (h, w)).astype(np.float32)
    reported = rng.random((H, W)) < 0.8
    full = _expand_sigma(sigma, reported)["column_sigma"]
    _, _, jidx = _coarse_columns(w, W, 0.2)
    rows = np.array([_coarse_row(v, h, H, 0.2)[0] for v in range(H)])
    want = sigma[rows][:, jidx]
    assert full.dtype == np.float32 and full.shape == (H, W)
    np.testing.assert_array_equal(full[reported], want[reported])
    assert np.isnan(full[~reported]).all()


@pytest.mark.slow
def test_lit_window_is_shrunk_decoded_and_expanded_alone():
    """A head before darkness through a 1280x960 camera: only its lit window (DecodeParams.crop) is
    shrunk, decoded and expanded; the result is the decode of that window cut out of the frame,
    pasted back with the whole frame's values for dark pixels.  Its shrunk grid starts at the
    window's corner, so it is not the whole frame's decode bit for bit: a sampling as good (none
    wrong, coverage within 2.5 points)."""
    import pickle

    from gbscan.decode import DARK, _Deferred

    r = render("head", 2.0)
    H, W = r.image.shape[:2]
    sm = decode(r.image, SPEC)
    whole = decode(r.image, SPEC, DecodeParams(crop=False))
    f = sm.stats["resample"]
    assert f > 1.5 and whole.stats["resample"] == f
    y0, y1, x0, x1 = sm.stats["decoded_window"]
    assert (y1 - y0) * (x1 - x0) < 0.4 * H * W and whole.stats["decoded_window"] == [0, H, 0, W]
    assert sm.stats["decoded_size"] == list(resample_size((y1 - y0, x1 - x0), f))[::-1]
    twin = pickle.loads(pickle.dumps(sm))
    ref = decode(np.ascontiguousarray(r.image[y0:y1, x0:x1]), SPEC, DecodeParams(resample=f, crop=False))
    inside = (slice(y0, y1), slice(x0, x1))
    out = np.ones((H, W), bool)
    out[inside] = False
    fills = {"column": np.nan, "stripe": -1, "confidence": 0, "mask": DARK, "relative": 0, "region": -1,
             "labels": 0, "column_relative": np.nan, "column_sigma": np.nan}
    assert isinstance(sm.__dict__["region"], _Deferred) and isinstance(sm.__dict__["column_sigma"], _Deferred)
    for name, fill in fills.items():
        a = getattr(sm, name)
        assert a.shape == (H, W), name
        np.testing.assert_array_equal(a[inside], getattr(ref, name), err_msg=name)
        np.testing.assert_array_equal(a[out], np.full(int(out.sum()), fill, a.dtype), err_msg=name)
        np.testing.assert_array_equal(getattr(twin, name), a, err_msg=name)
    assert sm.stats["pixels"] == H * W and sm.stats["reported"] == int(sm.valid.sum())
    assert sm.stats["reasons"]["dark"] == ref.stats["reasons"]["dark"] + int(out.sum())
    cover, wrong = scores(sm, r)
    cover_whole, wrong_whole = scores(whole, r)
    assert wrong == wrong_whole == 0 and cover > 75 and abs(cover - cover_whole) < 2.5


def _slopes_plain(col, region, limit):
    """The coarse slopes as pixel loops with branches (the kernel's rules written plainly): pairs of
    neighbours on one surface, their differences added into zeros in pair order, halved where two."""
    h, w = col.shape
    gx = np.zeros((h, w), np.float32)
    gy = np.zeros((h, w), np.float32)
    nb = np.zeros((h, w), np.uint8)
    for i in range(h):
        pair = [bool(region[i, j] == region[i, j + 1] and abs(col[i, j + 1] - col[i, j]) < limit) for j in range(w - 1)]
        for j in range(w):
            right = j < w - 1 and pair[j]
            left = j > 0 and pair[j - 1]
            nb[i, j] = (1 if right else 0) | (2 if left else 0)
            if right and left:
                gx[i, j] = np.float32(0.5 * (np.float32(col[i, j + 1] - col[i, j]) + np.float32(col[i, j] - col[i, j - 1])))
            elif right:
                gx[i, j] = col[i, j + 1] - col[i, j]
            elif left:
                gx[i, j] = col[i, j] - col[i, j - 1]
    for i in range(h - 1):
        for j in range(w):
            d = np.float32(col[i + 1, j] - col[i, j])
            if region[i, j] == region[i + 1, j] and abs(d) < limit:
                nb[i, j] |= 4
                nb[i + 1, j] |= 8
                gy[i, j] = np.float32(gy[i, j] + d)
                gy[i + 1, j] = np.float32(gy[i + 1, j] + d)
    both = (nb & 12) == 12
    gy[both] = (gy[both] * np.float32(0.5)).astype(np.float32)
    return gx, gy, nb


@pytest.mark.parametrize("seed", range(6))
def test_coarse_slopes_equal_their_rules_written_plainly_bit_for_bit(seed):
    # the branch-free row loops against the pixel loops, NaN columns, signed zeros and edges included
    rng = np.random.default_rng(seed)
    for _ in range(40):
        h, w = int(rng.integers(1, 10)), int(rng.integers(1, 10))
        col = (rng.normal(20.0, 3.0, (h, w)) * rng.integers(0, 2)).astype(np.float32)
        col[rng.random((h, w)) < 0.2] = np.nan
        col[rng.random((h, w)) < 0.1] = -0.0
        region = rng.integers(-1, 2, (h, w)).astype(np.int32)
        limit = float(rng.choice([0.5, 4.0, 8.0]))
        got = kernels._slopes(col, region, limit)
        want = _slopes_plain(col, region, limit)
        for g, e in zip(got, want):
            assert g.dtype == e.dtype
            assert np.array_equal(g.view(np.uint32) if g.dtype == np.float32 else g,
                                  e.view(np.uint32) if e.dtype == np.float32 else e)


@pytest.mark.parametrize("seed", range(4))
def test_general_expansion_equals_the_per_pixel_rule(seed):
    """The general loop (coarse rows gathered, each output by selects) against ``_expanded`` called
    pixel by pixel with each full pixel's nearest coarse pixel, for factors other than 2."""
    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(3, 9)), int(rng.integers(3, 9))
    H, W = int(h * rng.uniform(1.2, 2.6)), int(w * rng.uniform(1.2, 2.6))
    col = (40 + 1.1 * np.arange(w)[None, :] + rng.normal(0, 0.4, (h, w))).astype(np.float32)
    mask = np.where(rng.random((h, w)) < 0.25, rng.integers(1, 8, (h, w)), 0).astype(np.uint8)
    region = np.where(rng.random((h, w)) < 0.15, 1, 0).astype(np.int32)
    region[mask != 0] = -1
    col[mask != 0] = np.nan
    conf = rng.random((h, w)).astype(np.float32)
    stripe_px = float(rng.choice([8.0, 6.0]))
    gx, gy, nb = kernels._slopes(col, region, stripe_px)
    co, so, fo, mo, counts = kernels._upsample_any(H, W, col, conf, mask, gx, gy, nb, stripe_px, NO_BOUNDARY, RIM, 0.2)
    dxs, xbit, jidx = kernels._coarse_columns(w, W, 0.2)
    for v in range(H):
        i, dy, ybit = kernels._coarse_row(v, h, H, 0.2)
        for u in range(W):
            j = jidx[u]
            m, x, s = kernels._expanded(mask[i, j], nb[i, j], xbit[u] | ybit, col[i, j], gx[i, j], gy[i, j], dxs[u], dy,
                                        stripe_px, NO_BOUNDARY, RIM)
            assert mo[v, u] == m
            assert np.float32(co[v, u]).tobytes() == np.float32(x).tobytes()
            assert so[v, u] == s
            assert fo[v, u] == (conf[i, j] if m == 0 else 0.0)
    assert np.array_equal(counts, np.bincount(mo.ravel() & 15, minlength=16))
