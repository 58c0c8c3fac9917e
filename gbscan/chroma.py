"""Chroma subsampling seen in the pixels of an RGB frame.

Most cameras and codecs store colour at half the horizontal resolution of the brightness: YUYV
(4:2:2) and MJPEG (4:2:0) webcams, JPEG files (OpenCV's and most encoders' default 4:2:0), H.264
and most video.  Converted back to RGB, such a frame looks like any other, but its colour edges are
two pixels wide: at ~3.5 camera px per stripe the green / blue / cyan stripes then smear into each
other, fake cyan appears at green-blue transitions, and the decoder's absolute index can be
confidently wrong (``scripts/sweep_decode.py``, 48 scenes, pixels on a wrong stripe off depth
edges: 0 in full colour; 2039 through a YUYV camera and 830 through an I420 one, as OpenCV converts
them, ``--yuv``; 352 as JPEG q95 4:2:2, 111 as JPEG q90 4:2:0).  A
file's header or a stream's pixel format tells (``gbscan.io.jpeg_info``, ``gbscan.frames``); a frame
that arrives as an array, or as a PNG saved from such a camera, does not.  This module looks at the
pixels.

**How.**  A colour channel stored at half the width and upsampled by 2 along the rows, whatever
the filter (pixel repetition as OpenCV's YUYV and I420 conversions do, the JPEG decoder's
triangle, linear or cubic resizing; samples centred between pixel pairs or co-sited with the even
columns, as MPEG-2 / H.264 place them), makes windows of consecutive pixels obey more exact linear
relations when they start on one column parity than when they start on the other: repetition
makes the first difference across a pair vanish, the triangle the third difference centred on
one, a cubic filter a relation over 10 pixels, co-sited samples the second difference centred on
an odd column.  Full-resolution colour has no preferred parity.  :func:`chroma_check` takes the
Cb and Cr (BT.601) windows of ``WINDOW`` = 10 pixels along a sample of rows, every pixel of a
window striped, builds the 10x10 second-moment matrix of the windows starting on even columns and
of those starting on odd ones, and compares their eigenvalues: ``score`` is the lowest ratio
(smaller / larger) among the 6 smallest; ``score_cosited`` the same for the windows' first 9
pixels (odd lengths tell co-sited samples apart, even lengths centred ones).  Measured on the
simulator's frames (the 92 frames of ``scripts/sweep_decode.py``'s sets: typical, hard, clean,
room light, Bayer, supersampled or not; docs/method.md, "Camera frames"): full colour 0.76-0.99 /
0.79-0.99 (lossless), 0.86-0.99 / 0.41-0.80 (Bayer demosaiced; 0.41 at 1280x960), 0.79-1.00 / 0.49-0.99 (JPEG 4:4:4
q95); a YUYV or I420 camera through OpenCV 0.00-0.13, 4:2:2 / 4:2:0 upsampled linearly or by
cubic resizing 0.01-0.34, JPEG q95 4:2:2 / q90 4:2:0 0.03-0.21 (the hard preset's noise: up to
0.43); co-sited samples upsampled linearly or by a cubic 0.00-0.11 (co-sited score).  Frames are
called subsampled when ``score`` is under ``SCORE_MAX`` = 0.5 or ``score_cosited`` under
``COSITED_MAX`` = 0.2.

Over one (H, W, 3) uint8 RGB frame; the moments are one compiled pass
(:func:`gbscan.kernels.chroma_window_moments`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: score below which a frame's colour is called subsampled along its rows
SCORE_MAX = 0.5
#: ... and the co-sited score (windows of 9 pixels) below which
COSITED_MAX = 0.2
#: pixels per window along a row (10: cubic upsamplers too)
WINDOW = 10


@dataclass(frozen=True)
class ChromaCheck:
    """What :func:`chroma_check` found.

    score : the parity score of windows of 10 pixels (~1 full colour, ~0 colour upsampled by 2
        along the rows from samples centred between pixel pairs); NaN when too few striped pixels
        were seen.
    subsampled : ``score`` under ``SCORE_MAX`` or ``score_cosited`` under ``COSITED_MAX``.
    samples : windows the moments were taken over (both parities, both channels).
    score_cosited : the same for windows of 9 pixels (~0 for samples co-sited with the even
        columns, as MPEG-2 / H.264 place them).
    """

    score: float
    subsampled: bool
    samples: int
    score_cosited: float = float("nan")

    def describe(self) -> str:
        """One phrase for messages."""
        if not np.isfinite(self.score):
            return "colour resolution not measured (too few striped pixels)"
        if self.subsampled:
            which = (f"phase score {self.score:.2f} < {SCORE_MAX:g}" if self.score < SCORE_MAX else
                     f"co-sited phase score {self.score_cosited:.2f} < {COSITED_MAX:g}")
            return (f"colour stored at half the horizontal resolution (chroma subsampling: 4:2:2 / 4:2:0, e.g. a "
                    f"YUYV or MJPEG camera, JPEG, video; {which})")
        return f"full colour resolution (phase scores {self.score:.2f}, co-sited {self.score_cosited:.2f})"


def chroma_check(image_rgb: np.ndarray, *, level: int = 40, row_step: int = 8, max_rows: int = 16,
                 more_rows: int = 48, unsure: tuple[float, float] = (0.25, 0.75), min_samples: int = 2000,
                 score_max: float = SCORE_MAX, cosited_max: float = COSITED_MAX,
                 unsure_cosited: tuple[float, float] = (0.1, 0.4)) -> ChromaCheck:
    """Is this RGB frame's colour subsampled along its rows?  (See the module docstring.)

    image_rgb : (H, W, 3) uint8 RGB.
    level : a pixel takes part when its green or blue byte reaches it (the stripes, not the dark).
    row_step, max_rows : every ``row_step``-th row, at most ``max_rows`` rows (spread over the
        rows that hold striped pixels); a score inside ``unsure`` is measured again on up to
        ``more_rows`` rows (2 of the sweep's 92 full-colour frames; of its subsampled ones, the
        hard preset's JPEG frames alone).
    min_samples : fewer striped pixels than this: score NaN, not called subsampled.
    score_max, cosited_max, unsure_cosited : the thresholds, and the co-sited score's band measured
        again.
    """
    img = np.asarray(image_rgb)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"chroma_check: image must be (H, W, 3) uint8 RGB, got {img.dtype} {img.shape}")
    got = _check(img, level, row_step, max_rows, min_samples, score_max, cosited_max)
    if more_rows > max_rows and (unsure[0] < got.score < unsure[1]
                                 or unsure_cosited[0] < got.score_cosited < unsure_cosited[1]):
        got = _check(img, level, row_step, more_rows, min_samples, score_max, cosited_max)
    return got


def _check(img, level, row_step, max_rows, min_samples, score_max, cosited_max) -> ChromaCheck:
    H, W = img.shape[:2]
    if W < 4 * WINDOW:
        return ChromaCheck(float("nan"), False, 0)
    cand = np.arange(0, H, max(int(row_step), 1))
    sub = img[cand]
    striped = np.maximum(sub[..., 1], sub[..., 2]) >= level
    rows = cand[striped.any(axis=1)]
    if rows.size > max_rows:
        rows = rows[np.linspace(0, rows.size - 1, max_rows).round().astype(np.int64)]
    if rows.size == 0:
        return ChromaCheck(float("nan"), False, 0)
    from .kernels import chroma_window_moments

    sums, count = chroma_window_moments(img, rows.astype(np.int64), int(level), WINDOW)
    n = 0
    covs = []
    for phase in (0, 1):
        cnt = int(count[phase])
        if 4 * cnt < min_samples:
            return ChromaCheck(float("nan"), False, n + 2 * cnt)
        covs.append(sums[phase] / (2 * cnt))
        n += 2 * cnt
    if not max(c[-1, -1] for c in covs) > 1e-6:   # flat colour: nothing to tell the phases apart
        return ChromaCheck(float("nan"), False, n)
    # the smallest eigenvalues: a channel upsampled by 2 has more vanishing directions in one start
    # phase than in the other: in windows of 10 pixels for filters centred between the samples (JPEG
    # decoders, OpenCV's YUYV conversion, resizing), of 9 for samples co-sited with the even columns
    score, cosited = (_parity_score(np.stack([c[:size, :size] for c in covs])) for size in (WINDOW, WINDOW - 1))
    return ChromaCheck(score, bool(score < score_max or cosited < cosited_max), n, cosited)


def _parity_score(covs: np.ndarray) -> float:
    # the lowest smaller / larger ratio of the two start parities' smallest eigenvalues (2, L, L)
    ev = np.linalg.eigvalsh(covs)
    lo, hi = np.maximum(ev.min(axis=0), 0.0), ev.max(axis=0)
    k = covs.shape[1] // 2 + 1
    return float(np.min(lo[:k] / np.maximum(hi[:k], 1e-12 * hi[-1])))
