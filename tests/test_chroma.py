"""Chroma subsampling found in the pixels (gbscan.chroma), and what the decoder does with such frames."""
import dataclasses

import cv2
import numpy as np
import pytest

from gbscan import sim
from gbscan.chroma import SCORE_MAX, chroma_check
from gbscan.decode import OK, UNINDEXED, DecodeParams, StreamMemo, decode
from gbscan.errors import GBError
from gbscan.pattern import PatternSpec, render_pattern

_CACHE = {}


def frame(scene="multi_object", preset="typical", seed=1, args=(), **cond):
    """A simulated frame (supersample 1 to keep it quick) of ``scene(*args)`` under ``preset`` with
    Conditions ``cond``."""
    key = (scene, preset, seed, args, tuple(sorted(cond.items())))
    if key not in _CACHE:
        c = dataclasses.replace(sim.preset(preset), supersample=1, **cond)
        _CACHE[key] = sim.render(sim.paper_rig(), getattr(sim.scenes, scene)(*args), render_pattern(PatternSpec()),
                                 c, seed=seed)
    return _CACHE[key]


def _upsampled(chroma_rows: np.ndarray, interp: int) -> np.ndarray:
    h, w = chroma_rows.shape
    small = cv2.resize(chroma_rows, (w // 2, h), interpolation=cv2.INTER_AREA)
    return cv2.resize(small, (w, h), interpolation=interp)


def _with_chroma(img: np.ndarray, interp: int | None, shift: int = 0) -> np.ndarray:
    # the frame with its Cb, Cr halved along the rows and upsampled again with ``interp`` (None: as
    # it is), the pairs starting at column ``shift``
    ycc = cv2.cvtColor(img, cv2.COLOR_RGB2YCrCb).astype(np.float32)
    if interp is not None:
        for c in (1, 2):
            ch = ycc[:, shift:, c]
            w = ch.shape[1] // 2 * 2
            ycc[:, shift:shift + w, c] = _upsampled(np.ascontiguousarray(ch[:, :w]), interp)
    return cv2.cvtColor(np.clip(np.rint(ycc), 0, 255).astype(np.uint8), cv2.COLOR_YCrCb2RGB)


# -- the check on its own -----------------------------------------------------------------------
def _cosited(img: np.ndarray, cubic: bool, shift: int = 0) -> np.ndarray:
    # Cb, Cr kept on the columns shift, shift + 2, ... and interpolated between them (linear, or the
    # 4-tap cubic -1/16 9/16 9/16 -1/16), as MPEG-2 / H.264 site them
    ycc = cv2.cvtColor(img, cv2.COLOR_RGB2YCrCb).astype(np.float32)
    for c in (1, 2):
        ch = ycc[:, shift:, c]
        s = ch[:, ::2]
        p = np.pad(s, ((0, 0), (1, 2)), mode="edge")
        mid = (-p[:, :-3] + 9 * p[:, 1:-2] + 9 * p[:, 2:-1] - p[:, 3:]) / 16 if cubic else 0.5 * (p[:, 1:-2] + p[:, 2:-1])
        ch[:, 1::2] = mid[:, :ch[:, 1::2].shape[1]]
    return cv2.cvtColor(np.clip(np.rint(ycc), 0, 255).astype(np.uint8), cv2.COLOR_YCrCb2RGB)


def test_random_colour_is_full_and_every_2x_upsampler_is_found():
    rng = np.random.default_rng(3)
    img = rng.integers(60, 256, (96, 160, 3), dtype=np.uint8)
    full = chroma_check(img)
    assert full.score > 0.8 and full.score_cosited > 0.8 and not full.subsampled and full.samples > 2000
    for shift in (0, 1):      # pairs at even or odd columns (a frame cropped by one column)
        for interp in (cv2.INTER_NEAREST, cv2.INTER_LINEAR, cv2.INTER_CUBIC):
            got = chroma_check(_with_chroma(img, interp, shift))
            assert got.subsampled and got.score < 0.1, (interp, shift, got)
        for cubic in (False, True):
            got = chroma_check(_cosited(img, cubic, shift))
            assert got.subsampled and got.score_cosited < 0.1 and got.score > 0.5, (cubic, shift, got)
            assert "co-sited" in got.describe()


def test_simulated_cameras_full_colour_and_subsampled():
    """The decoder's frames: full colour (lossless RGB, a Bayer camera, JPEG 4:4:4 q95) against a
    YUYV / I420 camera and JPEG 4:2:2 / 4:2:0 (the sweep's 92 frames: >= 0.76 against <= 0.43)."""
    full = {"rgb": {}, "bayer": {"bayer": "RGGB"}, "jpeg444": {"jpeg_quality": 95, "jpeg_sampling": "4:4:4"}}
    half = {"yuyv": {"yuv": "yuyv"}, "i420": {"yuv": "i420"}, "jpeg422": {"jpeg_quality": 95, "jpeg_sampling": "4:2:2"},
            "jpeg420": {"jpeg_quality": 90, "jpeg_sampling": "4:2:0"}}
    for name, cond in full.items():
        got = chroma_check(frame(**cond).image)
        assert not got.subsampled and got.score > 0.7 and got.score_cosited > 0.4, (name, got)
    for name, cond in half.items():
        got = chroma_check(frame(**cond).image)
        assert got.subsampled and got.score < 0.25, (name, got)
    # the hard preset's noise lifts the subsampled score most; still under the threshold
    got = chroma_check(frame(preset="hard", jpeg_quality=90, jpeg_sampling="4:2:0").image)
    assert got.subsampled and got.score < SCORE_MAX, got


def test_nothing_to_measure_is_not_called_subsampled():
    for img in (np.zeros((48, 64, 3), np.uint8), np.full((48, 64, 3), 200, np.uint8),
                np.full((48, 20, 3), 200, np.uint8)):
        got = chroma_check(img)
        assert np.isnan(got.score) and not got.subsampled
        assert "not measured" in got.describe()
    with pytest.raises(ValueError, match="uint8 RGB"):
        chroma_check(np.zeros((48, 64), np.uint8))


def test_yuv_camera_conditions_and_round_trip():
    rng = np.random.default_rng(0)
    img = rng.integers(64, 192, (8, 12, 3), dtype=np.uint8)     # colours that stay inside RGB's gamut
    out = sim.yuv_round_trip(img, "yuyv")
    assert out.shape == img.shape and out.dtype == np.uint8
    cb = cv2.cvtColor(out, cv2.COLOR_RGB2YCrCb)[..., 2].astype(int)
    assert np.abs(cb[:, 0::2] - cb[:, 1::2]).max() <= 3     # pixel pairs share their colour (rounding)
    assert np.abs(cb[:, 1:-1:2] - cb[:, 2::2]).max() > 20
    with pytest.raises(GBError, match="even size"):
        sim.yuv_round_trip(img[:, :11], "i420")
    with pytest.raises(GBError, match="yuyv, i420"):
        sim.yuv_round_trip(img, "nv21")
    with pytest.raises(GBError, match="yuv must be"):
        sim.Conditions(yuv="rgb")
    with pytest.raises(GBError, match="neither JPEG"):
        sim.Conditions(yuv="yuyv", jpeg_quality=90)


# -- the decoder's policy -----------------------------------------------------------------------
def _wrong(sm, r, w=PatternSpec().stripe_px):
    err, bad = sim.column_errors(sm.column, sm.valid, r.proj_xy[..., 0], w)
    return int((bad & ~r.depth_edge).sum())


def test_decoder_withholds_the_index_of_a_yuyv_frame():
    """Decoded as full colour, the multi-object scene at 680 mm (the sweep's moving frame 6) through a
    YUYV camera puts a region on a wrong stripe (a 4:2:2 frame: pixel pairs share their colour); by
    default nothing is reported, every pixel that would have been is unindexed, and the relative
    unwrapping stays."""
    r = frame(seed=6, args=(680.0,), yuv="yuyv")
    anyway = decode(r.image, PatternSpec(), DecodeParams(subsampled_chroma="decode"))
    off = decode(r.image, PatternSpec(), DecodeParams(subsampled_chroma="off"))
    sm = decode(r.image, PatternSpec())
    assert anyway.stats["chroma"]["subsampled"] and "chroma" not in off.stats
    assert np.array_equal(anyway.mask, off.mask) and np.array_equal(anyway.column, off.column, equal_nan=True)
    assert _wrong(anyway, r) > 500 and anyway.stats["reported"] > 10000    # measured: 2037 wrong
    assert sm.stats["chroma"] == {**anyway.stats["chroma"], "withheld": True}
    assert sm.stats["reported"] == 0 and not (sm.mask == OK).any() and np.isnan(sm.column).all()
    assert (sm.stripe == -1).all() and (sm.confidence == 0).all()
    assert sm.stats["reasons"]["unindexed"] == anyway.stats["reasons"]["unindexed"] + anyway.stats["reported"]
    assert np.array_equal(sm.mask == UNINDEXED, (anyway.mask == UNINDEXED) | (anyway.mask == OK))
    assert np.array_equal(sm.relative, anyway.relative) and np.array_equal(sm.region, anyway.region)
    assert sm.column_sigma is None or np.isnan(sm.column_sigma).all()
    assert "withheld" in sm.stats["why"] and "subsampled_chroma" in sm.stats["why"]
    assert sm.stats["ms"]["chroma"] > 0


def test_full_colour_frames_decode_as_without_the_check():
    for cond in ({}, {"bayer": "RGGB"}):
        r = frame("sphere", **cond)
        a = decode(r.image, PatternSpec())
        b = decode(r.image, PatternSpec(), DecodeParams(subsampled_chroma="off"))
        assert a.stats["chroma"]["subsampled"] is False and a.stats["chroma"]["withheld"] is False
        assert a.stats["reported"] == b.stats["reported"] > 0
        assert np.array_equal(a.mask, b.mask) and np.array_equal(a.column, b.column, equal_nan=True)
        assert "why" not in a.stats


def test_subsampled_chroma_param_is_validated():
    with pytest.raises(GBError, match="subsampled_chroma"):
        DecodeParams(subsampled_chroma="ignore")


def test_a_camera_with_more_pixels_is_decoded_shrunk_and_reported():
    """Through a YUYV camera of 1280x960 pixels the stripes span ~7.5 px: the decoder shrinks the
    frame by 2 (``DecodeParams.resample``), each decoded pixel averages whole pixel pairs, and the
    frame is reported as in full colour (measured: 0 pixels on a wrong stripe either way)."""
    rig = sim.paper_rig(camera_px=(1280, 960))
    c = dataclasses.replace(sim.preset("typical"), supersample=1)
    r = sim.render(rig, sim.scenes.sphere(), render_pattern(PatternSpec()), c, seed=1)
    rgb = decode(r.image, PatternSpec())
    yuyv = decode(sim.yuv_round_trip(r.image, "yuyv"), PatternSpec())
    assert yuyv.stats["resample"] >= 2 and "chroma" not in yuyv.stats   # not checked
    cand = r.lit & ~r.depth_edge
    assert (yuyv.valid & cand).sum() > 0.95 * (rgb.valid & cand).sum() > 0
    assert _wrong(yuyv, r) == 0
    from gbscan.diagnose import check_frame

    keys = {f.key: f.level for f in check_frame(sim.yuv_round_trip(r.image, "yuyv"), yuyv).findings}
    assert keys.get("chroma") == "info"


# -- lateral chromatic aberration ---------------------------------------------------------------
def test_simulated_lens_magnifies_blue_and_shrinks_red_about_the_centre():
    img = np.zeros((60, 80, 3), np.float32)
    img[:] = np.clip((np.arange(80) - 66.0) / 8.0, 0, 1)[None, :, None]   # a ramp crossing 0.5 at x = 70
    out = sim.lateral_ca(img, (39.5, 29.5), 2.0)
    rc = np.hypot(39.5, 29.5)

    def edge(ch):                                      # the 0.5 crossing on the centre row
        row = ch[30]
        u = int(np.flatnonzero(row >= 0.5)[0])
        return u - 1 + (0.5 - row[u - 1]) / (row[u] - row[u - 1])

    g, b, r = edge(out[..., 1]), edge(out[..., 2]), edge(out[..., 0])
    assert g == pytest.approx(70.0, abs=1e-5)
    assert b - g == pytest.approx(2.0 * (70.0 - 39.5) / rc, abs=1e-3)    # outward
    assert g - r == pytest.approx(2.0 * (70.0 - 39.5) / rc, abs=1e-3)    # inward
    with pytest.raises(GBError, match="lateral_ca_px"):
        sim.Conditions(lateral_ca_px=20.0)


def test_decoder_measures_and_corrects_lateral_chromatic_aberration():
    """A lens whose blue image is 1 px larger than the green one at the corners (0.8 px at the
    sides): the boundaries' bias grows toward the sides and the column RMS on the plane goes
    0.025 -> 0.42 projector px; measured on the stripes and corrected, 0.046.  Without aberration
    nothing is corrected and the result is the same bit for bit."""
    spec = PatternSpec()

    def cols(r, **kw):
        sm = decode(r.image, spec, DecodeParams(**kw))
        err, bad = sim.column_errors(sm.column, sm.valid, r.proj_xy[..., 0], spec.stripe_px)
        e = err[sm.valid & ~bad & ~r.depth_edge]
        return sm, float(np.sqrt(np.mean(e ** 2))), int((bad & ~r.depth_edge).sum())

    clean = frame("plane", seed=0)
    sm0, rms0, w0 = cols(clean)
    off0, _, _ = cols(clean, lateral_ca=False)
    assert not sm0.stats["lateral_ca"]["corrected"] and "lateral_ca" not in off0.stats
    assert np.array_equal(sm0.column, off0.column, equal_nan=True) and np.array_equal(sm0.mask, off0.mask)
    r = frame("plane", seed=0, lateral_ca_px=1.0)
    sm, rms, w = cols(r)
    _, rms_off, _ = cols(r, lateral_ca=False)
    ca = sm.stats["lateral_ca"]
    assert ca["corrected"] and ca["t"] > 20 and ca["edge_px"] == pytest.approx(0.8, abs=0.15)
    assert w == w0 == 0 and rms < 2.5 * rms0 and rms < 0.25 * rms_off, (rms0, rms, rms_off)
    from gbscan.diagnose import check_frame

    f = {x.key: x for x in check_frame(r.image, sm).findings}["lateral_ca"]
    assert f.level == "warn" and "corrected" in f.text
    with pytest.raises(GBError, match="lateral_ca"):
        DecodeParams(lateral_ca_t=0)



def _same_maps(a, b) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True)
               for f in ("column", "stripe", "confidence", "mask", "column_sigma"))


def test_a_stream_reuses_the_lens_aberration_and_measures_it_again():
    """``StreamMemo``: the first frame of a stream measures the lens's aberration (the same result
    as without a memo, bit for bit); the next ones correct with its fit (here the sphere with the
    plane's fit: column RMS within 1.5 x of measuring its own, 0 wrong), until every ``every``-th
    use measures again; another size or rule measures afresh; a frame with nothing to measure (dark)
    leaves nothing to reuse."""
    spec = PatternSpec()
    plane = frame("plane", seed=0, lateral_ca_px=1.0)
    sphere = frame("sphere", seed=0, lateral_ca_px=1.0)

    def rms_wrong(sm, r):
        err, bad = sim.column_errors(sm.column, sm.valid, r.proj_xy[..., 0], spec.stripe_px)
        e = err[sm.valid & ~bad & ~r.depth_edge]
        return float(np.sqrt(np.mean(e ** 2))), int((bad & ~r.depth_edge & sm.valid).sum())

    memo = StreamMemo(3)
    first = decode(plane.image, spec, memo=memo)
    assert first.stats["stream"] == {"lateral_ca": "measured", "resample": "measured"}
    assert first.stats["lateral_ca"]["corrected"] and _same_maps(first, decode(plane.image, spec))
    own = decode(sphere.image, spec)
    second = decode(sphere.image, spec, memo=memo)
    assert second.stats["stream"] == {"lateral_ca": "reused (measured 1 frame before)",
                                      "resample": "reused (measured 1 frame before)"}
    assert second.stats["lateral_ca"] == first.stats["lateral_ca"] != own.stats["lateral_ca"]
    assert not _same_maps(second, own)
    (rms_own, w_own), (rms_reused, w_reused) = rms_wrong(own, sphere), rms_wrong(second, sphere)
    assert w_own == w_reused == 0 and rms_reused < 1.5 * rms_own, (rms_own, rms_reused)
    assert decode(sphere.image, spec, memo=memo).stats["stream"]["lateral_ca"] == "reused (measured 2 frames before)"
    again = decode(sphere.image, spec, memo=memo)                       # the 4th frame: every = 3
    assert again.stats["stream"]["lateral_ca"] == "measured" and _same_maps(again, own)
    # another rule (or frame size) is another key: measured, then reused
    p6 = DecodeParams(lateral_ca_t=6.0)
    assert decode(plane.image, spec, p6, memo=memo).stats["stream"]["lateral_ca"] == "measured"
    assert decode(plane.image, spec, p6, memo=memo).stats["stream"]["lateral_ca"].startswith("reused")
    small = np.ascontiguousarray(plane.image[:400])
    assert decode(small, spec, p6, memo=memo).stats["stream"] == {"lateral_ca": "measured", "resample": "measured"}
    # a dark first frame keeps nothing; clear() forgets
    m2 = StreamMemo()
    dark = decode(np.zeros_like(plane.image), spec, memo=m2)
    assert dark.stats["stream"] == {"resample": "measured"} and dark.stats["reported"] == 0
    assert decode(plane.image, spec, memo=m2).stats["stream"]["lateral_ca"] == "measured"
    m2.clear()
    assert decode(plane.image, spec, memo=m2).stats["stream"]["lateral_ca"] == "measured"
    # without a memo nothing is said; bad arguments are named
    assert "stream" not in own.stats
    for bad in (0, 1.5, True, "16"):
        with pytest.raises(GBError, match="StreamMemo: every"):
            StreamMemo(bad)
    with pytest.raises(GBError, match="memo must be a gbscan.decode.StreamMemo"):
        decode(plane.image, spec, memo={})


def test_lateral_chromatic_aberration_is_taken_out_before_the_unwrapping(monkeypatch):
    """The unwrapping's spacing and tilt cuts read the boundaries corrected already: step 1's
    positions (``locate``) are the uncorrected ones moved by the fit (``decode.correct_lateral_ca``:
    half the blue edge's offset for green|blue, all of it for green|cyan).  The sweep through the
    simulated lens at 1 px: 82.50 -> 82.80 % reported, nothing wrong either way."""
    from gbscan import unwrap as uw
    from gbscan.decode import correct_lateral_ca
    from gbscan.kernels._common import BLUE, CYAN, GREEN

    seen = []
    orig = uw.unwrap

    def spy(labels, params=None, locate=None, **kw):
        def rec(sg):
            x = locate(sg)
            seen.append((sg, x.copy()))
            return x
        return orig(labels, params, locate=rec, **kw)

    monkeypatch.setattr(uw, "unwrap", spy)
    r = frame("plane", seed=0, lateral_ca_px=1.0)
    spec = PatternSpec()
    sm = decode(r.image, spec)
    (sg, x_on), n_on = seen[0], len(seen)
    seen.clear()
    decode(r.image, spec, DecodeParams(lateral_ca=False))
    sg_off, x_off = seen[0]
    assert n_on == len(seen) and np.array_equal(sg.j_la, sg_off.j_la) and np.array_equal(sg.row, sg_off.row)
    ca = sm.stats["lateral_ca"]
    assert ca["corrected"]
    want = correct_lateral_ca(sg, x_off, ca["a_px"], ca["k"])
    ok = np.isfinite(x_off)
    assert np.allclose(x_on[ok], want[ok], atol=2e-3)
    la, lb = sg.j_la, sg.j_lb
    gb = ok & (((la == GREEN) & (lb == BLUE)) | ((la == BLUE) & (lb == GREEN)))
    bc = ok & (((la == BLUE) & (lb == CYAN)) | ((la == CYAN) & (lb == BLUE)))
    side = gb & (x_off > np.percentile(x_off[gb], 95))      # blue magnified: its edges further out
    assert gb.sum() > 1000 and np.median(x_off[side] - x_on[side]) > 0.2     # 0.26 (delta / 2 there)
    assert np.array_equal(x_on[bc], x_off[bc])             # located on the green channel alone


def test_lens_aberration_does_not_weld_a_wall_strip_beside_the_box():
    """Issue 3, every reported pixel right, through a lens whose blue image is 1 px larger than
    the green one at the corners: the multi-object scene with its wall at 800 mm (seed 0).  A
    strip of the wall beside the box lines up with the box's stripes 10 apart; the row check
    rejects it where the wall's green falls on the box's marker stripe with the blue channel dark
    -- dark but for the one edge pixel the shifted blue image lights.  The clean test takes the
    run's median ``min(gn, bn)`` (its mean left 80 wrong pixels here); without the clean rule 178."""
    from gbscan.unwrap import UnwrapParams

    spec = PatternSpec()
    r = frame(seed=0, args=(650.0, 800.0), lateral_ca_px=1.0)

    def wrong(sm):
        truth = r.proj_xy[..., 0]
        ok = sm.valid & np.isfinite(truth) & ~r.depth_edge
        return int((ok & (np.abs(sm.column - truth) >= spec.stripe_px / 2)).sum())

    sm = decode(r.image, spec)
    assert sm.stats["lateral_ca"]["corrected"] and wrong(sm) == 0
    assert wrong(decode(r.image, spec, DecodeParams(unwrap=UnwrapParams(conflict_clean_level=0.0)))) > 100


def test_robust_line_and_channel_edges_kernels():
    from gbscan import kernels

    x = np.linspace(0.0, 600.0, 2001)
    a, k, sig, n, sd = kernels.robust_line(x, 0.3 + 0.002 * x, 2)
    assert (a, k, n) == (pytest.approx(0.3, abs=1e-9), pytest.approx(0.002, abs=1e-12), 2001) and sig < 1e-9
    assert sd == pytest.approx(x.std())
    rng = np.random.default_rng(5)
    y = 0.3 + 0.002 * x + rng.normal(0, 0.05, x.size)
    y[::10] += rng.choice([-1.0, 1.0], y[::10].size) * rng.uniform(0.5, 2.0, y[::10].size)   # 10 % outliers
    a, k, sig, n, _ = kernels.robust_line(x, y, 2)
    assert abs(a - 0.3) < 0.02 and abs(k - 0.002) < 5e-5 and 0.04 < sig < 0.06 and n < 0.93 * x.size
    # one row: green 1 | blue 1, the green edge (gn = 1/2) at 10.25, the blue one (bn = 1/2) at 10.75
    u = np.arange(24, dtype=np.float64)
    gn = np.clip(0.5 - (u - 10.25) / 4, 0, 1).astype(np.float32)[None, :]     # ramps over 4 px
    bn = np.clip(0.5 + (u - 10.75) / 4, 0, 1).astype(np.float32)[None, :]
    i32 = lambda *v: np.array(v, np.int32)     # noqa: E731
    xs, ds = kernels.channel_edge_offsets(gn, bn, i32(0), i32(10), i32(11), np.array([1], np.uint8), i32(0),
                                          i32(23), i32(0), np.array([0], np.int64), np.array([10.5], np.float32),
                                          0, 2.0)
    assert xs.tolist() == [10.5] and ds[0] == pytest.approx(0.5, abs=1e-6)
    # blue | green: the blue edge (falling) at 12.25, the green one (rising) at 12.75 -> d = -0.5
    bn2 = np.clip(0.5 - (u - 12.25) / 4, 0, 1).astype(np.float32)[None, :]
    gn2 = np.clip(0.5 + (u - 12.75) / 4, 0, 1).astype(np.float32)[None, :]
    xs, ds = kernels.channel_edge_offsets(gn2, bn2, i32(0), i32(12), i32(13), np.array([2], np.uint8), i32(0),
                                          i32(23), i32(0), np.array([0], np.int64), np.array([12.5], np.float32),
                                          0, 2.0)
    assert ds[0] == pytest.approx(-0.5, abs=1e-6)
