"""The ``gbcal`` command: one subcommand per calibration stage (see gbcal/commands/)."""
from __future__ import annotations

import sys

from gbscan.cli_common import available_stages, run_cli

DESCRIPTION = """\
Calibrate a green-blue stripe rig: camera intrinsics, projector light planes, bundle refinement.

Workflow:
  1. gbcal patterns OUTDIR                    the projector frames one calibration pose needs
  2. capture a session: python scripts/guided_calibration.py (or --simulate), or
     gbcal simulate-session OUTDIR for a simulated one
  3. gbcal calibrate SESSION -o calib.yaml    the whole rig, refined together
  4. gbcal report calib.yaml -o DIR           residual plots, coverage maps, worst captures
  5. gbcal diff A.yaml B.yaml                 how far two calibrations disagree (mm)
  6. gbcal verify NEW_SESSION --calib calib.yaml   does it still hold: scan the board, measure it
  gbcal camera IMAGE... --board 9x6 --square-mm 25 -o camera.yaml   camera alone
"""

STAGES = ["patterns", "simulate-session", "camera", "calibrate", "report", "diff", "verify"]


def main(argv=None) -> int:
    return run_cli("gbcal", DESCRIPTION, "gbcal", available_stages("gbcal", STAGES), argv)


def entry() -> None:
    """The console script: :func:`main`, then a fast exit (:func:`gbscan.cli_common.exit_now`)."""
    from gbscan.cli_common import exit_now

    exit_now(main)


if __name__ == "__main__":
    entry()
