"""The calibration file: what ``gbcal`` writes and ``gbscan`` trusts.

YAML, versioned and checked strictly on load.  Fixed fields (other tools read them)::

    schema: gbcal.calibration
    version: 1
    units: {length: mm, pixel: px}
    camera: {width, height, matrix: [[fx,0,cx],[0,fy,cy],[0,0,1]], distortion: [k1,k2,p1,p2,k3]}
    planes:                      # one per light plane (stripe boundary) the decoder reports
      - {index: int,             # absolute boundary index k (between stripes k-1 and k)
         column: float,          # projector x (px) of this light plane, k*stripe_px - 0.5
         normal: [nx,ny,nz], d: float}   # unit normal; normal . X = d, camera frame, mm

Added fields: ``pattern`` (the projected pattern the planes belong to: ``{width, height,
stripe_px, markers, marker_code}``; without ``marker_code``, a file written before 2026-11-28,
marker code 1: :mod:`gbscan.pattern`), ``projector`` (the
pinhole projector model and ``T_cam_proj`` the planes were refined through, when known),
``created`` (command, date, tool version), ``residuals`` (statistics per capture and overall),
``uncertainty`` (parameter standard deviations).  ``gbscan`` triangulates from ``camera`` and
``planes`` alone.
"""
from __future__ import annotations

import datetime as _dt
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .camera import Camera
from .errors import GBError
from .io import load_yaml, save_yaml
from .pattern import PatternSpec
from .rig import Rig

SCHEMA = "gbcal.calibration"
VERSION = 1


@dataclass(eq=False)
class Calibration:
    """Camera intrinsics and light planes (camera frame, mm).

    plane_index : (P,) int64 boundary indices, strictly increasing.
    plane_column : (P,) float64 projector columns (px).
    plane_normal : (P, 3) float64 unit normals.
    plane_d : (P,) float64 offsets (mm): ``plane_normal[i] . p = plane_d[i]``.
    """

    camera: Camera
    plane_index: np.ndarray
    plane_column: np.ndarray
    plane_normal: np.ndarray
    plane_d: np.ndarray
    pattern: PatternSpec | None = None
    projector: dict | None = None
    created: dict = field(default_factory=dict)
    residuals: dict = field(default_factory=dict)
    uncertainty: dict = field(default_factory=dict)

    def __post_init__(self):
        self.plane_index = np.asarray(self.plane_index, dtype=np.int64).ravel()
        self.plane_column = np.asarray(self.plane_column, dtype=np.float64).ravel()
        self.plane_normal = np.asarray(self.plane_normal, dtype=np.float64).reshape(-1, 3)
        self.plane_d = np.asarray(self.plane_d, dtype=np.float64).ravel()
        n = self.plane_index.size
        if not (self.plane_column.size == n and self.plane_normal.shape[0] == n and self.plane_d.size == n):
            raise GBError("calibration planes: index, column, normal and d must have one entry per plane")
        if n and np.any(np.diff(self.plane_index) <= 0):
            order = np.argsort(self.plane_index)
            self.plane_index = self.plane_index[order]
            self.plane_column = self.plane_column[order]
            self.plane_normal = self.plane_normal[order]
            self.plane_d = self.plane_d[order]
            if np.any(np.diff(self.plane_index) == 0):
                raise GBError("calibration planes: duplicate plane index")

    @property
    def n_planes(self) -> int:
        return int(self.plane_index.size)


def calibration_from_rig(rig: Rig, pattern: PatternSpec, **meta) -> Calibration:
    """The exact calibration of a known (e.g. simulated) rig: planes of every stripe boundary."""
    k = pattern.boundary_indices
    cols = pattern.boundary_column(k)
    n, d = rig.column_planes(cols)
    proj = {
        "width": rig.projector.width,
        "height": rig.projector.height,
        "matrix": rig.projector.K.tolist(),
        "R_cam_proj": rig.R_cam_proj.tolist(),
        "t_cam_proj": rig.t_cam_proj.tolist(),
    }
    created = {"by": meta.pop("by", "calibration_from_rig (ground truth)"), "date": _now()}
    return Calibration(rig.camera, k, cols, n, d, pattern=pattern, projector=proj, created=created, **meta)


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()


def command_line() -> str:
    """The command that is running, for the ``created.by`` field."""
    argv = list(sys.argv)
    if argv:
        argv[0] = Path(argv[0]).name
    return " ".join(argv)


def save_calibration(path, calib: Calibration) -> Path:
    """Write ``calib`` to ``path`` (YAML, atomic)."""
    cam = calib.camera
    created = {"by": command_line(), "date": _now()}
    created.update(calib.created or {})
    data = {
        "schema": SCHEMA,
        "version": VERSION,
        "units": {"length": "mm", "pixel": "px"},
        "created": created,
        "camera": {
            "width": cam.width,
            "height": cam.height,
            "matrix": cam.K.tolist(),
            "distortion": cam.dist.tolist(),
        },
    }
    if calib.pattern is not None:
        data["pattern"] = calib.pattern.to_dict()
    if calib.projector is not None:
        data["projector"] = calib.projector
    if calib.residuals:
        data["residuals"] = calib.residuals
    if calib.uncertainty:
        data["uncertainty"] = calib.uncertainty
    data["planes"] = [
        {"index": int(i), "column": float(c), "normal": [float(v) for v in n], "d": float(dd)}
        for i, c, n, dd in zip(calib.plane_index, calib.plane_column, calib.plane_normal, calib.plane_d)
    ]
    header = "# gbcal calibration: camera intrinsics and projector light planes (camera frame, mm)\n"
    return save_yaml(path, data, header=header)


def load_calibration(path, *, require_planes: bool = True) -> Calibration:
    """Read and strictly check a calibration file; GBError names the file and field at fault."""
    path = Path(path)
    d = load_yaml(path, "calibration file")

    def bad(field_name: str, why: str):
        raise GBError(f"calibration file {path}: field '{field_name}' {why}")

    if d.get("schema") != SCHEMA:
        bad("schema", f"must be '{SCHEMA}', found {d.get('schema')!r} (is this a gbcal calibration file?)")
    if d.get("version") != VERSION:
        bad("version", f"is {d.get('version')!r}; this gbscan reads version {VERSION} "
                       "(recalibrate with this version of gbcal)")
    cam = d.get("camera")
    if not isinstance(cam, dict):
        bad("camera", "is missing")
    for key in ("width", "height", "matrix", "distortion"):
        if key not in cam:
            bad(f"camera.{key}", "is missing")
    K = _array(cam["matrix"], (3, 3), "camera.matrix", bad)
    dist = _array(cam["distortion"], (5,), "camera.distortion", bad)
    if not (K[0, 0] > 0 and K[1, 1] > 0 and K[2, 2] == 1 and K[1, 0] == 0 and K[2, 0] == 0 and K[2, 1] == 0):
        bad("camera.matrix", "must be [[fx,s,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0")
    for key in ("width", "height"):
        v = cam[key]
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            bad(f"camera.{key}", f"must be a positive integer, got {v!r}")
    camera = Camera(cam["width"], cam["height"], K, dist)

    planes = d.get("planes")
    if planes is None:
        planes = []
    if not isinstance(planes, list):
        bad("planes", "must be a list of {index, column, normal, d}")
    if require_planes and not planes:
        bad("planes", "is empty: this file holds no light planes (calibrate the projector with "
                      "'gbcal calibrate SESSION')")
    idx, col, nor, dd = [], [], [], []
    for i, p in enumerate(planes):
        where = f"planes[{i}]"
        if not isinstance(p, dict):
            bad(where, "must be a mapping {index, column, normal, d}")
        for key in ("index", "column", "normal", "d"):
            if key not in p:
                bad(f"{where}.{key}", "is missing")
        if isinstance(p["index"], bool) or not isinstance(p["index"], int):
            bad(f"{where}.index", f"must be an integer, got {p['index']!r}")
        n = _array(p["normal"], (3,), f"{where}.normal", bad)
        if abs(np.linalg.norm(n) - 1.0) > 1e-6:
            bad(f"{where}.normal", f"must be a unit vector (norm {np.linalg.norm(n):.6g})")
        c = _number(p["column"], f"{where}.column", bad)
        dv = _number(p["d"], f"{where}.d", bad)
        idx.append(p["index"]), col.append(c), nor.append(n), dd.append(dv)
    if len(set(idx)) != len(idx):
        bad("planes", "has duplicate indices")
    pattern = None
    if "pattern" in d:
        try:
            pattern = PatternSpec.from_dict(d["pattern"])
        except (KeyError, TypeError, ValueError, GBError) as e:
            bad("pattern", f"must be {{width, height, stripe_px, markers[, marker_code]}} ({e})")
    return Calibration(
        camera,
        np.array(idx, dtype=np.int64),
        np.array(col, dtype=np.float64),
        np.array(nor, dtype=np.float64).reshape(-1, 3),
        np.array(dd, dtype=np.float64),
        pattern=pattern,
        projector=d.get("projector"),
        created=d.get("created") or {},
        residuals=d.get("residuals") or {},
        uncertainty=d.get("uncertainty") or {},
    )


def _array(value, shape, name, bad) -> np.ndarray:
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        bad(name, f"must be numbers of shape {shape}")
    if a.shape != shape:
        bad(name, f"must have shape {shape}, found {a.shape}")
    if not np.all(np.isfinite(a)):
        bad(name, "holds a non-finite number")
    return a


def _number(value, name, bad) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        bad(name, f"must be a finite number, got {value!r}")
    return float(value)
