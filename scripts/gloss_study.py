"""Glossy surfaces: what highlights cost the decoder, and what the envelope that follows the
pattern's brightness takes back.

    python scripts/gloss_study.py [--scenes fran_face,head,sphere] [--ks 0.3,1] [--shininess 10,30,100]
                                  [--seed 0] [--follow-px 9] [--out DIR] [--decode NAME=VALUE ...]

Renders each scene matte and glossy (``gbscan.sim.Conditions.specular`` KS and ``shininess``:
Blinn-Phong highlights of the projector's own colour; typical preset, supersample 3, the paper
rig, 650 mm) and decodes every frame twice: with the wide min/max envelope alone (the default,
``envelope_follow_px=0``) and with the envelope that follows the pattern's brightness
(``envelope_follow_px`` = ``--follow-px``, 9).
Prints, per scene and gloss, the % of lit non-edge pixels reported and the pixels on a wrong
stripe off depth edges, both ways.  ``fran_face`` is the real face mesh of
``../shared/data/fran_face`` (skipped when it is not there).

``--out DIR`` writes ``gloss_<scene>.png`` for the brightest KS at the middle shininess: the
glossy frame, and the lit non-edge pixels it loses against the matte frame, by the decoder's
reason, with the wide envelope alone and with the following one (docs/img/gloss_fran_face.png).
``--decode NAME=VALUE`` changes a DecodeParams field for both decodes (repeatable).
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np


def _scene(name: str):
    from gbscan import sim

    S = sim.scenes
    if name == "fran_face":
        return S.fran_face(distance_mm=650.0) if S.FRAN_PATH.is_file() else None
    if name == "head":
        return S.head(650.0)
    if name == "sphere":
        return S.sphere((0.0, 0.0, 650.0), 100.0, wall_mm=900.0)
    raise SystemExit(f"gloss_study: unknown scene {name!r}; expected fran_face, head or sphere")


def _score(sm, r, stripe_px: int) -> tuple[float, int, np.ndarray]:
    from gbscan import sim

    cand = r.lit & ~r.depth_edge
    _, bad = sim.column_errors(sm.column, sm.valid, r.proj_xy[..., 0].astype(np.float32), stripe_px)
    return 100.0 * float(sm.valid[cand].mean()), int((bad & ~r.depth_edge).sum()), cand


def picture(path: Path, image: np.ndarray, cand: np.ndarray, matte_ok: np.ndarray, masks: dict, title: str) -> Path:
    """The glossy frame beside the lit non-edge pixels it loses against the matte one, by reason
    (``masks``: label -> the glossy frame's ``StripeMap.mask``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    from gbscan.decode import REASONS
    from gbscan.io import write_figure_png
    from gbscan.preview.decode import REASON_RGB

    own = {"dark": (60, 110, 255), "low_contrast": (210, 210, 120), "saturated": (255, 255, 255)}
    colours = {code: own.get(name, REASON_RGB.get(name, (255, 0, 255))) for code, name in REASONS.items() if code}
    ys, xs = np.nonzero(cand)
    sl = (slice(max(ys.min() - 4, 0), ys.max() + 5), slice(max(xs.min() - 4, 0), xs.max() + 5))
    fig, axes = plt.subplots(1, 1 + len(masks), figsize=(4.2 * (1 + len(masks)), 4.8), dpi=110)
    axes[0].imshow(image[sl], interpolation="nearest")
    axes[0].set_title("glossy frame", fontsize=9)
    for ax, (label, mask) in zip(axes[1:], masks.items()):
        rgb = (image * 0.25).astype(np.float64)
        kept = cand & (mask == 0)
        rgb[kept] = (150, 150, 150)
        lost = cand & matte_ok & (mask != 0)
        handles = [Patch(color=np.array((150, 150, 150)) / 255, label=f"reported ({int(kept.sum())})")]
        for code, col in colours.items():
            m = lost & (mask == code)
            if m.any():
                rgb[m] = col
                handles.append(Patch(color=np.array(col) / 255, label=f"{REASONS[code]} ({int(m.sum())})"))
        ax.imshow(rgb[sl].astype(np.uint8), interpolation="nearest")
        ax.legend(handles=handles, loc="lower right", fontsize=6, framealpha=0.8)
        ax.set_title(f"{label}: lost against the matte frame", fontsize=9)
    for ax in axes:
        ax.set_axis_off()
    fig.suptitle(title, fontsize=10)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    path = write_figure_png(path, fig, bbox_inches="tight")
    plt.close(fig)
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="fran_face,head,sphere")
    ap.add_argument("--ks", default="0.3,1", help="specular weights (comma-separated; 1 = as bright as white matte)")
    ap.add_argument("--shininess", default="10,30,100", help="Blinn-Phong exponents (comma-separated)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--follow-px", type=int, default=9, help="envelope_follow_px of the second decode (default 9)")
    ap.add_argument("--out", help="folder for the pictures (created)")
    ap.add_argument("--decode", action="append", default=[], metavar="NAME=VALUE",
                    help="a DecodeParams field other than the default, for both decodes (repeatable)")
    args = ap.parse_args(argv)

    from gbscan import sim
    from gbscan.commands.decode import pairs_to_kwargs
    from gbscan.decode import DecodeParams, decode
    from gbscan.errors import GBError
    from gbscan.pattern import PatternSpec, render_pattern

    names = [x for x in args.scenes.split(",") if x]
    bad = [x for x in names if x not in ("fran_face", "head", "sphere")]
    if bad or not names:
        print(f"gloss_study: unknown scene(s) {bad or args.scenes!r}; expected fran_face, head or sphere",
              file=sys.stderr)
        return 2
    try:
        ks_list = [float(x) for x in args.ks.split(",") if x]
        shin_list = [float(x) for x in args.shininess.split(",") if x]
    except ValueError:
        print(f"gloss_study: --ks {args.ks!r} / --shininess {args.shininess!r}: expected comma-separated numbers",
              file=sys.stderr)
        return 2
    try:
        base = DecodeParams(**pairs_to_kwargs(DecodeParams, args.decode, "--decode"))
        params = {"following": dataclasses.replace(base, envelope_follow_px=args.follow_px),
                  "wide alone": dataclasses.replace(base, envelope_follow_px=0)}
    except (ValueError, GBError) as e:
        print(f"gloss_study: {e}", file=sys.stderr)
        return 2
    if not ks_list or not shin_list:
        print("gloss_study: --ks and --shininess need at least one value each", file=sys.stderr)
        return 2
    spec = PatternSpec()
    pattern = render_pattern(spec)
    rig = sim.paper_rig()
    cond0 = dataclasses.replace(sim.preset("typical"), supersample=3)
    print(f"# glossy surfaces: % of lit non-edge pixels reported (pixels on a wrong stripe off depth edges), "
          f"seed {args.seed}, typical preset, supersample 3; envelope_follow_px {args.follow_px} / 0")
    for name in names:
        scene = _scene(name)
        if scene is None:
            print(f"## {name}: skipped (../shared/data/fran_face is not here)")
            continue
        print(f"## {name}", flush=True)
        matte = sim.render(rig, scene, pattern, cond0, seed=args.seed)
        res = {label: decode(matte.image, spec, p) for label, p in params.items()}
        scores = {label: _score(sm, matte, spec.stripe_px) for label, sm in res.items()}
        line = " | ".join(f"{label} {s[0]:5.1f} ({s[1]})" for label, s in scores.items())
        print(f"   matte:                      {line}", flush=True)
        matte_ok = res["following"].valid | res["wide alone"].valid
        shown = (max(ks_list), shin_list[len(shin_list) // 2])
        for ks in ks_list:
            for sh in shin_list:
                cond = dataclasses.replace(cond0, specular=ks, shininess=sh)
                r = sim.render(rig, scene, pattern, cond, seed=args.seed)
                got = {label: decode(r.image, spec, p) for label, p in params.items()}
                scores = {label: _score(sm, r, spec.stripe_px) for label, sm in got.items()}
                line = " | ".join(f"{label} {s[0]:5.1f} ({s[1]})" for label, s in scores.items())
                print(f"   KS {ks:g}, shininess {sh:5g}:   {line}", flush=True)
                if args.out and (ks, sh) == shown:
                    cand = scores["following"][2]
                    path = picture(Path(args.out) / f"gloss_{name}.png", r.image, cand, matte_ok,
                                   {"wide envelope alone": got["wide alone"].mask, "following envelope":
                                    got["following"].mask},
                                   f"{name}, KS {ks:g}, shininess {sh:g} (seed {args.seed})")
                    print(f"   picture: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
