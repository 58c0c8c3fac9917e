"""Comparing calibrations: identical files, known perturbations, camera-only files, the command."""
import subprocess
import sys

import numpy as np
import pytest

from gbcal.diff import (Stats, common_planes, compare, pixel_grid, plane_distances_mm, ray_plane,
                        reprojection_distances_px)
from gbscan.calibfile import Calibration, calibration_from_rig, load_calibration, save_calibration
from gbscan.camera import Camera
from gbscan.errors import GBError
from gbscan.pattern import PatternSpec
from gbscan.rig import paper_rig


@pytest.fixture(scope="module")
def calib():
    return calibration_from_rig(paper_rig(), PatternSpec())


def copy(c, **changes):
    fields = dict(camera=c.camera, plane_index=c.plane_index.copy(), plane_column=c.plane_column.copy(),
                  plane_normal=c.plane_normal.copy(), plane_d=c.plane_d.copy(), pattern=c.pattern)
    fields.update(changes)
    return Calibration(**fields)


def test_ray_plane():
    n = np.array([0.6, 0.0, 0.8])
    rays = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.8, 0.0, -0.6], [-0.6, 0.0, -0.8]])
    p = ray_plane(rays, n, 400.0)
    np.testing.assert_allclose(p[0], [0, 0, 500.0])
    np.testing.assert_allclose(p[1], [240.0, 0, 320.0])
    assert np.isnan(p[2]).all()  # parallel to the plane
    assert np.isnan(p[3]).all()  # behind the camera
    np.testing.assert_allclose(p[:2] @ n, 400.0)


def test_identical_calibrations_agree_exactly(calib):
    r = compare(calib, copy(calib))
    assert r["distance_mm"].count > 10000 and r["distance_mm"].max == 0.0
    assert r["reprojection_px"].max < 1e-9  # back-projection inverts the distortion to ~1e-13 px
    assert all(v == 0.0 for v in r["intrinsics"].values())
    assert r["planes"] == {"common": calib.n_planes, "only_a": 0, "only_b": 0}


def test_plane_shifted_along_its_normal(calib):
    # shifting plane k by 1 mm along its normal moves a ray's point by 1 / |n . r| mm along the ray
    k = 60
    d_b = calib.plane_d.copy()
    d_b[k] += 1.0
    b = copy(calib, plane_d=d_b)
    cam = calib.camera
    q = pixel_grid(cam, 8.0)
    rays = cam.rays(q)
    z = ray_plane(rays, calib.plane_normal[k], calib.plane_d[k])[:, 2]
    inside = (z >= 400) & (z <= 1000)
    expected = 1.0 / np.abs(rays[inside] @ calib.plane_normal[k])
    got = plane_distances_mm(cam, calib.plane_normal[[k]], calib.plane_d[[k]], cam, b.plane_normal[[k]],
                             b.plane_d[[k]], q=q)
    np.testing.assert_allclose(np.sort(got), np.sort(expected), rtol=1e-9)
    assert got.min() >= 1.0 - 1e-9
    # over all planes: only plane k's points move
    r = compare(calib, b)
    assert r["distance_mm"].max == pytest.approx(expected.max(), rel=1e-9)
    assert r["distance_mm"].median == 0.0


def test_every_plane_shifted(calib):
    b = copy(calib, plane_d=calib.plane_d + 1.0)
    st = compare(calib, b, depth_mm=(500, 800))["distance_mm"]
    assert st.count > 1000 and 1.0 <= st.median <= st.p95 <= st.max
    # the paper rig's triangulation angle is 10-25 degrees: a 1 mm plane shift is 2.5-6 mm along a ray
    assert 2.0 < st.median < 6.0


def test_planes_matched_by_index(calib):
    idx, ia, ib = common_planes([3, 5, 7, 9], [5, 6, 9])
    np.testing.assert_array_equal(idx, [5, 9])
    np.testing.assert_array_equal(ia, [1, 3])
    np.testing.assert_array_equal(ib, [0, 2])
    half = slice(0, calib.n_planes // 2)
    b = copy(calib, plane_index=calib.plane_index[half], plane_column=calib.plane_column[half],
             plane_normal=calib.plane_normal[half], plane_d=calib.plane_d[half])
    r = compare(calib, b)
    n = calib.n_planes
    assert r["planes"]["common"] == n // 2 and r["planes"]["only_a"] == n - n // 2
    assert r["distance_mm"].max == 0.0


def test_camera_only_reprojection():
    K = np.array([[800.0, 0.0, 319.5], [0.0, 800.0, 239.5], [0.0, 0.0, 1.0]])
    a = Camera(640, 480, K)
    K2 = K.copy()
    K2[0, 2] += 1.0
    d = reprojection_distances_px(a, Camera(640, 480, K2))
    np.testing.assert_allclose(d, 1.0, atol=1e-9)
    K3 = K.copy()
    K3[0, 0] *= 1.01  # 1 % longer focal length: u - cx grows by 1 %
    q = pixel_grid(a, 16.0)
    d = reprojection_distances_px(a, Camera(640, 480, K3), q=q, n_depths=3)
    np.testing.assert_allclose(d, np.tile(0.01 * np.abs(q[:, 0] - 319.5), 3), atol=1e-9)
    dist = Camera(640, 480, K, [-0.2, 0.1, 0.0, 0.0, 0.0])
    assert reprojection_distances_px(dist, dist).max() < 1e-8


def test_bad_inputs(calib):
    small = Camera(320, 240, np.array([[400.0, 0, 159.5], [0, 400.0, 119.5], [0, 0, 1]]))
    with pytest.raises(GBError, match="different image sizes"):
        reprojection_distances_px(calib.camera, small)
    with pytest.raises(GBError, match="depth range"):
        compare(calib, calib, depth_mm=(900, 400))
    with pytest.raises(GBError, match="grid step"):
        pixel_grid(calib.camera, 0)
    st = Stats.of(np.array([np.nan]))
    assert st.count == 0 and np.isnan(st.median)


def gbcal(*args):
    return subprocess.run([sys.executable, "-m", "gbcal.cli", *map(str, args)], capture_output=True, text=True)


def test_diff_command(calib, tmp_path):
    a = save_calibration(tmp_path / "a.yaml", calib)
    d_b = calib.plane_d.copy()
    d_b += 0.5
    b = save_calibration(tmp_path / "b.yaml", copy(calib, plane_d=d_b))
    cam_only = save_calibration(tmp_path / "cam.yaml", copy(calib, plane_index=[], plane_column=[],
                                                           plane_normal=np.zeros((0, 3)), plane_d=[]))
    assert load_calibration(cam_only, require_planes=False).n_planes == 0
    r = gbcal("diff", a, a)
    assert r.returncode == 0, r.stderr
    assert "median 0.0000 mm, 95% 0.0000 mm, max 0.0000 mm" in r.stdout and "fx +0.000 px" in r.stdout
    r = gbcal("diff", a, b, "--depth-mm", 500, 800)
    assert r.returncode == 0 and f"{calib.n_planes} in common" in r.stdout
    median = float(r.stdout.split("median ")[-1].split(" mm")[0])
    expected = compare(calib, load_calibration(b), depth_mm=(500, 800))["distance_mm"].median
    assert median == pytest.approx(expected, abs=1e-4) and median > 0.5
    r = gbcal("diff", cam_only, a)
    assert r.returncode == 0 and "none in common" in r.stdout and "reprojection" in r.stdout
    for args in ([a, tmp_path / "missing.yaml"], [a, a, "--depth-mm", 900, 100]):
        r = gbcal("diff", *args)
        assert r.returncode == 1 and "Traceback" not in r.stderr
        assert len(r.stderr.strip().splitlines()) == 1
