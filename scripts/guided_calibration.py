#!/usr/bin/env python3
"""Guided capture of a rig-calibration session at a real rig, then the calibration.

The projector shows each calibration frame full-screen on the second display, the camera grabs
it, and a live window tells you whether the board is seen, which image regions and board tilts
are still missing, and how many captures are left.

Keys (live window): SPACE capture this pose (all frames), q finish, then calibrate.

    python scripts/guided_calibration.py SESSION_DIR --camera 0 --screen-x 1920 --board 9x7 --square-mm 30
    python scripts/guided_calibration.py SESSION_DIR --simulate            # the same flow, simulated, headless

Hold the board still while a pose is captured (about a second per frame); vary the distance
and tilt the board 20-40 degrees left, right, up and down; cover the corners of the image.
``--simulate`` drives the very same flow with a simulated camera that renders the board at a
scripted sequence of poses under whatever frame the simulated projector shows.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without install

from gbscan.errors import GBError  # noqa: E402

WINDOW_PROJ = "gbcal projector"
WINDOW_LIVE = "gbcal guided calibration"
TILT_BINS = ("left", "right", "up", "down", "square-on")


# -- devices -----------------------------------------------------------------------------------
class ProjectorWindow:
    """A full-screen OpenCV window on the display whose top-left is at x = ``screen_x``."""

    def __init__(self, screen_x: int, screen_y: int = 0):
        import cv2

        self.cv2 = cv2
        try:
            cv2.namedWindow(WINDOW_PROJ, cv2.WINDOW_NORMAL)
        except cv2.error:
            raise GBError("this OpenCV build has no windows (the project depends on the headless wheel); for a "
                          "real rig install the GUI build into the venv: pip uninstall -y "
                          "opencv-contrib-python-headless && pip install opencv-contrib-python "
                          "(or try the flow with --simulate)") from None
        cv2.moveWindow(WINDOW_PROJ, int(screen_x), int(screen_y))
        cv2.setWindowProperty(WINDOW_PROJ, cv2.WND_PROP_FULLSCREEN, cv2.WINDOW_FULLSCREEN)

    def show(self, frame_rgb: np.ndarray) -> None:
        self.cv2.imshow(WINDOW_PROJ, np.ascontiguousarray(frame_rgb[:, :, ::-1]))
        self.cv2.waitKey(1)


class VideoCamera:
    """cv2.VideoCapture on a device index or a stream URL; ``read`` returns RGB uint8."""

    def __init__(self, source: str):
        import cv2

        self.cv2 = cv2
        src = int(source) if str(source).isdigit() else source
        self.cap = cv2.VideoCapture(src)
        if not self.cap.isOpened():
            raise GBError(f"cannot open camera '{source}' (a device index such as 0, or a stream URL)")

    def read(self) -> np.ndarray:
        ok, bgr = self.cap.read()
        if not ok or bgr is None:
            raise GBError("the camera stopped delivering frames")
        return np.ascontiguousarray(bgr[:, :, ::-1])

    def discard(self, n: int) -> None:
        for _ in range(n):
            self.cap.grab()

    def close(self):
        self.cap.release()


class LiveKeys:
    """Keys from the live window (cv2.waitKey)."""

    def __init__(self):
        import cv2

        self.cv2 = cv2

    def poll(self) -> str:
        k = self.cv2.waitKey(30) & 0xFF
        return {32: " ", ord("q"): "q", 27: "q"}.get(k, "")


# -- the simulated rig -------------------------------------------------------------------------
class SimulatedRig:
    """A simulated projector + camera + board operator, headless.

    ``show`` sets the projector frame; ``read`` renders the board at the current scripted pose
    under it (gbscan.sim; the pose's rays are traced once and reused for every frame); the key
    source presses SPACE once per scripted pose (after one live frame, as a person would look
    first) and then ``q``.
    """

    def __init__(self, rig, board, poses, preset="clean", seed=0):
        from gbscan import sim

        self.sim = sim
        self.rig = rig
        self.board = board
        self.poses = list(poses)
        self.cond = sim.preset(preset)
        self._trace = (None, None)
        self.frame = np.zeros((rig.projector.height, rig.projector.width, 3), np.uint8)
        self.i = 0
        self.n_render = 0
        self.seed = seed
        self._looked = False

    # projector
    def show(self, frame_rgb):
        self.frame = frame_rgb

    # camera
    def read(self):
        k = min(self.i, len(self.poses) - 1)
        if self._trace[0] != k:
            R, t = self.poses[k]
            scene = self.sim.scenes.board(self.board.cols, self.board.rows, self.board.square_mm, R, t)
            self._trace = (k, self.sim.trace(self.rig, scene, self.cond))
        self.n_render += 1
        return self.sim.render_traced(self.rig, self._trace[1], self.frame, seed=self.seed + self.n_render).image

    def discard(self, n):
        pass

    def close(self):
        pass

    # operator
    def poll(self) -> str:
        if self.i >= len(self.poses):
            return "q"
        if not self._looked:
            self._looked = True
            return ""
        return " "

    def captured(self):
        self.i += 1
        self._looked = False


def scripted_poses(rig, board, n: int, seed: int = 1):
    """``n`` varied board poses (R_cam_board, t_cam_board) that keep the board inside the camera
    image and the projector frame (those of the simulated sessions, :mod:`gbcal.simsession`)."""
    from gbcal.simsession import board_poses

    return board_poses(rig, (board.cols, board.rows, board.square_mm), n, seed)


# -- feedback ----------------------------------------------------------------------------------
class Coverage:
    """Which image cells have held board corners and which tilt directions have been captured."""

    def __init__(self, size, grid=(4, 3)):
        self.size = size
        self.grid = grid
        self.cells = np.zeros(grid[::-1], bool)
        self.tilts = dict.fromkeys(TILT_BINS, 0)

    @staticmethod
    def tilt_bin(normal) -> str:
        """The direction a board normal (camera frame, away from the camera) is tilted to."""
        nx, ny, nz = normal
        ang = np.degrees(np.arccos(np.clip(nz, -1, 1)))
        if ang < 10:
            return "square-on"
        if abs(nx) >= abs(ny):
            return "right" if nx > 0 else "left"
        return "down" if ny > 0 else "up"

    def add(self, corners, normal):
        W, H = self.size
        gx, gy = self.grid
        cx = np.clip((corners[:, 0] / W * gx).astype(int), 0, gx - 1)
        cy = np.clip((corners[:, 1] / H * gy).astype(int), 0, gy - 1)
        self.cells[cy, cx] = True
        self.tilts[self.tilt_bin(normal)] += 1

    def missing(self) -> str:
        parts = []
        empty = int((~self.cells).sum())
        if empty:
            parts.append(f"{empty} of {self.cells.size} image regions without corners")
        no_tilt = [k for k in ("left", "right", "up", "down") if self.tilts[k] == 0]
        if no_tilt:
            parts.append("no board tilted " + "/".join(no_tilt))
        return "; ".join(parts) if parts else "coverage complete"


def board_normal(corners, board, size):
    from gbcal.intrinsics import board_normals

    return board_normals([corners], board, size)[0]


def draw_feedback(image, det, board, coverage, left: int):
    """The live window's picture: detection, coverage grid, tilts and captures left."""
    import cv2

    img = image.copy()
    H, W = img.shape[:2]
    gx, gy = coverage.grid
    for j in range(gy):
        for i in range(gx):
            if not coverage.cells[j, i]:
                x0, y0 = int(i * W / gx), int(j * H / gy)
                cv2.rectangle(img, (x0 + 2, y0 + 2), (int((i + 1) * W / gx) - 2, int((j + 1) * H / gy) - 2),
                              (255, 160, 0), 1)
    if det is not None:
        cv2.drawChessboardCorners(img, board.pattern_size, det.corners.astype(np.float32).reshape(-1, 1, 2), True)
    status = "board found - SPACE to capture" if det is not None else "no board"
    cv2.putText(img, f"{status} | {left} captures left | q: finish", (8, 18), cv2.FONT_HERSHEY_SIMPLEX,
                0.5, (0, 255, 0) if det is not None else (255, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "tilts: " + " ".join(f"{k}:{v}" for k, v in coverage.tilts.items()), (8, H - 10),
                cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 0), 1, cv2.LINE_AA)
    return img


# -- the flow ----------------------------------------------------------------------------------
def capture_session(out_dir, projector, camera, keys, board, spec, *, n_poses: int, settle_frames: int,
                    live_window: bool, log=print, on_captured=None) -> int:
    """Run the guided capture; writes ``out_dir/pose_NNN/<frame>.png`` and ``session.yaml``.
    Returns the number of poses captured."""
    from gbcal.board import detect, detect_with_reason
    from gbcal.patterns import calibration_frames
    from gbscan.io import make_dir, write_png, write_session_yaml

    out = Path(out_dir)
    make_dir(out, "session folder")
    if any(out.glob("pose_*")):
        raise GBError(f"session folder {out} already holds captures; choose a new folder")
    frames = calibration_frames(spec)
    size = None
    coverage = None
    n = 0
    projector.show(frames["white"])
    camera.discard(settle_frames)
    while n < n_poses:
        live = camera.read()
        if size is None:
            size = (live.shape[1], live.shape[0])
            coverage = Coverage(size)
        det = detect(live, board, refine=False)
        if live_window:
            import cv2

            cv2.imshow(WINDOW_LIVE, draw_feedback(live, det, board, coverage, n_poses - n)[:, :, ::-1])
        key = keys.poll()
        if key == "q":
            break
        if key != " ":
            continue
        if det is None:
            log("  no board in view: not captured (the whole board must be visible and sharp)")
            continue
        pose_dir = out / f"pose_{n:03d}"
        pose_dir.mkdir(exist_ok=True)
        t0 = time.perf_counter()
        shots = {}
        for name, frame in frames.items():
            projector.show(frame)
            camera.discard(settle_frames)
            shots[name] = camera.read()
        projector.show(frames["white"])
        camera.discard(settle_frames)
        for name, img in shots.items():
            write_png(pose_dir / f"{name}.png", img)
        det2, why = detect_with_reason(shots["white"], board)
        if det2 is None:
            log(f"  pose {n}: captured, but the board is not usable in the white frame ({why}); keep the "
                "board still during the capture")
        else:
            coverage.add(det2.corners, board_normal(det2.corners, board, size))
        n += 1
        if on_captured:
            on_captured()
        log(f"  pose {n}/{n_poses} captured in {time.perf_counter() - t0:.1f} s; still missing: "
            f"{coverage.missing()}")
    if n:
        write_session_yaml(out, board=(board.cols, board.rows, board.square_mm), camera_size=size,
                           projector_size=(spec.width, spec.height), frames=list(frames),
                           extra={"pattern": spec.to_dict(), "captured_by": "scripts/guided_calibration.py"})
    return n


def main(argv=None) -> int:
    from gbcal.board import parse_board
    from gbscan.cli_common import size_arg
    from gbscan.pattern import PatternSpec

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("session", help="session folder to write (new)")
    p.add_argument("--camera", default="0", help="camera device index or stream URL (default 0)")
    p.add_argument("--screen-x", type=int, default=1920,
                   help="x offset (px) of the projector's display in the desktop (default 1920: right of a 1080p screen)")
    p.add_argument("--screen-y", type=int, default=0, help="y offset of the projector's display (default 0)")
    p.add_argument("--board", default="9x7", help="inner corners COLSxROWS (default 9x7)")
    p.add_argument("--square-mm", type=float, default=20.0,
                   help="square size in mm (default 20: the whole board must fit in the projector's light)")
    p.add_argument("--projector", type=size_arg, default=(1024, 768), metavar="WxH", help="projector resolution")
    p.add_argument("--stripe-px", type=int, default=8, help="stripe width in projector px (default 8)")
    p.add_argument("--no-markers", action="store_true", help="the paper's pure green/blue stripe frame")
    p.add_argument("--poses", type=int, default=12, help="captures to take (default 12; q finishes early)")
    p.add_argument("--settle-frames", type=int, default=4,
                   help="camera frames discarded after each projector change (latency; default 4)")
    p.add_argument("-o", "--calib", help="calibration file to write (default SESSION/calib.yaml)")
    p.add_argument("--no-calibrate", action="store_true", help="only capture the session")
    p.add_argument("--simulate", action="store_true", help="simulated rig, headless (for tests and demos)")
    p.add_argument("--sim-scale", type=float, default=0.5,
                   help="--simulate: camera resolution factor of the paper rig (default 0.5 = 320x240, fast)")
    p.add_argument("--sim-preset", default="clean", help="--simulate: imaging preset (default clean)")
    args = p.parse_args(argv)
    try:
        board = parse_board(args.board, args.square_mm)
        spec = PatternSpec(args.projector[0], args.projector[1], args.stripe_px, not args.no_markers)
        if args.poses < 1:
            raise GBError("--poses must be at least 1")
        log = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
        if args.simulate:
            from gbscan.rig import Rig, paper_rig

            true = paper_rig()
            if (spec.width, spec.height) != (true.projector.width, true.projector.height):
                raise GBError("--simulate uses the paper rig's 1024x768 projector; drop --projector")
            rig = Rig(true.camera.scaled(args.sim_scale), true.projector, true.R_cam_proj, true.t_cam_proj)
            simrig = SimulatedRig(rig, board, scripted_poses(rig, board, args.poses), preset=args.sim_preset)
            projector = camera = keys = simrig
            live, on_captured = False, simrig.captured
            log(f"simulated rig: camera {rig.camera.width}x{rig.camera.height}, {args.poses} scripted poses")
        else:
            projector = ProjectorWindow(args.screen_x, args.screen_y)
            camera = VideoCamera(args.camera)
            keys = LiveKeys()
            live, on_captured = True, None
        try:
            n = capture_session(args.session, projector, camera, keys, board, spec, n_poses=args.poses,
                                settle_frames=args.settle_frames, live_window=live, log=log, on_captured=on_captured)
        finally:
            camera.close()
            if live:
                import cv2

                cv2.destroyAllWindows()
        if n == 0:
            raise GBError("no pose captured; nothing written")
        log(f"session written: {args.session} ({n} poses)")
        if args.no_calibrate:
            return 0
        from gbcal.calibrate import calibrate_session, save_run, summary_lines

        run = calibrate_session(args.session, log=log)
        path, npz = save_run(args.calib or Path(args.session) / "calib.yaml", run)
        for line in summary_lines(run):
            print(line)
        print(f"wrote {path} and {npz.name}")
        return 0
    except GBError as e:
        print(f"guided_calibration: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("guided_calibration: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
