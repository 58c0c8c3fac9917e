"""The stripe-free grey texture (gbscan.texture): against the same scene under a uniform cyan frame."""
import dataclasses

import numpy as np
import pytest

from gbscan import sim
from gbscan.decode import decode, gamma_lut
from gbscan.errors import GBError
from gbscan.pattern import PatternSpec, render_pattern
from gbscan.texture import intensity, pattern_light, stripe_period_px, to_grey

SPEC = PatternSpec()


def _flood(scene, cond, seed):
    """Linear green and blue of ``scene`` under a uniform cyan projector frame: the truth."""
    frame = np.zeros_like(render_pattern(SPEC))
    frame[..., 1:] = 255
    img = sim.render(sim.paper_rig(), scene, frame, cond, seed=seed).image
    lut = gamma_lut(2.2)
    return lut[img[..., 1]], lut[img[..., 2]]


def _relative_errors(t, g, b, use):
    """|t / truth| - 1 after the best scale, truth = g / mean(g) + b / mean(b) on ``use``."""
    truth = g / g[use].mean() + b / b[use].mean()
    ratio = t[use] / truth[use]
    return np.abs(ratio / np.median(ratio) - 1), np.corrcoef(t[use], truth[use])[0, 1]


@pytest.fixture(scope="module")
def plane_frames():
    """A tilted plane of green-ish albedo (clean preset): striped render, decode, cyan-flood truth."""
    cond = dataclasses.replace(sim.preset("clean"), supersample=1)
    scene = sim.scenes.plane(650.0, (10.0, 20.0), albedo=(0.2, 0.8, 0.35))
    r = sim.render(sim.paper_rig(), scene, render_pattern(SPEC), cond, seed=0)
    sm = decode(r.image, SPEC)
    g, b = _flood(scene, cond, 1)
    return r, sm, g, b


def test_plane_texture_is_flat_and_the_markers_and_colour_ripple_are_divided_out(plane_frames):
    r, sm, g, b = plane_frames
    use = sm.valid & ~r.depth_edge
    t = intensity(r.image, sm.column, sm.valid, SPEC)
    assert np.isnan(t[~sm.valid]).all() and np.isfinite(t[use]).all()
    assert abs(float(np.mean(t[sm.valid])) - 1.0) < 1e-4     # scaled: the average decoded pixel is 1
    err, corr = _relative_errors(t, g, b, use)
    assert np.median(err) < 0.02 and np.percentile(err, 95) < 0.06 and corr > 0.995   # measured 1.4 %, 4.4 %, 0.9987
    # counterfactuals: the markers' double light left in (a pattern without markers), no box along the row
    # (the green-ish albedo reflects the green stripes 2.3 times as much as the blue ones), no light blur
    err_m, _ = _relative_errors(intensity(r.image, sm.column, sm.valid, PatternSpec(markers=False)), g, b, use)
    err_1, _ = _relative_errors(intensity(r.image, sm.column, sm.valid, SPEC, window_px=1), g, b, use)
    err_0, _ = _relative_errors(intensity(r.image, sm.column, sm.valid, SPEC, light_blur_px=0), g, b, use)
    assert np.percentile(err_m, 95) > 4 * np.percentile(err, 95)      # measured 45 %
    assert np.percentile(err_1, 95) > 2 * np.percentile(err, 95)      # measured 15.5 %
    assert np.percentile(err_0, 95) > np.percentile(err, 95)          # measured 5.5 %


def test_stripe_period_from_the_columns_matches_the_truth(plane_frames):
    r, sm, _, _ = plane_frames
    use = sm.valid & ~r.depth_edge
    du = np.abs(np.diff(r.proj_xy[..., 0], axis=1))[use[:, 1:] & use[:, :-1]]
    truth = 2 * SPEC.stripe_px / np.median(du)
    assert abs(stripe_period_px(sm.column, sm.valid, SPEC.stripe_px) - truth) < 0.01 * truth
    assert np.isnan(stripe_period_px(sm.column, np.zeros_like(sm.valid), SPEC.stripe_px))


def test_face_texture_follows_the_uniformly_lit_face():
    """The simulated head (skin albedo, eyebrows, lips; typical preset) against its cyan-flood render."""
    cond = dataclasses.replace(sim.preset("typical"), supersample=1)
    scene = sim.scenes.head(650.0)
    r = sim.render(sim.paper_rig(), scene, render_pattern(SPEC), cond, seed=0)
    sm = decode(r.image, SPEC)
    g, b = _flood(scene, cond, 1)
    use = sm.valid & ~r.depth_edge & (r.object_id == 0)
    t = intensity(r.image, sm.column, sm.valid, SPEC)
    err, corr = _relative_errors(t, g, b, use)
    assert np.median(err) < 0.05 and np.percentile(err, 95) < 0.15 and corr > 0.98   # measured 2.7 %, 10.3 %, 0.994


def test_pattern_light_counts_the_lit_channels():
    lab = SPEC.column_labels()
    light = pattern_light(SPEC)
    assert light.shape == (SPEC.width,) and set(np.unique(light)) == {1.0, 2.0}
    assert np.array_equal(light == 2, lab == 3)
    assert np.array_equal(pattern_light(PatternSpec(markers=False)), np.ones(SPEC.width, np.float32))
    soft = pattern_light(SPEC, 1.0)
    assert abs(soft.sum() - light.sum()) < 1e-2 * light.sum() and soft.max() < 2.0


def test_to_grey():
    t = np.array([[np.nan, 0.0, 0.25], [1.0, 4.0, -1.0]], np.float32)
    g = to_grey(t, white=1.0, gamma=1.0)
    assert g.dtype == np.uint8 and g.tolist() == [[0, 0, 64], [255, 255, 0]]
    assert to_grey(t, white=1.0)[0, 2] == round(255 * 0.25 ** (1 / 2.2))
    assert to_grey(np.full((2, 2), np.nan, np.float32)).max() == 0


def test_bad_input_names_the_argument():
    img = np.zeros((4, 5, 3), np.uint8)
    col = np.zeros((4, 5), np.float32)
    ok = np.ones((4, 5), bool)
    with pytest.raises(GBError, match="uint8 RGB"):
        intensity(img[..., 0], col, ok, SPEC)
    with pytest.raises(GBError, match="must be the image"):
        intensity(img, col[:3], ok, SPEC)
    with pytest.raises(GBError, match="window_px"):
        intensity(img + 50, col + 20, ok, SPEC, window_px=0)
    with pytest.raises(GBError, match="light_blur_px"):
        intensity(img, col, ok, SPEC, light_blur_px=-1)
    assert np.isnan(intensity(img, col, ~ok, SPEC)).all()   # nothing decoded: all NaN, no error
