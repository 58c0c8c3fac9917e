"""Calibrate the whole rig from a capture session: camera, board poses and projector, refined together.

Per capture the board is found in the `white` frame (captures without a usable board are dropped
with the reason), the Gray-code frames give sub-pixel stripe boundaries on the board, the camera
is calibrated from the corners, one plane is fitted per stripe boundary, a pinhole projector is
fitted to the planes, and one robust bundle adjustment refines camera, board poses and projector
against corner and stripe residuals together.  Writes CALIB (YAML) and CALIB's
<stem>.residuals.npz beside it (for 'gbcal report'); nothing is written if the run fails.

The depth scale of everything the scanner measures is the camera's fx, which the rig's small board
pins only so well (the summary prints the depth uncertainty that leaves). With --camera CAMERA.yaml
(from 'gbcal camera' on captures of a bigger board close up, in room light) the bundle holds the
camera to that file within its standard deviations, and says if the session disagrees with it.
"""
from __future__ import annotations

HELP = "calibrate camera + projector light planes from a capture session"


def add_corners_argument(p):
    """``--corners`` (the corner refiner, :data:`gbcal.board.CORNER_REFINERS`), shared by the commands
    that detect boards."""
    from ..board import CORNER_REFINERS, DEFAULT_CORNER_REFINER

    p.add_argument("--corners", choices=CORNER_REFINERS, default=DEFAULT_CORNER_REFINER,
                   help="corner refinement: symmetric (default; cornerSubPix, then a point-symmetry fit over "
                        "the corner's window: about half cornerSubPix's error on rendered boards) or "
                        "cornersubpix (OpenCV's alone, as before)")


def add_arguments(p):
    p.add_argument("session", help="capture session folder (session.yaml + pose_NNN/)")
    p.add_argument("-o", "--output", required=True, help="calibration file to write (YAML)")
    p.add_argument("--preview", metavar="DIR", help="also write per-capture pictures (board, boundary samples) here")
    p.add_argument("--model", default=None, choices=["k1k2p1p2k3", "k1k2p1p2", "k1k2", "k1", "none"],
                   help="camera distortion model (default k1k2p1p2: k3 fixed at 0; with --camera, that file's)")
    p.add_argument("--camera", metavar="CAMERA.yaml",
                   help="a camera calibrated on its own ('gbcal camera', e.g. a big board close up in room light): "
                        "the bundle holds the camera to it within its standard deviations, which pins fx and so "
                        "the depth scale better than the rig's board alone")
    add_corners_argument(p)
    p.add_argument("--loss", default="soft_l1", choices=["soft_l1", "huber", "cauchy", "linear"],
                   help="robust loss of the bundle adjustment (default soft_l1)")
    p.add_argument("--f-scale-px", type=float, default=0.5,
                   help="residual (camera px) where the robust loss starts to down-weight (default 0.5)")
    p.add_argument("--stripe-weight", type=float, default=1.0,
                   help="weight of a stripe-boundary sample relative to a corner coordinate (default 1)")
    p.add_argument("--max-samples", type=int, default=20000,
                   help="stripe-boundary samples used per capture, drawn at random (default 20000; fewer is "
                        "faster, more pins the principal point and the planes down better)")


def run(args) -> int:
    from pathlib import Path

    from gbscan.errors import GBError

    from ..calibrate import calibrate_session, save_run, summary_lines

    if args.f_scale_px <= 0 or args.stripe_weight <= 0 or args.max_samples < 10:
        raise GBError("--f-scale-px and --stripe-weight must be positive and --max-samples at least 10")
    out = Path(args.output)
    if not out.parent.is_dir():
        raise GBError(f"cannot write {out}: folder {out.parent} does not exist (create it first)")
    prior = None
    if args.camera:
        from ..calibrate import load_camera_prior

        prior, _ = load_camera_prior(args.camera, args.model)
    run_ = calibrate_session(args.session, model=args.model or "k1k2p1p2", loss=args.loss, f_scale_px=args.f_scale_px,
                             stripe_weight=args.stripe_weight, max_samples_per_capture=args.max_samples,
                             corner_refiner=args.corners, camera_prior=prior,
                             camera_prior_name=f"camera file {args.camera}")
    if args.preview:
        from ..report import write_capture_previews

        written = write_capture_previews(args.session, run_, args.preview)
        print(f"wrote {len(written)} preview pictures to {args.preview}")
    path, npz = save_run(out, run_)
    for line in summary_lines(run_):
        print(line)
    t = run_.timings
    print(f"time: captures {t['captures_s']:.1f} s, camera {t['camera_s']:.1f} s, planes {t['planes_s']:.1f} s, "
          f"bundle {t['bundle_s']:.1f} s, total {t['total_s']:.1f} s")
    print(f"wrote {path} ({run_.calibration.n_planes} light planes) and {npz.name}")
    return 0
