"""How often would a region the markers leave ambiguous be indexed wrongly by its stripe margin?

    python scripts/index_margin_study.py [--cache DIR] [--set main,room-light,...] [--quick]

For every frame of the sweep sets of ``scripts/sweep_decode.py`` (the same scenes, renders and
cache), decodes with the stripe margin off (``UnwrapParams.index_margin_stripes=0``) and records
every scoring of a region by :func:`gbscan.unwrap.index_regions` -- the first one and those of the
decoder's weld repairs -- with the simulator's truth:

* the region's true offset (the most common ``true stripe - relative index`` of its pixels) and
  its *purity* (the share of its pixels on that offset: below 95 % the region spans two surfaces);
* its ``why``, its best offset, its stripe margin (``RegionIndex.stripe_margin``: how many
  more stripes every other candidate offset contradicts than the best) and, for a margin of 1,
  the telling stripe's strength (``RegionIndex.stripe_strength``: the contradicting pixels of
  the one stripe that tells the best from the candidates one stripe worse).

Prints, for stripe margins 1-4, how many of the ambiguous (``ambiguous offset``) one-surface
regions that margin would index, their pixels, and how many of them at a wrong offset; the same for
the regions spanning two surfaces (their best offset is right for the larger part only: what is
left of them is the row checks' business); and the regions the pixel margin indexes, for scale.
Then the ambiguous regions (either kind) with a stripe margin of exactly 1 by their telling stripe's
strength: how many a threshold would index, and how many wrongly.
``UnwrapParams.index_margin_stripes`` (2) was chosen by it (twenty-eighth session), and
``UnwrapParams.index_strong_stripe_px`` (60) over the thirteen sets ``main`` ... ``holdout6``
(thirty-second session; run it with ``--set`` to leave out the sets kept fresh).  The sweep
itself (``sweep_decode.py``) measures the decoder end to end, the stripe margin included.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # measure this checkout, whatever the environment's install points at
    sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

PURE = 0.95   # a region with this share of its pixels on one offset lies on one surface


def region_records(labels, relative, region, idx, truth, stripe_px: int) -> list[dict]:
    """One record per scored region of one :func:`gbscan.unwrap.index_regions` call."""
    recs = []
    ts = np.floor((truth + 0.5) / stripe_px)
    ok = (region >= 0) & np.isfinite(ts)
    if not ok.any():
        return recs
    reg = region[ok]
    diff = (ts[ok] - relative[ok]).astype(np.int64)
    order = np.lexsort((diff, reg))
    reg, diff = reg[order], diff[order]
    starts = np.flatnonzero(np.r_[True, reg[1:] != reg[:-1]])
    ends = np.r_[starts[1:], reg.size]
    for a, b in zip(starts, ends):
        k = int(reg[a])
        if b - a < 10 or idx.stripe_margin is None:
            continue
        vals, cnt = np.unique(diff[a:b], return_counts=True)
        recs.append({"why": idx.why[k], "best": int(idx.offset[k]), "true": int(vals[np.argmax(cnt)]),
                     "purity": float(cnt.max() / cnt.sum()), "px": int(b - a),
                     "stripes": int(idx.stripe_margin[k]), "indexed": bool(idx.indexed[k]),
                     "strength": int(idx.stripe_strength[k]) if idx.stripe_strength is not None else 0})
    return recs


def study(sets: list[str], cache: Path | None, quick: bool) -> list[dict]:
    import sweep_decode as sd

    from gbscan import unwrap as uw
    from gbscan.decode import DecodeParams, decode
    from gbscan.pattern import PatternSpec

    spec = PatternSpec()
    # the stripe margin off; the whole frame (crop off): the maps index_regions sees are the frame's
    params = DecodeParams(crop=False, unwrap=uw.UnwrapParams(index_margin_stripes=0))
    recs: list[dict] = []
    current = {}
    scorer = uw.index_regions

    def recording(labels, relative, region, n_regions, pattern, p=uw.UnwrapParams(), stripe_range=None):
        idx = scorer(labels, relative, region, n_regions, pattern, p, stripe_range)
        t = current["truth"]
        if t.shape == region.shape:   # (a frame decoded shrunk scores a smaller grid: not recorded)
            recs.extend(region_records(labels, relative, region, idx, t, pattern.stripe_px))
        return idx

    uw.index_regions = recording
    try:
        for which in sets:
            scenes = sd.scene_list(quick, which)
            for i, (name, preset, seed, ss, factory) in enumerate(scenes):
                img, truth, _, _ = sd.load_or_render(name, preset, seed, ss, factory, cache)
                current["truth"] = truth
                decode(img, spec, params)
                print(f"[{which} {i + 1}/{len(scenes)}] {name}: {len(recs)} scorings so far", file=sys.stderr,
                      flush=True)
    finally:
        uw.index_regions = scorer
    return recs


def report(recs: list[dict]) -> None:
    amb = [r for r in recs if r["why"] == "ambiguous offset"]
    for label, sel in (("ambiguous, one surface", [r for r in amb if r["purity"] >= PURE]),
                       ("ambiguous, two surfaces", [r for r in amb if r["purity"] < PURE])):
        print(f"\n{label}: {len(sel)} scorings, {sum(r['px'] for r in sel)} px")
        print("  stripe margin   would index (px)        at a wrong offset (px)")
        for m in (1, 2, 3, 4):
            take = [r for r in sel if r["stripes"] >= m]
            wrong = [r for r in take if r["best"] != r["true"]]
            print(f"  >= {m}             {len(take):5d} ({sum(r['px'] for r in take):8d})     "
                  f"{len(wrong):5d} ({sum(r['px'] for r in wrong):7d})")
    # the strong-stripe index: ambiguous regions with a stripe margin of exactly 1, by how many
    # contradicting pixels the one stripe that tells the best from the others shows
    one = [r for r in amb if r["stripes"] == 1]
    print(f"\nambiguous, stripe margin 1: {len(one)} scorings, {sum(r['px'] for r in one)} px "
          f"(unwrap.index_strong_stripe_px indexes those whose telling stripe reaches it)")
    print("  telling stripe  would index (px)        at a wrong offset (px)   wrong, their stripes (px)")
    for t in (12, 24, 36, 48, 60, 80, 100):
        take = [r for r in one if r["strength"] >= t]
        wrong = [r for r in take if r["best"] != r["true"]]
        print(f"  >= {t:3d} px       {len(take):5d} ({sum(r['px'] for r in take):8d})     "
              f"{len(wrong):5d} ({sum(r['px'] for r in wrong):7d})      "
              f"{', '.join(str(r['strength']) for r in wrong[:12])}")
    ok = [r for r in recs if r["indexed"] and r["purity"] >= PURE]
    bad = [r for r in ok if r["best"] != r["true"]]
    print(f"\nindexed by the pixel margin, one surface: {len(ok)} scorings, {len(bad)} at a wrong offset")


def main(argv=None) -> int:
    import sweep_decode as sd

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cache", type=Path, default=None, help="the renders' cache of sweep_decode.py (read and filled)")
    ap.add_argument("--set", default=",".join(sd.SETS), help=f"comma-separated sweep sets (of {', '.join(sd.SETS)})")
    ap.add_argument("--quick", action="store_true", help="the sets' quick scene lists")
    args = ap.parse_args(argv)
    sets = [s for s in args.set.split(",") if s]
    unknown = [s for s in sets if s not in sd.SETS]
    if unknown:
        print(f"index_margin_study: unknown set(s) {', '.join(unknown)}; choose from {', '.join(sd.SETS)}",
              file=sys.stderr)
        return 2
    if args.cache is not None:
        args.cache.mkdir(parents=True, exist_ok=True)
    report(study(sets, args.cache, args.quick))
    return 0


if __name__ == "__main__":
    sys.exit(main())
