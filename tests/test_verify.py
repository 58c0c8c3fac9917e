"""Checking a calibration on fresh board poses (gbcal.verify, 'gbcal verify'): exact on synthetic
geometry, silent for the true calibration, and each kind of drift found."""
import copy
import dataclasses
import json

import numpy as np
import pytest

from gbcal.cli import main
from gbcal.patterns import calibration_frames
from gbcal.simsession import board_poses
from gbcal.verify import (BOW_WARN_MM, SCALE_WARN, check_flatness, check_scale, corners_on_plane, findings,
                          fit_plane)
from gbscan import sim
from gbscan.calibfile import calibration_from_rig, save_calibration
from gbscan.errors import GBError
from gbscan.io import write_png, write_session_yaml
from gbscan.pattern import PatternSpec
from gbscan.rig import paper_rig

BOARD = (9, 7, 20.0)
SPEC = PatternSpec()


# -- the geometry, exactly ------------------------------------------------------------------------
def test_plane_fit_is_exact_and_ignores_outliers():
    rng = np.random.default_rng(0)
    n_true = np.array([0.2, -0.1, -1.0])
    n_true /= np.linalg.norm(n_true)
    xy = rng.uniform(-100, 100, (2000, 2))
    # points on n . p + 640 = 0
    z = (-640 - n_true[0] * xy[:, 0] - n_true[1] * xy[:, 1]) / n_true[2]
    p = np.column_stack([xy, z])
    p[:50, 2] += 30.0                                     # 2.5 % far outliers
    n, d, use = fit_plane(p)
    assert np.allclose(n, n_true, atol=1e-12) and d == pytest.approx(640.0, abs=1e-9)
    assert not use[:50].any() and use[50:].all()
    f = check_flatness(p)
    assert f.rms_mm < 1e-9 and f.bow_mm < 1e-9 and f.outlier_frac == pytest.approx(0.025)
    assert f.distance_mm == pytest.approx(640.0) and f.tilt_deg == pytest.approx(np.degrees(np.arccos(-n_true[2])))


def test_bow_is_the_peak_to_valley_of_the_curvature():
    # a paraboloid cap z = 650 + c r^2 over a disk of radius 100 mm: peak to valley c * 100^2,
    # whatever the tilt and offset added to it
    rng = np.random.default_rng(1)
    r = 100 * np.sqrt(rng.uniform(0, 1, 20000))
    a = rng.uniform(0, 2 * np.pi, r.size)
    x, y = r * np.cos(a), r * np.sin(a)
    x[:4], y[:4] = [100, -100, 0, 0], [0, 0, 100, -100]   # the rim reached exactly
    x[4] = y[4] = 0.0                                     # and the apex
    c = 2e-5
    z = 650 + c * (x * x + y * y) + 0.1 * x - 0.05 * y
    f = check_flatness(np.column_stack([x, y, z]))
    assert f.bow_mm == pytest.approx(c * 100 ** 2, rel=0.02)   # 0.2 mm (the plane axes tilt a little)


def test_scale_from_corners_on_the_plane():
    cols, rows, s = 9, 7, 20.0
    j, i = np.mgrid[0:rows, 0:cols]
    model = np.stack([i.ravel() * s - 80, j.ravel() * s - 60, np.full(i.size, 650.0)], axis=1)
    rays = model / np.linalg.norm(model, axis=1, keepdims=True)
    c3 = corners_on_plane(rays, [0.0, 0.0, -1.0], 650.0)
    assert np.allclose(c3, model, atol=1e-9)
    sc = check_scale(c3, cols, rows, s)
    assert abs(sc.scale_error) < 1e-12 and sc.spacing_rms_mm < 1e-9 and sc.fit_rms_mm < 1e-9
    # the plane 1 % too far: every corner 1 % further along its ray, squares 1 % larger
    sc = check_scale(corners_on_plane(rays, [0.0, 0.0, -1.0], 656.5), cols, rows, s)
    assert sc.scale_error == pytest.approx(0.01, abs=1e-12)
    assert np.isnan(corners_on_plane(rays, [0.0, 0.0, -1.0], -650.0)).all()   # behind the camera
    with pytest.raises(GBError, match="expected 63 corners"):
        check_scale(c3[:10], cols, rows, s)


# -- a simulated rig: fresh poses, the true calibration and drifted ones -------------------------
@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """Three board poses (not a calibration session's) under the white and the pattern frames."""
    root = tmp_path_factory.mktemp("verify") / "fresh"
    rig = paper_rig()
    frames = {k: v for k, v in calibration_frames(SPEC).items() if k in ("white", "stripes")}
    cond = sim.preset("typical")
    for k, (R, t) in enumerate(board_poses(rig, BOARD, 3, seed=11)):
        tr = sim.trace(rig, sim.scenes.board(*BOARD, R, t), cond)
        (root / f"pose_{k:03d}").mkdir(parents=True)
        for i, (name, frame) in enumerate(frames.items()):
            r = sim.render_traced(rig, tr, frame, np.random.default_rng([11, k, i]))
            write_png(root / f"pose_{k:03d}" / f"{name}.png", r.image)
    write_session_yaml(root, board=BOARD, camera_size=rig.camera.size,
                       projector_size=(rig.projector.width, rig.projector.height), frames=list(frames))
    return root


def _focal(cal, factor):
    c = copy.deepcopy(cal)
    K = cal.camera.K.copy()
    K[0, 0] *= factor
    K[1, 1] *= factor
    c.camera = dataclasses.replace(cal.camera, K=K)
    return c


CALIBS = {
    "true": lambda: calibration_from_rig(paper_rig(), SPEC),
    # measured on two simulated sessions (5 + 6 poses): scale -0.2 ... -2.3 %, median -0.9 / -1.0 %
    "focal +1 %": lambda: _focal(calibration_from_rig(paper_rig(), SPEC), 1.01),
    # bow 1.1-6.2 mm
    "no distortion": lambda: calibration_from_rig(paper_rig(distortion=False), SPEC),
    # bow 0.15-0.25 mm (the true calibration's 0.01-0.05): points moved 0.5 mm median, 2.5 mm p95
    "baseline +1 %": lambda: calibration_from_rig(paper_rig(baseline_mm=202.0), SPEC),
}
EXPECT = {"true": set(), "focal +1 %": {"scale"}, "no distortion": {"bow"}, "baseline +1 %": {"bow"}}


@pytest.mark.parametrize("name", list(CALIBS))
def test_drift_is_found_and_a_sound_calibration_passes(session, tmp_path, capsys, name):
    cal = save_calibration(tmp_path / "calib.yaml", CALIBS[name]())
    js = tmp_path / "v.json"
    rc = main(["verify", str(session), "--calib", str(cal), "--json", str(js), "--strict"])
    out = capsys.readouterr().out
    d = json.loads(js.read_text())
    keys = {f["key"] for f in d["findings"]}
    if name == "no distortion":
        keys.discard("scale")        # (it may scale some poses too; the bow is what it must show)
    assert keys == EXPECT[name], (name, out)
    assert rc == (3 if EXPECT[name] else 0)
    assert len(d["poses"]) == 3 and not d["skipped"]
    if name == "true":
        assert "the calibration holds" in out
        for p in d["poses"]:
            f, s = p["flatness"], p["scale"]
            assert f["rms_mm"] < 0.12 and f["bow_mm"] < BOW_WARN_MM / 2 and abs(s["scale_error"]) < SCALE_WARN / 3
            assert s["n_corners"] == 63 and s["fit_rms_mm"] < 0.1 and 400 < f["distance_mm"] < 850   # (to the plane: a tilted board is nearer)
    if name == "focal +1 %":
        assert -0.02 < np.median([p["scale"]["scale_error"] for p in d["poses"]]) < -0.005


def test_findings_follow_the_figures(session, tmp_path):
    from gbcal.verify import Flatness, PoseCheck, Scale

    def pose(bow=0.03, scale=0.0, rms=0.08):
        f = Flatness(1000, (0.0, 0.0, -1.0), 650.0, 650.0, 0.0, rms, 3 * rms, bow, 0.01)
        return PoseCheck("p", f, Scale(63, 20.0, 20 * (1 + scale), scale, 0.02, 0.02), 10000, 0.4)

    assert findings([pose(), pose()]) == []
    assert [f.key for f in findings([pose(scale=0.01), pose(scale=0.01), pose()])] == ["scale"]   # the median
    assert findings([pose(scale=0.01), pose(), pose()]) == []
    assert [f.key for f in findings([pose(), pose(bow=0.5)])] == ["bow"]                       # the worst
    assert [f.key for f in findings([pose(rms=0.5)])] == ["rms"]
    assert [f.key for f in findings([pose(rms=0.5, bow=0.5)])] == ["bow"]


def test_verify_preview_and_bad_input(session, tmp_path, capsys):
    cal = save_calibration(tmp_path / "calib.yaml", CALIBS["true"]())
    prev = tmp_path / "prev"
    assert main(["verify", str(session / "pose_001"), "--calib", str(cal), "--preview", str(prev)]) == 0
    assert sorted(p.name for p in prev.iterdir()) == ["verify_pose_001.png"]     # one pose: the board from ..
    capsys.readouterr()
    # one line each, non-zero
    bare = tmp_path / "bare"
    bare.mkdir()
    (bare / "white.png").write_bytes((session / "pose_000" / "white.png").read_bytes())
    cases = [
        (["verify", str(tmp_path / "nowhere"), "--calib", str(cal)], "is not a folder"),
        (["verify", str(bare), "--calib", str(cal)], "no session.yaml: give --board"),
        (["verify", str(bare), "--calib", str(cal), "--board", "9x7", "--square-mm", "20"], "has no stripes.png"),
        (["verify", str(session), "--calib", str(cal), "--json", str(tmp_path / "v.txt")], "must end in .json"),
        (["verify", str(session), "--calib", str(tmp_path / "none.yaml")], "none.yaml"),
    ]
    for argv, match in cases:
        assert main(argv) == 1
        err = capsys.readouterr().err
        assert err.startswith("gbcal verify: error:") and match in err and len(err.strip().splitlines()) == 1, err
