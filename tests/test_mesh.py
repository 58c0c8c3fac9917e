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
