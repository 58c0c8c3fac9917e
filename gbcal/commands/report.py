"""Pictures and a summary of a calibration: residual vector field, histograms, per-capture RMS,
corner and stripe coverage, light-plane residuals, and summary.txt naming the worst captures.

Per-point pictures need the residual samples <stem>.residuals.npz that 'gbcal calibrate' writes
beside the calibration; without it only per_capture.png and summary.txt are made.
"""
from __future__ import annotations

HELP = "residual plots, coverage maps and worst captures of a calibration (PNG + summary.txt)"


def add_arguments(p):
    p.add_argument("calibration", help="calibration file written by 'gbcal calibrate'")
    p.add_argument("-o", "--output", required=True, metavar="DIR", help="report folder (created if missing)")


def run(args) -> int:
    from ..report import write_report

    paths = write_report(args.calibration, args.output)
    for p in paths:
        print(f"wrote {p}")
    summary = [p for p in paths if p.name == "summary.txt"]
    if summary:
        print(summary[0].read_text(encoding="utf-8").rstrip())
    return 0
