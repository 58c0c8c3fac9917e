"""gbscan.heap: freed memory kept for the next frame (glibc's malloc thresholds)."""
from __future__ import annotations

import platform
import resource
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from gbscan import heap

GLIBC = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"

# a frame's worth of large arrays allocated, written and freed again and again; prints the minor
# page faults of the last 10 rounds (the first rounds grow the heap)
_ROUNDS = textwrap.dedent("""
    import resource, sys
    import numpy as np
    if sys.argv[1] == "keep":
        from gbscan.heap import keep_freed_memory
        assert keep_freed_memory()

    def frame():
        arrays = [np.empty((1024, 1280), np.float32) for _ in range(6)]
        for a in arrays:
            a.fill(1.0)
        return sum(float(a[0, 0]) for a in arrays)

    for _ in range(3):
        frame()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(10):
        frame()
    print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
""")


def _faults(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", _ROUNDS, mode], capture_output=True, text=True, check=True,
                         cwd=str(__import__("pathlib").Path(__file__).resolve().parents[1]))
    return int(out.stdout.strip())


@pytest.mark.skipif(not GLIBC, reason="glibc's malloc only")
def test_frames_reuse_freed_memory_without_page_faults():
    # 10 rounds of 6 x 5.2 MB: ~7700 fresh pages when the memory goes back to the system each time
    # (the arrays are above glibc's default 128 KiB mmap threshold until a free raises it; the
    # trim threshold then returns the heap's top)
    kept = _faults("keep")
    pages = 10 * 6 * 1024 * 1280 * 4 // 4096
    assert kept < pages // 20, (kept, pages)


@pytest.mark.skipif(not GLIBC, reason="glibc's malloc only")
def test_without_the_settings_the_same_rounds_fault():
    # the counterfactual: glibc's adaptive thresholds alone give back (and fault in again) at least
    # part of each frame's memory in this pattern -- what keep_freed_memory removes
    system = _faults("system")
    assert system > 10 * 1024 * 1280 * 4 // 4096, system


def test_opt_out_and_idempotence(monkeypatch):
    monkeypatch.setattr(heap, "_state", {})
    monkeypatch.setenv(heap.ENV, "system")
    assert heap.keep_freed_memory() is False
    assert heap.keep_freed_memory() is False   # remembered: no second mallopt
    monkeypatch.setattr(heap, "_state", {})
    monkeypatch.delenv(heap.ENV)
    assert heap.keep_freed_memory() is GLIBC
    assert heap.keep_freed_memory() is GLIBC


def test_scanner_and_commands_set_it(monkeypatch, tmp_path):
    # the Scanner and the command line call it (the call itself is cheap and idempotent)
    calls = []
    monkeypatch.setattr(heap, "keep_freed_memory", lambda: calls.append(1) or True)
    from gbscan import cli

    assert cli.main(["pattern", "-o", str(tmp_path / "p.png")]) == 0
    assert calls, "gbscan commands must keep freed memory"
    calls.clear()
    from gbscan.calibfile import calibration_from_rig
    from gbscan.pattern import PatternSpec
    from gbscan.rig import paper_rig
    from gbscan.scan import Scanner

    Scanner(calibration_from_rig(paper_rig(), PatternSpec()))
    assert calls, "Scanner must keep freed memory"
