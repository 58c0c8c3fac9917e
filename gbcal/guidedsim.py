"""A simulated rig and operator for the guided capture (``guided_calibration.py --simulate``, tests).

:class:`SimulatedRig` is the world the flow of :mod:`gbcal.guided` talks to:

* ``rig.display(inner)`` -- a display that passes everything to ``inner`` (a real Tk window, or
  :class:`gbcal.display.NullDisplay`), also hands every projector frame to the simulated
  projector, and answers :meth:`poll_key` with the scripted operator's keys (keys typed into a
  real window come first, so ESC works in a demo);
* ``rig.camera`` -- renders the board at the operator's current pose under the frame the
  projector shows (:mod:`gbscan.sim`; each pose is ray-traced once and re-lit per frame).

The operator follows a script of :class:`Step`: for each step it looks once (one live frame
without a key), then presses the step's key with the board at the step's pose; a step may carry a
fault that spoils the capture, so every rejection path can be driven end to end:

``"move"``  the board shifts ~4 mm and turns ~1 degree from the third frame of the capture on;
``"blur"``  strong camera blur while capturing (defocus, shaking board);
``"bright"`` exposure x 2.5 (saturated white frame);
``"dim"``   projector at 10 % against strong ambient light (little modulation);
``"lag"``   the camera sees the previous projector frame (no synchronisation).
Faults apply from the key press on.  ``pose=None`` is a step with no board in view.
When a capture without a fault is rejected anyway (a pose the detector cannot use), the
operator does what a person would: tries another position, the next pose not in the script
(spare poses), while there are any.  After the script the operator presses ``then`` (default ``q``).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from gbscan.errors import GBError

FAULTS = ("", "move", "blur", "bright", "dim", "lag")


@dataclass(frozen=True)
class Step:
    """One operator action: board at ``poses[pose]`` (None: no board in view), then ``key``."""

    pose: int | None
    key: str = " "
    fault: str = ""

    def __post_init__(self):
        if self.fault not in FAULTS:
            raise GBError(f"unknown simulated fault '{self.fault}'; choose one of {', '.join(f for f in FAULTS if f)}")


def parse_faults(text: str, n_poses: int) -> dict:
    """``"2:move,4:blur"`` -> {2: "move", 4: "blur"} (1-based capture attempts); GBError if malformed."""
    out = {}
    for part in filter(None, (p.strip() for p in str(text or "").split(","))):
        try:
            k, f = part.split(":")
            k = int(k)
        except ValueError:
            raise GBError(f"--sim-faults must be like 2:move,4:blur (attempt:fault), got '{part}'") from None
        if f not in FAULTS or not f:
            raise GBError(f"--sim-faults: unknown fault '{f}'; choose one of {', '.join(x for x in FAULTS if x)}")
        if k < 1:
            raise GBError(f"--sim-faults: attempts count from 1, got {k}")
        out[k] = f
    return out


def script_for(n_poses: int, faults: dict | None = None) -> list[Step]:
    """Operator script capturing poses 0..n_poses-1; attempt ``k`` (1-based) in ``faults`` is
    spoilt by that fault and the same pose is captured again after it (as a person would)."""
    steps, pose, attempt = [], 0, 1
    faults = dict(faults or {})
    while pose < n_poses:
        f = faults.pop(attempt, "")
        steps.append(Step(pose, " ", f))
        if not f:
            pose += 1
        attempt += 1
    return steps


def _rot(axis, deg):
    import cv2

    v = np.radians(deg) * np.asarray(axis, np.float64) / np.linalg.norm(axis)
    return cv2.Rodrigues(v)[0]


class SimulatedRig:
    """The simulated rig, board and operator (module docstring).

    rig : gbscan.rig.Rig; board : gbcal.board.Board; poses : [(R_cam_board, t_cam_board mm), ...];
    steps : the operator script (default: every pose once); preset : imaging conditions.
    """

    def __init__(self, rig, board, poses, steps=None, *, preset="clean", seed=0, then: str = "q"):
        from gbscan import sim

        self.sim = sim
        self.rig = rig
        self.board = board
        self.poses = list(poses)
        self.steps = list(steps) if steps is not None else [Step(k) for k in range(len(self.poses))]
        for s in self.steps:
            if s.pose is not None and not 0 <= s.pose < len(self.poses):
                raise GBError(f"operator step {s} refers to pose {s.pose} of {len(self.poses)}")
        self.cond = sim.preset(preset)
        self.seed = int(seed)
        self.then = then
        H, W = rig.projector.height, rig.projector.width
        self.shown = [np.zeros((H, W, 3), np.uint8)] * 2  # previous and current projector frame
        self.white = np.full((H, W, 3), 255, np.uint8)
        self.step = 0
        self.looked = False
        self.pressed = False      # the current step's key was pressed (faults active)
        self.reads_since_key = 0
        self.n_render = 0
        self.last_view = None     # what the live window showed last (the operator reads it)
        used = {st.pose for st in self.steps}
        self.spares = [k for k in range(len(self.poses)) if k not in used]
        self.retakes = 0
        self._traces = {}
        self.camera = _SimCamera(self)

    # -- the operator ---------------------------------------------------------------------------
    def current(self) -> Step | None:
        return self.steps[self.step] if self.step < len(self.steps) else None

    def operator_key(self) -> str:
        if self.pressed:  # the last action is over: next step
            st = self.current()
            v = self.last_view
            if (st.key == " " and not st.fault and st.pose is not None and v is not None and not v.message_ok
                    and v.message.startswith("rejected") and self.spares):
                self.steps.insert(self.step + 1, Step(self.spares.pop(0)))  # try another position
                self.retakes += 1
            self.step += 1
            self.pressed, self.looked, self.reads_since_key = False, False, 0
        st = self.current()
        if st is None:
            return self.then
        if not self.looked:
            self.looked = True
            return ""
        self.pressed = True
        return st.key

    def display(self, inner):
        """A display for the flow: ``inner`` shows, this rig's projector and operator take part."""
        return _SimDisplay(self, inner)

    # -- the projector and the camera -----------------------------------------------------------
    def project(self, frame):
        self.shown = [self.shown[1], np.asarray(frame)]

    def _trace(self, key):
        if key not in self._traces:
            if key is None:
                scene = self.sim.scenes.plane(distance_mm=1500.0, albedo=0.5)
            else:
                k, moved = key
                R, t = self.poses[k]
                if moved:  # turned ~1 deg about the board's y axis and shifted 4 mm along its x axis
                    R = R @ _rot((0, 1, 0), 1.0)
                    t = t + R[:, 0] * 4.0
                scene = self.sim.scenes.board(self.board.cols, self.board.rows, self.board.square_mm, R, t)
            if len(self._traces) > 4:
                self._traces.pop(next(iter(self._traces)))
            self._traces[key] = self.sim.trace(self.rig, scene, self.cond)
        return self._traces[key]

    def render(self) -> np.ndarray:
        from gbscan.sim.render import camera_image, linear_signal

        st = self.current()
        fault = st.fault if (st is not None and self.pressed) else ""
        if self.pressed:
            self.reads_since_key += 1
        pose = st.pose if st is not None else None
        moved = fault == "move" and self.reads_since_key >= 3
        tr = self._trace(None if pose is None else (pose, moved))
        frame = self.shown[0] if fault == "lag" else self.shown[1]
        lin = linear_signal(tr, frame)
        cond = tr.cond
        if fault == "dim":
            lin = 0.1 * lin + 0.5 * linear_signal(tr, self.white)
        elif fault == "bright":
            lin = 2.5 * lin
        elif fault == "blur":
            cond = dataclasses.replace(cond, cam_sigma_px=2.5)
        self.n_render += 1
        rng = np.random.default_rng([self.seed, self.n_render])
        return camera_image(lin, self.rig.camera, cond, rng)


class _SimCamera:
    def __init__(self, world: SimulatedRig):
        self.world = world

    def read(self) -> np.ndarray:
        return self.world.render()

    def drop(self, n: int) -> None:
        pass  # a simulated camera has no stale frames (the "lag" fault models one that does)

    def close(self):
        pass


class _SimDisplay:
    def __init__(self, world: SimulatedRig, inner):
        self.world = world
        self.inner = inner
        self.name = f"{getattr(inner, 'name', 'display')}+simulated rig"

    def show_projector(self, frame_rgb):
        self.inner.show_projector(frame_rgb)
        self.world.project(frame_rgb)

    def show_live(self, image_rgb, corners, view):
        self.inner.show_live(image_rgb, corners, view)
        self.world.last_view = view

    def wait_ms(self, ms):
        self.inner.wait_ms(ms)

    def poll_key(self) -> str:
        return self.inner.poll_key() or self.world.operator_key()

    def drain_keys(self) -> list:
        return self.inner.drain_keys()

    def problems(self) -> list:
        return self.inner.problems()

    def close(self):
        self.inner.close()
