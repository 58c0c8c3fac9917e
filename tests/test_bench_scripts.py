"""The benchmark scripts still run end to end (smallest settings, in a subprocess: they set the
process's thread counts).  Their figures are not checked here -- speed belongs to the scripts --
only that they print every line their docstrings promise."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(script: str, *args: str) -> str:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / script), *args], capture_output=True, text=True,
                       env=env, timeout=600)
    assert p.returncode == 0, p.stdout + p.stderr
    return p.stdout


@pytest.mark.slow
def test_bench_decode_prints_stages_memory_and_the_stream_figure():
    out = _run("bench_decode.py", "--runs", "2", "--sizes", "640", "--scene", "head", "--no-peers")
    assert "## 640x480: gbscan decode" in out and "stages: input" in out and "bytes/px" in out
    assert "in a stream (camera measured every 16 frames" in out
    assert "lit window" in out and "(whole frame: --decode-param crop=false)" in out


@pytest.mark.slow
def test_bench_scan_prints_every_stage_and_the_stream_figure():
    out = _run("bench_scan.py", "--scene", "head", "--repeats", "1", "--sizes", "640x480", "--no-command")
    for row in ("decode", "decode (stream)", "triangulate", "clean in scan()", "scan()+mesh", "write .stl"):
        assert f"\n{row:<20}" in out, row
    assert "decode+triangulate: 640x480" in out and "decode+triangulate in a stream" in out
