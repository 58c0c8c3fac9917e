"""Sequential row/segment kernels of the decoder and the cleaning, compiled with numba
(``cache=True``).

Only :mod:`gbscan.unwrap`, :mod:`gbscan.decode` and (inside their functions) :mod:`gbscan.clean`,
:mod:`gbscan.scan` and :mod:`gbscan.diagnose` import this package, so ``gbscan --help`` never
pays for numba.  Every kernel works on plain numpy arrays; the conventions are those of
:mod:`gbscan.unwrap`:

* ``labels`` (H, W) uint8 colour class per pixel (``NONE=0, GREEN=1, BLUE=2, CYAN=3``).
* A *run* is a maximal horizontal stretch of one label; a *segment* is a maximal chain of runs
  along a row whose consecutive labels form valid stripe transitions; ``rel`` is the relative
  stripe index of a pixel inside its segment, with parity fixed by colour (green even, blue odd).
* A *junction* is the place between two consecutive runs of a segment (one stripe boundary).

The kernels live in one module per concept and are all reachable here as ``kernels.NAME``:

=================  =================================================================================
``segments``       paper steps 1-2 and 4: runs, segments, links, strips (``link_strips``), junctions, columns, cuts
``classify``       stages 1-3: blur, colour balance, threshold, classify; the fused ``stream_frame``; the lit window
``regions``        final masks (``finish_pixels``), dark transitions, region histograms, offset scores and the
                   indexing's tests, step 7, rim; pasting a window's map into the frame
``linking``        vertical votes between rows, marker conflicts, the linking's votes grouped, slope samples, verdicts
``guards``         rim guard rows, stripe SNR, orphans, brightness-step guard, bridge cuts, tilt-step cuts
``resample``       stripe width from runs, linear-light shrinking, expanding a coarse decode
``pointmap``       cleaning an organised point map (``gbscan.clean``)
``colour``         the frame's colour resolution: chroma window moments (``gbscan.chroma``)
=================  =================================================================================

Row loops that vectorise: one loop per array written, indexed from 0, no calls, no early exits.
On AVX2 machines (no AVX-512) also: **read every byte-array element before a select**.  In
``d[u] = k if c else d[u]`` with ``d`` uint8 the read happens on one branch only; AVX2 has no
masked load of bytes, so LLVM keeps the whole loop scalar and branchy (12x slower alone, measured
on a Zen 3), while an AVX-512 machine vectorises it.  ``old = d[u]; d[u] = k if c else old``
vectorises on both.  Another trap found the same way: an int64 -> float64 conversion (AVX2
has no vector instruction for it: convert from int32, or compute in float64 throughout).  Branches
per pixel (``if`` chains choosing among outputs) keep a loop scalar on any CPU: compute every
candidate and select.  ``python scripts/vector_report.py`` lists the loops LLVM
could have vectorised on this CPU but did not (it compiles every kernel afresh with LLVM's
remarks on; ``--missed`` / ``--all`` for more).

The first call compiles (a few seconds, cached on disk afterwards); tests and benchmarks warm up.
numba's on-disk cache is checked against the calling kernel's own file only: after editing a
kernel that a kernel in *another* file calls (``segments._vertical_votes_sorted`` from ``linking``;
the helpers of ``_common``: ``run_starts``, ``fill_row``, ``copy_row``, ``ctz64``, ``contradicts``,
``contradicting_px``, ``fit_add``, ``fit_slope``, ``lower_bound``), delete
``gbscan/kernels/__pycache__`` (or touch the caller's file), or the caller keeps running the old code.
"""
from __future__ import annotations

from ._common import BLUE, CYAN, GREEN, NONE  # noqa: F401
from .linking import *  # noqa: F401,F403
from .classify import *  # noqa: F401,F403
from .colour import *  # noqa: F401,F403
from .classify import _box4_8to15, _minmax4_from_quads, _quad_minmax2, _raw_hi_row  # noqa: F401  (tests)
from .guards import *  # noqa: F401,F403
from .guards import _brightness, _tilt_step  # noqa: F401  (tests)
from .pointmap import *  # noqa: F401,F403
from .regions import *  # noqa: F401,F403
from .resample import *  # noqa: F401,F403
from .resample import _coarse_columns, _coarse_row, _expanded, _slopes, _upsample_any, _upsample_x2  # noqa: F401  (tests)
from .segments import *  # noqa: F401,F403
from .segments import _merge_runs_pass, _vertical_votes_sorted  # noqa: F401  (unwrap, tests)
