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
boundary never shows.  The gaps between consecutive markers are drawn from ``MARKER_GAPS``
(the *marker code*, :func:`marker_gap_symbols`): first a de Bruijn sequence B(5, 2), in which
every pair of consecutive gaps is distinct, so that any three consecutive markers within the
first 167 stripes fix a region's absolute offset; then (code 2, the default) a continuation in
which every three consecutive gaps are distinct across the whole sequence (any four consecutive
markers fix the offset, over up to 639 stripes: 5 100 projector px at 8 px a stripe) and a pair
of gaps recurs no sooner than 9 gaps later where the walk allows.  Code 1, the sequence before
2026-11-28, read B(5, 2) again after its 25 gaps: a pattern of more than 167 stripes (a
1920-px projector at 8 px) was periodic with a period of 154 stripes, so regions that did not
reach the pattern's middle fitted two offsets equally and were dropped as ambiguous.  Patterns of
at most 167 stripes are the same under both codes (1024 px at 8 px: 128).  The decoder scores
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
#: The marker codes (:func:`marker_gap_symbols`): 1, the sequence before 2026-11-28 (B(5, 2)
#: repeated: periodic beyond 167 stripes); 2, B(5, 2) continued without repeating any three
#: consecutive gaps (the default).  The same markers on patterns of at most
#: ``CODES_AGREE_STRIPES`` stripes.
MARKER_CODES = (1, 2)
MARKER_CODE = 2
#: the largest number of stripes whose markers both codes place alike
CODES_AGREE_STRIPES = 167
#: code 2's continuation: a pair of consecutive gaps recurs at least this many gaps later where
#: the walk can keep to it (then only the three-gap rule holds)
PAIR_SPACING = 8


@dataclass(frozen=True)
class PatternSpec:
    """What the projector shows for a scan.

    width, height : projector resolution in pixels.
    stripe_px : stripe width in projector pixels (see docs/method.md "Stripe width" for the choice
        of 8 at the paper's geometry: about 3.4 camera pixels per stripe at 650 mm).
    markers : embed cyan marker stripes for absolute indexing (False: the paper's pure pattern).
    marker_code : which marker sequence (``MARKER_CODES``; module docstring): 2, the default, or 1
        for a pattern made before 2026-11-28 (a calibration file or session without the field
        reads as 1).  Where both codes give the same markers (at most ``CODES_AGREE_STRIPES``
        stripes, or no markers) it is stored as the default, so such specs compare equal.
    """

    width: int = 1024
    height: int = 768
    stripe_px: int = 8
    markers: bool = True
    marker_code: int = MARKER_CODE

    def __post_init__(self):
        if int(self.width) < 16 or int(self.height) < 1:
            raise GBError(f"projector size {self.width}x{self.height} is too small (need width >= 16)")
        if not 2 <= int(self.stripe_px) <= int(self.width) // 4:
            raise GBError(f"stripe width {self.stripe_px} px must be between 2 and width/4")
        code = self.marker_code
        if isinstance(code, bool) or not isinstance(code, (int, np.integer)) or int(code) not in MARKER_CODES:
            raise GBError(f"marker code must be one of {', '.join(map(str, MARKER_CODES))}, got {code!r}")
        if not self.markers or self.n_stripes <= CODES_AGREE_STRIPES:
            code = MARKER_CODE   # the codes agree here: one spelling
        object.__setattr__(self, "marker_code", int(code))

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
        return _marker_sequence(self.n_stripes, self.marker_code)

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
                "stripe_px": int(self.stripe_px), "markers": bool(self.markers), "marker_code": int(self.marker_code)}

    @classmethod
    def from_dict(cls, d: dict) -> "PatternSpec":
        """The inverse of :meth:`to_dict`; a mapping without ``marker_code`` (written before
        2026-11-28) is marker code 1, the sequence it was projected with."""
        return cls(int(d["width"]), int(d["height"]), int(d["stripe_px"]), bool(d["markers"]),
                   d.get("marker_code", 1))


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


@lru_cache(maxsize=4)
def marker_gap_symbols(code: int = MARKER_CODE) -> tuple[int, ...]:
    """The marker code's gaps, as indices into ``MARKER_GAPS``, read from the first marker on
    (after the last one the sequence starts again).

    Both codes begin with B(len(MARKER_GAPS), 2) and its first symbol again (26 symbols: its 25
    pairs of consecutive gaps all distinct).  Code 1 ends there.  Code 2 walks on, choosing at
    each step a symbol whose three-gap window (with the two before it) has not occurred yet --
    among those, one whose pair with the symbol before has not occurred within the last
    ``PAIR_SPACING`` gaps while any such remains, the one whose pair occurred longest ago (never:
    first), ties to the smaller gap -- until no three-gap window is left (108 symbols: the last
    marker at stripe 639)."""
    k = len(MARKER_GAPS)
    seq = _de_bruijn(k, 2)
    seq = seq + seq[:1]
    if code == 1:
        return tuple(seq)
    if code != 2:
        raise GBError(f"marker code must be one of {', '.join(map(str, MARKER_CODES))}, got {code!r}")
    used = {tuple(seq[i:i + 3]) for i in range(len(seq) - 2)}
    last = {tuple(seq[i:i + 2]): i for i in range(len(seq) - 1)}   # where each pair last began
    never = -(1 << 30)
    for spacing in (PAIR_SPACING, 1):
        while True:
            a, b = seq[-2], seq[-1]
            at = len(seq) - 1   # the new pair (b, s) begins here
            free = [s for s in range(k) if (a, b, s) not in used and at - last.get((b, s), never) >= spacing]
            if not free:
                break
            s = min(free, key=lambda s: (last.get((b, s), never), s))
            used.add((a, b, s))
            last[(b, s)] = at
            seq.append(s)
    return tuple(seq)


@lru_cache(maxsize=16)
def _marker_sequence_cached(n_stripes: int, code: int) -> tuple[int, ...]:
    # The code's gaps read linearly (and again if the projector is wider than the sequence),
    # keeping both neighbours of every marker inside the pattern.
    symbols = marker_gap_symbols(code)
    pos, out, i = FIRST_MARKER, [FIRST_MARKER], 0
    while True:
        g = MARKER_GAPS[symbols[i % len(symbols)]]
        if pos + g > n_stripes - 3:
            break
        pos += g
        out.append(pos)
        i += 1
    return tuple(out)


def _marker_sequence(n_stripes: int, code: int = MARKER_CODE) -> np.ndarray:
    if n_stripes < FIRST_MARKER + 3:
        return np.zeros(0, dtype=np.int64)
    return np.array(_marker_sequence_cached(int(n_stripes), int(code)), dtype=np.int64)


def render_pattern(spec: PatternSpec) -> np.ndarray:
    """The single-shot projector frame, (height, width, 3) uint8 RGB."""
    lut = np.array([LABEL_RGB[i] for i in range(4)], dtype=np.uint8)
    row = lut[spec.column_labels()]
    return np.ascontiguousarray(np.broadcast_to(row[None], (spec.height, spec.width, 3)))
