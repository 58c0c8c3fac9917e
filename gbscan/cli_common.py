"""Shared command-line plumbing for ``gbscan`` and ``gbcal``.

Each pipeline stage is a module ``<package>/commands/<stage>.py`` that defines

* ``HELP`` -- one line for the command list,
* ``add_arguments(parser)`` -- its options,
* ``run(args) -> int`` -- the work; raises :class:`gbscan.errors.GBError` for bad input.

The dispatcher imports only the chosen stage's module (heavy libraries such as open3d load only
when a command needs them), turns GBError, a missing file or a bad option into one line on
stderr and a non-zero exit status (2 for usage, 1 for a failed run), and never shows a traceback
for bad input.  ``GB_DEBUG=1`` shows tracebacks for unexpected errors.
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys

from .errors import GBError


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, not argparse's usage dump
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def size_arg(text: str) -> tuple[int, int]:
    """'WxH' -> (W, H) for argparse."""
    try:
        w, h = text.lower().split("x")
        w, h = int(w), int(h)
        if w <= 0 or h <= 0:
            raise ValueError
        return w, h
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 1024x768, got '{text}'") from None


def add_bayer_argument(p) -> None:
    """``--bayer PATTERN`` of the simulators and the study scripts: a colour camera with that Bayer
    mosaic (``gbscan.sim.Conditions.bayer``); default "" (full RGB per pixel)."""
    from .sim.presets import BAYER_PATTERNS

    p.add_argument("--bayer", default="", choices=BAYER_PATTERNS, metavar="PATTERN",
                   help=f"a colour camera with this Bayer mosaic ({', '.join(BAYER_PATTERNS)}), demosaiced by "
                        "OpenCV; default: full RGB per pixel, like the paper's 3-CCD camera")


#: the simulated paper rig's default camera-projector baseline, camera and projector
#: (``gbscan.rig.paper_rig``)
DEFAULT_BASELINE_MM = 200.0
DEFAULT_CAMERA_PX = (640, 480)
DEFAULT_PROJECTOR_PX = (1024, 768)


def camera_size(text: str) -> tuple[int, int]:
    """``--camera WxH``: a camera size in pixels (:func:`size_arg`) that
    :func:`gbscan.rig.paper_rig` builds (``CAMERA_SIDE_PX``)."""
    return _rig_size(text, "camera")


def projector_size(text: str) -> tuple[int, int]:
    """``--projector WxH`` of the simulators: a projector size in pixels that
    :func:`gbscan.rig.paper_rig` builds (``CAMERA_SIDE_PX``)."""
    return _rig_size(text, "projector")


def _rig_size(text: str, what: str) -> tuple[int, int]:
    from .rig import CAMERA_SIDE_PX

    w, h = size_arg(text)
    lo, hi = CAMERA_SIDE_PX
    if not (lo <= w <= hi and lo <= h <= hi):
        raise argparse.ArgumentTypeError(f"{what} size must be {lo}-{hi} pixels a side, got {text!r}")
    return w, h


def add_rig_arguments(p) -> None:
    """``--baseline-mm B``, ``--camera WxH`` and ``--projector WxH`` of the simulators and the study
    scripts: the simulated paper rig with its projector ``B`` mm right of the camera (still toed in
    to 650 mm), a camera and a projector of W x H pixels behind the paper's lenses; see
    :func:`rig_from_args`."""
    p.add_argument("--baseline-mm", type=float, default=DEFAULT_BASELINE_MM,
                   help="camera-projector baseline of the simulated rig in mm (default 200; the projector stays "
                        "toed in to 650 mm; negative: on the camera's left): less baseline, less grazing light "
                        "and shadow, more depth noise.  "
                        "Plan a rig: 'gbcal simulate-session --baseline-mm B', 'gbcal calibrate', then scan "
                        "'gbscan simulate --baseline-mm B' frames with that calibration")
    p.add_argument("--camera", type=camera_size, default=DEFAULT_CAMERA_PX, metavar="WxH",
                   help="camera pixels behind the paper camera's lens (default 640x480; e.g. 1280x960: twice the "
                        "pixels over the same field of view, stripes twice as wide in the image, which the "
                        "decoder shrinks back: --resample)")
    p.add_argument("--projector", type=projector_size, default=DEFAULT_PROJECTOR_PX, metavar="WxH",
                   help="projector pixels behind the paper projector's lens (default 1024x768; e.g. 1920x1080: "
                        "stripes of the same width in projector px 1.9 times narrower in the image -- pair it "
                        "with --camera 1280x1024 -- and 240 stripes of 8 px, see the marker code in "
                        "docs/method.md)")


def rig_from_args(args):
    """The simulated paper rig of ``--baseline-mm``, ``--camera`` and ``--projector``
    (:func:`add_rig_arguments`); GBError naming the option for a baseline that is not a positive
    length."""
    from .errors import GBError
    from .rig import paper_rig

    b = args.baseline_mm
    if not (b != 0 and abs(b) < float("inf")):
        raise GBError(f"--baseline-mm must be a non-zero length in mm (the projector that far right of the camera; "
                      f"negative: left), got {b}")
    return paper_rig(baseline_mm=b, camera_px=tuple(args.camera), projector_px=tuple(args.projector))


def rig_label(args) -> str:
    """", baseline B mm, camera WxH, projector WxH" for a rig other than the default one (progress
    lines, headers), else ""."""
    out = "" if args.baseline_mm == DEFAULT_BASELINE_MM else f", baseline {args.baseline_mm:g} mm"
    cam = tuple(args.camera)
    out += "" if cam == DEFAULT_CAMERA_PX else f", camera {cam[0]}x{cam[1]}"
    proj = tuple(args.projector)
    return out + ("" if proj == DEFAULT_PROJECTOR_PX else f", projector {proj[0]}x{proj[1]}")


def add_capture_arguments(p) -> None:
    """``--jpeg QUALITY``, ``--jpeg-sampling``, ``--yuv``, ``--lateral-ca-px`` and ``--gloss`` of the
    simulators and the study scripts: frames stored as JPEG (``gbscan.sim.Conditions.jpeg_quality``
    / ``jpeg_sampling``) or delivered as YUV (``Conditions.yuv``), a lens with lateral chromatic
    aberration (``Conditions.lateral_ca_px``), glossy surfaces (``Conditions.specular`` /
    ``shininess``); default lossless RGB through a perfect lens, matte surfaces."""
    from .sim.presets import DEFAULT_SHININESS, JPEG_SAMPLINGS, YUV_FORMATS

    p.add_argument("--jpeg", type=int, default=0, metavar="QUALITY",
                   help="the camera stores JPEG of this quality (1-100; default 0: lossless frames)")
    p.add_argument("--jpeg-sampling", default="4:2:0", choices=JPEG_SAMPLINGS,
                   help="its chroma subsampling (default 4:2:0, most encoders' default)")
    p.add_argument("--yuv", default="", choices=("",) + YUV_FORMATS,
                   help="the camera delivers YUYV (4:2:2) or I420 (4:2:0) frames, converted to RGB by OpenCV "
                        "(default: RGB frames)")
    p.add_argument("--lateral-ca-px", type=float, default=0.0, metavar="PX",
                   help="the camera lens's lateral chromatic aberration: the blue image lies PX further out than "
                        "the green one at the frame's corners, the red one as far in (default 0)")
    p.add_argument("--gloss", type=_gloss, default=(0.0, DEFAULT_SHININESS), metavar="KS[,SHININESS]",
                   help="glossy surfaces: the light's own colour reflected with weight KS (a white matte "
                        "surface = 1) times (n.h)**SHININESS, Blinn-Phong (default 0: matte; skin ~0.3-1 "
                        f"with SHININESS 20-40, the default {DEFAULT_SHININESS:g})")


def _gloss(text: str) -> tuple[float, float]:
    # --gloss KS[,SHININESS] -> (KS, SHININESS)
    import argparse

    from .sim.presets import DEFAULT_SHININESS

    try:
        v = [float(t) for t in text.split(",")]
        if len(v) in (1, 2) and v[0] >= 0 and (len(v) == 1 or v[1] > 0):
            return (v[0], v[1] if len(v) == 2 else DEFAULT_SHININESS)
    except ValueError:
        pass
    raise argparse.ArgumentTypeError(f"expected KS or KS,SHININESS (KS >= 0, SHININESS > 0), got {text!r}")


def capture_fields(args) -> dict:
    """The :class:`gbscan.sim.Conditions` fields of :func:`add_capture_arguments`' options."""
    out = {"jpeg_quality": int(args.jpeg), "jpeg_sampling": args.jpeg_sampling, "yuv": getattr(args, "yuv", ""),
           "lateral_ca_px": float(getattr(args, "lateral_ca_px", 0.0))}
    if hasattr(args, "gloss"):
        out["specular"], out["shininess"] = (float(v) for v in args.gloss)
    return out


def capture_label(args) -> str:
    """", JPEG q85 4:2:0" (", YUYV", ", gloss 1 (shininess 30)") for the options of
    :func:`add_capture_arguments`, "" for lossless RGB frames of matte surfaces."""
    yuv = f", {args.yuv.upper()}" if getattr(args, "yuv", "") else ""
    ca = f", lateral CA {args.lateral_ca_px:g} px" if getattr(args, "lateral_ca_px", 0.0) else ""
    ks, shininess = getattr(args, "gloss", (0.0, 0.0))
    gloss = f", gloss {ks:g} (shininess {shininess:g})" if ks else ""
    return (f", JPEG q{args.jpeg} {args.jpeg_sampling}" if args.jpeg else "") + yuv + ca + gloss


#: the colour of ``--ambient`` room light in the camera's red, green and blue (warm: tungsten or
#: warm-white LED light, which the camera's red sees most and its blue least)
AMBIENT_TINT_RGB = (1.0, 0.8, 0.6)


def add_ambient_argument(p) -> None:
    """``--ambient LEVEL`` of the simulators and the study scripts: room light on the scene, in the
    camera's red (green, blue: 0.8, 0.6 of it, ``AMBIENT_TINT_RGB``) as a fraction of what the
    projector's full green puts on a white surface facing it at 650 mm; default: the preset's
    (typical 0.05 grey, hard 0.25 / 0.2 / 0.15)."""
    p.add_argument("--ambient", type=float, default=None, metavar="LEVEL",
                   help="room light on the scene as a fraction of the projector's light on a surface facing it "
                        "(0-2; warm light: 1 / 0.8 / 0.6 of LEVEL in the camera's red / green / blue); default: "
                        "the preset's (typical 0.05)")


def ambient_fields(args) -> dict:
    """The :class:`gbscan.sim.Conditions` field of ``--ambient`` ({} when not given); GBError for a
    level outside 0-2."""
    from .errors import GBError

    a = getattr(args, "ambient", None)
    if a is None:
        return {}
    if not 0.0 <= a <= 2.0:
        raise GBError(f"--ambient must be 0-2 (a fraction of the projector's light), got {a}")
    return {"ambient_rgb": tuple(round(a * t, 6) for t in AMBIENT_TINT_RGB)}


def ambient_label(args) -> str:
    """", ambient L" when ``--ambient`` is given, else ""."""
    a = getattr(args, "ambient", None)
    return "" if a is None else f", ambient {a:g}"


def run_cli(prog: str, description: str, package: str, stages: list[str], argv=None) -> int:
    parser = _Parser(prog=prog, description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    from gbscan import __version__

    parser.add_argument("--version", action="version", version=f"{prog} {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    modules = {}
    argv = sys.argv[1:] if argv is None else list(argv)
    wanted = next((a for a in argv if not a.startswith("-")), None)
    for name in stages:
        # Import every stage for the command list only when help is asked for; otherwise just the chosen one.
        if wanted is not None and wanted != name and wanted in stages:
            sub.add_parser(name, help="")
            continue
        mod = importlib.import_module(f"{package}.commands.{name.replace('-', '_')}")
        modules[name] = mod
        p = sub.add_parser(name, help=mod.HELP, description=(mod.__doc__ or mod.HELP),
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        mod.add_arguments(p)
    args = parser.parse_args(argv)
    if not args.command:
        parser.print_help()
        return 2
    from gbscan.heap import keep_freed_memory

    keep_freed_memory()   # frames reuse the memory the last one freed (no fresh page faults)
    return guarded(f"{prog} {args.command}", lambda: int(modules[args.command].run(args) or 0),
                   "; outputs not finished were not written")


def guarded(label: str, fn, interrupted_note: str = "") -> int:
    """Run ``fn()`` (returning the exit status) the way every command and rig script ends: a
    GBError, OSError or MemoryError in one line ``label: error: ...`` (status 1), Ctrl-C in
    ``label: interrupted`` + ``interrupted_note`` (130), anything else in one line saying it is a
    bug (3; ``GB_DEBUG=1`` shows the traceback instead)."""
    try:
        return fn()
    except (GBError, OSError, MemoryError) as e:
        print(f"{label}: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{label}: interrupted{interrupted_note}", file=sys.stderr)
        return 130
    except Exception as e:  # an unexpected failure is a bug: say so in one line unless debugging
        if os.environ.get("GB_DEBUG"):
            raise
        print(f"{label}: internal error: {type(e).__name__}: {e} "
              f"(please report it; rerun with GB_DEBUG=1 for a traceback)", file=sys.stderr)
        return 3


def available_stages(package: str, stages: list[str]) -> list[str]:
    """The stages whose command module exists (lets the CLI grow one stage at a time)."""
    import importlib.util

    return [s for s in stages if importlib.util.find_spec(f"{package}.commands.{s.replace('-', '_')}") is not None]


class _SkipNumbaBlasProbe:
    """A finder on ``sys.meta_path`` that fails one import: ``scipy.linalg`` asked for while numba's
    ``numba.np.arraymath`` runs its module body (before it sets ``_HAVE_BLAS``).  Every other
    import, and ``scipy.linalg`` at any other moment, goes to the usual finders."""

    @staticmethod
    def find_spec(name, path=None, target=None):
        if name != "scipy.linalg":
            return None
        m = sys.modules.get("numba.np.arraymath")
        if m is None or hasattr(m, "_HAVE_BLAS"):
            return None
        raise ModuleNotFoundError("numba's BLAS probe skipped (gbscan.cli_common.skip_numba_blas_probe)",
                                  name=name)


def skip_numba_blas_probe() -> None:
    """Let numba start without importing SciPy's linear algebra (console scripts only).

    When numba first loads a kernel it imports ``numba.np.arraymath``, whose module body probes
    for a BLAS by importing ``scipy.linalg.cython_blas``.  That imports all of ``scipy.linalg``
    and, through its ``array_api_compat``, every numpy submodule (``numpy.f2py`` among them):
    0.2-0.3 s of a ``gbscan scan`` command on this project's hosts, for a BLAS that no gbscan
    kernel calls (none uses ``np.dot``, ``np.vdot``, ``np.inner``, ``@`` or ``np.linalg``;
    ``tests/test_cli_core.py`` checks their source).  This puts :class:`_SkipNumbaBlasProbe`
    first on ``sys.meta_path``, so the probe's import fails fast and numba answers "no BLAS":
    its 1-D ``np.dot`` then uses its own loop, and its 2-D ``np.dot`` and ``np.linalg`` check
    for the BLAS again when they are compiled.  ``scipy.linalg`` imported at any other moment
    (before numba starts, or after: ``gbcal``'s optimiser, the Poisson mesher's ``scipy.sparse``)
    loads as usual.  Only the console scripts call it: a library user's process keeps numba's
    defaults."""
    if not any(isinstance(f, _SkipNumbaBlasProbe) for f in sys.meta_path):
        sys.meta_path.insert(0, _SkipNumbaBlasProbe())


def exit_now(main) -> None:
    """Console-script entry: run ``main()`` and exit as soon as its output is flushed and the
    ``atexit`` handlers have run, skipping the interpreter's teardown of the loaded native
    libraries (numba/LLVM, OpenCV: 0.6-0.8 s of every command measured here).  Every file the
    commands write is complete and renamed into place before ``main`` returns (``gbscan.io``), so
    nothing is lost.  Tests call ``main`` itself, which returns normally."""
    import atexit
    import os

    skip_numba_blas_probe()
    try:
        rc = main()
    except SystemExit as e:  # argparse --help / usage errors
        rc = e.code
    if rc is None:
        rc = 0
    elif not isinstance(rc, int):
        print(rc, file=sys.stderr)
        rc = 1
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:  # a closed pipe: nothing more to say
            pass
    os._exit(rc)
