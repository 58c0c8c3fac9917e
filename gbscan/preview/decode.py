"""Pictures of the decoder's stages (PNG, RGB uint8, no matplotlib needed).

:func:`write_decode_previews` writes one picture per stage of a ``decode(..., keep_stages=True)``
result: blurred and balanced channels, colour classes, relative index, regions, absolute stripe,
final column, confidence and mask reasons.  Colour maps are small numpy look-up tables.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..pattern import BLUE, CYAN, GREEN, NONE

#: Colours of the mask reasons (by name, see gbscan.decode.REASONS).
REASON_RGB = {
    "ok": (70, 170, 90), "dark": (25, 25, 25), "saturated": (250, 250, 250), "low_contrast": (120, 120, 120),
    "isolated": (240, 110, 200), "inconsistent": (230, 40, 40), "unindexed": (230, 160, 30),
    "no_boundary": (90, 90, 200), "rim": (40, 200, 230),
}
LABEL_RGB = {NONE: (0, 0, 0), GREEN: (0, 200, 0), BLUE: (40, 70, 255), CYAN: (0, 230, 230)}


def turbo_like(x: np.ndarray, lo: float | None = None, hi: float | None = None) -> np.ndarray:
    """Map a float image (NaN = black) to RGB uint8 with a blue-green-yellow-red ramp."""
    x = np.asarray(x, dtype=np.float64)
    fin = np.isfinite(x)
    if lo is None or hi is None:
        vals = x[fin]
        lo = float(np.percentile(vals, 1)) if vals.size else 0.0
        hi = float(np.percentile(vals, 99)) if vals.size else 1.0
    t = np.clip((x - lo) / max(hi - lo, 1e-12), 0, 1)
    knots = np.array([[48, 18, 59], [40, 120, 240], [30, 210, 170], [160, 240, 60], [250, 180, 40], [200, 30, 20]],
                     np.float64)
    pos = np.where(fin, t, 0) * (len(knots) - 1)
    i = np.minimum(pos.astype(int), len(knots) - 2)
    f = (pos - i)[..., None]
    rgb = knots[i] * (1 - f) + knots[i + 1] * f
    rgb[~fin] = 0
    return rgb.astype(np.uint8)


def label_image(labels: np.ndarray) -> np.ndarray:
    lut = np.zeros((256, 3), np.uint8)
    for k, c in LABEL_RGB.items():
        lut[k] = c
    return lut[labels]


def id_colours(ids: np.ndarray) -> np.ndarray:
    """Distinct pseudo-random colours per non-negative id, black for -1."""
    ids = np.asarray(ids, dtype=np.int64)
    h = (ids * 2654435761) % (2 ** 32)
    rgb = np.stack([(h >> 8) & 255, (h >> 16) & 255, (h >> 24) & 255], -1).astype(np.uint8) | 64
    rgb[ids < 0] = 0
    return rgb


def reason_image(mask: np.ndarray) -> np.ndarray:
    from ..decode import REASONS

    lut = np.zeros((256, 3), np.uint8)
    for code, name in REASONS.items():
        lut[code] = REASON_RGB.get(name, (255, 0, 255))
    return lut[mask]


def channels_image(planes: np.ndarray) -> np.ndarray:
    """(H, W, 2) green/blue float planes -> RGB with green and blue scaled to their 99th percentile."""
    g, b = planes[..., 0], planes[..., 1]
    s = max(float(np.percentile(np.concatenate([g.ravel(), b.ravel()]), 99)), 1e-6)
    out = np.zeros(planes.shape[:2] + (3,), np.uint8)
    out[..., 1] = np.clip(255 * g / s, 0, 255)
    out[..., 2] = np.clip(255 * b / s, 0, 255)
    return out


def stage_images(image: np.ndarray, sm) -> dict[str, np.ndarray]:
    """Name -> RGB uint8 picture of each stage (needs ``sm.stages``)."""
    st = sm.stages or {}
    out = {"0_input": np.asarray(image, np.uint8)}
    if "blurred" in st:
        out["1_blurred"] = channels_image(st["blurred"])
        out["2_balanced"] = channels_image(st["balanced"])
    out["3_classified"] = label_image(sm.labels)
    rel = np.where(sm.region >= 0, sm.relative, np.nan).astype(np.float64)
    out["4_relative"] = turbo_like(rel)
    out["5_regions"] = id_colours(sm.region)
    out["6_stripe"] = turbo_like(np.where(sm.stripe >= 0, sm.stripe, np.nan), 0, sm.pattern.n_stripes - 1)
    out["7_column"] = turbo_like(sm.column, 0, sm.pattern.width - 1)
    out["8_confidence"] = turbo_like(np.where(sm.valid, sm.confidence, np.nan), 0, 1)
    out["9_mask"] = reason_image(sm.mask)
    return out


def write_decode_previews(folder, image: np.ndarray, sm) -> list[Path]:
    """Write ``decode_<stage>.png`` into ``folder`` (must exist); returns the paths."""
    from ..io import write_png

    folder = Path(folder)
    paths = []
    for name, pic in stage_images(image, sm).items():
        paths.append(write_png(folder / f"decode_{name}.png", np.ascontiguousarray(pic)))
    return paths
