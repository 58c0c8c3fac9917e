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


# -- the console scripts' start-up: numba's BLAS probe skipped ---------------------------------------
_BLAS_CALLS = {"dot", "vdot", "inner", "matmul", "linalg"}


def _blas_uses(source: str, name: str) -> list[str]:
    """Where the numba-compiled functions of ``source`` call something numba backs with a BLAS
    (``np.dot``, ``np.vdot``, ``np.inner``, ``np.matmul``, ``np.linalg``, ``@``): "file:line what"."""
    import ast

    found = []
    for fn in ast.walk(ast.parse(source)):
        if not isinstance(fn, ast.FunctionDef):
            continue
        if not any("jit" in ast.unparse(d) for d in fn.decorator_list):
            continue
        for node in ast.walk(fn):
            if isinstance(node, (ast.BinOp, ast.AugAssign)) and isinstance(node.op, ast.MatMult):
                found.append(f"{name}:{node.lineno} @")
            elif isinstance(node, ast.Attribute) and node.attr in _BLAS_CALLS:
                found.append(f"{name}:{node.lineno} .{node.attr}")
    return found


def test_no_numba_kernel_needs_a_blas():
    """The console scripts tell numba there is no BLAS (gbscan.cli_common.skip_numba_blas_probe):
    that is only free while no kernel of the project calls one."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    files = sorted([*root.joinpath("gbscan").rglob("*.py"), *root.joinpath("gbcal").rglob("*.py")])
    n_kernels = sum(f.read_text().count("@njit") for f in files)
    assert n_kernels > 200  # the scan looks where the kernels are
    uses = [u for f in files for u in _blas_uses(f.read_text(), str(f.relative_to(root)))]
    assert uses == [], f"numba kernels calling a BLAS (drop skip_numba_blas_probe, or these): {uses}"
    # the check itself finds each kind of call, in a kernel only
    planted = ("from numba import njit\nimport numpy as np\n"
               "@njit(cache=True)\ndef k(a, b):\n    c = a @ b\n    return np.dot(a, b) + np.linalg.norm(c)\n"
               "def plain(a):\n    return a @ a\n")
    assert _blas_uses(planted, "x") == ["x:5 @", "x:6 .dot", "x:6 .linalg"]


_PROBE = """
import sys
import numpy as np
from numba import njit
if sys.argv[1] == "skip":
    from gbscan.cli_common import skip_numba_blas_probe
    skip_numba_blas_probe()
    skip_numba_blas_probe()  # twice: one finder
    from gbscan.cli_common import _SkipNumbaBlasProbe
    assert sum(isinstance(f, _SkipNumbaBlasProbe) for f in sys.meta_path) == 1

@njit
def dot2(a, b):
    return np.dot(a, b)

@njit
def add(a):
    return a + 1

add(1)  # numba's first kernel: it imports numba.np.arraymath, which probes for a BLAS
import numba.np.arraymath
before = "scipy.linalg" in sys.modules
import scipy.linalg  # loads as usual afterwards
x = np.arange(9.0).reshape(3, 3)
print(numba.np.arraymath._HAVE_BLAS, before, np.allclose(dot2(x, x), x @ x), scipy.linalg.cython_blas is not None)
"""


def test_console_scripts_skip_numbas_blas_probe():
    """With the probe skipped numba starts without importing scipy.linalg, and scipy.linalg and
    numba's BLAS-backed np.dot still work afterwards; without it (a library process) numba probes
    as it always did.  If a numba release stops probing, the second half fails: the skip can go."""
    out = {}
    for mode in ("skip", "probe"):
        r = subprocess.run([sys.executable, "-c", _PROBE, mode], capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        out[mode] = r.stdout.split()
    assert out["skip"] == ["False", "False", "True", "True"]
    assert out["probe"] == ["True", "True", "True", "True"]
