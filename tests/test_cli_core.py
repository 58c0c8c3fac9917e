"""The command-line front ends: help, the pattern commands, one-line errors."""
import subprocess
import sys

import numpy as np
import yaml

from gbcal.patterns import calibration_frames, gray_code, gray_decode
from gbscan.io import read_image_rgb
from gbscan.pattern import PatternSpec, render_pattern


def run(*args):
    return subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True)


def test_help_explains_workflow():
    r = run("gbscan.cli", "--help")
    assert r.returncode == 0 and "Workflow" in r.stdout and "pattern" in r.stdout
    r = run("gbcal.cli", "--help")
    assert r.returncode == 0 and "calibrate" in r.stdout


def test_pattern_command(tmp_path):
    r = run("gbscan.cli", "pattern", "-o", str(tmp_path / "p.png"), "--projector", "800x600")
    assert r.returncode == 0, r.stderr
    img = read_image_rgb(tmp_path / "p.png")
    np.testing.assert_array_equal(img, render_pattern(PatternSpec(800, 600)))


def test_patterns_command(tmp_path):
    r = run("gbcal.cli", "patterns", str(tmp_path / "frames"))
    assert r.returncode == 0, r.stderr
    listing = yaml.safe_load((tmp_path / "frames" / "patterns.yaml").read_text())
    frames = listing["frames"]
    assert frames[:3] == ["white", "black", "stripes"] and len(frames) == 17
    for name in frames:
        assert read_image_rgb(tmp_path / "frames" / f"{name}.png").shape == (768, 1024, 3)


def test_gray_code_decodes_every_stripe():
    spec = PatternSpec()
    frames = calibration_frames(spec)
    bits = [n for n in frames if n.startswith("gray_") and not n.endswith("_inv")]
    code = np.zeros(spec.width, np.int64)
    for name in bits:
        code = code * 2 + (frames[name][0, :, 1] > frames[name + "_inv"][0, :, 1])
    np.testing.assert_array_equal(gray_decode(code), np.arange(spec.width) // spec.stripe_px)
    np.testing.assert_array_equal(gray_decode(gray_code(np.arange(1000))), np.arange(1000))


def test_errors_are_one_line(tmp_path):
    for args in (["gbscan.cli", "pattern", "-o", str(tmp_path / "no" / "p.png")],
                 ["gbscan.cli", "pattern"],
                 ["gbscan.cli", "pattern", "-o", "x.png", "--stripe-px", "1"],
                 ["gbcal.cli", "patterns", str(tmp_path), "--projector", "axb"],
                 ["gbscan.cli", "nonsense"]):
        r = run(*args)
        assert r.returncode != 0
        assert "Traceback" not in r.stderr
        assert len(r.stderr.strip().splitlines()) == 1, r.stderr
