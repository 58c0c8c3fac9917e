"""The projected green-blue stripe pattern and its geometry.

Stripe ``k`` (0-based, left to right) covers projector pixel columns ``k*w .. k*w + w - 1`` for
stripe width ``w = stripe_px``.  Its colour is pure green (0, 255, 0) for even ``k`` and pure blue
(0, 0, 255) for odd ``k`` -- the paper's pattern.  Boundary ``k`` (``k = 1 .. n_stripes - 1``) lies
between stripes ``k - 1`` and ``k`` at projector column ``x = k*w - 0.5`` (pixel centres at
integers); each boundary is one calibrated light plane.

Absolute indexing (beyond the paper).  The green-blue pair repeats, so on its own the pattern
only gives stripe indices relative to an unknown even offset per connected region.  With
``markers=True`` a sparse set of stripes is projected cyan (0, 255, 255) instead: green *and*
blue.  A cyan stripe is recognisable independently of albedo (after colour balancing both
channels are high, whereas a green or blue stripe has one channel at the crosstalk floor), and
its two neighbours always share one colour (``G C G`` or ``B C B``), which a blurred green-blue
boundary never shows.  The gaps between consecutive markers are drawn from ``MARKER_GAPS`` so
that every pair of consecutive gaps is distinct (a de Bruijn-like sequence): any three
consecutive markers seen in a region fix that region's absolute offset, and the decoder scores
all of a region's markers and non-markers at once (see ``gbscan.unwrap``).  ``markers=False``
gives the paper's pure pattern.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .errors import GBError

#: Per-pixel / per-stripe colour labels used by the pattern, the simulator and the decoder.
NONE, GREEN, BLUE, CYAN = 0, 1, 2, 3
LABEL_NAMES = {NONE: "none", GREEN: "green", BLUE: "blue", CYAN: "cyan"}
LABEL_RGB = {GREEN: (0, 255, 0), BLUE: (0, 0, 255), CYAN: (0, 255, 255), NONE: (0, 0, 0)}

#: Allowed gaps (in stripes) between consecutive markers.
MARKER_GAPS = (4, 5, 6, 7, 8)
#: Index of the first marker stripe.
FIRST_MARKER = 3


@dataclass(frozen=True)
class PatternSpec:
    """What the projector shows for a scan.

    width, height : projector resolution in pixels.
    stripe_px : stripe width in projector pixels (see docs/method.md "Stripe width" for the choice
        of 8 at the paper's geometry: about 3.4 camera pixels per stripe at 650 mm).
    markers : embed cyan marker stripes for absolute indexing (False: the paper's pure pattern).
    """

    width: int = 1024
    height: int = 768
    stripe_px: int = 8
    markers: bool = True

    def __post_init__(self):
        if int(self.width) < 16 or int(self.height) < 1:
            raise GBError(f"projector size {self.width}x{self.height} is too small (need width >= 16)")
        if not 2 <= int(self.stripe_px) <= int(self.width) // 4:
            raise GBError(f"stripe width {self.stripe_px} px must be between 2 and width/4")

    @property
    def n_stripes(self) -> int:
        """Number of stripes across the projector (the last one may be cut by the edge)."""
        return math.ceil(self.width / self.stripe_px)

    @property
    def boundary_indices(self) -> np.ndarray:
        """(n_stripes - 1,) int indices ``k`` of the boundaries (light planes) 1 .. n-1."""
        return np.arange(1, self.n_stripes, dtype=np.int64)

    def boundary_column(self, k) -> np.ndarray:
        """Projector column (px) of boundary ``k`` (between stripes k-1 and k): ``k*w - 0.5``."""
        return np.asarray(k, dtype=np.float64) * self.stripe_px - 0.5

    def stripe_of_column(self, x) -> np.ndarray:
        """Stripe index of continuous projector column(s) ``x`` (pixel centres at integers)."""
        return np.floor((np.asarray(x, dtype=np.float64) + 0.5) / self.stripe_px).astype(np.int64)

    def marker_indices(self) -> np.ndarray:
        """Sorted stripe indices that are cyan markers (empty for the pure pattern)."""
        if not self.markers:
            return np.zeros(0, dtype=np.int64)
        return _marker_sequence(self.n_stripes)

    def is_marker(self) -> np.ndarray:
        """(n_stripes,) bool: True at the cyan marker stripes (all False for the pure pattern)."""
        out = np.zeros(self.n_stripes, np.bool_)
        out[self.marker_indices()] = True
        return out

    def stripe_labels(self) -> np.ndarray:
        """(n_stripes,) uint8 colour label of each stripe (GREEN, BLUE or CYAN)."""
        k = np.arange(self.n_stripes)
        lab = np.where(k % 2 == 0, GREEN, BLUE).astype(np.uint8)
        lab[self.marker_indices()] = CYAN
        return lab

    def column_labels(self) -> np.ndarray:
        """(width,) uint8 colour label of every projector column."""
        return self.stripe_labels()[np.arange(self.width) // self.stripe_px]

    def to_dict(self) -> dict:
        return {"width": int(self.width), "height": int(self.height),
                "stripe_px": int(self.stripe_px), "markers": bool(self.markers)}

    @classmethod
    def from_dict(cls, d: dict) -> "PatternSpec":
        return cls(int(d["width"]), int(d["height"]), int(d["stripe_px"]), bool(d["markers"]))


def _de_bruijn(k: int, n: int) -> list[int]:
    """The lexicographically least de Bruijn sequence B(k, n) (cyclic, length k**n)."""
    a = [0] * k * n
    seq: list[int] = []

    def db(t: int, p: int) -> None:
        if t > n:
            if n % p == 0:
                seq.extend(a[1 : p + 1])
        else:
            a[t] = a[t - p]
            db(t + 1, p)
            for j in range(a[t - p] + 1, k):
                a[t] = j
                db(t + 1, t)

    db(1, 1)
    return seq


@lru_cache(maxsize=16)
def _marker_sequence_cached(n_stripes: int) -> tuple[int, ...]:
    # Gaps follow B(len(MARKER_GAPS), 2) read linearly (and again if the projector is wider than
    # one period): the first len(MARKER_GAPS)**2 consecutive gap pairs are all distinct.
    symbols = _de_bruijn(len(MARKER_GAPS), 2)
    symbols = symbols + symbols[:1]
    pos, out, i = FIRST_MARKER, [FIRST_MARKER], 0
    while True:
        g = MARKER_GAPS[symbols[i % len(symbols)]]
        if pos + g > n_stripes - 3:  # keep both neighbours of every marker inside the pattern
            break
        pos += g
        out.append(pos)
        i += 1
    return tuple(out)


def _marker_sequence(n_stripes: int) -> np.ndarray:
    if n_stripes < FIRST_MARKER + 3:
        return np.zeros(0, dtype=np.int64)
    return np.array(_marker_sequence_cached(int(n_stripes)), dtype=np.int64)


def render_pattern(spec: PatternSpec) -> np.ndarray:
    """The single-shot projector frame, (height, width, 3) uint8 RGB."""
    lut = np.array([LABEL_RGB[i] for i in range(4)], dtype=np.uint8)
    row = lut[spec.column_labels()]
    return np.ascontiguousarray(np.broadcast_to(row[None], (spec.height, spec.width, 3)))
