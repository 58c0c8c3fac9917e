"""The projector frames one calibration pose needs (``gbcal patterns``).

A calibration pose is a static board; besides the single-shot stripe frame the scanner uses, it
can afford extra frames, which make the stripe planes' absolute indices certain and the board
easy to find:

* ``white`` -- full white: the board is detected in this frame; also the per-pixel maximum for
  normalising the others.
* ``black`` -- projector dark: ambient light and the per-pixel minimum.
* ``stripes`` -- the single-shot green-blue (+ cyan marker) pattern the scanner projects; the
  sub-pixel stripe boundaries on the board come from it.
* ``gray_NN`` and ``gray_NN_inv`` -- Gray code of the *stripe index* (bit NN, most significant
  first) and its inverse, in white: bit = image > inverse image, robust to albedo.  They give
  every lit board pixel its absolute stripe index independently of the decoder.

Frame names are the file names in each ``pose_NNN/`` folder of a capture session.
"""
from __future__ import annotations

import math

import numpy as np

from gbscan.pattern import PatternSpec, render_pattern


def n_gray_bits(spec: PatternSpec) -> int:
    return max(1, math.ceil(math.log2(spec.n_stripes)))


def gray_code(k: np.ndarray) -> np.ndarray:
    k = np.asarray(k, dtype=np.int64)
    return k ^ (k >> 1)


def gray_decode(g: np.ndarray) -> np.ndarray:
    """Inverse of :func:`gray_code` for non-negative ints (any shape)."""
    k = np.asarray(g, dtype=np.int64).copy()
    shift = k >> 1
    while np.any(shift):
        k ^= shift
        shift >>= 1
    return k


def frame_names(spec: PatternSpec) -> list[str]:
    """Display order of the calibration frames."""
    names = ["white", "black", "stripes"]
    for b in range(n_gray_bits(spec)):
        names += [f"gray_{b:02d}", f"gray_{b:02d}_inv"]
    return names


def calibration_frames(spec: PatternSpec) -> dict[str, np.ndarray]:
    """Every frame by name (insertion order = display order), each (H, W, 3) uint8 RGB."""
    H, W = spec.height, spec.width
    frames: dict[str, np.ndarray] = {}
    frames["white"] = np.full((H, W, 3), 255, np.uint8)
    frames["black"] = np.zeros((H, W, 3), np.uint8)
    frames["stripes"] = render_pattern(spec)
    nb = n_gray_bits(spec)
    g = gray_code(np.arange(W) // spec.stripe_px)
    for b in range(nb):
        bit = ((g >> (nb - 1 - b)) & 1).astype(bool)
        row = np.where(bit, 255, 0).astype(np.uint8)
        img = np.ascontiguousarray(np.broadcast_to(row[None, :, None], (H, W, 3)))
        frames[f"gray_{b:02d}"] = img
        frames[f"gray_{b:02d}_inv"] = 255 - img
    assert list(frames) == frame_names(spec)
    return frames
