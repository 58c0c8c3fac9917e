#!/usr/bin/env python3
"""Live scanning at a calibrated rig: watch the depth map at video rate, save scans with SPACE.

The projector shows the single-shot pattern of the calibration full-screen on its own display;
every camera frame is decoded, triangulated and cleaned (``gbscan.scan.Scanner``, as
``gbscan scan``), and a live window shows the frame beside its colour-coded depth map (near red,
far blue), with the points, the time per scan and the frame rate, and, every 15 frames, what
the rig check (``gbscan check``) finds wrong with the frame: dim, saturated, noisy, ambient light,
a weak colour, an unfocused projector, stripes too narrow for the camera.

    python scripts/live_scan.py --calib calib.yaml --camera 0 --screen-x 1920 -o scans/
    python scripts/live_scan.py --calib calib.yaml --simulate --frames 20 -o scans/   # simulated rig, headless

Keys (live window focused): SPACE save the current scan   q or ESC quit

Each saved scan is a folder ``scans/scan_NNN`` with ``frame.png`` (lossless: scan it again with
``gbscan scan`` and other options), ``cloud.ply`` (with the grey texture), ``xyz.npy`` and
``mesh.ply``; a folder that exists is complete.

Before you start: the projector's display extended (not mirrored) at its native resolution,
--screen-x/--screen-y its top-left in the desktop; the camera's exposure, gain and white balance
locked (auto exposure chases the stripes); the camera delivering uncompressed RGB frames if it
can (--camera-fourcc; a YUYV, MJPG or 4:2:0 stream halves the stripes' colour resolution: the
script warns, and the decoder finds it in the frames and withholds their absolute index, so
nothing is scanned; see docs/method.md, "Camera frames").
--depth-range MIN MAX (mm) is the working volume, as for ``gbscan scan``.

--simulate films a simulated face turning before a wall with the paper rig (it needs a
calibration of that rig: ``gbcal calibrate calib_data/session``); --display none (the default
with --simulate) runs without windows and ends after --frames frames.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without install

from gbscan.errors import GBError  # noqa: E402


def build_parser() -> argparse.ArgumentParser:
    from gbscan.cli_common import size_arg

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--calib", required=True, help="calibration file (gbcal calibrate)")
    p.add_argument("-o", "--output", default="live_scans", help="folder for saved scans (default live_scans)")
    p.add_argument("--camera", default="0", help="camera device index or stream URL (default 0)")
    p.add_argument("--camera-size", type=size_arg, metavar="WxH",
                   help="camera resolution to ask for (default: the calibration's)")
    p.add_argument("--camera-fourcc", metavar="FOURCC",
                   help="camera pixel format to ask for, e.g. RGB3 or BGR3 (a YUYV or MJPG webcam format "
                        "subsamples chroma: the script warns); default: the driver's")
    p.add_argument("--screen-x", type=int, default=1920,
                   help="x offset (px) of the projector's display in the desktop (default 1920)")
    p.add_argument("--screen-y", type=int, default=0, help="y offset of the projector's display (default 0)")
    p.add_argument("--display", choices=("auto", "tk", "opencv", "none"), default=None,
                   help="window backend (default auto: Tk, else OpenCV highgui; --simulate: none)")
    p.add_argument("--depth-range", type=float, nargs=2, metavar=("MIN_MM", "MAX_MM"),
                   help="working volume in mm (cleaning and the decoder's indexing), as gbscan scan")
    p.add_argument("--frames", type=int, help="stop after this many frames (default: until q / ESC)")
    p.add_argument("--simulate", action="store_true", help="a simulated camera filming a turning face")
    p.add_argument("--save-every", type=int, default=0, metavar="N",
                   help="--display none: save every N-th frame's scan as if SPACE were pressed (default 0: none)")
    return p


class _ScriptedKeys:
    """A display without windows whose key is SPACE every ``every``-th frame (``--save-every``)."""

    def __init__(self, inner, every: int):
        self.inner, self.every, self.n = inner, int(every), 0

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def poll_key(self) -> str:
        self.n += 1
        return " " if self.every and self.n % self.every == 0 else self.inner.poll_key()


def main(argv=None) -> int:
    from gbcal.display import run_script

    args = build_parser().parse_args(argv)
    return run_script("live_scan", lambda devices: _run(args, devices))


def _run(args, devices) -> int:
    log = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    from gbcal.display import VideoCamera, choose_display
    from gbscan.calibfile import load_calibration
    from gbscan.clean import CleanParams
    from gbscan.io import make_dir
    from gbscan.live import SimulatedCamera, run_live
    from gbscan.pattern import render_pattern
    from gbscan.scan import Scanner

    if args.frames is not None and args.frames < 1:
        raise GBError(f"--frames must be >= 1, got {args.frames}")
    if args.save_every < 0:
        raise GBError(f"--save-every must be >= 0, got {args.save_every}")
    clean = CleanParams()
    if args.depth_range is not None:
        near, far = args.depth_range
        if not 0 < near < far:
            raise GBError(f"--depth-range: expected 0 < MIN_MM < MAX_MM, got {near:g} {far:g}")
        clean = CleanParams(min_depth_mm=near, max_depth_mm=far)
    calib = load_calibration(args.calib)
    scanner = Scanner(calib, clean_params=clean)
    spec = scanner.pattern
    kind = args.display or ("none" if args.simulate else "auto")
    if kind == "none" and not args.simulate:
        raise GBError("--display none works only with --simulate (at a rig the keys come from the live window)")
    if kind == "none" and args.frames is None:
        raise GBError("--display none needs --frames N (there is no window to press q in)")
    if args.simulate:
        from gbscan import sim

        rig = sim.paper_rig()
        if (spec.width, spec.height) != (rig.projector.width, rig.projector.height) or \
                calib.camera.size != rig.camera.size:
            raise GBError(f"--simulate films with the paper rig (camera {rig.camera.width}x{rig.camera.height}, "
                          f"projector {rig.projector.width}x{rig.projector.height}); {args.calib} is for "
                          f"{calib.camera.width}x{calib.camera.height} / {spec.width}x{spec.height}")
    outdir = make_dir(args.output, "output folder")
    display = devices.open(choose_display(kind, (spec.width, spec.height), (args.screen_x, args.screen_y), log=log,
                                          title="gbscan live scan"))
    if kind == "none":
        display = _ScriptedKeys(display, args.save_every)
    if args.simulate:
        camera = devices.open(SimulatedCamera(render_pattern(spec), rig))
        log("simulated camera: a face turning before a wall (paper rig, typical preset)")
    else:
        camera = devices.open(VideoCamera(args.camera, args.camera_size or calib.camera.size, args.camera_fourcc))
        for problem in display.problems() + [camera.input_warning()]:
            if problem:
                log(problem if problem.startswith("warning:") else f"warning: {problem}")
    dr = args.depth_range or (None, None)
    res = run_live(display, camera, scanner, outdir, max_frames=args.frames, near_mm=dr[0], far_mm=dr[1], log=log)
    print(f"{res.frames} frames scanned ({res.fps:.1f} frames/s), {len(res.saved)} scans saved"
          + (f" in {outdir}" if res.saved else ""))
    for p in res.saved:
        print(f"wrote {p}")
    return 0

if __name__ == "__main__":
    sys.exit(main())
