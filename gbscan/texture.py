"""A stripe-free grey texture of a scan, from its own single striped frame.

There is no second, uniformly lit frame in single-shot scanning, but the striped one holds the
surface's brightness all the same: after colour balancing, green light read in the green channel
and blue light read in the blue channel are on one scale, so on a pixel lit by the green-blue
pattern ``g / s_g + b / s_b`` (linear channels over their means on the decoded pixels) is the
same whether the pixel sits on a green stripe, a blue one or the blurred boundary between them.
Two things still print the pattern on it:

* the cyan markers light both channels: twice the light of a green or blue stripe.  The decoder
  gives each pixel its projector column, so the pattern's light there (1 for green or blue, 2 for
  cyan: :func:`pattern_light`) is known and divided out;
* a coloured surface reflects green and blue differently, so the stripes come back as a ripple.
  A box along the row over one stripe period (two stripes, :func:`stripe_period_px`: from the
  decoded columns) averages it out.

Both sums run over decoded pixels only (a normalised box filter), so the texture does not bleed
across holes.  The result is the surface's *relative* reflected intensity under the pattern's
green and blue light (illumination fall-off and shading included, as any camera image), scaled
so that the average decoded pixel is 1.  Red albedo is not seen (the pattern has no red).

Measured against the same scene rendered under a uniform cyan frame (``tests/test_texture.py``,
typical preset): median relative error 2.7 %, 95th percentile 10 %, correlation 0.994 on the
simulated face; 1.4 % / 4.4 % on a tilted plane of green-ish albedo (clean preset).

Conventions as in :mod:`gbscan.decode`: image (H, W, 3) uint8 RGB; column (H, W) continuous
projector column (projector px, pixel centres at integers); stripe ``k`` covers projector columns
``k*w .. k*w + w - 1``.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from .errors import GBError
from .pattern import BLUE, CYAN, GREEN, PatternSpec

#: Widest box (camera px) :func:`intensity` averages over along a row.
MAX_WINDOW_PX = 31
#: Default blur (projector px) of the pattern's light per column (:func:`intensity`): on a tilted
#: plane (paper rig) against a uniform cyan frame, the relative error's 95th percentile is 5.4 /
#: 4.1 / 5.3 % at 0 / 1 / 2 px (clean preset), 6.7 / 5.0 / 5.2 % (typical).
LIGHT_BLUR_PX = 1.0


def pattern_light(pattern: PatternSpec, blur_px: float = 0.0) -> np.ndarray:
    """(pattern.width,) float32: channels the projector lights at each of its columns (green or
    blue stripe 1, cyan marker 2, black 0), blurred by a Gaussian of ``blur_px`` projector px
    (0: none)."""
    import cv2

    lab = pattern.column_labels()
    light = np.isin(lab, (GREEN, CYAN)).astype(np.float32) + np.isin(lab, (BLUE, CYAN)).astype(np.float32)
    if blur_px > 0:
        light = cv2.GaussianBlur(light[None, :], (0, 0), float(blur_px), borderType=cv2.BORDER_REPLICATE)[0]
    return light


def stripe_period_px(column: np.ndarray, valid: np.ndarray, stripe_px: float) -> float:
    """Camera pixels per stripe period (two stripes) along a row: ``2 stripe_px`` over the median
    of ``|column[v, u + 1] - column[v, u]|`` where both pixels are decoded.  NaN with fewer than
    10 such pairs.  column : (H, W) projector px; valid : (H, W) bool."""
    column, valid = column[::2], valid[::2]   # every other row is plenty for a median
    both = valid[:, 1:] & valid[:, :-1]
    if np.count_nonzero(both) < 10:
        return float("nan")
    d = np.abs(np.subtract(column[:, 1:], column[:, :-1], dtype=np.float32)[both])
    d = d[np.isfinite(d) & (d > 0)]
    if d.size < 10:
        return float("nan")
    return float(2.0 * stripe_px / np.median(d))


def intensity(image_rgb: np.ndarray, column: np.ndarray, valid: np.ndarray, pattern: PatternSpec, *,
              camera_gamma: float = 2.2, window_px: int | None = None,
              light_blur_px: float = LIGHT_BLUR_PX) -> np.ndarray:
    """The stripe-free relative intensity (H, W) float32 of the decoded pixels, NaN elsewhere.

    image_rgb : (H, W, 3) uint8 RGB, the striped frame the columns were decoded from.
    column : (H, W) float projector column per pixel (``StripeMap.column``); valid : (H, W) bool
        pixels to use (``StripeMap.valid``, or the scan's kept pixels).
    pattern : the projected :class:`gbscan.pattern.PatternSpec`.
    camera_gamma : the camera's encoding gamma (``DecodeParams.camera_gamma``).
    window_px : box width along the row (camera px, made odd); default one stripe period
        (:func:`stripe_period_px`), 7 if it cannot be measured, at most ``MAX_WINDOW_PX``.
    light_blur_px : the pattern's light per column is blurred by this much (projector px) before
        it is divided out (:func:`pattern_light`): a pixel integrates over ~2 projector columns at
        the paper's geometry, and the projector is defocused, so a marker's edge is soft.
    """
    import cv2

    from .decode import gamma_lut

    img = np.asarray(image_rgb)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise GBError(f"texture: image must be (H, W, 3) uint8 RGB, got {img.shape} {img.dtype}")
    H, W = img.shape[:2]
    column = np.asarray(column)
    valid = np.asarray(valid, dtype=bool)
    if column.shape != (H, W) or valid.shape != (H, W):
        raise GBError(f"texture: column {column.shape} and valid {valid.shape} must be the image's {(H, W)}")
    if not float(camera_gamma) > 0 or not float(light_blur_px) >= 0:
        raise GBError(f"texture: camera_gamma must be > 0 and light_blur_px >= 0, got {camera_gamma}, {light_blur_px}")
    out = np.full((H, W), np.nan, np.float32)
    light = pattern_light(pattern, float(light_blur_px))
    use = valid & np.isfinite(column)
    k = np.rint(np.where(use, column, 0)).astype(np.int64)
    use &= (k >= 0) & (k < light.size)
    if not use.any():
        return out
    lut = gamma_lut(camera_gamma)
    g = cv2.LUT(np.ascontiguousarray(img[..., 1]), lut)
    b = cv2.LUT(np.ascontiguousarray(img[..., 2]), lut)
    sg, sb = float(g[use].mean()), float(b[use].mean())
    if not (sg > 0 and sb > 0):
        return out
    s = cv2.addWeighted(g, 1.0 / sg, b, 1.0 / sb, 0.0)
    s[~use] = 0
    e = np.zeros((H, W), np.float32)
    e[use] = light[k[use]]
    if window_px is None:
        period = stripe_period_px(column, use, float(pattern.stripe_px))
        window_px = 7 if not np.isfinite(period) else int(round(period))
    window_px = int(window_px)
    if window_px < 1:
        raise GBError(f"texture: window_px must be >= 1, got {window_px}")
    window_px = min(window_px | 1, MAX_WINDOW_PX)
    if window_px > 1:
        num = cv2.boxFilter(s, -1, (window_px, 1), normalize=False, borderType=cv2.BORDER_CONSTANT)
        den = cv2.boxFilter(e, -1, (window_px, 1), normalize=False, borderType=cv2.BORDER_CONSTANT)
    else:
        num, den = s, e
    ok = use & (den > 0)
    t = num[ok] / den[ok]
    out[ok] = t / np.float32(t.mean())   # 1 = the average decoded pixel
    return out


def to_grey(texture: np.ndarray, *, white: float | None = None, gamma: float = 2.2) -> np.ndarray:
    """Display grey levels (H, W) uint8 of :func:`intensity`: ``255 (t / white) ** (1 / gamma)``,
    clipped, with ``t / white`` rounded to 1/65535 (a table look-up); 0 where NaN.  white : the
    intensity shown as 255 (default the 99.5th percentile of the finite values, every fourth of
    them, so that a few specular pixels do not darken the rest)."""
    t = np.asarray(texture, dtype=np.float32)
    if white is None:
        fin = t[np.isfinite(t)]
        white = float(np.percentile(fin[::4], 99.5)) if fin.size else 1.0
    if not white > 0:
        white = 1.0
    lut = _grey_lut(float(gamma))
    x = np.nan_to_num(t, nan=0.0, posinf=float(white), neginf=0.0) * np.float32(65535.0 / white)
    np.clip(x, 0, 65535, out=x)
    return lut[np.rint(x).astype(np.uint16)]


@lru_cache(maxsize=4)
def _grey_lut(gamma: float) -> np.ndarray:
    """(65536,) uint8: ``rint(255 (i / 65535) ** (1 / gamma))``."""
    return np.rint(255.0 * (np.arange(65536) / 65535.0) ** (1.0 / gamma)).astype(np.uint8)
