"""gbcal calibrate / gbcal report end to end on simulated sessions, and their failure modes."""
import shutil
import subprocess
import sys

import numpy as np
import pytest
import yaml

from gbscan.calibfile import calibration_from_rig, load_calibration
from gbscan.errors import GBError
from gbscan.pattern import PatternSpec

BOARD = (7, 5, 25.0)


def _small_rig():
    from gbscan import sim
    from gbscan.rig import Rig

    r = sim.paper_rig()
    return Rig(r.camera.scaled(0.5), r.projector, r.R_cam_proj, r.t_cam_proj)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """5 poses at 320x240 (typical conditions): small enough to render in well under a minute."""
    from gbcal.simsession import write_session

    out = tmp_path_factory.mktemp("sess") / "s"
    write_session(out, _small_rig(), PatternSpec(), board=BOARD, n_poses=5, preset="typical", seed=0,
                  progress=False)
    return out


@pytest.fixture(scope="module")
def run(session):
    from gbcal.calibrate import calibrate_session

    return calibrate_session(session, log=lambda s: None)


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "gbcal.cli", *map(str, args)], capture_output=True, text=True)


def _normal_errors_deg(calib, rig):
    n, _ = rig.column_planes(calib.plane_column)
    return np.degrees(np.arccos(np.clip(np.sum(n * calib.plane_normal, axis=1), -1, 1)))


def test_calibration_recovers_the_small_rig(run, session):
    from gbcal.simsession import load_truth

    truth = load_truth(session)
    rig = truth["rig"]
    cal = run.calibration
    K, K0 = cal.camera.K, rig.camera.K
    st = cal.uncertainty["camera_std"]
    assert abs(K[0, 0] / K0[0, 0] - 1) < 0.006 and abs(K[1, 1] / K0[1, 1] - 1) < 0.006
    for i, j, name in ((0, 2, "cx"), (1, 2, "cy")):
        assert abs(K[i, j] - K0[i, j]) < max(4 * st[name], 0.5)
    assert _normal_errors_deg(cal, rig).max() < 0.3  # 4 small views: the acceptance test is the slow one
    # planes of every boundary seen, from the pinhole model: a consistent pencil
    assert cal.n_planes > 40 and np.all(np.diff(cal.plane_index) > 0)
    np.testing.assert_allclose(cal.plane_column, cal.pattern.boundary_column(cal.plane_index))
    assert abs(cal.projector["baseline_mm"] - np.linalg.norm(rig.t_cam_proj)) < 2.0
    r = cal.residuals
    assert r["corner_rms_px"] < 0.3 and r["stripe_rms_px"] < 0.1 and r["captures_used"] >= 4
    assert len(r["captures"]) == 5
    for c in r["captures"]:
        assert c["used"] or c["reason"]
    assert r["corner_refiner"] == "symmetric"
    # the depth uncertainty a scan inherits, and the depth error the estimated rig really has there
    ds = cal.uncertainty["depth_std_mm"]
    assert 400 < ds["distance_mm"] < 900 and 0 < ds["centre"] <= ds["max"] < 5.0
    est = run.bundle.rig
    q = np.array([[(rig.camera.width - 1) / 2, (rig.camera.height - 1) / 2]])
    p = np.concatenate([rig.camera.normalize(q), [[1.0]]], axis=1) * ds["distance_mm"]
    n, d = est.column_planes(rig.project_to_projector(p)[:, 0])
    ray = np.concatenate([est.camera.normalize(q), [[1.0]]], axis=1)
    assert abs(d[0] / (n[0] @ ray[0]) - ds["distance_mm"]) < 4.5 * ds["centre"]


def test_save_run_writes_yaml_and_samples(run, tmp_path):
    from gbcal.calibrate import save_run

    path, npz = save_run(tmp_path / "calib.yaml", run)
    back = load_calibration(path)
    np.testing.assert_allclose(back.plane_normal, run.calibration.plane_normal, atol=1e-12)
    assert back.residuals["samples"] == "calib.residuals.npz" and npz.is_file()
    with np.load(npz) as z:
        assert z["stripe_uv"].shape[0] == z["stripe_residual_px"].shape[0] == z["stripe_index"].shape[0]
        assert z["corner_uv"].shape == z["corner_residual_px"].shape


@pytest.mark.slow
def test_cli_calibrate_then_report(session, tmp_path):
    r = _cli("calibrate", session, "-o", tmp_path / "calib.yaml", "--preview", tmp_path / "prev")
    assert r.returncode == 0, r.stderr
    assert "fx" in r.stdout and "baseline" in r.stdout and "pose_" in r.stderr
    assert "depth uncertainty of a scan at" in r.stdout and "(symmetric refinement)" in r.stdout
    assert len(list((tmp_path / "prev").glob("pose_*.png"))) == 5
    r = _cli("report", tmp_path / "calib.yaml", "-o", tmp_path / "rep")
    assert r.returncode == 0, r.stderr
    for name in ("residual_field", "residual_histogram", "per_capture", "coverage", "plane_residuals"):
        assert (tmp_path / "rep" / f"{name}.png").stat().st_size > 1000
    summary = (tmp_path / "rep" / "summary.txt").read_text()
    assert "worst captures" in summary and "depth uncertainty of a scan at" in summary
    # without the samples file the report still works, with fewer pictures and a note
    (tmp_path / "calib.residuals.npz").unlink()
    r = _cli("report", tmp_path / "calib.yaml", "-o", tmp_path / "rep2")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "rep2" / "per_capture.png").is_file()
    assert not (tmp_path / "rep2" / "residual_field.png").exists()
    assert "missing" in (tmp_path / "rep2" / "summary.txt").read_text()


def _copy(session, tmp_path):
    dst = tmp_path / "s"
    shutil.copytree(session, dst)
    return dst


def _fails(args, out, *words):
    r = _cli(*args)
    assert r.returncode == 1, r.stdout + r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert "Traceback" not in r.stderr and last.startswith("gbcal calibrate: error:")
    for w in words:
        assert w in last, last
    assert not out.exists() and not out.with_name(out.stem + ".residuals.npz").exists()


def test_missing_frame_is_named(session, tmp_path):
    s = _copy(session, tmp_path)
    (s / "pose_001" / "gray_03_inv.png").unlink()
    out = tmp_path / "c.yaml"
    _fails(["calibrate", s, "-o", out], out, "gray_03_inv.png", "does not exist")


def test_corrupt_png_is_named(session, tmp_path):
    s = _copy(session, tmp_path)
    (s / "pose_003" / "black.png").write_bytes(b"\x89PNG broken")
    out = tmp_path / "c.yaml"
    _fails(["calibrate", s, "-o", out], out, "pose_003", "could not be read")


def test_mixed_image_sizes_are_refused(session, tmp_path):
    from gbscan.io import write_png

    s = _copy(session, tmp_path)
    write_png(s / "pose_002" / "white.png", np.zeros((480, 640, 3), np.uint8))
    out = tmp_path / "c.yaml"
    _fails(["calibrate", s, "-o", out], out, "640x480", "320x240")


def test_captures_without_board_are_dropped_then_too_few(session, tmp_path):
    from gbscan.io import write_png

    s = _copy(session, tmp_path)
    for p in ("pose_000", "pose_001"):
        write_png(s / p / "white.png", np.full((240, 320, 3), 90, np.uint8))
    out = tmp_path / "c.yaml"
    _fails(["calibrate", s, "-o", out], out, "too few usable captures", "pose_000", "pose_001")


def test_parallel_captures_are_refused_naming_the_unobservable(session, tmp_path):
    s = _copy(session, tmp_path)
    for p in ("pose_001", "pose_002", "pose_003", "pose_004"):
        shutil.rmtree(s / p)
        shutil.copytree(s / "pose_000", s / p)
    out = tmp_path / "c.yaml"
    _fails(["calibrate", s, "-o", out], out, "fx", "tilt")


def test_session_without_gray_frames_is_refused(session, tmp_path):
    s = _copy(session, tmp_path)
    d = yaml.safe_load((s / "session.yaml").read_text())
    d["frames"] = ["white", "black", "stripes"]
    (s / "session.yaml").write_text(yaml.safe_dump(d))
    from gbcal.calibrate import calibrate_session

    with pytest.raises(GBError, match="Gray-code"):
        calibrate_session(s, log=lambda s: None)


@pytest.mark.slow
def test_paper_geometry_accuracy(tmp_path_factory):
    """The acceptance figures: 12 poses, typical conditions, the paper's rig; and a scan of a plane
    with the estimated calibration vs the true one (true projector columns + 0.1 px noise)."""
    from gbcal.calibrate import calibrate_session
    from gbcal.simsession import load_truth, write_session
    from gbscan import sim
    from gbscan.pattern import render_pattern
    from gbscan.triangulate import PlaneTable, triangulate

    s = write_session(tmp_path_factory.mktemp("paper") / "s", sim.paper_rig(), PatternSpec(), n_poses=12,
                      preset="typical", seed=0, progress=False)
    rig = load_truth(s)["rig"]
    cal = calibrate_session(s, log=lambda m: None).calibration
    K, K0 = cal.camera.K, rig.camera.K
    assert abs(K[0, 0] / K0[0, 0] - 1) < 1e-3 and abs(K[1, 1] / K0[1, 1] - 1) < 1e-3
    assert abs(K[0, 2] - K0[0, 2]) < 0.5 and abs(K[1, 2] - K0[1, 2]) < 0.5
    assert _normal_errors_deg(cal, rig).max() < 0.02
    spec = PatternSpec()
    r = sim.render(rig, sim.scenes.plane(650.0, (0.0, 20.0)), render_pattern(spec), "typical", seed=1)
    col = np.where(r.lit, r.proj_xy[..., 0], np.nan) + np.random.default_rng(0).normal(0, 0.1, r.lit.shape)
    z_true = r.point[..., 2]
    rms = []
    for c in (cal, calibration_from_rig(rig, spec)):
        p = triangulate(c.camera.pixel_rays(), col.astype(np.float64), PlaneTable.from_calibration(c))
        e = p[..., 2] - z_true
        rms.append(float(np.sqrt(np.nanmean(e ** 2))))
    assert rms[0] < 1.3 * rms[1], rms


def _camera_file(camera, std, model="k1k2p1p2"):
    """A camera-only calibration file's contents (what 'gbcal camera' writes) for ``camera``."""
    from gbscan.calibfile import Calibration

    names = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    return Calibration(camera, np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)), np.zeros(0),
                       residuals={"camera_rms_px": 0.03, "model": model},
                       uncertainty={"camera_std": {n: float(s) for n, s in zip(names, std)}})


def test_a_camera_prior_holds_the_camera_and_is_recorded(session, run, tmp_path):
    from gbcal.calibrate import calibrate_session, summary_lines
    from gbcal.simsession import load_truth

    rig = load_truth(session)["rig"]
    free = run.calibration
    # the true camera, known to 0.02 px (fx, fy), 0.05 px (cx, cy), 1e-4 (distortion)
    std = [0.02, 0.02, 0.05, 0.05, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5]
    held = calibrate_session(session, log=lambda s: None, camera_prior=_camera_file(rig.camera, std),
                             camera_prior_name="camera file truth.yaml")
    K, K0, Kf = held.calibration.camera.K, rig.camera.K, free.camera.K
    assert abs(K[0, 0] - K0[0, 0]) < 0.1 and abs(K[1, 1] - K0[1, 1]) < 0.1, (K, Kf)  # 5 sigma of the prior
    assert abs(K[0, 2] - K0[0, 2]) < 0.25 and abs(K[1, 2] - K0[1, 2]) < 0.25
    assert [c["capture"] for c in held.calibration.residuals["captures"]] == [f"pose_{i:03d}" for i in range(5)]
    assert list(held.samples["used_captures"]) == list(run.samples["used_captures"])
    pr = held.calibration.residuals["camera_prior"]
    assert pr["file"] == "camera file truth.yaml" and set(pr["z"]) == {"fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"}
    ds, ds_free = held.calibration.uncertainty["depth_std_mm"], free.uncertainty["depth_std_mm"]
    assert ds["centre"] < 0.5 * ds_free["centre"], (ds, ds_free)
    assert any("camera held to camera file truth.yaml" in line for line in summary_lines(held))
    # a prior far from what the session sees is reported, sigma by sigma
    off = rig.camera.scaled(1.0)
    off.K[0, 0] += 15.0  # a refocused lens
    far = calibrate_session(session, log=lambda s: None, camera_prior=_camera_file(off, std))
    assert any("disagrees with it on fx" in line for line in summary_lines(far)), far.calibration.residuals["camera_prior"]


def test_a_camera_prior_that_cannot_apply_is_refused(session, run, tmp_path):
    from gbcal.calibrate import calibrate_session, prior_arrays, prior_model

    # a whole rig's calibration carries its camera's model too, and can serve
    assert prior_model(run.calibration, "rig") == "k1k2p1p2"
    mu, sd = prior_arrays(run.calibration, "k1k2p1p2", "rig")
    assert mu.shape == sd.shape == (8,) and np.all(sd > 0)
    from gbscan.calibfile import save_calibration

    from gbscan import sim

    std = [0.1] * 4 + [1e-3] * 5
    big = sim.paper_rig().camera  # 640x480: the session is 320x240
    with pytest.raises(GBError, match="640x480 camera but session .* 320x240"):
        calibrate_session(session, log=lambda s: None, camera_prior=_camera_file(big, std))
    small = _small_rig().camera
    with pytest.raises(GBError, match="uncertainty.camera_std must give .* k1, k2, p1, p2"):
        calibrate_session(session, log=lambda s: None, camera_prior=_camera_file(small, std[:4]))
    with pytest.raises(GBError, match="residuals.model must name"):
        calibrate_session(session, log=lambda s: None, camera_prior=_camera_file(small, std, model="fisheye"))
    # the command: one line naming the file and the fault, nothing written
    cam = tmp_path / "camera.yaml"
    save_calibration(cam, _camera_file(small, std[:4]))
    out = tmp_path / "c.yaml"
    _fails(["calibrate", session, "-o", out, "--camera", cam], out, str(cam), "uncertainty.camera_std")
    save_calibration(cam, _camera_file(small, std))
    _fails(["calibrate", session, "-o", out, "--camera", cam, "--model", "k1k2p1p2k3"], out,
           "--model k1k2p1p2k3 differs", "k1k2p1p2")
    _fails(["calibrate", session, "-o", out, "--camera", tmp_path / "missing.yaml"], out, "missing.yaml")
