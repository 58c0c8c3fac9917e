"""Fixtures shared by the test modules."""
import importlib.util
import os
import shutil
import subprocess

import pytest


@pytest.fixture(scope="session")
def xvfb(tmp_path_factory):
    """A private X server (1400x800) whose screen is readable as a file; skips without Xvfb.  One per test
    session: a Tk interpreter keeps its X connection after its windows are destroyed, and Xlib ends the
    process when that server goes away, so the server lives as long as the process."""
    if importlib.util.find_spec("tkinter") is None:
        pytest.skip("this Python has no tkinter (Debian: apt-get install python3-tk): the Tk backend is not exercised")
    exe = shutil.which("Xvfb")
    if exe is None:
        pytest.skip("Xvfb is not installed (apt-get install xvfb): the Tk backend is not exercised")
    fbdir = tmp_path_factory.mktemp("xvfb")
    r, w = os.pipe()
    proc = subprocess.Popen([exe, "-displayfd", str(w), "-screen", "0", "1400x800x24", "-fbdir", str(fbdir),
                             "-nolisten", "tcp"], pass_fds=(w,), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    os.close(w)
    num = b""
    while not num.endswith(b"\n"):
        ch = os.read(r, 1)
        if not ch:
            break
        num += ch
    os.close(r)
    if not num.strip():
        proc.kill()
        pytest.skip("Xvfb did not start")
    yield f":{num.decode().strip()}", fbdir / "Xvfb_screen0"
    proc.terminate()
    proc.wait(timeout=10)
