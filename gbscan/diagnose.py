"""What the frame itself says about the rig: measured imaging figures and what to change.

A scan that keeps 10 % of the face does not say why.  :func:`check_frame` measures, on one
decoded frame, the quantities that decide how well the stripes decode, and :func:`findings` turns
the ones outside the range of a good rig into one sentence each: the figure, what it means, what
to change at the rig (exposure, ambient light, projector focus, colour settings, distance, stripe
width).  Pure functions over arrays; the commands print them (``gbscan check``; ``gbscan scan``
and ``gbscan decode`` print the warnings as ``hint:`` lines).

Measures (:class:`FrameCheck`), all over the pixels where the pattern is seen (the *stripe area*:
every pixel the decoder did not call dark or low-contrast, i.e. reported, saturated, or lost in
the unwrapping) or over its green / blue labelled pixels:

* ``stripe_snr``, ``noise_dn``, ``modulation_dn``: :func:`gbscan.kernels.stripe_snr` (the
  decoder's automatic blur uses the same figure), linear DN;
* ``peak_dn``: 95th percentile of the encoded max(green, blue) on labelled pixels (0..255): how
  much of the camera's range the stripes use;
* ``saturated_frac``: share of the stripe area at or above the decoder's saturation level;
* ``contrast``: median over labelled pixels of min over green and blue of the local
  (max - min) / max along the row (the decoder's ``min_contrast`` rule, with its window): 1 on
  an ideal rig, lowered by ambient light, colour crosstalk and projector defocus;
* ``ambient_ratio``: median linear red over the median local stripe maximum on labelled pixels.
  The projector's green and blue barely reach the red channel (crosstalk ~0.05), ambient light
  does; a red surface raises it too (skin: 0.06-0.07 in the simulator's typical preset);
* ``blue_green_ratio``: median local maximum of blue over that of green (camera and projector
  colour balance, surface colour; the colour balancing divides it out, the noise stays);
* ``stripe_camera_px``: camera pixels per projector stripe, from the decoded columns (median
  horizontal gradient; from the colour runs when nothing was decoded);
* ``window_px``: the decoder's local window (``DecodeParams.norm_window_px``; in frame pixels:
  times the factor the decoder shrank a frame of wide stripes by, ``stats['resample']``), checked
  against the stripes' width;
* ``resample``: the factor the decoder shrank the frame by (1: decoded as it is);
* ``reported_frac`` and ``lost_frac`` (per decoder reason) of the stripe area;
* ``lateral_ca_px``, ``lateral_ca_corrected``: the blue stripe edges' offset from the green ones at
  the frame's sides and whether the decoder corrected it (``stats['lateral_ca']``,
  :func:`gbscan.decode.lateral_chromatic_aberration`);
* ``chroma_score``, ``chroma_subsampled``, ``withheld``: whether the frame's colour was stored at
  half the horizontal resolution (:func:`gbscan.chroma.chroma_check`, from the decode's stats) and
  whether the decoder withheld its absolute index for it (``DecodeParams.subsampled_chroma``).

Thresholds (module constants) come from simulated frames of the plane, sphere, head, real face
and multi-object scenes (``typical`` preset and one condition changed at a time; see
``tests/test_diagnose.py`` and README "When a scan comes out thin").
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

#: stripe SNR below this: noisy stripes.  Typical preset 21-37, hard 4.3-7.5, exposure x0.2 9-17.
SNR_WARN = 12.0
#: 95th percentile of the stripes' encoded level below this (DN): dim.  Typical 134-208, exposure
#: x0.2 52-78, hard 96-142.
PEAK_DIM_DN = 90.0
#: share of the stripe area saturated above this: overexposed.  Typical 0; exposure x3: 5-58 %.
SATURATED_WARN = 0.01
#: median local stripe contrast below this: washed out.  Typical 0.84-0.90; ambient 0.3: 0.60-0.73,
#: blue 0.3: 0.68-0.77, projector defocus 3 px: 0.69-0.73, hard 0.51-0.63.
CONTRAST_WARN = 0.75
#: ambient ratio above this: ambient light.  Typical 0.03-0.07; ambient 0.3: 0.20-0.42; hard 0.25-0.56.
AMBIENT_WARN = 0.15
#: blue / green outside this range: one colour weak.  Typical 0.76-0.99 (skin reflects less
#: blue); projector blue at 0.3: 0.23-0.33; hard 0.42-0.56.
BLUE_GREEN_RANGE = (0.5, 2.0)
#: camera px per stripe below this: the stripes alias (docs/method.md "Stripe width"); above the second:
#: a narrower pattern would put more boundaries on the surface.  Paper rig at 650 mm: 3.5-4.7.
STRIPE_PX_RANGE = (2.5, 12.0)
#: shares of the stripe area lost as isolated / unindexed above these.  Typical: isolated up to
#: 0.07 (Bayer 0.11), unindexed up to 0.12 (multi-object; Bayer 0.17); hard: 0.27-0.70 / 0.03-0.15.
ISOLATED_WARN = 0.2
UNINDEXED_WARN = 0.25
#: lateral chromatic aberration (blue against green edges at the frame's sides, camera px) above this:
#: corrected, but a warning.  The sweep's 48 scenes with the blue image magnified against the green
#: one (applied to the finished frames; 0.32 / 0.8 px at the sides): column RMS 0.20 / 0.49
#: projector px uncorrected, 0.10 / 0.14 corrected (0.094 without aberration); 7 / 94 pixels on
#: wrong stripes at silhouettes (welds, where the shifted blue image mixes two surfaces' colours)
#: until the row check's persistent marker and median clean test (twenty-second session): 0 / 0
LATERAL_CA_WARN_PX = 0.5
#: below this many labelled pixels (and this share of the image) nothing is measured but "no stripes"
MIN_LABELLED_PX = 200
MIN_LABELLED_FRAC = 0.005
#: the decoder's local windows (threshold, min/max normalisation) should span 2-5.5 stripes in the
#: camera; the suggestion is 3.5.  Plane, typical preset, 15 px windows: 16 px stripes (8.4 camera
#: px, 1.8 stripes) 81 % of the stripe area reported against 98 % with the suggested 29 px; 24 px
#: stripes 14 % against 98 % (41 px; the head 55 -> 81 %, 33 px); 4 px stripes (2.2 camera px,
#: 6.8 stripes) 76 % against 89 % with 7 px.  Smaller windows at the default 8 px stripes are no
#: gain: 11-13 px keep up to 5 points more of the head but put points 4.6-6.4 mm off
#: (scripts/coverage_study.py), so the decoder's 15 stays.
WINDOW_STRIPES = (2.0, 5.5, 3.5)


@dataclass(frozen=True)
class Finding:
    """One observation: ``key`` (stable name, for tools), ``level`` ("warn" or "info"), ``text``
    (the figure, what it means, what to change) and ``short`` (a few words of it, for the live
    window)."""

    key: str
    level: str
    text: str
    short: str = ""


@dataclass
class FrameCheck:
    """Measured imaging figures of one decoded frame (see the module docstring).  NaN where a
    figure cannot be measured (no labelled pixels, nothing decoded)."""

    pixels: int
    stripe_area_px: int
    labelled_px: int
    reported_frac: float
    lost_frac: dict
    stripe_snr: float
    noise_dn: float
    modulation_dn: float
    peak_dn: float
    saturated_frac: float
    contrast: float
    ambient_ratio: float
    blue_green_ratio: float
    stripe_camera_px: float
    window_px: int = 15
    resample: float = 1.0
    chroma_score: float = float("nan")
    chroma_subsampled: bool = False
    withheld: bool = False
    lateral_ca_px: float = float("nan")
    lateral_ca_corrected: bool = False
    findings: list = field(default_factory=list)

    def warnings(self) -> list:
        """The findings of level "warn"."""
        return [f for f in self.findings if f.level == "warn"]

    def to_dict(self) -> dict:
        """Plain types (JSON): every figure (NaN as None) and the findings."""
        d = asdict(self)
        for k, v in d.items():
            if isinstance(v, float) and not np.isfinite(v):
                d[k] = None
        d["lost_frac"] = {k: float(v) for k, v in self.lost_frac.items()}
        return d


def _median(x: np.ndarray) -> float:
    return float(np.median(x)) if x.size else float("nan")


def stripe_camera_px(column: np.ndarray, labels: np.ndarray, stripe_px: int) -> float:
    """Camera pixels per projector stripe.  ``column`` (H, W) float32 decoded projector column
    (NaN where not reported): ``stripe_px`` over the median of ``|column[u+1] - column[u-1]| / 2``
    where both are reported (at least 100 such pixels); otherwise from ``labels`` (H, W) uint8: the
    median length of green / blue runs along the rows that end in a green / blue neighbour (a
    lower bound where noise breaks runs).  NaN when neither has enough pixels."""
    c = np.asarray(column, dtype=np.float32)
    if c.shape[1] >= 3:
        dc = np.abs(c[:, 2:] - c[:, :-2]) * 0.5
        ok = np.isfinite(dc) & (dc > 0)
        if int(ok.sum()) >= 100:
            return float(stripe_px / np.median(dc[ok]))
    lab = np.asarray(labels)
    H, W = lab.shape
    padded = np.full((H, W + 2), 255, np.uint8)       # a sentinel at both ends of every row
    padded[:, 1:-1] = lab
    flat = padded.ravel()
    starts = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    a, b = starts[:-1], starts[1:]                    # run [a, b); the sentinels end the rows' runs

    def coloured(x):
        return (x == 1) | (x == 2)

    # interior runs only: both neighbours green or blue (so a row's first and last runs never count)
    lengths = (b - a)[coloured(flat[a]) & coloured(flat[a - 1]) & coloured(flat[b])]
    return float(np.median(lengths)) if lengths.size >= 100 else float("nan")


def check_frame(image_rgb: np.ndarray, stripemap, params=None) -> FrameCheck:
    """Measure one decoded frame.

    image_rgb : (H, W, 3) uint8 RGB, the frame ``stripemap`` was decoded from.
    stripemap : its :class:`gbscan.decode.StripeMap`.
    params : the :class:`gbscan.decode.DecodeParams` it was decoded with (camera gamma,
        saturation level, windows; default: the defaults).
    Returns a :class:`FrameCheck` with its :func:`findings` filled in.  ~10 ms at 640x480.
    """
    from . import kernels
    from .decode import (DARK, LOW_CONTRAST, OK, REASONS, SATURATED, SNR_STEP, DecodeParams, gamma_lut,
                         local_minmax)

    params = DecodeParams() if params is None else params
    img = np.asarray(image_rgb)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"check_frame: expected an (H, W, 3) uint8 RGB image, got {img.shape} {img.dtype}")
    mask = stripemap.mask
    if mask.shape != img.shape[:2]:
        raise ValueError(f"check_frame: stripe map {mask.shape} and image {img.shape[:2]} differ in size")
    H, W = mask.shape
    # the decoder's local window in this frame's pixels (a frame of wide stripes is decoded shrunk)
    resample = float(stripemap.stats.get("resample", 1.0))
    window = int(round(int(params.norm_window_px) * resample)) | 1
    area = (mask != DARK) & (mask != LOW_CONTRAST)
    n_area = int(area.sum())
    lab = stripemap.labels
    gb = (lab == 1) | (lab == 2)
    n_gb = int(gb.sum())
    reported = int((mask == OK).sum())
    lost = {}
    for code, name in REASONS.items():
        if code in (OK, DARK, LOW_CONTRAST):
            continue
        lost[name] = float((mask == code).sum()) / n_area if n_area else float("nan")
    nan = float("nan")
    snr = noise = mod = peak = contrast = ambient = bg = nan
    img = np.ascontiguousarray(img)
    lut = gamma_lut(params.camera_gamma)
    noise_, mod_, n_ = kernels.stripe_snr(img, lut, SNR_STEP[0], SNR_STEP[1], float(max(4.0 * params.dark_level, 1.0)))
    if n_ >= 500 and mod_ > 0:
        noise, mod = float(noise_), float(mod_)
        snr = mod / max(noise, 0.05)
    if n_gb >= MIN_LABELLED_PX:
        enc = np.maximum(img[..., 1], img[..., 2])
        peak = float(np.percentile(enc[gb], 95))
        import cv2

        sigma = stripemap.stats.get("blur_sigma_along_px") or 1.0
        k = 2 * int(np.ceil(3 * sigma)) + 1
        g = cv2.GaussianBlur(lut[img[..., 1]], (1, k), 0, sigmaY=float(sigma))
        b = cv2.GaussianBlur(lut[img[..., 2]], (1, k), 0, sigmaY=float(sigma))
        w = window
        lo_g, hi_g = local_minmax(g, w)
        lo_b, hi_b = local_minmax(b, w)
        hg, hb = hi_g[gb], hi_b[gb]
        cg = (hg - lo_g[gb]) / np.maximum(hg, 1e-3)
        cb = (hb - lo_b[gb]) / np.maximum(hb, 1e-3)
        contrast = _median(np.minimum(cg, cb))
        top = _median(np.maximum(hg, hb))
        ambient = _median(lut[img[..., 0][gb]]) / top if top > 0 else nan
        mg = _median(hg)
        bg = _median(hb) / mg if mg > 0 else nan
    sat = float((mask == SATURATED).sum()) / n_area if n_area else 0.0
    lca = stripemap.stats.get("lateral_ca")
    ch = stripemap.stats.get("chroma")
    if ch is None:   # decoded without the check (DecodeParams.subsampled_chroma="off"): measure it here
        from .chroma import chroma_check

        c_ = chroma_check(img)
        ch = {"score": c_.score if np.isfinite(c_.score) else None, "subsampled": c_.subsampled, "withheld": False}
    chk = FrameCheck(
        pixels=H * W, stripe_area_px=n_area, labelled_px=n_gb,
        reported_frac=reported / n_area if n_area else 0.0, lost_frac=lost,
        stripe_snr=snr, noise_dn=noise, modulation_dn=mod, peak_dn=peak, saturated_frac=sat,
        contrast=contrast, ambient_ratio=ambient, blue_green_ratio=bg,
        stripe_camera_px=stripe_camera_px(stripemap.column, lab, int(stripemap.pattern.stripe_px)),
        window_px=window, resample=resample,
        chroma_score=nan if ch.get("score") is None else float(ch["score"]),
        chroma_subsampled=bool(ch.get("subsampled")), withheld=bool(ch.get("withheld")),
        lateral_ca_px=float(lca["edge_px"]) if lca else nan, lateral_ca_corrected=bool(lca and lca["corrected"]))
    chk.findings = findings(chk)
    return chk


def findings(c: FrameCheck) -> list:
    """The observations a rig's operator acts on, warnings first (see the thresholds above)."""
    out = []

    def warn(key, text, short):
        out.append(Finding(key, "warn", text, short))

    if c.labelled_px < max(MIN_LABELLED_PX, MIN_LABELLED_FRAC * c.pixels):
        warn("no_stripes", f"green/blue stripes found on only {c.labelled_px} pixels: is the projector on, showing "
                           "the 'gbscan pattern' frame, and the object in its light and in the camera's view?",
             "no stripes seen: projector on, object in its light?")
        return out
    if c.chroma_subsampled:
        what = (f"the frame's colour was stored at half the horizontal resolution (chroma subsampling 4:2:2 / "
                f"4:2:0: a YUYV or MJPEG camera format, JPEG, most video; phase score {c.chroma_score:.2f})")
        fix = "set the camera to an RGB or raw format and record lossless files (PNG, TIFF, FFV1)"
        if c.withheld:
            warn("chroma", f"{what}: the stripes' colours smear into each other, so the decoder withholds the "
                           f"absolute index: nothing is reported; {fix}",
                 "chroma subsampled (YUYV/MJPEG): use RGB or raw frames")
        elif c.resample >= 2.0:
            out.append(Finding("chroma", "info",
                               f"{what}: decoded shrunk by {c.resample:g}, each decoded pixel averages whole pixel "
                               f"pairs, so the stripes keep their colours; 4:2:0 leaves the columns noisier; {fix}",
                               "chroma subsampled: decoded shrunk"))
        else:
            warn("chroma", f"{what}: decoded anyway (subsampled_chroma=decode), expect regions on wrong stripes; "
                           f"{fix}", "chroma subsampled (YUYV/MJPEG): use RGB or raw frames")
    if c.lateral_ca_corrected:
        text = (f"the blue stripe edges lie {c.lateral_ca_px:.2f} camera px off the green ones at the frame's "
                "sides (the lens's lateral chromatic aberration, or the projector's): measured on the stripes and "
                "corrected")
        if c.lateral_ca_px > LATERAL_CA_WARN_PX:
            warn("lateral_ca", text + "; so large an offset also mixes two surfaces' colours at silhouettes: a lens "
                                      "with less lateral chromatic aberration, or the object nearer the frame's "
                                      "centre, where it is smallest",
                 f"chromatic aberration {c.lateral_ca_px:.1f} px: a better lens")
        else:
            out.append(Finding("lateral_ca", "info", text, f"chromatic aberration {c.lateral_ca_px:.2f} px: corrected"))
    if c.saturated_frac > SATURATED_WARN:
        warn("saturated", f"{100 * c.saturated_frac:.1f} % of the stripe area is saturated: lower the camera's "
                          "exposure (or the projector's brightness); saturated pixels are dropped",
             f"{100 * c.saturated_frac:.0f} % saturated: lower the exposure")
    dim = np.isfinite(c.peak_dn) and c.peak_dn < PEAK_DIM_DN
    if dim:
        warn("dim", f"the stripes reach only {c.peak_dn:.0f} of 255 (95th percentile): raise the camera's exposure "
                    "time or aperture, or the projector's brightness (camera gain adds noise as well as signal)",
             f"dim (level {c.peak_dn:.0f}): raise the exposure")
    if np.isfinite(c.stripe_snr) and c.stripe_snr < SNR_WARN:
        why = "more light on the object (see 'dim')" if dim else \
            "less camera gain and a longer exposure, more projector light, less ambient light"
        warn("noise", f"stripe signal-to-noise {c.stripe_snr:.1f} (a good rig: 20-40; modulation "
                      f"{c.modulation_dn:.1f} DN over noise {c.noise_dn:.2f} DN): fewer pixels decode; {why}",
             f"noisy stripes (SNR {c.stripe_snr:.0f}): more light, less gain")
    ambient = np.isfinite(c.ambient_ratio) and c.ambient_ratio > AMBIENT_WARN
    if ambient:
        warn("ambient", f"red light at {c.ambient_ratio:.2f} of the stripes' level (the projector's green and blue "
                        "hardly reach the camera's red): ambient light washes the stripes out; darken the room or "
                        "shield the object (or the surface itself is red)",
             f"ambient light ({c.ambient_ratio:.2f}): darken the room")
    lo, hi = BLUE_GREEN_RANGE
    weak = np.isfinite(c.blue_green_ratio) and not lo <= c.blue_green_ratio <= hi
    if weak:
        which, other = ("blue", "green") if c.blue_green_ratio < lo else ("green", "blue")
        ratio = c.blue_green_ratio if which == "blue" else 1.0 / c.blue_green_ratio
        warn("colour_balance", f"the camera sees the {which} stripes at {ratio:.2f} of the {other} ones: check the "
                               f"projector's {which} output and colour settings and the camera's white balance (a "
                               f"surface that reflects little {which} does this too)",
             f"{which} weak ({ratio:.2f}): check colour settings")
    if np.isfinite(c.contrast) and c.contrast < CONTRAST_WARN and not ambient and not weak:
        warn("contrast", f"stripe contrast {c.contrast:.2f} (a good rig: 0.85-0.9): focus the projector on the "
                         "object, and check that the camera keeps green and blue apart (colour saturation setting, "
                         "no colour-mixing filters); ambient light lowers it too",
             f"low contrast ({c.contrast:.2f}): focus the projector")
    if np.isfinite(c.stripe_camera_px):
        lo, hi = STRIPE_PX_RANGE
        if c.stripe_camera_px < lo:
            warn("narrow_stripes", f"a stripe covers {c.stripe_camera_px:.1f} camera pixels: too narrow to resolve "
                                   "reliably; move closer, zoom the camera in, or project wider stripes "
                                   "('gbscan pattern --stripe-px', then calibrate again)",
                 f"stripes {c.stripe_camera_px:.1f} camera px: move closer")
        elif c.stripe_camera_px > hi:
            out.append(Finding("wide_stripes", "info",
                               f"a stripe covers {c.stripe_camera_px:.1f} camera pixels: narrower stripes "
                               "('gbscan pattern --stripe-px') would put more boundaries on the surface",
                               f"stripes {c.stripe_camera_px:.0f} camera px: could be narrower"))
    if c.resample > 1.0:
        out.append(Finding("resampled", "info",
                           f"stripes span {c.stripe_camera_px:.1f} camera px: the decoder shrank the frame by "
                           f"{c.resample:g} to ~{c.stripe_camera_px / c.resample:.1f} px per stripe, the width its "
                           "rules are validated at, and expanded the result to every pixel (a camera with more "
                           "pixels than the stripes need; --resample never decodes the frame as it is)",
                           f"decoded shrunk by {c.resample:g} (wide stripes)"))
    if np.isfinite(c.stripe_camera_px) and c.stripe_camera_px > 0:
        lo, hi, best = WINDOW_STRIPES
        n = c.window_px / c.stripe_camera_px
        w = max(5, int(round(best * c.stripe_camera_px)) | 1)
        if n < lo:
            # stripes wide in the camera: the decoder shrinks such frames by itself (--resample auto,
            # the default), which keeps its pixel-sized rules where they are validated; wider
            # windows alone left welded strips on a wrong stripe (docs/method.md "Cameras with more pixels")
            warn("windows", f"the decoder's local windows ({c.window_px} px) span {n:.1f} stripes of "
                            f"{c.stripe_camera_px:.1f} camera px (best 2-5): decode with --resample auto (the "
                            f"default: the frame shrunk to ~3.75 px per stripe), or else --local-window-px {w}",
                 "windows: --resample auto")
        elif n > hi:
            warn("windows", f"the decoder's local windows ({c.window_px} px) span {n:.1f} stripes of "
                            f"{c.stripe_camera_px:.1f} camera px (best 2-5): decode with --local-window-px {w}",
                 f"windows: --local-window-px {w}")
    iso = c.lost_frac.get("isolated", 0.0)
    if np.isfinite(iso) and iso > ISOLATED_WARN:
        warn("fragmented", f"{100 * iso:.0f} % of the stripe area falls apart into pieces too small to keep: "
                           "the stripes are broken up (see the figures above; 'gbscan decode --preview' shows "
                           "where)", f"{100 * iso:.0f} % in fragments")
    un = c.lost_frac.get("unindexed", 0.0)
    if np.isfinite(un) and un > UNINDEXED_WARN and not c.withheld:
        warn("unindexed", f"{100 * un:.0f} % of the stripe area could not be given an absolute stripe (too few "
                          "cyan markers seen on its surfaces): larger surfaces, less blur and noise, or a "
                          "camera that keeps full colour (no 4:2:0 chroma)", f"{100 * un:.0f} % unindexed: few markers seen")
    return out


def report(c: FrameCheck) -> str:
    """The figures and the findings as text (``gbscan check``)."""

    def f(x, fmt):
        return "n/a" if x is None or not np.isfinite(x) else format(x, fmt)

    lines = [
        f"stripe area: {c.stripe_area_px} of {c.pixels} pixels ({100 * c.stripe_area_px / max(c.pixels, 1):.1f} %), "
        f"reported {f(100 * c.reported_frac, '.1f')} % of it",
        "lost: " + (", ".join(f"{k} {100 * v:.1f} %" for k, v in c.lost_frac.items() if v and np.isfinite(v))
                    or "none"),
        f"stripe SNR {f(c.stripe_snr, '.1f')} (modulation {f(c.modulation_dn, '.1f')} DN, noise "
        f"{f(c.noise_dn, '.2f')} DN); level {f(c.peak_dn, '.0f')} of 255; saturated "
        f"{100 * c.saturated_frac:.2f} %",
        f"contrast {f(c.contrast, '.2f')}; ambient (red) {f(c.ambient_ratio, '.2f')}; blue/green "
        f"{f(c.blue_green_ratio, '.2f')}; {f(c.stripe_camera_px, '.1f')} camera px per stripe",
        "lateral chromatic aberration (blue against green edges at the frame's sides): "
        + ("n/a" if not np.isfinite(c.lateral_ca_px) else
           f"{c.lateral_ca_px:.2f} px{', corrected' if c.lateral_ca_corrected else ' (not corrected: unclear or small)'}"),
        "colour resolution: " + ("n/a" if not np.isfinite(c.chroma_score) else
                                 f"{'half (chroma subsampled)' if c.chroma_subsampled else 'full'} along the rows "
                                 f"(phase score {c.chroma_score:.2f}; under 0.5: subsampled)"),
    ]
    if not c.findings:
        lines.append("no findings: the frame looks like a good rig's")
    for x in c.findings:
        lines.append(f"{x.level}: {x.text}")
    return "\n".join(lines)
