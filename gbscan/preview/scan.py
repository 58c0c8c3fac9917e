"""Pictures of a scan (PNG, headless): depth map, coverage by reason, shaded mesh renders.

The shaded renders use a small numpy z-buffer rasteriser (:func:`render_mesh`): it needs no
display or GPU.  (open3d's OffscreenRenderer does not work headless here: open3d-cpu 0.20 falls
back to headless mode and then fails with "Failed to load vulkan library".)
matplotlib (Agg) is imported only by the pictures with a colour bar or legend.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..clean import REASONS
from ..errors import GBError
from ..io import write_figure_png, write_png

#: RGB colour of each cleaning reason in the coverage picture.
REASON_RGB = {
    "ok": (70, 170, 90),
    "not_decoded": (25, 25, 25),
    "no_plane": (120, 60, 160),
    "low_confidence": (230, 160, 30),
    "depth_range": (90, 90, 200),
    "outlier": (230, 40, 40),
    "discontinuity": (250, 240, 60),
    "grazing": (60, 200, 220),
    "small_cluster": (240, 110, 200),
    "gap_edge": (250, 150, 60),
    "high_sigma": (200, 120, 120),
}


# -- rasteriser -------------------------------------------------------------------------------
def render_mesh(vertices: np.ndarray, triangles: np.ndarray, K: np.ndarray, size: tuple[int, int], *,
                normals: np.ndarray | None = None, light_dir=(-0.35, -0.45, -1.0), ambient: float = 0.12,
                background: int = 0, albedo: np.ndarray | None = None) -> np.ndarray:
    """Gouraud-shaded grey image (H, W) uint8 of a mesh seen by a pinhole camera at the origin.

    vertices : (V, 3) mm in the viewing camera's frame (OpenCV: z forward).
    triangles : (T, 3) vertex indices.  K : (3, 3) intrinsics.  size : (width, height).
    normals : (V, 3) vertex normals (default: from the triangles); shading uses |n . l| so the
        render does not depend on the winding.
    light_dir : direction *towards* the light (camera frame); default up-left of the camera.
    albedo : optional (V,) vertex brightness in [0, 1] multiplying the shading (a scan's grey
        texture: ``Mesh.colors[:, 0] / 255``).
    """
    from ..mesh import vertex_normals

    W, H = size
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    img = np.full(H * W, background, np.uint8)
    if len(t) == 0:
        return img.reshape(H, W)
    n = vertex_normals(v, t) if normals is None else np.asarray(normals, dtype=np.float64)
    light = np.asarray(light_dir, dtype=np.float64)
    light = light / np.linalg.norm(light)
    shade = ambient + (1 - ambient) * np.abs(np.nan_to_num(n) @ light)
    if albedo is not None:
        albedo = np.asarray(albedo, dtype=np.float64).reshape(-1)
        if albedo.shape != (len(v),):
            raise GBError(f"render_mesh: albedo has {albedo.shape}, expected ({len(v)},)")
        shade = shade * np.clip(albedo, 0.0, 1.0)
    z = v[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * v[:, 0] / z + K[0, 1] * v[:, 1] / z + K[0, 2]
        w = K[1, 1] * v[:, 1] / z + K[1, 2]
    front = np.all(z[t] > 1e-6, axis=1)
    t = t[front]
    tu, tv = u[t], w[t]  # (T, 3)
    u0 = np.clip(np.ceil(tu.min(1)), 0, W).astype(np.int64)
    u1 = np.clip(np.floor(tu.max(1)), -1, W - 1).astype(np.int64)
    v0 = np.clip(np.ceil(tv.min(1)), 0, H).astype(np.int64)
    v1 = np.clip(np.floor(tv.max(1)), -1, H - 1).astype(np.int64)
    span = np.maximum(u1 - u0, v1 - v0) + 1
    ok = (u1 >= u0) & (v1 >= v0) & (span <= 512)
    pix_all, depth_all, shade_all = [], [], []
    B = 1
    while True:  # triangles grouped by bounding-box size: candidates (T_b, B, B) per group
        sel = np.flatnonzero(ok & (span <= B) & (span > B // 2))
        if sel.size:
            # chunk so that a group never allocates more than ~4M candidate pixels
            step = max(1, 4_000_000 // (B * B))
            for c0 in range(0, sel.size, step):
                s = sel[c0:c0 + step]
                pix, dep, sh = _raster_group(tu[s], tv[s], u0[s], v0[s], u1[s], v1[s], z[t[s]], shade[t[s]], B, W)
                pix_all.append(pix), depth_all.append(dep), shade_all.append(sh)
        if B >= 512:
            break
        B *= 2
    if not pix_all:
        return img.reshape(H, W)
    pix = np.concatenate(pix_all)
    dep = np.concatenate(depth_all)
    sh = np.concatenate(shade_all)
    order = np.lexsort((dep, pix))  # by pixel, nearest first
    pix, sh = pix[order], sh[order]
    first = np.ones(pix.size, bool)
    first[1:] = pix[1:] != pix[:-1]
    img[pix[first]] = np.clip(sh[first] * 255, 0, 255).astype(np.uint8)
    return img.reshape(H, W)


def _raster_group(tu, tv, u0, v0, u1, v1, tz, tshade, B, W):
    """Candidate pixels of triangles whose bounding box fits in B x B: inside test + interpolation."""
    oy, ox = np.mgrid[0:B, 0:B]
    pu = u0[:, None] + ox.ravel()[None]  # (T, B*B)
    pv = v0[:, None] + oy.ravel()[None]
    inbox = (pu <= u1[:, None]) & (pv <= v1[:, None])
    ax, ay = tu[:, 0:1], tv[:, 0:1]
    bx, by = tu[:, 1:2], tv[:, 1:2]
    cx, cy = tu[:, 2:3], tv[:, 2:3]
    area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    with np.errstate(divide="ignore", invalid="ignore"):
        w0 = ((bx - pu) * (cy - pv) - (by - pv) * (cx - pu)) / area
        w1 = ((cx - pu) * (ay - pv) - (cy - pv) * (ax - pu)) / area
    w2 = 1.0 - w0 - w1
    eps = -1e-9
    inside = inbox & (w0 >= eps) & (w1 >= eps) & (w2 >= eps) & (np.abs(area) > 1e-12)
    # perspective-correct: 1/z is affine in screen space
    iz = w0 / tz[:, 0:1] + w1 / tz[:, 1:2] + w2 / tz[:, 2:3]
    sh = (w0 * tshade[:, 0:1] / tz[:, 0:1] + w1 * tshade[:, 1:2] / tz[:, 1:2] + w2 * tshade[:, 2:3] / tz[:, 2:3]) / iz
    return (pv * W + pu)[inside], (1.0 / iz)[inside], sh[inside]


def orbit(vertices: np.ndarray, normals: np.ndarray | None, yaw_deg: float, pitch_deg: float = 0.0,
          centre: np.ndarray | None = None):
    """Rotate a model about ``centre`` (default: median vertex) by yaw (about camera y) then pitch
    (about camera x): the view of a camera orbiting the object.  Returns (vertices, normals)."""
    v = np.asarray(vertices, dtype=np.float64)
    c = np.median(v, axis=0) if centre is None else np.asarray(centre, dtype=np.float64)
    a, b = np.radians(yaw_deg), np.radians(pitch_deg)
    Ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    Rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    R = Rx @ Ry
    return (v - c) @ R.T + c, (None if normals is None else np.asarray(normals) @ R.T)


# -- pictures ----------------------------------------------------------------------------------
def coverage_rgb(reason: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 picture of the per-pixel reason codes (``gbscan.clean.REASONS``)."""
    lut = np.zeros((256, 3), np.uint8)
    for code, name in REASONS.items():
        lut[code] = REASON_RGB.get(name, (128, 128, 128))
    return lut[np.asarray(reason, dtype=np.uint8)]


def save_depth_picture(path, xyz: np.ndarray, title: str = "depth (mm)") -> Path:
    """Colour-coded depth map z (mm) with a colour bar; no-point pixels black."""
    z = np.asarray(xyz)[..., 2].astype(np.float64)
    finite = np.isfinite(z)
    lo, hi = (np.percentile(z[finite], [1, 99]) if finite.any() else (0.0, 1.0))
    return _save_map_picture(path, z, "turbo", lo, max(hi, lo + 1e-3), f"{title}: {int(finite.sum())} points", "z (mm)")


def save_sigma_picture(path, sigma_mm: np.ndarray, title: str = "predicted error along the ray (mm, 1 sigma)") -> Path:
    """Map of each point's predicted error (:attr:`gbscan.scan.Scan.sigma_mm`, mm) with a colour
    bar from 0 to its 99th percentile; no-point pixels black."""
    sig = np.asarray(sigma_mm, np.float64)
    finite = np.isfinite(sig)
    med, hi = (np.percentile(sig[finite], [50, 99]) if finite.any() else (0.0, 1.0))
    return _save_map_picture(path, sig, "magma", 0.0, max(hi, 1e-3), f"{title}: median {med:.3f} mm", "sigma (mm)")


def _save_map_picture(path, values: np.ndarray, cmap_name: str, vmin: float, vmax: float, title: str,
                      label: str) -> Path:
    """(H, W) values as a colour map with a colour bar, NaN black, written atomically as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    H, W = values.shape
    fig, ax = plt.subplots(figsize=(W / 100 + 1.6, H / 100 + 0.6), dpi=100)
    try:
        cmap = plt.get_cmap(cmap_name).with_extremes(bad="black")
        im = ax.imshow(np.ma.masked_invalid(values), cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
        ax.set_title(title)
        ax.set_axis_off()
        fig.colorbar(im, ax=ax, fraction=0.04, pad=0.02, label=label)
        _save_figure(fig, path)
    finally:
        plt.close(fig)
    return Path(path)


def _save_figure(fig, path) -> None:
    """Lay out and write a matplotlib figure as PNG, atomically."""
    fig.tight_layout()
    write_figure_png(path, fig)

def save_coverage_picture(path, reason: np.ndarray) -> Path:
    """Pixels coloured by why they have (green) or have no point, with a legend of counts."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    reason = np.asarray(reason)
    H, W = reason.shape
    codes, n = np.unique(reason, return_counts=True)
    fig, ax = plt.subplots(figsize=(W / 100 + 2.4, H / 100 + 0.6), dpi=100)
    try:
        ax.imshow(coverage_rgb(reason), interpolation="nearest")
        ax.set_axis_off()
        ax.set_title(f"coverage: {100 * float((reason == 0).mean()):.1f}% of pixels have a point")
        handles = [Patch(color=np.array(REASON_RGB.get(REASONS[int(c)], (128, 128, 128))) / 255,
                         label=f"{REASONS[int(c)]} {int(k)}") for c, k in zip(codes, n)]
        ax.legend(handles=handles, loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=8, frameon=False)
        _save_figure(fig, path)
    finally:
        plt.close(fig)
    return Path(path)


def write_scan_previews(scan, outdir, *, camera, mesh=None, yaw_deg: float = 35.0) -> list[Path]:
    """Write ``depth.png``, ``coverage.png``, ``shaded_camera.png`` and ``shaded_angle.png``;
    when the scan has a texture ``texture.png`` (the grey texture of the kept points) and
    ``textured_angle.png`` (the angled render with it); when it has a predicted error per point
    ``sigma.png`` (:attr:`gbscan.scan.Scan.sigma_mm`).

    scan : :class:`gbscan.scan.Scan`; camera : the calibration's :class:`gbscan.camera.Camera`
    (its K and size frame the renders); mesh : a :class:`gbscan.mesh.Mesh` (default: the scan's
    grid mesh).  Returns the paths written.
    """
    outdir = Path(outdir)
    paths = [save_depth_picture(outdir / "depth.png", scan.xyz),
             save_coverage_picture(outdir / "coverage.png", scan.reason)]
    if scan.n_points == 0:
        return paths
    sigma = scan.sigma_mm
    if sigma is not None:
        paths.append(save_sigma_picture(outdir / "sigma.png", sigma))
    if mesh is None:
        mesh = scan.mesh_arrays("grid")
    size = camera.size
    img = render_mesh(mesh.vertices, mesh.triangles, camera.K, size, normals=mesh.normals())
    paths.append(write_png(outdir / "shaded_camera.png", img))
    v, n = orbit(mesh.vertices, mesh.normals(), yaw_deg, -15.0)
    img = render_mesh(v, mesh.triangles, camera.K, size, normals=n)
    paths.append(write_png(outdir / "shaded_angle.png", img))
    grey = scan.grey()
    if grey is not None:
        paths.append(write_png(outdir / "texture.png", grey))
        if mesh.colors is not None:
            img = render_mesh(v, mesh.triangles, camera.K, size, normals=n, ambient=0.35,
                              albedo=mesh.colors[:, 0] / 255.0)
            paths.append(write_png(outdir / "textured_angle.png", img))
    return paths
