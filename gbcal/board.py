"""Checkerboard model and detection.

Board convention (docs/design.md, shared with ``gbscan.sim.scenes.board``):

* ``cols`` x ``rows`` *inner* corners (OpenCV ``patternSize = (cols, rows)``), ``square_mm`` the
  side of one square.
* Board frame: origin at the first inner corner, x along ``cols``, y along ``rows``, z = 0 on the
  printed surface and +z pointing *into* the board (away from a camera that sees its face), so
  the frame is right-handed and a board seen upright has x to the image right and y down.
* Inner corner ``(i, j)`` is at ``(i * square_mm, j * square_mm, 0)``; points are ordered row by
  row, x fastest (OpenCV's order).  The square spanning x in [0, s], y in [0, s] is **white**.
* Pose: ``p_cam = R_cam_board @ p_board + t_cam_board``.

Detected corners follow the same order (the *canonical order*, :func:`canonical_order`): of the
orderings of the ``cols`` x ``rows`` grid that are consistent with a board seen from its printed
side, the one whose first square is white; when the board's symmetry leaves several (``cols +
rows`` even, or a square grid), the one whose x axis points most to the image right.  Corners
are pixels ``(u, v)`` with pixel centres at integers (OpenCV's convention).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gbscan.errors import GBError

#: Default limit on the checkerboard edge width (10%-90% rise, px) from
#: ``cv2.estimateChessboardSharpness``.  Sharp real 640x480 captures measure 2.8-4.6 px; above
#: this the corners are too blurred to trust.
MAX_SHARPNESS_PX = 7.0
#: Default minimum white-minus-black brightness (grey levels, 0-255) on the board.
MIN_CONTRAST = 20.0
#: Corners closer than this to the image border (px) mean the board is cut by the frame.
BORDER_PX = 2.0
#: Largest accepted :func:`grid_irregularity`.  Real captures (Bouguet's 20 images, boards tilted
#: up to ~50 degrees, strong barrel distortion) measure 0.05-0.15 and simulated sessions 0.01-0.05;
#: a grid with one corner assigned to the wrong square measures ~1.
MAX_IRREGULARITY = 0.5
#: Corner refiners of :func:`refine_corners`: ``"symmetric"`` (the default: ``cornerSubPix``, then
#: :func:`refine_corners_symmetric`) or ``"cornersubpix"`` (OpenCV's ``cornerSubPix`` alone).
CORNER_REFINERS = ("symmetric", "cornersubpix")
DEFAULT_CORNER_REFINER = "symmetric"
#: Radius of :func:`refine_corners_symmetric`'s window as a fraction of the smallest corner spacing.
#: On rendered boards (known corners) the error falls as the window grows (0.45: 0.025 px RMS,
#: 0.7: 0.021 px; cornerSubPix 0.050 px); on Bouguet's real captures the estimate drifts as the
#: window grows past half a square (those corners are not point-symmetric at that scale), and at
#: 0.45 the intrinsics stay within the published values' tolerances.  docs/method.md, "Corners".
SYMMETRIC_WINDOW_FRAC = 0.45


@dataclass(frozen=True)
class Board:
    """A checkerboard of ``cols`` x ``rows`` inner corners with squares of ``square_mm``."""

    cols: int
    rows: int
    square_mm: float

    def __post_init__(self):
        for name in ("cols", "rows"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 2:
                raise GBError(f"board {name} must be an integer >= 2 (inner corners), got {v!r}")
            object.__setattr__(self, name, int(v))
        s = self.square_mm
        if isinstance(s, bool) or not isinstance(s, (int, float, np.floating, np.integer)) or not np.isfinite(s) \
                or s <= 0:
            raise GBError(f"board square_mm must be a positive number of millimetres, got {s!r}")
        object.__setattr__(self, "square_mm", float(s))
        if self.cols == 2 and self.rows == 2:
            raise GBError("board of 2x2 inner corners is too small to calibrate with; use at least 3x3")

    @property
    def pattern_size(self) -> tuple[int, int]:
        """OpenCV's ``patternSize`` ``(cols, rows)``."""
        return (self.cols, self.rows)

    @property
    def n_corners(self) -> int:
        return self.cols * self.rows

    def object_points(self) -> np.ndarray:
        """(N, 3) float64 inner-corner positions in the board frame, mm (row by row, x fastest)."""
        j, i = np.mgrid[0 : self.rows, 0 : self.cols]
        return np.stack([i.ravel() * self.square_mm, j.ravel() * self.square_mm, np.zeros(i.size)], axis=1)

    def __str__(self) -> str:
        return f"{self.cols}x{self.rows} inner corners, {self.square_mm:g} mm squares"


def parse_board(text: str, square_mm: float) -> Board:
    """``'COLSxROWS'`` and a square size -> :class:`Board` (GBError on a malformed size)."""
    try:
        c, r = str(text).lower().split("x")
        return Board(int(c), int(r), square_mm)
    except ValueError:
        raise GBError(f"--board must be COLSxROWS inner corners such as 9x6, got '{text}'") from None


@dataclass(frozen=True, eq=False)
class Detection:
    """One board found in one image.

    corners : (N, 2) float64 pixels ``(u, v)`` in the canonical order (``board.object_points()``).
    image_size : (width, height) px of the image it was found in.
    sharpness_px : mean edge width (10%-90% rise, px) across the board's squares; lower is sharper.
    black, white : mean brightness (0-255) of the black and white squares.
    method : ``"sb"`` (OpenCV's sector-based detector) or ``"classic"`` (findChessboardCorners +
        cornerSubPix).
    """

    corners: np.ndarray
    image_size: tuple[int, int]
    sharpness_px: float
    black: float
    white: float
    method: str

    @property
    def contrast(self) -> float:
        return self.white - self.black


def as_gray(image: np.ndarray, what: str = "image") -> np.ndarray:
    """RGB (H, W, 3) or grey (H, W) uint8/uint16 -> grey uint8 (H, W)."""
    import cv2

    img = np.asarray(image)
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    if img.dtype != np.uint8:
        raise GBError(f"{what}: expected 8-bit (or 16-bit) pixels, got {img.dtype}")
    if img.ndim == 3 and img.shape[2] in (3, 4):
        return cv2.cvtColor(np.ascontiguousarray(img[:, :, :3]), cv2.COLOR_RGB2GRAY)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim != 2:
        raise GBError(f"{what}: expected a grey (H, W) or RGB (H, W, 3) image, got shape {img.shape}")
    if min(img.shape) < 16:
        raise GBError(f"{what}: image of {img.shape[1]}x{img.shape[0]} px is too small to hold a board")
    return np.ascontiguousarray(img)


def detect(image: np.ndarray, board: Board, *, refine: bool = True, max_sharpness_px: float = MAX_SHARPNESS_PX,
           min_contrast: float = MIN_CONTRAST, refiner: str = DEFAULT_CORNER_REFINER) -> Detection | None:
    """Find ``board`` in ``image`` (grey (H, W) or RGB (H, W, 3) uint8); None if not found or rejected.

    :func:`detect_with_reason` does the same and says why a board was not accepted.
    """
    return detect_with_reason(image, board, refine=refine, max_sharpness_px=max_sharpness_px,
                              min_contrast=min_contrast, refiner=refiner)[0]


def detect_with_reason(image: np.ndarray, board: Board, *, refine: bool = True,
                       max_sharpness_px: float = MAX_SHARPNESS_PX,
                       min_contrast: float = MIN_CONTRAST, what: str = "image",
                       refiner: str = DEFAULT_CORNER_REFINER) -> tuple[Detection | None, str]:
    """Find ``board`` in ``image``; returns ``(detection, "")`` or ``(None, reason)``.  An image
    that cannot hold a board (not 8/16-bit grey or RGB, under 16 px a side) is a GBError naming
    it ``what``; an unknown ``refiner`` (:data:`CORNER_REFINERS`) is a GBError too.

    OpenCV's sector-based detector (``findChessboardCornersSBWithMeta`` with NORMALIZE_IMAGE |
    EXHAUSTIVE) runs first, then the classic ``findChessboardCorners``; with ``refine`` the
    corners are then polished by :func:`refine_corners` with ``refiner`` (measurably more
    accurate than SB alone; ``refine=False`` is the fast mode for live previews).  A found board is
    rejected, with the reason, when its edges are wider than ``max_sharpness_px`` (blur), its
    contrast is below ``min_contrast`` grey levels, or a corner lies within ``BORDER_PX`` of the
    image border (board cut by the frame).  Corners are returned in the canonical order.
    """
    import cv2

    check_refiner(refiner)
    gray = as_gray(image, what)
    h, w = gray.shape
    size = board.pattern_size
    # CALIB_CB_ACCURACY (2x upsampled fit) is left out: cornerSubPix replaces its positions anyway
    # (same result either way on rendered and real boards) and it costs ~4x the time.
    flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE
    ok, corners, _meta = cv2.findChessboardCornersSBWithMeta(gray, size, flags)
    method = "sb"
    if not ok or corners is None or corners.size != 2 * board.n_corners:
        method = "classic"
        cflags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        ok, corners = cv2.findChessboardCorners(gray, size, flags=cflags)
        if not ok or corners is None or corners.size != 2 * board.n_corners:
            return None, _why_not_found(gray, board)
    if refine:
        corners = refine_corners(gray, board, corners, refiner)
    c = corners.reshape(-1, 2).astype(np.float64)
    if not np.all(np.isfinite(c)):
        return None, "detector returned non-finite corners"
    margin = min(c[:, 0].min(), c[:, 1].min(), (w - 1) - c[:, 0].max(), (h - 1) - c[:, 1].max())
    if margin < BORDER_PX:
        return None, (f"board touches the image border (a corner {max(margin, 0):.1f} px from the edge); "
                      "keep the whole board with a margin inside the frame")
    irregular = grid_irregularity(c, board)
    if not irregular <= MAX_IRREGULARITY:
        return None, (f"the {method} detector returned a corner grid that is not a regular checkerboard "
                      f"(irregularity {irregular:.2f}, limit {MAX_IRREGULARITY:g}: corners assigned to the wrong "
                      "squares); retake the capture with the whole board sharp and evenly lit")
    c = canonical_order(c, board, gray)
    sharp, black, white = _sharpness(gray, board, c)
    if not np.isfinite(sharp):
        return None, "could not measure the board's sharpness (board too small in the image?)"
    if white - black < min_contrast:
        return None, (f"contrast too low: white squares {white:.0f} vs black {black:.0f} grey levels "
                      f"(need {min_contrast:.0f}); light the board better or raise the exposure")
    if sharp > max_sharpness_px:
        return None, (f"board blurred: edges {sharp:.1f} px wide (limit {max_sharpness_px:.1f} px); "
                      "refocus, hold the board still, or shorten the exposure")
    return Detection(c, (w, h), float(sharp), float(black), float(white), method), ""


def grid_irregularity(corners: np.ndarray, board: Board) -> float:
    """How far a detected (N, 2) corner grid is from a smooth (projective, mildly distorted) grid.

    The largest second difference along the board's rows and columns, ``|c[i+1] - 2 c[i] +
    c[i-1]|``, divided by the local corner spacing ``|c[i+1] - c[i-1]| / 2``.  A perspective view of
    a planar board, even with strong lens distortion, changes the spacing slowly (values around
    0.01-0.15); a corner assigned to the wrong square jumps by a whole spacing (~1).  Unitless.
    """
    g = np.asarray(corners, dtype=np.float64).reshape(board.rows, board.cols, 2)
    worst = 0.0
    for a in (g, g.transpose(1, 0, 2)):
        if a.shape[1] < 3:
            continue
        d2 = np.linalg.norm(a[:, 2:] - 2.0 * a[:, 1:-1] + a[:, :-2], axis=-1)
        spacing = 0.5 * np.linalg.norm(a[:, 2:] - a[:, :-2], axis=-1)
        worst = max(worst, float(np.max(d2 / np.maximum(spacing, 1e-9))))
    return worst


def check_refiner(refiner: str) -> str:
    """``refiner`` if it is one of :data:`CORNER_REFINERS`, else a GBError naming the choices."""
    if refiner not in CORNER_REFINERS:
        raise GBError(f"corner refiner must be one of {', '.join(CORNER_REFINERS)}, got {refiner!r}")
    return refiner


def refine_corners(gray: np.ndarray, board: Board, corners: np.ndarray,
                   refiner: str = DEFAULT_CORNER_REFINER) -> np.ndarray:
    """(N, 2) corners -> refined (N, 2) float64 pixels.

    Always first ``cv2.cornerSubPix``, half-window 0.35 x the smallest corner spacing (2..11 px):
    after the sector-based detector too, because on Bouguet's real captures a few of SB's corners
    are 2-3 px off, which it corrects (calibration RMS 0.27 -> 0.17 px, fx, fy within 0.1 px of the
    published values).  With ``refiner="symmetric"`` (the default) the corners are then polished
    by :func:`refine_corners_symmetric`, which halves the remaining error on rendered boards with
    known corners (0.050 -> 0.025 px RMS; cornerSubPix's own error there is a bias of each corner,
    not noise) and lowers the calibration RMS on Bouguet's captures from 0.17 to 0.14 px.
    """
    import cv2

    check_refiner(refiner)
    c = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    spacing = _min_spacing_px(c, board)
    half = int(np.clip(round(0.35 * spacing), 2, 11))
    out = cv2.cornerSubPix(gray, c.astype(np.float32).reshape(-1, 1, 2).copy(), (half, half), (-1, -1),
                           (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4))
    out = out.reshape(-1, 2).astype(np.float64)
    if refiner == "symmetric":
        out = refine_corners_symmetric(gray, board, out)
    return out


def _bilinear(img: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``img`` (H, W) float64 sampled bilinearly at pixels ``q`` (..., 2), clamped to the image."""
    h, w = img.shape
    x = np.clip(q[..., 0], 0.0, w - 1.000001)
    y = np.clip(q[..., 1], 0.0, h - 1.000001)
    x0 = x.astype(np.int64)
    y0 = y.astype(np.int64)
    fx, fy = x - x0, y - y0
    top = img[y0, x0] * (1.0 - fx) + img[y0, x0 + 1] * fx
    bottom = img[y0 + 1, x0] * (1.0 - fx) + img[y0 + 1, x0 + 1] * fx
    return top * (1.0 - fy) + bottom * fy


def refine_corners_symmetric(gray: np.ndarray, board: Board, corners: np.ndarray, *,
                             window_frac: float = SYMMETRIC_WINDOW_FRAC, min_radius_px: int = 3,
                             max_radius_px: int = 12, iterations: int = 20,
                             max_shift_px: float = 1.0) -> np.ndarray:
    """Polish (N, 2) checkerboard corners by point symmetry; returns (N, 2) float64 pixels.

    Near an inner corner a checkerboard is two straight edges crossing, and the picture of two
    crossing lines with opposite wedges of equal colour is point-symmetric about the crossing,
    whatever the angles (perspective), the blur (any point-symmetric PSF), the tone curve (gamma,
    saturation) or the contrast.  So the corner ``q`` is where ``I(q + d) = I(q - d)`` for every
    offset ``d`` of a disc of radius ``window_frac`` x the smallest corner spacing (clipped to
    ``min_radius_px .. max_radius_px``), weighted by a Gaussian of the same sigma.  The model
    allows a linear change of light across the window, gain and offset
    (``I(q + d) = (1 + a . d) I(q - d) + b . d``: a lighting gradient, with the white squares
    saturated), and Gauss-Newton solves for ``q``, ``a`` and ``b`` with bilinear samples of the
    image and of its central-difference gradient.

    This is the symmetry criterion of corner finders such as ROCHADE and of OpenCV's
    ``findChessboardCornersSB`` refinement, fitted here over every pixel of the window.  A corner
    that moves more than ``max_shift_px``, does not settle or cannot be solved for (NaN pixels)
    keeps its input position.
    """
    c0 = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    if c0.size == 0:
        return c0.copy()
    g = np.asarray(gray, dtype=np.float64)
    gx = np.zeros_like(g)
    gy = np.zeros_like(g)
    gx[:, 1:-1] = 0.5 * (g[:, 2:] - g[:, :-2])
    gy[1:-1] = 0.5 * (g[2:] - g[:-2])
    r = int(np.clip(round(window_frac * _min_spacing_px(c0, board)), min_radius_px, max_radius_px))
    dv, du = np.mgrid[-r : r + 1, -r : r + 1]
    half = (du * du + dv * dv <= r * r) & ((dv > 0) | ((dv == 0) & (du > 0)))  # one of each +-d pair
    d = np.stack([du[half], dv[half]], axis=1).astype(np.float64)             # (K, 2)
    w = np.exp(-0.5 * np.sum(d * d, axis=1) / float(r * r))                    # (K,)
    c = c0.copy()
    active = np.ones(len(c), bool)
    for _ in range(iterations):
        p, m = c[active, None, :] + d, c[active, None, :] - d                  # (n, K, 2)
        ip, im = _bilinear(g, p), _bilinear(g, m)
        jq = np.stack([_bilinear(gx, p) - _bilinear(gx, m), _bilinear(gy, p) - _bilinear(gy, m)], axis=-1)
        jac = np.concatenate([jq, -im[..., None] * d, -np.broadcast_to(d, jq.shape)], axis=-1)  # (n, K, 6)
        a = np.einsum("nki,nkj,k->nij", jac, jac, w) + 1e-9 * np.eye(6)
        b = np.einsum("nki,nk,k->ni", jac, ip - im, w)
        try:
            sol = np.linalg.solve(a, b[..., None])[..., 0]
        except np.linalg.LinAlgError:  # some window without a corner (or with NaNs): corner by corner
            sol = np.full(b.shape, np.nan)
            for k in range(len(a)):
                try:
                    sol[k] = np.linalg.solve(a[k], b[k])
                except np.linalg.LinAlgError:
                    pass
        step = -sol[:, :2]
        idx = np.flatnonzero(active)
        c[idx] += step
        last_step = np.max(np.abs(step), axis=1)
        active[idx[~(last_step >= 1e-5)]] = False  # settled, or NaN (reverted below)
        if not active.any():
            break
    unsettled = np.zeros(len(c), bool)
    if active.any():  # still moving after ``iterations`` steps: only a last step under 1e-3 px is kept
        unsettled[np.flatnonzero(active)[last_step[active[idx]] >= 1e-3]] = True
    bad = unsettled | ~np.all(np.isfinite(c), axis=1) | (np.linalg.norm(c - c0, axis=1) > max_shift_px)
    c[bad] = c0[bad]
    return c


def _min_spacing_px(c: np.ndarray, board: Board) -> float:
    g = c.reshape(board.rows, board.cols, 2)
    dx = np.linalg.norm(np.diff(g, axis=1), axis=-1)
    dy = np.linalg.norm(np.diff(g, axis=0), axis=-1)
    return float(min(dx.min(), dy.min()))


def _why_not_found(gray: np.ndarray, board: Board) -> str:
    import cv2

    lo, hi = np.percentile(gray, [2, 98])
    if hi - lo < 20:
        return (f"no checkerboard found: the image has almost no contrast (grey levels {lo:.0f}-{hi:.0f}); "
                "check exposure and lighting")
    small = gray
    while max(small.shape) > 1400:
        small = cv2.pyrDown(small)
    if cv2.checkChessboard(small, board.pattern_size):
        return (f"a checkerboard is visible but not all {board.cols}x{board.rows} inner corners were found "
                "(partly outside the frame, occluded, blurred, or a different board size than --board?)")
    return (f"no {board.cols}x{board.rows} checkerboard found (board absent, too small, too oblique, or "
            "--board does not count inner corners?)")


# -- canonical order ---------------------------------------------------------------------------
def _grid_candidates(g: np.ndarray, square: bool) -> list[np.ndarray]:
    """Orderings of a (rows, cols, 2) corner grid that keep its shape (rotations and mirrors)."""
    out = [g, g[::-1, ::-1], g[:, ::-1], g[::-1, :]]
    if square:
        t = g.transpose(1, 0, 2)
        out += [t, t[::-1, ::-1], t[:, ::-1], t[::-1, :]]
    return [np.ascontiguousarray(x) for x in out]


def _handedness(g: np.ndarray) -> float:
    """Signed area of the grid's outline in the image (u right, v down): > 0 for a board seen from
    its printed side with this ordering (x cross y along the viewing direction)."""
    outline = np.concatenate([g[0, :], g[1:, -1], g[-1, -2::-1], g[-2:0:-1, 0]], axis=0)
    u, v = outline[:, 0], outline[:, 1]
    return 0.5 * float(np.sum(u * np.roll(v, -1) - np.roll(u, -1) * v))


def _square_brightness(gray: np.ndarray, g: np.ndarray) -> np.ndarray:
    """(rows-1, cols-1) mean brightness of each square between inner corners of grid ``g``."""
    import cv2

    a, b, c, d = g[:-1, :-1], g[:-1, 1:], g[1:, :-1], g[1:, 1:]
    centre = (a + b + c + d) / 4.0
    pts = [centre] + [centre + 0.5 * (x - centre) for x in (a, b, c, d)]
    pts = np.stack(pts, axis=0).astype(np.float32)  # (5, rows-1, cols-1, 2)
    flat = pts.reshape(1, -1, 2)
    vals = cv2.remap(gray.astype(np.float32), flat[..., 0], flat[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)
    return vals.reshape(pts.shape[:-1]).mean(axis=0)


def canonical_order(corners: np.ndarray, board: Board, gray: np.ndarray) -> np.ndarray:
    """Reorder (N, 2) grid corners into the board convention's order (see the module docstring).

    Among the orderings that keep the ``cols`` x ``rows`` shape and are right-handed as seen from
    the printed side, keep those whose first square (between corners (0,0) and (1,1)) is white in
    ``gray``; then pick the one whose x axis is most aligned with the image's +u direction.
    """
    g = np.asarray(corners, dtype=np.float64).reshape(board.rows, board.cols, 2)
    cands = [x for x in _grid_candidates(g, board.cols == board.rows) if _handedness(x) > 0]
    if not cands:  # degenerate outline; keep the detector's order
        return g.reshape(-1, 2)
    scored = []
    for x in cands:
        sq = _square_brightness(gray, x)
        parity = (np.add.outer(np.arange(sq.shape[0]), np.arange(sq.shape[1])) % 2) == 0
        colour = sq[parity].mean() - (sq[~parity].mean() if np.any(~parity) else 0.0)
        xdir = x[:, -1] - x[:, 0]
        xdir = xdir.sum(axis=0)
        right = xdir[0] / (np.linalg.norm(xdir) + 1e-12)
        scored.append((colour > 0, right, x))
    white_first = [s for s in scored if s[0]] or scored
    best = max(white_first, key=lambda s: s[1])
    return best[2].reshape(-1, 2).copy()


def _sharpness(gray: np.ndarray, board: Board, corners: np.ndarray) -> tuple[float, float, float]:
    """(edge width px, black level, white level) from ``cv2.estimateChessboardSharpness``."""
    import cv2

    try:
        res = cv2.estimateChessboardSharpness(gray, board.pattern_size, corners.astype(np.float32).reshape(-1, 1, 2))
    except cv2.error:
        return float("nan"), float("nan"), float("nan")
    vals = res[0] if isinstance(res, tuple) else res
    return float(vals[0]), float(vals[1]), float(vals[2])


def draw_detection(image: np.ndarray, board: Board, detection: Detection | None,
                   reprojected: np.ndarray | None = None) -> np.ndarray:
    """RGB (H, W, 3) uint8 picture: corners (OpenCV colouring), the first corner circled, the board
    x (red) and y (green) directions, and optional reprojected corners (N, 2) as magenta crosses."""
    import cv2

    gray = as_gray(image)
    out = cv2.cvtColor(gray, cv2.COLOR_GRAY2RGB)
    if detection is None:
        return out
    c = detection.corners
    cv2.drawChessboardCorners(out, board.pattern_size, c.astype(np.float32).reshape(-1, 1, 2), True)
    p0 = tuple(int(round(v)) for v in c[0])
    px = tuple(int(round(v)) for v in c[board.cols - 1])
    py = tuple(int(round(v)) for v in c[(board.rows - 1) * board.cols])
    cv2.arrowedLine(out, p0, px, (255, 0, 0), 2, tipLength=0.05)
    cv2.arrowedLine(out, p0, py, (0, 255, 0), 2, tipLength=0.05)
    cv2.circle(out, p0, 8, (255, 255, 0), 2)
    if reprojected is not None:
        for u, v in np.asarray(reprojected).reshape(-1, 2):
            if np.isfinite(u) and np.isfinite(v):
                cv2.drawMarker(out, (int(round(u)), int(round(v))), (255, 0, 255), cv2.MARKER_CROSS, 6, 1)
    return out
