"""Robustness sweep of the decoder's absolute index (issue 3): every reported pixel on its true stripe.

Renders a set of simulated scenes of the paper rig (multi-object at several depths and seeds,
the moving multi-object sequence of the batch tests, sphere and head at several positions, a
step, tilted planes; "typical" and "hard" presets; a Bayer colour camera; the real face mesh of
``../shared/data/fran_face`` when it is there), decodes each and compares every reported
pixel with the simulator's truth (``r.proj_xy``):

* ``wrong``: reported, off any depth edge, column more than half a stripe from the truth (the
  absolute stripe index is wrong, not just the sub-pixel position);
* ``wrong_edge``: the same on depth-edge pixels (they mix two surfaces; counted apart);
* ``col_rms``, ``>1px``: the sub-pixel accuracy, column error RMS (projector px) of the reported
  non-edge pixels on their right stripe, and how many of them are more than 1 px off;
* the wrong pixels grouped by region: size, offset error (stripes), how the region was indexed
  (markers / linked) and its index statistics (markers seen, evidence, mismatch, runner-up);
* after the total, the unindexed share of the lit non-edge pixels by why (too few markers,
  ambiguous offset, ...; "ok": rows of an indexed region its row checks dropped) and the scene
  that loses most to each: where coverage goes that the markers could still win.

``--out DIR`` writes ``wrong_<scene>.png`` for each scene with a pixel on a wrong stripe: the
frame, its reported pixels grey, the wrong ones red off depth edges and orange on them, the lit
pixels left unreported dark blue, and a close-up of the largest cluster of wrong pixels (off
depth edges when there are any).

    python scripts/sweep_decode.py [--cache DIR] [--only SUBSTR] [--quick] [--decode NAME=VALUE]
    python scripts/sweep_decode.py --cache DIR --blur-grid 1,1.25,1.5,1.75,2,2.25,2.5,2.75,3
    python scripts/sweep_decode.py --cache DIR --depth-range 400 1200   # with a working volume
    python scripts/sweep_decode.py --cache DIR --jpeg 90 --jpeg-sampling 4:4:4   # frames stored as JPEG
    python scripts/sweep_decode.py --cache DIR --yuv yuyv --decode subsampled_chroma=decode
                                   # a YUYV camera, decoded anyway (by default such frames are withheld)
    python scripts/sweep_decode.py --cache DIR --lateral-ca-px 0.5   # a lens with lateral chromatic aberration
    python scripts/sweep_decode.py --cache DIR --gloss 1,30          # glossy surfaces (Blinn-Phong highlights)
    python scripts/sweep_decode.py --cache DIR --set room-light   # warm and cool room light (44 frames)
    python scripts/sweep_decode.py --cache DIR --set clean        # the clean preset (16 frames)
    python scripts/sweep_decode.py --cache DIR --set baselines    # other baselines (33 frames)
    python scripts/sweep_decode.py --cache DIR --set mirrored     # the projector on the camera's left (21 frames)
    python scripts/sweep_decode.py --cache DIR --set panels       # the multi-object scene's panel plain (45 frames)
    python scripts/sweep_decode.py --cache DIR --set layouts      # other depths, walls, albedos (32 frames)
    python scripts/sweep_decode.py --cache DIR --set layouts --out DIR   # and pictures of the wrong pixels
    python scripts/sweep_decode.py --cache DIR --set holdout      # frames kept out of the rules (32; one rule since)
    python scripts/sweep_decode.py --cache DIR --set holdout2     # 32 frames more (one rule since)
    python scripts/sweep_decode.py --cache DIR --set holdout3     # 32 frames more (two rules since)
    python scripts/sweep_decode.py --cache DIR --set holdout4     # 32 frames more (one rule since)
    python scripts/sweep_decode.py --cache DIR --set holdout5     # 32 frames more (one rule since)
    python scripts/sweep_decode.py --cache DIR --set holdout6     # 32 frames more (one rule since)
    python scripts/sweep_decode.py --cache DIR --set holdout7     # 32 frames more (thirty-second session)
    python scripts/sweep_decode.py --cache DIR --set holdout8     # 32 frames more (thirty-third session; one rule since)
    python scripts/sweep_decode.py --cache DIR --set holdout9     # 32 frames more (thirty-third session)
    python scripts/sweep_decode.py --cache DIR --set holdout10    # 32 frames more (thirty-fourth session)
    python scripts/sweep_decode.py --cache DIR --set holdout11    # 32 frames more (thirty-fourth session)
    python scripts/sweep_decode.py --cache DIR --set holdout12    # 32 frames more (thirty-fifth session)
    python scripts/sweep_decode.py --cache DIR --set holdout13    # 32 frames more (thirty-fifth session)
    python scripts/sweep_decode.py --cache DIR --set faces        # heads and real faces at 575-805 mm, turned (32)

Prints one line per scene (reported % of lit non-edge pixels, wrong pixels), the regions with
wrong non-edge pixels under it (all wrong regions with ``--edges``), and a total.  Progress lines go to stderr.  Renders are cached in ``--cache`` (npz).
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # measure this checkout, whatever the environment's install points at
    sys.path.insert(0, str(ROOT))


#: the frame sets of ``--set``: the sweep's 48 scenes, the same objects under room light, the clean
#: preset, other baselines, the rig mirrored, the multi-object scene's panel plain, other layouts of
#: it, thirteen sets of frames of it kept out of the rules' making (the first two each spent by a
#: rule of the thirtieth session, the third to fifth by the thirty-first session's piece rules, the
#: sixth by the thirty-second session's strong-stripe threshold, the eighth by the thirty-third
#: session's ``DecodeParams.piece_linked``, the tenth by the thirty-fourth's jump cut, the eleventh
#: and twelfth looked into in the thirty-fifth with no rule kept; the thirteenth made then, the
#: freshest) and a set of faces kept out too
SETS = ("main", "room-light", "clean", "baselines", "mirrored", "panels", "layouts", "holdout", "holdout2",
        "holdout3", "holdout4", "holdout5", "holdout6", "holdout7", "holdout8", "holdout9", "holdout10", "holdout11", "holdout12", "holdout13", "faces")


def scene_list(quick: bool = False, which: str = "main") -> list[tuple[str, str, int, int, object]]:
    """``(name, preset, seed, supersample, factory)`` of every scene of the set ``which``
    (:data:`SETS`).  A preset ``P+RGGB`` renders ``P`` through a Bayer mosaic; ``P@warmL`` /
    ``P@coolL`` adds room light of level ``L`` (warm: red / green / blue 1 / 0.8 / 0.6 of it, as
    ``--ambient``; cool: 0.6 / 0.8 / 1)."""
    from gbscan import sim

    S = sim.scenes
    if which == "room-light":
        return _room_light(S, quick)
    if which == "clean":
        return _clean_set(S, quick)
    if which == "baselines":
        return _baseline_set(S, quick)
    if which == "mirrored":
        return _mirrored_set(S, quick)
    if which == "panels":
        return _panel_set(S, quick)
    if which == "layouts":
        return _layout_set(S, quick)
    if which in HELD_OUT:
        return _multi_grid(S, which, *HELD_OUT[which], quick)
    if which == "faces":
        return _face_set(S, quick)
    if which != "main":
        raise ValueError(f"unknown frame set {which!r}, expected one of {SETS}")
    out = []
    # the batch tests' moving sequence (supersample 1, seed = frame)
    for i in range(0, 10):
        out.append((f"multi_move_i{i}", "typical", i, 1, lambda i=i: S.multi_object(650.0 + 5.0 * i)))
    for seed in range(4):
        out.append((f"multi_650_s{seed}", "typical", seed, 3, lambda: S.multi_object(650.0)))
    for d in (600.0, 700.0, 760.0):
        out.append((f"multi_{d:.0f}_s1", "typical", 1, 3, lambda d=d: S.multi_object(d)))
    out.append(("multi_650_wall800_s0", "typical", 0, 3, lambda: S.multi_object(650.0, wall_mm=800.0)))
    for seed in range(2):
        out.append((f"multi_650_hard_s{seed}", "hard", seed, 3, lambda: S.multi_object(650.0)))
    for seed, c in enumerate([(0.0, 0.0, 650.0), (-60.0, 20.0, 620.0), (50.0, -30.0, 700.0)]):
        out.append((f"sphere_{seed}_s{seed}", "typical", seed, 3,
                    lambda c=c: S.sphere(c, 100.0, wall_mm=900.0)))
    out.append(("sphere_hard_s1", "hard", 1, 3, lambda: S.sphere((0.0, 0.0, 650.0), 100.0)))
    for seed, (d, yaw, pitch) in enumerate([(650.0, 0.0, 0.0), (620.0, 20.0, 0.0), (700.0, -15.0, 10.0)]):
        out.append((f"head_{seed}_s{seed}", "typical", seed, 3,
                    lambda d=d, yaw=yaw, pitch=pitch: S.head(d, yaw, pitch)))
    out.append(("head_hard_s1", "hard", 1, 3, lambda: S.head(650.0)))
    for seed, (d, h, x) in enumerate([(650.0, 40.0, 0.0), (700.0, 80.0, -40.0)]):
        out.append((f"step_{seed}_s{seed}", "typical", seed, 3, lambda d=d, h=h, x=x: S.step(d, h, edge_x_mm=x)))
    out.append(("step_hard_s1", "hard", 1, 3, lambda: S.step(650.0, 40.0)))
    for seed, tilt in enumerate([(0.0, 30.0), (25.0, -20.0), (-35.0, 10.0)]):
        out.append((f"plane_tilt_{seed}_s{seed}", "typical", seed, 3, lambda tilt=tilt: S.plane(650.0, tilt)))
    out.append(("plane_hard_s2", "hard", 2, 3, lambda: S.plane(650.0, (10.0, 20.0))))
    # a Bayer colour camera (RGGB mosaic, noise per photosite, OpenCV's edge-aware demosaicing):
    # most real colour cameras; the demosaicing mixes neighbouring pixels' colours at every stripe
    for seed in range(3):
        out.append((f"multi_650_bayer_s{seed}", "typical+RGGB", seed, 3, lambda: S.multi_object(650.0)))
    for i in (2, 6):
        out.append((f"multi_move_bayer_i{i}", "typical+RGGB", i, 1, lambda i=i: S.multi_object(650.0 + 5.0 * i)))
    out.append(("sphere_bayer_s0", "typical+RGGB", 0, 3, lambda: S.sphere((0.0, 0.0, 650.0), 100.0, wall_mm=900.0)))
    out.append(("head_bayer_s0", "typical+RGGB", 0, 3, lambda: S.head(650.0)))
    out.append(("plane_tilt_bayer_s0", "typical+RGGB", 0, 3, lambda: S.plane(650.0, (0.0, 30.0))))
    out.append(("step_bayer_s0", "typical+RGGB", 0, 3, lambda: S.step(650.0, 40.0)))
    # the real face mesh (../shared/data/fran_face, not part of the project): when it is there
    if S.FRAN_PATH.is_file():
        for seed, yaw in ((0, 0.0), (1, 20.0), (2, -15.0)):
            out.append((f"fran_face_y{yaw:+.0f}_s{seed}", "typical", seed, 3,
                        lambda yaw=yaw: S.fran_face(distance_mm=650.0, yaw_deg=yaw)))
        out.append(("fran_face_bayer_s0", "typical+RGGB", 0, 3, lambda: S.fran_face(distance_mm=650.0)))
    if quick:
        out = out[::3]
    return out


def _room_light(S, quick: bool) -> list:
    # docs/method.md "Ambient light": warm light at 4 levels on four objects, cool light at 2 on three (44 frames)
    objects = {"sphere": lambda: S.sphere((0.0, 0.0, 650.0), 100.0, wall_mm=900.0), "head": lambda: S.head(650.0),
               "multi": lambda: S.multi_object(650.0), "step": lambda: S.step(650.0, 40.0)}
    out = []
    for tint, levels, names in (("warm", (0.05, 0.15, 0.25, 0.4), ("sphere", "head", "multi", "step")),
                                ("cool", (0.15, 0.25), ("sphere", "head", "multi"))):
        for level in levels:
            for name in names:
                for seed in (0, 1):
                    out.append((f"{name}_{tint}{level:g}_s{seed}", f"typical@{tint}{level:g}", seed, 3, objects[name]))
    return out[::3] if quick else out


def _clean_set(S, quick: bool) -> list:
    # the clean preset (no noise, a sharper projector): the multi-object scene at three distances,
    # spheres, heads, steps, the real face (16 frames with it)
    out = []
    for d in (600.0, 650.0, 700.0):
        for seed in (0, 1):
            out.append((f"multi_{d:.0f}_clean_s{seed}", "clean", seed, 3, lambda d=d: S.multi_object(d)))
    for seed, c in enumerate([(0.0, 0.0, 650.0), (-60.0, 20.0, 620.0), (50.0, -30.0, 700.0)]):
        out.append((f"sphere_{seed}_clean_s{seed}", "clean", seed, 3, lambda c=c: S.sphere(c, 100.0, wall_mm=900.0)))
    for seed, (d, yaw, pitch) in enumerate([(650.0, 0.0, 0.0), (620.0, 20.0, 0.0), (700.0, -15.0, 10.0)]):
        out.append((f"head_{seed}_clean_s{seed}", "clean", seed, 3,
                    lambda d=d, yaw=yaw, pitch=pitch: S.head(d, yaw, pitch)))
    for seed, (d, h, x) in enumerate([(650.0, 40.0, 0.0), (700.0, 80.0, -40.0)]):
        out.append((f"step_{seed}_clean_s{seed}", "clean", seed, 3, lambda d=d, h=h, x=x: S.step(d, h, edge_x_mm=x)))
    if S.FRAN_PATH.is_file():
        for seed, yaw in ((0, 0.0), (1, 20.0)):
            out.append((f"fran_face_y{yaw:+.0f}_clean_s{seed}", "clean", seed, 3,
                        lambda yaw=yaw: S.fran_face(distance_mm=650.0, yaw_deg=yaw)))
    return out[::3] if quick else out


#: the baselines of the ``baselines`` set (mm); the paper rig's other dimensions stay
BASELINES_MM = (100, 125, 140, 150, 160, 175, 190, 200, 225, 250, 300)


def _baseline_set(S, quick: bool) -> list:
    # the multi-object scene at 650 mm with the projector at other baselines (seeds 0-2): where two
    # surfaces' stripes line up differs with the baseline (docs/method.md "Baseline 200 mm")
    out = []
    for b in BASELINES_MM:
        for seed in range(3):
            out.append((f"multi_650_b{b}_s{seed}", f"typical/b{b}", seed, 3, lambda: S.multi_object(650.0)))
    return out[::3] if quick else out


#: the ``panels`` set's panel albedos and depths
PANEL_ALBEDOS = (0.3, 0.45, 0.6, 0.7, 0.85)
PANEL_DEPTHS_MM = (650.0, 700.0, 760.0)


def _panel_set(S, quick: bool) -> list:
    # the multi-object scene with its panel of one albedo instead of colour patches, at three
    # depths, seeds 0-2 (45 frames): the panel's stripes meet the wall's at its right silhouette,
    # and where they line up 6 stripes apart the wall's markers 96 / 102 land on the panel's 90 /
    # 96 (docs/method.md "Decoder", UnwrapParams.conflict_extend)
    out = []
    for d in PANEL_DEPTHS_MM:
        for a in PANEL_ALBEDOS:
            for seed in range(3):
                out.append((f"multi_{d:.0f}_panel{a:g}_s{seed}", "typical", seed, 3,
                            lambda d=d, a=a: S.multi_object(d, panel_albedo=a)))
    return out[::3] if quick else out


#: the ``layouts`` set's depths (mm) and walls (times the depth)
LAYOUT_DEPTHS_MM = (620.0, 680.0, 740.0, 800.0)
LAYOUT_WALLS = (800.0 / 650.0, 1000.0 / 650.0)


def _multi_grid(S, prefix: str, depths, walls, albedo: float, seeds: tuple[int, int], plain: float,
                quick: bool) -> list:
    # the multi-object scene at each depth x wall (times the depth) x albedo (the scene's, or
    # ``albedo``) x seed (the first: the panel patched; the second: plain, of albedo ``plain``)
    out = []
    for d in depths:
        for w in walls:
            for a in (None, albedo):
                for seed in seeds:
                    flat = seed == seeds[1]
                    name = f"{prefix}_{d:.0f}_wall{d * w:.0f}{'' if a is None else f'_a{a:g}'}{'_plain' if flat else ''}_s{seed}"
                    out.append((name, "typical", seed, 3,
                                lambda d=d, w=w, a=a, flat=flat: S.multi_object(d, wall_mm=d * w, albedo=a,
                                                                                panel_albedo=plain if flat else None)))
    return out[::3] if quick else out


def _layout_set(S, quick: bool) -> list:
    # the multi-object scene at four depths with its wall nearer and farther than the main set's
    # (1.23 / 1.54 x the depth against 1.38), objects of albedo 0.7 or 0.4, the panel patched
    # (seed 0) or plain (0.6, seed 1): 32 frames of layouts no rule was tuned on until the
    # twenty-ninth session made three from them (docs/method.md "Known limits")
    return _multi_grid(S, "multi", LAYOUT_DEPTHS_MM, LAYOUT_WALLS, 0.4, (0, 1), 0.6, quick)


#: the held-out sets, frames kept out of the rules' making: per set ``_multi_grid``'s depths (mm),
#: walls (times the depth), albedo, seeds (panel patched, plain) and plain panel albedo.  Each
#: set's depths and walls are none of the other sets' (a test checks it).  Run a set to check that a
#: rule found elsewhere holds; a rule made from one of its frames spends it (say so in
#: docs/history.md and make another before the next rule is run on it)
HELD_OUT = {
    # twenty-ninth session; spent in the thirtieth by ``UnwrapParams.tilt_follow_rows``
    "holdout": ((590.0, 710.0, 770.0, 830.0), (1.3, 1.46), 0.55, (2, 3), 0.5),
    # thirtieth session, made before that rule was run on it; spent the same session by
    # ``DecodeParams.sandwich_rows``
    "holdout2": ((565.0, 675.0, 785.0, 855.0), (1.25, 1.52), 0.65, (4, 5), 0.45),
    # thirtieth session, after the sandwich guard; spent in the thirty-first by
    # ``DecodeParams.piece_check_px`` and ``piece_alone``, made from its 875 mm / 1 400 mm islands
    "holdout3": ((635.0, 725.0, 815.0, 875.0), (1.35, 1.6), 0.5, (6, 7), 0.55),
    # thirty-first session, made before ``piece_check_px`` was run on it; spent the same session by
    # ``piece_alone``, made from its pieces
    "holdout4": ((605.0, 745.0, 820.0, 890.0), (1.33, 1.56), 0.6, (8, 9), 0.5),
    # thirty-first session, made before ``piece_alone`` was run on it; spent the same session:
    # pieces joined along rows and columns only, made from its 755 mm band
    "holdout5": ((615.0, 755.0, 845.0, 905.0), (1.4, 1.65), 0.45, (10, 11), 0.6),
    # thirty-first session, made before the pieces were joined by shared edges only
    "holdout6": ((660.0, 735.0, 790.0, 860.0), (1.28, 1.48), 0.5, (12, 13), 0.65),
    # thirty-second session, made before any rule of that session was run on it
    "holdout7": ((645.0, 715.0, 805.0, 880.0), (1.36, 1.62), 0.45, (14, 15), 0.55),
    # thirty-third session, made at its start, before holdout7's wrong pixels were looked into
    "holdout8": ((585.0, 695.0, 765.0, 850.0), (1.32, 1.58), 0.6, (16, 17), 0.5),
    # thirty-third session, made before the rule made from holdout8 was run on it
    "holdout9": ((625.0, 690.0, 780.0, 865.0), (1.34, 1.5), 0.5, (18, 19), 0.6),
    # thirty-fourth session, made at its start, before holdout9's wrong pixels were looked into
    "holdout10": ((580.0, 670.0, 775.0, 840.0), (1.37, 1.44), 0.55, (24, 25), 0.5),
    # thirty-fourth session, made before any rule made from holdout10 was run on it; looked into in
    # the thirty-fifth (its 595 mm strip), the rules made from it not kept
    "holdout11": ((595.0, 685.0, 795.0, 870.0), (1.39, 1.53), 0.45, (26, 27), 0.6),
    # thirty-fifth session, made at its start, before holdout11's wrong pixels were looked into;
    # looked into the same session (its 705 and 750 mm cases), no rule made
    "holdout12": ((610.0, 705.0, 750.0, 885.0), (1.31, 1.57), 0.5, (28, 29), 0.55),
    # thirty-fifth session, made after ``UnwrapParams.link_hang_rows`` 3 (from holdout11; not kept)
    # was run on holdout12 and before holdout12's wrong pixels were looked into
    "holdout13": ((630.0, 720.0, 810.0, 895.0), (1.42, 1.59), 0.6, (30, 31), 0.5),
}


#: the ``faces`` set's synthetic heads: nose tip distance (mm), yaw, pitch (degrees) and a wall
#: behind (times the distance) or none; each with seeds 20 and 21
FACE_HEADS = ((575.0, -30.0, 10.0, None), (595.0, 25.0, -12.0, 1.45), (630.0, -15.0, -8.0, None),
              (665.0, 30.0, 5.0, 1.3), (705.0, 10.0, 12.0, None), (745.0, -25.0, 0.0, 1.55),
              (785.0, 20.0, -10.0, None), (610.0, 0.0, 15.0, 1.4), (725.0, -35.0, -5.0, None),
              (765.0, 35.0, 8.0, 1.35))
#: its real faces (``../shared/data/fran_face``): distance, yaw, wall (times the distance) or none;
#: each with seeds 22 and 23
FACE_FRANS = ((585.0, -25.0, None), (640.0, 30.0, 1.4), (695.0, -10.0, None), (750.0, 15.0, 1.5),
              (805.0, -30.0, None), (680.0, 0.0, 1.35))


def _face_set(S, quick: bool) -> list:
    # held out (thirty-second session, made before that session's rule ran): the synthetic head
    # and the real face at 575-805 mm, turned up to 35 degrees, some before a wall -- the
    # scanner's showcase at poses and distances no rule was tuned on (the other sets hold 620-700
    # mm heads and faces)
    out = []
    for d, yaw, pitch, w in FACE_HEADS:
        for seed in (20, 21):
            name = f"faces_head_{d:.0f}_y{yaw:+.0f}_p{pitch:+.0f}{'' if w is None else f'_wall{d * w:.0f}'}_s{seed}"
            out.append((name, "typical", seed, 3, lambda d=d, yaw=yaw, pitch=pitch, w=w: S.head(
                d, yaw, pitch, wall_mm=None if w is None else d * w)))
    if S.FRAN_PATH.is_file():
        for d, yaw, w in FACE_FRANS:
            for seed in (22, 23):
                name = f"faces_fran_{d:.0f}_y{yaw:+.0f}{'' if w is None else f'_wall{d * w:.0f}'}_s{seed}"
                out.append((name, "typical", seed, 3, lambda d=d, yaw=yaw, w=w: _fran_before(S, d, yaw, w)))
    return out[::3] if quick else out


def _fran_before(S, d: float, yaw: float, w: float | None):
    # the real face, with a grey wall (albedo 0.5, as the head's) at w times its distance when w
    face = S.fran_face(distance_mm=d, yaw_deg=yaw)
    if w is None:
        return face
    return S.combine(face, S.Plane(np.eye(3), [0.0, 0.0, d * w], 0.5))


def _mirrored_set(S, quick: bool) -> list:
    # the paper rig mirrored, its projector 200 mm to the camera's left (docs/method.md "Known
    # limits": every rule was tuned with it on the right): the multi-object scene at four depths,
    # the head, the sphere and the step, seeds 0-2
    out = []
    for seed in range(3):
        for d in (600.0, 650.0, 700.0, 760.0):
            out.append((f"multi_{d:.0f}_left_s{seed}", "typical/b-200", seed, 3, lambda d=d: S.multi_object(d)))
        out.append((f"head_left_s{seed}", "typical/b-200", seed, 3, lambda: S.head(650.0)))
        out.append((f"sphere_left_s{seed}", "typical/b-200", seed, 3, lambda: S.sphere()))
        out.append((f"step_left_s{seed}", "typical/b-200", seed, 3, lambda: S.step(650.0, 40.0)))
    return out[::3] if quick else out


def _rig_and_preset(preset: str):
    """(the paper rig, at the baseline of a ``P/bB`` preset string's suffix when there, the preset
    without it)."""
    from gbscan import sim

    base, _, b = preset.partition("/b")
    return sim.paper_rig(baseline_mm=float(b)) if b else sim.paper_rig(), base


#: the ``@cool`` preset suffix's room light (red, green, blue per unit of level); ``@warm`` is
#: ``gbscan.cli_common.AMBIENT_TINT_RGB``, the simulator's ``--ambient``
COOL_TINT_RGB = (0.6, 0.8, 1.0)


def _conditions(preset: str, ss: int, jpeg: dict | None):
    """The :class:`gbscan.sim.Conditions` of a scene's preset string (see :func:`scene_list`)."""
    from gbscan import sim
    from gbscan.cli_common import AMBIENT_TINT_RGB

    base, _, light = preset.partition("@")
    name_, _, bayer = base.partition("+")   # "typical+RGGB": the preset seen through a Bayer mosaic
    extra = {}
    if light:
        tint = light.rstrip("0123456789.")
        rgb = {"warm": AMBIENT_TINT_RGB, "cool": COOL_TINT_RGB}[tint]
        extra["ambient_rgb"] = tuple(round(float(light[len(tint):]) * t, 6) for t in rgb)
    return dataclasses.replace(sim.preset(name_), supersample=ss, bayer=bayer, **extra, **(jpeg or {}))


def load_or_render(name, preset, seed, ss, factory, cache: Path | None, jpeg: dict | None = None):
    """(image, truth_column, depth_edge, lit) of one scene, from the cache when there; ``jpeg``:
    :class:`gbscan.sim.Conditions` JPEG, YUV and lens fields (frames stored as JPEG, delivered as
    YUV, a lens with lateral chromatic aberration), None: lossless RGB."""
    from gbscan import sim
    from gbscan.io import save_npz
    from gbscan.pattern import PatternSpec, render_pattern

    if jpeg and jpeg.get("yuv"):
        # a YUV camera: the RGB frame's round trip through OpenCV's YUV conversions (a cheap
        # transform of the cached frame, the same as rendering with Conditions.yuv)
        image, truth, depth_edge, lit = load_or_render(name, preset, seed, ss, factory, cache, {**jpeg, "yuv": ""})
        return sim.yuv_round_trip(image, jpeg["yuv"]), truth, depth_edge, lit
    tag = ""
    if jpeg and jpeg["jpeg_quality"]:
        tag = f"_jpeg{jpeg['jpeg_quality']}_{jpeg['jpeg_sampling'].replace(':', '')}"
    if jpeg and jpeg.get("lateral_ca_px"):
        tag += f"_ca{jpeg['lateral_ca_px']:g}"
    if jpeg and jpeg.get("specular"):
        from gbscan.sim.presets import DEFAULT_SHININESS

        tag += f"_gloss{jpeg['specular']:g}_{jpeg.get('shininess', DEFAULT_SHININESS):g}"
    f = cache / f"{name}_{preset.replace('+', '_').replace('@', '_').replace('/', '_')}_ss{ss}{tag}.npz" \
        if cache is not None else None
    if f is not None and f.exists():
        z = np.load(f)
        return z["image"], z["truth"], z["depth_edge"], z["lit"]
    rig, preset = _rig_and_preset(preset)
    cond = _conditions(preset, ss, jpeg)
    r = sim.render(rig, factory(), render_pattern(PatternSpec()), cond, seed=seed)
    out = (r.image, r.proj_xy[..., 0].astype(np.float32), r.depth_edge, r.lit)
    if f is not None:
        save_npz(f, image=out[0], truth=out[1], depth_edge=out[2], lit=out[3])
    return out


def wrong_regions(sm, truth, depth_edge, stripe_px: int) -> tuple[dict, list[dict], np.ndarray]:
    """Per scene counts, the wrong pixels grouped by region (``sm`` decoded with keep_stages) and
    the (H, W) bool map of the wrong pixels (:func:`gbscan.sim.column_errors`)."""
    from gbscan import sim

    err, bad = sim.column_errors(sm.column, sm.valid, truth, stripe_px)
    counts = {"wrong": int((bad & ~depth_edge).sum()), "wrong_edge": int((bad & depth_edge).sum())}
    idx = sm.stages["index"] if sm.stages else None
    rows = []
    for g in np.unique(sm.region[bad]):
        m = bad & (sm.region == g)
        off = np.round(err[m] / stripe_px).astype(int)
        vals, cnt = np.unique(off, return_counts=True)
        d = {"region": int(g), "wrong_px": int(m.sum()), "region_px": int((sm.valid & (sm.region == g)).sum()),
             "edge_px": int((m & depth_edge).sum()),
             "offset_err": {int(a): int(b) for a, b in zip(vals, cnt)},
             "rows": (int(np.flatnonzero(m.any(1))[0]), int(np.flatnonzero(m.any(1))[-1])),
             "cols": (int(np.flatnonzero(m.any(0))[0]), int(np.flatnonzero(m.any(0))[-1]))}
        if idx is not None and 0 <= g < len(idx.why):
            d.update(how=idx.why[g], markers=int(idx.markers_seen[g]), evidence=int(idx.evidence[g]),
                     mismatch=int(idx.mismatch[g]), runner_up=int(idx.runner_up[g]))
        rows.append(d)
    return counts, rows, bad


#: ``wrong_picture``'s colours (RGB): reported on the right stripe, on a wrong one off / on depth
#: edges, lit and not reported
WRONG_RGB = {"right": (150, 150, 150), "wrong": (255, 40, 40), "wrong_edge": (255, 165, 0),
             "unreported": (40, 60, 150)}


def wrong_picture(path: Path, name: str, image, valid, bad, depth_edge, lit, zoom_px: int = 24) -> Path:
    """PNG of one scene's wrong pixels (``bad``: reported on a wrong stripe, :func:`gbscan.sim.
    column_errors`): the frame at a quarter of its brightness, the reported pixels grey, the
    wrong ones red off depth edges and orange on them, the lit pixels not reported dark blue (the
    colours of ``WRONG_RGB``); beside it the ``2 zoom_px``-px square around the largest
    8-connected cluster of wrong pixels off depth edges (on them when there are none), enlarged.
    Written atomically; returns the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch, Rectangle
    from scipy import ndimage

    from gbscan.io import write_figure_png

    valid, bad, edge, lit = (np.asarray(a, bool) for a in (valid, bad, depth_edge, lit))
    rgb = np.asarray(image, np.float64) * 0.25
    layers = {"unreported": lit & ~valid, "right": valid & ~bad, "wrong_edge": bad & edge, "wrong": bad & ~edge}
    for key, m in layers.items():
        rgb[m] = WRONG_RGB[key]
    rgb = rgb.astype(np.uint8)
    focus = layers["wrong"] if layers["wrong"].any() else layers["wrong_edge"]
    H, W = focus.shape
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6), dpi=100, gridspec_kw={"width_ratios": [W / H, 1]})
    axes[0].imshow(rgb, interpolation="nearest")
    if focus.any():
        lab, n = ndimage.label(focus, structure=np.ones((3, 3), bool))
        big = 1 + int(np.argmax(ndimage.sum(focus, lab, range(1, n + 1))))
        ys, xs = np.nonzero(lab == big)
        cy, cx = int(np.median(ys)), int(np.median(xs))
        y0, x0 = min(max(cy - zoom_px, 0), max(H - 2 * zoom_px, 0)), min(max(cx - zoom_px, 0), max(W - 2 * zoom_px, 0))
        axes[1].imshow(rgb[y0:y0 + 2 * zoom_px, x0:x0 + 2 * zoom_px], interpolation="nearest",
                       extent=(x0 - 0.5, x0 + 2 * zoom_px - 0.5, y0 + 2 * zoom_px - 0.5, y0 - 0.5))
        axes[0].add_patch(Rectangle((x0 - 0.5, y0 - 0.5), 2 * zoom_px, 2 * zoom_px, fill=False, ec="white", lw=0.8))
        axes[1].set_title(f"rows {y0}-{y0 + 2 * zoom_px - 1}, columns {x0}-{x0 + 2 * zoom_px - 1}", fontsize=9)
    else:
        axes[1].set_axis_off()
    axes[0].set_axis_off()
    labels = {"right": "reported, right stripe", "wrong": "wrong stripe, off depth edges",
              "wrong_edge": "wrong stripe, on depth edges", "unreported": "lit, not reported"}
    axes[0].legend(handles=[Patch(color=np.array(WRONG_RGB[k]) / 255, label=f"{labels[k]} ({int(layers[k].sum())})")
                            for k in ("right", "wrong", "wrong_edge", "unreported")],
                   loc="lower right", fontsize=7, framealpha=0.85)
    axes[0].set_title(name, fontsize=10)
    path = write_figure_png(path, fig, bbox_inches="tight")
    plt.close(fig)
    return path


def unindexed_by_why(sm, cand) -> dict:
    """{why: pixels} of the pixels of ``cand`` (lit, off depth edges) that ``sm`` (decoded with
    keep_stages) left unindexed, by their region's ``RegionIndex.why`` ("too few markers (k < n)"
    counted as one; "no region": rows the row checks dropped outside any region)."""
    from gbscan.decode import UNINDEXED

    un = cand & (sm.mask == UNINDEXED)
    if not un.any():
        return {}
    why = sm.stages["index"].why if sm.stages else []
    out: dict = {}
    for g, n in zip(*np.unique(sm.region[un], return_counts=True)):
        w = why[g] if 0 <= g < len(why) else "no region"
        w = "too few markers" if w.startswith("too few markers") else w
        out[w] = out.get(w, 0) + int(n)
    return out


def unindexed_line(tot: dict) -> str:
    """One line: the unindexed share of the lit non-edge pixels by why, the scene that loses most."""
    parts = []
    for why, per in sorted(tot["unindexed"].items(), key=lambda kv: -sum(kv[1].values())):
        top = max(per, key=per.get)
        parts.append(f"{why} {100.0 * sum(per.values()) / max(tot['lit'], 1):.2f} % (most: {top})")
    return "unindexed, by why: " + ("; ".join(parts) if parts else "none")


def working_volume(depth_range):
    """The decoder's stripe prior for the paper rig's true calibration and a depth range (mm), as
    ``gbscan scan --depth-range`` gives it (:attr:`gbscan.scan.Scanner.stripe_range`); None: none."""
    if depth_range is None:
        return None
    from gbscan import sim
    from gbscan.calibfile import calibration_from_rig
    from gbscan.clean import CleanParams
    from gbscan.pattern import PatternSpec
    from gbscan.scan import Scanner

    near, far = depth_range
    cal = calibration_from_rig(sim.paper_rig(), PatternSpec())
    return Scanner(cal, clean_params=CleanParams(min_depth_mm=near, max_depth_mm=far)).stripe_range


def sweep(params, scenes, cache: Path | None, edges: bool = False, show: bool = True,
          stripe_range=None, jpeg: dict | None = None, pictures: Path | None = None) -> dict:
    """Decode every scene with ``params`` (and the working volume ``stripe_range``); per-scene
    lines (and wrong regions) when ``show``; ``pictures``: a folder for a :func:`wrong_picture` of
    each scene with wrong pixels.  Returns the totals: lit non-edge pixels, reported, wrong, wrong_edge,
    bad_scenes, scenes, pictures (their paths)."""
    from gbscan.decode import decode
    from gbscan.pattern import PatternSpec

    spec = PatternSpec()
    out = print if show else (lambda *a, **k: None)
    tot = {"lit": 0, "reported": 0, "wrong": 0, "wrong_edge": 0, "bad_scenes": 0, "scenes": len(scenes),
           "sq_err": 0.0, "n_err": 0, "over_1px": 0, "unindexed": {}, "pictures": []}
    out(f"{'scene':26s} {'preset':16s} {'reported%':>9s} {'wrong':>6s} {'wrong_edge':>10s} {'col_rms':>7s} "
        f"{'>1px':>5s} {'ms':>6s}")
    for k, (name, preset, seed, ss, factory) in enumerate(scenes):
        t0 = time.perf_counter()
        image, truth, depth_edge, lit = load_or_render(name, preset, seed, ss, factory, cache, jpeg)
        t1 = time.perf_counter()
        sm = decode(image, spec, params, keep_stages=True, stripe_range=stripe_range)
        t2 = time.perf_counter()
        print(f"[{k + 1}/{len(scenes)}] {name}: render/load {t1 - t0:.1f} s, decode {t2 - t1:.2f} s",
              file=sys.stderr, flush=True)
        cand = lit & ~depth_edge
        rep = int((sm.valid & cand).sum())
        counts, rows, bad = wrong_regions(sm, truth, depth_edge, spec.stripe_px)
        # sub-pixel accuracy: column error of the reported non-edge pixels on their right stripe
        ok = sm.valid & cand & np.isfinite(truth)
        e = (sm.column - truth)[ok]
        e = e[np.abs(e) < spec.stripe_px / 2]
        col_rms = float(np.sqrt(np.mean(e.astype(np.float64) ** 2))) if e.size else float("nan")
        tot["sq_err"] += float(np.sum(e.astype(np.float64) ** 2))
        tot["n_err"] += int(e.size)
        tot["over_1px"] += int((np.abs(e) > 1.0).sum())
        tot["lit"] += int(cand.sum())
        tot["reported"] += rep
        tot["wrong"] += counts["wrong"]
        tot["wrong_edge"] += counts["wrong_edge"]
        tot["bad_scenes"] += int(counts["wrong"] + counts["wrong_edge"] > 0)
        for why, n in unindexed_by_why(sm, cand).items():
            per = tot["unindexed"].setdefault(why, {})
            per[name] = per.get(name, 0) + n
        if pictures is not None and counts["wrong"] + counts["wrong_edge"] > 0:
            tot["pictures"].append(wrong_picture(pictures / f"wrong_{name}.png", name, image, sm.valid, bad,
                                                 depth_edge, lit))
        out(f"{name:26s} {preset:16s} {100.0 * rep / max(cand.sum(), 1):9.2f} {counts['wrong']:6d} "
            f"{counts['wrong_edge']:10d} {col_rms:7.3f} {int((np.abs(e) > 1.0).sum()):5d} {(t2 - t1) * 1e3:6.0f}",
            flush=True)
        for d in rows:
            if d["wrong_px"] == d["edge_px"] and not edges:
                continue  # depth-edge pixels only (they mix two surfaces): see --edges
            out("    " + " ".join(f"{a}={b}" for a, b in d.items()), flush=True)
    return tot


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cache", help="folder to keep the renders in between runs (created)")
    ap.add_argument("--only", help="run only the scenes whose name contains this")
    ap.add_argument("--quick", action="store_true", help="every third scene")
    ap.add_argument("--set", default="main", choices=SETS,
                    help="the frames: main (the 48 scenes, default), room-light (44 frames: warm light 0.05-0.4 on "
                         "sphere / head / multi-object / step, cool light 0.15, 0.25 on the first three, seeds "
                         "0-1; docs/method.md 'Ambient light'), clean (the clean preset, 16 frames), baselines "
                         "(the multi-object scene with the projector 100-300 mm from the camera, seeds 0-2, 33 "
                         "frames; docs/method.md 'Baseline 200 mm'), mirrored (the projector 200 mm to the "
                         "camera's left: the multi-object scene at 600-760 mm, head, sphere, step, seeds 0-2, 21 "
                         "frames; docs/method.md 'Known limits'), panels (the multi-object scene's panel plain, "
                         "45 frames), layouts (other depths, walls and albedos, 32 frames), holdout (32 frames "
                         "of the multi-object scene kept out of the rules' making: check a rule on them, do not "
                         "tune on them; one rule was made from them in the thirtieth session), holdout2, holdout3 "
                         "(32 frames more each, at other depths, walls and albedos, made then; one rule was made "
                         "from each since), holdout4, holdout5, holdout6 (32 more each, made in the thirty-first "
                         "session; one rule was made from holdout4 and one from holdout5), holdout7 (32 more, "
                         "thirty-second session), holdout8, holdout9 (32 more each, thirty-third session; one rule was "
                         "made from holdout8), holdout10, holdout11 (32 more each, thirty-fourth session; one rule was made from holdout10), "
                         "holdout12, holdout13 (32 more each, thirty-fifth session; holdout11 and holdout12 were looked into "
                         "then, no rule kept), faces (held out too: the synthetic head at 575-785 mm turned "
                         "up to 35 degrees and the real face at 585-805 mm, some before a wall; 32 frames with the "
                         "real face's mesh, 20 without)")
    ap.add_argument("--edges", action="store_true", help="also list regions wrong only on depth-edge pixels")
    ap.add_argument("--out", help="folder for a picture of each scene with pixels on wrong stripes (created)")
    ap.add_argument("--unwrap", action="append", default=[], metavar="NAME=VALUE",
                    help="override an UnwrapParams field (repeatable), e.g. --unwrap link_rows=3")
    ap.add_argument("--decode", action="append", default=[], metavar="NAME=VALUE",
                    help="override a DecodeParams field (repeatable), e.g. --decode blur_sigma_along_px=1, "
                         "--decode join_transitions=false")
    ap.add_argument("--depth-range", type=float, nargs=2, metavar=("MIN_MM", "MAX_MM"),
                    help="a working volume for the indexing prior, as gbscan scan --depth-range (the paper "
                         "rig's true calibration); default: none")
    ap.add_argument("--blur-grid", metavar="S1,S2,...",
                    help="run the whole sweep once per fixed blur sigma (px) and print one total line each "
                         "(the automatic blur picks 1-3 px by the frame's SNR: the index must hold at all)")
    from gbscan.cli_common import add_capture_arguments, capture_fields

    add_capture_arguments(ap)
    args = ap.parse_args(argv)
    jpeg = capture_fields(args)
    sigmas = []
    if args.blur_grid:
        try:
            sigmas = [float(x) for x in args.blur_grid.split(",") if x.strip()]
        except ValueError:
            ap.error(f"--blur-grid: expected comma-separated sigmas in px, got {args.blur_grid!r}")

    from dataclasses import replace

    from gbscan.commands.decode import pairs_to_kwargs
    from gbscan.decode import DecodeParams
    from gbscan.errors import GBError
    from gbscan.io import make_dir
    from gbscan.unwrap import UnwrapParams

    cache = Path(args.cache) if args.cache else None
    if cache is not None:
        make_dir(cache, "--cache")
    out = Path(args.out) if args.out else None
    if out is not None and args.blur_grid:
        ap.error("--out: pictures of one sweep, not of --blur-grid's")
    if out is not None:
        make_dir(out, "--out")
    try:   # the fields as the commands' --decode-param reads them (numbers, switches, none)
        over = pairs_to_kwargs(UnwrapParams, args.unwrap, "--unwrap")
        dover = pairs_to_kwargs(DecodeParams, args.decode, "--decode")   # unwrap.NAME too
        if over and "unwrap" in dover:
            raise GBError("--unwrap and --decode unwrap.NAME=VALUE: give the unwrapping's fields one way")
        if over or "unwrap" not in dover:
            dover["unwrap"] = UnwrapParams(**over)
        params = DecodeParams(**dover)
    except GBError as e:
        ap.error(str(e))
    scenes = [s for s in scene_list(args.quick, args.set) if not args.only or args.only in s[0]]
    if args.depth_range is not None and not 0 < args.depth_range[0] < args.depth_range[1]:
        ap.error(f"--depth-range: expected 0 < MIN_MM < MAX_MM, got {args.depth_range}")
    if args.depth_range is not None and args.set in ("baselines", "mirrored"):
        ap.error(f"--depth-range: the working volume is the 200 mm rig's; not with --set {args.set}")
    volume = working_volume(args.depth_range)
    if sigmas:
        print(f"{'blur_px':>7s} {'reported%':>9s} {'wrong':>6s} {'wrong_edge':>10s} {'bad scenes':>10s}")
        for sg in sigmas:
            tot = sweep(replace(params, blur_sigma_along_px=sg), scenes, cache, show=False, stripe_range=volume,
                        jpeg=jpeg)
            print(f"{sg:7.2f} {100.0 * tot['reported'] / max(tot['lit'], 1):9.2f} {tot['wrong']:6d} "
                  f"{tot['wrong_edge']:10d} {tot['bad_scenes']:>7d}/{tot['scenes']}", flush=True)
        return 0
    tot = sweep(params, scenes, cache, args.edges, stripe_range=volume, jpeg=jpeg, pictures=out)
    rms = (tot["sq_err"] / tot["n_err"]) ** 0.5 if tot["n_err"] else float("nan")
    print(f"{'TOTAL':26s} {'':16s} {100.0 * tot['reported'] / max(tot['lit'], 1):9.2f} {tot['wrong']:6d} "
          f"{tot['wrong_edge']:10d} {rms:7.3f} {tot['over_1px']:5d}   scenes with wrong pixels: "
          f"{tot['bad_scenes']}/{tot['scenes']}")
    print(unindexed_line(tot))
    if out is not None:
        print(f"pictures of the scenes with wrong pixels: {len(tot['pictures'])} in {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
