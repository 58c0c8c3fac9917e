"""One camera frame of the green-blue stripe pattern -> a :class:`StripeMap` (the decoder).

Pipeline (each step a named function; the paper's steps 1-4, then beyond the paper):

1. :func:`motion_blur` -- directional Gaussian along the stripe direction (paper's "motion
   blurring"): averages noise and texture along stripes without smearing across them.
2. :func:`colour_balance` -- ``c_i = C_i / mean_window(C_i)`` for green and blue (red ignored).
3. :func:`classify` -- green / blue by ``d = (g - b)/(g + b)`` against its local mean (paper's local
   thresholding; ``threshold="global"`` compares with 0), cyan markers where both channels are
   near their local maxima; "none" for dark (shadow), saturated and low-contrast pixels.
4. :func:`gbscan.unwrap.unwrap` -- the paper's seven unwrapping steps (relative stripe index per
   connected region).
5. :func:`gbscan.unwrap.index_regions` -- absolute index per region from the cyan markers.
6. :func:`subpixel_boundaries` + column interpolation -- stripe boundaries to a fraction of a
   camera pixel, then each pixel's continuous projector column.

Conventions: image ``(H, W, 3)`` RGB, arrays indexed ``[v, u]``, pixel centres at integers,
projector columns in projector px with boundary ``k`` at ``k * stripe_px - 0.5``.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from .errors import GBError
from .pattern import PatternSpec
from .unwrap import UnwrapParams

#: Mask reason codes (``StripeMap.mask``); 0 means the pixel is reported.
OK, DARK, SATURATED, LOW_CONTRAST, ISOLATED, INCONSISTENT, UNINDEXED, NO_BOUNDARY = range(8)
REASONS = {
    OK: "ok",
    DARK: "dark",                   # no signal: shadow, background, too little light
    SATURATED: "saturated",         # a colour channel clipped: the boundary position is unreliable
    LOW_CONTRAST: "low_contrast",   # ambiguous colour: no clear green/blue modulation
    ISOLATED: "isolated",           # not linked to a region / region too small
    INCONSISTENT: "inconsistent",   # disagrees with its vertical neighbours (step 7)
    UNINDEXED: "unindexed",         # region whose absolute index is not certain
    NO_BOUNDARY: "no_boundary",     # not enclosed by located boundaries (segment end, image border)
}


@dataclass(frozen=True)
class DecodeParams:
    """Decoder parameters (px are camera pixels).

    blur_sigma_along_px, blur_sigma_across_px : Gaussian sigma along / across the stripes.
    stripe_angle_deg : stripe direction in the image, 0 = vertical (fast separable path).
    balance_window_px : colour-balance window (odd int); 0/None = whole image (uniform objects).
    threshold : "local" (d against its local mean) or "global" (d against 0).
    threshold_window_px : window of the local mean of d (should span >= 2 stripe periods).
    norm_window_px : horizontal window of the local min/max used for contrast, cyan and the
        sub-pixel signals (should span two stripe periods).
    camera_gamma : the camera's encoding gamma; pixel values are linearised as
        ``255 (v/255)**camera_gamma`` first (1 = linear camera), so that boundary midpoints,
        crosstalk and colour balance are physical (sRGB-like cameras: 2.2).
    dark_level : a pixel whose local (max - min) modulation in both channels is below this
        (linear DN) is dark.
    saturation_level : raw green or blue at or above this (DN) is saturated.
    min_contrast : minimum local (max - min) / max of each channel.
    cyan_level : both normalised channels above this -> cyan marker.
    min_level : a pixel whose normalised green and blue are both below this is dark (the unlit
        side of a shadow or of the pattern's border).
    raw_margin : a pixel whose unblurred normalised green - blue contradicts its (blurred) colour
        class by more than this is ambiguous (colour carried across a horizontal edge by the blur).
    extrapolate : pixels beyond a segment's last boundary get a column up to this many
        stripe widths away (0: only pixels between two boundaries).
    unwrap : parameters of the unwrapping and absolute indexing.
    """

    blur_sigma_along_px: float = 2.0
    blur_sigma_across_px: float = 0.0
    stripe_angle_deg: float = 0.0
    balance_window_px: int | None = None
    threshold: str = "local"
    threshold_window_px: int = 15
    norm_window_px: int = 15
    camera_gamma: float = 2.2
    dark_level: float = 2.0
    saturation_level: int = 250
    min_contrast: float = 0.25
    cyan_level: float = 0.6
    min_level: float = 0.35
    raw_margin: float = 0.3
    extrapolate: float = 0.75
    unwrap: UnwrapParams = field(default_factory=UnwrapParams)

    def __post_init__(self):
        def bad(name, why):
            raise GBError(f"DecodeParams.{name}: {why}")

        if not (self.blur_sigma_along_px >= 0 and self.blur_sigma_across_px >= 0):
            bad("blur_sigma_*_px", "sigmas must be >= 0")
        if not math.isfinite(self.stripe_angle_deg) or abs(self.stripe_angle_deg) > 45:
            bad("stripe_angle_deg", f"must be within [-45, 45] degrees of vertical, got {self.stripe_angle_deg}")
        if self.balance_window_px not in (None, 0) and int(self.balance_window_px) < 3:
            bad("balance_window_px", "must be 0/None (whole image) or >= 3")
        if self.threshold not in ("local", "global"):
            bad("threshold", f"must be 'local' or 'global', got {self.threshold!r}")
        if int(self.threshold_window_px) < 3 or int(self.norm_window_px) < 3:
            bad("threshold_window_px/norm_window_px", "must be >= 3")
        if not 0.2 <= float(self.camera_gamma) <= 5:
            bad("camera_gamma", f"must be in [0.2, 5], got {self.camera_gamma}")
        if not 0 <= self.min_contrast < 1 or not 0.5 < self.cyan_level < 1:
            bad("min_contrast/cyan_level", "min_contrast in [0, 1), cyan_level in (0.5, 1)")
        if not isinstance(self.unwrap, UnwrapParams):
            bad("unwrap", "must be an UnwrapParams")

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class StripeMap:
    """Decoder output for one frame (H, W = camera image size).

    column : (H, W) float32 continuous projector column (px), NaN where not reported.
    stripe : (H, W) int32 absolute stripe index of the pixel's colour run, -1 where not reported.
    confidence : (H, W) float32 in [0, 1], 0 where not reported.
    mask : (H, W) uint8 reason code, 0 = reported (see ``REASONS``).
    relative : (H, W) int32 relative stripe index (consistent within ``region``; also for
        unindexed regions, e.g. with the pure pattern).
    region : (H, W) int32 region id (-1 none).
    column_relative : (H, W) float32 projector column from the *relative* index (correct up to
        one multiple of ``2 * stripe_px`` per region; NaN outside regions).  For the pure pattern
        or priors from elsewhere (e.g. the previous frame).
    labels : (H, W) uint8 colour class (NONE/GREEN/BLUE/CYAN).
    stats : counts per reason, regions found/indexed/dropped, per-stage milliseconds.
    stages : intermediate images (only when ``decode(..., keep_stages=True)``).
    """

    column: np.ndarray
    stripe: np.ndarray
    confidence: np.ndarray
    mask: np.ndarray
    relative: np.ndarray
    region: np.ndarray
    labels: np.ndarray
    stats: dict
    pattern: PatternSpec
    stages: dict | None = None
    column_relative: np.ndarray | None = None

    @property
    def valid(self) -> np.ndarray:
        """(H, W) bool, pixels reported (``mask == 0``)."""
        return self.mask == OK

    def arrays(self) -> dict:
        """The arrays and metadata written to ``stripes.npz``."""
        return {
            "column": self.column, "stripe": self.stripe, "confidence": self.confidence, "mask": self.mask,
            "relative": self.relative, "region": self.region, "labels": self.labels,
            "reasons": np.array([f"{k}:{v}" for k, v in REASONS.items()]),
            "pattern": np.array(json.dumps(self.pattern.to_dict())),
            "stats": np.array(json.dumps(self.stats, default=_json_default)),
        }


def _json_default(x):
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    return str(x)


# -- input --------------------------------------------------------------------------------------
def validate_image(image) -> np.ndarray:
    """Check a camera frame; return it as (H, W, 3) uint8 RGB.

    Accepts uint8, uint16 (scaled to 8 bits) and float in [0, 1] (finite).  Raises GBError for
    grey/2-D or non-3-channel images, other dtypes, NaN/inf and images smaller than 8x8.
    """
    if not isinstance(image, np.ndarray):
        raise GBError(f"decode: image must be a numpy array, got {type(image).__name__}")
    if image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 1):
        raise GBError(f"decode: image is grey {image.shape}; the green-blue decoder needs an RGB colour image")
    if image.ndim != 3 or image.shape[2] not in (3, 4):
        raise GBError(f"decode: image must be (H, W, 3) RGB, got shape {image.shape}")
    if image.shape[0] < 8 or image.shape[1] < 8:
        raise GBError(f"decode: image {image.shape[1]}x{image.shape[0]} is too small (need >= 8x8)")
    img = image[:, :, :3]
    if img.dtype == np.uint8:
        return np.ascontiguousarray(img)
    if img.dtype == np.uint16:
        return np.ascontiguousarray((img >> 8).astype(np.uint8))
    if np.issubdtype(img.dtype, np.floating):
        if not np.isfinite(img).all():
            raise GBError("decode: image holds NaN or infinite values; pass a finite image (uint8 RGB preferred)")
        lo, hi = float(img.min()), float(img.max())
        if lo < 0 or hi > 1:
            raise GBError(f"decode: float image values must lie in [0, 1], got [{lo:g}, {hi:g}]; "
                          "pass uint8 RGB or scale to [0, 1]")
        return np.ascontiguousarray(np.round(img * 255.0).astype(np.uint8))
    raise GBError(f"decode: image dtype {img.dtype} is not supported; expected uint8 RGB (or uint16, float in [0, 1])")


def linearize(image_rgb: np.ndarray, camera_gamma: float = 2.2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(H, W, 3) uint8 RGB -> linear green, blue (H, W) float32 (0..255 scale) and the raw
    (H, W) uint8 max of green and blue (for the saturation test).  Red is not used."""
    import cv2

    _, g8, b8 = cv2.split(image_rgb)
    lut = (255.0 * (np.arange(256) / 255.0) ** float(camera_gamma)).astype(np.float32)
    return cv2.LUT(g8, lut), cv2.LUT(b8, lut), cv2.max(g8, b8)


# -- step 1: motion blurring --------------------------------------------------------------------
def _gauss1d(sigma: float) -> np.ndarray:
    if sigma <= 0:
        return np.ones(1, np.float32)
    r = max(1, int(math.ceil(3.0 * sigma)))
    x = np.arange(-r, r + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    return (k / k.sum()).astype(np.float32)


def motion_kernel(sigma_along_px: float, sigma_across_px: float, angle_deg: float) -> np.ndarray:
    """2-D anisotropic Gaussian kernel (odd square, sums to 1), long axis along the stripes.

    ``angle_deg`` is the stripe direction measured from the image's vertical axis (positive
    = clockwise on screen: the stripe's lower end moves to +u).  ``sigma_across_px = 0`` gives
    a kernel one sample wide across (sampled on the rotated line with bilinear weights).
    """
    a = math.radians(angle_deg)
    along = np.array([math.sin(a), math.cos(a)])   # (du, dv) unit vector along the stripe
    across = np.array([math.cos(a), -math.sin(a)])
    r = max(1, int(math.ceil(3.0 * max(sigma_along_px, sigma_across_px, 0.5))))
    v, u = np.mgrid[-r:r + 1, -r:r + 1].astype(np.float64)
    s_al = (u * along[0] + v * along[1])
    s_ac = (u * across[0] + v * across[1])
    sa = max(sigma_along_px, 1e-6)
    if sigma_across_px > 0:
        k = np.exp(-0.5 * (s_al / sa) ** 2 - 0.5 * (s_ac / sigma_across_px) ** 2)
    else:  # a line: triangle (bilinear) weight across, Gaussian along
        k = np.exp(-0.5 * (s_al / sa) ** 2) * np.clip(1.0 - np.abs(s_ac), 0.0, None)
    return (k / k.sum()).astype(np.float32)


def motion_blur(channels: np.ndarray, sigma_along_px: float = 2.0, sigma_across_px: float = 0.0,
                angle_deg: float = 0.0) -> np.ndarray:
    """Paper step 1, *motion blurring*: Gaussian along the stripe direction.

    channels : (H, W) or (H, W, C) float32.  Vertical stripes (``angle_deg == 0``) use the
    separable path (``cv2.sepFilter2D``); other angles the rotated anisotropic kernel
    (``cv2.filter2D``).  Borders are reflected.  Returns float32 of the same shape.
    """
    import cv2

    x = np.ascontiguousarray(channels, dtype=np.float32)
    if sigma_along_px <= 0 and sigma_across_px <= 0:
        return x
    if abs(angle_deg) < 1e-9:
        kx = _gauss1d(sigma_across_px)
        ky = _gauss1d(sigma_along_px)
        return cv2.sepFilter2D(x, cv2.CV_32F, kx, ky, borderType=cv2.BORDER_REFLECT_101)
    k = motion_kernel(sigma_along_px, sigma_across_px, angle_deg)
    return cv2.filter2D(x, cv2.CV_32F, k, borderType=cv2.BORDER_REFLECT_101)


# -- step 2: colour balancing -------------------------------------------------------------------
def colour_balance(planes, window_px: int | None = None, floor: float = 0.5) -> list[np.ndarray]:
    """Paper step 2, *colour balancing*: ``c_i = C_i / mean_window(C_i)`` per channel.

    planes : sequence of (H, W) float32 channels (here linear green and blue; red is not used).
    ``window_px`` 0/None: the mean over the whole image's lit pixels (uniform objects); an odd
    int: a local box mean (``cv2.blur``), for objects whose colour varies (faces).  Means below
    ``floor`` (dark windows) are clamped to ``floor`` so shadows do not explode.
    Returns a list of float32 planes, ~1 on average.
    """
    import cv2

    planes = [np.asarray(x, dtype=np.float32) for x in planes]
    if not window_px:
        bright = planes[0]
        for x in planes[1:]:
            bright = cv2.max(bright, x)
        # the means from every 4th pixel in both directions (plenty for a global mean)
        sub = [np.ascontiguousarray(x[::4, ::4]) for x in planes]
        lit = cv2.compare(bright[::4, ::4], 4.0 * floor, cv2.CMP_GT)
        if cv2.countNonZero(lit) < 16:
            lit = None
        return [x * np.float32(1.0 / max(cv2.mean(xs, mask=lit)[0], floor)) for x, xs in zip(planes, sub)]
    w = int(window_px) | 1
    return [x / np.maximum(cv2.blur(x, (w, w), borderType=cv2.BORDER_REFLECT_101), np.float32(floor))
            for x in planes]


# -- step 3: thresholding -----------------------------------------------------------------------
@dataclass
class Classified:
    """Result of :func:`classify` (all (H, W)).

    labels : uint8 NONE/GREEN/BLUE/CYAN.  reason : uint8 OK/DARK/SATURATED/LOW_CONTRAST.
    d : float32 (g - b)/(g + b) of the balanced channels.  thr : float32 its threshold.
    gn, bn : float32 channels normalised to [0, 1] between their local min and max (sub-pixel).
    contrast : float32 min over the two channels of (local max - local min) / local max.
    """

    labels: np.ndarray
    reason: np.ndarray
    d: np.ndarray
    thr: np.ndarray
    gn: np.ndarray
    bn: np.ndarray
    contrast: np.ndarray


def local_minmax(x: np.ndarray, window_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal running min and max of (H, W) float32 over ``window_px`` (odd), then smoothed
    by a box of the same width so they vary smoothly across stripes."""
    import cv2

    w = int(window_px) | 1
    k = np.ones((1, w), np.uint8)
    lo = cv2.erode(x, k, borderType=cv2.BORDER_REPLICATE)
    hi = cv2.dilate(x, k, borderType=cv2.BORDER_REPLICATE)
    lo = cv2.blur(lo, (w, 1), borderType=cv2.BORDER_REPLICATE)
    hi = cv2.blur(hi, (w, 1), borderType=cv2.BORDER_REPLICATE)
    return lo, hi


def classify(blurred, balanced, raw, raw_max: np.ndarray, params: DecodeParams) -> Classified:
    """Paper step 3, *thresholding* into green / blue / cyan / none.

    blurred : (g, b) (H, W) float32 linear channels after motion blur.  balanced : the same after
    colour balancing.  raw : (g, b) linear channels before blurring.  raw_max : (H, W)
    uint8 max of the raw encoded green and blue (saturation test).
    Green/blue: ``d = (g - b)/(g + b)`` of the balanced channels against its local box mean
    (``threshold="local"``) or 0 (``"global"``).  Cyan (beyond the paper): both channels above
    ``cyan_level`` of their local range.  None: saturated; dark (local modulation below
    ``dark_level``, the pixel far below the local stripe level, or a row that is dark before
    blurring -- vertical blur leaks light into shadowed rows); low contrast (a channel's local
    modulation below ``min_contrast`` of its maximum, or the unblurred pixel clearly shows the
    other colour: blurring along the stripes must not carry a colour across a horizontal depth
    edge or shadow edge onto another surface).
    """
    import cv2

    from . import kernels

    g, b = balanced
    d = cv2.divide(cv2.subtract(g, b), cv2.max(cv2.add(g, b), 1e-6))
    if params.threshold == "local":
        w = int(params.threshold_window_px) | 1
        thr = cv2.blur(d, (w, w), borderType=cv2.BORDER_REFLECT_101)
    else:
        thr = np.zeros_like(d)
    lo_g, hi_g = local_minmax(blurred[0], params.norm_window_px)
    lo_b, hi_b = local_minmax(blurred[1], params.norm_window_px)
    w = int(params.norm_window_px) | 1
    raw_hi = cv2.dilate(cv2.max(raw[0], raw[1]), np.ones((1, w), np.uint8), borderType=cv2.BORDER_REPLICATE)
    labels, reason, gn, bn, contrast = kernels.classify_pixels(
        blurred[0], blurred[1], d, thr, lo_g, hi_g, lo_b, hi_b, raw[0], raw[1], raw_hi, raw_max,
        np.float32(params.cyan_level), np.float32(params.min_level), np.float32(params.raw_margin),
        np.float32(params.min_contrast), np.float32(params.dark_level), int(params.saturation_level))
    return Classified(labels, reason, d, thr, gn, bn, contrast)


# -- sub-pixel boundaries -----------------------------------------------------------------------
def subpixel_boundaries(cls: Classified, segs) -> np.ndarray:
    """Sub-pixel camera position ``u`` of every junction (stripe boundary) of ``segs``.

    Crossing of the changing channel(s), normalised between local min and max: ``gn = bn`` for
    green|blue, ``bn = 1/2`` for green|cyan, ``gn = 1/2`` for blue|cyan; linear interpolation
    between the two bracketing samples.  Returns (n_junctions,) float32, NaN where not found.
    """
    from . import kernels

    j_row = segs.row[segs.j_seg] if segs.j_seg.size else np.zeros(0, np.int32)
    return kernels.subpixel_junctions(cls.gn, cls.bn, j_row.astype(np.int32), segs.j_ua, segs.j_ub, segs.j_la,
                                      segs.j_lb, segs.u0, segs.u1, segs.j_seg)


# -- everything ---------------------------------------------------------------------------------
def empty_stripemap(shape, pattern: PatternSpec, reason: int, why: str, stats: dict | None = None) -> StripeMap:
    """A StripeMap reporting nothing, every pixel masked with ``reason``; ``stats['why']`` says why."""
    H, W = shape
    st = dict(stats or {})
    st.update(_count_reasons(np.full((H, W), reason, np.uint8)))
    st["why"] = why
    return StripeMap(np.full((H, W), np.nan, np.float32), np.full((H, W), -1, np.int32),
                     np.zeros((H, W), np.float32), np.full((H, W), reason, np.uint8),
                     np.zeros((H, W), np.int32), np.full((H, W), -1, np.int32), np.zeros((H, W), np.uint8), st,
                     pattern)


def cv2_max(a: np.ndarray, b: np.ndarray) -> float:
    """Largest value of two same-shape arrays (OpenCV's fast reductions)."""
    import cv2

    return max(cv2.minMaxLoc(a)[1], cv2.minMaxLoc(b)[1])


def _count_reasons(mask: np.ndarray) -> dict:
    from . import kernels

    counts = kernels.count_codes(np.ascontiguousarray(mask, dtype=np.uint8), len(REASONS))
    return {"pixels": int(mask.size), "reported": int(counts[OK]),
            "reasons": {REASONS[k]: int(counts[k]) for k in REASONS}}


def decode(image_rgb, pattern: PatternSpec, params: DecodeParams = DecodeParams(), *,
           keep_stages: bool = False) -> StripeMap:
    """Decode one camera frame of the green-blue stripe pattern.

    image_rgb : (H, W, 3) uint8 RGB (uint16 and float in [0, 1] are converted).
    pattern : the projected pattern (stripe width, markers).
    params : :class:`DecodeParams`.
    keep_stages : also return the intermediate images in ``StripeMap.stages`` (previews).

    Returns a :class:`StripeMap`.  Raises GBError for unusable input (grey image, bad dtype,
    NaN); an image without a usable stripe signal gives an empty StripeMap whose ``stats['why']``
    says why.
    """
    from . import kernels
    from . import unwrap as uw

    if not isinstance(pattern, PatternSpec):
        raise GBError(f"decode: pattern must be a gbscan.pattern.PatternSpec, got {type(pattern).__name__}")
    if not isinstance(params, DecodeParams):
        raise GBError(f"decode: params must be a DecodeParams, got {type(params).__name__}")
    ms: dict[str, float] = {}
    t0 = time.perf_counter()
    img = validate_image(image_rgb)
    H, W = img.shape[:2]
    g_lin, b_lin, raw_max = linearize(img, params.camera_gamma)
    t = time.perf_counter()
    ms["input"] = (t - t0) * 1e3
    if int(raw_max.max()) == 0 or float(cv2_max(g_lin, b_lin)) < params.dark_level:
        return empty_stripemap((H, W), pattern, DARK, "image is dark: no projected light seen "
                               f"(green/blue never reach dark_level={params.dark_level:g} linear DN)", {"ms": ms})

    blurred = [motion_blur(x, params.blur_sigma_along_px, params.blur_sigma_across_px, params.stripe_angle_deg)
               for x in (g_lin, b_lin)]
    t1 = time.perf_counter()
    ms["blur"] = (t1 - t) * 1e3
    balanced = colour_balance(blurred, params.balance_window_px)
    t2 = time.perf_counter()
    ms["balance"] = (t2 - t1) * 1e3
    import cv2

    cls = classify(blurred, balanced, (g_lin, b_lin), raw_max, params)
    t3 = time.perf_counter()
    ms["classify"] = (t3 - t2) * 1e3
    if cv2.countNonZero(cls.labels) == 0:
        why = ("image is saturated" if (cls.reason == SATURATED).mean() > 0.5 else
               "no stripes found: no pixel shows green/blue modulation (uniform colour, out of focus, or no pattern)")
        sm = empty_stripemap((H, W), pattern, LOW_CONTRAST, why, {"ms": ms})
        sm.mask[:] = cls.reason
        sm.mask[sm.mask == OK] = LOW_CONTRAST
        sm.stats.update(_count_reasons(sm.mask))
        return sm

    un = uw.unwrap(cls.labels, params.unwrap, locate=lambda sg: subpixel_boundaries(cls, sg))
    t4 = time.perf_counter()
    ms["unwrap"] = (t4 - t3) * 1e3
    n_reg = int(un.region_px.size)
    idx = uw.index_regions(cls.labels, un.relative, un.region, n_reg, pattern, params.unwrap)
    t5 = time.perf_counter()
    ms["index"] = (t5 - t4) * 1e3

    segs = un.segments
    jx = segs.j_x if segs.j_x is not None else subpixel_boundaries(cls, segs)
    seg_reg = un.seg_region
    # relative columns for every region (consistent inside it; unknown multiple of 2*stripe_px)
    j_bnd = (segs.j_rel.astype(np.int64) + un.seg_P[segs.j_seg]).astype(np.float64) if segs.j_seg.size else \
        np.zeros(0, np.float64)
    column_rel = kernels.interpolate_columns(H, W, segs.row, segs.u0, segs.u1, segs.j0, segs.j1,
                                             (seg_reg >= 0).astype(np.uint8), jx.astype(np.float64), j_bnd,
                                             float(pattern.stripe_px), float(params.extrapolate))
    t6 = time.perf_counter()
    ms["subpixel"] = (t6 - t5) * 1e3

    # -- masks, stripe, confidence
    nr = max(n_reg, 1)
    reg_indexed = np.zeros(nr, bool)
    reg_margin = np.ones(nr, np.float32)
    reg_shift = np.zeros(nr, np.int64)
    if n_reg:
        reg_indexed[:] = idx.indexed
        reg_shift[:] = idx.offset
        if pattern.markers:
            reg_margin[:] = np.clip((idx.runner_up - idx.mismatch) / np.maximum(idx.evidence, 1), 0, 1)
    mask, column, stripe, conf, region = kernels.finish_pixels(
        cls.reason, cls.labels, un.region, un.relative, column_rel, un.inconsistent, reg_shift, reg_indexed,
        reg_margin, cls.contrast, int(pattern.stripe_px), int(pattern.n_stripes), float(params.min_contrast))
    t7 = time.perf_counter()
    ms["finish"] = (t7 - t6) * 1e3
    ms["total"] = (t7 - t0) * 1e3

    stats = _count_reasons(mask)
    stats.update(un.stats)
    stats["regions_indexed"] = int(idx.indexed.sum())
    stats["regions_unindexed"] = int(n_reg - idx.indexed.sum())
    stats["region_why"] = {k: int(v) for k, v in zip(*np.unique(np.array(idx.why, dtype=object).astype(str),
                                                                  return_counts=True))} if n_reg else {}
    stats["boundaries"] = int(np.isfinite(jx).sum())
    stats["ms"] = {k: round(v, 3) for k, v in ms.items()}
    if not pattern.markers:
        stats["why"] = "pure pattern (no markers): relative stripe index only, see StripeMap.relative/region"
    stages = None
    if keep_stages:
        stages = {"blurred": np.dstack(blurred), "balanced": np.dstack(balanced), "d": cls.d, "threshold": cls.thr,
                  "labels": cls.labels, "gn": cls.gn, "bn": cls.bn, "contrast": cls.contrast, "relative": un.relative, "region": un.region,
                  "believable": np.where(segs.seg >= 0, un.believable[np.maximum(segs.seg, 0)], False),
                  "index": idx}
    column_rel = np.where(region >= 0, column_rel, np.nan).astype(np.float32)
    return StripeMap(column, stripe, conf, mask, un.relative, region, cls.labels, stats, pattern, stages,
                     column_rel)
