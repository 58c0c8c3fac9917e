"""Imaging conditions of the simulated rig: :class:`Conditions` and the named presets.

Every field is a plain number (or tuple) so conditions can be written to YAML
(:meth:`Conditions.to_dict`) and changed with ``dataclasses.replace``.

Signal chain (see :mod:`gbscan.sim.render`)::

    projector frame value v (0..255)  --linearise: (v/255)**proj_gamma, times proj_gain_rgb-->
    blurred by projector defocus (Gaussian, proj_sigma_px at proj_focus_mm, growing by
    proj_defocus_px_per_100mm per 100 mm away from focus) --> irradiance
    E = radiance * cos(incidence) / (distance_to_projector / ref_distance_mm)**2
    camera linear signal = exposure * albedo * albedo_gain_rgb * (crosstalk @ E + ambient_rgb)
    --> supersample average --> [lateral chromatic aberration: lateral_ca_px] --> vignetting
    --> camera blur (cam_sigma_px) --> motion blur
    --> [optional Bayer mosaic] --> shot noise (Gaussian, variance = signal / full_well_e)
    + read noise (read_noise_dn / 255) --> encode ~255 * lin**(1/gamma) (small linear toe at
    black, see gbscan.sim.render.encode) --> round, clip to 0..255 --> [demosaic]
    --> [optional JPEG round trip: OpenCV's encoder at jpeg_quality with jpeg_sampling]
    --> [optional YUV round trip: a camera delivering YUYV (4:2:2) or I420 (4:2:0) frames that
        OpenCV converts to RGB: yuv]

``crosstalk[c, p]`` is how much camera channel ``c`` (R, G, B) sees of projector channel ``p``.
``ambient_rgb`` is ambient irradiance relative to a white projector pixel at ``ref_distance_mm``
head-on.  Measured output noise (standard deviation, no blur; tests/test_sim.py checks the
ranges) on a flat grey surface lit white at 650 mm:

    preset   albedo 0.5: level / noise     albedo 0.15      black frame (ambient only)
    clean    ~147 DN / 0.4 DN              ~73 / 0.4        ~0 / 0.2
    typical  ~158 DN / 1.8 DN              ~79 / 1.8        ~8 / 1.6
    hard     ~95-133 DN / 4.9 DN           ~45-65 / 5.6     ~15 / 7.0
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import numpy as np

from ..errors import GBError


#: Colour filter mosaics ``Conditions.bayer`` takes, named by the sensor's top-left 2x2, row by row
BAYER_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
#: JPEG chroma subsamplings ``Conditions.jpeg_sampling`` takes
JPEG_SAMPLINGS = ("4:4:4", "4:2:2", "4:2:0")
#: camera YUV formats ``Conditions.yuv`` takes (OpenCV's conversions to and from RGB)
YUV_FORMATS = ("yuyv", "i420")
#: ``Conditions.shininess`` unless given (``--gloss KS`` without a shininess)
DEFAULT_SHININESS = 20.0


def _m(rows):
    return tuple(tuple(float(v) for v in r) for r in rows)


@dataclass(frozen=True)
class Conditions:
    """Imaging conditions (see the module docstring for the signal chain)."""

    supersample: int = 3                 # ss x ss camera rays per pixel
    proj_gamma: float = 2.2              # projector frame values are sRGB-ish: linear = (v/255)**gamma
    proj_gain_rgb: tuple = (1.0, 1.0, 1.0)
    proj_sigma_px: float = 1.0           # projector defocus at focus (Gaussian sigma, projector px)
    proj_focus_mm: float = 650.0
    proj_defocus_px_per_100mm: float = 0.5
    ref_distance_mm: float = 650.0
    crosstalk: tuple = _m([[1.0, 0.04, 0.02], [0.05, 1.0, 0.12], [0.02, 0.10, 1.0]])
    ambient_rgb: tuple = (0.05, 0.05, 0.05)
    exposure: float = 0.8                # linear camera value of albedo 1, white, head-on, ref distance
    albedo_gain_rgb: tuple = (1.0, 1.0, 1.0)  # scales every surface's albedo (dark / tinted scenes)
    vignetting: float = 0.1              # relative fall-off at the image corner (quadratic in radius)
    specular: float = 0.0                # Blinn-Phong gloss: the light's colour reflected with this
                                         # weight (albedo 1 diffuse = 1) times (n . h)**shininess
    shininess: float = DEFAULT_SHININESS  # its exponent (skin ~10-40, glossy paint ~100)
    lateral_ca_px: float = 0.0           # lateral chromatic aberration: blue lies this far out from
                                         # green at the farthest corner (red as far in), px
    cam_sigma_px: float = 0.5            # camera blur (optics + demosaicing), Gaussian sigma px
    motion_px: float = 0.0               # linear motion blur length (camera px)
    motion_deg: float = 0.0              # its direction (0 = along image x)
    full_well_e: float = 6000.0          # electrons at linear full scale (shot noise); 0 = none
    read_noise_dn: float = 0.2           # read noise, linear DN (of 255); ~1.3 DN after encoding at black
    gamma: float = 2.2                   # camera encoding 255 * lin**(1/gamma); 1 = linear
    bayer: str = ""                      # "" = full RGB per pixel; "RGGB" etc. = colour filter mosaic
                                         # sampled per photosite, noise per photosite, then
                                         # demosaiced (OpenCV edge-aware) like a real colour camera
    bayer_raw: bool = False              # with bayer: deliver the raw mosaic (H, W) uint8, not demosaiced
    jpeg_quality: int = 0                # 0 = lossless frames; 1..100 = stored as JPEG of this quality
    jpeg_sampling: str = "4:2:0"         # its chroma subsampling (4:2:0: most encoders' default)
    yuv: str = ""                        # "" = RGB frames; "yuyv" (4:2:2) / "i420" (4:2:0) = the camera
                                         # delivers YUV that OpenCV converts to RGB (pixel pairs
                                         # share their colour: most webcams' uncompressed formats)

    def __post_init__(self):
        if int(self.supersample) < 1:
            raise GBError(f"supersample must be >= 1, got {self.supersample}")
        c = np.asarray(self.crosstalk, dtype=np.float64)
        if c.shape != (3, 3) or np.any(c < 0):
            raise GBError("crosstalk must be a non-negative 3x3 matrix (camera channel x projector channel)")
        if not (np.isfinite(self.lateral_ca_px) and abs(float(self.lateral_ca_px)) <= 10):
            raise GBError(f"lateral_ca_px must be within [-10, 10] px, got {self.lateral_ca_px!r}")
        for name in ("proj_gamma", "gamma", "exposure", "ref_distance_mm", "proj_focus_mm"):
            if not float(getattr(self, name)) > 0:
                raise GBError(f"condition {name} must be positive, got {getattr(self, name)}")
        for name in ("proj_sigma_px", "proj_defocus_px_per_100mm", "cam_sigma_px", "motion_px",
                     "full_well_e", "read_noise_dn", "vignetting", "specular", "shininess"):
            if float(getattr(self, name)) < 0:
                raise GBError(f"condition {name} must be >= 0, got {getattr(self, name)}")
        if self.bayer not in ("",) + BAYER_PATTERNS:
            raise GBError(f"bayer must be '' or one of RGGB, BGGR, GRBG, GBRG, got {self.bayer!r}")
        if not (isinstance(self.jpeg_quality, (int, np.integer)) and 0 <= int(self.jpeg_quality) <= 100):
            raise GBError(f"jpeg_quality must be an integer 0 (lossless) .. 100, got {self.jpeg_quality!r}")
        if self.bayer_raw and not self.bayer:
            raise GBError("bayer_raw needs a Bayer mosaic (bayer='RGGB', ...)")
        if self.bayer_raw and self.jpeg_quality:
            raise GBError("bayer_raw frames are not stored as JPEG (a raw mosaic is the sensor's own data)")
        if self.yuv not in ("",) + YUV_FORMATS:
            raise GBError(f"yuv must be '' or one of {', '.join(YUV_FORMATS)}, got {self.yuv!r}")
        if self.yuv and (self.jpeg_quality or self.bayer_raw):
            raise GBError("yuv frames are neither JPEG nor raw mosaics: set one of yuv, jpeg_quality, bayer_raw")
        if self.jpeg_sampling not in JPEG_SAMPLINGS:
            raise GBError(f"jpeg_sampling must be one of {', '.join(JPEG_SAMPLINGS)}, got {self.jpeg_sampling!r}")
        object.__setattr__(self, "crosstalk", _m(c))
        object.__setattr__(self, "albedo_gain_rgb", tuple(float(v) for v in np.broadcast_to(self.albedo_gain_rgb, 3)))
        object.__setattr__(self, "ambient_rgb", tuple(float(v) for v in np.broadcast_to(self.ambient_rgb, 3)))
        object.__setattr__(self, "proj_gain_rgb", tuple(float(v) for v in np.broadcast_to(self.proj_gain_rgb, 3)))

    def to_dict(self) -> dict:
        d = asdict(self)
        return {k: (list(map(list, v)) if k == "crosstalk" else list(v) if isinstance(v, tuple) else v)
                for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict) -> "Conditions":
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise GBError(f"unknown condition field(s) {sorted(unknown)}; known: {sorted(names)}")
        return cls(**{k: (tuple(map(tuple, v)) if k == "crosstalk" else tuple(v) if isinstance(v, list) else v)
                      for k, v in d.items()})


PRESETS = {
    # Nearly ideal: tiny noise, no ambient, small crosstalk, mild blur.
    "clean": Conditions(
        supersample=3, proj_sigma_px=0.5, proj_defocus_px_per_100mm=0.0,
        crosstalk=_m([[1.0, 0.01, 0.01], [0.01, 1.0, 0.02], [0.01, 0.02, 1.0]]),
        ambient_rgb=(0.0, 0.0, 0.0), vignetting=0.0, cam_sigma_px=0.3,
        full_well_e=200000.0, read_noise_dn=0.05),
    # The acceptance target: realistic noise ~1-2 DN, crosstalk ~0.1, ambient ~5 %,
    # defocus ~1 projector px, camera blur ~0.5 px.
    "typical": Conditions(),
    # Strong noise, coloured ambient, crosstalk ~0.3, more blur, weaker blue, some motion,
    # darker skin-tinted albedo (blue reflected least).
    "hard": Conditions(
        supersample=3, proj_gain_rgb=(1.0, 1.0, 0.8), proj_sigma_px=1.8, proj_defocus_px_per_100mm=1.0,
        crosstalk=_m([[1.0, 0.10, 0.06], [0.10, 1.0, 0.30], [0.05, 0.28, 1.0]]),
        ambient_rgb=(0.25, 0.2, 0.15), exposure=0.6, albedo_gain_rgb=(0.8, 0.65, 0.5), vignetting=0.25, cam_sigma_px=0.9,
        motion_px=1.5, motion_deg=20.0, full_well_e=900.0, read_noise_dn=1.5),
}


def preset(name: str = "typical") -> Conditions:
    """The named conditions: ``"clean"``, ``"typical"`` or ``"hard"``."""
    if isinstance(name, Conditions):
        return name
    try:
        return PRESETS[str(name)]
    except KeyError:
        raise GBError(f"unknown simulation preset '{name}'; choose one of {', '.join(PRESETS)}") from None
