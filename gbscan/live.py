"""Live scanning at a rig: the projector shows the pattern, every camera frame is scanned, a
window shows the frame beside its depth map, and SPACE saves the scan (``scripts/live_scan.py``).

No windows and no camera here: :func:`run_live` drives any display with ``show_projector(frame)``,
``show_image(picture)``, ``poll_key()`` and ``close()`` (:mod:`gbcal.display`: Tk, OpenCV's
highgui, or :class:`gbcal.display.NullDisplay` for tests) and any camera with ``read()`` (RGB
uint8) and ``close()`` (:class:`gbcal.display.VideoCamera`, or :class:`SimulatedCamera`).

A saved scan is a folder ``OUTDIR/scan_NNN`` holding what ``gbscan scan`` writes -- ``frame.png``
(the camera frame, lossless: scan it again with other options), ``cloud.ply`` (organised, grey
texture as colours), ``xyz.npy`` (float32 (H, W, 3) mm, NaN where no point) and ``mesh.ply``
(grid mesh) -- staged in a hidden folder and renamed into place, so a folder that exists is whole.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import GBError

KEYS = "SPACE save this scan    q quit"
#: Largest size (W, H) of the live picture's image row (camera frame + depth map)
LIVE_MAX_PX = (1280, 520)


def depth_picture(xyz: np.ndarray, valid: np.ndarray, near_mm: float | None = None,
                  far_mm: float | None = None) -> np.ndarray:
    """(H, W, 3) uint8 RGB: depth ``xyz[..., 2]`` (mm) coloured near = red to far = blue (OpenCV's
    turbo map), black where ``valid`` is False.  ``near_mm``/``far_mm`` default to the 2nd and 98th
    percentiles of the valid depths."""
    import cv2

    z = np.asarray(xyz, dtype=np.float32)[..., 2]
    valid = np.asarray(valid, bool) & np.isfinite(z)
    if not valid.any():
        return np.zeros(z.shape + (3,), np.uint8)
    if near_mm is None or far_mm is None:
        zv = z[valid][::7]                       # every 7th valid depth: plenty for two percentiles
        lo_p, hi_p = np.percentile(zv, (2, 98))
    lo = float(lo_p) if near_mm is None else float(near_mm)
    hi = float(hi_p) if far_mm is None else float(far_mm)
    if not hi > lo:
        hi = lo + 1.0
    # turbo's 20 (blue, far) .. 235 (red, near): its two ends are dark
    g = np.nan_to_num(z, nan=hi, posinf=hi, neginf=lo)
    g = (g - np.float32(lo)) * np.float32(-215.0 / (hi - lo)) + np.float32(235.0)
    np.clip(g, 20, 235, out=g)
    rgb = cv2.cvtColor(cv2.applyColorMap(g.astype(np.uint8), cv2.COLORMAP_TURBO), cv2.COLOR_BGR2RGB)
    return rgb * valid[..., None].view(np.uint8)


def compose(frame_rgb: np.ndarray, depth_rgb: np.ndarray, lines: list[tuple[str, tuple]],
            max_size: tuple[int, int] = LIVE_MAX_PX) -> np.ndarray:
    """The live window's picture (RGB uint8): the camera frame and the depth picture side by side,
    shrunk to fit ``max_size``, and below them one text line per ``(text, rgb colour)``."""
    import cv2

    row = np.concatenate([np.asarray(frame_rgb, np.uint8), np.asarray(depth_rgb, np.uint8)], axis=1)
    H, W = row.shape[:2]
    s = min(1.0, max_size[0] / W, max_size[1] / H)
    if s < 1:
        row = cv2.resize(row, (max(1, int(W * s)), max(1, int(H * s))), interpolation=cv2.INTER_AREA)
    w = row.shape[1]
    line_h = 20
    panel = np.full((8 + line_h * len(lines), w, 3), 24, np.uint8)
    for k, (text, colour) in enumerate(lines):
        cv2.putText(panel, text, (8, 4 + line_h * (k + 1) - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1,
                    cv2.LINE_AA)
    return np.ascontiguousarray(np.concatenate([row, panel], axis=0))


def save_scan(outdir, index: int, frame_rgb: np.ndarray, scan) -> Path:
    """Write ``scan`` (a :class:`gbscan.scan.Scan`) and its frame into ``outdir/scan_{index:03d}``
    (module docstring), staged in a hidden folder and renamed; GBError if the folder exists."""
    import os
    import shutil

    from .io import save_npy, write_png
    from .mesh import write_mesh

    outdir = Path(outdir)
    final = outdir / f"scan_{index:03d}"
    if final.exists():
        raise GBError(f"{final} exists already; give another output folder (-o) or move it away")
    tmp = outdir / f".scan_{index:03d}.partial"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    try:
        write_png(tmp / "frame.png", frame_rgb)
        if scan.n_points:
            scan.save_ply(tmp / "cloud.ply")
            mesh = scan.mesh_arrays("grid")
            if mesh.n_triangles:
                write_mesh(tmp / "mesh.ply", mesh)
        save_npy(tmp / "xyz.npy", np.ascontiguousarray(scan.xyz, dtype=np.float32))
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


@dataclass
class LiveResult:
    """What a live session did: frames scanned, folders saved, how it ended ("quit": q or ESC,
    "frames": ``max_frames`` reached), frames per second over the session, and the last rig hint
    the window showed ("" when the frames looked like a good rig's)."""

    frames: int = 0
    saved: list = field(default_factory=list)
    status: str = ""
    fps: float = 0.0
    hint: str = ""


_WHITE, _GREEN, _RED, _GREY, _YELLOW = (235, 235, 235), (90, 220, 90), (240, 80, 80), (150, 150, 150), (240, 210, 60)


#: frames between two rig checks (:func:`gbscan.diagnose.check_frame`, ~10 ms) in the live window
HINT_EVERY = 15


def run_live(display, camera, scanner, outdir, *, max_frames: int | None = None, near_mm: float | None = None,
             far_mm: float | None = None, log=None) -> LiveResult:
    """Show the scanner's pattern on the projector, then scan camera frames until q / ESC (or
    ``max_frames``): each frame's picture (:func:`compose`) shows the frame, its depth map
    (:func:`depth_picture` between ``near_mm`` and ``far_mm``), the points, the time per scan and
    the frame rate, and the first two warnings of the rig check (:func:`gbscan.diagnose.check_frame`,
    every ``HINT_EVERY`` frames: dim, saturated, noisy, ambient light, ...); SPACE saves the
    current scan into ``outdir`` (:func:`save_scan`).

    scanner : a :class:`gbscan.scan.Scanner` (its pattern is projected).  A camera frame of the
    wrong size raises GBError (naming both sizes).
    """
    from .pattern import render_pattern

    say = log or (lambda s: None)
    outdir = Path(outdir)
    display.show_projector(render_pattern(scanner.pattern))
    res = LiveResult()
    message, ok = "scanning: hold the object in the projector's light", True
    # number on from the highest scan_NNN already there (folders may have been removed in between)
    n_saved = max([int(p.name[5:]) for p in outdir.glob("scan_*") if p.name[5:].isdigit()], default=0) \
        if outdir.is_dir() else 0
    t_start = time.perf_counter()
    hint = ""
    rate = 0.0
    t_prev = t_start
    while True:
        frame = camera.read()
        t0 = time.perf_counter()
        scan = scanner.scan(frame)
        scan_ms = (time.perf_counter() - t0) * 1e3
        now = time.perf_counter()
        rate = 1.0 / max(now - t_prev, 1e-6) if res.frames == 0 else 0.8 * rate + 0.2 / max(now - t_prev, 1e-6)
        t_prev = now
        res.frames += 1
        if scan.stripemap is not None and (res.frames == 1 or res.frames % HINT_EVERY == 0):
            from .diagnose import check_frame

            warns = check_frame(frame, scan.stripemap, scanner.decode_params).warnings()
            hint = res.hint = "; ".join(f.short for f in warns[:2])
        reasons = scan.stripemap.stats.get("reasons", {}) if scan.stripemap is not None else {}
        share = {k: 100.0 * reasons.get(k, 0) / max(scan.reason.size, 1) for k in ("dark", "saturated", "unindexed")}
        lines = [(f"frame {res.frames}: {scan.n_points} points ({100 * scan.coverage:.1f} % of the image), "
                  f"scan {scan_ms:.0f} ms, {rate:.1f} frames/s", _WHITE),
                 (f"dark {share['dark']:.0f} %, saturated {share['saturated']:.1f} %, unindexed "
                  f"{share['unindexed']:.1f} % of the image", _GREY),
                 (message, _GREEN if ok else _RED), (KEYS, _YELLOW)]
        if hint:
            lines.insert(2, (f"rig: {hint}", _RED))
        display.show_image(compose(frame, depth_picture(scan.xyz, scan.valid, near_mm, far_mm), lines))
        key = display.poll_key()
        if key == " ":
            try:
                n_saved += 1
                path = save_scan(outdir, n_saved, frame, scan)
                res.saved.append(path)
                message, ok = f"saved {path} ({scan.n_points} points)", True
                say(message)
            except (GBError, OSError) as e:
                message, ok = f"not saved: {e}", False
                say(message)
        elif key in ("q", "esc"):
            res.status = "quit"
            break
        if max_frames is not None and res.frames >= max_frames:
            res.status = "frames"
            break
    res.fps = res.frames / max(time.perf_counter() - t_start, 1e-6)
    return res


class SimulatedCamera:
    """A simulated camera for ``live_scan.py --simulate`` and tests: the paper rig (or ``rig``)
    films a face turning slowly (``gbscan.sim.scenes.head``, yaw ``amplitude_deg`` sin(2 pi i /
    ``period``) at frame ``i``, before a wall) under the frame the projector shows."""

    def __init__(self, frame_rgb: np.ndarray, rig=None, *, preset: str = "typical", distance_mm: float = 650.0,
                 amplitude_deg: float = 20.0, period: int = 24, seed: int = 0):
        import dataclasses

        from . import sim

        self.sim = sim
        self.rig = rig or sim.paper_rig()
        self.frame = np.asarray(frame_rgb)
        self.cond = dataclasses.replace(sim.preset(preset), supersample=1)
        self.distance_mm, self.amplitude_deg, self.period = float(distance_mm), float(amplitude_deg), int(period)
        self.seed = int(seed)
        self.i = 0

    def read(self) -> np.ndarray:
        yaw = self.amplitude_deg * np.sin(2 * np.pi * self.i / self.period)
        scene = self.sim.scenes.head(self.distance_mm, yaw, wall_mm=self.distance_mm + 250.0)
        r = self.sim.render(self.rig, scene, self.frame, self.cond, seed=self.seed + self.i)
        self.i += 1
        return r.image

    def close(self):
        pass
