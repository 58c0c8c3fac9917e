"""Surfaces from scans: organised-grid mesh, Poisson, Taubin smoothing, and file export.

Everything here works on numpy arrays (camera frame, mm); open3d is imported only for Poisson
reconstruction and for the ``to_open3d`` conversions.

Organised point clouds on disk
------------------------------
``gbscan scan`` writes its cloud as a binary little-endian PLY whose vertices carry, besides
``x y z nx ny nz`` (float32, mm), the decoder ``confidence`` (float32) and the camera pixel they
came from, ``row`` and ``col`` (int32), then each point's predicted error ``sigma_mm`` (float32,
mm along the camera ray, one standard deviation: :attr:`gbscan.scan.Scan.sigma_mm`) when the
decoder gave one, then, when the scan has its frame, the stripe-free grey texture as ``red green
blue`` (uchar, :mod:`gbscan.texture`), and a header comment
``gbscan_grid WIDTH HEIGHT``.  Any PLY reader (MeshLab, CloudCompare, open3d, Blender) reads the
points, normals and colours and ignores or keeps the extra properties; ``gbscan mesh --method
grid`` uses them to rebuild the organised grid.  A PLY without them can still be meshed with
``--method poisson``.

Mesh files: ``.ply`` (binary, vertex normals, vertex colours when the mesh has them), ``.obj``
(text, ``v``/``vn``/``f v//vn``), ``.stl`` (binary, triangle normals); OBJ and STL carry no
colours.  All writes are atomic (:func:`gbscan.io.atomic_path`).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import GBError
from .io import atomic_path

MESH_SUFFIXES = (".ply", ".obj", ".stl")


@dataclass(eq=False)
class Mesh:
    """A triangle mesh.

    vertices : (V, 3) float64 mm (camera frame).
    triangles : (T, 3) int64 vertex indices, counter-clockwise seen from the outside
        (for scans: from the camera).
    vertex_normals : (V, 3) float64 unit normals or None (computed on demand).
    pixel : (V, 2) int32 camera pixel ``(row, col)`` of each vertex of a grid mesh, else None.
    colors : (V, 3) uint8 RGB vertex colours (a scan's grey texture) or None.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    vertex_normals: np.ndarray | None = None
    pixel: np.ndarray | None = None
    colors: np.ndarray | None = None

    def __post_init__(self):
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.triangles = np.asarray(self.triangles, dtype=np.int64).reshape(-1, 3)
        if self.triangles.size and (self.triangles.min() < 0 or self.triangles.max() >= len(self.vertices)):
            raise GBError("mesh: triangle indices out of range")
        if self.colors is not None:
            self.colors = _colors_u8(self.colors, len(self.vertices), "mesh colors")

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_triangles(self) -> int:
        return int(self.triangles.shape[0])

    def normals(self) -> np.ndarray:
        """Vertex normals (V, 3), computed from the triangles if not stored."""
        if self.vertex_normals is None:
            self.vertex_normals = vertex_normals(self.vertices, self.triangles)
        return self.vertex_normals

    def to_open3d(self):
        """An ``open3d.geometry.TriangleMesh`` with vertex normals."""
        import open3d as o3d

        m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(self.vertices),
                                      o3d.utility.Vector3iVector(self.triangles.astype(np.int32)))
        m.vertex_normals = o3d.utility.Vector3dVector(np.nan_to_num(self.normals()))
        if self.colors is not None:
            m.vertex_colors = o3d.utility.Vector3dVector(self.colors.astype(np.float64) / 255.0)
        return m

    @classmethod
    def from_open3d(cls, m) -> "Mesh":
        v = np.asarray(m.vertices)
        n = np.asarray(m.vertex_normals) if m.has_vertex_normals() else None
        c = _colors_from_unit(np.asarray(m.vertex_colors)) if m.has_vertex_colors() else None
        return cls(v.copy(), np.asarray(m.triangles).copy(), None if n is None else n.copy(), colors=c)


def _colors_u8(colors, n: int, what: str) -> np.ndarray:
    """(n, 3) uint8 from (n, 3) or (n,) grey uint8 values; GBError naming ``what`` otherwise."""
    c = np.asarray(colors)
    if c.dtype != np.uint8:
        raise GBError(f"{what} must be uint8 (0..255), got {c.dtype}")
    if c.shape == (n,):
        c = np.repeat(c[:, None], 3, axis=1)
    if c.shape != (n, 3):
        raise GBError(f"{what} must be ({n}, 3) or ({n},), got {c.shape}")
    return np.ascontiguousarray(c)


def _colors_from_unit(c: np.ndarray) -> np.ndarray:
    """open3d's float colours in [0, 1] (N, 3) -> uint8."""
    return np.rint(np.clip(c, 0.0, 1.0) * 255.0).astype(np.uint8)


# -- geometry ----------------------------------------------------------------------------------
def _face_cross(v: np.ndarray, t: np.ndarray):
    """Per-triangle (b - a) x (c - a) as three (T,) arrays (length = twice the area)."""
    vx, vy, vz = (np.ascontiguousarray(v[:, k]) for k in range(3))
    i0, i1, i2 = (np.ascontiguousarray(t[:, k]) for k in range(3))
    ex, ey, ez = vx[i1] - vx[i0], vy[i1] - vy[i0], vz[i1] - vz[i0]
    fx, fy, fz = vx[i2] - vx[i0], vy[i2] - vy[i0], vz[i2] - vz[i0]
    return (ey * fz - ez * fy, ez * fx - ex * fz, ex * fy - ey * fx), (i0, i1, i2)


def triangle_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit normals (T, 3) of triangles (right-hand rule on the vertex order); zero if degenerate."""
    (nx, ny, nz), _ = _face_cross(np.asarray(vertices, dtype=np.float64), np.asarray(triangles))
    n = np.stack([nx, ny, nz], axis=1)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (V, 3); zero for vertices in no triangle."""
    from . import geomkernels as gk

    v = np.ascontiguousarray(vertices, dtype=np.float64).reshape(-1, 3)
    n = np.zeros((len(v), 3))
    if len(triangles) == 0:
        return n
    t = np.ascontiguousarray(triangles, dtype=np.int64).reshape(-1, 3)
    if t.min() < 0 or t.max() >= len(v):
        raise GBError("vertex_normals: triangle indices out of range")
    gk.area_weighted_normals(v, t, np.ones(len(v), bool), n)  # compiled: np.bincount's sums, in its order
    return n


def grid_mesh(xyz: np.ndarray, valid: np.ndarray | None = None, *, max_jump: float = 0.01,
              normals: np.ndarray | None = None, colors: np.ndarray | None = None) -> Mesh:
    """Mesh an organised point map: two triangles per 2x2 pixel quad whose four points are valid.

    xyz : (H, W, 3) float mm (camera frame), NaN where missing.
    valid : (H, W) bool, default: finite points.
    max_jump : a quad is cut when its depths span more than ``max_jump`` times its nearest depth
        (no triangles across depth discontinuities).
    normals : optional (H, W, 3) normals of the grid (e.g. ``Scan.normals_map``) to use as vertex
        normals where they are finite and non-zero; area-weighted from the triangles elsewhere,
        and everywhere without ``normals``.
    colors : optional (H, W, 3) or (H, W) grey uint8 colours of the grid (e.g. ``Scan.grey()``)
        for the vertices (``Mesh.colors``).

    Vertices are the valid pixels used by a triangle, in raster order (``Mesh.pixel`` gives their
    (row, col)); triangles face the camera.
    """
    from . import geomkernels as gk

    xyz = np.asarray(xyz)
    if xyz.ndim != 3 or xyz.shape[2] != 3:
        raise GBError(f"grid_mesh: expected an organised (H, W, 3) point map, got {xyz.shape}")
    H, W = xyz.shape[:2]
    if xyz.dtype not in (np.float32, np.float64):
        xyz = xyz.astype(np.float64)
    xyz = np.ascontiguousarray(xyz)
    use_valid = valid is not None
    valid = np.ascontiguousarray(valid, dtype=bool) if use_valid else np.zeros((H, W), bool)
    if valid.shape != (H, W):
        raise GBError(f"grid_mesh: valid is {valid.shape}, expected {(H, W)}")
    use_normals = normals is not None
    if use_normals:
        normals = np.asarray(normals)
        if normals.shape != (H, W, 3):
            raise GBError(f"grid_mesh: normals are {normals.shape}, expected {(H, W, 3)}")
        if normals.dtype not in (np.float32, np.float64):
            normals = normals.astype(np.float64)
        normals = np.ascontiguousarray(normals)
    else:
        normals = np.zeros((1, 1, 3))
    if colors is not None:
        colors = np.asarray(colors)
        if colors.dtype != np.uint8 or colors.shape[:2] != (H, W) or colors.ndim not in (2, 3) or \
                (colors.ndim == 3 and colors.shape[2] != 3):
            raise GBError(f"grid_mesh: colors are {colors.shape} {colors.dtype}, "
                          f"expected uint8 {(H, W, 3)} or {(H, W)}")
    # one compiled pass: depths, quads, vertex numbering, triangles, vertex normals -- over the
    # bounding box of the points when it is a small part of the grid (an object before darkness:
    # the same mesh, its vertices in the same raster order, their pixels moved back)
    y0, x0 = 0, 0
    win = grid_window(valid if use_valid else np.isfinite(xyz[..., 2]), 0, MESH_WINDOW_MAX_FRACTION)
    if win is not None:
        y0, y1, x0, x1 = win
        xyz = np.ascontiguousarray(xyz[y0:y1, x0:x1])
        valid = np.ascontiguousarray(valid[y0:y1, x0:x1]) if use_valid else valid
        normals = np.ascontiguousarray(normals[y0:y1, x0:x1]) if use_normals else normals
    verts, tris, pixel, vn, has_normal = gk.grid_mesh_arrays(xyz, valid, use_valid, np.float32(max_jump), normals,
                                                             use_normals)
    if win is not None:
        pixel += np.array([y0, x0], pixel.dtype)
    mesh = Mesh(verts, tris, pixel=pixel)
    if colors is not None:
        mesh.colors = _colors_u8(colors[pixel[:, 0], pixel[:, 1]], len(verts), "grid_mesh colors")
    if not use_normals:
        vn = vertex_normals(verts, tris)
    elif not has_normal.all():  # area-weighted where the grid has no normal, only there
        gk.area_weighted_normals(verts, tris, ~has_normal, vn)
    mesh.vertex_normals = vn
    return mesh


#: a bounding box of the points over this fraction of the grid is not worth cutting out
MESH_WINDOW_MAX_FRACTION = 0.6


def grid_window(present: np.ndarray, margin_px: int, max_fraction: float) -> tuple[int, int, int, int] | None:
    """(y0, y1, x0, x1), half-open: the bounding box of the True pixels of an (H, W) bool map grown
    by ``margin_px`` on each side (clipped to the map), for the organised-grid passes that can skip
    the rest (this module's :func:`grid_mesh`; the scan's cleaning, :func:`gbscan.scan.point_window`).
    None: no True pixel, or a box over ``max_fraction`` of the map (not worth cutting out)."""
    H, W = present.shape
    rows = np.flatnonzero(present.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(present[rows[0]:rows[-1] + 1].any(axis=0))
    m = int(margin_px)
    y0, y1 = max(0, int(rows[0]) - m), min(H, int(rows[-1]) + 1 + m)
    x0, x1 = max(0, int(cols[0]) - m), min(W, int(cols[-1]) + 1 + m)
    if (y1 - y0) * (x1 - x0) > max_fraction * H * W:
        return None
    return y0, y1, x0, x1


def remove_unreferenced(mesh: Mesh) -> Mesh:
    """Drop vertices used by no triangle (re-indexing the triangles)."""
    used = np.zeros(mesh.n_vertices, bool)
    used[mesh.triangles.ravel()] = True
    if used.all():
        return mesh
    new = np.cumsum(used) - 1
    return Mesh(mesh.vertices[used], new[mesh.triangles],
                None if mesh.vertex_normals is None else mesh.vertex_normals[used],
                None if mesh.pixel is None else mesh.pixel[used],
                None if mesh.colors is None else mesh.colors[used])


def taubin_smooth(mesh: Mesh, iterations: int = 5, lam: float = 0.5, mu: float = -0.53) -> Mesh:
    """Taubin's lambda|mu smoothing with the uniform (umbrella) Laplacian, in numpy.

    Each iteration moves every vertex by ``lam`` times the mean of its neighbours minus itself,
    then by ``mu`` (< -lam) times the same: noise is removed without the shrinkage of plain
    Laplacian smoothing.  Returns a new mesh with recomputed normals.
    """
    if iterations <= 0 or mesh.n_triangles == 0:
        return mesh
    if not (0 < lam < -mu):
        raise GBError(f"Taubin smoothing needs 0 < lam < -mu, got lam={lam}, mu={mu}")
    from scipy import sparse

    t = mesh.triangles
    V = mesh.n_vertices
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    A = sparse.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(V, V)).tocsr()
    A = ((A + A.T) > 0).astype(np.float64)  # symmetric 0/1 adjacency
    deg = np.asarray(A.sum(axis=1)).ravel()
    inv = np.divide(1.0, deg, out=np.zeros(V), where=deg > 0)
    has = (deg > 0)[:, None]
    v = mesh.vertices.copy()
    for _ in range(int(iterations)):
        for f in (lam, mu):
            lap = (A @ v) * inv[:, None] - v
            v += f * np.where(has, lap, 0.0)
    return Mesh(v, t.copy(), vertex_normals(v, t), None if mesh.pixel is None else mesh.pixel.copy(),
                None if mesh.colors is None else mesh.colors.copy())


def poisson_mesh(points: np.ndarray, normals: np.ndarray, *, depth: int = 9, density_quantile: float = 0.05,
                 crop_margin: float = 0.02, colors: np.ndarray | None = None) -> Mesh:
    """Screened Poisson surface (open3d) of an oriented cloud, trimmed to where data was.

    points, normals : (N, 3) mm and unit normals (oriented, e.g. towards the camera).
    depth : octree depth (9 -> ~512 cells across the cloud; each +1 doubles the resolution).
    density_quantile : vertices whose Poisson density (points supporting them) is in this lowest
        fraction are removed -- Poisson closes the surface far from the data; this cuts it back.
    crop_margin : also remove vertices outside the cloud's bounding box grown by this fraction.
    colors : optional (N, 3) uint8 point colours; the surface's vertices get open3d's
        interpolation of them (``Mesh.colors``).
    """
    import open3d as o3d

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if len(points) < 10:
        raise GBError(f"Poisson meshing needs at least 10 points, got {len(points)}")
    if not 1 <= int(depth) <= 14:
        raise GBError(f"Poisson depth must be between 1 and 14, got {depth}")
    good = np.isfinite(points).all(1) & np.isfinite(normals).all(1) & (np.linalg.norm(normals, axis=1) > 0)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[good]))
    pcd.normals = o3d.utility.Vector3dVector(normals[good])
    if colors is not None:
        colors = _colors_u8(colors, len(points), "poisson_mesh colors")
        pcd.colors = o3d.utility.Vector3dVector(colors[good].astype(np.float64) / 255.0)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        m, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=int(depth))
    dens = np.asarray(dens)
    v = np.asarray(m.vertices)
    lo, hi = points[good].min(0), points[good].max(0)
    margin = crop_margin * (hi - lo)
    keep = np.all((v >= lo - margin) & (v <= hi + margin), axis=1)
    if density_quantile > 0 and dens.size:
        keep &= dens >= np.quantile(dens, density_quantile)
    m.remove_vertices_by_mask(~keep)
    m.remove_unreferenced_vertices()
    out = Mesh(np.asarray(m.vertices).copy(), np.asarray(m.triangles).copy(),
               colors=_colors_from_unit(np.asarray(m.vertex_colors)) if colors is not None else None)
    out.vertex_normals = vertex_normals(out.vertices, out.triangles)
    return out


# -- point clouds on disk ----------------------------------------------------------------------
@dataclass(eq=False)
class Cloud:
    """A point cloud read from disk: points (N, 3) mm, normals (N, 3) or None, confidence (N,)
    or None, pixel (N, 2) int (row, col) or None, grid_size (width, height) or None, colors
    (N, 3) uint8 RGB or None, sigma_mm (N,) float32 predicted error per point (mm) or None."""

    points: np.ndarray
    normals: np.ndarray | None = None
    confidence: np.ndarray | None = None
    pixel: np.ndarray | None = None
    grid_size: tuple[int, int] | None = None
    colors: np.ndarray | None = None
    sigma_mm: np.ndarray | None = None

    @property
    def organised(self) -> bool:
        return self.pixel is not None and self.grid_size is not None

    def grid(self) -> tuple[np.ndarray, np.ndarray]:
        """The organised map: xyz (H, W, 3) float64 with NaN holes and valid (H, W) bool."""
        if not self.organised:
            raise GBError("this cloud carries no pixel grid (row/col); mesh it with --method poisson")
        W, H = self.grid_size
        r, c = self.pixel[:, 0], self.pixel[:, 1]
        if r.size and (r.min() < 0 or c.min() < 0 or r.max() >= H or c.max() >= W):
            raise GBError(f"cloud pixel rows/cols fall outside its {W}x{H} grid")
        xyz = self._on_grid(self.points, np.nan)
        return xyz, np.isfinite(xyz).all(-1)

    def _on_grid(self, values: np.ndarray, fill) -> np.ndarray:
        """(H, W, 3) map of per-point ``values`` (N, 3) at their pixels, ``fill`` elsewhere."""
        W, H = self.grid_size
        out = np.full((H, W, 3), fill, dtype=np.float64 if fill is np.nan else values.dtype)
        out[self.pixel[:, 0], self.pixel[:, 1]] = values
        return out

    def normal_grid(self) -> np.ndarray | None:
        """(H, W, 3) normals on the pixel grid (NaN where no point), or None without normals."""
        return self._on_grid(self.normals, np.nan) if self.normals is not None and self.organised else None

    def color_grid(self) -> np.ndarray | None:
        """(H, W, 3) uint8 colours on the pixel grid (0 where no point), or None without colours."""
        return self._on_grid(self.colors, 0) if self.colors is not None and self.organised else None


def write_cloud_ply(path, points: np.ndarray, normals: np.ndarray | None = None, *,
                    confidence: np.ndarray | None = None, pixel: np.ndarray | None = None,
                    grid_size: tuple[int, int] | None = None, colors: np.ndarray | None = None) -> Path:
    """Write a binary PLY point cloud atomically (see the module docstring for the layout).

    points (N, 3) mm; normals (N, 3); confidence (N,); pixel (N, 2) (row, col); grid_size (W, H);
    colors (N, 3) or (N,) grey uint8.
    """
    points = np.asarray(points).reshape(-1, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if confidence is not None:
        fields += [("confidence", "<f4")]
    if pixel is not None:
        fields += [("row", "<i4"), ("col", "<i4")]
    if colors is not None:
        colors = _colors_u8(colors, len(points), "write_cloud_ply colors")
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    rec = np.empty(len(points), dtype=np.dtype(fields))
    rec["x"], rec["y"], rec["z"] = points[:, 0], points[:, 1], points[:, 2]
    if normals is not None:
        normals = np.nan_to_num(np.asarray(normals).reshape(-1, 3))
        rec["nx"], rec["ny"], rec["nz"] = normals[:, 0], normals[:, 1], normals[:, 2]
    if confidence is not None:
        rec["confidence"] = np.asarray(confidence).ravel()
    if pixel is not None:
        pixel = np.asarray(pixel).reshape(-1, 2)
        rec["row"], rec["col"] = pixel[:, 0], pixel[:, 1]
    if colors is not None:
        rec["red"], rec["green"], rec["blue"] = colors[:, 0], colors[:, 1], colors[:, 2]
    comments = ["gbscan point cloud, camera frame (x right, y down, z forward), mm"]
    if pixel is not None and grid_size is not None:
        comments.append(f"gbscan_grid {int(grid_size[0])} {int(grid_size[1])}")
    return _write_ply(path, rec, None, comments)


def write_grid_cloud_ply(path, xyz: np.ndarray, normals: np.ndarray, confidence: np.ndarray,
                         reason: np.ndarray, colors: np.ndarray | None = None, *,
                         sigma_mm: np.ndarray | None = None) -> Path:
    """Write the kept pixels (``reason == 0``) of an organised scan as the PLY of
    :func:`write_cloud_ply` with normals, confidence, pixel, grid size, (when given) each point's
    predicted error and colours -- the same bytes -- in one compiled pass over the maps (no
    per-field gathers but the error's).

    xyz, normals : (H, W, 3) float32; confidence : (H, W) float32; reason : (H, W) uint8;
    colors : (H, W, 3) or (H, W) grey uint8, or None; sigma_mm : (H, W) float32 (property
    ``sigma_mm`` after ``row col``), or None.
    """
    from . import geomkernels as gk

    reason = np.ascontiguousarray(reason, dtype=np.uint8)
    H, W = reason.shape
    for name, a, shape in (("xyz", xyz, (H, W, 3)), ("normals", normals, (H, W, 3)),
                           ("confidence", confidence, (H, W)), ("sigma_mm", sigma_mm, (H, W))):
        if a is not None and np.shape(a) != shape:
            raise GBError(f"write_grid_cloud_ply: {name} is {np.shape(a)}, expected {shape}")
    n = int(np.count_nonzero(reason == 0))
    arr = np.empty((n, 9 if sigma_mm is None else 10), np.float32)
    gk.pack_cloud(np.ascontiguousarray(xyz, dtype=np.float32), np.ascontiguousarray(normals, dtype=np.float32),
                  np.ascontiguousarray(confidence, dtype=np.float32), reason, True, True, True, arr, arr.view(np.int32))
    fields = [(k, "<f4") for k in ("x", "y", "z", "nx", "ny", "nz", "confidence")] + [("row", "<i4"), ("col", "<i4")]
    if sigma_mm is not None:   # (pack_cloud fills the first nine columns, in raster order as this gather)
        arr[:, 9] = np.asarray(sigma_mm, np.float32)[reason == 0]
        fields.append(("sigma_mm", "<f4"))
    comments = ["gbscan point cloud, camera frame (x right, y down, z forward), mm", f"gbscan_grid {W} {H}"]
    if colors is not None:
        colors = np.asarray(colors)
        if colors.dtype != np.uint8 or colors.shape not in ((H, W), (H, W, 3)):
            raise GBError(f"write_grid_cloud_ply: colors are {colors.shape} {colors.dtype}, "
                          f"expected uint8 {(H, W, 3)} or {(H, W)}")
        colors = _colors_u8(colors[reason == 0], n, "write_grid_cloud_ply colors")
    return _write_ply(path, _vertex_records(arr, fields, colors), None, comments)


def read_cloud_ply(path) -> Cloud:
    """Read the vertices of a PLY file (binary or ASCII) into a :class:`Cloud`.

    Reads ``x y z`` and, when present, ``nx ny nz``, ``confidence``, ``row col``, ``sigma_mm``,
    ``red green blue`` and the ``gbscan_grid`` comment.  GBError naming the file if it is not a readable PLY point cloud.
    """
    path = Path(path)
    if not path.is_file():
        raise GBError(f"point cloud {path} does not exist")
    try:
        header, elements, data_start, fmt = _parse_ply_header(path)
    except (ValueError, UnicodeDecodeError, IndexError) as e:
        raise GBError(f"point cloud {path} is not a valid PLY file ({e})") from None
    grid = None
    for line in header:
        parts = line.split()
        if len(parts) == 4 and parts[0] in ("comment", "obj_info") and parts[1] == "gbscan_grid":
            grid = (int(parts[2]), int(parts[3]))
    if not elements or elements[0][0] != "vertex":
        raise GBError(f"point cloud {path}: the first PLY element must be 'vertex'")
    _, count, props = elements[0]
    names = [p[0] for p in props]
    if any(p[1] == "list" for p in props):
        raise GBError(f"point cloud {path}: list properties on vertices are not supported")
    for need in ("x", "y", "z"):
        if need not in names:
            raise GBError(f"point cloud {path}: vertices have no '{need}' property")
    try:
        if fmt == "ascii":
            with open(path, "rb") as fh:
                fh.seek(data_start)
                arr = np.loadtxt(fh, max_rows=count, ndmin=2, dtype=np.float64)
            if arr.shape != (count, len(names)):
                raise ValueError(f"expected {count} rows of {len(names)} numbers")
            rec = {n: arr[:, k] for k, n in enumerate(names)}
        else:
            end = "<" if fmt == "binary_little_endian" else ">"
            dt = np.dtype([(n, end + _PLY_TYPES[t]) for n, t in props])
            raw = np.fromfile(path, dtype=dt, count=count, offset=data_start)
            if raw.size != count:
                raise ValueError(f"file ends after {raw.size} of {count} vertices")
            rec = {n: raw[n] for n in names}
    except (ValueError, KeyError) as e:
        raise GBError(f"point cloud {path}: cannot read vertex data ({e}); is the file complete?") from None
    pts = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64)
    nrm = (np.stack([rec["nx"], rec["ny"], rec["nz"]], axis=1).astype(np.float64)
           if all(k in rec for k in ("nx", "ny", "nz")) else None)
    conf = rec["confidence"].astype(np.float32) if "confidence" in rec else None
    pix = (np.stack([rec["row"], rec["col"]], axis=1).astype(np.int64)
           if "row" in rec and "col" in rec else None)
    col = None
    if all(k in rec for k in ("red", "green", "blue")):
        col = np.stack([rec["red"], rec["green"], rec["blue"]], axis=1)
        if col.dtype != np.uint8:  # float colours in [0, 1] (some writers), or wider integers
            col = (_colors_from_unit(col.astype(np.float64)) if np.issubdtype(col.dtype, np.floating)
                   else np.clip(col, 0, 255).astype(np.uint8))
    sig = rec["sigma_mm"].astype(np.float32) if "sigma_mm" in rec else None
    return Cloud(pts, nrm, conf, pix, grid if pix is not None else None, col, sig)


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def _parse_ply_header(path: Path):
    with open(path, "rb") as fh:
        first = fh.readline()
        if first.strip() != b"ply":
            raise ValueError("missing 'ply' magic line")
        header, elements, fmt = [], [], None
        while True:
            line = fh.readline()
            if not line:
                raise ValueError("no end_header")
            text = line.decode("ascii").strip()
            header.append(text)
            parts = text.split()
            if not parts:
                continue
            if parts[0] == "format":
                fmt = parts[1]
                if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
                    raise ValueError(f"unknown format {fmt}")
            elif parts[0] == "element":
                elements.append((parts[1], int(parts[2]), []))
            elif parts[0] == "property":
                if parts[1] == "list":
                    elements[-1][2].append((parts[-1], "list"))
                else:
                    if parts[1] not in _PLY_TYPES:
                        raise ValueError(f"unknown property type {parts[1]}")
                    elements[-1][2].append((parts[2], parts[1]))
            elif parts[0] == "end_header":
                return header, elements, fh.tell(), fmt


def _vertex_records(arr: np.ndarray, fields: list, colors: np.ndarray | None) -> np.ndarray:
    """PLY vertex records: the 4-byte columns of ``arr`` (N, K) as ``fields``, followed by
    ``red green blue`` (uchar) from ``colors`` (N, 3) uint8 when given (packed: 4K + 3 bytes)."""
    n, k = arr.shape
    rec = arr.view(np.dtype(fields)).reshape(-1)
    if colors is None:
        return rec
    out = np.empty(n, np.dtype(fields + [("red", "u1"), ("green", "u1"), ("blue", "u1")]))
    b = out.view(np.uint8).reshape(n, 4 * k + 3)
    b[:, :4 * k] = arr.view(np.uint8).reshape(n, 4 * k)
    b[:, 4 * k:] = colors
    return out


def _write_ply(path, vertex_rec: np.ndarray, faces: np.ndarray | None, comments: list[str]) -> Path:
    inv = {"<f4": "float", "<i4": "int", "<u1": "uchar", "|u1": "uchar", "<f8": "double"}
    lines = ["ply", "format binary_little_endian 1.0"]
    lines += [f"comment {c}" for c in comments]
    lines.append(f"element vertex {len(vertex_rec)}")
    for name in vertex_rec.dtype.names:
        lines.append(f"property {inv[vertex_rec.dtype[name].str]} {name}")
    if faces is not None:
        lines.append(f"element face {len(faces)}")
        lines.append("property list uchar int vertex_indices")
    lines.append("end_header")
    fbuf = None
    if faces is not None:  # records "uchar 3, int32 a b c": 13 bytes, packed by a kernel
        from . import geomkernels as gk

        fbuf = np.empty(13 * len(faces), np.uint8)
        gk.pack_ply_faces(np.ascontiguousarray(faces, dtype=np.int64), fbuf)
    with atomic_path(path, suffix=".ply") as tmp:
        with open(tmp, "wb") as fh:
            fh.write(("\n".join(lines) + "\n").encode("ascii"))
            fh.write(memoryview(np.ascontiguousarray(vertex_rec)).cast("B"))
            if fbuf is not None:
                fh.write(memoryview(fbuf))
    return Path(path)


# -- meshes on disk ----------------------------------------------------------------------------
def write_mesh(path, mesh: Mesh) -> Path:
    """Write ``mesh`` as .ply (binary, vertex normals), .obj (vertex normals) or .stl (binary,
    triangle normals), chosen by the suffix; atomically."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise GBError(f"cannot write mesh {path}: the name must end in {', '.join(MESH_SUFFIXES)}")
    if mesh.n_triangles == 0:
        raise GBError(f"not writing {path}: the mesh has no triangles")
    from . import geomkernels as gk

    v = mesh.vertices
    n = np.nan_to_num(mesh.normals())
    if suffix == ".ply":
        arr = np.empty((len(v), 6), np.float32)  # x y z nx ny nz, viewed as the vertex records
        arr[:, :3] = v
        arr[:, 3:] = n
        fields = [(k, "<f4") for k in ("x", "y", "z", "nx", "ny", "nz")]
        return _write_ply(path, _vertex_records(arr, fields, mesh.colors), mesh.triangles,
                          ["gbscan mesh, camera frame, mm"])
    if suffix == ".obj":
        parts = [b"# gbscan mesh, camera frame (x right, y down, z forward), mm\n",
                 _obj_rows(b"v", v, 4), _obj_rows(b"vn", n, 5)]
        t = np.ascontiguousarray(mesh.triangles, dtype=np.int64)
        fbuf = np.empty(len(t) * (2 + 3 * (3 + 2 * _n_digits(len(v)))), np.uint8)
        parts.append(memoryview(fbuf[:gk.format_obj_faces(t, fbuf)]))
        with atomic_path(path, suffix=".obj") as tmp:
            with open(tmp, "wb") as fh:
                for part in parts:
                    fh.write(part)
        return path
    # .stl: 80-byte header, count, then per triangle normal + 3 corners (float32) + attribute
    buf = np.empty(50 * mesh.n_triangles, np.uint8)
    gk.stl_records(np.ascontiguousarray(v, dtype=np.float64), np.ascontiguousarray(mesh.triangles, dtype=np.int64),
                   buf)
    with atomic_path(path, suffix=".stl") as tmp:
        with open(tmp, "wb") as fh:
            fh.write(b"gbscan mesh, camera frame, mm".ljust(80, b" "))
            fh.write(np.uint32(mesh.n_triangles).tobytes())
            fh.write(memoryview(buf))
    return path


def _n_digits(n: int) -> int:
    return len(str(max(int(n), 1)))


def _obj_rows(prefix: bytes, values: np.ndarray, decimals: int):
    """OBJ lines ``prefix a b c`` with ``'%.{decimals}f'`` numbers, as bytes-like.

    The same text as Python's ``%`` formatting (correct rounding, half to even, ``-0.0000`` for
    small negatives): a compiled kernel rounds ``|x| * 10**decimals`` and writes the digits; the
    few values whose float64 product lies within two ulps of a half are rounded by Python.
    Values that are not finite or beyond 1e9 take Python's formatting for the whole block."""
    from . import geomkernels as gk

    x = np.ascontiguousarray(values, dtype=np.float64).reshape(-1)
    if x.size and not (np.all(np.isfinite(x)) and np.max(np.abs(x)) < 1e9):
        fmt = prefix.decode() + (f" %.{decimals}f" * 3) + "\n"
        return ((fmt * (x.size // 3)) % tuple(x)).encode("ascii")
    k = np.empty(x.size, np.int64)
    amb = np.empty(x.size, np.bool_)
    if gk.fixed_point_digits(x, decimals, k, amb):
        for i in np.flatnonzero(amb):
            k[i] = int(f"{abs(x[i]):.{decimals}f}".replace(".", ""))
    buf = np.empty((x.size // 3) * (len(prefix) + 1 + 3 * (decimals + 13)), np.uint8)
    nbytes = gk.format_rows(np.frombuffer(prefix, np.uint8), k, np.signbit(x), decimals, buf)
    return memoryview(buf[:nbytes])


def read_mesh(path) -> Mesh:
    """Read a mesh file with open3d (any format it knows); GBError if unreadable or empty."""
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise GBError(f"mesh {path} does not exist")
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        m = o3d.io.read_triangle_mesh(str(path))
    if len(m.triangles) == 0:
        raise GBError(f"mesh {path} could not be read or has no triangles")
    return Mesh.from_open3d(m)
