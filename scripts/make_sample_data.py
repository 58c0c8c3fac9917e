#!/usr/bin/env python
"""Regenerate the bundled sample data in calib_data/ (deterministic: fixed seeds).

    python scripts/make_sample_data.py [--out calib_data] [--poses 6]

Writes
  calib_data/session/        a simulated calibration session (gbcal simulate-session layout,
                             with truth.yaml): paper rig, 9x7 board of 20 mm squares, typical preset
  calib_data/scan_head.png   the simulated head under the single-shot pattern (typical preset)
  calib_data/scan_multi.png  several objects at different depths (typical preset)
  calib_data/scan_*_truth.npz ground truth of the two scans, only with --truth (~5 MB each)
  calib_data/README.md       what these are and how they were made
"""
from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SESSION_SEED = 2024
HEAD_SEED = 1
MULTI_SEED = 2

README = """\
# calib_data — bundled sample data (simulated, with ground truth)

Made by `python scripts/make_sample_data.py` (deterministic; rerun it to regenerate). Every
image comes from the project's simulator (`gbscan.sim`) with the paper's rig geometry
(`gbscan.rig.paper_rig()`: 640x480 camera with lens distortion, 1024x768 projector 200 mm to the
right, toed in to cross the camera axis at 650 mm) and the `typical` imaging preset (noise
~1-2 DN, crosstalk ~0.1, ambient ~5 %, projector defocus ~1 px, camera blur ~0.5 px).

- `session/` — a calibration session in the capture-session format of `gbscan/io.py`:
  `session.yaml` and `pose_NNN/<frame>.png` for the {n_frames} frames of `gbcal patterns`
  (white, black, the single-shot stripes, Gray code of the stripe index and inverses), {n_poses}
  poses of a 9x7-inner-corner board of 20 mm squares (tilts up to ~40 degrees, 550-800 mm),
  seed {session_seed}. `session/truth.yaml` holds the true camera, projector, camera-projector
  pose, pattern, conditions and board poses (read it with `gbcal.simsession.load_truth`).
  Calibrate it with `gbcal calibrate calib_data/session -o calib.yaml`.
- `scan_head.png` — a face-like head (`gbscan.sim.scenes.head(650)`, wall at 900 mm) under the
  single-shot pattern with cyan markers (`gbscan pattern`), seed {head_seed}.
- `scan_multi.png` — separate objects at different depths in front of a wall
  (`gbscan.sim.scenes.multi_object()`), seed {multi_seed}.
- The scans' ground truth (`point` mm, `lit`, `proj_xy`, `depth_edge`, `object_id`) is not
  bundled (5 MB each): `python scripts/make_sample_data.py --truth` writes `scan_*_truth.npz`.

Sizes: session {session_mb:.1f} MB, whole folder {total_mb:.1f} MB.
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(ROOT / "calib_data"), help="output folder (default calib_data/)")
    ap.add_argument("--poses", type=int, default=6, help="calibration poses (default 6: ~30 MB)")
    ap.add_argument("--truth", action="store_true", help="also write scan_*_truth.npz (ground truth, ~5 MB each)")
    args = ap.parse_args(argv)

    from gbcal.patterns import frame_names
    from gbcal.simsession import write_session
    from gbscan import sim
    from gbscan.io import write_png, write_text_atomic
    from gbscan.pattern import PatternSpec, render_pattern

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rig = sim.paper_rig()
    spec = PatternSpec()
    t0 = time.time()

    session = out / "session"
    if session.exists():
        shutil.rmtree(session)  # no stale poses from an earlier, longer run
    print(f"session: {args.poses} poses ...", file=sys.stderr)
    write_session(session, rig, spec, board=(9, 7, 20.0), n_poses=args.poses, preset="typical",
                  seed=SESSION_SEED, progress=True, compact=True)

    pattern = render_pattern(spec)
    for name, scene, seed in (("head", sim.scenes.head(650.0, wall_mm=900.0), HEAD_SEED),
                              ("multi", sim.scenes.multi_object(), MULTI_SEED)):
        print(f"scan_{name}.png ...", file=sys.stderr)
        r = sim.render(rig, scene, pattern, "typical", seed=seed)
        write_png(out / f"scan_{name}.png", r.image)
        if args.truth:
            r.save_truth(out / f"scan_{name}_truth.npz")

    def mb(p: Path) -> float:
        return sum(f.stat().st_size for f in p.rglob("*") if f.is_file()) / 1e6

    session_mb = mb(session)
    total_mb = mb(out) + 1e-3 * 3  # + this README (~3 kB)
    write_text_atomic(out / "README.md", README.format(
        n_frames=len(frame_names(spec)), n_poses=args.poses, session_seed=SESSION_SEED, head_seed=HEAD_SEED,
        multi_seed=MULTI_SEED, session_mb=session_mb, total_mb=total_mb))
    print(f"wrote {out}: session {session_mb:.1f} MB, total {total_mb:.1f} MB in {time.time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
