"""Render a simulated calibration session: a checkerboard in varied poses under every frame.

Writes OUTDIR/session.yaml, OUTDIR/pose_NNN/<frame>.png (the frames of 'gbcal patterns') and
OUTDIR/truth.yaml (the true camera, projector, pose between them, pattern, imaging conditions
and board poses) -- a test bed for 'gbcal calibrate' with known answers.
"""
from __future__ import annotations

HELP = "render a simulated calibration session with known ground truth"


def _board_arg(text: str) -> tuple[int, int]:
    import argparse

    try:
        c, r = (int(v) for v in text.lower().split("x"))
        if c < 3 or r < 3:
            raise ValueError
        return c, r
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected COLSxROWS inner corners (each >= 3) such as 9x7, got '{text}'") from None


def add_arguments(p):
    from gbscan.cli_common import add_rig_arguments, add_bayer_argument

    p.add_argument("outdir", help="session folder to write (created if missing)")
    p.add_argument("--poses", type=int, default=12, help="number of board poses (default 12)")
    p.add_argument("--preset", default="typical", choices=["clean", "typical", "hard"],
                   help="imaging conditions (default typical)")
    p.add_argument("--seed", type=int, default=0, help="random seed for poses and noise (default 0)")
    add_bayer_argument(p)
    p.add_argument("--board", type=_board_arg, default=(9, 7), metavar="COLSxROWS",
                   help="inner corners of the board (default 9x7)")
    p.add_argument("--square-mm", type=float, default=20.0,
                   help="square size in mm (default 20: the board then fits the paper rig's projector frame)")
    p.add_argument("--stripe-px", type=int, default=8, help="stripe width in projector pixels (default 8)")
    add_rig_arguments(p)
    p.add_argument("--no-markers", action="store_true", help="the paper's pure green/blue stripe frame")
    p.add_argument("--quiet", action="store_true", help="no progress lines")


def run(args) -> int:
    import dataclasses
    import time

    from gbscan import sim

    from gbscan.errors import GBError
    from gbscan.pattern import PatternSpec
    from gbscan.cli_common import rig_label, rig_from_args

    from ..simsession import write_session

    if args.poses < 1:
        raise GBError(f"--poses must be at least 1, got {args.poses}")
    if not args.square_mm > 0:
        raise GBError(f"--square-mm must be positive, got {args.square_mm}")
    rig = rig_from_args(args)
    spec = PatternSpec(rig.projector.width, rig.projector.height, args.stripe_px, not args.no_markers)
    t0 = time.time()
    cond = dataclasses.replace(sim.preset(args.preset), bayer=args.bayer)
    out = write_session(args.outdir, rig, spec, (args.board[0], args.board[1], args.square_mm), args.poses,
                        cond, args.seed, progress=not args.quiet)
    camera = (f", Bayer {args.bayer}" if args.bayer else "") + rig_label(args)
    print(f"wrote simulated session {out}: {args.poses} poses of a {args.board[0]}x{args.board[1]} board "
          f"({args.square_mm:g} mm), preset {args.preset}{camera}, seed {args.seed}, in {time.time() - t0:.0f} s; "
          f"ground truth in {out / 'truth.yaml'}")
    return 0
