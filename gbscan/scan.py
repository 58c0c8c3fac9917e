"""The scanning API: load a calibration once, turn camera frames into clean range images.

```python
from gbscan.scan import Scanner
scanner = Scanner("calib.yaml")               # or a Calibration; precomputes rays and planes
scan = scanner.scan(image_rgb)                # (H, W, 3) uint8 RGB -> Scan
scan.points, scan.normals                     # (N, 3) mm camera frame, unit normals to camera
scan.xyz                                      # (H, W, 3) float32 mm, NaN where no point
scan.counts                                   # points removed per cleaning filter
scan.texture, scan.grey()                     # stripe-free intensity (H, W) float32 / grey uint8
scan.to_open3d(); scan.mesh("grid")           # open3d PointCloud / TriangleMesh (grey colours)
```

Pipeline per frame: :func:`gbscan.decode.decode` (continuous projector column per pixel) ->
:class:`gbscan.triangulate.GridTriangulator` (rays x light planes, exact; vectorised) ->
:func:`gbscan.clean.clean` (filters with per-pixel reasons) -> grid normals.  When the projector
columns come from elsewhere (ground truth, another decoder), :meth:`Scanner.reconstruct` runs
the same pipeline from them.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .calibfile import Calibration, load_calibration
from .clean import CODE, REASONS, CleanParams, clean
from .errors import GBError
from .pattern import PatternSpec


@dataclass(eq=False)
class Scan:
    """One reconstructed frame (H, W = camera image size; camera frame, mm).

    xyz : (H, W, 3) float32 points, NaN where no point survived.
    normals_map : (H, W, 3) float32 unit normals towards the camera, NaN where no point.
    confidence : (H, W) float32 decoder confidence in [0, 1] (1 for external columns without one).
    reason : (H, W) uint8 code of why a pixel has no point, 0 = kept (``gbscan.clean.REASONS``).
    counts : points removed per step, in order (``not_decoded``, ``no_plane``, filters...),
        plus ``pixels`` and ``kept``.
    timings_ms : milliseconds per stage: decode, triangulate, clean (the filters and the grid
        normals the grazing filter needs), normals (NaN-ing the rejected pixels' xyz and normals), total.
    stripe : (H, W) int32 absolute stripe index from the decoder (-1 none) or None.
    stripemap : the decoder's :class:`gbscan.decode.StripeMap` or None.
    image : the (H, W, 3) uint8 RGB frame scanned (:meth:`Scanner.scan`) or None; with
        ``stripemap`` it gives :attr:`texture`.
    pattern : the projected :class:`gbscan.pattern.PatternSpec` (for :attr:`texture`) or None.
    camera_gamma : the decoder's ``camera_gamma`` (for :attr:`texture`).
    column_sigma : (H, W) predicted error of each pixel's projector column (px), when
        :meth:`Scanner.reconstruct` was given one; a decoded scan reads its ``stripemap``'s.
        With the triangulator it gives :attr:`sigma_mm`.
    """

    xyz: np.ndarray
    normals_map: np.ndarray
    confidence: np.ndarray
    reason: np.ndarray
    counts: dict = field(default_factory=dict)
    timings_ms: dict = field(default_factory=dict)
    stripe: np.ndarray | None = None
    stripemap: object = None
    image: np.ndarray | None = None
    pattern: PatternSpec | None = None
    camera_gamma: float = 2.2
    column_sigma: np.ndarray | None = None
    _texture: np.ndarray | None = field(default=None, init=False, repr=False)
    _sigma_mm: np.ndarray | None = field(default=None, init=False, repr=False)
    _sigma_source: tuple | None = field(default=None, init=False, repr=False)   # (triangulator, column)
    _grey: np.ndarray | None = field(default=None, init=False, repr=False)

    @property
    def shape(self) -> tuple[int, int]:
        return self.reason.shape

    @property
    def valid(self) -> np.ndarray:
        """(H, W) bool: pixels with a point."""
        return self.reason == 0

    @property
    def points(self) -> np.ndarray:
        """(N, 3) float32 mm, the valid pixels in raster order."""
        return self.xyz[self.valid]

    @property
    def normals(self) -> np.ndarray:
        """(N, 3) float32 unit normals of :attr:`points` (towards the camera)."""
        return self.normals_map[self.valid]

    @property
    def pixel(self) -> np.ndarray:
        """(N, 2) int32 camera pixel (row, col) of each point."""
        return np.argwhere(self.valid).astype(np.int32)

    @property
    def point_confidence(self) -> np.ndarray:
        return self.confidence[self.valid]

    @property
    def sigma_mm(self) -> np.ndarray | None:
        """(H, W) float32 predicted error (one standard deviation, mm) of each kept point along
        its camera ray, NaN where no point: the decoder's per-pixel column error
        (``StripeMap.column_sigma``) through the triangulation's derivative
        (:func:`gbscan.triangulate.point_sigma_mm`).  None without a column error (the decoder's
        ``confidence_spread_px`` 0, or :meth:`Scanner.reconstruct` from columns given without
        one).  Computed on first use (two triangulations, 1.8 ms at 640x480) unless the
        cleaning's ``max_sigma_mm`` needed it.  It is the noise of the point, not the
        calibration's error, nor the risk of a wrong stripe."""
        if self._sigma_mm is None and self._sigma_source is not None:
            from .triangulate import point_sigma_mm

            tri, column = self._sigma_source
            cs = self.column_sigma if self.column_sigma is not None else \
                getattr(self.stripemap, "column_sigma", None)
            if cs is not None:
                sig = point_sigma_mm(tri, column, cs, xyz=self.xyz)
                sig[~self.valid] = np.nan
                self._sigma_mm = sig
        return self._sigma_mm

    @property
    def point_sigma_mm(self) -> np.ndarray | None:
        """(N,) float32 :attr:`sigma_mm` of :attr:`points`, or None."""
        sig = self.sigma_mm
        return None if sig is None else sig[self.valid]

    @property
    def masks(self) -> dict[str, np.ndarray]:
        """{reason name: (H, W) bool} for every reason that occurs, ``ok`` = kept."""
        codes = np.unique(self.reason)
        return {REASONS[int(c)]: self.reason == c for c in codes}

    @property
    def n_points(self) -> int:
        return int(self.valid.sum())

    @property
    def coverage(self) -> float:
        """Fraction of the image's pixels that have a point."""
        return self.n_points / self.reason.size

    @property
    def texture(self) -> np.ndarray | None:
        """(H, W) float32 stripe-free relative intensity of the kept pixels, NaN elsewhere
        (:func:`gbscan.texture.intensity` on the scanned frame; 1 = the average decoded
        pixel).  None without the frame and the decoder's map (:meth:`Scanner.reconstruct` from
        external columns).  Computed on first use (~3 ms at 640x480)."""
        if self._texture is None and self.image is not None and self.stripemap is not None:
            from .texture import intensity

            sm = self.stripemap
            t = intensity(self.image, sm.column, sm.valid, self.pattern or PatternSpec(),
                          camera_gamma=self.camera_gamma)
            t[~self.valid] = np.nan
            self._texture = t
        return self._texture

    def grey(self) -> np.ndarray | None:
        """(H, W) uint8 display grey of :attr:`texture` (:func:`gbscan.texture.to_grey`: the 99.5th
        percentile of the kept points is white), 0 where no point; None without a texture.
        Computed once (the cloud, the mesh and the previews all use it)."""
        from .texture import to_grey

        if self._grey is None and self.texture is not None:
            self._grey = to_grey(self.texture)
        return self._grey

    def to_open3d(self):
        """``open3d.geometry.PointCloud`` with normals (and grey colours when there is a texture)."""
        import open3d as o3d

        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.points.astype(np.float64)))
        pc.normals = o3d.utility.Vector3dVector(np.nan_to_num(self.normals.astype(np.float64)))
        g = self.grey()
        if g is not None:
            pc.colors = o3d.utility.Vector3dVector(np.repeat(g[self.valid, None], 3, axis=1) / 255.0)
        return pc

    def mesh_arrays(self, method: str = "grid", *, max_jump: float = 0.01, depth: int = 9,
                    density_quantile: float = 0.05, smooth: int = 0):
        """A :class:`gbscan.mesh.Mesh` (numpy arrays) of this scan, with grey vertex colours when
        the scan has a :attr:`texture`.

        method : "grid" (organised-grid triangulation, fast, default) or "poisson" (open3d).
        smooth : Taubin smoothing iterations applied afterwards.
        """
        from . import mesh as gm

        if self.n_points == 0:
            raise GBError("cannot mesh a scan with no points")
        grey = self.grey()
        if method == "grid":
            m = gm.grid_mesh(self.xyz, self.valid, max_jump=max_jump, normals=self.normals_map, colors=grey)
        elif method == "poisson":
            m = gm.poisson_mesh(self.points, self.normals, depth=depth, density_quantile=density_quantile,
                                colors=None if grey is None else grey[self.valid])
        else:
            raise GBError(f"mesh method must be 'grid' or 'poisson', got {method!r}")
        return gm.taubin_smooth(m, smooth) if smooth else m

    def mesh(self, method: str = "grid", **options):
        """``open3d.geometry.TriangleMesh`` of this scan (options as :meth:`mesh_arrays`)."""
        return self.mesh_arrays(method, **options).to_open3d()

    def save_ply(self, path, *, colors: bool = True) -> Path:
        """Write the cloud as an organised binary PLY (see :mod:`gbscan.mesh`), with the grey
        texture as vertex colours when ``colors`` and the scan has one, and each point's
        :attr:`sigma_mm` (property ``sigma_mm``) when it has one."""
        from .mesh import write_grid_cloud_ply

        return write_grid_cloud_ply(path, self.xyz, self.normals_map, self.confidence, self.reason,
                                    self.grey() if colors else None, sigma_mm=self.sigma_mm)

    def summary(self) -> str:
        """Human-readable lines: removals per step, points, coverage, timings."""
        c = self.counts
        removed = [f"{k} {v}" for k, v in c.items() if k not in ("pixels", "input", "kept")]
        lines = [f"pixels {c.get('pixels', self.reason.size)}, removed: " + ", ".join(removed),
                 f"points {self.n_points} (coverage {100 * self.coverage:.1f}% of the image)"]
        if self.timings_ms:
            lines.append("time " + ", ".join(f"{k} {v:.1f} ms" for k, v in self.timings_ms.items()))
        return "\n".join(lines)


class Scanner:
    """Scans frames with one calibration.  Construction precomputes the pixel rays (through the
    camera model, distortion included) and the plane table (:attr:`triangulator`, a
    :class:`gbscan.triangulate.GridTriangulator`); :meth:`scan` is then cheap.

    calibration : a :class:`gbscan.calibfile.Calibration` or the path of a calibration file.
    pattern : the projected pattern; default the calibration's (or ``PatternSpec()`` if the file
        records none).  Must match the calibration's pattern when both are known.
    decode_params : :class:`gbscan.decode.DecodeParams` (default: its defaults).
    clean_params : :class:`gbscan.clean.CleanParams` (default: its defaults).
    min_angle_deg : rays closer than this to a light plane give no point.
    remeasure_every : the frames it scans are one stream of its camera: the decoder's measurements
        of the camera rather than the scene (the resampling factor, the lens's lateral chromatic
        aberration) are made on one frame and reused on the next ones, measured again every
        ``remeasure_every`` frames (:class:`gbscan.decode.StreamMemo`, :attr:`memo`; 1: on every
        frame).  After a change of lens setting call ``scanner.memo.clear()``.
    """

    def __init__(self, calibration: Calibration | str | Path, *, pattern: PatternSpec | None = None,
                 decode_params=None, clean_params: CleanParams | None = None, min_angle_deg: float = 2.0,
                 remeasure_every: int | None = None):
        from .decode import STREAM_REMEASURE_EVERY, StreamMemo
        from .heap import keep_freed_memory
        from .triangulate import GridTriangulator, PlaneTable

        keep_freed_memory()   # each scan reuses the memory the last one freed (gbscan.heap)
        if isinstance(calibration, (str, Path)):
            calibration = load_calibration(calibration)
        if not isinstance(calibration, Calibration):
            raise GBError("Scanner: calibration must be a Calibration or a file path, "
                          f"got {type(calibration).__name__}")
        if calibration.n_planes < 2:
            raise GBError(f"the calibration has {calibration.n_planes} light planes; scanning needs at least 2 "
                          "(calibrate the projector with 'gbcal calibrate SESSION')")
        if pattern is not None and calibration.pattern is not None and pattern != calibration.pattern:
            raise GBError(f"pattern {pattern} differs from the calibration's {calibration.pattern}; "
                          "scan with the pattern the rig was calibrated with")
        self.calibration = calibration
        self.pattern = pattern or calibration.pattern or PatternSpec()
        self.decode_params = decode_params
        self.clean_params = clean_params or CleanParams()
        if not isinstance(self.clean_params, CleanParams):
            raise GBError("Scanner: clean_params must be a gbscan.clean.CleanParams")
        self.min_angle_deg = float(min_angle_deg)
        self.camera = calibration.camera
        self.planes = PlaneTable.from_calibration(calibration)
        # every pixel's ray (distortion inverted) and the planes in the form the frame kernel uses
        self.triangulator = GridTriangulator(self.camera, self.planes, min_angle_deg=self.min_angle_deg)
        self._rays = None
        try:
            self.memo = StreamMemo(STREAM_REMEASURE_EVERY if remeasure_every is None else remeasure_every)
        except GBError:
            raise GBError("Scanner: remeasure_every must be an integer >= 1 (the frames a measurement of the "
                          f"camera is used on; 1: every frame), got {remeasure_every!r}") from None

    @property
    def rays(self) -> np.ndarray:
        """(H, W, 3) float64 unit rays of the pixel centres (``Camera.pixel_rays()``; computed on
        first use: scanning itself uses :attr:`triangulator`'s per-pixel rays)."""
        if self._rays is None:
            self._rays = self.camera.pixel_rays()
        return self._rays

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of the frames this scanner accepts."""
        return self.camera.size

    @property
    def stripe_range(self) -> np.ndarray | None:
        """(2, H, W) float32 absolute stripe indices (low, high) each pixel can see between the
        cleaning's ``min_depth_mm`` and ``max_depth_mm`` (the working volume), one stripe of margin
        either side; NaN where the ray meets the light planes edge-on in that range.  The decoder's
        indexing prior (:func:`gbscan.decode.decode`'s ``stripe_range``).  None when the light
        planes are not one pencil (a projector's: ``gbcal`` calibrations are), or when the range
        lets every pixel see every stripe: no prior then, at no cost.  The default range (50 mm -
        10 m) still bounds the far side (no surface beyond 10 m): on ``scripts/sweep_decode.py``
        it changes nothing but one region (83.26 -> 83.25 % reported).  Computed on first use."""
        if "_stripe_range" not in self.__dict__:
            sr = stripe_range_from_pencil(self.triangulator, float(self.pattern.stripe_px),
                                          float(self.clean_params.min_depth_mm), float(self.clean_params.max_depth_mm))
            if sr is not None and bool(np.all(np.nan_to_num(sr[0], nan=-1.0) <= 0)) and \
                    bool(np.all(np.nan_to_num(sr[1], nan=np.inf) >= self.pattern.n_stripes - 1)):
                sr = None  # every pixel may see every stripe: the range carries no information
            self._stripe_range = sr
        return self._stripe_range

    def scan(self, image_rgb: np.ndarray, *, clean: bool = True, keep_stages: bool = False) -> Scan:
        """Decode, triangulate, clean one camera frame (H, W, 3) uint8 RGB -> :class:`Scan`."""
        from .decode import DecodeParams, decode

        image_rgb = np.asarray(image_rgb)
        W, H = self.size
        if image_rgb.ndim != 3 or image_rgb.shape[:2] != (H, W):
            raise GBError(f"image is {'x'.join(map(str, image_rgb.shape[1::-1]))} but the calibration's camera "
                          f"is {W}x{H}; scan images from the calibrated camera")
        t0 = time.perf_counter()
        params = self.decode_params or DecodeParams()
        sm = decode(image_rgb, self.pattern, params, keep_stages=keep_stages,
                    stripe_range=self.stripe_range, memo=self.memo)
        t_dec = (time.perf_counter() - t0) * 1e3
        # the column errors are read (a resampled decode expands them) only if the cleaning needs them
        need_sigma = clean and self.clean_params.max_sigma_mm is not None
        if need_sigma and sm.column_sigma is None:
            raise GBError("the cleaning's max_sigma_mm needs the decoder's per-pixel column error: "
                          "decode with confidence_spread_px > 0 (the default)")
        s = self.reconstruct(sm.column, sm.confidence, decoded=sm.valid, clean=clean,
                             column_sigma=sm.column_sigma if need_sigma else None)
        s.stripe, s.stripemap = sm.stripe, sm
        s.image, s.pattern = image_rgb, self.pattern
        s.camera_gamma = float(params.camera_gamma)
        s.timings_ms = {"decode": t_dec, **s.timings_ms}
        s.timings_ms["total"] = t_dec + s.timings_ms.get("total", 0.0)
        return s

    def reconstruct(self, column: np.ndarray, confidence: np.ndarray | None = None, *,
                    decoded: np.ndarray | None = None, clean: bool = True,
                    column_sigma: np.ndarray | None = None) -> Scan:
        """Triangulate and clean from projector columns (H, W) px (NaN = none).

        confidence : (H, W) in [0, 1] or None (all 1: no confidence filtering).
        decoded : (H, W) bool pixels the decoder reported (default: finite column); the others
            are counted as ``not_decoded``.
        column_sigma : (H, W) predicted error of each column (px) or None; gives
            :attr:`Scan.sigma_mm` and is required by the cleaning's ``max_sigma_mm``.

        The cleaning runs on the window of the decoded pixels (:func:`point_window`: an object
        before darkness), with the same result as on the whole frame.
        """
        from . import kernels

        W, H = self.size
        column = np.asarray(column)
        if column.shape != (H, W):
            raise GBError(f"column map is {column.shape[::-1]} but the camera is {W}x{H}")
        t0 = time.perf_counter()
        decoded = np.isfinite(column) if decoded is None else (np.asarray(decoded, bool) & np.isfinite(column))
        if confidence is None:
            conf = np.ones((H, W), np.float32)
        else:
            conf = np.asarray(confidence, np.float32)
            if conf.shape != (H, W):
                raise GBError(f"confidence map is {conf.shape[::-1]} but the camera is {W}x{H}")
            conf = np.where(decoded, conf, np.float32(0))
        if column_sigma is not None:
            column_sigma = np.asarray(column_sigma, np.float32)
            if column_sigma.shape != (H, W):
                raise GBError(f"column_sigma map is {column_sigma.shape[::-1]} but the camera is {W}x{H}")
        xyz = self.triangulator(np.where(decoded, column, np.float32(np.nan)))
        t1 = time.perf_counter()
        reason = (~decoded).view(np.uint8) * np.uint8(CODE["not_decoded"])  # 0 = in play
        counts = {"pixels": H * W, "not_decoded": int(np.count_nonzero(reason))}
        sigma = None
        if clean and self.clean_params.max_sigma_mm is not None:
            if column_sigma is None:
                raise GBError("the cleaning's max_sigma_mm needs each column's predicted error: pass column_sigma "
                              "(a decoder's StripeMap.column_sigma)")
            from .triangulate import point_sigma_mm

            sigma = point_sigma_mm(self.triangulator, column, column_sigma, xyz=xyz)
        win = point_window(decoded, self.clean_params) if clean else None
        if clean and win is not None:
            # the filters on the window of the decoded pixels (every pixel outside is out of play):
            # the same result, without the passes over the rest of the frame
            y0, y1, x0, x1 = win
            sl = (slice(y0, y1), slice(x0, x1))
            cp = self.clean_params
            if cp.min_cluster_px is None:   # the frame's default, not the window's
                cp = dataclasses.replace(cp, min_cluster_px=(H * W) // 1000)
            xyz_w = np.ascontiguousarray(xyz[sl])
            res = _clean(xyz_w, np.ascontiguousarray(conf[sl]) if confidence is not None else None, cp,
                         np.ascontiguousarray(reason[sl]), None if sigma is None else np.ascontiguousarray(sigma[sl]))
            counts.update({k: v for k, v in res.counts.items() if k != "input"})
            t2 = time.perf_counter()
            kernels.mask_rejected(res.reason, xyz_w, res.normals)  # NaN wherever there is no point
            reason[sl] = res.reason
            xyz[sl] = xyz_w
            normals = np.full((H, W, 3), np.nan, np.float32)
            normals[sl] = res.normals
            t3 = time.perf_counter()
        elif clean:
            res = _clean(xyz, conf if confidence is not None else None, self.clean_params, reason, sigma)
            reason, normals = res.reason, res.normals  # normals: computed before the grazing filter
            counts.update({k: v for k, v in res.counts.items() if k != "input"})
        else:  # only the points triangulation could not make
            counts["no_plane"] = int(kernels.clean_pointwise(xyz, conf, False, 0.0, -np.inf, np.inf, reason,
                                                             CODE["no_plane"], 0, 0)[0])
            counts["kept"] = int(np.count_nonzero(reason == 0))
            normals = np.empty((H, W, 3), np.float32)
            kernels.grid_normals_into(xyz, reason, int(self.clean_params.normal_step_px), normals, -np.inf, 0)
        if win is None:
            t2 = time.perf_counter()
            kernels.mask_rejected(reason, xyz, normals)  # NaN wherever there is no point
            t3 = time.perf_counter()
        timings = {"triangulate": (t1 - t0) * 1e3, "clean": (t2 - t1) * 1e3, "normals": (t3 - t2) * 1e3,
                   "total": (t3 - t0) * 1e3}
        s = Scan(xyz, normals, conf, reason, counts, timings, column_sigma=column_sigma)
        s._sigma_source = (self.triangulator, column)
        if sigma is not None:
            sigma[reason != 0] = np.nan
            s._sigma_mm = sigma
        return s


def stripe_range_from_pencil(triangulator, stripe_px: float, near_mm: float, far_mm: float,
                             margin_stripes: float = 1.0) -> np.ndarray | None:
    """(2, H, W) float32 absolute stripe indices (low, high) that each pixel's ray meets between
    depths ``near_mm`` and ``far_mm`` (``margin_stripes`` added either side), from the triangulator's
    pencil of light planes: on the ray ``p = z (mx, my, 1)`` the plane of column ``x`` holds ``p``
    where ``x = xc + (ad - z a.m) / (z b.m - bd)`` (:class:`gbscan.triangulate.Pencil`), monotonic
    in ``z`` between its pole; NaN where the pole falls inside the range.  None without a pencil."""
    pen = triangulator.pencil
    if pen is None or not (0 < near_mm < far_mm):
        return None
    H, W = triangulator.shape
    mx, my = triangulator.mx, triangulator.my
    am = pen.a[0] * mx + pen.a[1] * my + pen.a[2]
    bm = pen.b[0] * mx + pen.b[1] * my + pen.b[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        cols = [pen.xc + (pen.ad - z * am) / (z * bm - pen.bd) for z in (near_mm, far_mm)]
        pole = pen.bd / bm                      # the depth where the ray runs along the planes
        inside = (pole >= near_mm) & (pole <= far_mm)
    lo = (np.minimum(*cols) + 0.5) / stripe_px - margin_stripes
    hi = (np.maximum(*cols) + 0.5) / stripe_px + margin_stripes
    bad = inside | ~np.isfinite(lo) | ~np.isfinite(hi)
    lo[bad] = np.nan
    hi[bad] = np.nan
    return np.stack([lo.reshape(H, W), hi.reshape(H, W)]).astype(np.float32)


def _clean(xyz, confidence, params, reason, sigma_mm=None):
    return clean(xyz, confidence, params, reason=reason, sigma_mm=sigma_mm)


#: a window of the decoded pixels over this fraction of the frame is not used by the cleaning
POINT_WINDOW_MAX_FRACTION = 0.6


def point_window(decoded: np.ndarray, params: CleanParams) -> tuple[int, int, int, int] | None:
    """The window (y0, y1, x0, x1), half-open, that :meth:`Scanner.reconstruct` runs the cleaning
    on: the bounding box of the ``decoded`` (H, W) pixels grown by twice the filters' reach along
    a row or column (``max_gap_px`` and the run ends it trims, ``normal_step_px``; the rest look at
    4-neighbours), at least 8 px.  Pixels outside it are out of play, so the filters give the
    whole frame's result there (the components' default size is the frame's, not the window's).
    None: nothing decoded or a window over ``POINT_WINDOW_MAX_FRACTION`` of the frame."""
    from .mesh import grid_window

    m = 2 * (int(params.max_gap_px) + max(int(params.gap_far_px), int(params.gap_near_px)) +
             int(params.normal_step_px)) + 8
    return grid_window(decoded, m, POINT_WINDOW_MAX_FRACTION)
