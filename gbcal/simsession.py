"""Simulated calibration sessions: a board in varied poses, every calibration frame rendered.

``write_session`` writes the capture-session layout of :mod:`gbscan.io` (``session.yaml`` and
``pose_NNN/<frame>.png``) plus ``truth.yaml``: the true rig (camera K/dist, projector K/size,
``R_cam_proj``/``t_cam_proj``), the pattern, the imaging conditions and every board pose
(``p_cam = R_cam_board @ p_board + t_cam_board``, board convention of docs/design.md).

Board poses: tilts of up to ~40 degrees about both axes (one fronto-parallel-ish pose), in-plane
roll up to 15 degrees, distances 550-800 mm, boards spread over the projector frame so that every
light plane crosses some board (:func:`board_poses`).  Every pose
keeps the whole board (printed grid and margin) inside the camera image and the printed grid
inside the projector frame, so the white frame shows the full board lit.  (With the paper rig's
narrow projector, a 9x7 board of 30 mm squares does not fit the projector frame at 650 mm;
the default is 20 mm squares, about 240 x 200 mm with margins: ~40 % of the image width.)

Every frame of every pose has its own noise realisation (seed derived from ``seed``, the pose
and the frame), so the session is deterministic for a given ``seed``.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from gbscan.errors import GBError
from gbscan.io import atomic_path, load_yaml, make_dir, save_yaml, write_session_yaml
from gbscan.pattern import PatternSpec
from gbscan.rig import Rig

from .patterns import calibration_frames

DEFAULT_BOARD = (9, 7, 20.0)


def _write_png(path: Path, rgb: np.ndarray, compact: bool) -> None:
    """Atomic RGB PNG; ``compact``: maximum compression (noisy frames ~16 % smaller, ~10x slower)."""
    import cv2

    with atomic_path(path, suffix=".png") as tmp:
        params = ([cv2.IMWRITE_PNG_COMPRESSION, 9, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_FILTERED]
                  if compact else [])
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(rgb[:, :, ::-1]), params):
            raise GBError(f"could not encode {path} as PNG")


def _rot(ax_deg: float, ay_deg: float, roll_deg: float) -> np.ndarray:
    ax, ay, az = np.radians([ax_deg, ay_deg, roll_deg])
    Rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    Ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    Rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return Ry @ Rx @ Rz


def _pose_ok(rig: Rig, R, t, cols, rows, s, margin_mm, edge_px=8.0) -> bool:
    cam, proj = rig.camera, rig.projector
    m = margin_mm
    outline = np.array([[x, y, 0.0] for x in (-s - m, cols * s + m) for y in (-s - m, rows * s + m)])
    grid = np.array([[x, y, 0.0] for x in (-s, cols * s) for y in (-s, rows * s)])
    # densify the edges (lens distortion bends them)
    def edges(c):
        a, b, d, e = c[0], c[1], c[3], c[2]
        return np.concatenate([np.linspace(p, q, 9) for p, q in ((a, b), (b, d), (d, e), (e, a))])

    pc = edges(outline) @ R.T + t
    if np.any(pc[:, 2] < 100):
        return False
    q = cam.project(pc)
    if not (np.all(np.isfinite(q)) and q[:, 0].min() > edge_px and q[:, 1].min() > edge_px
            and q[:, 0].max() < cam.width - 1 - edge_px and q[:, 1].max() < cam.height - 1 - edge_px):
        return False
    xy = rig.project_to_projector(edges(grid) @ R.T + t)
    if not (np.all(np.isfinite(xy)) and xy[:, 0].min() > 2 and xy[:, 1].min() > 2
            and xy[:, 0].max() < proj.width - 3 and xy[:, 1].max() < proj.height - 3):
        return False
    # both the camera and the projector see the board's front at less than 65 degrees
    n = -R[:, 2]  # board normal towards the camera side
    centre = np.array([(cols - 1) * s / 2, (rows - 1) * s / 2, 0.0]) @ R.T + t
    to_cam = -centre / np.linalg.norm(centre)
    to_proj = (rig.t_cam_proj - centre) / np.linalg.norm(rig.t_cam_proj - centre)
    return bool(n @ to_cam > np.cos(np.radians(65)) and n @ to_proj > np.cos(np.radians(65)))


def _grid_projector_x(rig: Rig, R, t, cols, rows, s) -> tuple[float, float]:
    """(min, max) projector column covered by the printed grid of a board pose."""
    g = np.array([[x, y, 0.0] for x in np.linspace(-s, cols * s, 5) for y in np.linspace(-s, rows * s, 5)])
    x = rig.project_to_projector(g @ R.T + t)[:, 0]
    return float(x.min()), float(x.max())


def board_poses(rig: Rig, board=DEFAULT_BOARD, n_poses: int = 12, seed: int = 0,
                margin_mm: float | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n_poses`` varied board poses ``(R_cam_board (3, 3), t_cam_board (3,) mm)``, deterministic in ``seed``.

    Pose k tilts towards direction ``2 pi k / n`` by 15-42 degrees (pose 0: at most 8 degrees)
    with up to 15 degrees of roll, at 550-800 mm.  Poses cycle through the centre, the left and
    the right of the projector frame; a side pose is the candidate (of up to 25 valid ones)
    reaching furthest towards that side, so the session covers every stripe boundary (light
    plane) from near projector column 0 to near the last one.  Every pose keeps the board
    inside the camera image and its printed grid inside the projector frame.
    """
    cols, rows, s = int(board[0]), int(board[1]), float(board[2])
    m = s if margin_mm is None else float(margin_mm)
    if n_poses < 1:
        raise GBError(f"need at least one board pose, got {n_poses}")
    rng = np.random.default_rng(seed)
    proj = rig.projector
    Kinv = np.linalg.inv(proj.K)
    C = rig.t_cam_proj
    centre_b = np.array([(cols - 1) * s / 2, (rows - 1) * s / 2, 0.0])
    poses = []
    for k in range(n_poses):
        phi = 2 * np.pi * k / n_poses
        side = (0, -1, 1)[k % 3]
        best, best_score, n_valid = None, -np.inf, 0
        for attempt in range(3000):
            relax = min(1.0, attempt / 1500)  # widen the search if a pose is hard to place
            mag = rng.uniform(0, 8) if k == 0 else rng.uniform(15 - 10 * relax, 42 - 12 * relax)
            ph = phi + rng.uniform(-0.4, 0.4)
            R = _rot(mag * np.sin(ph), mag * np.cos(ph), rng.uniform(-15, 15))
            z = rng.uniform(550, 800)
            # aim the board centre along a projector ray: centre, left or right of its frame
            xp = proj.width * (0.5 + side * rng.uniform(0.1, 0.4) * (1 - 0.5 * relax))
            yp = proj.height * (0.5 + rng.uniform(-0.25, 0.25) * (1 - 0.5 * relax))
            d = rig.R_cam_proj @ (Kinv @ [xp, yp, 1.0])
            centre = C + d * (z - C[2]) / d[2]
            t = centre - R @ centre_b
            if not _pose_ok(rig, R, t, cols, rows, s, m):
                continue
            n_valid += 1
            lo, hi = _grid_projector_x(rig, R, t, cols, rows, s)
            score = -lo if side < 0 else hi if side > 0 else 0.0
            if score > best_score:
                best, best_score = (R, t), score
            if side == 0 or n_valid >= 25:
                break
        if best is None:
            raise GBError(f"could not place board pose {k} of a {cols}x{rows} board of {s} mm squares "
                          "inside the camera image and projector frame; use a smaller board (--square-mm)")
        poses.append(best)
    return poses


def write_session(out_dir, rig: Rig, pattern: PatternSpec, board=DEFAULT_BOARD, n_poses: int = 12,
                  preset="typical", seed: int = 0, progress: bool = True, compact: bool = False) -> Path:
    """Render a simulated calibration session into ``out_dir`` (created if missing); returns it.

    ``board = (cols, rows, square_mm)`` inner corners; ``preset`` a name or ``gbscan.sim.Conditions``;
    ``compact`` writes PNGs at maximum compression (for bundled data; slower).
    """
    from gbscan import sim

    out = Path(out_dir)
    cols, rows, s = int(board[0]), int(board[1]), float(board[2])
    if cols < 3 or rows < 3 or not s > 0:
        raise GBError(f"board must have at least 3x3 inner corners and a positive square size, got {board}")
    if (pattern.width, pattern.height) != (rig.projector.width, rig.projector.height):
        raise GBError(f"pattern is {pattern.width}x{pattern.height} but the projector is "
                      f"{rig.projector.width}x{rig.projector.height}")
    cond = sim.preset(preset)
    make_dir(out, "session folder")
    frames = calibration_frames(pattern)
    poses = board_poses(rig, (cols, rows, s), n_poses, seed)
    t0 = time.time()
    for k, (R, t) in enumerate(poses):
        scene = sim.scenes.board(cols, rows, s, R, t)
        tr = sim.trace(rig, scene, cond)
        pose_dir = out / f"pose_{k:03d}"
        pose_dir.mkdir(exist_ok=True)
        for i, (name, frame) in enumerate(frames.items()):
            r = sim.render_traced(rig, tr, frame, np.random.default_rng([int(seed), k, i]))
            _write_png(pose_dir / f"{name}.png", r.image, compact)
        if progress:
            print(f"  pose {k + 1}/{len(poses)}: {len(frames)} frames ({time.time() - t0:.0f} s)", file=sys.stderr)
    cam, proj = rig.camera, rig.projector
    truth = {
        "schema": "gbcal.simtruth",
        "version": 1,
        "camera": {"width": cam.width, "height": cam.height, "matrix": cam.K, "distortion": cam.dist},
        "projector": {"width": proj.width, "height": proj.height, "matrix": proj.K},
        "R_cam_proj": rig.R_cam_proj,
        "t_cam_proj": rig.t_cam_proj,
        "pattern": pattern.to_dict(),
        "board": {"cols": cols, "rows": rows, "square_mm": s},
        "conditions": cond.to_dict(),
        "seed": int(seed),
        "poses": [{"R_cam_board": R, "t_cam_board": t} for R, t in poses],
    }
    save_yaml(out / "truth.yaml", truth, header="# true rig and board poses of a simulated session (gbcal simulate-session)\n")
    write_session_yaml(out, board=(cols, rows, s), camera_size=cam.size, projector_size=(proj.width, proj.height),
                       frames=list(frames), extra={"pattern": pattern.to_dict(), "simulated": True})
    return out


def load_truth(session_dir) -> dict:
    """Read ``truth.yaml`` of a simulated session.

    Returns a dict: ``rig`` (gbscan.rig.Rig), ``camera`` (Camera), ``pattern`` (PatternSpec),
    ``board`` ((cols, rows, square_mm)), ``conditions`` (gbscan.sim.Conditions), ``seed``,
    ``poses`` (list of (R_cam_board (3, 3), t_cam_board (3,))).
    """
    from gbscan.camera import Camera
    from gbscan.rig import Projector
    from gbscan.sim import Conditions

    path = Path(session_dir) / "truth.yaml"
    d = load_yaml(path, "simulated-session truth file")
    try:
        cam = Camera(d["camera"]["width"], d["camera"]["height"], np.array(d["camera"]["matrix"]),
                     np.array(d["camera"]["distortion"]))
        proj = Projector(d["projector"]["width"], d["projector"]["height"], np.array(d["projector"]["matrix"]))
        rig = Rig(cam, proj, np.array(d["R_cam_proj"]), np.array(d["t_cam_proj"]))
        b = d["board"]
        return {
            "rig": rig,
            "camera": cam,
            "pattern": PatternSpec.from_dict(d["pattern"]),
            "board": (int(b["cols"]), int(b["rows"]), float(b["square_mm"])),
            "conditions": Conditions.from_dict(d["conditions"]),
            "seed": d.get("seed"),
            "poses": [(np.array(p["R_cam_board"], dtype=np.float64), np.array(p["t_cam_board"], dtype=np.float64))
                      for p in d["poses"]],
        }
    except (KeyError, TypeError, ValueError) as e:
        raise GBError(f"truth file {path} is malformed ({type(e).__name__}: {e}); regenerate the session") from None
