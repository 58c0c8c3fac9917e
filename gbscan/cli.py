"""The ``gbscan`` command: one subcommand per pipeline stage (see gbscan/commands/)."""
from __future__ import annotations

import sys

from .cli_common import run_cli

DESCRIPTION = """\
Single-shot green-blue structured-light scanning.

Workflow:
  1. gbscan pattern -o pattern.png            the frame the projector shows while scanning
  2. gbcal calibrate SESSION -o calib.yaml    calibrate the rig once (see 'gbcal --help')
     gbscan check IMAGE                       what a frame says about the rig (exposure, light, focus)
  3. gbscan scan IMAGE --calib calib.yaml -o cloud.ply --mesh mesh.ply --preview DIR
     (gbscan decode IMAGE -o stripes.npz --preview DIR shows the decoder's stages alone)
  4. gbscan mesh cloud.ply -o mesh.ply        mesh a saved cloud (grid or poisson)
  5. gbscan batch FRAMES_OR_VIDEO --calib calib.yaml -o OUTDIR   many frames
  gbscan simulate ... renders scenes with the simulated rig (no hardware needed).
"""

STAGES = ["pattern", "simulate", "check", "decode", "scan", "mesh", "batch"]


def main(argv=None) -> int:
    from .cli_common import available_stages

    return run_cli("gbscan", DESCRIPTION, "gbscan", available_stages("gbscan", STAGES), argv)


def entry() -> None:
    """The console script: :func:`main`, then a fast exit (:func:`gbscan.cli_common.exit_now`)."""
    from gbscan.cli_common import exit_now

    exit_now(main)


if __name__ == "__main__":
    entry()
