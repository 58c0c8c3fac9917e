"""Render one camera image of a simulated scene with the simulated rig (paper geometry).

SCENE is one of: plane, sphere, head, step, multi, board, face (the real face mesh from
../shared/data/fran_face, when present).  The projector shows the single-shot pattern unless
--frame gives another projector frame (PNG of the projector's size).  --truth writes the
ground truth (point, lit, depth_edge, proj_xy, object_id, image) as .npz.

--move-mm DX,DY,DZ and --turn-deg DEG make the object move during the exposure (camera frame,
mm: x right, y down, z forward; the turn is about the vertical axis through the middle of the
object): the frame averages --exposure-steps instants of it, the truth is mid-exposure, and the
truth file also holds ``motion_edge`` (the pixels that see another surface meanwhile).  A wall
behind the object (an unbounded plane) stays put.
"""
from __future__ import annotations

HELP = "render a simulated scene (plane, sphere, head, step, multi, board, face) to a PNG"

SCENES = ["plane", "sphere", "head", "step", "multi", "board", "face"]


def add_arguments(p):
    from gbscan.cli_common import add_rig_arguments, add_ambient_argument, add_bayer_argument, add_capture_arguments

    p.add_argument("scene", choices=SCENES, metavar="SCENE", help="one of " + ", ".join(SCENES))
    p.add_argument("-o", "--output", required=True, help="output PNG (camera image, RGB)")
    p.add_argument("--preset", default="typical", choices=["clean", "typical", "hard"],
                   help="imaging conditions (default typical)")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    add_ambient_argument(p)
    add_bayer_argument(p)
    p.add_argument("--raw", action="store_true",
                   help="with --bayer: write the raw mosaic (one channel), as a machine-vision camera delivers "
                        "it (scan it with 'gbscan scan --bayer PATTERN')")
    add_capture_arguments(p)
    p.add_argument("--distance-mm", type=float, default=650.0, help="scene distance in mm (default 650)")
    add_rig_arguments(p)
    p.add_argument("--truth", help="also write the ground truth to this .npz")
    p.add_argument("--frame", help="projector frame PNG (default: the single-shot pattern)")
    p.add_argument("--stripe-px", type=int, default=8, help="stripe width of the default pattern (default 8)")
    p.add_argument("--no-markers", action="store_true", help="default pattern without cyan markers")
    p.add_argument("--move-mm", metavar="DX,DY,DZ",
                   help="the object moves this far during the exposure (mm, camera frame), e.g. 2,0,0")
    p.add_argument("--turn-deg", type=float, default=0.0,
                   help="the object turns this much during the exposure, about its vertical axis (a head "
                        "turning), degrees")
    p.add_argument("--exposure-steps", type=int, default=9,
                   help="instants of the exposure rendered when the object moves (odd, default 9)")


def make_scene(name: str, distance_mm: float = 650.0):
    """The named demo scene (see the module docstring)."""
    import numpy as np

    from gbscan.sim import scenes

    if name == "plane":
        return scenes.plane(distance_mm, tilt_deg=(10, 25), albedo=scenes.colour_patches(40.0, low=0.3))
    if name == "sphere":
        return scenes.sphere((0.0, 0.0, distance_mm), 0.17 * distance_mm, albedo=0.7, wall_mm=distance_mm + 150)
    if name == "head":
        return scenes.head(distance_mm, wall_mm=distance_mm + 250)
    if name == "step":
        return scenes.step(distance_mm, 40.0)
    if name == "multi":
        return scenes.multi_object(distance_mm)
    if name == "board":
        return scenes.board(9, 7, 20.0, scenes._rot_xy(-15, 20), np.array([-80.0, -60.0, distance_mm]))
    if name == "face":
        return scenes.fran_face(distance_mm=distance_mm)
    raise ValueError(name)


def run(args) -> int:
    import dataclasses
    import math
    import time
    from pathlib import Path

    from gbscan import sim
    from gbscan.errors import GBError
    from gbscan.cli_common import ambient_fields, ambient_label, rig_label, capture_fields, capture_label, rig_from_args
    from gbscan.io import read_image_rgb, write_png
    from gbscan.pattern import PatternSpec, render_pattern

    if not args.distance_mm > 0:
        raise GBError(f"--distance-mm must be positive, got {args.distance_mm}")
    if args.raw and not args.bayer:
        raise GBError("--raw writes a Bayer camera's mosaic: give --bayer PATTERN too")
    if args.truth and not args.truth.endswith(".npz"):
        raise GBError(f"--truth {args.truth}: the ground truth is written as .npz; give a name ending in .npz")
    move = None
    if args.move_mm is not None:
        try:
            move = [float(x) for x in args.move_mm.split(",")]
        except ValueError:
            move = []
        if len(move) != 3 or not all(map(math.isfinite, move)):
            raise GBError(f"--move-mm {args.move_mm}: expected three numbers DX,DY,DZ in mm, e.g. 2,0,0")
    if not math.isfinite(args.turn_deg) or abs(args.turn_deg) > 90:
        raise GBError(f"--turn-deg {args.turn_deg}: expected degrees within -90 .. 90")
    moving = move is not None or args.turn_deg != 0
    if moving and (args.exposure_steps < 3 or args.exposure_steps % 2 == 0):
        raise GBError(f"--exposure-steps {args.exposure_steps}: expected an odd number >= 3 (the middle "
                      f"instant is the ground truth)")
    rig = rig_from_args(args)
    pw, ph = rig.projector.width, rig.projector.height
    if args.frame:
        frame = read_image_rgb(args.frame, size=(pw, ph), what="projector frame")
    else:
        frame = render_pattern(PatternSpec(pw, ph, args.stripe_px, not args.no_markers))
    t0 = time.time()
    scene = make_scene(args.scene, args.distance_mm)
    cond = dataclasses.replace(sim.preset(args.preset), bayer=args.bayer, bayer_raw=args.raw, **capture_fields(args),
                               **ambient_fields(args))
    if moving:
        poses = sim.scenes.exposure_poses(scene, move or (0.0, 0.0, 0.0), args.turn_deg, args.exposure_steps)
        r = sim.render_moving(rig, poses, frame, cond, seed=args.seed)
    else:
        r = sim.render(rig, scene, frame, cond, seed=args.seed)
    out = write_png(args.output, r.image)
    camera = (f", Bayer {args.bayer}{' raw mosaic' if args.raw else ''}" if args.bayer else "") + capture_label(args) \
        + ambient_label(args)
    if moving:
        camera += (f", moving {','.join(f'{x:g}' for x in move or (0, 0, 0))} mm"
                   f"{f' turning {args.turn_deg:g} deg' if args.turn_deg else ''} during the exposure "
                   f"({args.exposure_steps} instants)")
    msg = (f"wrote {out} ({args.scene}, preset {args.preset}{camera}{rig_label(args)}, seed {args.seed}, "
           f"{time.time() - t0:.1f} s)")
    if args.truth:
        r.save_truth(args.truth)
        msg += f"; ground truth {Path(args.truth)}"
    print(msg)
    return 0
