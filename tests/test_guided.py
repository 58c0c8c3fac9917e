"""scripts/guided_calibration.py --simulate: the guided capture flow end to end, headless."""
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from gbscan.calibfile import load_calibration
from gbscan.io import load_session

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "guided_calibration.py"


def _module():
    spec = importlib.util.spec_from_file_location("guided_calibration", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_coverage_bookkeeping():
    g = _module()
    cov = g.Coverage((320, 240), grid=(4, 3))
    assert "12 of 12" in cov.missing() and "left/right/up/down" in cov.missing()
    cov.add(np.array([[10.0, 10.0], [300.0, 230.0]]), np.array([0.5, 0.0, 0.866]))
    assert cov.cells[0, 0] and cov.cells[2, 3] and cov.tilts["right"] == 1
    assert g.Coverage.tilt_bin(np.array([0.0, -0.4, 0.9])) == "up"
    assert g.Coverage.tilt_bin(np.array([0.0, 0.0, 1.0])) == "square-on"


@pytest.mark.slow
def test_simulated_guided_session_end_to_end(tmp_path, capsys):
    g = _module()
    sess = tmp_path / "session"
    rc = g.main([str(sess), "--simulate", "--poses", "5", "--board", "7x5", "--square-mm", "25",
                 "--sim-preset", "typical", "-o", str(tmp_path / "calib.yaml")])
    out = capsys.readouterr()
    assert rc == 0, out.err
    s = load_session(sess)
    assert len(s.poses) == 5 and s.camera_size == (320, 240) and s.extra["pattern"]["stripe_px"] == 8
    assert all(s.frame_path(4, f).is_file() for f in s.frames)
    assert "pose 5/5 captured" in out.err and "still missing" in out.err
    cal = load_calibration(tmp_path / "calib.yaml")
    assert abs(cal.camera.K[0, 0] / 400.0 - 1) < 0.01 and cal.n_planes > 40
    assert (tmp_path / "calib.residuals.npz").is_file()
    # a second run into the same folder is refused, with one line and nothing overwritten
    rc = g.main([str(sess), "--simulate", "--poses", "1", "--no-calibrate"])
    assert rc == 1 and "already holds captures" in capsys.readouterr().err


def test_bad_options_are_one_line(tmp_path, capsys):
    g = _module()
    assert g.main([str(tmp_path / "s"), "--simulate", "--board", "9by7"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "COLSxROWS" in err[0]
