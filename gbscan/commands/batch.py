"""Scan every frame of a video or a folder of images: one range image per frame.

INPUT is a folder of images (frames in natural file-name order, numbered from 0; other files are
ignored) or a video file (any codec OpenCV's FFmpeg reads; frame numbers from 0).

Outputs in OUTDIR (created if missing), each written atomically:
  frame_NNNNNN.xyz.npy    float32 (H, W, 3) mm, camera frame, NaN where no point (always)
  frame_NNNNNN.ply        the cloud (--ply), the same organised PLY as 'gbscan scan'
  frame_NNNNNN.mesh.ply   grid mesh (--mesh)
  manifest.csv            per frame: frame, source, status (ok/failed/skipped), reason, points,
                          coverage, time_ms, cpu_ms, outputs, temporal_px -- rewritten
                          atomically as frames complete (skipped = not reached when interrupted)
  job.yaml                input, calibration (sha256) and options the outputs belong to

Resumable: rerun the same command after an interruption or a crash; frames listed ok whose
outputs exist are skipped, failed and missing ones are (re)done.  A bad frame (unreadable, wrong
size, no stripes) is recorded with its reason and the batch goes on; so does a frame that kills
its worker process.  Exit status 0 when every selected frame is ok, 1 when some failed.

Parallel: --workers N local processes (default: all cores).  --scheduler tcp://HOST:8786 runs on
an existing Dask cluster instead (pip install 'gbscan[batch]'); its workers must see INPUT and
OUTDIR at the same paths (a video is decoded here and frames are sent to the workers).

--temporal (experimental) processes consecutive frames in order (in chunks, each started by
re-decoding the frame before it) and lets each frame borrow, from its predecessor's stripes and
projector columns, the offset of regions the cyan markers cannot index alone
(gbscan.batch.temporal_offsets).  A region borrows only when most of it overlaps the previous
frame's columns, these agree with one offset within 3/4 of a stripe on 90% of the overlap and not
with the neighbouring offsets (small motion), and any marker seen fits; then only its pixels that
agree pixel by pixel, at least 3 px inside the region, get points (confidence <= 0.5; counted in
temporal_px).  On simulated moving sequences every borrowed pixel was right; it is wrong when the
previous frame was wrong there, or when a region moves by exactly two stripes (~7 camera px at
650 mm) between frames.

--timeout-s S (default 60): a frame still running after S seconds is recorded failed with reason
'timeout' and the batch goes on (a local worker stuck in C code is killed and replaced).
"""
from __future__ import annotations

import sys

HELP = "scan a video or a folder of frames: one range image per frame, resumable, parallel"


def add_arguments(p):
    from .decode import add_decode_arguments
    from .scan import add_clean_arguments

    p.add_argument("input", help="folder of camera frames, or a video file")
    p.add_argument("--calib", required=True, help="calibration file (gbcal calibrate)")
    p.add_argument("-o", "--output", required=True, metavar="OUTDIR", help="output folder")
    p.add_argument("--workers", type=int, help="local worker processes (default: all cores)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="run on a Dask cluster (tcp://HOST:8786)")
    p.add_argument("--ply", action="store_true", help="also write each frame's cloud (.ply)")
    p.add_argument("--mesh", action="store_true", help="also write each frame's grid mesh (.mesh.ply)")
    p.add_argument("--start", type=int, default=0, help="first frame number (default 0)")
    p.add_argument("--stop", type=int, help="stop before this frame number (default: the end)")
    p.add_argument("--every", type=int, default=1, metavar="K", help="every K-th frame (default 1)")
    p.add_argument("--temporal", action="store_true",
                   help="use the previous frame to index regions the markers cannot (see above)")
    p.add_argument("--restart", action="store_true",
                   help="ignore results already in OUTDIR (needed to reuse it with other settings)")
    p.add_argument("--timeout-s", type=float, default=60.0, metavar="S",
                   help="a frame still running after S seconds is abandoned and recorded failed with reason "
                        "'timeout' (default 60, plus 300 for each worker's first frame, which compiles the "
                        "kernels; 0 = no limit)")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    add_decode_arguments(p)
    add_clean_arguments(p, no_clean=False)


def params_from_pairs(cls, pairs: list[str], option: str):
    """A dataclass ``cls`` from ``NAME=VALUE`` strings, or None (see :mod:`gbscan.commands.decode`)."""
    from .decode import params_from_pairs as from_pairs

    return from_pairs(cls, pairs, option)


def rig_summary(manifest, input_path=None, kind: str = "folder") -> str:
    """One line from the manifest's ``rig`` column (the rig check of a frame in every
    ``gbscan.batch.RIG_EVERY``): how many frames were checked and how many of them raised each
    warning, and the command that says more about the first such frame (``input_path``: the
    batch's input, a folder of frames or a video (``kind``)); "" when no frame was checked."""
    from collections import Counter
    from pathlib import Path

    from ..batch import read_manifest

    checked = [r for r in read_manifest(manifest).values() if r.get("rig")]
    if not checked:
        return ""
    count = Counter(k for r in checked for k in r["rig"].split(";") if k != "ok")
    if not count:
        return f"rig check on {len(checked)} frame(s): no findings"
    first = next(r for r in checked if r["rig"] != "ok")
    if input_path is None:
        how = f"gbscan check on frame {first['frame']}"
    elif kind == "folder":
        how = f"gbscan check {Path(input_path) / first['source']}"
    else:
        how = f"gbscan check {input_path} --frame {first['frame']}"
    return (f"rig check on {len(checked)} frame(s): " + ", ".join(f"{k} {n}" for k, n in count.most_common())
            + f" (what to change: {how})")


def run(args) -> int:
    from ..batch import ScannerProcessor, run_batch
    from ..errors import GBError
    from ..frames import open_frames
    from .decode import decode_params_from_args
    from .scan import clean_params_from_args

    if args.workers is not None and args.workers < 1:
        raise GBError(f"--workers must be >= 1, got {args.workers}")
    if args.every < 1:
        raise GBError(f"--every must be >= 1, got {args.every}")
    if not args.timeout_s >= 0:
        raise GBError(f"--timeout-s must be >= 0 seconds (0 = no limit), got {args.timeout_s}")
    proc = ScannerProcessor(args.calib,
                            decode_params=decode_params_from_args(args),
                            clean_params=clean_params_from_args(args, none_if_default=True),
                            temporal=args.temporal)
    with open_frames(args.input, args.bayer) as source:
        what = (f"{len(source)} frames in folder {source.path}" if source.kind == "folder"
                else f"video {source.path.name}: {len(source)} frames of {source.width}x{source.height}")
        where = f"Dask cluster {args.scheduler}" if args.scheduler else f"{args.workers or 'all'} local workers"
        print(f"{what}; {where}", file=sys.stderr)
        if source.ignored:
            shown = ", ".join(source.ignored[:5]) + (" ..." if len(source.ignored) > 5 else "")
            print(f"ignored {len(source.ignored)} non-image file(s): {shown}", file=sys.stderr)
        warning = source.input_warning()
        if warning:
            print(warning, file=sys.stderr, flush=True)
        s = run_batch(source, proc, args.output, start=args.start, stop=args.stop, every=args.every,
                      workers=args.workers, scheduler=args.scheduler, ply=args.ply, mesh=args.mesh,
                      temporal=args.temporal, restart=args.restart, progress=not args.quiet,
                      timeout_s=args.timeout_s or None)
    print(f"{s.selected} frames selected: {s.already_done} already done, {s.ok} done now, {s.failed} failed "
          f"({s.frames_per_s:.1f} frames/s over {s.elapsed_s:.1f} s)")
    for frame, why in s.failures[:10]:
        print(f"  frame {frame}: {why}")
    if len(s.failures) > 10:
        print(f"  ... {len(s.failures) - 10} more in {s.manifest}")
    line = rig_summary(s.manifest, source.path, source.kind)
    if line:
        print(line)
    print(f"manifest: {s.manifest}")
    return 1 if s.failed else 0
