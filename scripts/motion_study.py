"""How far may the object move while the camera exposes?  Scan simulated frames of moving objects.

    python scripts/motion_study.py [--scenes sphere,head,fran_face] [--motions x,y,z,yaw]
                                   [--travel-mm 0,0.5,1,2,4] [--seeds 0] [--steps 9]
                                   [--preset typical] [--out DIR]

The method's promise is one frame per range image, so that moving and deforming objects (a face)
can be scanned at video rate.  One frame still takes an exposure: the object moves during it.
The projector and the camera stand still, so the stripes stay where the light planes meet the
surface -- an object sliding sideways smears its texture, not its stripes -- while its depth
changes shift them along the rows.  ``gbscan.sim.render_moving`` renders that: the scene at
``--steps`` equally spaced instants of the exposure (``gbscan.sim.scenes.moved``), their linear
light averaged, the camera's noise added once; the ground truth is the mid-exposure pose.

Motions, each over a *travel* (mm the object moves during the exposure; its speed is the travel
over the exposure time: 1 mm in a 10 ms exposure is 100 mm/s):

* ``x``: sideways (across the stripes); ``y``: up / down (along them);
* ``z``: toward the camera;
* ``yaw``: turning about a vertical axis 100 mm behind the object's front, by the angle that
  moves a point 100 mm from the axis by the travel (a face turning its head).

The scenes are ``scripts/coverage_study.py``'s (the still rows are its figures).  Each frame is
decoded and scanned with the true calibration (``gbscan.scan.Scanner``, default decoder and
cleaning) and the script prints, over the lit non-edge pixels of the mid-exposure pose (*edge*:
its depth edges and the *swept* pixels, which see another surface during the exposure,
``Render.motion_edge``):

* the decoder's reported %, and its pixels more than half a stripe off the mid-exposure truth
  off those edges (``wrong``: the absolute index must hold);
* the scan's kept %, depth RMS (mm, against the mid-exposure surface) and worst point (mm, as
  ``scripts/coverage_study.py`` counts it) off the swept pixels;
* the points kept on swept pixels (their own truth may be another surface or none): how many, and
  the farthest one's distance to the mid-exposure surface (mm).

``--out DIR`` writes ``motion_<scene>.png``: kept % and depth RMS against the travel per motion.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

MOTIONS = ("x", "y", "z", "yaw")
#: a yaw turns about a vertical axis this far behind the object's front; the travel is the arc
#: a point at this distance from the axis moves
YAW_ARM_MM = 100.0


def scene_parts(name: str):
    """(scene, turning centre mm) of a study scene."""
    from gbscan import sim

    S = sim.scenes
    if name == "sphere":
        return S.sphere((0.0, 0.0, 650.0), 100.0), (0.0, 0.0, 650.0)
    if name == "head":
        return S.head(650.0), (0.0, 0.0, 650.0 + YAW_ARM_MM)
    if name == "fran_face":
        return S.fran_face(distance_mm=650.0), (0.0, 0.0, 650.0 + YAW_ARM_MM)
    if name == "plane":
        return S.plane(650.0, tilt_deg=(0.0, 20.0)), (0.0, 0.0, 650.0)
    raise ValueError(name)


def poses(name: str, motion: str, travel_mm: float, steps: int) -> list:
    """The scene at ``steps`` equally spaced instants of an exposure over which the object moves
    ``travel_mm`` (centred on mid-exposure; one instant when it does not move)."""
    from gbscan import sim

    scene, centre = scene_parts(name)
    n = 1 if travel_mm == 0 else steps
    if motion == "yaw":
        return sim.scenes.exposure_poses(scene, turn_deg=np.degrees(travel_mm / YAW_ARM_MM), steps=n, about_mm=centre)
    move = np.zeros(3)
    move["xyz".index(motion)] = travel_mm
    return sim.scenes.exposure_poses(scene, move, steps=n)


def study(name: str, motion: str, travel_mm: float, seed: int, steps: int, preset: str, supersample: int,
          scanner) -> dict:
    import dataclasses

    from gbscan import sim
    from gbscan.pattern import PatternSpec, render_pattern

    cond = dataclasses.replace(sim.preset(preset), supersample=supersample)
    r = sim.render_moving(sim.paper_rig(), poses(name, motion, travel_mm, steps), render_pattern(PatternSpec()), cond,
                          seed=seed)
    s = scanner.scan(r.image)
    edge = r.depth_edge if r.motion_edge is None else (r.depth_edge | r.motion_edge)
    P = r.point.astype(np.float64)
    good = r.lit & ~edge & np.isfinite(P[..., 2])
    sm = s.stripemap
    _, bad = sim.column_errors(sm.column, sm.valid, r.proj_xy[..., 0], int(PatternSpec().stripe_px))
    kept = good & s.valid
    dz = (s.xyz[..., 2] - P[..., 2])[kept]
    swept = np.zeros_like(good) if r.motion_edge is None else r.motion_edge
    err = sim.point_errors_mm(r, s.xyz, s.valid)[s.valid & ~swept]
    # a point where the surface swept past during the exposure: its distance to the mid-exposure
    # surface (the pixel's own truth may be another surface, or none)
    fly = s.valid & swept
    fly_mm = float("nan")
    if fly.any():
        from scipy.spatial import cKDTree

        surf = P[np.isfinite(P[..., 2])]
        fly_mm = float(cKDTree(surf).query(s.xyz[fly].astype(np.float64))[0].max())
    n = max(int(good.sum()), 1)
    return {"scene": name, "motion": motion, "travel_mm": travel_mm, "seed": seed, "lit": int(good.sum()),
            "reported": float((good & sm.valid).sum() / n), "wrong": int((bad & good).sum()),
            "kept": float(kept.sum() / n), "rms_mm": float(np.sqrt(np.mean(dz ** 2))) if dz.size else float("nan"),
            "worst_mm": float(np.nanmax(err)) if err.size else float("nan"), "swept_mm": fly_mm,
            "swept_px": int(fly.sum())}


def _label(motion: str, travel_mm: float) -> str:
    if motion == "yaw" and travel_mm:
        return f"{travel_mm:g} mm ({np.degrees(travel_mm / YAW_ARM_MM):.2f} deg)"
    return f"{travel_mm:g} mm"


def picture(rows: list, name: str, out: Path) -> Path:
    """kept % and depth RMS against the travel, one line per motion (median over the seeds)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from gbscan.io import write_bytes_atomic

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.6))
    for motion in MOTIONS:
        sel = [r for r in rows if r["scene"] == name and r["motion"] == motion]
        if not sel:
            continue
        tr = sorted({r["travel_mm"] for r in sel})
        med = lambda k: [np.median([r[k] for r in sel if r["travel_mm"] == t]) for t in tr]  # noqa: E731
        ax[0].plot(tr, [100 * v for v in med("kept")], "o-", label=motion)
        ax[1].plot(tr, med("rms_mm"), "o-", label=motion)
    ax[0].set_ylabel("lit non-edge pixels kept (%)")
    ax[1].set_ylabel("depth RMS (mm)")
    for a in ax:
        a.set_xlabel("travel during the exposure (mm)")
        a.grid(alpha=0.3)
        a.legend(title="motion", fontsize=8)
    fig.suptitle(f"{name}: an object moving during one exposure")
    fig.tight_layout()
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    path = out / f"motion_{name}.png"
    write_bytes_atomic(path, buf.getvalue())
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="sphere,head,fran_face",
                    help="sphere, head, fran_face (the real face mesh, skipped when ../shared lacks it), plane")
    ap.add_argument("--motions", default=",".join(MOTIONS), help="x, y, z, yaw (default all)")
    ap.add_argument("--travel-mm", default="0,0.5,1,2,4",
                    help="how far the object moves during the exposure, mm (default 0,0.5,1,2,4)")
    ap.add_argument("--seeds", default="0", help="comma-separated render seeds (default 0)")
    ap.add_argument("--steps", type=int, default=9, help="instants of the exposure rendered (odd, default 9)")
    ap.add_argument("--preset", default="typical", choices=("clean", "typical", "hard"))
    ap.add_argument("--supersample", type=int, default=3, help="camera rays per pixel side (default 3)")
    ap.add_argument("--out", help="folder for the pictures (created)")
    args = ap.parse_args(argv)
    from gbscan import sim
    from gbscan.calibfile import calibration_from_rig
    from gbscan.errors import GBError
    from gbscan.io import make_dir
    from gbscan.pattern import PatternSpec
    from gbscan.scan import Scanner

    def floats(text, what):
        try:
            v = [float(x) for x in text.split(",") if x.strip()]
        except ValueError:
            ap.error(f"{what}: expected comma-separated numbers, got {text!r}")
        if not v or any(not np.isfinite(x) or x < 0 for x in v):
            ap.error(f"{what}: expected numbers >= 0, got {text!r}")
        return v

    travels = floats(args.travel_mm, "--travel-mm")
    seeds = [int(x) for x in floats(args.seeds, "--seeds")]
    motions = [m.strip() for m in args.motions.split(",") if m.strip()]
    for m in motions:
        if m not in MOTIONS:
            ap.error(f"--motions: expected some of {', '.join(MOTIONS)}, got {m!r}")
    names = [x.strip() for x in args.scenes.split(",") if x.strip()]
    for n in names:
        if n not in ("sphere", "head", "fran_face", "plane"):
            ap.error(f"--scenes: expected some of sphere, head, fran_face, plane, got {n!r}")
    if args.steps < 1 or args.steps % 2 == 0:
        ap.error(f"--steps: expected an odd number >= 1 (the middle instant is the truth), got {args.steps}")
    if not 1 <= args.supersample <= 5:
        ap.error(f"--supersample: expected 1..5, got {args.supersample}")
    out = None
    if args.out:
        try:
            out = make_dir(args.out, "--out")
        except GBError as e:
            ap.error(str(e))
    if "fran_face" in names and not sim.scenes.FRAN_PATH.is_file():
        print(f"# fran_face skipped: {sim.scenes.FRAN_PATH} is not there", file=sys.stderr)
        names.remove("fran_face")
    # every frame its own measurements (remeasure_every=1): the frames are separate experiments, not a stream
    scanner = Scanner(calibration_from_rig(sim.paper_rig(), PatternSpec()), remeasure_every=1)
    print(f"# motion study, paper rig, preset {args.preset}, {args.steps} instants per exposure, supersample "
          f"{args.supersample}, true calibration, default decoder and cleaning")
    print(f"{'scene':10s} {'motion':6s} {'travel':>18s} {'reported%':>9s} {'wrong':>5s} {'kept%':>6s} "
          f"{'rms_mm':>7s} {'worst_mm':>8s} {'swept_pts':>9s} {'swept_mm':>8s}")
    rows = []
    for name in names:
        for motion in motions:
            for travel in travels:
                if travel == 0 and motion != motions[0]:
                    continue     # the still frame once per scene
                for seed in seeds:
                    print(f"rendering {name} {motion} {travel:g} mm seed {seed} ...", file=sys.stderr, flush=True)
                    r = study(name, motion, travel, seed, args.steps, args.preset, args.supersample, scanner)
                    rows.append(r)
                    print(f"{name:10s} {motion if travel else 'still':6s} {_label(motion, travel):>18s} "
                          f"{100 * r['reported']:9.2f} {r['wrong']:5d} {100 * r['kept']:6.2f} {r['rms_mm']:7.3f} "
                          f"{r['worst_mm']:8.2f} {r['swept_px']:9d} {r['swept_mm']:8.2f}", flush=True)
        if out is not None:
            still = [dict(r, motion=m) for r in rows if r["scene"] == name and r["travel_mm"] == 0 for m in motions]
            print(f"# wrote {picture(rows + still, name, out)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
