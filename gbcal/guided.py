"""Guided capture of a rig-calibration session: the flow, independent of windows and cameras.

``scripts/guided_calibration.py`` runs it at a real rig (Tk or OpenCV windows, OpenCV
VideoCapture) and against the simulated rig (``--simulate``); tests run it headless with scripted
devices.  Everything that decides something lives here and is tested without a display:

* :class:`Coverage` -- which cells of the camera image have held board corners, and which
  board tilts (left / right / up / down / square-on) have been captured.
* :class:`GuidedState` -- accepted captures, the last message, what a key press means
  (:meth:`GuidedState.decide`) and what the live window shows (:meth:`GuidedState.view`).
* :func:`check_capture` -- the quality checks of a pose's frames: board found and sharp, board
  still between the first and the last frame, exposure (no saturation) and projector modulation.
* :class:`SessionWriter` -- writes the session atomically: captures go to a hidden staging folder
  beside the session folder and the folder appears under its name only when the session is
  complete (``session.yaml`` written).  An abort (ESC) leaves nothing; an error or Ctrl-C after
  some captures leaves ``SESSION.incomplete/`` with ``INCOMPLETE.txt`` saying why (it has no
  ``session.yaml``, so no tool mistakes it for a session).
* :func:`run_capture` -- the loop tying them together over three duck-typed devices:

  ``display``: ``show_projector(frame_rgb)``, ``show_live(image_rgb, corners, view)``,
  ``wait_ms(ms)`` (keeps the windows responsive while waiting), ``poll_key() -> str``
  (``""``, ``" "``, ``"q"``, ``"u"`` or ``"esc"``), ``drain_keys() -> list[str]``, ``close()``
  (:mod:`gbcal.display`).
  ``camera``: ``read() -> (H, W, 3) uint8 RGB``, ``drop(n)`` (discard ``n`` buffered frames),
  ``close()``.

Synchronisation of projector and camera (:func:`capture_pose`): for every frame the projector
window is updated and the window system flushed (``show_projector``), then the flow waits
``settle_ms`` (projector input lag + one camera exposure; the windows stay responsive), then drops
``drop_frames`` camera frames (frames buffered by the driver before the change), then reads one.
A camera that still lags shows up in the checks: the black frame looks like the white one.

Units: pixels (px) of the camera image, grey levels (DN, 0-255), ms.
"""
from __future__ import annotations

import dataclasses
import os
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from gbscan.errors import GBError

from .board import MAX_SHARPNESS_PX, Board, Detection

#: Tilt directions of a board, as shown to the user.
TILT_BINS = ("left", "right", "up", "down", "square-on")
#: Keys the flow understands (display backends map their key codes to these).
KEY_CAPTURE, KEY_FINISH, KEY_UNDO, KEY_ABORT = " ", "q", "u", "esc"
#: A board whose normal is within this angle of the optical axis counts as square-on.
SQUARE_ON_DEG = 10.0
#: Mean white-minus-black below this (grey levels) means the camera saw the same projector frame twice.
SAME_FRAME_DN = 4.0
#: Image grid of the coverage map (columns, rows).
DEFAULT_GRID = (4, 3)


# -- coverage ----------------------------------------------------------------------------------
def tilt_deg(normal) -> float:
    """Angle (degrees) between a board normal (camera frame, away from the camera) and the optical axis."""
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    return float(np.degrees(np.arccos(np.clip(abs(n[2]), -1.0, 1.0))))


def tilt_bin(normal, square_on_deg: float = SQUARE_ON_DEG) -> str:
    """The direction a board normal (camera frame, pointing away from the camera) is tilted to.

    ``"square-on"`` within ``square_on_deg`` of the optical axis; otherwise the dominant image
    direction of the normal: ``"right"`` (+x), ``"left"``, ``"down"`` (+y) or ``"up"``.
    """
    n = np.asarray(normal, dtype=np.float64)
    if n.shape != (3,) or not np.all(np.isfinite(n)) or not np.linalg.norm(n) > 0:
        raise GBError(f"tilt_bin: expected a finite 3-vector board normal, got {normal!r}")
    if tilt_deg(n) < square_on_deg:
        return "square-on"
    nx, ny = n[0], n[1]
    if abs(nx) >= abs(ny):
        return "right" if nx > 0 else "left"
    return "down" if ny > 0 else "up"


def _region_name(i: int, j: int, grid: tuple[int, int]) -> str:
    """Plain-words name of coverage cell (column i, row j), e.g. 'top-left', 'middle-right'."""
    gx, gy = grid
    rows = {0: "top", gy - 1: "bottom"}.get(j, "middle") if gy > 1 else ""
    if gx == 1:
        cols = ""
    elif i == 0:
        cols = "left"
    elif i == gx - 1:
        cols = "right"
    else:
        cols = "centre" if gx == 3 else ("centre-left" if i < gx / 2 else "centre-right")
    return "-".join(x for x in (rows, cols) if x) or "centre"


@dataclass(frozen=True)
class Coverage:
    """What the accepted captures cover.

    image_size : (width, height) px of the camera image.
    cells : (rows, cols) int, number of captures with at least one corner in each image cell.
    tilts : captures per tilt bin (:data:`TILT_BINS`).
    """

    image_size: tuple[int, int]
    cells: np.ndarray
    tilts: dict

    @property
    def grid(self) -> tuple[int, int]:
        return (self.cells.shape[1], self.cells.shape[0])

    @classmethod
    def of(cls, image_size, corners_list=(), normals=(), grid=DEFAULT_GRID) -> "Coverage":
        """Coverage of captures given by their (N, 2) corners px and board normals."""
        W, H = int(image_size[0]), int(image_size[1])
        gx, gy = int(grid[0]), int(grid[1])
        if W <= 0 or H <= 0 or gx < 1 or gy < 1:
            raise GBError(f"coverage needs a positive image size and grid, got {image_size} and {grid}")
        cells = np.zeros((gy, gx), np.int64)
        tilts = dict.fromkeys(TILT_BINS, 0)
        for corners, normal in zip(corners_list, normals):
            c = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
            cx = np.clip(np.floor((c[:, 0] + 0.5) / W * gx).astype(int), 0, gx - 1)
            cy = np.clip(np.floor((c[:, 1] + 0.5) / H * gy).astype(int), 0, gy - 1)
            hit = np.zeros((gy, gx), bool)
            hit[cy, cx] = True
            cells += hit
            tilts[tilt_bin(normal)] += 1
        return cls((W, H), cells, tilts)

    def missing_regions(self) -> list[str]:
        gx, gy = self.grid
        return [_region_name(i, j, (gx, gy)) for j in range(gy) for i in range(gx) if self.cells[j, i] == 0]

    def missing_tilts(self) -> list[str]:
        return [k for k in ("left", "right", "up", "down") if self.tilts[k] == 0]

    @property
    def complete(self) -> bool:
        return not self.missing_regions() and not self.missing_tilts()

    def missing(self) -> str:
        """One line for the log: what is still uncovered."""
        parts = []
        empty = int((self.cells == 0).sum())
        if empty:
            parts.append(f"{empty} of {self.cells.size} image regions without corners")
        if self.missing_tilts():
            parts.append("no board tilted " + "/".join(self.missing_tilts()))
        return "; ".join(parts) if parts else "coverage complete"

    def hint(self) -> str:
        """What the person should do next, in words (a missing tilt first, then a missing region)."""
        tilts = self.missing_tilts()
        if tilts:
            return f"next: tilt the board {tilts[0]} by 20-40 degrees"
        regions = self.missing_regions()
        if regions:
            return f"next: move the board towards the {regions[0]} of the image"
        return "coverage complete: vary the distance, or q to finish"


def board_normal(corners: np.ndarray, board: Board, image_size: tuple[int, int]) -> np.ndarray:
    """(3,) approximate unit board normal (camera frame, away from the camera) from one capture's
    corners (focal length from the view itself; enough to bin the tilt)."""
    from .intrinsics import board_normals

    return board_normals([np.asarray(corners, np.float64)], board, image_size)[0]


# -- live detection ----------------------------------------------------------------------------
#: The live view looks for the board in at most this many pixels of width (faster on big images).
LIVE_WIDTH_PX = 800


def live_detect(image: np.ndarray, board: Board, max_sharpness_px: float = MAX_SHARPNESS_PX
                ) -> tuple[np.ndarray | None, str]:
    """Fast board finder for the live view: ``(corners (N, 2) px or None, problem)``.

    OpenCV's classic detector with its fast check (a few ms at 640x480), else the sector-based
    one on an image at most :data:`LIVE_WIDTH_PX` wide (tens of ms; the full detector of
    :func:`gbcal.board.detect_with_reason` takes up to ~0.5 s when its first try fails).  Corners
    are in the detector's order, not refined: for the overlay and the go-ahead only; a capture is
    checked with the full detector (:func:`check_capture`).  ``problem`` is "" when the board is
    usable, else why not (not found, touching the border, blurred); corners are returned with a
    problem when the board was found.
    """
    import cv2

    from .board import BORDER_PX, as_gray

    gray = as_gray(image)
    h, w = gray.shape
    size = board.pattern_size
    ok, c = cv2.findChessboardCorners(gray, size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
                                      | cv2.CALIB_CB_FAST_CHECK)
    if not ok or c is None or c.size != 2 * board.n_corners:
        small, scale = gray, 1.0
        while small.shape[1] > LIVE_WIDTH_PX:
            small, scale = cv2.pyrDown(small), scale * 2.0
        ok, c = cv2.findChessboardCornersSB(small, size, cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not ok or c is None or c.size != 2 * board.n_corners:
            return None, f"no {board.cols}x{board.rows} board found (whole board in view, sharp, lit?)"
        c = (c.reshape(-1, 2).astype(np.float64) + 0.5) * scale - 0.5
    c = c.reshape(-1, 2).astype(np.float64)
    margin = min(c[:, 0].min(), c[:, 1].min(), (w - 1) - c[:, 0].max(), (h - 1) - c[:, 1].max())
    if margin < BORDER_PX + 2:
        return c, "board touches the image border: bring it fully into view"
    try:  # edge width (10-90 % rise, px), as the full detector measures it
        res = cv2.estimateChessboardSharpness(gray, size, c.astype(np.float32).reshape(-1, 1, 2))
        sharp = float((res[0] if isinstance(res, tuple) else res)[0])
    except cv2.error:
        sharp = float("nan")
    if np.isfinite(sharp) and sharp > max_sharpness_px:
        return c, f"board blurred (edges {sharp:.1f} px, limit {max_sharpness_px:g}): refocus or hold it still"
    return c, ""


# -- quality checks ----------------------------------------------------------------------------
@dataclass(frozen=True)
class QualityLimits:
    """Limits of :func:`check_capture`.

    max_sharpness_px : widest accepted board edge (10-90 % rise, px; ``cv2.estimateChessboardSharpness``).
    max_motion_px : largest corner shift between the first and the last white frame of a pose.
    saturation_dn : a channel value at or above this is saturated.
    max_saturated_fraction : largest accepted fraction of board pixels saturated in the white frame.
    min_modulation_dn : least accepted mean white-minus-black grey level on the board's white squares.
    max_unlit_fraction : above this fraction of white squares below ``min_modulation_dn`` the
        capture is rejected (part of the board outside the projector's light).
    """

    max_sharpness_px: float = MAX_SHARPNESS_PX
    max_motion_px: float = 0.5
    saturation_dn: int = 254
    max_saturated_fraction: float = 0.02
    min_modulation_dn: float = 30.0
    max_unlit_fraction: float = 0.25

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if not np.isfinite(v) or v <= 0:
                raise GBError(f"quality limit {f.name} must be a positive number, got {v!r}")


@dataclass(frozen=True)
class CaptureCheck:
    """Outcome of :func:`check_capture`.

    ok : the capture is usable.  reason : "" when ok, else one sentence naming the first failed
    check and what to do.  detection : the board in the (first) white frame, refined, or None.
    Figures (NaN where not measured): sharpness_px (edge width), motion_px (largest corner shift
    first -> last white frame), saturated_fraction (of board pixels, white frame), modulation_dn
    (mean white - black on white squares), unlit_fraction (of white squares).
    """

    ok: bool
    reason: str
    detection: Detection | None
    sharpness_px: float = float("nan")
    motion_px: float = float("nan")
    saturated_fraction: float = float("nan")
    modulation_dn: float = float("nan")
    unlit_fraction: float = float("nan")

    def figures(self) -> dict:
        out = {}
        for k in ("sharpness_px", "motion_px", "saturated_fraction", "modulation_dn", "unlit_fraction"):
            v = getattr(self, k)
            if np.isfinite(v):
                out[k] = round(float(v), 4)
        return out


def _gray(image: np.ndarray) -> np.ndarray:
    from .board import as_gray

    return as_gray(image).astype(np.float32)


def board_mask(corners: np.ndarray, board: Board, image_size: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: the board's printed grid area (the inner-corner grid grown by one square)."""
    import cv2

    g = np.asarray(corners, np.float64).reshape(board.rows, board.cols, 2)
    # each outer inner corner, one square outwards along the grid's own directions
    quad = [g[r, c] + (g[r, c] - g[r, c2]) + (g[r, c] - g[r2, c])
            for r, c, r2, c2 in ((0, 0, 1, 1), (0, -1, 1, -2), (-1, -1, -2, -2), (-1, 0, -2, 1))]
    W, H = image_size
    mask = np.zeros((H, W), np.uint8)
    cv2.fillConvexPoly(mask, np.round(np.array(quad)).astype(np.int32), 1)
    return mask.astype(bool)


def white_square_centres(corners: np.ndarray, board: Board) -> np.ndarray:
    """(M, 5, 2) px: centre and four half-way points of every white square between inner corners
    (canonical order: the square between corners (0, 0) and (1, 1) is white)."""
    g = np.asarray(corners, np.float64).reshape(board.rows, board.cols, 2)
    a, b, c, d = g[:-1, :-1], g[:-1, 1:], g[1:, :-1], g[1:, 1:]
    centre = (a + b + c + d) / 4.0
    pts = np.stack([centre] + [centre + 0.5 * (x - centre) for x in (a, b, c, d)], axis=2)
    jj, ii = np.mgrid[0 : board.rows - 1, 0 : board.cols - 1]
    return pts[(ii + jj) % 2 == 0]


def _sample(gray: np.ndarray, pts: np.ndarray) -> np.ndarray:
    import cv2

    flat = pts.reshape(1, -1, 2).astype(np.float32)
    vals = cv2.remap(gray, flat[..., 0], flat[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return vals.reshape(pts.shape[:-1])


def check_capture(white: np.ndarray, black: np.ndarray, white_end: np.ndarray, board: Board,
                  limits: QualityLimits = QualityLimits()) -> CaptureCheck:
    """Quality checks of one pose: the white frame at the start, the black frame, and a white
    frame taken again after the last pattern frame (all (H, W, 3) uint8 RGB of one camera).

    In order, the first failure is the reason: board found in the white frame (with the
    detector's own reasons: not found, cut by the border, blurred beyond
    ``max_sharpness_px``, low contrast); black frame different from the white one on the
    board's white squares (else the camera did not see the projector change: no
    synchronisation, or the window is not on the projector); board found again in the final
    white frame with its corners within ``max_motion_px`` of the first (board held still);
    white frame not saturated on the board; mean projector modulation (white - black on the
    white squares) at least ``min_modulation_dn`` and at most ``max_unlit_fraction`` of the
    white squares below it (board in the projector's light).
    """
    from .board import detect_with_reason

    shapes = {np.asarray(x).shape for x in (white, black, white_end)}
    if len(shapes) != 1:
        raise GBError(f"check_capture: frames of one pose differ in size: {sorted(shapes)}")
    det, why = detect_with_reason(white, board, max_sharpness_px=limits.max_sharpness_px)
    if det is None:
        return CaptureCheck(False, why, None)
    fig = {"sharpness_px": det.sharpness_px}
    pts = white_square_centres(det.corners, board)
    w = _sample(_gray(white), pts).mean(axis=1)
    b = _sample(_gray(black), pts).mean(axis=1)
    mod = w - b
    if float(mod.mean()) < SAME_FRAME_DN:
        return CaptureCheck(False, f"the black frame looks the same as the white one (board {b.mean():.0f} vs "
                                   f"{w.mean():.0f} grey levels): the camera grabbed before the projector changed "
                                   "frame, or the projector window is not on the projector; raise --settle-ms / "
                                   "--drop-frames, check --screen-x/--screen-y, lock the camera's exposure", det,
                            **fig, modulation_dn=float(mod.mean()))
    det_end, why_end = detect_with_reason(white_end, board, max_sharpness_px=2 * limits.max_sharpness_px)
    if det_end is None:
        return CaptureCheck(False, "the board moved or left the view during the capture (not found in the final "
                                   f"white frame: {why_end}); hold it still until the capture ends", det, **fig)
    motion = float(np.max(np.linalg.norm(det_end.corners - det.corners, axis=1)))
    fig["motion_px"] = motion
    if not motion <= limits.max_motion_px:
        return CaptureCheck(False, f"the board moved during the capture: corners shifted by up to {motion:.2f} px "
                                   f"(limit {limits.max_motion_px:g} px); rest it on a stand or hold it still "
                                   "until the capture ends", det, **fig)
    size = (white.shape[1], white.shape[0])
    mask = board_mask(det.corners, board, size)
    sat = float(np.mean(np.any(np.asarray(white)[mask] >= limits.saturation_dn, axis=-1))) if mask.any() else 0.0
    fig["saturated_fraction"] = sat
    if sat > limits.max_saturated_fraction:
        return CaptureCheck(False, f"overexposed: {100 * sat:.1f} % of the board is saturated in the white frame "
                                   f"(limit {100 * limits.max_saturated_fraction:g} %); lower the camera exposure "
                                   "or gain, or the projector brightness", det, **fig)
    fig["modulation_dn"] = float(mod.mean())
    fig["unlit_fraction"] = float(np.mean(mod < limits.min_modulation_dn))
    if fig["modulation_dn"] < limits.min_modulation_dn:
        return CaptureCheck(False, f"too little projector light on the board: white minus black is "
                                   f"{fig['modulation_dn']:.0f} grey levels on the white squares (need "
                                   f"{limits.min_modulation_dn:g}); dim the room, lower the ambient light, raise "
                                   "the exposure, or move the board closer to the projector", det, **fig)
    if fig["unlit_fraction"] > limits.max_unlit_fraction:
        return CaptureCheck(False, f"{100 * fig['unlit_fraction']:.0f} % of the board's white squares are outside "
                                   "the projector's light; move the board into the projected area", det, **fig)
    return CaptureCheck(True, "", det, **fig)


# -- the flow state ----------------------------------------------------------------------------
@dataclass(frozen=True)
class Accepted:
    """One accepted capture: its pose folder name, refined corners (N, 2) px, board normal (3,)
    and tilt bin, and the quality figures."""

    name: str
    corners: np.ndarray
    normal: np.ndarray
    tilt: str
    figures: dict


@dataclass(frozen=True)
class LiveView:
    """What the live window shows (backend-independent)."""

    status: str          # board found / not found (and why), or "capturing ..."
    status_ok: bool
    message: str         # result of the last action (accepted / rejected with the reason / undone)
    message_ok: bool
    captured: int
    n_poses: int
    coverage: Coverage
    hint: str
    keys: str = "SPACE capture   u undo last   q finish   ESC abort"

    @property
    def left(self) -> int:
        return max(self.n_poses - self.captured, 0)


class Action:
    NONE, CAPTURE, NO_BOARD, UNDO, NOTHING_TO_UNDO, FINISH, ABORT = (
        "none", "capture", "no-board", "undo", "nothing-to-undo", "finish", "abort")


@dataclass
class GuidedState:
    """Accepted captures and the last message of a guided capture; pure bookkeeping."""

    board: Board
    image_size: tuple[int, int]
    n_poses: int
    grid: tuple[int, int] = DEFAULT_GRID
    accepted: list = field(default_factory=list)
    message: str = "show the board to the camera, then SPACE"
    message_ok: bool = True
    rejected: int = 0

    def __post_init__(self):
        if isinstance(self.n_poses, bool) or not isinstance(self.n_poses, (int, np.integer)) or self.n_poses < 1:
            raise GBError(f"the number of poses must be a positive integer, got {self.n_poses!r}")

    @property
    def left(self) -> int:
        return max(self.n_poses - len(self.accepted), 0)

    @property
    def coverage(self) -> Coverage:
        return Coverage.of(self.image_size, [a.corners for a in self.accepted], [a.normal for a in self.accepted],
                           self.grid)

    def decide(self, key: str, board_seen: bool) -> str:
        """What a key press means now (:class:`Action`)."""
        if key == KEY_ABORT:
            return Action.ABORT
        if key == KEY_FINISH or self.left == 0:
            return Action.FINISH
        if key == KEY_UNDO:
            return Action.UNDO if self.accepted else Action.NOTHING_TO_UNDO
        if key == KEY_CAPTURE:
            return Action.CAPTURE if board_seen else Action.NO_BOARD
        return Action.NONE

    def accept(self, name: str, check: CaptureCheck) -> Accepted:
        c = check.detection.corners
        n = board_normal(c, self.board, self.image_size)
        a = Accepted(name, c, n, tilt_bin(n), check.figures())
        self.accepted.append(a)
        fig = a.figures
        self.message = (f"capture {len(self.accepted)} accepted ({a.tilt}, {tilt_deg(n):.0f} deg; edges "
                        f"{fig.get('sharpness_px', float('nan')):.1f} px, moved {fig.get('motion_px', 0):.2f} px)")
        self.message_ok = True
        return a

    def reject(self, reason: str) -> None:
        self.rejected += 1
        self.message = f"rejected: {reason}"
        self.message_ok = False

    def undo(self) -> Accepted:
        a = self.accepted.pop()
        self.message = f"capture {len(self.accepted) + 1} ({a.name}) removed"
        self.message_ok = True
        return a

    def view(self, board_ok: bool, problem: str = "", status: str | None = None) -> LiveView:
        """The live window's content; ``board_ok``: the live detector found a usable board, else
        ``problem`` says why not; ``status`` replaces the status line (during a capture)."""
        cov = self.coverage
        if status is not None:
            st, ok = status, True
        elif board_ok:
            st, ok = "board found: SPACE to capture", True
        else:
            st, ok = problem or "no board", False
        return LiveView(st, ok, self.message, self.message_ok, len(self.accepted), self.n_poses, cov, cov.hint())


# -- the session folder ------------------------------------------------------------------------
def check_new_session_folder(path) -> Path:
    """GBError unless ``path`` is a folder that does not exist yet or is empty."""
    path = Path(path)
    if path.exists():
        if not path.is_dir():
            raise GBError(f"session folder {path} exists and is not a folder; choose a new folder")
        if any(path.glob("pose_*")):
            raise GBError(f"session folder {path} already holds captures; choose a new folder")
        if any(path.iterdir()):
            raise GBError(f"session folder {path} is not empty; choose a new folder")
    return path


def _usual_mode(folder: Path) -> None:
    """mkdtemp makes 0700 folders; a session gets the usual mode (umask)."""
    mask = os.umask(0)
    os.umask(mask)
    os.chmod(folder, 0o777 & ~mask)


class SessionWriter:
    """Writes a capture session atomically (module docstring).

    Captures go to a hidden staging folder ``.<name>.partial-XXXX`` beside ``root``; each pose is
    written into ``pose_NNN.tmp/`` and renamed to ``pose_NNN/`` when all its frames are on disk.
    :meth:`publish` writes ``session.yaml`` and renames the staging folder to ``root``.
    ``capture_log.yaml`` records every capture attempt (accepted or rejected with its reason)
    and is rewritten atomically after each one.
    """

    def __init__(self, root):
        from gbscan.io import make_dir

        self.root = check_new_session_folder(root)
        parent = self.root.resolve().parent
        make_dir(parent, "folder for the session")
        try:
            self.staging = Path(tempfile.mkdtemp(prefix=f".{self.root.name}.partial-", dir=parent))
        except OSError as e:
            raise GBError(f"cannot create a staging folder in {parent}: {e.strerror}") from None
        self.poses: list[Path] = []
        self.events: list[dict] = []
        self.t0 = time.time()

    def add_pose(self, shots: dict) -> str:
        """Write one pose's frames (name -> (H, W, 3) uint8 RGB); returns the pose folder name."""
        from gbscan.io import write_png

        name = f"pose_{len(self.poses):03d}"
        tmp = self.staging / f"{name}.tmp"
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir()
        for frame, img in shots.items():
            write_png(tmp / f"{frame}.png", img)
        final = self.staging / name
        os.replace(tmp, final)
        self.poses.append(final)
        return name

    def remove_last(self) -> str:
        p = self.poses.pop()
        shutil.rmtree(p)
        return p.name

    def log_event(self, event: str, **info) -> None:
        from gbscan.io import save_yaml

        self.events.append({"t_s": round(time.time() - self.t0, 2), "event": event, **info})
        save_yaml(self.staging / "capture_log.yaml",
                  {"schema": "gbcal.capture_log", "version": 1, "attempts": self.events},
                  header="# every capture attempt of the guided calibration, with the reason for each rejection\n")

    def publish(self, **session) -> Path:
        """Write ``session.yaml`` (``gbscan.io.write_session_yaml`` arguments) and move the
        staging folder to the session folder; returns it."""
        from gbscan.io import write_session_yaml

        write_session_yaml(self.staging, **session)
        check_new_session_folder(self.root)
        if self.root.exists():
            self.root.rmdir()  # empty (checked); os.replace onto a folder is not portable
        _usual_mode(self.staging)
        os.replace(self.staging, self.root)
        return self.root

    def discard(self) -> None:
        shutil.rmtree(self.staging, ignore_errors=True)

    def keep_incomplete(self, why: str) -> Path:
        """Move what was captured to ``<root>.incomplete[-N]/`` with ``INCOMPLETE.txt``; returns it."""
        from gbscan.io import write_text_atomic

        write_text_atomic(self.staging / "INCOMPLETE.txt",
                          f"This capture session did not finish: {why}\n{len(self.poses)} poses were captured "
                          "(pose_NNN/); there is no session.yaml, so this is not a usable session.\n"
                          "Capture again into a new folder.\n")
        dest = Path(f"{self.root}.incomplete")
        k = 2
        while dest.exists():
            dest = Path(f"{self.root}.incomplete-{k}")
            k += 1
        _usual_mode(self.staging)
        os.replace(self.staging, dest)
        return dest


# -- the loop ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class CaptureOutcome:
    """Result of :func:`run_capture`: ``status`` is ``"complete"`` (session written),
    ``"empty"`` (finished with no capture: nothing written) or ``"aborted"`` (ESC: nothing written)."""

    status: str
    session: Path | None
    accepted: tuple
    rejected: int
    coverage: Coverage | None


def capture_pose(display, camera, frames: dict, settle_ms: float, drop_frames: int,
                 progress: Callable[[int, int], None] | None = None) -> tuple[dict, np.ndarray]:
    """Show every frame and grab one camera image of each (synchronised as in the module
    docstring); then the white frame again.  Returns ``(shots by name, final white image)``."""
    shots = {}
    order = list(frames.items()) + [("white", frames["white"])]
    for i, (name, frame) in enumerate(order):
        display.show_projector(frame)
        display.wait_ms(settle_ms)
        camera.drop(drop_frames)
        img = camera.read()
        if i < len(frames):
            shots[name] = img
        if progress:
            progress(i + 1, len(order), img)
    return shots, img


def _check_camera_image(img, size=None) -> np.ndarray:
    a = np.asarray(img)
    if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] != 3:
        raise GBError(f"the camera delivered {a.dtype} images of shape {a.shape}; expected colour (H, W, 3) 8-bit")
    if size is not None and (a.shape[1], a.shape[0]) != tuple(size):
        raise GBError(f"the camera changed its image size from {size[0]}x{size[1]} to {a.shape[1]}x{a.shape[0]} "
                      "during the session; fix the camera's resolution (--camera-size) and start again")
    return a


def run_capture(session_dir, display, camera, board: Board, spec, *, n_poses: int, settle_ms: float = 150.0,
                drop_frames: int = 4, limits: QualityLimits = QualityLimits(), grid=DEFAULT_GRID,
                log: Callable[[str], None] = print, extra: dict | None = None) -> CaptureOutcome:
    """Run the guided capture loop (module docstring) and write the session folder.

    ``spec`` is the :class:`gbscan.pattern.PatternSpec` of the calibration frames
    (:func:`gbcal.patterns.calibration_frames`); ``extra`` goes into ``session.yaml``.
    Keys: SPACE capture (when the board is seen), u undo the last capture, q finish, ESC abort.
    The loop ends by itself after ``n_poses`` accepted captures.
    """
    from .patterns import calibration_frames

    if settle_ms < 0 or drop_frames < 0:
        raise GBError(f"settle time and dropped frames must be >= 0, got {settle_ms} ms and {drop_frames}")
    writer = SessionWriter(session_dir)
    frames = calibration_frames(spec)
    state: GuidedState | None = None
    done = False
    try:
        display.show_projector(frames["white"])
        display.wait_ms(settle_ms)
        camera.drop(drop_frames)
        while True:
            live = camera.read()
            live = _check_camera_image(live, state.image_size if state else None)
            if state is None:
                state = GuidedState(board, (live.shape[1], live.shape[0]), n_poses, grid)
            corners, why = live_detect(live, board, limits.max_sharpness_px)
            display.show_live(live, corners, state.view(not why, why))
            action = state.decide(display.poll_key(), not why)
            if action == Action.NONE:
                continue
            if action == Action.ABORT:
                break
            if action == Action.FINISH:
                break
            if action == Action.NOTHING_TO_UNDO:
                state.message, state.message_ok = "nothing to undo", True
                continue
            if action == Action.UNDO:
                a = state.undo()
                writer.remove_last()
                writer.log_event("undo", pose=a.name)
                log(f"  {state.message}; {state.left} captures left")
                continue
            if action == Action.NO_BOARD:
                state.reject(why)
                writer.log_event("rejected", reason=why)
                log(f"  {state.message}")
                continue
            # Action.CAPTURE
            t0 = time.perf_counter()

            def progress(i, n, img):
                display.show_live(img, None, state.view(False, status=f"capturing frame {i}/{n}: hold the board still"))

            shots, white_end = capture_pose(display, camera, frames, settle_ms, drop_frames, progress)
            for img in list(shots.values()) + [white_end]:
                _check_camera_image(img, state.image_size)
            check = check_capture(shots["white"], shots["black"], white_end, board, limits)
            dt = time.perf_counter() - t0
            if check.ok:
                name = writer.add_pose(shots)
                a = state.accept(name, check)
                writer.log_event("accepted", pose=name, tilt=a.tilt, tilt_deg=round(tilt_deg(a.normal), 1),
                                 **check.figures())
                log(f"  pose {len(state.accepted)}/{n_poses} captured in {dt:.1f} s ({a.tilt}); still missing: "
                    f"{state.coverage.missing()}")
            else:
                state.reject(check.reason)
                writer.log_event("rejected", reason=check.reason, **check.figures())
                log(f"  capture rejected ({dt:.1f} s): {check.reason}")
            if KEY_ABORT in display.drain_keys():  # keys pressed during the capture: only ESC counts
                action = Action.ABORT
                break
            if state.left == 0:
                break
        if action == Action.ABORT:
            writer.discard()
            done = True
            log(f"aborted: {len(state.accepted)} captures discarded, nothing written")
            return CaptureOutcome("aborted", None, tuple(state.accepted), state.rejected, state.coverage)
        if not state.accepted:
            writer.discard()
            done = True
            return CaptureOutcome("empty", None, (), state.rejected, state.coverage)
        cov = state.coverage
        if not cov.complete:
            log(f"  note: {cov.missing()} (the calibration may be weaker there)")
        meta = {"captured_by": "scripts/guided_calibration.py", "rejected_captures": state.rejected}
        root = writer.publish(board=(board.cols, board.rows, board.square_mm), camera_size=state.image_size,
                              projector_size=(spec.width, spec.height), frames=list(frames),
                              extra={"pattern": spec.to_dict(), **meta, **(extra or {})})
        done = True
        return CaptureOutcome("complete", root, tuple(state.accepted), state.rejected, cov)
    except BaseException as e:
        if not done:
            if writer.poses:
                why = str(e) or type(e).__name__
                try:
                    dest = writer.keep_incomplete(why if isinstance(e, GBError) else f"{type(e).__name__}: {why}")
                    log(f"the {len(writer.poses)} captures so far are in {dest} (marked incomplete, not a session)")
                except (OSError, GBError) as e2:
                    log(f"the {len(writer.poses)} captures so far stay in {writer.staging} ({e2})")
            else:
                writer.discard()
        raise
