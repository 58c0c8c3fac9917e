#!/usr/bin/env python3
"""Guided capture of a rig-calibration session at a real rig, then the calibration.

The projector shows each calibration frame full-screen on its own display, the camera grabs it,
and a live window shows whether the board is seen, which image regions and board tilts are
still missing, and how many captures are left.  The windows use Tk (Python's standard library;
works with the project's headless OpenCV); OpenCV's own windows are used only if Tk cannot open
one and the installed OpenCV has a GUI (--display chooses).

    python scripts/guided_calibration.py SESSION --camera 0 --screen-x 1920 --board 9x7 --square-mm 20
    python scripts/guided_calibration.py SESSION --simulate                # the same flow, simulated, headless
    python scripts/guided_calibration.py SESSION --simulate --display tk   # simulated, with the real windows

Before you start
  * Extend the desktop onto the projector (not mirror) at the projector's native resolution
    (--projector, default 1024x768); --screen-x/--screen-y give the projector's top-left in the
    desktop (e.g. 1920 0 when it is right of a 1920x1080 monitor).  The script warns if the
    projector window did not land there at that size (frames must be pixel-exact).
  * Lock the camera's exposure, gain, white balance and focus (auto exposure makes the black
    frame as bright as the white one; the capture is then rejected).  --camera-size WxH fixes
    the resolution.  Dim the room.
  * A printed checkerboard of COLSxROWS inner corners (--board) with squares of --square-mm,
    flat and rigid, ideally on a stand: every pose takes 18 frames (0.2-0.35 s each with the
    default --settle-ms and --drop-frames, so 4-6 s per pose), and the board must not move meanwhile.

What you do
  1. Hold the board in the projector's light, fully inside the camera image.  The live window
     shows the camera image with the board's corners drawn when it is found; "no board: ..."
     says why not (cut by the border, blurred, low contrast, ...).
  2. Press SPACE (with the live window focused) and keep the board still.  The projector steps through
     white, black, the stripe frame and the Gray-code frames, then white again.
  3. The capture is checked: board found and sharp (edge width), board still (corners of the
     first and last white frames within --max-motion-px), white frame not saturated on the
     board, black frame really darker than the white one (else the camera lagged the projector:
     raise --settle-ms / --drop-frames), enough projector light on the white squares.  An
     accepted capture turns its image regions green and its tilt box green; a rejected one is
     shown in red with the reason (also in SESSION/capture_log.yaml and on stderr).
  4. Move the board and repeat, following the yellow hint: tilt it 20-40 degrees left, right,
     up and down (the tilt boxes), bring it to every region of the image (orange outlines are
     regions no capture covered yet), vary the distance.
  5. After --poses captures (or q) the session is written and calibrated.

Keys: SPACE capture   u undo the last accepted capture   q finish now   ESC abort (nothing kept)

Synchronisation: after each projector frame the window is drawn and the window system flushed,
the script waits --settle-ms (projector input lag plus one camera exposure; the windows stay
responsive) and drops --drop-frames camera frames (the driver's buffer) before it keeps one.

The session folder must be new.  Captures are staged in a hidden folder beside it and the
session appears under its name only when complete (with session.yaml); ESC leaves nothing; an
error or Ctrl-C after some captures leaves SESSION.incomplete/ with INCOMPLETE.txt (not a session).

--simulate drives the very same flow with a simulated camera that renders the board at a scripted
sequence of poses under whatever frame the simulated projector shows; --sim-faults spoils chosen
capture attempts (move, blur, bright, dim, lag) to show the rejections.  The simulated rig is the
paper's, with a projector of --projector's pixels behind its lens (e.g. --projector 1920x1080
--sim-scale 2: stripes about as wide in the 1280x960 camera as the paper rig's).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without install

from gbscan.errors import GBError  # noqa: E402


SPARE_POSES = 3


def scripted_poses(rig, board, n: int, seed: int = 1):
    """``n`` varied board poses (R_cam_board, t_cam_board) that keep the board inside the camera
    image and the projector frame (those of the simulated sessions, :mod:`gbcal.simsession`)."""
    from gbcal.simsession import board_poses

    return board_poses(rig, (board.cols, board.rows, board.square_mm), n, seed)


def build_parser() -> argparse.ArgumentParser:
    from gbscan.cli_common import size_arg

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("session", help="session folder to write (must be new or empty)")
    g = p.add_argument_group("rig")
    g.add_argument("--camera", default="0", help="camera device index or stream URL (default 0)")
    g.add_argument("--camera-size", type=size_arg, metavar="WxH", help="camera resolution to ask for (checked)")
    g.add_argument("--screen-x", type=int, default=1920,
                   help="x offset (px) of the projector's display in the desktop (default 1920: right of a 1080p screen)")
    g.add_argument("--screen-y", type=int, default=0, help="y offset of the projector's display (default 0)")
    g.add_argument("--display", choices=("auto", "tk", "opencv", "none"), default=None,
                   help="window backend (default auto: Tk, else OpenCV highgui; --simulate: none)")
    g.add_argument("--projector", type=size_arg, default=(1024, 768), metavar="WxH",
                   help="projector resolution (native; default 1024x768)")
    g.add_argument("--settle-ms", type=float, default=150.0,
                   help="wait after each projector frame before grabbing (ms, default 150)")
    g.add_argument("--drop-frames", "--settle-frames", dest="drop_frames", type=int, default=4,
                   help="camera frames dropped after each projector frame (the driver's buffer; default 4)")
    g = p.add_argument_group("board and pattern")
    g.add_argument("--board", default="9x7", help="inner corners COLSxROWS (default 9x7)")
    g.add_argument("--square-mm", type=float, default=20.0,
                   help="square size in mm (default 20: the whole board must fit in the projector's light)")
    g.add_argument("--stripe-px", type=int, default=8, help="stripe width in projector px (default 8)")
    g.add_argument("--no-markers", action="store_true", help="the paper's pure green/blue stripe frame")
    g = p.add_argument_group("captures")
    g.add_argument("--poses", type=int, default=12, help="captures to take (default 12; q finishes early)")
    g.add_argument("--max-motion-px", type=float, default=0.5,
                   help="largest corner shift between the first and last white frame of a pose (px, default 0.5)")
    g.add_argument("--max-blur-px", type=float, default=None,
                   help="widest board edge accepted (10-90%% rise, px; default 7, for a 640x480-class camera; "
                        "--simulate: 7 x --sim-scale)")
    g.add_argument("--min-modulation", type=float, default=30.0,
                   help="least white-minus-black grey level on the white squares (default 30)")
    g = p.add_argument_group("calibration")
    g.add_argument("-o", "--calib", help="calibration file to write (default SESSION/calib.yaml)")
    g.add_argument("--no-calibrate", action="store_true", help="only capture the session")
    g.add_argument("--camera-calib", metavar="CAMERA.yaml",
                   help="hold the camera to one calibrated on its own ('gbcal camera' on a bigger board close up): "
                        "a better depth scale (what 'gbcal calibrate --camera' does)")
    g = p.add_argument_group("simulation")
    g.add_argument("--simulate", action="store_true", help="simulated rig and operator (for tests and demos)")
    g.add_argument("--sim-scale", type=float, default=0.5,
                   help="--simulate: camera resolution factor of the paper rig (default 0.5 = 320x240, fast)")
    g.add_argument("--sim-preset", default="clean", help="--simulate: imaging preset (default clean)")
    g.add_argument("--sim-faults", default="",
                   help="--simulate: spoil capture attempts, e.g. 2:move,4:blur (move, blur, bright, dim, lag)")
    return p


def main(argv=None) -> int:
    from gbcal.display import run_script

    args = build_parser().parse_args(argv)
    return run_script("guided_calibration", lambda devices: _run(args, devices))


def _run(args, devices) -> int:
    log = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    from gbcal.board import parse_board
    from gbcal.display import VideoCamera, choose_display
    from gbcal.guided import QualityLimits, check_new_session_folder, run_capture
    from gbscan.pattern import PatternSpec

    board = parse_board(args.board, args.square_mm)
    spec = PatternSpec(args.projector[0], args.projector[1], args.stripe_px, not args.no_markers)
    prior = None
    if args.camera_calib:  # read before any capture: a bad file should not cost a session
        from gbcal.calibrate import load_camera_prior

        prior, _ = load_camera_prior(args.camera_calib)
    if args.poses < 1:
        raise GBError("--poses must be at least 1")
    max_blur_px = args.max_blur_px or (7.0 * args.sim_scale if args.simulate else 7.0)
    limits = QualityLimits(max_sharpness_px=max_blur_px, max_motion_px=args.max_motion_px,
                           min_modulation_dn=args.min_modulation)
    check_new_session_folder(args.session)
    kind = args.display or ("none" if args.simulate else "auto")
    if kind == "none" and not args.simulate:
        raise GBError("--display none works only with --simulate (at a rig the keys come from the live window)")
    extra = {}
    if args.simulate:
        from gbcal.guidedsim import SimulatedRig, parse_faults, script_for
        from gbscan.rig import Rig, paper_rig

        # the paper rig, with a projector of --projector's pixels behind its lens
        true = paper_rig(projector_px=(spec.width, spec.height))
        rig = Rig(true.camera.scaled(args.sim_scale), true.projector, true.R_cam_proj, true.t_cam_proj)
        steps = script_for(args.poses, parse_faults(args.sim_faults, args.poses))
        # spare poses: the simulated operator tries another position after an unexpected rejection
        poses = scripted_poses(rig, board, args.poses) + scripted_poses(rig, board, SPARE_POSES, seed=2)
        world = SimulatedRig(rig, board, poses, steps, preset=args.sim_preset)
        display = devices.open(world.display(choose_display(kind, args.projector, (args.screen_x, args.screen_y),
                                                            pattern_size=board.pattern_size, log=log)))
        camera = devices.open(world.camera)
        extra["simulated"] = True
        log(f"simulated rig: camera {rig.camera.width}x{rig.camera.height}, {args.poses} scripted poses, "
            f"display {display.name}")
    else:
        display = devices.open(choose_display(kind, args.projector, (args.screen_x, args.screen_y),
                                              pattern_size=board.pattern_size, log=log))
        log(f"display: {display.name}; projector window {spec.width}x{spec.height} at "
            f"+{args.screen_x}+{args.screen_y}")
        camera = devices.open(VideoCamera(args.camera, args.camera_size))
    display.show_projector(np.zeros((spec.height, spec.width, 3), np.uint8))  # map the window, then check it
    for problem in display.problems():
        log(f"warning: {problem}")
    out = run_capture(args.session, display, camera, board, spec, n_poses=args.poses,
                      settle_ms=args.settle_ms, drop_frames=args.drop_frames, limits=limits, log=log, extra=extra)
    devices.close_all()   # the windows go before the calibration's minutes
    if out.status == "aborted":
        raise GBError("aborted (ESC): nothing written")
    if out.status == "empty":
        raise GBError("no pose captured; nothing written")
    log(f"session written: {args.session} ({len(out.accepted)} poses, {out.rejected} captures rejected)")
    if args.no_calibrate:
        log(f"check a calibration on these poses: gbcal verify {args.session} --calib CALIB.yaml")
        return 0
    from gbcal.calibrate import calibrate_session, save_run, summary_lines

    run = calibrate_session(args.session, log=log, camera_prior=prior,
                            camera_prior_name=f"camera file {args.camera_calib}")
    path, npz = save_run(args.calib or Path(args.session) / "calib.yaml", run)
    for line in summary_lines(run):
        print(line)
    print(f"wrote {path} and {npz.name}")
    print(f"later, to see whether it still holds: capture a few poses (--poses 3 --no-calibrate) and run "
          f"gbcal verify NEW_SESSION --calib {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
