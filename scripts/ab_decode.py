"""Is a change to the decoder faster?  Two versions in ONE process, call by call (A/B).

    python scripts/ab_decode.py --base REV [--new REV] [--scene plane,head] [--runs 80] [--preset typical]

On a shared or noisy machine, the medians of two benchmark processes run one after the other can
differ by 15 % while the change being measured is worth 3 % (this machine: 2 cores, other jobs).
This script imports the decoder of revision ``--base`` (and of ``--new``: by default the checkout
the script lives in, uncommitted edits included) side by side in one process, and decodes each
frame with them alternately, one call each in turn, so that both see the same load.  It prints,
per scene:

* each version's median and fastest CPU milliseconds per frame (``time.thread_time``: the
  decoding thread's own time, less sensitive to other processes than the wall clock);
* the median of the per-pair ratios new / old (< 1: new is faster), the figure to quote;
* the median of each decoder stage (``StripeMap.stats["ms"]``), old -> new;
* whether both give identical maps (mask, column, stripe, confidence, column_sigma; NaN equal to
  NaN) and identical stats (timings aside) -- a speed-up that changes results says so.

A revision is extracted once with ``git archive`` into ``--cache`` (default
``~/.cache/gbscan/ab``) as a package of its own name (``gbscan_<sha12>``): the decoder imports
itself relatively, so both versions live in one process.  numba compiles the extracted copy's
kernels on its first use (about a minute and a half here) and caches them there; later runs start
at once.  One thread (numba and OpenCV), glibc's freed memory kept (:mod:`gbscan.heap`), frames
rendered by the simulator at 640x480 (the paper's rig; ``--width 1280`` for 1280x1024) with the
same scenes as ``scripts/bench_decode.py``.

Two compiled copies of the kernels in one process are outside what numba promises: with
``--base 42fb9bd`` or a later base (893fb30 too, 2026-11-28) the checkout's first
``link_components`` call segfaults once the
base has decoded a head frame (the checkout decoding first, or ``--base a279d7d``, run fine; each
version alone runs fine, and a bounds-checked build of the checkout reads and writes nothing out
of bounds on the frames that exercise this session's rules).  If a base crashes the script, take
a neighbouring revision.
"""
from __future__ import annotations

import argparse
import importlib
import os
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCENES = ("plane", "head", "sphere", "multi_object")
MAPS = ("mask", "column", "stripe", "confidence", "column_sigma")


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def resolve(rev: str, repo: Path = ROOT) -> str:
    """The full commit id of ``rev`` in ``repo``; ValueError naming it when git does not know it."""
    r = subprocess.run(["git", "-C", str(repo), "rev-parse", "--verify", "--quiet", f"{rev}^{{commit}}"],
                       capture_output=True, text=True)
    if r.returncode != 0 or not r.stdout.strip():
        raise ValueError(f"revision {rev!r} is not a commit of the git repository {repo} "
                         f"(expected a commit id, tag or branch; see `git log`)")
    return r.stdout.strip()


def extract(sha: str, cache: Path, repo: Path = ROOT) -> tuple[Path, str]:
    """Revision ``sha``'s ``gbscan`` package as ``cache/<sha>/gbscan_<sha12>``, extracted once
    (``git archive``; an interrupted extraction is redone).  Returns (folder for sys.path, name)."""
    name = f"gbscan_{sha[:12]}"
    home = cache / sha
    done = home / ".complete"
    if not done.exists():
        tmp = cache / f".{sha}.{os.getpid()}.tar"
        cache.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as f:
            subprocess.run(["git", "-C", str(repo), "archive", "--format=tar", sha, "gbscan"], stdout=f, check=True)
        home.mkdir(parents=True, exist_ok=True)
        with tarfile.open(tmp) as t:
            if hasattr(tarfile, "data_filter"):      # Python >= 3.11.4: refuse odd members
                t.extractall(home, filter="data")
            else:
                t.extractall(home)
        os.unlink(tmp)
        target = home / name
        if target.exists():
            import shutil

            shutil.rmtree(target)
        (home / "gbscan").rename(target)
        done.write_text(sha + "\n")
    return home, name


def import_decoder(folder: Path | None, name: str):
    """The ``decode`` and ``pattern`` modules of package ``name`` (from ``folder``; None: as
    installed).  A version that imports ``gbscan`` by its absolute name would mix with the
    checkout's: refused, naming the modules."""
    before = set(sys.modules)
    if folder is not None and str(folder) not in sys.path:
        sys.path.insert(0, str(folder))
    dec = importlib.import_module(f"{name}.decode")
    pat = importlib.import_module(f"{name}.pattern")
    if name != "gbscan":
        leaked = sorted(m for m in set(sys.modules) - before if m == "gbscan" or m.startswith("gbscan."))
        if leaked:
            raise RuntimeError(f"{name} imported the checkout's own modules {leaked}: it cannot run beside "
                               f"another version in one process")
    return dec, pat


def same_results(a, b) -> tuple[bool, bool]:
    """(maps identical, stats identical except the timings) of two StripeMaps."""
    maps = True
    for k in MAPS:
        x, y = getattr(a, k), getattr(b, k)
        if x is None or y is None:
            maps &= x is None and y is None
        else:
            maps &= x.shape == y.shape and x.dtype == y.dtype and bool(np.array_equal(x, y, equal_nan=x.dtype.kind == "f"))
    sa = {k: v for k, v in a.stats.items() if k != "ms"}
    sb = {k: v for k, v in b.stats.items() if k != "ms"}
    return maps, repr(sa) == repr(sb)


def alternate(fa, fb, runs: int, clock=time.thread_time) -> tuple[np.ndarray, np.ndarray, list, list]:
    """Call ``fa`` and ``fb`` ``runs`` times each, alternately (ab, ba, ab, ...): their times
    (ms) and return values in call order."""
    ta, tb, ra, rb = [], [], [], []
    for i in range(runs):
        for f, t, r in ((fa, ta, ra), (fb, tb, rb)) if i % 2 == 0 else ((fb, tb, rb), (fa, ta, ra)):
            c = clock()
            out = f()
            t.append((clock() - c) * 1e3)
            r.append(out)
    return np.array(ta), np.array(tb), ra, rb


def stage_medians(ms: list) -> dict:
    """Median of each stage over the decodes' ``stats["ms"]`` dicts."""
    keys = [k for k in ms[0] if k != "total"]
    return {k: float(np.median([m.get(k, np.nan) for m in ms])) for k in keys}


def report(scene: str, ta: np.ndarray, tb: np.ndarray, ra: list, rb: list, maps: bool, stats: bool) -> str:
    """The lines printed for a scene: times (ms) of old and new, their decodes' ``stats["ms"]``."""
    sa, sb = stage_medians(ra), stage_medians(rb)
    lines = [f"## {scene}: old {np.median(ta):.2f} ms (fastest {ta.min():.2f}) -> new {np.median(tb):.2f} ms "
             f"(fastest {tb.min():.2f}); median ratio of pairs new/old {np.median(tb / ta):.3f} "
             f"(quartiles {np.percentile(tb / ta, 25):.3f}-{np.percentile(tb / ta, 75):.3f})",
             "   stages (ms, old -> new): " + "  ".join(f"{k} {sa[k]:.2f}->{sb.get(k, np.nan):.2f}" for k in sa),
             f"   results: maps {'identical' if maps else 'DIFFERENT'}, stats {'identical' if stats else 'DIFFERENT'}"]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--base", required=True, help="the revision to compare against (commit, tag, branch, HEAD~1)")
    ap.add_argument("--new", default=None, help="the revision to measure (default: this checkout as it is)")
    ap.add_argument("--scene", default="plane,head",
                    help=f"comma-separated, of {', '.join(SCENES)} (default plane,head)")
    ap.add_argument("--runs", type=int, default=80, help="calls of each version per scene (default 80)")
    ap.add_argument("--preset", default="typical", choices=("clean", "typical", "hard"))
    ap.add_argument("--width", type=int, default=640, choices=(640, 1280), help="camera width (640x480 or 1280x1024)")
    ap.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "gbscan" / "ab",
                    help="where revisions are extracted and their kernels cached")
    args = ap.parse_args(argv)
    scenes = [s.strip() for s in args.scene.split(",") if s.strip()]
    bad = [s for s in scenes if s not in SCENES]
    if bad or not scenes:
        ap.error(f"--scene: expected names of {', '.join(SCENES)}, got {args.scene!r}")
    if args.runs < 2:
        ap.error(f"--runs: expected at least 2, got {args.runs}")
    try:
        old_sha = resolve(args.base)
        new_sha = resolve(args.new) if args.new else None
    except ValueError as e:
        ap.error(str(e))

    import cv2
    import numba

    cv2.setNumThreads(1)
    numba.set_num_threads(1)
    from gbscan.heap import keep_freed_memory

    keep_freed_memory()
    sys.path.insert(0, str(ROOT / "scripts"))
    from bench_decode import frames

    folder, name = extract(old_sha, args.cache)
    old_dec, old_pat = import_decoder(folder, name)
    if new_sha is None:
        new_dec, new_pat = import_decoder(None, "gbscan")
        new_label = "this checkout" + (" (with uncommitted changes)" if subprocess.run(
            ["git", "-C", str(ROOT), "diff", "--quiet", "HEAD", "--", "gbscan"]).returncode else "")
    else:
        nfolder, nname = extract(new_sha, args.cache)
        new_dec, new_pat = import_decoder(nfolder, nname)
        new_label = new_sha[:12]
    print(f"# decoder A/B: old {old_sha[:12]} ({args.base}) vs new {new_label}; one process, calls alternating, "
          f"CPU ms per frame, {args.runs} calls each, 1 thread, {args.preset} preset, width {args.width}")
    for scene in scenes:
        img = frames(args.width, scene, args.preset).image
        log(f"[{scene}] warming up (the first use of an extracted revision compiles its kernels) ...")
        t0 = time.perf_counter()
        a = old_dec.decode(img, old_pat.PatternSpec())
        b = new_dec.decode(img, new_pat.PatternSpec())
        log(f"[{scene}] ready in {time.perf_counter() - t0:.1f} s; timing ...")
        maps, stats = same_results(a, b)
        # (each call keeps its stage times only: holding on to the maps would make every decode
        # allocate fresh pages, and the page faults would be timed)
        ta, tb, ra, rb = alternate(lambda: old_dec.decode(img, old_pat.PatternSpec()).stats["ms"],
                                   lambda: new_dec.decode(img, new_pat.PatternSpec()).stats["ms"], args.runs)
        print(report(scene, ta, tb, ra, rb, maps, stats), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
