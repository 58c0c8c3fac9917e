"""Cleaning filters on analytic scenes with noise and planted outliers (known ground truth)."""
import numpy as np
import pytest
from test_triangulate import pixel_rays, tilted_plane, truth

from gbscan.calibfile import calibration_from_rig
from gbscan.clean import (CODE, CleanParams, clean, cluster_filter, confidence_filter, depth_range_filter,
                          discontinuity_filter, gap_edge_filter, grazing_filter, grid_normals, outlier_filter,
                          sigma_filter)
from gbscan.errors import GBError
from gbscan.pattern import PatternSpec
from gbscan.rig import paper_rig
from gbscan.triangulate import PlaneTable, triangulate


@pytest.fixture(scope="module")
def scene():
    """Sphere (r 90 mm at 600 mm) before a tilted wall at ~800 mm, decoded with column noise."""
    rig = paper_rig()
    calib = calibration_from_rig(rig, PatternSpec())
    p, col, oid = truth(rig, spheres=[((20.0, -10.0, 600.0), 90.0)], planes=[tilted_plane(800.0, (0.2, 0.1, -1.0))])
    rng = np.random.default_rng(1)
    noisy = col + rng.normal(0, 0.05, col.shape)  # projector px: ~0.06 mm depth noise at 650 mm
    xyz = triangulate(pixel_rays(rig.camera), noisy, PlaneTable.from_calibration(calib))
    return rig, p, xyz, oid


def depth_edges(p, ratio=0.02, width=2):
    """True depth discontinuities / silhouettes, dilated by ``width`` px."""
    import cv2

    z = p[..., 2]
    fin = np.isfinite(z)
    e = np.zeros(z.shape, bool)
    with np.errstate(invalid="ignore"):
        for a, b, sa, sb in (((slice(None), slice(1, None)), (slice(None), slice(None, -1)), 1, 1),
                             ((slice(1, None), slice(None)), (slice(None, -1), slice(None)), 1, 1)):
            j = (np.abs(z[a] - z[b]) > ratio * np.fmin(z[a], z[b])) | (fin[a] != fin[b])
            e[a] |= j
            e[b] |= j
    return cv2.dilate(e.view(np.uint8), np.ones((2 * width + 1, 2 * width + 1), np.uint8)).astype(bool)


def true_angle_deg(p, centre, oid, wall_n):
    """Angle between viewing ray and true normal of the analytic scene."""
    n = np.where((oid == 0)[..., None], p - centre, -wall_n)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    r = p / np.linalg.norm(p, axis=-1, keepdims=True)
    return np.degrees(np.arccos(np.clip(-(n * r).sum(-1), -1, 1)))


def plant(xyz, p, rng):
    """Spikes, flying pixels at depth edges, a detached cluster: returns (corrupted xyz, planted mask)."""
    out = xyz.copy()
    valid = np.isfinite(xyz[..., 2])
    planted = np.zeros(valid.shape, bool)
    # 1. random spikes: 0.5% of points moved 4-60 mm along their ray
    idx = np.flatnonzero(valid)
    spikes = rng.choice(idx, size=idx.size // 200, replace=False)
    scale = 1 + rng.choice([-1, 1], spikes.size) * rng.uniform(0.006, 0.09, spikes.size)
    out.reshape(-1, 3)[spikes] *= scale[:, None]
    planted.flat[spikes] = True
    # 2. flying pixels: the background pixel right of each foreground->background edge becomes a blend
    z = np.where(valid, xyz[..., 2], np.nan)
    with np.errstate(invalid="ignore"):
        edge = (z[:, 1:] - z[:, :-1]) > 0.05 * z[:, :-1]  # pixel u+1 is background, u foreground
    vv, uu = np.nonzero(edge)
    a = rng.uniform(0.2, 0.8, vv.size)
    zf, zb = z[vv, uu], z[vv, uu + 1]
    out[vv, uu + 1] *= ((a * zf + (1 - a) * zb) / zb)[:, None]
    planted[vv, uu + 1] = True
    # 3. a detached 10x10 cluster 80 mm in front of the wall
    v0 = int(np.flatnonzero(valid.any(1))[0]) + 15
    u0 = int(np.flatnonzero(valid[v0])[0]) + 20
    assert valid[v0:v0 + 10, u0:u0 + 10].all()
    blk = out[v0:v0 + 10, u0:u0 + 10]
    blk *= ((blk[..., 2] - 80.0) / blk[..., 2])[..., None]
    planted[v0:v0 + 10, u0:u0 + 10] = True
    return out, planted & valid, (spikes.size, vv.size, 100)


def test_cleaning_removes_planted_outliers_and_keeps_good_points(scene):
    rig, p, xyz, oid = scene
    rng = np.random.default_rng(7)
    bad_xyz, planted, (n_spikes, n_flying, n_cluster) = plant(xyz, p, rng)
    assert n_spikes > 500 and n_flying > 100
    params = CleanParams()
    res = clean(bad_xyz, None, params)
    kept = res.kept
    angle = true_angle_deg(p, np.array([20.0, -10.0, 600.0]), oid, tilted_plane(800.0, (0.2, 0.1, -1.0))[0])
    good = np.isfinite(xyz[..., 2]) & ~planted & ~depth_edges(p) & (angle < params.max_angle_deg - 5)
    removed_planted = 1 - (kept & planted).sum() / planted.sum()
    kept_good = (kept & good).sum() / good.sum()
    err = np.linalg.norm(bad_xyz[kept] - p[kept], axis=1)
    print(f"planted {planted.sum()}: removed {100 * removed_planted:.2f}%; good kept {100 * kept_good:.3f}%; "
          f"max error kept {err.max():.2f} mm; counts {res.counts}")
    assert removed_planted >= 0.99
    assert kept_good >= 0.995
    assert err.max() < 3.0
    assert sum(v for k, v in res.counts.items() if k not in ("input", "kept")) == (~kept).sum()
    assert res.counts["kept"] == kept.sum()
    assert set(np.unique(res.reason)) <= set(CODE.values())


def test_clean_data_loses_almost_nothing_but_edges(scene):
    _, p, xyz, _ = scene
    res = clean(xyz, None, CleanParams())
    inner = np.isfinite(xyz[..., 2]) & ~depth_edges(p)
    assert (res.kept & inner).sum() / inner.sum() > 0.99


def test_confidence_and_depth_range():
    xyz = np.zeros((4, 5, 3))
    xyz[..., 2] = np.linspace(100, 900, 20).reshape(4, 5)
    valid = np.ones((4, 5), bool)
    conf = np.linspace(0, 1, 20).reshape(4, 5)
    kept, name = confidence_filter(conf, valid, 0.5)
    assert name == "low_confidence" and kept.sum() == 10
    kept, name = depth_range_filter(xyz, valid, 300.0, 600.0)
    z = xyz[..., 2]
    assert name == "depth_range" and np.array_equal(kept, (z >= 300) & (z <= 600))


def test_discontinuity_cuts_both_sides_of_a_step_only():
    z = np.full((20, 30), 600.0)
    z[:, 15:] = 660.0
    xyz = np.stack([np.zeros_like(z), np.zeros_like(z), z], -1)
    kept, _ = discontinuity_filter(xyz, np.ones(z.shape, bool), 0.01)
    assert np.array_equal(np.nonzero(~kept.all(0))[0], [14, 15])
    xyz[:, 15:, 2] = 603.0  # 0.5% step: not a discontinuity at 1%
    kept, _ = discontinuity_filter(xyz, np.ones(z.shape, bool), 0.01)
    assert kept.all()


def test_outlier_filter_keeps_steep_smooth_surfaces_and_drops_spikes(scene):
    rig, _, _, _ = scene
    rays = pixel_rays(rig.camera)
    n, d = tilted_plane(650.0, (np.tan(np.radians(75)), 0.0, -1.0))  # 75 degrees steep
    s = d / (rays @ n)
    ang = np.degrees(np.arccos(np.abs(rays @ n)))
    valid = (s > 0) & (ang < 85)
    xyz = np.where(valid[..., None], rays * s[..., None], np.nan)
    assert valid.mean() > 0.3 and np.nanmax(ang[valid]) > 80
    kept, _ = outlier_filter(xyz, valid, 0.002, 1)
    inner = valid.copy()  # away from the region's border (its corners have no complete pair)
    inner[1:-1, 1:-1] = valid[:-2, 1:-1] & valid[2:, 1:-1] & valid[1:-1, :-2] & valid[1:-1, 2:] & valid[1:-1, 1:-1]
    inner[:, [0, -1]] = inner[[0, -1], :] = False
    assert kept[inner].all()
    xyz[100, 100] *= 1.006
    kept, _ = outlier_filter(xyz, valid, 0.002, 1)
    assert not kept[100, 100] and kept[99:102, 99:102].sum() == 8


def test_grid_normals_and_grazing(scene):
    rig, _, _, _ = scene
    rays = pixel_rays(rig.camera)
    for tilt in (0.0, 40.0, 70.0):
        n_true, d = tilted_plane(650.0, (np.sin(np.radians(tilt)), 0.0, -np.cos(np.radians(tilt))))
        s = d / (rays @ n_true)
        seen = (s > 0) & (s < 5000)
        xyz = np.where(seen[..., None], rays * s[..., None], np.nan)
        n = grid_normals(xyz, seen, 2)
        inner = seen.copy()
        inner[:, :3] = inner[:, -3:] = False
        inner[1:] &= inner[:-1].copy()
        assert seen.mean() > 0.5
        assert np.max(np.abs(n[inner] - n_true)) < 1e-4  # a plane: exact to float32, facing the camera
        assert np.isfinite(n[seen]).all()  # one-sided differences at the border
    # points on a plane tilted 70 deg from the optical axis are seen at 60-80 deg
    kept, name = grazing_filter(xyz, seen, 75.0)
    ang = np.degrees(np.arccos(-(rays @ n_true)))
    near = np.abs(ang - 75.0) < 0.01  # float32 normals decide these either way
    assert name == "grazing" and (ang[inner] > 75).any() and (ang[inner] < 75).any()
    assert np.array_equal(kept[inner & ~near], (ang <= 75.0)[inner & ~near])


def test_cluster_filter():
    valid = np.zeros((50, 50), bool)
    valid[5:30, 5:30] = True
    valid[40:45, 40:45] = True
    valid[40:42, 5:6] = True
    kept, name = cluster_filter(valid, 30)
    assert name == "small_cluster" and kept.sum() == 625 and kept[5:30, 5:30].all()


def test_bad_params_raise():
    for kw in ({"min_confidence": 2}, {"min_depth_mm": 500, "max_depth_mm": 100}, {"max_angle_deg": 0},
               {"min_pairs": 5}, {"max_jump": 0}, {"max_gap_px": -1}, {"gap_far_px": -1},
               {"gap_near_px": -2}):
        with pytest.raises(GBError, match="cleaning parameters"):
            CleanParams(**kw)
    with pytest.raises(GBError, match="organised"):
        clean(np.zeros((10, 3)))


def _reference_normals(xyz, valid, s):
    """Plain numpy grid normals (the definition): central differences over ``s`` px where both
    sides are valid, one-sided otherwise, n = t_v x t_u facing the camera; NaN without tangents."""
    p = np.where(valid[..., None], np.asarray(xyz, np.float64), np.nan)

    def tangent(axis):
        fwd = np.full_like(p, np.nan)
        bwd = np.full_like(p, np.nan)
        if axis == 1:
            fwd[:, :-s] = p[:, s:] - p[:, :-s]
            bwd[:, s:] = fwd[:, :-s]
        else:
            fwd[:-s] = p[s:] - p[:-s]
            bwd[s:] = fwd[:-s]
        central = fwd + bwd
        one = np.where(np.isnan(fwd), bwd, fwd)
        return np.where(np.isnan(central), one, central)

    n = np.cross(tangent(0), tangent(1))
    with np.errstate(invalid="ignore", divide="ignore"):
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        n *= np.where((n * p).sum(-1) > 0, -1.0, 1.0)[..., None]
    return n


@pytest.mark.parametrize("step", [1, 2, 3])
def test_grid_normals_match_the_finite_difference_definition(scene, step):
    _, _, xyz, _ = scene
    rng = np.random.default_rng(3)
    valid = np.isfinite(xyz[..., 2]) & (rng.random(xyz.shape[:2]) > 0.05)  # holes everywhere
    n = grid_normals(xyz.astype(np.float32), valid, step)
    ref = _reference_normals(xyz.astype(np.float32), valid, step)
    assert n.dtype == np.float32 and n.shape == xyz.shape
    np.testing.assert_array_equal(np.isnan(n[..., 0]), np.isnan(ref[..., 0]))
    ok = np.isfinite(ref[..., 0])
    assert ok.sum() > 0.8 * valid.sum()
    assert np.max(np.abs(n[ok] - ref[ok])) < 1e-5
    assert np.isnan(n[~valid]).all()


def test_clean_is_the_filters_in_order(scene):
    """clean() runs compiled kernels on one reason map; the result must be exactly the public
    filters applied one after the other (first rejecting filter wins)."""
    _, p, xyz, _ = scene
    rng = np.random.default_rng(11)
    bad_xyz, _, _ = plant(xyz, p, rng)
    bad_xyz = bad_xyz.astype(np.float32)
    bad_xyz[rng.random(xyz.shape[:2]) < 0.01] = np.nan            # no plane
    bad_xyz[300:310, 300:310, 2] = 5.0                             # out of the depth range
    conf = rng.uniform(0.0, 1.0, xyz.shape[:2]).astype(np.float32)  # 20% below min_confidence
    conf[100:140, 200:260] = np.nan                                  # counts as 0
    sigma = rng.uniform(0.0, 0.35, xyz.shape[:2]).astype(np.float32)  # predicted error (mm): ~14% above 0.3
    sigma[400:420, 100:300] = np.nan                                  # unknown: dropped
    upstream = np.zeros(xyz.shape[:2], np.uint8)
    upstream[:, :20] = CODE["not_decoded"]
    params = CleanParams(max_angle_deg=70.0, max_sigma_mm=0.3)
    res = clean(bad_xyz, conf, params, reason=upstream, sigma_mm=sigma)
    with pytest.raises(GBError, match="sigma_mm"):
        clean(bad_xyz, conf, params, reason=upstream)
    with pytest.raises(GBError, match="sigma_mm"):
        clean(bad_xyz, conf, params, reason=upstream, sigma_mm=sigma[:, 1:])

    reason = upstream.copy()
    finite = np.isfinite(bad_xyz).all(-1)
    reason[(reason == 0) & ~finite] = CODE["no_plane"]
    valid = reason == 0
    chain = [lambda v: confidence_filter(conf, v, params.min_confidence),
             lambda v: depth_range_filter(bad_xyz, v, params.min_depth_mm, params.max_depth_mm),
             lambda v: sigma_filter(sigma, v, params.max_sigma_mm),
             lambda v: outlier_filter(bad_xyz, v, params.outlier_tol, params.min_pairs),
             lambda v: discontinuity_filter(bad_xyz, v, params.max_jump),
             lambda v: gap_edge_filter(bad_xyz, v, params.max_jump, params.max_gap_px, params.gap_far_px,
                                           params.gap_near_px),
             lambda v: grazing_filter(bad_xyz, v, params.max_angle_deg, params.normal_step_px),
             lambda v: cluster_filter(v, (xyz.shape[0] * xyz.shape[1]) // 1000)]
    counts = {}
    for f in chain:
        kept, name = f(valid)
        reason[valid & ~kept] = CODE[name]
        counts[name] = int((valid & ~kept).sum())
        valid = kept
    np.testing.assert_array_equal(res.reason, reason)
    assert all(res.counts[k] == v for k, v in counts.items()) and min(counts.values()) > 0, (res.counts, counts)
    assert res.counts["kept"] == valid.sum() and np.array_equal(res.kept, valid)
    assert res.counts["input"] == int(((upstream == 0) & finite).sum())


# -- depth edges across holes (gap_edge_filter) -------------------------------------------------
def _edge_with_hole(gap_px, far_mm=900.0, wrong_px=0):
    """Rows of a far wall (columns < 15) beside a near object (600 mm, columns >= 15), like a
    decoder leaves them: the wall's depth spills ``wrong_px`` px into the object, then ``gap_px``
    columns of the object are missing.  Returns (xyz, valid, wrong)."""
    z = np.full((12, 40), far_mm)
    z[:, 15 + wrong_px:] = 600.0
    valid = np.ones(z.shape, bool)
    valid[:, 15 + wrong_px:15 + wrong_px + gap_px] = False
    wrong = np.zeros(z.shape, bool)
    wrong[:, 15:15 + wrong_px] = True
    xyz = np.stack([np.zeros_like(z), np.zeros_like(z), np.where(valid, z, np.nan)], -1)
    return xyz, valid, wrong


def _dropped_columns(valid, kept):
    d = valid & ~kept
    assert np.array_equal(d, d.any(0)[None].repeat(d.shape[0], 0))  # whole columns
    return np.nonzero(d.any(0))[0].tolist()


@pytest.mark.parametrize("gap_px", [1, 3, 8])
def test_gap_edge_drops_run_ends_across_a_hole(gap_px):
    xyz, valid, _ = _edge_with_hole(gap_px)
    # the plain jump test has no pair to compare
    assert discontinuity_filter(xyz, valid, 0.01)[0].sum() == valid.sum()
    kept, name = gap_edge_filter(xyz, valid, 0.01, max_gap_px=8)
    assert name == "gap_edge" and _dropped_columns(valid, kept) == [13, 14]  # far side, 2 px
    kept, _ = gap_edge_filter(xyz, valid, 0.01, max_gap_px=8, far_px=1, near_px=2)
    assert _dropped_columns(valid, kept) == [14, 15 + gap_px, 16 + gap_px]


def test_gap_edge_removes_the_far_surface_spilled_over_a_silhouette():
    """The wall's depth continues 2 px into the object, then a hole, then the object: no
    neighbour pair jumps, every wrong point lies on the wall; the gap test drops exactly them."""
    xyz, valid, wrong = _edge_with_hole(3, wrong_px=2)
    assert discontinuity_filter(xyz, valid, 0.01)[0].sum() == valid.sum()
    inner = wrong.copy()
    inner[[0, -1]] = False  # the first and last rows' run ends have no complete pair: outliers
    assert outlier_filter(xyz, valid, 0.002, 1)[0][inner].all()
    kept, _ = gap_edge_filter(xyz, valid, 0.01, 8)
    assert np.array_equal(valid & ~kept, wrong)
    res = clean(xyz, None, CleanParams(min_cluster_px=0), reason=(~valid).view(np.uint8))
    assert not (res.kept & wrong).any() and res.kept[1:-1].sum() == (valid & ~wrong)[1:-1].sum()
    res = clean(xyz, None, CleanParams(min_cluster_px=0, max_gap_px=0), reason=(~valid).view(np.uint8))
    assert res.kept[inner].all() and res.counts["gap_edge"] == 0  # what the cleaning did before


def test_gap_edge_keeps_holes_in_smooth_and_steep_surfaces(scene):
    rig, _, _, _ = scene
    rays = pixel_rays(rig.camera)
    n, d = tilted_plane(650.0, (np.tan(np.radians(75)), 0.0, -1.0))  # 75 degrees: ~3 mm per pixel
    s = d / (rays @ n)
    valid = (s > 0) & (np.degrees(np.arccos(np.abs(rays @ n))) < 79)
    xyz = np.where(valid[..., None], rays * s[..., None], np.nan)
    rng = np.random.default_rng(5)
    holes = valid & (rng.random(valid.shape) < 0.2)  # 20% of the pixels missing, holes of any length
    holes[200:208, :] = True                         # and an 8-row band
    holes[:, 300:309] = True                         # and a 9-column band (longer than max_gap_px)
    ok = valid & ~holes
    kept, _ = gap_edge_filter(xyz, ok, 0.01, 8, 2, 2)
    assert ok.sum() > 0.5 * valid.sum() and np.array_equal(kept, ok)


def test_gap_edge_reach_slope_and_parameters():
    xyz, valid, _ = _edge_with_hole(9)
    assert gap_edge_filter(xyz, valid, 0.01, 8)[0].sum() == valid.sum()  # far side out of reach
    assert _dropped_columns(valid, gap_edge_filter(xyz, valid, 0.01, 9)[0]) == [13, 14]
    assert gap_edge_filter(xyz, valid, 0.01, 0, 2, 2)[0].sum() == valid.sum()  # disabled
    xyz, valid, _ = _edge_with_hole(3, far_mm=630.0)  # 30 mm over 4 px: 1.25% per px > 1%
    assert _dropped_columns(valid, gap_edge_filter(xyz, valid, 0.01, 8)[0]) == [13, 14]
    xyz, valid, _ = _edge_with_hole(3, far_mm=620.0)  # 20 mm over 4 px: 0.83% per px, a slope
    assert gap_edge_filter(xyz, valid, 0.01, 8, 2, 2)[0].sum() == valid.sum()
    with pytest.raises(GBError, match="gap_edge_filter"):
        gap_edge_filter(xyz, valid, 0.01, -1)
