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

--temporal processes consecutive frames in order (in chunks, each started by re-decoding the
frame before it) and gives each frame its predecessor's absolute stripe map, from which regions
the cyan markers cannot index alone take their offset (gbscan.batch.temporal_offsets; right while
the stripes move less than one stripe between frames, or half a marker gap when the region shows
a marker; faster motion gives a whole-stripe-pair error on that region).  temporal_px counts
those pixels.  They become points once the decoder reports the projector column of unindexed
regions (StripeMap.column_relative); until then the points are each frame's own.
"""
from __future__ import annotations

import sys

HELP = "scan a video or a folder of frames: one range image per frame, resumable, parallel"


def add_arguments(p):
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
    p.add_argument("--quiet", action="store_true", help="no progress line")
    g = p.add_argument_group("scan parameters (defaults as 'gbscan scan')")
    g.add_argument("--decode-param", action="append", default=[], metavar="NAME=VALUE",
                   help="a gbscan.decode.DecodeParams field, e.g. blur_sigma_along_px=3 (repeatable)")
    g.add_argument("--clean-param", action="append", default=[], metavar="NAME=VALUE",
                   help="a gbscan.clean.CleanParams field, e.g. min_confidence=0.3 (repeatable)")


def params_from_pairs(cls, pairs: list[str], option: str):
    """A dataclass ``cls`` from ``NAME=VALUE`` strings (defaults elsewhere), or None if none given.

    Values are converted like the field's default (bool, int, float, str); ``none`` gives None.
    """
    import dataclasses

    from ..errors import GBError

    if not pairs:
        return None
    fields = {f.name for f in dataclasses.fields(cls)}
    defaults = cls()
    kw = {}
    for item in pairs:
        name, sep, value = item.partition("=")
        name, value = name.strip().replace("-", "_"), value.strip()
        current = getattr(defaults, name, None)
        if not sep or name not in fields or dataclasses.is_dataclass(current):
            raise GBError(f"{option} {item!r}: expected NAME=VALUE with NAME one of "
                          f"{', '.join(n for n in fields if not dataclasses.is_dataclass(getattr(defaults, n)))}")
        try:
            if value.lower() in ("none", "null"):
                kw[name] = None
            elif isinstance(current, bool):
                if value.lower() not in ("1", "0", "true", "false", "yes", "no", "on", "off"):
                    raise ValueError
                kw[name] = value.lower() in ("1", "true", "yes", "on")
            elif isinstance(current, int):
                kw[name] = int(value)
            elif isinstance(current, float):
                kw[name] = float(value)
            elif current is None:  # optional field: a number if it looks like one
                try:
                    kw[name] = int(value)
                except ValueError:
                    kw[name] = float(value)
            else:
                kw[name] = value
        except ValueError:
            raise GBError(f"{option} {item!r}: {value!r} is not a valid value for {name} "
                          f"(default {current!r})") from None
    try:
        return cls(**kw)
    except (TypeError, ValueError) as e:
        raise GBError(f"{option}: {e}") from None


def run(args) -> int:
    from ..batch import ScannerProcessor, run_batch
    from ..errors import GBError
    from ..frames import open_frames
    from ..clean import CleanParams
    from ..decode import DecodeParams

    if args.workers is not None and args.workers < 1:
        raise GBError(f"--workers must be >= 1, got {args.workers}")
    if args.every < 1:
        raise GBError(f"--every must be >= 1, got {args.every}")
    proc = ScannerProcessor(args.calib,
                            decode_params=params_from_pairs(DecodeParams, args.decode_param, "--decode-param"),
                            clean_params=params_from_pairs(CleanParams, args.clean_param, "--clean-param"),
                            temporal=args.temporal)
    with open_frames(args.input) as source:
        what = (f"{len(source)} frames in folder {source.path}" if source.kind == "folder"
                else f"video {source.path.name}: {len(source)} frames of {source.width}x{source.height}")
        where = f"Dask cluster {args.scheduler}" if args.scheduler else f"{args.workers or 'all'} local workers"
        print(f"{what}; {where}", file=sys.stderr)
        if source.ignored:
            shown = ", ".join(source.ignored[:5]) + (" ..." if len(source.ignored) > 5 else "")
            print(f"ignored {len(source.ignored)} non-image file(s): {shown}", file=sys.stderr)
        s = run_batch(source, proc, args.output, start=args.start, stop=args.stop, every=args.every,
                      workers=args.workers, scheduler=args.scheduler, ply=args.ply, mesh=args.mesh,
                      temporal=args.temporal, restart=args.restart, progress=not args.quiet)
    print(f"{s.selected} frames selected: {s.already_done} already done, {s.ok} done now, {s.failed} failed "
          f"({s.frames_per_s:.1f} frames/s over {s.elapsed_s:.1f} s)")
    for frame, why in s.failures[:10]:
        print(f"  frame {frame}: {why}")
    if len(s.failures) > 10:
        print(f"  ... {len(s.failures) - 10} more in {s.manifest}")
    print(f"manifest: {s.manifest}")
    return 1 if s.failed else 0
