"""Files at the edge: images, YAML, NPZ, capture sessions.  Every write is atomic.

A write goes to a temporary file in the destination folder, is flushed to disk, and replaces the
destination with ``os.replace``; a failure at any point removes the temporary file, so a failed
run never leaves a half-written output behind.

Images in memory are RGB ``uint8`` arrays ``(H, W, 3)`` (OpenCV's BGR appears only here).

Capture session (a fixed contract, written by the simulator and the guided capture script)::

    SESSION/session.yaml   board: {cols, rows, square_mm}   # inner corners along x and y
                           camera: {width, height}
                           projector: {width, height}
                           frames: [name, ...]             # projector frames, display order
    SESSION/pose_000/<name>.png, SESSION/pose_001/<name>.png, ...   one camera image per frame
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from .errors import GBError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".ppm", ".pgm")


# -- atomic writes -----------------------------------------------------------------------------
@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None):
    """Yield a temporary path beside ``path``; on success it replaces ``path`` atomically.

    ``suffix`` defaults to the destination's own (writers such as OpenCV and open3d pick the
    format from it).  Raises GBError if the destination folder is missing or not writable.
    """
    with _atomic_path(path, suffix, sync=True) as tmp:
        yield tmp


@contextlib.contextmanager
def atomic_path_unsynced(path: str | os.PathLike, suffix: str | None = None):
    """:func:`atomic_path` without flushing the file to disk before the rename.

    Every reader sees the whole file or none of it, as long as the system runs; after a power
    failure or a kernel crash the file may be missing or empty.  For bulk writers that make
    their files durable together (:func:`fsync_paths`) before recording them anywhere, so that
    the write does not wait for the disk (``gbscan batch``: workers write, the parent syncs
    before the manifest lists the frame).
    """
    with _atomic_path(path, suffix, sync=False) as tmp:
        yield tmp


def fsync_paths(paths) -> None:
    """Flush the given files to disk, then their folders (each once); missing files are skipped."""
    folders = set()
    for p in paths:
        p = Path(p)
        try:
            fd = os.open(p, os.O_RDONLY)
        except FileNotFoundError:
            continue
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        folders.add(p.parent if str(p.parent) else Path("."))
    for d in folders:
        with contextlib.suppress(OSError):  # not every file system can sync a folder
            fd = os.open(d, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)


@contextlib.contextmanager
def _atomic_path(path, suffix, sync: bool):
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise GBError(f"cannot write {path}: folder {folder} does not exist (create it first)")
    if not os.access(folder, os.W_OK):
        raise GBError(f"cannot write {path}: folder {folder} is not writable")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix if suffix is not None else path.suffix,
                               dir=folder)
    os.close(fd)
    try:
        yield Path(tmp)
        if not Path(tmp).exists() or Path(tmp).stat().st_size == 0:
            raise GBError(f"writing {path} produced no data")
        if sync:
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; outputs get the usual mode
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def make_dir(path, what: str = "output folder") -> Path:
    """Create folder ``path`` (and parents) if missing; GBError "cannot create <what> <path>: why"."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise GBError(f"cannot create {what} {path}: {e.strerror}") from None
    return path


def write_bytes_atomic(path, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_text_atomic(path, text: str) -> Path:
    return write_bytes_atomic(path, text.encode("utf-8"))


def save_yaml(path, data: dict, header: str = "") -> Path:
    """Write ``data`` as block-style YAML (keys in insertion order), atomically."""
    text = yaml.safe_dump(_plain(data), sort_keys=False, default_flow_style=None, width=100)
    return write_text_atomic(path, header + text)


def load_yaml(path, what: str = "YAML file") -> dict:
    """Read a YAML mapping; GBError naming the file if it is missing, unreadable or not a mapping."""
    path = Path(path)
    if not path.is_file():
        raise GBError(f"{what} {path} does not exist")
    try:
        # libyaml's loader when PyYAML has it (the calibration file: 17 ms instead of 115 ms)
        data = yaml.load(path.read_text(encoding="utf-8"), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise GBError(f"{what} {path} is not valid YAML ({_first_line(e)}); fix or regenerate it") from None
    if not isinstance(data, dict):
        raise GBError(f"{what} {path} must hold a YAML mapping, found {type(data).__name__}")
    return data


def save_npz(path, **arrays) -> Path:
    """Write a compressed .npz atomically (the name must end in .npz)."""
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez_compressed(tmp, **arrays)
    return Path(path)


def save_npy(path, array: np.ndarray) -> Path:
    with atomic_path(path, suffix=".npy") as tmp:
        np.save(tmp, array)
    return Path(path)


def _plain(x):
    """numpy scalars/arrays -> plain Python for YAML."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    return x


def _first_line(e: Exception) -> str:
    return str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__


# -- images ------------------------------------------------------------------------------------
#: Bayer mosaics (named by the sensor's top-left 2x2, row by row) -> OpenCV's edge-aware
#: demosaicing code.  OpenCV's COLOR_Bayer<XXXX>2RGB aliases are named the same way (checked in tests).
BAYER_CODES = {"RGGB": "COLOR_BayerRGGB2RGB_EA", "BGGR": "COLOR_BayerBGGR2RGB_EA",
               "GRBG": "COLOR_BayerGRBG2RGB_EA", "GBRG": "COLOR_BayerGBRG2RGB_EA"}


def demosaic(raw: np.ndarray, pattern: str) -> np.ndarray:
    """A raw Bayer mosaic (H, W) uint8 or uint16 -> RGB (H, W, 3) of the same type, by OpenCV's
    edge-aware demosaicing (what ``gbscan.sim`` models a colour camera with).  ``pattern``: the
    sensor's top-left 2x2, one of :data:`BAYER_CODES`."""
    import cv2

    if pattern not in BAYER_CODES:
        raise GBError(f"Bayer pattern must be one of {', '.join(BAYER_CODES)}, got {pattern!r}")
    raw = np.asarray(raw)
    if raw.ndim != 2 or raw.dtype not in (np.uint8, np.uint16) or min(raw.shape) < 2:
        raise GBError(f"a raw Bayer mosaic must be one 8- or 16-bit channel, got {raw.shape} {raw.dtype}")
    return cv2.cvtColor(np.ascontiguousarray(raw), getattr(cv2, BAYER_CODES[pattern]))


def read_image_rgb(path, *, size: tuple[int, int] | None = None, what: str = "image",
                   bayer: str = "") -> np.ndarray:
    """Read a colour image as RGB uint8 (H, W, 3).

    16-bit images are scaled to 8 bits.  ``bayer`` (e.g. "RGGB"): the file is a camera's raw
    mosaic, one channel, demosaiced here (:func:`demosaic`).  Raises GBError naming the file if it
    is missing, unreadable, grey (the decoder needs colour) -- or colour when ``bayer`` says raw --,
    or not ``size = (width, height)`` when given.
    """
    import cv2

    path = Path(path)
    if not path.is_file():
        raise GBError(f"{what} {path} does not exist")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise GBError(f"{what} {path} could not be read as an image (corrupt or unsupported format)")
    if img.dtype not in (np.uint8, np.uint16):
        raise GBError(f"{what} {path} has pixel type {img.dtype}; expected 8- or 16-bit")
    grey = img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 1)
    if bayer:
        if not grey:
            raise GBError(f"{what} {path} is a colour image, not a raw Bayer mosaic; drop --bayer")
        rgb = demosaic(img.reshape(img.shape[:2]), bayer)
    elif grey:
        raise GBError(f"{what} {path} is a grey image; the green-blue decoder needs a colour (RGB) image "
                      "(a camera's raw Bayer mosaic: give --bayer PATTERN, e.g. RGGB)")
    elif img.shape[2] not in (3, 4):
        raise GBError(f"{what} {path} has {img.shape[2]} channels; expected a colour image (3 channels, or 4 with alpha)")
    else:   # (OpenCV's swap: 30x faster than numpy's copy of img[:, :, ::-1])
        rgb = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    if rgb.dtype == np.uint16:
        rgb = (rgb >> 8).astype(np.uint8)
    if size is not None and (rgb.shape[1], rgb.shape[0]) != tuple(size):
        raise GBError(f"{what} {path} is {rgb.shape[1]}x{rgb.shape[0]} but {size[0]}x{size[1]} was expected "
                      "(the calibration's camera size); use images from the calibrated camera")
    return rgb


#: IJG (libjpeg) standard luminance quantisation table (JPEG Annex K), natural order, summed:
#: the reference :func:`jpeg_info` scales against.
_IJG_LUMA_SUM = sum((16, 11, 10, 16, 24, 40, 51, 61, 12, 12, 14, 19, 26, 58, 60, 55, 14, 13, 16, 24, 40, 57,
                     69, 56, 14, 17, 22, 29, 51, 87, 80, 62, 18, 22, 37, 56, 68, 109, 103, 77, 24, 35, 55, 64,
                     81, 104, 113, 92, 49, 64, 78, 87, 103, 121, 120, 101, 72, 92, 95, 98, 112, 100, 103, 99))
_SOF_MARKERS = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_SUBSAMPLING = {(1, 1): "4:4:4", (2, 1): "4:2:2", (2, 2): "4:2:0", (4, 1): "4:1:1", (1, 2): "4:4:0"}


def jpeg_info(path) -> dict | None:
    """Chroma subsampling and approximate quality of a JPEG file, from its header; None if the
    file is not a JPEG (or its header cannot be parsed).

    Returns ``{"sampling": "4:4:4" | "4:2:2" | "4:2:0" | "4:1:1" | "4:4:0" | "other" | "grey",
    "quality": int | None}``.  The quality is the IJG scale (libjpeg, OpenCV, most cameras' encoders
    use its tables) that reproduces the luminance table's sum: exact for IJG-made files, an
    equivalent figure for others."""
    try:
        with open(path, "rb") as fh:
            data = fh.read(1 << 16)   # headers come first; 64 KiB holds them
    except OSError:
        return None
    if data[:2] != b"\xff\xd8":
        return None
    i, sampling, quality = 2, None, None
    while i + 4 <= len(data) and data[i] == 0xFF:
        marker = data[i + 1]
        if marker == 0xFF:            # fill byte
            i += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        n = int.from_bytes(data[i + 2:i + 4], "big")
        seg = data[i + 4:i + 2 + n]
        if marker == 0xDB:            # quantisation tables: [Pq|Tq] + 64 entries (8 or 16 bit)
            j = 0
            while j < len(seg):
                pq, tq = seg[j] >> 4, seg[j] & 15
                size = 128 if pq else 64
                vals = np.frombuffer(seg[j + 1:j + 1 + size], dtype=">u2" if pq else np.uint8)
                if tq == 0 and vals.size == 64 and quality is None:
                    scale = 100.0 * float(vals.sum()) / _IJG_LUMA_SUM
                    q = (200.0 - scale) / 2.0 if scale <= 100 else 5000.0 / scale
                    quality = 100 if vals.max() == 1 else int(min(max(round(q), 1), 100))
                j += 1 + size
        elif marker in _SOF_MARKERS and len(seg) >= 6:
            nf = seg[5]
            comps = [(seg[6 + 3 * k + 1] >> 4, seg[6 + 3 * k + 1] & 15) for k in range(nf) if 8 + 3 * k < len(seg)]
            if nf == 1:
                sampling = "grey"
            elif nf == 3 and len(comps) == 3 and comps[1] == comps[2] == (1, 1):
                sampling = _SUBSAMPLING.get(comps[0], "other")
            else:
                sampling = "other"
        elif marker == 0xDA:          # start of scan: the header is over
            break
        i += 2 + n
    if sampling is None:
        return None
    return {"sampling": sampling, "quality": quality}


#: What halving the colour resolution costs (simulated, ``scripts/coverage_study.py --jpeg``): the
#: words every input warning about chroma subsampling uses (files, videos, cameras).
CHROMA_COST = ("the colour stripes lose half their resolution and whole regions land on wrong stripes, so the "
               "decoder withholds the absolute index of such frames (DecodeParams.subsampled_chroma)")


def input_warning(path) -> str | None:
    """One line of warning when a camera frame is stored lossily in a way that costs the colour
    stripes (a JPEG: chroma subsampling or low quality), else None.  Measured on simulated frames
    of the paper rig (``scripts/coverage_study.py --jpeg``; docs/method.md "Camera frames")."""
    info = jpeg_info(path)
    if info is None or info["sampling"] == "grey":
        return None
    q = info["quality"]
    qtext = f", quality ~{q}" if q is not None else ""
    if info["sampling"] != "4:4:4":
        return (f"warning: {path} is a JPEG with {info['sampling']} chroma subsampling{qtext}: {CHROMA_COST}; "
                "capture lossless frames (PNG, TIFF) or JPEG 4:4:4 at quality 95+")
    if q is not None and q < 95:
        return (f"warning: {path} is a JPEG of quality ~{q}: its artefacts cost points and add depth noise "
                "(simulated face, quality 85: 72-76 % of its pixels kept instead of 84-86 %, depth RMS x1.4; "
                "points up to 6 mm off); capture lossless frames (PNG, TIFF) or JPEG 4:4:4 at quality 95+")
    return None


def read_image_gray(path, *, what: str = "image") -> np.ndarray:
    """Read any image as grey uint8 (H, W); GBError naming the file if it cannot be read."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise GBError(f"{what} {path} does not exist")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise GBError(f"{what} {path} could not be read as an image (corrupt or unsupported format)")
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    if img.ndim == 3:
        img = cv2.cvtColor(img[:, :, :3], cv2.COLOR_BGR2GRAY)
    return img


def write_png(path, image: np.ndarray) -> Path:
    """Write an RGB (H, W, 3) or grey (H, W) uint8 image as PNG, atomically."""
    import cv2

    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise GBError(f"write_png({path}): expected uint8 pixels, got {image.dtype}")
    out = image[:, :, ::-1] if image.ndim == 3 else image
    with atomic_path(path, suffix=".png") as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(out)):
            raise GBError(f"could not encode {path} as PNG")
    return Path(path)


def write_figure_png(path, fig, **savefig_kw) -> Path:
    """Write a matplotlib figure as PNG, atomically (``savefig_kw``: matplotlib's ``savefig``
    options, e.g. ``dpi``, ``bbox_inches``).  The figure stays open: the caller closes it."""
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png", **savefig_kw)
    return Path(path)


# -- capture sessions --------------------------------------------------------------------------
@dataclass(frozen=True)
class Session:
    """A capture session folder (see the module docstring for the layout)."""

    root: Path
    board_cols: int
    board_rows: int
    square_mm: float
    camera_size: tuple[int, int]
    projector_size: tuple[int, int]
    frames: tuple[str, ...]
    poses: tuple[Path, ...]
    extra: dict

    def frame_path(self, pose: int, name: str) -> Path:
        return self.poses[pose] / f"{name}.png"


def write_session_yaml(root, *, board: tuple[int, int, float], camera_size, projector_size, frames,
                       extra: dict | None = None) -> Path:
    data = {
        "schema": "gbcal.session",
        "version": 1,
        "board": {"cols": int(board[0]), "rows": int(board[1]), "square_mm": float(board[2])},
        "camera": {"width": int(camera_size[0]), "height": int(camera_size[1])},
        "projector": {"width": int(projector_size[0]), "height": int(projector_size[1])},
        "frames": [str(f) for f in frames],
    }
    data.update(extra or {})
    return save_yaml(Path(root) / "session.yaml", data)


def load_session(root) -> Session:
    """Read and check a capture session folder; GBError naming what is missing or malformed."""
    root = Path(root)
    if not root.is_dir():
        raise GBError(f"session folder {root} does not exist")
    f = root / "session.yaml"
    if not f.is_file():
        raise GBError(f"{root} is not a capture session: {f.name} is missing "
                      "(make one with scripts/guided_calibration.py or gbcal simulate-session)")
    d = load_yaml(f, "session file")

    def need(mapping, key, where):
        if not isinstance(mapping, dict) or key not in mapping:
            raise GBError(f"session file {f}: field '{where}{key}' is missing")
        return mapping[key]

    def pos_int(v, name):
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise GBError(f"session file {f}: '{name}' must be a positive integer, got {v!r}")
        return v

    board = need(d, "board", "")
    cols = pos_int(need(board, "cols", "board."), "board.cols")
    rows = pos_int(need(board, "rows", "board."), "board.rows")
    sq = need(board, "square_mm", "board.")
    if isinstance(sq, bool) or not isinstance(sq, (int, float)) or not sq > 0:
        raise GBError(f"session file {f}: 'board.square_mm' must be a positive number, got {sq!r}")
    cam = need(d, "camera", "")
    proj = need(d, "projector", "")
    cam_size = (pos_int(need(cam, "width", "camera."), "camera.width"),
                pos_int(need(cam, "height", "camera."), "camera.height"))
    proj_size = (pos_int(need(proj, "width", "projector."), "projector.width"),
                 pos_int(need(proj, "height", "projector."), "projector.height"))
    frames = need(d, "frames", "")
    if not isinstance(frames, list) or not frames or not all(isinstance(x, str) and x for x in frames):
        raise GBError(f"session file {f}: 'frames' must be a non-empty list of frame names")
    poses = tuple(sorted(p for p in root.glob("pose_[0-9][0-9][0-9]*") if p.is_dir()))
    if not poses:
        raise GBError(f"session {root} has no pose_000/ ... folders with captures")
    known = {"schema", "version", "board", "camera", "projector", "frames"}
    extra = {k: v for k, v in d.items() if k not in known}
    return Session(root, cols, rows, float(sq), cam_size, proj_size, tuple(frames), poses, extra)
