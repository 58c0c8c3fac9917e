"""The Scanner API and the ``gbscan scan`` / ``gbscan mesh`` commands."""
import os
import subprocess
import sys

import numpy as np
import pytest
import yaml
from test_triangulate import tilted_plane, truth

from gbscan import cli
from gbscan.calibfile import calibration_from_rig, save_calibration
from gbscan.errors import GBError
from gbscan.io import write_png
from gbscan.mesh import read_cloud_ply
from gbscan.pattern import PatternSpec
from gbscan.rig import paper_rig
from gbscan.scan import Scanner

SPHERE = ((10.0, -5.0, 620.0), 85.0)
WALL = tilted_plane(760.0, (0.15, 0.05, -1.0))


@pytest.fixture(scope="module")
def rig():
    return paper_rig()


@pytest.fixture(scope="module")
def scene(rig):
    return truth(rig, spheres=[SPHERE], planes=[WALL])


@pytest.fixture(scope="module")
def scanner(rig):
    return Scanner(calibration_from_rig(rig, PatternSpec()))


@pytest.fixture()
def calib_file(tmp_path, rig):
    return save_calibration(tmp_path / "calib.yaml", calibration_from_rig(rig, PatternSpec()))


# -- API -----------------------------------------------------------------------------------------
def test_reconstruct_from_true_columns_is_exact(scanner, scene):
    p, col, _ = scene
    s = scanner.reconstruct(col, clean=False)
    ok = np.isfinite(col)
    assert np.array_equal(s.valid, ok)
    assert np.max(np.abs(s.xyz[ok] - p[ok])) < 1e-3  # float32 storage of ~700 mm values
    assert s.points.shape == (ok.sum(), 3) and s.points.dtype == np.float32
    assert s.counts["not_decoded"] == (~ok).sum() and s.counts["kept"] == ok.sum()
    assert np.all((s.normals * s.points).sum(1) < 0)  # normals face the camera


def test_scan_texture_is_the_kept_pixels_grey_and_goes_into_the_cloud(tmp_path, scanner, scene):
    """Scanner.scan keeps its frame: a stripe-free texture on exactly the kept pixels, in the PLY and the
    open3d cloud; a scan from external columns has none (and its PLY no colour properties)."""
    from gbscan import sim
    from gbscan.pattern import render_pattern

    r = sim.render(sim.paper_rig(), sim.scenes.head(650.0), render_pattern(PatternSpec()), "typical", seed=0)
    s = scanner.scan(r.image)
    t = s.texture
    assert t.shape == s.shape and np.array_equal(np.isfinite(t), s.valid) and s.texture is t   # computed once
    g = s.grey()
    assert g.dtype == np.uint8 and (g[~s.valid] == 0).all() and np.percentile(g[s.valid], 50) > 100
    s.save_ply(tmp_path / "c.ply")
    c = read_cloud_ply(tmp_path / "c.ply")
    np.testing.assert_array_equal(c.colors[:, 0], g[s.valid])
    assert np.allclose(np.asarray(s.to_open3d().colors)[:, 0], g[s.valid] / 255.0)
    s.save_ply(tmp_path / "plain.ply", colors=False)
    assert read_cloud_ply(tmp_path / "plain.ply").colors is None
    p, col, _ = scene
    ext = scanner.reconstruct(col, clean=False)
    assert ext.texture is None and ext.grey() is None and ext.mesh_arrays("grid").colors is None
    ext.save_ply(tmp_path / "ext.ply")
    assert b"red" not in (tmp_path / "ext.ply").read_bytes()[:400]


def test_reconstruct_cleans_and_reports_reasons(scanner, scene):
    p, col, _ = scene
    s = scanner.reconstruct(col, np.full(col.shape, 0.9, np.float32))
    masks = s.masks
    assert set(masks) >= {"ok", "not_decoded", "discontinuity"}
    assert sum(int(m.sum()) for m in masks.values()) == col.size
    assert np.array_equal(masks["ok"], s.valid)
    assert s.n_points > 0.95 * np.isfinite(col).sum()
    low = scanner.reconstruct(col, np.full(col.shape, 0.1, np.float32))
    assert low.n_points == 0 and low.counts["low_confidence"] == np.isfinite(col).sum()
    assert {"triangulate", "clean", "normals", "total"} <= set(s.timings_ms)
    assert "points" in s.summary()


def test_scan_mesh_and_open3d(scanner, scene):
    _, col, _ = scene
    s = scanner.reconstruct(col)
    m = s.mesh_arrays("grid")
    assert m.n_triangles > 1.5 * s.n_points
    pc = s.to_open3d()
    assert len(pc.points) == s.n_points and pc.has_normals()
    tm = s.mesh("grid")
    assert len(tm.triangles) == m.n_triangles
    with pytest.raises(GBError, match="grid' or 'poisson"):
        s.mesh_arrays("marching")


def test_scanner_validates_inputs(rig, scanner):
    cal = calibration_from_rig(rig, PatternSpec())
    with pytest.raises(GBError, match="differs from the calibration"):
        Scanner(cal, pattern=PatternSpec(stripe_px=10))
    cal.plane_index, cal.plane_column = cal.plane_index[:1], cal.plane_column[:1]
    cal.plane_normal, cal.plane_d = cal.plane_normal[:1], cal.plane_d[:1]
    with pytest.raises(GBError, match="at least 2"):
        Scanner(cal)
    with pytest.raises(GBError, match="but the calibration's camera is 640x480"):
        scanner.scan(np.zeros((240, 320, 3), np.uint8))
    with pytest.raises(GBError, match="column map"):
        scanner.reconstruct(np.zeros((10, 10)))



def test_scanner_measures_the_camera_once_per_stream(rig):
    """A Scanner's frames are one stream: the second reuses the first's measurements of the camera
    (``stats['stream']``), every ``remeasure_every``-th measures again (1: every frame), and a
    bad ``remeasure_every`` is named."""
    from gbscan import sim
    from gbscan.pattern import render_pattern

    cal = calibration_from_rig(rig, PatternSpec())
    import dataclasses

    cond = dataclasses.replace(sim.preset("typical"), supersample=1)
    img = sim.render(rig, sim.scenes.sphere(), render_pattern(PatternSpec()), cond, seed=0).image
    sc = Scanner(cal, remeasure_every=2)
    said = [sc.scan(img).stripemap.stats["stream"]["lateral_ca"] for _ in range(3)]
    assert said == ["measured", "reused (measured 1 frame before)", "measured"]
    every = Scanner(cal, remeasure_every=1)
    assert [every.scan(img).stripemap.stats["stream"]["resample"] for _ in range(2)] == ["measured"] * 2
    assert Scanner(cal).memo.every == 16
    with pytest.raises(GBError, match="Scanner: remeasure_every"):
        Scanner(cal, remeasure_every=0)


# -- CLI -----------------------------------------------------------------------------------------
def fake_decoder(monkeypatch, col):
    """Replace the decoder by the ground truth: the CLI plumbing is tested without its noise."""
    import gbscan.decode as dec

    def decode(image, pattern, params=None, keep_stages=False, stripe_range=None, memo=None):
        ok = np.isfinite(col)
        z = np.zeros(col.shape, np.int32)
        return dec.StripeMap(column=col.astype(np.float32), stripe=np.where(ok, 1, -1).astype(np.int32),
                             confidence=np.where(ok, 0.9, 0).astype(np.float32),
                             mask=np.where(ok, 0, 1).astype(np.uint8), relative=z, region=z,
                             labels=z.astype(np.uint8), stats={}, pattern=pattern)

    monkeypatch.setattr(dec, "decode", decode)


def run_main(capsys, *args):
    rc = cli.main([str(a) for a in args])
    out, err = capsys.readouterr()
    return rc, out, err


def test_scan_command_writes_every_output(tmp_path, monkeypatch, capsys, calib_file, scene):
    p, col, _ = scene
    fake_decoder(monkeypatch, col)
    img = write_png(tmp_path / "frame.png", np.full((480, 640, 3), 90, np.uint8))
    out = tmp_path / "out"
    out.mkdir()
    rc, text, err = run_main(capsys, "scan", img, "--calib", calib_file, "-o", out / "cloud.ply",
                             "--xyz", out / "xyz.npy", "--mesh", out / "mesh.ply", "--preview", out / "prev")
    assert rc == 0, err
    assert "removed:" in text and "points:" in text and "time (ms)" in text and "wrote" in text
    xyz = np.load(out / "xyz.npy")
    assert xyz.dtype == np.float32 and xyz.shape == (480, 640, 3)
    ok = np.isfinite(xyz[..., 2])
    assert ok.sum() > 0.9 * np.isfinite(col).sum() and np.max(np.abs(xyz[ok] - p[ok])) < 1e-3
    cloud = read_cloud_ply(out / "cloud.ply")
    assert cloud.organised and len(cloud.points) == ok.sum()
    # the grey texture as vertex colours (this fake frame is uniform grey: white but on the marker columns,
    # whose light the texture divides out, and their box windows)
    c = cloud.colors
    assert c is not None and c.shape == (ok.sum(), 3) and (c == c[:, :1]).all() and np.median(c) > 200
    assert {f.name for f in (out / "prev").iterdir()} == {"depth.png", "coverage.png", "shaded_camera.png",
                                                          "shaded_angle.png", "texture.png", "textured_angle.png"}
    assert not [f for f in out.rglob(".*")]  # no temporary files left
    import open3d as o3d
    assert o3d.io.read_triangle_mesh(str(out / "mesh.ply")).has_vertex_colors()
    # mesh the saved cloud: grid (organised) to OBJ and PLY, Poisson to STL and PLY; colours carried to the PLYs
    rc, text, err = run_main(capsys, "mesh", out / "cloud.ply", "-o", out / "grid.obj", "--smooth", "2")
    assert rc == 0, err and "triangles" in text
    rc, text, err = run_main(capsys, "mesh", out / "cloud.ply", "-o", out / "p.stl", "--method", "poisson",
                             "--depth", "6")
    assert rc == 0, err
    assert (out / "grid.obj").stat().st_size > 0 and (out / "p.stl").stat().st_size > 84
    for method in ("grid", "poisson"):
        rc, text, err = run_main(capsys, "mesh", out / "cloud.ply", "-o", out / f"{method}.ply", "--method", method,
                                 "--depth", "6")
        assert rc == 0, err
        m = o3d.io.read_triangle_mesh(str(out / f"{method}.ply"))
        assert m.has_vertex_colors() and np.median(np.asarray(m.vertex_colors)) > 0.8, method


def test_scan_command_warns_about_a_chroma_subsampled_jpeg(tmp_path, monkeypatch, capsys, calib_file, scene):
    import cv2

    _, col, _ = scene
    fake_decoder(monkeypatch, col)
    cv2.imwrite(str(tmp_path / "frame.jpg"), np.full((480, 640, 3), 90, np.uint8))   # OpenCV's default: 4:2:0
    rc, text, err = run_main(capsys, "scan", tmp_path / "frame.jpg", "--calib", calib_file, "-o", tmp_path / "c.ply")
    assert rc == 0 and "points:" in text
    assert err.startswith("warning:") and "4:2:0 chroma subsampling" in err and "PNG" in err
    write_png(tmp_path / "frame.png", np.full((480, 640, 3), 90, np.uint8))
    rc, text, err = run_main(capsys, "scan", tmp_path / "frame.png", "--calib", calib_file, "-o", tmp_path / "c.ply")
    assert rc == 0 and "warning" not in err


def test_scan_command_withholds_a_yuyv_frame_and_writes_nothing(tmp_path, capsys, calib_file):
    """A frame from a YUYV camera (pixel pairs share their colour): no points, one line saying why
    and what to do, exit 1, no file; --decode-param subsampled_chroma=decode scans it anyway."""
    from gbscan import sim as gsim
    from gbscan.pattern import render_pattern

    cond = dict(supersample=1, yuv="yuyv")
    import dataclasses

    r = gsim.render(paper_rig(), gsim.scenes.plane(650.0), render_pattern(PatternSpec()),
                    dataclasses.replace(gsim.preset("typical"), **cond), seed=0)
    write_png(tmp_path / "yuyv.png", r.image)
    rc, text, err = run_main(capsys, "scan", tmp_path / "yuyv.png", "--calib", calib_file, "-o", tmp_path / "c.ply")
    assert rc == 1 and text == "" and not (tmp_path / "c.ply").exists()
    assert err.count("\n") == 1 and "withheld" in err and "subsampled_chroma=decode" in err and "RGB or raw" in err
    rc, text, err = run_main(capsys, "scan", tmp_path / "yuyv.png", "--calib", calib_file, "-o", tmp_path / "c.ply",
                             "--decode-param", "subsampled_chroma=decode")
    assert rc == 0 and "points:" in text and (tmp_path / "c.ply").exists()
    assert "hint: " in err and "chroma subsampling" in err and "decoded anyway" in err


def test_raw_bayer_frame_from_the_simulator_to_the_cloud(tmp_path, capsys, calib_file, scanner):
    """gbscan simulate --bayer RGGB --raw writes a mosaic; gbscan scan/decode --bayer RGGB demosaic and scan it
    as the API does with gbscan.io.demosaic; without --bayer, one line says what to give."""
    import cv2

    from gbscan.io import demosaic

    raw = tmp_path / "raw.png"
    rc, text, err = run_main(capsys, "simulate", "head", "-o", raw, "--bayer", "RGGB", "--raw")
    assert rc == 0 and "raw mosaic" in text, err
    mosaic = cv2.imread(str(raw), cv2.IMREAD_UNCHANGED)
    assert mosaic.shape == (480, 640) and mosaic.dtype == np.uint8
    rc, text, err = run_main(capsys, "scan", raw, "--calib", calib_file, "-o", tmp_path / "c.ply", "--bayer", "RGGB")
    assert rc == 0, err
    want = scanner.scan(demosaic(mosaic, "RGGB"))
    assert len(read_cloud_ply(tmp_path / "c.ply").points) == want.n_points > 50_000
    rc, text, err = run_main(capsys, "decode", raw, "--calib", calib_file, "-o", tmp_path / "s.npz", "--bayer", "RGGB")
    assert rc == 0, err
    np.testing.assert_array_equal(np.load(tmp_path / "s.npz")["column"], want.stripemap.column)
    rc, text, err = run_main(capsys, "scan", raw, "--calib", calib_file, "-o", tmp_path / "c2.ply")
    _one_line_error(rc, err, "--bayer PATTERN")


def _one_line_error(rc, err, match):
    assert rc == 1, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert match in err, err


def test_scan_command_bad_inputs(tmp_path, capsys, calib_file, rig):
    good = write_png(tmp_path / "frame.png", np.zeros((480, 640, 3), np.uint8))
    small = write_png(tmp_path / "small.png", np.zeros((240, 320, 3), np.uint8))
    (tmp_path / "junk.png").write_bytes(b"\x89PNG garbage")
    d = yaml.safe_load(calib_file.read_text())
    no_planes = tmp_path / "noplanes.yaml"
    no_planes.write_text(yaml.safe_dump({**d, "planes": []}))
    v2 = tmp_path / "v2.yaml"
    v2.write_text(yaml.safe_dump({**d, "version": 2}))
    out = tmp_path / "o"
    out.mkdir()
    cases = [
        ([small, "--calib", calib_file, "-o", out / "c.ply"], "320x240 but 640x480 was expected"),
        ([good, "--calib", no_planes, "-o", out / "c.ply"], "no light planes"),
        ([good, "--calib", v2, "-o", out / "c.ply"], "field 'version'"),
        ([tmp_path / "junk.png", "--calib", calib_file, "-o", out / "c.ply"], "could not be read as an image"),
        ([tmp_path / "none.png", "--calib", calib_file, "-o", out / "c.ply"], "does not exist"),
        ([good, "--calib", calib_file, "-o", tmp_path / "missing" / "c.ply"], "does not exist (create it first)"),
        ([good, "--calib", calib_file, "-o", out / "c.xyz"], "must end in .ply"),
        ([good, "--calib", calib_file, "-o", out / "c.ply", "--mesh", out / "m.vrml"], "must end in"),
        ([good, "--calib", calib_file, "-o", out / "c.ply", "--decode-param", "bogus=1"], "--decode-param"),
        ([good, "--calib", calib_file, "-o", out / "c.ply", "--depth-range", "900", "100"], "min_depth_mm"),
        ([good, "--calib", calib_file, "-o", out / "c.ply", "--xyz", out / "x.npy"], "no points reconstructed"),
    ]
    for args, match in cases:
        rc, _, err = run_main(capsys, "scan", *args)
        _one_line_error(rc, err, match)
    assert list(out.iterdir()) == []  # nothing written, not even temporaries


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_scan_command_read_only_output(tmp_path, capsys, calib_file):
    good = write_png(tmp_path / "frame.png", np.zeros((480, 640, 3), np.uint8))
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        rc, _, err = run_main(capsys, "scan", good, "--calib", calib_file, "-o", ro / "c.ply")
        _one_line_error(rc, err, "not writable")
    finally:
        ro.chmod(0o700)


def test_mesh_command_bad_inputs(tmp_path, capsys):
    from gbscan.mesh import write_cloud_ply

    write_cloud_ply(tmp_path / "plain.ply", np.random.default_rng(0).normal(size=(50, 3)))
    (tmp_path / "junk.ply").write_text("hello")
    for args, match in [([tmp_path / "plain.ply", "-o", tmp_path / "m.ply"], "no pixel grid"),
                        ([tmp_path / "plain.ply", "-o", tmp_path / "m.ply", "--method", "poisson"], "no normals"),
                        ([tmp_path / "junk.ply", "-o", tmp_path / "m.ply"], "not a valid PLY"),
                        ([tmp_path / "none.ply", "-o", tmp_path / "m.ply"], "does not exist"),
                        ([tmp_path / "plain.ply", "-o", tmp_path / "m.fbx"], "must end in")]:
        rc, _, err = run_main(capsys, "mesh", *args)
        _one_line_error(rc, err, match)
    assert sorted(f.name for f in tmp_path.iterdir()) == ["junk.ply", "plain.ply"]


def test_scan_command_subprocess_no_traceback(tmp_path, calib_file):
    small = write_png(tmp_path / "small.png", np.zeros((100, 100, 3), np.uint8))
    r = subprocess.run([sys.executable, "-m", "gbscan.cli", "scan", str(small), "--calib", str(calib_file),
                        "-o", str(tmp_path / "c.ply")], capture_output=True, text=True)
    _one_line_error(r.returncode, r.stderr, "100x100 but 640x480")


# -- end to end on the simulated rig with the real decoder (slow: rendering) ----------------------
SIM_SCENES = {"plane": lambda sim: sim.scenes.plane(650.0),
              "sphere": lambda sim: sim.scenes.sphere(),
              "head": lambda sim: sim.scenes.head()}
_RENDERS = {}


def sim_scan(name):
    """Render ``name`` with the typical preset (cached), scan it with the true calibration."""
    from gbscan import sim
    from gbscan.pattern import render_pattern

    if name not in _RENDERS:
        rig = sim.paper_rig()
        spec = PatternSpec()
        r = sim.render(rig, SIM_SCENES[name](sim), render_pattern(spec), sim.preset("typical"), seed=0)
        _RENDERS[name] = (r, Scanner(calibration_from_rig(rig, spec)).scan(r.image))
    return _RENDERS[name]


def sim_figures(r, s, max_angle_deg=90.0):
    """(kept fraction of lit non-edge pixels, depth RMS there (mm), max 3D error of any kept point)."""
    from gbscan.clean import grid_normals

    P = r.point.astype(np.float64)
    good = r.lit & ~r.depth_edge & np.isfinite(P[..., 2])
    if max_angle_deg < 90:
        n = grid_normals(P, np.isfinite(P[..., 2]), 1)
        ray = P / np.linalg.norm(P, axis=-1, keepdims=True)
        with np.errstate(invalid="ignore"):
            good &= np.degrees(np.arccos(np.clip(-(n * ray).sum(-1), -1, 1))) < max_angle_deg
    kept = s.valid & good
    dz = s.xyz[..., 2][kept] - P[..., 2][kept]
    err = np.linalg.norm(s.xyz[s.valid] - P[s.valid], axis=1)
    return kept.sum() / good.sum(), float(np.sqrt(np.mean(dz ** 2))), float(np.nanmax(err))


@pytest.mark.slow
def test_sim_plane_accuracy():
    kept, rms, worst = sim_figures(*sim_scan("plane"))
    print(f"plane: kept {100 * kept:.1f}% of lit non-edge, depth RMS {rms:.3f} mm, worst {worst:.2f} mm")
    assert kept >= 0.95 and rms <= 0.2 and worst <= 3.0


@pytest.mark.slow
@pytest.mark.parametrize("name", ["sphere", "head"])
def test_sim_curved_cleaning_keeps_decoded_good_points(name):
    """Away from the rims (< 70 degrees) cleaning keeps >= 99% of what the decoder reported and
    the median depth error is a fraction of the RMS target (the tails are the decoder's)."""
    from gbscan.clean import grid_normals

    r, s = sim_scan(name)
    P = r.point.astype(np.float64)
    n = grid_normals(P, np.isfinite(P[..., 2]), 1)
    ray = P / np.linalg.norm(P, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore"):
        ang = np.degrees(np.arccos(np.clip(-(n * ray).sum(-1), -1, 1)))
    good = r.lit & ~r.depth_edge & np.isfinite(P[..., 2]) & (ang < 70) & s.stripemap.valid
    kept = (s.valid & good).sum() / good.sum()
    med = np.median(np.abs(s.xyz[..., 2] - P[..., 2])[s.valid & good])
    print(f"{name} (< 70 deg): cleaning kept {100 * kept:.2f}% of decoded points, median |dz| {med:.3f} mm")
    assert kept >= 0.99 and med <= 0.15


@pytest.mark.slow
@pytest.mark.parametrize("name, min_kept", [("sphere", 0.995), ("head", 0.94)])
def test_sim_curved_coverage_away_from_grazing_incidence(name, min_kept):
    """Where what the full 95 % target misses is: the lit non-edge pixels whose surface faces both
    the camera and the projector within 70 degrees are kept at 99.9 % (sphere) / 94.9 % (head,
    whose nose casts shadows and splits regions) at seed 0; the rest (17 % / 21 % of the pixels)
    are at grazing incidence, where the stripes arrive dim and compressed or are seen edge-on."""
    from gbscan import sim

    r, s = sim_scan(name)
    cam, proj = sim.incidence_deg(paper_rig(), r)
    good = r.lit & ~r.depth_edge & np.isfinite(r.point[..., 2])
    facing = good & (cam < 70) & (proj < 70)
    kept = (s.valid & facing).sum() / facing.sum()
    print(f"{name}: {100 * facing.sum() / good.sum():.1f}% of lit non-edge pixels within 70 degrees of both, "
          f"{100 * kept:.2f}% of them kept; beyond: {100 * (s.valid & good & ~facing).sum() / (good & ~facing).sum():.1f}%")
    assert facing.sum() > 0.75 * good.sum() and kept >= min_kept


@pytest.mark.slow
def test_face_coverage_target_needs_pixels_beyond_80_degrees():
    """Why the face's 95 % is out of reach at the paper's geometry: even a decoder that kept every
    lit non-edge pixel whose surface is within 80 degrees of both the camera and the projector,
    and none beyond, would keep under 95 % of them (94.6 % at seed 0; the sphere 95.3 %).  Beyond
    80 degrees an 8 px stripe arrives under 0.7 camera px wide."""
    from gbscan import sim

    for name, lo, hi in (("head", 0.93, 0.95), ("sphere", 0.95, 0.96)):
        r, _ = sim_scan(name)
        cam, proj = sim.incidence_deg(paper_rig(), r)
        good = r.lit & ~r.depth_edge & np.isfinite(r.point[..., 2])
        ceiling = (good & (np.maximum(cam, proj) < 80)).sum() / good.sum()
        print(f"{name}: {100 * ceiling:.1f} % of lit non-edge pixels within 80 degrees of both")
        assert lo < ceiling < hi


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="coverage only: depth RMS and worst error pass, but ~92% (sphere) / ~86% (head) "
                                       "of lit non-edge pixels are kept, not 95%: the rest sits at grazing incidence "
                                       "(the surface beyond 70 degrees from the camera or the projector: 17% / 21% of "
                                       "the pixels, where the stripes arrive dim and compressed or are seen edge-on), "
                                       "and for the face around the nose (within 70 degrees: 99.9% / 96% kept); for "
                                       "the face 95% needs pixels beyond 80 degrees "
                                       "(test_face_coverage_target_needs_pixels_beyond_80_degrees)")
@pytest.mark.parametrize("name", ["sphere", "head"])
def test_sim_curved_accuracy_full_target(name):
    kept, rms, worst = sim_figures(*sim_scan(name))
    print(f"{name}: kept {100 * kept:.1f}% of lit non-edge, depth RMS {rms:.3f} mm, worst {worst:.2f} mm")
    assert kept >= 0.95 and rms <= 0.3 and worst <= 3.0


@pytest.mark.slow
def test_sim_scan_command_end_to_end(tmp_path):
    r, in_process = sim_scan("head")
    from gbscan import sim

    img = write_png(tmp_path / "head.png", r.image)
    cal = save_calibration(tmp_path / "calib.yaml", calibration_from_rig(sim.paper_rig(), PatternSpec()))
    p = subprocess.run([sys.executable, "-m", "gbscan.cli", "scan", str(img), "--calib", str(cal),
                        "-o", str(tmp_path / "cloud.ply"), "--xyz", str(tmp_path / "xyz.npy"),
                        "--mesh", str(tmp_path / "mesh.stl")], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    xyz = np.load(tmp_path / "xyz.npy")
    ok = np.isfinite(xyz[..., 2])
    assert ok.sum() > 0.8 * r.lit.sum()
    assert np.nanmedian(np.abs(xyz[..., 2] - r.point[..., 2])[ok]) < 0.3
    # the command (numba told there is no BLAS: skip_numba_blas_probe) gives the API's points bit for bit
    np.testing.assert_array_equal(xyz, in_process.xyz)
    assert (tmp_path / "mesh.stl").stat().st_size > 84
    cloud = read_cloud_ply(tmp_path / "cloud.ply")
    assert len(cloud.points) == ok.sum()
    # each point's predicted error rides along (mm); --max-sigma-mm keeps the points within it
    assert cloud.sigma_mm is not None and np.isfinite(cloud.sigma_mm).all() and 0.03 < np.median(cloud.sigma_mm) < 0.5
    p = subprocess.run([sys.executable, "-m", "gbscan.cli", "scan", str(img), "--calib", str(cal),
                        "-o", str(tmp_path / "strict.ply"), "--max-sigma-mm", "0.2", "--preview", str(tmp_path / "prev")],
                       capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    assert "high_sigma" in p.stdout and (tmp_path / "prev" / "sigma.png").stat().st_size > 1000
    line = next(x for x in p.stdout.splitlines() if x.startswith("predicted error along the ray"))
    med = float(line.split("median ")[1].split(" mm")[0])
    assert 0.03 < med <= 0.2, line       # what the strict cloud keeps: all under 0.2 mm
    strict = read_cloud_ply(tmp_path / "strict.ply")
    assert strict.sigma_mm.max() <= 0.2 and 0.3 * len(cloud.points) < len(strict.points) < len(cloud.points)


def test_decoder_and_cleaning_flags_are_one_set_across_commands():
    """decode, scan and batch take the same decoder flags with the same meaning (old spellings
    still work, hidden); scan and batch the same cleaning flags."""
    from gbscan.cli_common import _Parser
    from gbscan.commands import batch as batch_cmd
    from gbscan.commands import decode as decode_cmd
    from gbscan.commands import scan as scan_cmd
    from gbscan.decode import DecodeParams

    heads = {decode_cmd: ["img.png"], scan_cmd: ["img.png", "--calib", "c.yaml", "-o", "o.ply"],
             batch_cmd: ["frames", "--calib", "c.yaml", "-o", "out"]}
    flags = ["--blur-px", "3", "--balance-window-px", "31", "--local-window-px", "21", "--angle-deg", "5",
             "--threshold", "global", "--gamma", "1.0", "--decode-param", "min_contrast=0.2"]
    old = ["--blur", "3", "--window", "31", "--window-px", "21", "--angle", "5", "--threshold", "global",
           "--gamma", "1.0", "--decode-param", "min_contrast=0.2"]
    want = DecodeParams(blur_sigma_along_px=3.0, balance_window_px=31, threshold_window_px=21, norm_window_px=21,
                        stripe_angle_deg=5.0, threshold="global", camera_gamma=1.0, min_contrast=0.2)
    for mod, head in heads.items():
        p = _Parser()
        mod.add_arguments(p)
        assert decode_cmd.decode_params_from_args(p.parse_args(head)) is None
        assert decode_cmd.decode_params_from_args(p.parse_args(head + flags)) == want, mod.__name__
        assert decode_cmd.decode_params_from_args(p.parse_args(head + old)) == want, mod.__name__
        text = p.format_help()
        assert "--local-window-px" in text and "--window-px" not in text and "--window " not in text
        a = p.parse_args(head + ["--follow-envelope-px", "9"])     # the opt-in following envelope
        assert decode_cmd.decode_params_from_args(a) == DecodeParams(envelope_follow_px=9)
        if mod is not decode_cmd:
            a = p.parse_args(head + ["--max-jump", "0.02", "--clean-param", "normal_step_px=3", "--max-sigma-mm", "0.25"])
            c = scan_cmd.clean_params_from_args(a)
            assert (c.max_jump, c.normal_step_px, c.max_sigma_mm) == (0.02, 3, 0.25)
    p = _Parser()
    batch_cmd.add_arguments(p)
    assert scan_cmd.clean_params_from_args(p.parse_args(heads[batch_cmd]), none_if_default=True) is None
    with pytest.raises(GBError, match="--decode-param.*unwrap.NAME"):
        decode_cmd.decode_params_from_args(p.parse_args(heads[batch_cmd] + ["--decode-param", "unwrap=1"]))
    # the nested unwrapping parameters, field by field (the rest at their defaults)
    from gbscan.unwrap import UnwrapParams

    got = decode_cmd.decode_params_from_args(p.parse_args(
        heads[batch_cmd] + ["--decode-param", "unwrap.link_rows=3", "--decode-param", "unwrap.conflict_confirm=off",
                            "--decode-param", "rim_end_dim_ratio=0"]))
    assert got == DecodeParams(unwrap=UnwrapParams(link_rows=3, conflict_confirm=False), rim_end_dim_ratio=0.0)
    for bad, match in (("unwrap.bogus=1", "--decode-param unwrap. 'bogus=1'.*link_rows"),
                       ("unwrap.link_rows=x", "not a valid value for link_rows"), ("bogus.x=1", "bogus.x=1")):
        with pytest.raises(GBError, match=match):
            decode_cmd.decode_params_from_args(p.parse_args(heads[batch_cmd] + ["--decode-param", bad]))
    # the blur: a sigma or "auto" (the default, None), also through --decode-param as a float
    for extra, sigma in ((["--blur-px", "auto", "--gamma", "1.0"], None), (["--blur-px", "1.5"], 1.5),
                         (["--decode-param", "blur_sigma_along_px=1.25"], 1.25),
                         (["--decode-param", "blur_sigma_along_px=none", "--gamma", "1.0"], None)):
        assert decode_cmd.decode_params_from_args(p.parse_args(heads[batch_cmd] + extra)).blur_sigma_along_px == sigma
    with pytest.raises(SystemExit):
        p.parse_args(heads[batch_cmd] + ["--blur-px", "fast"])


# -- no flying pixels at depth edges (issue 5) ---------------------------------------------------
SIM_SCENES["step"] = lambda sim: sim.scenes.step()
SIM_SCENES["multi_object"] = lambda sim: sim.scenes.multi_object()


def _errors_mm(r, s, footprint=False):
    """(H, W) 3D error (mm) of every kept point of scan ``s`` (:func:`gbscan.sim.point_errors_mm`)."""
    from gbscan import sim

    return sim.point_errors_mm(r, s.xyz, s.valid, footprint)


def test_footprint_error_metric():
    """The footprint error differs from the centre error on depth-edge pixels only, where it is
    the distance to the nearest of the 3x3 true points."""
    from types import SimpleNamespace

    P = np.zeros((4, 5, 3))
    P[..., 2] = 500.0
    P[2:, :, 2] = 700.0
    edge = np.zeros((4, 5), bool)
    edge[1:3] = True
    xyz = P.astype(np.float32).copy()
    xyz[2, 1, 2] = 501.0   # an edge pixel of the far surface measured on the near one: 1 mm off it
    xyz[3, 3, 2] = 690.0   # off the edge: 10 mm off its own surface
    xyz[1, 4, 2] = 600.0   # a flying pixel between the surfaces on an edge: 100 mm off both
    r = SimpleNamespace(point=P, depth_edge=edge)
    s = SimpleNamespace(valid=np.ones((4, 5), bool), xyz=xyz)
    centre, foot = _errors_mm(r, s), _errors_mm(r, s, footprint=True)
    assert centre[2, 1] == pytest.approx(199.0) and foot[2, 1] == pytest.approx(1.0)
    assert centre[3, 3] == foot[3, 3] == pytest.approx(10.0)
    assert foot[1, 4] == pytest.approx(100.0)
    assert (foot[~edge] == centre[~edge]).all() and (foot <= centre).all()
    from gbscan import sim
    from gbscan.errors import GBError

    with pytest.raises(GBError, match="must match the render"):
        sim.point_errors_mm(r, xyz[:3], np.ones((3, 5), bool))


@pytest.mark.slow
@pytest.mark.parametrize("name", ["step", "multi_object", "sphere", "head"])
def test_sim_no_point_off_by_3mm_after_cleaning(name):
    """No kept point more than 3 mm off the surface its pixel sees (:func:`_errors_mm` with the
    footprint: on depth-edge pixels, the nearest of the 3x3 true points).  Measured at seed 0
    (footprint / centre metric, worst mm): step 0 / 0; multi_object 0 / 2 mixed pixels, worst 2.91
    (was 2 / 43, 211 mm before the decoder's rim guard: the blur carried the wall's stripes onto
    the top rows of objects the decoder dropped; with the automatic 1 px blur, 1-2 wall points
    3.0-3.1 mm off beside a slanted shadow edge until ``rim_end_px`` 1 -> 2, 2.75 with the quadratic end
    extrapolation); head 0 / 0, worst 2.83 (2.22 with it)."""
    r, s = sim_scan(name)
    err = _errors_mm(r, s, footprint=True)
    centre = _errors_mm(r, s)
    print(f"{name}: {int((err > 3).sum())} points > 3 mm ({int((centre > 3).sum())} by the pixel centres' "
          f"truth), {int((err > 1).sum())} > 1 mm, worst {err.max():.2f} mm")
    assert (err > 3).sum() == 0


def test_stripe_range_brackets_the_true_stripes_and_the_depths():
    """Scanner.stripe_range (the decoder's working volume from ``CleanParams`` min/max depth): the
    closed form of the light planes' pencil.  Columns at its bounds triangulate back to the near
    and far depths; every lit pixel of a scene inside the volume sees a stripe within its range."""
    from gbscan import sim
    from gbscan.clean import CleanParams
    from gbscan.scan import stripe_range_from_pencil

    r, _ = sim_scan("multi_object")
    cal = calibration_from_rig(paper_rig(), PatternSpec())
    s = Scanner(cal, clean_params=CleanParams(min_depth_mm=400.0, max_depth_mm=1200.0))
    sr = s.stripe_range
    assert sr.shape == (2, 480, 640) and sr.dtype == np.float32 and np.isfinite(sr).all()
    assert (sr[1] > sr[0]).all()
    raw = stripe_range_from_pencil(s.triangulator, 8.0, 400.0, 1200.0, margin_stripes=0.0)
    # the bounds' columns (stripe * 8 - 0.5) back through the triangulator: the near and far depths
    # (columns grow with depth on this rig: the projector is to the right), where they are in the
    # projector's frame
    for bound, z in ((raw[0], 400.0), (raw[1], 1200.0)):
        xyz = s.triangulator((bound * 8.0 - 0.5).astype(np.float64))
        ok = np.isfinite(xyz[..., 2])
        assert ok.mean() > 0.5 and np.allclose(xyz[..., 2][ok], z, rtol=1e-4)
    k = np.floor((r.proj_xy[..., 0] + 0.5) / 8.0)
    inside = r.lit & np.isfinite(k) & (r.point[..., 2] > 400) & (r.point[..., 2] < 1200)
    assert inside.sum() > 100000
    assert ((k >= np.floor(sr[0])) & (k <= np.ceil(sr[1])))[inside].all()
    # no pencil (planes that are not one projector's), no prior; an empty range, none either
    assert stripe_range_from_pencil(s.triangulator, 8.0, 1200.0, 400.0) is None


@pytest.mark.slow
def test_sim_working_volume_indexes_more_never_wrong():
    """``gbscan scan --depth-range`` also bounds the decoder's indexing (Scanner.stripe_range): on
    the multi-object scene a 400-1200 mm volume rules out the runner-up offsets of regions whose
    2-3 markers fit two offsets 30-50 stripes apart (1.3-1.7 m deep): the small sphere is indexed
    (82.4 -> 84.3 % of lit non-edge pixels kept at seed 0), no point is added off its surface.
    (The stripe margin, ``UnwrapParams.index_margin_stripes``, indexes the small sphere without a
    volume since the twenty-eighth session: off here, in both scans.)"""
    from gbscan.clean import CleanParams
    from gbscan.decode import DecodeParams
    from gbscan.unwrap import UnwrapParams

    r, _ = sim_scan("multi_object")
    cal = calibration_from_rig(paper_rig(), PatternSpec())
    pixel_margin = DecodeParams(unwrap=UnwrapParams(index_margin_stripes=0))
    s0 = Scanner(cal, decode_params=pixel_margin).scan(r.image)
    s = Scanner(cal, decode_params=pixel_margin,
                clean_params=CleanParams(min_depth_mm=400.0, max_depth_mm=1200.0)).scan(r.image)
    k0, _, _ = sim_figures(r, s0)
    k, rms, _ = sim_figures(r, s)
    err = _errors_mm(r, s, footprint=True)
    print(f"multi-object: kept {100 * k0:.1f} -> {100 * k:.1f} %, depth RMS {rms:.3f} mm, worst {err.max():.2f} mm")
    assert k > k0 + 0.015 and (err > 3).sum() == 0
    assert s.stripemap.stats["region_why"].get("ambiguous offset", 0) < \
        s0.stripemap.stats["region_why"].get("ambiguous offset", 0)


@pytest.mark.slow
def test_sim_hard_multi_object_end_rows_follow_the_blur():
    """Hard preset (the automatic blur takes 3 px): the blur carries a box's stripes past its
    bottom silhouette onto the wall below, where one row of guard (the fixed ``rim_end_rows`` of
    before) left a point 231 mm off what its pixel sees.  The automatic end rows (the sigma
    rounded: 3 here) remove it; with one row it comes back, unless the brightness-step guard
    (``step_guard_ratio``, on by default) sees the edge, which it does here too, or the
    rejection's growth (``UnwrapParams.conflict_grow``) takes the carried rows."""
    from gbscan import sim
    from gbscan.decode import DecodeParams, guard_end_rows
    from gbscan.pattern import render_pattern
    from gbscan.unwrap import UnwrapParams

    rig, spec = sim.paper_rig(), PatternSpec()
    r = sim.render(rig, sim.scenes.multi_object(), render_pattern(spec), sim.preset("hard"), seed=0)
    cal = calibration_from_rig(rig, spec)
    s = Scanner(cal).scan(r.image)
    assert s.stripemap.stats["blur_sigma_along_px"] == 3.0
    assert guard_end_rows(DecodeParams(blur_sigma_along_px=3.0)) == 3
    assert guard_end_rows(DecodeParams(blur_sigma_along_px=1.0)) == 1
    assert guard_end_rows(DecodeParams(blur_sigma_along_px=3.0, rim_end_rows=1)) == 1
    err = sim.point_errors_mm(r, s.xyz, s.valid)
    # (the rejection's growth through rows without a marker, conflict_grow, removes it as well
    # since the twenty-seventh session: off here, to pin the end rows)
    s1 = Scanner(cal, decode_params=DecodeParams(rim_end_rows=1, step_guard_ratio=0,
                                                 unwrap=UnwrapParams(conflict_grow=False))).scan(r.image)
    err1 = sim.point_errors_mm(r, s1.xyz, s1.valid)
    # the brightness-step guard sees the same edge (the wall is dimmer than the box) on its own
    s2 = Scanner(cal, decode_params=DecodeParams(rim_end_rows=1)).scan(r.image)
    err2 = sim.point_errors_mm(r, s2.xyz, s2.valid)
    print(f"hard multi-object: worst {err.max():.2f} mm, {int((err > 3).sum())} > 3 mm "
          f"(one end row, no step guard: worst {err1.max():.1f} mm, {int((err1 > 3).sum())} > 3 mm; "
          f"one end row with it: worst {err2.max():.1f} mm)")
    assert (err > 3).sum() == 0 and (err2 > 3).sum() == 0
    assert (err1 > 3).sum() >= 1
    s3 = Scanner(cal, decode_params=DecodeParams(rim_end_rows=1, step_guard_ratio=0)).scan(r.image)
    assert (sim.point_errors_mm(r, s3.xyz, s3.valid) > 3).sum() == 0      # the growth alone


@pytest.mark.slow
@pytest.mark.parametrize("ambient_rgb", [(0.15, 0.2, 0.25), (0.15, 0.12, 0.09)], ids=["cool0.25", "warm0.15"])
def test_sim_room_light_crease_rows_are_masked(ambient_rgb):
    """Room light on the multi-object scene (the sweep's cool 0.25 and warm 0.15 frames, rendered
    3x3 supersampled): a box's top face, seen edge-on above its front, is lit but its stripes run
    slanted (6 projector px a row) and the blur along the stripes washes them out; its first one
    or two rows above the crease borrow the front face's stripes through the blur and decoded as
    the front face's next row, 4-7 projector px off: points 4.8-7.7 mm off what their pixels see,
    which the cleaning keeps (they continue the front face smoothly).  The rim guard's lit rows
    (``DecodeParams.rim_lit_rows``: two rows from a lit pixel the decoder could not use) mask
    them.  Measured (seed 0, worst kept point / points > 3 mm / decoded pixels a stripe off off
    depth edges): cool 7.71 / 10 / 12 -> 2.49 / 0 / 2, warm 6.14 / 4 / 6 -> 2.62 / 0 / 0; 2.31 and
    1.91 mm since the frame's sides end row stretches (``rim_end_px``).  The cool frame's last 2
    sat beside a top-face pixel the classifier called dark: 0 since a lit dark pixel is in the
    rule's class too (2026-11-27, sixteenth session).  The end rule beside fragments of another
    surface (``rim_end_isolated``, twentieth session) masks some of the warm frame's rows as well:
    the counterfactual runs without it."""
    import dataclasses

    from gbscan import sim
    from gbscan.decode import DecodeParams
    from gbscan.pattern import render_pattern

    rig, spec = sim.paper_rig(), PatternSpec()
    cond = dataclasses.replace(sim.preset("typical"), supersample=3, ambient_rgb=ambient_rgb)
    r = sim.render(rig, sim.scenes.multi_object(650.0), render_pattern(spec), cond, seed=0)
    cal = calibration_from_rig(rig, spec)
    out = {}
    for lit_rows in (0, None):
        # (without the lit rows, without the end rule beside fragments too; with: the defaults)
        s = Scanner(cal, decode_params=DecodeParams(rim_lit_rows=lit_rows, rim_end_isolated=lit_rows is None)).scan(r.image)
        err = sim.point_errors_mm(r, s.xyz, s.valid)
        _, bad = sim.column_errors(s.stripemap.column, s.stripemap.valid, r.proj_xy[..., 0], spec.stripe_px)
        out[lit_rows] = (float(err.max()), int((err > 3).sum()), int((bad & ~r.depth_edge).sum()))
    print(f"room light {ambient_rgb}: (worst mm, > 3 mm, a stripe off) without the lit rows {out[0]}, "
          f"with {out[None]}")
    assert out[0][1] >= 3 and out[0][2] >= 5          # the crease rows, without the rule
    assert out[None][1] == 0 and out[None][2] == 0


@pytest.mark.slow
def test_sim_multi_object_end_run_overflow_keeps_the_wall_off_the_box():
    """The multi-object scene at 700 mm (seeds 0, 1): a box's last blue stripe and the wall's first
    one meet across the box's silhouette as one run, 1.5 stripes wide; the wall's row stretch
    extrapolated its column one stripe into it, so the stretch's last pixel, on the box, took the
    wall's column and the scan kept a point 92 mm behind what the pixel sees (on the wall's plane:
    no cleaning step can see it).  ``rim_end_overflow`` masks a stretch's last pixel whose run
    goes on for 2 px or more past the columns' reach."""
    from gbscan import sim
    from gbscan.decode import DecodeParams
    from gbscan.pattern import render_pattern

    rig, spec = sim.paper_rig(), PatternSpec()
    r = sim.render(rig, sim.scenes.multi_object(700.0), render_pattern(spec), "typical", seed=0)
    cal = calibration_from_rig(rig, spec)
    worst = {}
    for on in (True, False):
        s = Scanner(cal, decode_params=DecodeParams(rim_end_overflow=on)).scan(r.image)
        worst[on] = float(sim.point_errors_mm(r, s.xyz, s.valid).max())
    print(f"multi-object at 700 mm: worst point {worst[True]:.1f} mm ({worst[False]:.1f} mm without the rule)")
    assert worst[False] > 50
    assert worst[True] < 10      # what remains: a 3x3 block 3-5 mm off beside a shadow (Known limits)


def test_sim_multi_object_gap_edges_remove_what_the_point_map_shows():
    """The gap-edge test removes about half of the points extended across silhouettes (> 3 mm off:
    108 -> 56 at seed 0 with the decoder's rim guard off) for ~0.1% of the lit non-edge pixels;
    what stays far off is on true depth edges.  (The rim guard, on by default, removes most of
    them in the decoder already; this test keeps it off to see the cleaning's own effect.)"""
    from dataclasses import replace

    from gbscan import sim
    from gbscan.decode import DecodeParams
    from gbscan.pattern import render_pattern

    r, _ = sim_scan("multi_object")
    cal = calibration_from_rig(paper_rig(), PatternSpec())
    # (measured with the fixed 2 px blur and its rim rules, before the automatic blur: with the
    # 1 px blur it picks here, 100 -> 67 points, the rim rules removing more of them first)
    unguarded = DecodeParams(blur_sigma_along_px=2.0, rim_end_px=1, rim_guard_px=0, rim_end_rows=0, rim_lit_rows=0)
    s = Scanner(cal, decode_params=unguarded).scan(r.image)
    sm = s.stripemap
    scanner = Scanner(cal, decode_params=unguarded,
                      clean_params=replace(Scanner(cal).clean_params, max_gap_px=0))
    s0 = scanner.reconstruct(sm.column, sm.confidence, decoded=sm.valid)
    err, err0 = _errors_mm(r, s), _errors_mm(r, s0)
    kept, _, _ = sim_figures(r, s)
    kept0, _, _ = sim_figures(r, s0)
    print(f"multi_object > 3 mm: {int((err0 > 3).sum())} without the gap test, {int((err > 3).sum())} with it; "
          f"lit non-edge kept {100 * kept0:.2f}% -> {100 * kept:.2f}%; gap_edge removed {s.counts['gap_edge']}")
    assert (err0 > 3).sum() >= 30 and (err > 3).sum() <= 0.6 * (err0 > 3).sum()
    assert err[~r.depth_edge].max() < 5.0  # off the edges: a few wall points 3.0x mm off next to holes
    assert kept >= kept0 - 0.005


def test_gap_edge_flags_in_scan_and_batch():
    from gbscan.cli_common import _Parser
    from gbscan.commands import batch as batch_cmd
    from gbscan.commands import scan as scan_cmd

    for mod, head in ((scan_cmd, ["img.png", "--calib", "c.yaml", "-o", "o.ply"]),
                      (batch_cmd, ["frames", "--calib", "c.yaml", "-o", "out"])):
        p = _Parser()
        mod.add_arguments(p)
        c = scan_cmd.clean_params_from_args(p.parse_args(head + ["--max-gap-px", "0", "--clean-param",
                                                                  "gap_near_px=1"]))
        assert (c.max_gap_px, c.gap_near_px) == (0, 1), mod.__name__
        with pytest.raises(GBError, match="max_gap_px"):
            scan_cmd.clean_params_from_args(p.parse_args(head + ["--max-gap-px", "-2"]))


def test_coverage_study_script_options(capsys):
    """scripts/coverage_study.py (the figures README and docs/figures.md quote): a decoder parameter off its default
    and the yaw are applied and named in the header; bad ones are a usage error, not a traceback."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "scripts" / "coverage_study.py"
    spec = importlib.util.spec_from_file_location("coverage_study", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    for argv, msg in ((["--scenes", "sphere", "--yaw-deg", "10"], "takes no yaw"),
                      (["--scenes", "sphere", "--decode-param", "bogus=1"], "--decode-param"),
                      (["--scenes", "sphere", "--decode-param", "extrapolate_fit=2"], "extrapolate_fit"),
                      (["--scenes", "sphere", "--baseline-mm", "0"], "--baseline-mm"),
                      (["--scenes", "sphere", "--projector", "40x30"], "--projector"),
                      (["--scenes", "sphere", "--marker-code", "3"], "--marker-code")):
        with pytest.raises(SystemExit) as e:
            mod.main(argv)
        assert e.value.code == 2 and msg in capsys.readouterr().err
    assert mod.main(["--scenes", "plane", "--decode-param", "extrapolate_fit=0", "--baseline-mm", "150",
                     "--edge-profile", "--confidence", "--sigma"]) == 0
    out = capsys.readouterr().out
    assert "decoder extrapolate_fit=0" in out and "## plane, seed 0: kept" in out and "(baseline 150 mm, camera 640x480, projector 1024x768)" in out
    # the edge profile: a plane's interior columns are within a tenth of a camera px
    line = next(x for x in out.splitlines() if "column error near the reported area's edges" in x)
    mean, rms = (float(t) for t in line.split("5+ px from any: ")[1].split(" (")[0].split(" / "))
    assert abs(mean) < 0.05 and rms < 0.1, line
    assert "unreported pixel toward the projector" in out and "along the column" in out
    # the confidence table: a higher threshold keeps fewer points, those it keeps are no worse
    rows = [x for x in out.splitlines() if x.strip().startswith(("0.3:", "0.5:"))]
    kept = [float(x.split(":")[1].split("%")[0]) for x in rows]
    assert len(rows) == 2 and kept[0] >= kept[1] > 0, rows
    # the sigma tables: six bands whose predicted and actual RMS are near each other, then thresholds
    # that keep fewer points as they tighten
    bands = [x for x in out.splitlines() if "predicted" in x and "actual RMS" in x]
    assert len(bands) == 6
    ratios = [float(x.split("(x")[1].split(")")[0]) for x in bands]
    assert all(0.3 < r_ < 2.0 for r_ in ratios), bands
    rows = [x for x in out.splitlines() if x.strip().startswith(("0.10 mm:", "0.50 mm:"))]
    kept = [float(x.split(":")[1].split("%")[0]) for x in rows]
    assert len(rows) == 2 and 0 < kept[0] <= kept[1], rows


def test_coverage_study_edge_distances():
    """The edge profile's distances: along the row to the nearest unreported pixel on each side,
    along the column to the nearest above or below; exact on a small mask."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "scripts" / "coverage_study.py"
    spec = importlib.util.spec_from_file_location("coverage_study", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    un = np.zeros((5, 7), bool)
    un[2, 1] = True
    un[0, 5] = True
    left, right, vert = mod.edge_distances(un)
    big = 5 + 7
    assert left[2].tolist()[1:] == [0, 1, 2, 3, 4, 5] and left[2, 0] > big - 1
    assert right[2].tolist()[:2] == [1, 0] and (right[2, 2:] > big - 5).all()
    assert right[0].tolist()[:6] == [5, 4, 3, 2, 1, 0] and left[0, 6] == 1
    assert vert[:, 1].tolist() == [2, 1, 0, 1, 2] and vert[:, 5].tolist() == [0, 1, 2, 3, 4]
    assert (vert[:, 0] >= big - 5).all()


# -- each point's predicted error in mm (Scan.sigma_mm) ------------------------------------------------
@pytest.mark.slow
def test_sigma_mm_predicts_the_points_error_on_a_sphere_and_its_filter_keeps_the_accurate_ones(tmp_path):
    """On the simulated sphere (true calibration, typical preset) the decoder's per-pixel column error
    through the triangulation predicts each kept point's 3D error: measured (seed 0) actual / predicted
    RMS 0.64 / 0.77 / 1.33 in the lower three quarters of sigma, 0.98-0.99 up to 97 %, 0.61 over the
    top 3 % (conservative); |error| < 2 sigma for 91-99 % of each band (0.88-1.14 in the five lower
    sixths before the pixel-locking correction halved the smoothest points' error, 2026-11-27
    sixteenth session: the model's floor, which the noisy frames also need, now over-predicts them).
    The test asks for 0.6-1.4 on the lower three quarters (0.7-1.4 before), at least 88 % within 2
    sigma overall, and a ranking: the top quarter's error RMS at least twice the lowest half's.  ``max_sigma_mm`` then keeps only points whose sigma is within it (measured 0.2 mm: 83.5 %
    kept, error RMS 0.095 -> 0.071 mm), and the PLY carries the same values."""
    from gbscan import sim
    from gbscan.clean import CleanParams
    from gbscan.pattern import render_pattern

    r, s = sim_scan("sphere")
    sig = s.sigma_mm
    assert sig is s.sigma_mm and sig.dtype == np.float32       # computed once
    assert np.array_equal(np.isfinite(sig), s.valid)
    err = sim.point_errors_mm(r, s.xyz, s.valid)
    good = r.lit & ~r.depth_edge & s.valid
    e, sg = err[good], sig[good]
    q25, q50, q75 = np.quantile(sg, [0.25, 0.5, 0.75])
    for lo, hi in ((0, q25), (q25, q50), (q50, q75)):
        m = (sg >= lo) & (sg < hi)
        ratio = np.sqrt(np.mean(e[m] ** 2)) / np.sqrt(np.mean(sg[m] ** 2))
        assert 0.6 < ratio < 1.4, (lo, hi, ratio)
    assert np.mean(e < 2 * sg) > 0.88
    assert np.sqrt(np.mean(e[sg >= q75] ** 2)) > 2 * np.sqrt(np.mean(e[sg < q50] ** 2))
    # the filter: only points within max_sigma_mm, fewer and more accurate, counted under their reason
    rig, spec = sim.paper_rig(), PatternSpec()
    f = Scanner(calibration_from_rig(rig, spec), clean_params=CleanParams(max_sigma_mm=0.2)).scan(r.image)
    assert f.counts["high_sigma"] > 0 and (f.reason == 10).sum() == f.counts["high_sigma"]
    assert np.nanmax(f.sigma_mm) <= 0.2 and f.n_points < s.n_points
    kept = r.lit & ~r.depth_edge & f.valid
    assert np.sqrt(np.mean(err[kept & s.valid] ** 2)) < 0.85 * np.sqrt(np.mean(e ** 2))
    np.testing.assert_array_equal(f.sigma_mm[f.valid], s.sigma_mm[f.valid])
    s.save_ply(tmp_path / "c.ply")
    c = read_cloud_ply(tmp_path / "c.ply")
    np.testing.assert_array_equal(c.sigma_mm, s.point_sigma_mm)
    assert c.colors is not None and c.organised   # the other properties still read


def test_sigma_mm_needs_a_column_error(tmp_path, scanner, scene, rig):
    """No column error, no sigma: a decode with the model off or external columns without one give
    None, their PLY no sigma_mm property, and max_sigma_mm refuses them with a message; external columns
    with an error map get one (NaN where the map is)."""
    from gbscan import sim
    from gbscan.clean import CleanParams
    from gbscan.decode import DecodeParams
    from gbscan.pattern import render_pattern

    p, col, _ = scene
    ext = scanner.reconstruct(col)
    assert ext.sigma_mm is None and ext.point_sigma_mm is None
    ext.save_ply(tmp_path / "ext.ply")
    assert read_cloud_ply(tmp_path / "ext.ply").sigma_mm is None
    cs = np.where(np.isfinite(col), np.float32(0.1), np.nan).astype(np.float32)
    cs[240, :320] = np.nan
    withe = scanner.reconstruct(col, column_sigma=cs)
    sig = withe.sigma_mm
    assert np.isfinite(sig[withe.valid & np.isfinite(cs)]).all() and np.isnan(sig[240, :320]).all()
    assert 0.01 < np.nanmedian(sig) < 0.2      # 0.1 projector px at 600-760 mm
    calib = calibration_from_rig(rig, PatternSpec())
    strict = Scanner(calib, clean_params=CleanParams(max_sigma_mm=0.5))
    with pytest.raises(GBError, match="column_sigma"):
        strict.reconstruct(col)
    kept = strict.reconstruct(col, column_sigma=cs)
    # unknown (NaN) sigma is dropped, at the pointwise stage (before the spike and jump filters)
    in_play = np.isfinite(scanner.triangulator(col)[..., 2])
    assert kept.counts["high_sigma"] == int((in_play & np.isnan(cs)).sum()) > 200
    assert not kept.valid[240, :320].any() and kept.valid[239, :320].sum() > 200
    r = sim.render(rig, sim.scenes.plane(650.0), render_pattern(PatternSpec()), "clean", seed=0)
    off = Scanner(calib, decode_params=DecodeParams(confidence_spread_px=0.0))
    s = off.scan(r.image)
    assert s.stripemap.column_sigma is None and s.sigma_mm is None and s.n_points > 0
    with pytest.raises(GBError, match="confidence_spread_px"):
        Scanner(calib, decode_params=DecodeParams(confidence_spread_px=0.0),
                clean_params=CleanParams(max_sigma_mm=0.5)).scan(r.image)
    assert Scanner(calib, decode_params=DecodeParams(confidence_spread_px=0.0),
                   clean_params=CleanParams(max_sigma_mm=0.5)).scan(r.image, clean=False).n_points > 0
    with pytest.raises(GBError, match="max_sigma_mm"):
        CleanParams(max_sigma_mm=0.0)


# -- the cleaning on the window of the decoded pixels ---------------------------------------------
def _reconstruct_both(monkeypatch, scanner, column, **kw):
    """reconstruct() with the cleaning on the decoded pixels' window, then on the whole frame."""
    import gbscan.scan as scan_module

    out = []
    for frac in (scan_module.POINT_WINDOW_MAX_FRACTION, -1.0):
        monkeypatch.setattr(scan_module, "POINT_WINDOW_MAX_FRACTION", frac)
        out.append(scanner.reconstruct(column, **kw))
    return out


def _assert_same_scan(a, b):
    for name in ("xyz", "normals", "confidence", "reason"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.shape == y.shape and np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), name
    assert a.counts == b.counts


def test_point_window_is_the_decoded_box_grown_by_the_filters_reach():
    from gbscan.clean import CleanParams
    from gbscan.scan import point_window

    p = CleanParams()
    m = 2 * (p.max_gap_px + max(p.gap_far_px, p.gap_near_px) + p.normal_step_px) + 8
    d = np.zeros((480, 640), bool)
    assert point_window(d, p) is None                          # nothing decoded
    d[200:230, 300:350] = True
    d[250, 320] = True
    assert point_window(d, p) == (200 - m, 251 + m, 300 - m, 350 + m)
    d[0, 639] = True                                           # clipped at the frame's edges
    assert point_window(d, p) == (0, 251 + m, 300 - m, 640)
    d[470, 5] = True                                           # most of the frame: not worth it
    assert point_window(d, p) is None


def test_cleaning_on_the_decoded_window_is_the_whole_frames(monkeypatch, scanner, rig):
    """Points decoded in one part of the frame: the cleaning on their window gives the whole
    frame's points, normals, reasons and counts, bit for bit -- a small component is measured
    against the frame's default size (307 px at 640x480), not the window's."""
    import gbscan.scan as scan_module

    p, col, _ = truth(rig, spheres=[SPHERE])                 # a sphere alone: columns on its pixels
    col = np.where(np.isfinite(col), col, np.nan).astype(np.float32)
    rng = np.random.default_rng(3)
    conf = rng.uniform(0.1, 1.0, col.shape).astype(np.float32)
    ys, xs = np.nonzero(np.isfinite(col))
    blob = (slice(ys[0] - 20, ys[0] - 8), slice(xs[0] - 6, xs[0] + 6))   # 144 px above it
    col[blob] = col[ys[0], xs[0]]
    noisy = col + rng.normal(0, 0.05, col.shape).astype(np.float32)
    noisy[rng.random(col.shape) < 0.01] += 30.0                # spikes for the outlier filter
    assert scan_module.point_window(np.isfinite(noisy), scanner.clean_params) is not None
    a, b = _reconstruct_both(monkeypatch, scanner, noisy, confidence=conf)
    _assert_same_scan(a, b)
    assert a.counts["small_cluster"] >= 144 and a.counts["outlier"] > 0 and a.counts["kept"] > 5000
    assert np.isnan(a.xyz[blob]).all()


@pytest.mark.slow
@pytest.mark.parametrize("name", ["head", "sphere"])
def test_scan_of_an_object_before_darkness_cleans_its_window_identically(monkeypatch, name):
    from gbscan import sim

    r, _ = sim_scan(name)
    sc = Scanner(calibration_from_rig(sim.paper_rig(), PatternSpec()))
    sm = sc.scan(r.image).stripemap
    a, b = _reconstruct_both(monkeypatch, sc, sm.column, confidence=sm.confidence, decoded=sm.valid)
    _assert_same_scan(a, b)
    assert a.counts["kept"] > 10000


def test_motion_study_script(capsys, tmp_path):
    """scripts/motion_study.py: a plane turning and sliding during the exposure is scanned from the
    mid-exposure truth's point of view (still row first, none wrong, the picture written); bad
    options are a usage error, not a traceback."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "scripts" / "motion_study.py"
    spec = importlib.util.spec_from_file_location("motion_study", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    for argv, msg in ((["--steps", "4"], "--steps"), (["--motions", "roll"], "--motions"),
                      (["--travel-mm", "1,-2"], "--travel-mm"), (["--scenes", "cube"], "--scenes")):
        with pytest.raises(SystemExit) as e:
            mod.main(argv)
        assert e.value.code == 2 and msg in capsys.readouterr().err
    assert mod.main(["--scenes", "plane", "--motions", "x,z", "--travel-mm", "0,3", "--steps", "3",
                     "--supersample", "1", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    rows = [x.split() for x in out.splitlines() if x.startswith("plane")]
    assert [r[1] for r in rows] == ["still", "x", "z"], out
    for r in rows:
        assert int(r[5]) == 0 and float(r[4]) > 95.0 and float(r[7]) < 0.1, r   # none wrong, plane kept, RMS
    # sliding along x, the tilted plane's depth changes under each pixel: a measurable smear, still
    # scanned like the still frame
    assert abs(float(rows[1][6]) - float(rows[0][6])) < 2.0
    assert (tmp_path / "motion_plane.png").stat().st_size > 1000
