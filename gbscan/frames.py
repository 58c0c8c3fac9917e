"""Frame sources for sequences: a folder of images or a video file (the edge ``gbscan batch`` reads).

A *frame number* is the frame's position in its input, counted from 0:

* folder: the image files (suffixes in ``gbscan.io.IMAGE_SUFFIXES``, hidden files excluded) in
  natural order (``f2.png`` before ``f10.png``); other files are listed in ``ignored``;
* video: the decoded frame number (``cv2.VideoCapture``, read sequentially; skipped frames are
  grabbed, not converted, so the frame numbers are exact whatever the codec's key frames).

Frames come out as RGB ``uint8 (H, W, 3)`` like every image in memory.  A frame that cannot be
read (corrupt file, grey image, wrong size, video ending early) is not an exception for the
sequence: :meth:`FrameSource.frames` yields it with a :class:`GBError` instead of pixels, so the
caller can record it and go on.
"""
from __future__ import annotations

import contextlib
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from .errors import GBError
from .io import CHROMA_COST, IMAGE_SUFFIXES, input_warning, read_image_rgb

#: Video file suffixes opened with cv2.VideoCapture (anything FFmpeg reads; these are the usual ones).
VIDEO_SUFFIXES = (".avi", ".mkv", ".mp4", ".mov", ".m4v", ".webm", ".mpg", ".mpeg", ".wmv", ".ts")


@dataclass(frozen=True)
class FrameRef:
    """One frame of an input: its number, a human-readable source, its file (folder input), and
    the Bayer pattern of a raw mosaic file ("": a colour image)."""

    index: int
    source: str
    path: Path | None = None
    bayer: str = ""


@contextlib.contextmanager
def _quiet_opencv():
    """Silence OpenCV's own log lines while probing a file (errors are reported as GBError)."""
    import cv2

    log = cv2.utils.logging
    old = log.getLogLevel()
    log.setLogLevel(log.LOG_LEVEL_SILENT)
    try:
        yield
    finally:
        log.setLogLevel(old)


def _natural_key(name: str):
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def select(n_frames: int, start: int = 0, stop: int | None = None, every: int = 1) -> range:
    """Frame numbers ``start, start+every, ... < stop`` within ``0 .. n_frames-1``.

    ``stop`` None means the end; negative ``start``/``stop`` count from the end like Python slices.
    """
    if isinstance(every, bool) or int(every) < 1:
        raise GBError(f"--every must be a positive integer, got {every!r}")
    return range(n_frames)[slice(start, stop, int(every))]


class FrameSource:
    """A sequence of frames; open one with :func:`open_frames`."""

    kind: str = ""
    path: Path
    ignored: tuple[str, ...] = ()

    def __len__(self) -> int:  # number of frames in the input
        raise NotImplementedError

    @property
    def random_access(self) -> bool:
        """True when any frame can be read on its own (a worker can read it from ``ref.path``)."""
        return False

    def ref(self, index: int) -> FrameRef:
        raise NotImplementedError

    def refs(self, start: int = 0, stop: int | None = None, every: int = 1) -> list[FrameRef]:
        return [self.ref(i) for i in select(len(self), start, stop, every)]

    def frames(self, refs: list[FrameRef], size: tuple[int, int] | None = None
               ) -> Iterator[tuple[FrameRef, np.ndarray | GBError]]:
        """Yield ``(ref, rgb)`` in the order of ``refs`` (ascending for a video), or ``(ref, GBError)``.

        ``size = (width, height)`` makes a frame of another size an error for that frame.
        """
        raise NotImplementedError

    def input_warning(self) -> str | None:
        """One line of warning when the frames are stored lossily in a way that costs the colour
        stripes (JPEG frames, a chroma-subsampled or lossy video codec), else None."""
        return None

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class FolderFrames(FrameSource):
    """The image files of one folder, in natural order."""

    kind = "folder"

    def __init__(self, path: str | Path, bayer: str = ""):
        self.path = Path(path)
        self.bayer = bayer
        if not self.path.is_dir():
            raise GBError(f"input folder {self.path} does not exist")
        files, ignored = [], []
        for p in self.path.iterdir():
            if p.name.startswith("."):
                continue  # hidden files and the temporary files of atomic writes
            if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES:
                files.append(p)
            else:
                ignored.append(p.name)
        files.sort(key=lambda p: _natural_key(p.name))
        if not files:
            raise GBError(f"input folder {self.path} holds no images ({', '.join(IMAGE_SUFFIXES)}); "
                          "give a folder of frames or a video file")
        self.files = tuple(files)
        self.ignored = tuple(sorted(ignored, key=_natural_key))

    def __len__(self) -> int:
        return len(self.files)

    @property
    def random_access(self) -> bool:
        return True

    def ref(self, index: int) -> FrameRef:
        p = self.files[index]
        return FrameRef(index, p.name, p, self.bayer)

    def frames(self, refs, size=None):
        for r in refs:
            yield r, read_frame(r, size)

    def input_warning(self) -> str | None:
        """:func:`gbscan.io.input_warning` of the first JPEG frame (the others are alike, as a rule)."""
        first = next((p for p in self.files if p.suffix.lower() in (".jpg", ".jpeg")), None)
        w = input_warning(first) if first is not None else None
        n = sum(p.suffix.lower() in (".jpg", ".jpeg") for p in self.files)
        return None if w is None else w + (f" ({n} JPEG frames)" if n > 1 else "")


def read_frame(ref: FrameRef, size: tuple[int, int] | None = None) -> np.ndarray | GBError:
    """Read the image file of a folder frame; a GBError (returned, not raised) when it is bad."""
    if ref.path is None:
        return GBError(f"frame {ref.index} ({ref.source}) has no file to read")
    try:
        return read_image_rgb(ref.path, size=size, what="frame", bayer=ref.bayer)
    except GBError as e:
        return e


#: Codec pixel formats (FourCC, as FFmpeg in OpenCV reports them) that subsample chroma
CHROMA_SUBSAMPLED = {"I420": "4:2:0", "IYUV": "4:2:0", "YV12": "4:2:0", "NV12": "4:2:0", "NV21": "4:2:0",
                      "J420": "4:2:0", "YUY2": "4:2:2", "YUYV": "4:2:2", "UYVY": "4:2:2", "Y42B": "4:2:2",
                      "J422": "4:2:2", "Y41B": "4:1:1"}
#: Lossless video codecs (FourCC, case-insensitive)
_LOSSLESS_CODECS = {"ffv1", "hfyu", "ffvh", "png", "mpng", "raw"}


def fourcc_text(value) -> str:
    """A FourCC property of cv2.VideoCapture as text ("" when absent), trailing NULs / blanks dropped."""
    v = int(value or 0)
    return v.to_bytes(4, "little").decode("latin-1").rstrip("\x00 ") if v > 0 else ""


class VideoFrames(FrameSource):
    """A video file read with cv2.VideoCapture (FFmpeg backend), sequentially.  ``codec`` and
    ``pixel_format`` are the stream's FourCCs as FFmpeg reports them ("" when unknown)."""

    kind = "video"

    def __init__(self, path: str | Path):
        import cv2

        self.path = Path(path)
        if not self.path.is_file():
            raise GBError(f"input video {self.path} does not exist")
        with _quiet_opencv():
            cap = cv2.VideoCapture(str(self.path), cv2.CAP_FFMPEG)
            ok, first = cap.read() if cap.isOpened() else (False, None)
        if not ok or first is None:
            cap.release()
            raise GBError(f"input video {self.path} could not be opened or holds no readable frame "
                          "(corrupt, or a codec FFmpeg in OpenCV cannot decode); convert it, e.g. "
                          "'ffmpeg -i IN -c:v ffv1 OUT.mkv', or extract the frames to a folder")
        self.width, self.height = int(first.shape[1]), int(first.shape[0])
        self.codec = fourcc_text(cap.get(cv2.CAP_PROP_FOURCC))
        self.pixel_format = fourcc_text(cap.get(cv2.CAP_PROP_CODEC_PIXEL_FORMAT))
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        self.fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        cap.release()
        if n <= 0:  # some containers do not say: count by grabbing once
            cap = cv2.VideoCapture(str(self.path), cv2.CAP_FFMPEG)
            n = 0
            while cap.grab():
                n += 1
            cap.release()
        self.n_frames = n
        self.ignored = ()

    def __len__(self) -> int:
        return self.n_frames

    def input_warning(self) -> str | None:
        """A warning for a chroma-subsampled (4:2:0 / 4:2:2) or lossy video codec (most are)."""
        sampling = CHROMA_SUBSAMPLED.get(self.pixel_format)
        if sampling:
            return (f"warning: video {self.path} stores {sampling} chroma ({self.codec or 'codec ?'} / "
                    f"{self.pixel_format}): {CHROMA_COST}; record lossless RGB frames (an image sequence, or "
                    "FFV1 / HuffYUV in RGB): converting this file does not bring the chroma back")
        if self.codec and self.codec.lower() not in _LOSSLESS_CODECS:
            return (f"warning: video {self.path} uses the lossy codec {self.codec}: its artefacts cost points and "
                    "add depth noise; record lossless frames (FFV1, PNG) where the camera allows")
        return None

    def ref(self, index: int) -> FrameRef:
        if not 0 <= index < self.n_frames:
            raise IndexError(index)
        return FrameRef(index, f"{self.path.name}#{index}", None)

    def frames(self, refs, size=None):
        import cv2

        refs = list(refs)
        if any(b.index <= a.index for a, b in zip(refs, refs[1:])):
            raise GBError("video frames must be requested in increasing order")
        if size is not None and (self.width, self.height) != tuple(size):
            for r in refs:
                yield r, GBError(f"video {self.path.name} is {self.width}x{self.height} but {size[0]}x{size[1]} "
                                 "was expected (the calibration's camera size)")
            return
        cap = cv2.VideoCapture(str(self.path), cv2.CAP_FFMPEG)
        pos, ended = 0, False
        try:
            for r in refs:
                while not ended and pos < r.index:
                    ended = not cap.grab()
                    pos += 1
                frame = None
                if not ended:
                    ok, frame = cap.read()
                    pos += 1
                    ended = not ok
                if ended or frame is None:
                    yield r, GBError(f"frame {r.index}: the video ended or could not be decoded there "
                                     f"(its container announced {self.n_frames} frames)")
                    continue
                if frame.ndim == 2:
                    yield r, GBError(f"frame {r.index}: grey video frame; the decoder needs colour")
                    continue
                # OpenCV decodes to BGR: convert at this edge so the rest sees RGB.
                yield r, np.ascontiguousarray(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
        finally:
            cap.release()


def open_frames(path: str | Path, bayer: str = "") -> FrameSource:
    """A folder of images or a video file; GBError naming the path if it is neither.  ``bayer``:
    the folder's images are raw mosaics of this pattern (:func:`gbscan.io.demosaic`)."""
    path = Path(path)
    if path.is_dir():
        return FolderFrames(path, bayer)
    if bayer:
        raise GBError(f"--bayer applies to a folder of raw frames; {path} is not a folder (a video's frames "
                      "come out of FFmpeg in colour already)")
    if not path.exists():
        raise GBError(f"input {path} does not exist (give a folder of frames or a video file)")
    if path.suffix.lower() in IMAGE_SUFFIXES:
        raise GBError(f"input {path} is a single image; use 'gbscan scan' for one frame, or give its folder")
    return VideoFrames(path)


def write_video(path: str | Path, frames, fps: float = 30.0, fourcc: str = "FFV1") -> Path:
    """Write RGB uint8 frames (each (H, W, 3), same size) as a video, atomically.

    ``FFV1`` (default; .avi or .mkv) is lossless and works in opencv-python-headless; ``MJPG``
    is lossy.  Used for test and demo sequences.
    """
    import cv2

    from .io import atomic_path

    path = Path(path)
    frames = list(frames)
    if not frames:
        raise GBError(f"write_video({path}): no frames")
    h, w = frames[0].shape[:2]
    with atomic_path(path) as tmp:
        with _quiet_opencv():
            vw = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*fourcc), float(fps), (w, h))
        if not vw.isOpened():
            raise GBError(f"cannot write video {path} with codec {fourcc!r} (not available in this OpenCV)")
        try:
            for f in frames:
                f = np.asarray(f)
                if f.shape != (h, w, 3) or f.dtype != np.uint8:
                    raise GBError(f"write_video({path}): every frame must be uint8 ({h}, {w}, 3), got "
                                  f"{f.dtype} {f.shape}")
                vw.write(np.ascontiguousarray(f[:, :, ::-1]))
        finally:
            vw.release()
    return path
