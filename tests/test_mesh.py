"""Grid and Poisson meshing, smoothing, PLY/OBJ/STL export, shaded renders."""
import warnings

import numpy as np
import pytest
from test_triangulate import tilted_plane, truth

from gbscan.errors import GBError
from gbscan.mesh import (Mesh, grid_mesh, poisson_mesh, read_cloud_ply, taubin_smooth, triangle_normals,
                         vertex_normals, write_cloud_ply, write_mesh)
from gbscan.preview.scan import render_mesh
from gbscan.rig import paper_rig


@pytest.fixture(scope="module")
def rig():
    return paper_rig()


@pytest.fixture(scope="module")
def sphere_scene(rig):
    """Sphere (r 80 at 600 mm) before a wall at 750 mm: ground-truth points."""
    p, _, oid = truth(rig, spheres=[((0.0, 0.0, 600.0), 80.0)], planes=[tilted_plane(750.0, (0.0, 0.0, -1.0))])
    return p, oid


def test_grid_mesh_counts_orientation_and_cuts(sphere_scene):
    p, oid = sphere_scene
    m = grid_mesh(p, max_jump=0.01)
    ok = np.isfinite(p[..., 2])
    z = p[..., 2]
    quads = ok[:-1, :-1] & ok[1:, :-1] & ok[:-1, 1:] & ok[1:, 1:]
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        zs = np.stack([z[:-1, :-1], z[1:, :-1], z[:-1, 1:], z[1:, 1:]])
        same = np.nanmax(zs, 0) - np.nanmin(zs, 0) <= 0.01 * np.nanmin(zs, 0)
    assert m.n_triangles == 2 * int((quads & same).sum())
    # no triangle spans sphere and wall
    tri_oid = oid[m.pixel[m.triangles, 0], m.pixel[m.triangles, 1]]
    assert np.all(tri_oid == tri_oid[:, :1])
    # all triangles face the camera; vertex normals too
    tn = triangle_normals(m.vertices, m.triangles)
    centroid = m.vertices[m.triangles].mean(1)
    assert np.all((tn * centroid).sum(1) < 0)
    assert np.all((m.normals() * m.vertices).sum(1) < 0)
    # vertices are exactly the input points of their pixels
    np.testing.assert_array_equal(m.vertices, p[m.pixel[:, 0], m.pixel[:, 1]])


def test_vertex_normals_of_a_sphere_point_outwards(sphere_scene):
    p, oid = sphere_scene
    m = grid_mesh(np.where((oid == 0)[..., None], p, np.nan))
    radial = m.vertices - [0.0, 0.0, 600.0]
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    cos = (vertex_normals(m.vertices, m.triangles) * radial).sum(1)
    assert np.median(cos) > 0.9999 and cos.min() > 0.9


def test_taubin_reduces_noise_without_shrinking(rig):
    n, d = tilted_plane(650.0, (0.0, 0.0, -1.0))
    p, _, _ = truth(rig, planes=[(n, d)])
    rng = np.random.default_rng(3)
    noisy = p + rng.normal(0, 0.3, p.shape)
    m = grid_mesh(noisy, max_jump=0.05)
    s = taubin_smooth(m, 10)
    before = np.std(m.vertices[:, 2] - 650.0)
    after = np.std(s.vertices[:, 2] - 650.0)
    assert after < 0.5 * before
    span = lambda v: np.ptp(v[:, 0])  # noqa: E731
    assert abs(span(s.vertices) - span(m.vertices)) < 0.01 * span(m.vertices)
    with pytest.raises(GBError, match="lam"):
        taubin_smooth(m, 1, lam=0.6, mu=-0.5)


def test_poisson_on_a_sphere_cap(sphere_scene):
    p, oid = sphere_scene
    sel = (oid == 0) & np.isfinite(p[..., 2])
    pts = p[sel][::3]
    nrm = (pts - [0.0, 0.0, 600.0]) / 80.0
    m = poisson_mesh(pts, nrm, depth=7)
    r = np.linalg.norm(m.vertices - [0.0, 0.0, 600.0], axis=1)
    assert m.n_triangles > 1000
    assert np.median(np.abs(r - 80.0)) < 0.5 and np.percentile(np.abs(r - 80.0), 95) < 2.0
    with pytest.raises(GBError, match="at least 10"):
        poisson_mesh(pts[:5], nrm[:5])


def test_mesh_files_round_trip(tmp_path, sphere_scene):
    import open3d as o3d

    p, _ = sphere_scene
    m = grid_mesh(p[::4, ::4], max_jump=0.05)
    for suffix in ("ply", "obj", "stl"):
        path = write_mesh(tmp_path / f"m.{suffix}", m)
        r = o3d.io.read_triangle_mesh(str(path))
        assert len(r.triangles) == m.n_triangles, suffix
        corners = np.asarray(r.vertices)[np.asarray(r.triangles)]  # readers may re-index vertices
        np.testing.assert_allclose(corners, m.vertices[m.triangles], atol=1e-3)
        if suffix == "stl":  # binary STL: 80-byte header, count, then normal + 3 corners + attribute
            raw = path.read_bytes()
            rec = np.frombuffer(raw, np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")]), offset=84)
            assert int(np.frombuffer(raw[80:84], "<u4")[0]) == len(rec) == m.n_triangles
            np.testing.assert_allclose(rec["n"], triangle_normals(m.vertices, m.triangles), atol=1e-6)
    with pytest.raises(GBError, match="must end in"):
        write_mesh(tmp_path / "m.xyz", m)
    with pytest.raises(GBError, match="does not exist"):
        write_mesh(tmp_path / "missing" / "m.ply", m)
    assert sorted(x.name for x in tmp_path.iterdir()) == ["m.obj", "m.ply", "m.stl"]


def test_organised_cloud_round_trip_rebuilds_the_grid(tmp_path, sphere_scene):
    p, _ = sphere_scene
    ok = np.isfinite(p[..., 2])
    rows, cols = np.nonzero(ok)
    pts = p[ok].astype(np.float32)
    nrm = np.tile([0.0, 0.0, -1.0], (len(pts), 1))
    write_cloud_ply(tmp_path / "c.ply", pts, nrm, confidence=np.full(len(pts), 0.5),
                    pixel=np.stack([rows, cols], 1), grid_size=(640, 480))
    c = read_cloud_ply(tmp_path / "c.ply")
    assert c.organised and c.grid_size == (640, 480)
    np.testing.assert_array_equal(c.points, pts)
    np.testing.assert_array_equal(c.confidence, 0.5)
    xyz, valid = c.grid()
    np.testing.assert_array_equal(valid, ok)
    assert grid_mesh(xyz, valid).n_triangles == grid_mesh(p.astype(np.float32)).n_triangles
    # open3d reads it as an ordinary cloud with normals
    import open3d as o3d

    pc = o3d.io.read_point_cloud(str(tmp_path / "c.ply"))
    assert len(pc.points) == len(pts) and pc.has_normals()


def test_read_cloud_rejects_bad_files(tmp_path):
    (tmp_path / "bad.ply").write_bytes(b"not a ply\n")
    with pytest.raises(GBError, match="not a valid PLY"):
        read_cloud_ply(tmp_path / "bad.ply")
    write_cloud_ply(tmp_path / "c.ply", np.zeros((100, 3)))
    data = (tmp_path / "c.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[: len(data) - 50])
    with pytest.raises(GBError, match="is the file complete"):
        read_cloud_ply(tmp_path / "cut.ply")
    (tmp_path / "a.ply").write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                                    "property float z\nend_header\n1 2 3\n4 5 6\n")
    c = read_cloud_ply(tmp_path / "a.ply")
    np.testing.assert_array_equal(c.points, [[1, 2, 3], [4, 5, 6]])
    assert not c.organised
    with pytest.raises(GBError, match="poisson"):
        c.grid()


def test_render_shows_the_mesh_where_it_projects(rig, sphere_scene):
    p, oid = sphere_scene
    m = grid_mesh(np.where((oid == 0)[..., None], p, np.nan))
    img = render_mesh(m.vertices, m.triangles, rig.camera.K, (640, 480))
    assert img.shape == (480, 640) and img.dtype == np.uint8
    # the undistorted projection of the sphere is a disc of radius ~ f * r / sqrt(d^2 - r^2)
    v, u = np.nonzero(img > 0)
    radius = 800.0 * 80.0 / np.sqrt(600.0 ** 2 - 80.0 ** 2)
    dist = np.hypot(u - 319.5, v - 239.5)
    assert dist.max() < radius + 2 and (img[239, 319] > 150)
    assert np.pi * radius ** 2 * 0.97 < (img > 0).sum() < np.pi * radius ** 2 * 1.01
    empty = Mesh(np.zeros((0, 3)), np.zeros((0, 3), int))
    assert not render_mesh(empty.vertices, empty.triangles, rig.camera.K, (64, 48)).any()
    # a per-vertex albedo (a scan's grey texture) multiplies the shading
    half = render_mesh(m.vertices, m.triangles, rig.camera.K, (640, 480), albedo=np.full(m.n_vertices, 0.5))
    lit = img > 20
    assert np.array_equal(half > 0, img > 0) and np.abs(half[lit] - 0.5 * img[lit].astype(float)).max() <= 1
    with pytest.raises(GBError, match="albedo"):
        render_mesh(m.vertices, m.triangles, rig.camera.K, (640, 480), albedo=np.ones(3))


# -- compiled mesh building and writers: the same arrays and bytes as plain numpy ----------------
def _grid_mesh_numpy(xyz, valid=None, max_jump=0.01, normals=None):
    """The numpy formulation of grid_mesh's rules (the reference the compiled pass must equal)."""
    H, W = xyz.shape[:2]
    with np.errstate(invalid="ignore"):
        z = ((xyz[..., 0] + xyz[..., 1] + xyz[..., 2]) * 0 + xyz[..., 2]).astype(np.float32)
    if valid is not None:
        z[~valid] = np.nan
    a, b, c, d = z[:-1, :-1], z[1:, :-1], z[:-1, 1:], z[1:, 1:]
    with np.errstate(invalid="ignore"):
        lo = np.minimum(np.minimum(a, b), np.minimum(c, d))
        quad = np.maximum(np.maximum(a, b), np.maximum(c, d)) - lo <= np.float32(max_jump) * lo
    used = np.zeros((H, W), bool)
    for dv, du in ((0, 0), (1, 0), (0, 1), (1, 1)):
        used[dv:H - 1 + dv, du:W - 1 + du] |= quad
    rows, cols = np.nonzero(used)
    index = np.full((H, W), -1, np.int64)
    index[rows, cols] = np.arange(rows.size)
    qv, qu = np.nonzero(quad)
    ia, ib, ic, id_ = index[qv, qu], index[qv + 1, qu], index[qv, qu + 1], index[qv + 1, qu + 1]
    tris = np.stack([np.stack([ia, ib, ic], 1), np.stack([ic, ib, id_], 1)], 1).reshape(-1, 3)
    verts = xyz[rows, cols].astype(np.float64)
    n = _vertex_normals_numpy(verts, tris)
    if normals is not None:  # the grid's normals where finite and non-zero
        given = normals[rows, cols].astype(np.float64)
        use = np.isfinite(given).all(1) & (np.abs(given).sum(1) > 0)
        n[use] = given[use]
    return verts, tris, np.stack([rows, cols], 1).astype(np.int32), n


def _vertex_normals_numpy(v, t):
    e, f = v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]
    fn = (e[:, 1] * f[:, 2] - e[:, 2] * f[:, 1], e[:, 2] * f[:, 0] - e[:, 0] * f[:, 2],
          e[:, 0] * f[:, 1] - e[:, 1] * f[:, 0])
    n = np.stack([sum(np.bincount(t[:, k], weights=fn[c], minlength=len(v)) for k in range(3)) for c in range(3)], 1)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_grid_mesh_equals_the_numpy_formulation(sphere_scene, dtype):
    p, oid = sphere_scene
    xyz = p.astype(dtype)
    xyz[100:104, 300:330, 0] = np.inf  # not finite in one coordinate: no vertex
    rng = np.random.default_rng(0)
    valid = np.isfinite(p[..., 2]) & (rng.random(p.shape[:2]) > 0.02)
    nrm = np.where(np.isfinite(xyz), -xyz / np.linalg.norm(p, axis=-1, keepdims=True), np.nan).astype(np.float32)
    holed = nrm.copy()
    holed[240, 320] = np.nan  # one vertex without a normal: area-weighted there only
    holed[250, 300] = 0.0
    for kw in (dict(), dict(valid=valid), dict(valid=valid, normals=nrm), dict(normals=holed), dict(max_jump=0.2)):
        m = grid_mesh(xyz, **kw)
        ref = _grid_mesh_numpy(xyz, **kw)
        for got, want in zip((m.vertices, m.triangles, m.pixel, m.normals()), ref):
            assert got.dtype == want.dtype and np.array_equal(got, want), kw
    assert np.array_equal(vertex_normals(m.vertices, m.triangles), _vertex_normals_numpy(m.vertices, m.triangles))


def _numpy_mesh_bytes(m, suffix):
    """The files as plain numpy/Python formatting writes them."""
    v, n, t = m.vertices, np.nan_to_num(m.normals()), m.triangles
    if suffix == "obj":
        text = "# gbscan mesh, camera frame (x right, y down, z forward), mm\n"
        text += ("v %.4f %.4f %.4f\n" * len(v)) % tuple(v.ravel())
        text += ("vn %.5f %.5f %.5f\n" * len(n)) % tuple(n.ravel())
        text += ("f %d//%d %d//%d %d//%d\n" * len(t)) % tuple(np.repeat(t + 1, 2, axis=1).ravel())
        return text.encode("ascii")
    if suffix == "stl":
        rec = np.zeros(len(t), np.dtype([("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("a", "<u2")]))
        rec["n"], rec["v"] = triangle_normals(v, t), v[t]
        return b"gbscan mesh, camera frame, mm".ljust(80, b" ") + np.uint32(len(t)).tobytes() + rec.tobytes()
    rec = np.empty(len(v), np.dtype([(k, "<f4") for k in ("x", "y", "z", "nx", "ny", "nz")]))
    for k, col in zip(rec.dtype.names, np.concatenate([v, n], 1).T):
        rec[k] = col
    frec = np.empty(len(t), np.dtype([("n", "u1"), ("v", "<i4", (3,))]))
    frec["n"], frec["v"] = 3, t
    head = ("ply\nformat binary_little_endian 1.0\ncomment gbscan mesh, camera frame, mm\n"
            f"element vertex {len(v)}\n" + "".join(f"property float {k}\n" for k in rec.dtype.names) +
            f"element face {len(t)}\nproperty list uchar int vertex_indices\nend_header\n")
    return head.encode("ascii") + rec.tobytes() + frec.tobytes()


def test_mesh_files_are_the_bytes_numpy_formatting_writes(tmp_path, sphere_scene):
    p, _ = sphere_scene
    m = grid_mesh(p[::3, ::3], max_jump=0.05)
    # awkward numbers for the fixed-point text: exact ties (half to even), values just off a
    # tie, tiny negatives ('-0.0000'), negative zero, long integer parts
    odd = np.array([1.03125, 2.00005, -1.03125, -1e-6, -0.0, 0.0, 123456.78125, 0.00015, 0.00025, 9.99995,
                    -9.999949999, 12345678.5, 0.5, 1.5, 2.5, 4.4999999999])
    m.vertices[:len(odd) // 3] = odd[:len(odd) // 3 * 3].reshape(-1, 3)
    m.vertex_normals[:5] = [[-0.0, 1e-7, -1e-7], [0.000005, 0.000015, -0.000025], [1, 0, 0], [0, 0, 0], [0.1, 0.2, 0.3]]
    for suffix in ("obj", "ply", "stl"):
        path = write_mesh(tmp_path / f"m.{suffix}", m)
        assert path.read_bytes() == _numpy_mesh_bytes(m, suffix), suffix
    m.vertices[0, 0] = 3e12  # beyond the kernel's range: Python formats that block
    assert write_mesh(tmp_path / "big.obj", m).read_bytes() == _numpy_mesh_bytes(m, "obj")


def test_scan_cloud_is_write_cloud_ply(tmp_path, sphere_scene):
    """The compiled organised-cloud writer writes the bytes of write_cloud_ply with every field."""
    from gbscan.mesh import write_grid_cloud_ply

    p, _ = sphere_scene
    H, W = p.shape[:2]
    rng = np.random.default_rng(2)
    xyz = p.astype(np.float32)
    reason = np.where(np.isfinite(p[..., 2]) & (rng.random((H, W)) > 0.1), 0, 3).astype(np.uint8)
    nrm = rng.normal(size=(H, W, 3)).astype(np.float32)
    nrm[5, 5] = [np.nan, np.inf, -np.inf]
    reason[5, 5] = 0
    conf = rng.random((H, W)).astype(np.float32)
    ok = reason == 0
    write_grid_cloud_ply(tmp_path / "a.ply", xyz, nrm, conf, reason)
    write_cloud_ply(tmp_path / "b.ply", xyz[ok], nrm[ok], confidence=conf[ok], pixel=np.argwhere(ok).astype(np.int32),
                    grid_size=(W, H))
    assert (tmp_path / "a.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()
    c = read_cloud_ply(tmp_path / "a.ply")
    assert c.organised and c.grid_size == (W, H) and len(c.points) == ok.sum()
    # with colours (the scan's grey texture, or RGB): the same bytes again, and read back
    grey = rng.integers(0, 256, (H, W), dtype=np.uint8)
    rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    for col in (grey, rgb):
        write_grid_cloud_ply(tmp_path / "ca.ply", xyz, nrm, conf, reason, col)
        write_cloud_ply(tmp_path / "cb.ply", xyz[ok], nrm[ok], confidence=conf[ok],
                        pixel=np.argwhere(ok).astype(np.int32), grid_size=(W, H), colors=col[ok])
        assert (tmp_path / "ca.ply").read_bytes() == (tmp_path / "cb.ply").read_bytes()
        c = read_cloud_ply(tmp_path / "ca.ply")
        want = np.repeat(col[ok][:, None], 3, 1) if col.ndim == 2 else col[ok]
        np.testing.assert_array_equal(c.colors, want)
        np.testing.assert_array_equal(c.color_grid()[ok], want)
        assert b"property uchar red\nproperty uchar green\nproperty uchar blue\n" in (tmp_path / "ca.ply").read_bytes()
    with pytest.raises(GBError, match="colors"):
        write_grid_cloud_ply(tmp_path / "bad.ply", xyz, nrm, conf, reason, grey[:5])


def test_mesh_colours_follow_the_vertices_to_every_file_and_through_every_step(tmp_path, sphere_scene):
    import open3d as o3d

    from gbscan.mesh import remove_unreferenced

    p, _ = sphere_scene
    H, W = p.shape[:2]
    rgb = np.random.default_rng(3).integers(0, 256, (H, W, 3), dtype=np.uint8)
    m = grid_mesh(p, colors=rgb)
    np.testing.assert_array_equal(m.colors, rgb[m.pixel[:, 0], m.pixel[:, 1]])
    np.testing.assert_array_equal(grid_mesh(p, colors=rgb[..., 0]).colors, np.repeat(m.colors[:, :1], 3, 1))
    assert grid_mesh(p).colors is None
    write_mesh(tmp_path / "m.ply", m)
    back = o3d.io.read_triangle_mesh(str(tmp_path / "m.ply"))
    np.testing.assert_array_equal(np.rint(np.asarray(back.vertex_colors) * 255).astype(np.uint8), m.colors)
    np.testing.assert_allclose(np.asarray(back.vertices), m.vertices, atol=1e-3)   # float32 on disk
    np.testing.assert_array_equal(Mesh.from_open3d(m.to_open3d()).colors, m.colors)
    np.testing.assert_array_equal(taubin_smooth(m, 2).colors, m.colors)
    sub = Mesh(m.vertices, m.triangles[:10], colors=m.colors)
    used = np.unique(sub.triangles)
    np.testing.assert_array_equal(remove_unreferenced(sub).colors, m.colors[used])
    # Poisson: open3d interpolates the points' colours onto its vertices (uniform in, uniform out)
    ok = np.isfinite(p[..., 2])
    pm = poisson_mesh(p[ok], -p[ok] / np.linalg.norm(p[ok], axis=1, keepdims=True), depth=6,
                      colors=np.full((ok.sum(), 3), 77, np.uint8))
    assert pm.colors is not None and len(pm.colors) == pm.n_vertices and np.abs(pm.colors.astype(int) - 77).max() <= 1
    with pytest.raises(GBError, match="mesh colors"):
        Mesh(m.vertices, m.triangles, colors=m.colors[:-1])
    with pytest.raises(GBError, match="uint8"):
        Mesh(m.vertices, m.triangles, colors=m.colors.astype(np.float32))
    with pytest.raises(GBError, match="grid_mesh: colors"):
        grid_mesh(p, colors=rgb[:-1])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_grid_mesh_of_an_object_alone_meshes_its_window_the_same(sphere_scene, dtype):
    """A sphere without its wall (points in a quarter of the grid): the mesh is built on the
    points' bounding box and its vertices moved back -- the numpy formulation's mesh over the
    whole grid, array for array, with and without valid / normals, the box at the grid's edge too."""
    import gbscan.mesh as mesh_module

    p, oid = sphere_scene
    alone = np.where((oid == 0)[..., None], p, np.nan).astype(dtype)
    edge = np.full_like(alone, np.nan)                   # the same sphere moved to the grid's corner
    ys, xs = np.nonzero(oid == 0)
    edge[:ys.max() + 1 - ys.min(), -(xs.max() + 1 - xs.min()):] = alone[ys.min():ys.max() + 1, xs.min():xs.max() + 1]
    for xyz in (alone, edge):
        valid = np.isfinite(xyz[..., 2])
        valid[np.random.default_rng(1).random(valid.shape) < 0.02] = False
        nrm = np.where(np.isfinite(xyz), -xyz / np.linalg.norm(xyz, axis=-1, keepdims=True), np.nan).astype(np.float32)
        win = mesh_module.grid_window(np.isfinite(xyz[..., 2]), 0, mesh_module.MESH_WINDOW_MAX_FRACTION)
        assert win is not None and (win[1] - win[0]) * (win[3] - win[2]) < 0.3 * valid.size
        for kw in (dict(), dict(valid=valid), dict(valid=valid, normals=nrm)):
            m = grid_mesh(xyz, **kw)
            ref = _grid_mesh_numpy(xyz, **kw)
            assert m.n_triangles > 1000
            for got, want in zip((m.vertices, m.triangles, m.pixel, m.normals()), ref):
                assert got.dtype == want.dtype and np.array_equal(got, want), kw
