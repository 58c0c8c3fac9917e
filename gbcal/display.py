"""The guided calibration's devices at the edge: display backends and the camera.

A display backend shows projector frames on the projector and the live feedback window, and
reports keys; the flow (:mod:`gbcal.guided`) does not know which one it drives:

* :class:`TkDisplay` -- Python's standard ``tkinter``: works with the project's headless OpenCV
  wheel.  The projector window is a borderless (override-redirect) window of exactly the
  projector's size placed at the desktop offset of the projector's display (``screen_xy``);
  frames are shown pixel for pixel (a ``PhotoImage`` built from the frame's PPM bytes: no
  scaling, no smoothing, no colour management).
* :class:`OpenCVDisplay` -- OpenCV highgui, when the installed OpenCV has a GUI.
* :class:`NullDisplay` -- no windows (``--simulate``, tests); keys from a script.

:func:`choose_display` picks one (``auto``: Tk if a window can be opened, else OpenCV highgui,
else a GBError that says why and what to do).  :func:`compose_feedback` draws the live window's
picture (the same for every backend).  :class:`VideoCamera` wraps ``cv2.VideoCapture``.

Keys are reported as the flow's names: ``" "`` (SPACE), ``"q"``, ``"u"``, ``"esc"``.
"""
from __future__ import annotations

import os
import sys
import time
from collections import deque

import numpy as np

from gbscan.errors import GBError

WINDOW_LIVE = "gbcal guided calibration"
WINDOW_PROJ = "gbcal projector"
#: Largest size (px) of the camera picture in the live window; bigger camera images are shrunk.
LIVE_MAX_PX = (960, 720)
_TK_KEYS = {"space": " ", "q": "q", "Q": "q", "u": "u", "U": "u", "Escape": "esc"}
_CV_KEYS = {32: " ", ord("q"): "q", ord("Q"): "q", ord("u"): "u", ord("U"): "u", 27: "esc"}

# colours (RGB)
_GREEN, _RED, _ORANGE, _GREY, _WHITE, _YELLOW = (60, 220, 60), (255, 70, 60), (255, 160, 0), (110, 110, 110), \
    (255, 255, 255), (255, 230, 80)


def ppm_bytes(frame_rgb: np.ndarray) -> bytes:
    """Binary PPM (P6) of an (H, W, 3) uint8 RGB image: Tk's PhotoImage reads it losslessly."""
    f = np.ascontiguousarray(frame_rgb)
    if f.dtype != np.uint8 or f.ndim != 3 or f.shape[2] != 3:
        raise GBError(f"a displayed image must be (H, W, 3) uint8 RGB, got {f.dtype} {f.shape}")
    return b"P6 %d %d 255\n" % (f.shape[1], f.shape[0]) + f.tobytes()


def _check_projector_frame(frame: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    f = np.asarray(frame)
    if f.dtype != np.uint8 or f.shape != (size[1], size[0], 3):
        raise GBError(f"projector frame of shape {f.shape} {f.dtype} does not match the {size[0]}x{size[1]} "
                      "projector (expected (H, W, 3) uint8); --projector must be the projector's native resolution")
    return f


# -- the live picture --------------------------------------------------------------------------
def fit_size(size: tuple[int, int], max_size: tuple[int, int] = LIVE_MAX_PX) -> tuple[float, tuple[int, int]]:
    """(scale, (w, h)) to fit an image of ``size = (W, H)`` into ``max_size``: shrunk if larger,
    enlarged by a whole factor if at most half as large (a small camera image stays legible)."""
    s = min(max_size[0] / size[0], max_size[1] / size[1])
    s = float(np.floor(s)) if s >= 2 else min(s, 1.0)
    return s, (max(1, int(round(size[0] * s))), max(1, int(round(size[1] * s))))


def compose_feedback(image: np.ndarray, corners: np.ndarray | None, pattern_size: tuple[int, int], view,
                     max_size: tuple[int, int] = LIVE_MAX_PX) -> np.ndarray:
    """The live window's picture, (H', W', 3) uint8 RGB.

    The camera image (shrunk to fit ``max_size``) with the coverage grid (cells holding corners
    of an accepted capture tinted green, empty cells outlined orange) and the detected board
    (``corners`` (N, 2) camera px, OpenCV's colouring); below it a panel: status, captures
    done/left, the tilt bins (green when captured), the last message (red: a rejection and its
    reason), the hint of what to do next, and the keys.  ``view`` is a :class:`gbcal.guided.LiveView`.
    """
    import cv2

    img = np.asarray(image)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    H, W = img.shape[:2]
    s, (w, h) = fit_size((W, H), max_size)
    pic = img.copy() if s == 1 else cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_NEAREST)
    pic = np.ascontiguousarray(pic)
    cells = view.coverage.cells
    gy, gx = cells.shape
    tint = pic.copy()
    for j in range(gy):
        for i in range(gx):
            x0, y0 = int(round(i * w / gx)), int(round(j * h / gy))
            x1, y1 = int(round((i + 1) * w / gx)) - 1, int(round((j + 1) * h / gy)) - 1
            if cells[j, i]:
                cv2.rectangle(tint, (x0, y0), (x1, y1), _GREEN, -1)
            else:
                cv2.rectangle(pic, (x0 + 2, y0 + 2), (x1 - 2, y1 - 2), _ORANGE, 1)
    pic = cv2.addWeighted(tint, 0.25, pic, 0.75, 0)
    if corners is not None:
        c = (np.asarray(corners, np.float32).reshape(-1, 1, 2) + 0.5) * s - 0.5
        cv2.drawChessboardCorners(pic, tuple(pattern_size), c.astype(np.float32), True)
    # panel
    font, fs = cv2.FONT_HERSHEY_SIMPLEX, 0.5
    line_h = 20
    pw = max(w, 480)
    lines = []  # (text, colour)
    lines.append((view.status, _GREEN if view.status_ok else _RED))
    lines.append((f"{view.captured} of {view.n_poses} captured, {view.left} left", _WHITE))
    lines.append((None, None))  # tilt boxes
    for text in _wrap(view.message, pw - 16, font, fs):
        lines.append((text, _GREEN if view.message_ok else _RED))
    lines.append((view.hint, _YELLOW))
    lines.append((view.keys, _GREY))
    panel = np.full((8 + line_h * len(lines), pw, 3), 24, np.uint8)
    y = 4 + line_h - 6
    for text, colour in lines:
        if text is None:
            x = 8
            cv2.putText(panel, "tilts:", (x, y), font, fs, _WHITE, 1, cv2.LINE_AA)
            x += 52
            for k, n in view.coverage.tilts.items():
                label = f"{k} {n}"
                tw = cv2.getTextSize(label, font, fs, 1)[0][0] + 10
                cv2.rectangle(panel, (x, y - 14), (x + tw, y + 4), _GREEN if n else _GREY, -1 if n else 1)
                cv2.putText(panel, label, (x + 5, y), font, fs, (0, 0, 0) if n else _WHITE, 1, cv2.LINE_AA)
                x += tw + 6
        else:
            cv2.putText(panel, text, (8, y), font, fs, colour, 1, cv2.LINE_AA)
        y += line_h
    if pw > w:
        pad = np.full((h, pw - w, 3), 24, np.uint8)
        pic = np.concatenate([pic, pad], axis=1)
    return np.ascontiguousarray(np.concatenate([pic, panel], axis=0))


def _wrap(text: str, width_px: int, font, fs) -> list[str]:
    import cv2

    words, out, cur = text.split(), [], ""
    for wd in words:
        trial = f"{cur} {wd}".strip()
        if cur and cv2.getTextSize(trial, font, fs, 1)[0][0] > width_px:
            out.append(cur)
            cur = wd
        else:
            cur = trial
    return out + [cur] if cur else out or [""]


# -- backends ----------------------------------------------------------------------------------
class NullDisplay:
    """No windows: for ``--simulate`` and tests.  Keys come from ``keys`` (a sequence of key
    names, one per :meth:`poll_key` call; ``""`` = no key); when they run out, ``then`` is
    returned (``""``: no key, for a display whose keys come from elsewhere).  Keeps the live views
    shown and counts the projector frames."""

    name = "none"

    def __init__(self, keys=(), then: str = ""):
        self.keys = deque(keys)
        self.then = then
        self.projector_frame = None
        self.n_projector = 0
        self.last_live = None
        self.views = []
        self.images = 0
        self.last_image = None

    def show_projector(self, frame_rgb):
        self.projector_frame = frame_rgb
        self.n_projector += 1

    def show_live(self, image_rgb, corners, view):
        self.last_live = (image_rgb, corners, view)
        self.views.append(view)

    def show_image(self, picture_rgb):
        self.last_image = picture_rgb
        self.images += 1

    def wait_ms(self, ms):
        pass

    def poll_key(self) -> str:
        return self.keys.popleft() if self.keys else self.then

    def drain_keys(self) -> list:
        return []

    def problems(self) -> list:
        return []

    def close(self):
        pass


class TkDisplay:
    """Tk windows: a borderless projector window and the live feedback window (module docstring).

    projector_size : (W, H) projector px; every frame must be exactly this size.
    screen_xy : desktop offset (px) of the projector's display, e.g. (1920, 0) for a projector
        to the right of a 1920-wide monitor.
    screen_name : X display to use (None: ``$DISPLAY``).
    Keys (live window; the borderless projector window gets them only where the window manager
    gives it the focus): SPACE, q, u, ESC; closing the live window counts as ESC.
    """

    name = "tk"

    def __init__(self, projector_size, screen_xy=(1920, 0), *, live_max_px=LIVE_MAX_PX, screen_name=None,
                 pattern_size=(9, 7), title=WINDOW_LIVE):
        try:
            import tkinter as tk
        except ImportError as e:
            raise GBError(f"this Python has no tkinter ({e}); install it (Debian/Ubuntu: apt install python3-tk)") \
                from None
        self.tk = tk
        try:
            self.root = tk.Tk(screenName=screen_name, className="gbcal")
        except tk.TclError as e:
            raise GBError(f"Tk cannot open a window: {e}") from None
        self.size = (int(projector_size[0]), int(projector_size[1]))
        self.xy = (int(screen_xy[0]), int(screen_xy[1]))
        self.live_max_px = live_max_px
        self.pattern_size = tuple(pattern_size)
        self._keys = deque()
        self._images = {}
        root = self.root
        root.title(title)
        root.geometry("+40+40")  # top-left of the primary screen, away from the projector
        root.configure(bg="black")
        self._live = tk.Label(root, bd=0, highlightthickness=0, bg="black")
        self._live.pack()
        root.protocol("WM_DELETE_WINDOW", lambda: self._keys.append("esc"))
        W, H = self.size
        self.proj = tk.Toplevel(root, bg="black", cursor="none", bd=0, highlightthickness=0)
        self.proj.title(WINDOW_PROJ)
        self.proj.overrideredirect(True)
        self.proj.geometry(f"{W}x{H}+{self.xy[0]}+{self.xy[1]}")
        self._proj = tk.Label(self.proj, bd=0, highlightthickness=0, padx=0, pady=0, bg="black")
        self._proj.place(x=0, y=0, width=W, height=H)
        for w in (root, self.proj):
            w.bind("<KeyPress>", self._on_key)
        try:
            self.proj.attributes("-topmost", True)
        except tk.TclError:
            pass
        root.update()
        root.focus_force()

    def _on_key(self, event):
        k = _TK_KEYS.get(event.keysym)
        if k:
            self._keys.append(k)

    def _photo(self, slot: str, rgb: np.ndarray):
        img = self.tk.PhotoImage(master=self.root, data=ppm_bytes(rgb), format="PPM")
        self._images[slot] = img  # keep a reference; the previous one is freed
        return img

    def show_projector(self, frame_rgb):
        f = _check_projector_frame(frame_rgb, self.size)
        self._proj.configure(image=self._photo("proj", f))
        self.root.update_idletasks()
        self.root.update()

    def show_live(self, image_rgb, corners, view):
        self.show_image(compose_feedback(image_rgb, corners, self.pattern_size, view, self.live_max_px))

    def show_image(self, picture_rgb):
        """Any (H, W, 3) uint8 RGB picture in the live window."""
        self._live.configure(image=self._photo("live", np.ascontiguousarray(picture_rgb)))
        self.root.update()

    def wait_ms(self, ms):
        end = time.perf_counter() + max(float(ms), 0.0) / 1000.0
        while True:
            self.root.update()
            left = end - time.perf_counter()
            if left <= 0:
                break
            time.sleep(min(left, 0.005))

    def poll_key(self) -> str:
        self.root.update()
        return self._keys.popleft() if self._keys else ""

    def drain_keys(self) -> list:
        self.root.update()
        out = list(self._keys)
        self._keys.clear()
        return out

    def geometry(self) -> tuple[int, int, int, int]:
        """(x, y, width, height) of the projector window on the desktop, as the window system has it."""
        self.root.update_idletasks()
        p = self.proj
        return p.winfo_rootx(), p.winfo_rooty(), p.winfo_width(), p.winfo_height()

    def problems(self) -> list:
        """Sentences about a projector window that is not where or as big as asked (empty if fine)."""
        x, y, w, h = self.geometry()
        out = []
        if (w, h) != self.size:
            out.append(f"the projector window is {w}x{h} px, not the projector's {self.size[0]}x{self.size[1]}: "
                       "frames would not be pixel-exact (window manager resized it?)")
        if (x, y) != self.xy:
            out.append(f"the projector window is at +{x}+{y}, not +{self.xy[0]}+{self.xy[1]} (--screen-x/--screen-y)")
        sw, sh = self.root.winfo_screenwidth(), self.root.winfo_screenheight()
        if self.xy[0] + self.size[0] > sw or self.xy[1] + self.size[1] > sh:
            out.append(f"the desktop is {sw}x{sh} px: a {self.size[0]}x{self.size[1]} window at "
                       f"+{self.xy[0]}+{self.xy[1]} does not fit in it; is the projector's display extended there?")
        return out

    def close(self):
        try:
            self.root.destroy()
        except self.tk.TclError:
            pass


def opencv_gui() -> tuple[bool, str]:
    """(available, why not): whether the installed OpenCV can open windows."""
    import cv2

    info = cv2.getBuildInformation()
    for line in info.splitlines():
        if line.strip().startswith("GUI:"):
            if line.split(":", 1)[1].strip().upper() in ("NONE", "NO", ""):
                return False, "the installed OpenCV has no GUI (headless wheel)"
            return True, ""
    return True, ""


class OpenCVDisplay:
    """OpenCV highgui windows (only with an OpenCV build that has a GUI); same keys as Tk."""

    name = "opencv"

    def __init__(self, projector_size, screen_xy=(1920, 0), *, live_max_px=LIVE_MAX_PX, pattern_size=(9, 7),
                 title=WINDOW_LIVE):
        import cv2

        ok, why = opencv_gui()
        if not ok:
            raise GBError(why)
        self.cv2 = cv2
        self.size = (int(projector_size[0]), int(projector_size[1]))
        self.xy = (int(screen_xy[0]), int(screen_xy[1]))
        self.live_max_px = live_max_px
        self.pattern_size = tuple(pattern_size)
        self._keys = deque()
        self.title = title
        try:
            cv2.namedWindow(WINDOW_PROJ, cv2.WINDOW_NORMAL)
            cv2.namedWindow(title, cv2.WINDOW_AUTOSIZE)
        except cv2.error as e:
            raise GBError(f"OpenCV cannot open a window: {str(e).strip().splitlines()[-1]}") from None
        cv2.moveWindow(WINDOW_PROJ, *self.xy)
        cv2.setWindowProperty(WINDOW_PROJ, cv2.WND_PROP_FULLSCREEN, cv2.WINDOW_FULLSCREEN)

    def _pump(self, ms: int):
        k = self.cv2.waitKey(max(1, int(ms)))
        if k >= 0 and (k & 0xFF) in _CV_KEYS:
            self._keys.append(_CV_KEYS[k & 0xFF])

    def show_projector(self, frame_rgb):
        f = _check_projector_frame(frame_rgb, self.size)
        self.cv2.imshow(WINDOW_PROJ, np.ascontiguousarray(f[:, :, ::-1]))
        self._pump(1)

    def show_live(self, image_rgb, corners, view):
        self.show_image(compose_feedback(image_rgb, corners, self.pattern_size, view, self.live_max_px))

    def show_image(self, picture_rgb):
        """Any (H, W, 3) uint8 RGB picture in the live window."""
        self.cv2.imshow(self.title, np.ascontiguousarray(np.asarray(picture_rgb)[:, :, ::-1]))
        self._pump(1)

    def wait_ms(self, ms):
        end = time.perf_counter() + max(float(ms), 0.0) / 1000.0
        while True:
            left = end - time.perf_counter()
            if left <= 0:
                break
            self._pump(min(left * 1000, 10))

    def poll_key(self) -> str:
        self._pump(10)
        return self._keys.popleft() if self._keys else ""

    def drain_keys(self) -> list:
        self._pump(1)
        out = list(self._keys)
        self._keys.clear()
        return out

    def problems(self) -> list:
        return []

    def close(self):
        self.cv2.destroyAllWindows()


def choose_display(kind: str, projector_size, screen_xy=(1920, 0), *, pattern_size=(9, 7),
                   live_max_px=LIVE_MAX_PX, log=None, title=WINDOW_LIVE):
    """The display backend ``kind``: ``"auto"`` (Tk, else OpenCV highgui), ``"tk"``, ``"opencv"``
    or ``"none"``; ``title`` names the live window.  GBError naming what is missing and what to
    do when no window can be opened."""
    kw = dict(pattern_size=pattern_size, live_max_px=live_max_px, title=title)
    if kind == "none":
        return NullDisplay()
    if kind == "tk":
        return TkDisplay(projector_size, screen_xy, **kw)
    if kind == "opencv":
        return OpenCVDisplay(projector_size, screen_xy, **kw)
    if kind != "auto":
        raise GBError(f"--display must be auto, tk, opencv or none, got '{kind}'")
    try:
        return TkDisplay(projector_size, screen_xy, **kw)
    except GBError as e:
        tk_why = str(e)
    ok, cv_why = opencv_gui()
    if ok:
        if log:
            log(f"Tk is not usable ({tk_why}); using OpenCV's windows")
        return OpenCVDisplay(projector_size, screen_xy, **kw)
    hint = ("run the script inside the rig computer's desktop session" +
            (" (no $DISPLAY is set: e.g. export DISPLAY=:0)" if sys.platform.startswith("linux")
             and not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY") else ""))
    raise GBError(f"no window can be opened for the projector and the live view: {tk_why}; and {cv_why}. "
                  f"{hint[0].upper() + hint[1:]}, or try the flow without windows with --simulate")


# -- scripts ------------------------------------------------------------------------------------
class Devices(list):
    """The windows and cameras a script opened (:func:`run_script` closes them, newest first)."""

    def open(self, device):
        """Keep ``device`` (anything with ``close()``) for closing; returns it."""
        self.append(device)
        return device

    def close_all(self) -> None:
        while self:
            self.pop().close()


def run_script(prog: str, body) -> int:
    """A rig script's main: ``body(devices)`` returns the exit status, errors end in one line as
    the commands' do (:func:`gbscan.cli_common.guarded`), and every device opened through
    ``devices`` (:class:`Devices`) is closed however it ends."""
    from gbscan.cli_common import guarded

    devices = Devices()
    try:
        return guarded(prog, lambda: body(devices))
    finally:
        devices.close_all()


# -- camera ------------------------------------------------------------------------------------
class VideoCamera:
    """``cv2.VideoCapture`` on a device index (``"0"``) or a stream URL / file; ``read`` returns
    (H, W, 3) uint8 RGB; ``drop(n)`` discards ``n`` frames the driver has buffered.

    size : optional (W, H) to request from the camera (checked: GBError if it delivers another).
    fourcc : optional pixel format to request (e.g. "RGB3", "BGR3", "YUYV", "MJPG"; what the device
        offers: ``v4l2-ctl --list-formats-ext``); :attr:`fourcc` is what it delivers.
    """

    def __init__(self, source: str, size: tuple[int, int] | None = None, fourcc: str | None = None):
        import cv2

        self.cv2 = cv2
        if fourcc and len(fourcc) != 4:
            raise GBError(f"--camera-fourcc must be 4 characters such as RGB3 or YUYV, got '{fourcc}'")
        src = int(source) if str(source).isdigit() else str(source)
        self.source = source
        self.cap = cv2.VideoCapture(src)
        if not self.cap.isOpened():
            raise GBError(f"cannot open camera '{source}' (a device index such as 0, or a stream URL)")
        if fourcc:
            self.cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*fourcc))
        if size is not None:
            self.cap.set(cv2.CAP_PROP_FRAME_WIDTH, int(size[0]))
            self.cap.set(cv2.CAP_PROP_FRAME_HEIGHT, int(size[1]))
        first = self.read()
        if size is not None and (first.shape[1], first.shape[0]) != tuple(size):
            raise GBError(f"camera '{source}' delivers {first.shape[1]}x{first.shape[0]} images, not the "
                          f"{size[0]}x{size[1]} asked for (--camera-size)")

    @property
    def fourcc(self) -> str:
        """The pixel format the camera delivers (its FourCC, e.g. "YUYV"; "" when not reported)."""
        from gbscan.frames import fourcc_text

        return fourcc_text(self.cap.get(self.cv2.CAP_PROP_FOURCC))

    def input_warning(self) -> str | None:
        """One line of warning when the camera's pixel format subsamples chroma or is JPEG (most
        webcams: YUYV is 4:2:2, MJPG is JPEG), which costs the colour stripes; else None."""
        from gbscan.frames import CHROMA_SUBSAMPLED
        from gbscan.io import CHROMA_COST

        f = self.fourcc
        what = "JPEG-compressed" if f.upper() in ("MJPG", "JPEG") else (
            f"{CHROMA_SUBSAMPLED[f]} chroma" if f in CHROMA_SUBSAMPLED else "")
        if not what:
            return None
        return (f"warning: camera '{self.source}' delivers {f} ({what}): {CHROMA_COST}; ask for an RGB or raw "
                "format if it has one (--camera-fourcc, formats: v4l2-ctl --list-formats-ext)")

    def read(self) -> np.ndarray:
        ok, bgr = self.cap.read()
        if not ok or bgr is None:
            raise GBError(f"camera '{self.source}' stopped delivering frames")
        if bgr.ndim == 2:
            raise GBError(f"camera '{self.source}' delivers grey images; the calibration needs a colour camera")
        return np.ascontiguousarray(bgr[:, :, 2::-1])

    def drop(self, n: int) -> None:
        for _ in range(int(n)):
            self.cap.grab()

    def close(self):
        self.cap.release()
