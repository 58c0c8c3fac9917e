"""Diagnostics of a rig calibration: pictures and a text summary (``gbcal report``).

Pictures (matplotlib, Agg backend, PNG), from the calibration file and the residual samples
``<stem>.residuals.npz`` that ``gbcal calibrate`` writes beside it (named in the file's
``residuals.samples``):

* ``residual_field.png`` -- corner residual vectors and stripe residuals (horizontal) over the image;
* ``residual_histogram.png`` -- corner (u, v) and stripe residual distributions, px;
* ``per_capture.png`` -- corner and stripe RMS per capture (dropped captures marked);
* ``coverage.png`` -- where corners and stripe-boundary samples fell in the image;
* ``plane_residuals.png`` -- per light plane: RMS distance (mm) of its samples to the plane;
* ``summary.txt`` -- the figures, the worst captures and why, uncovered image regions.

Without the .npz (moved, deleted) only ``per_capture.png`` and ``summary.txt`` are made, and the
summary says so.  :func:`write_capture_previews` draws per-capture pictures for
``gbcal calibrate --preview``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from gbscan.io import make_dir, write_figure_png, write_png, write_text_atomic


def load_samples(calib_path, calib) -> tuple[dict | None, str]:
    """The residual samples named by ``calib.residuals['samples']``: (arrays or None, note)."""
    name = (calib.residuals or {}).get("samples")
    if not name:
        return None, "the calibration names no residual samples file (made by an older or other tool)"
    p = Path(calib_path).parent / str(name)
    if not p.is_file():
        return None, f"residual samples file {p} is missing: per-point pictures skipped"
    try:
        with np.load(p, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}, ""
    except (OSError, ValueError) as e:
        return None, f"residual samples file {p} could not be read ({e}): per-point pictures skipped"


def _savefig(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt

    write_figure_png(path, fig, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def _rms(a) -> float:
    a = np.asarray(a, float)
    return float(np.sqrt(np.mean(a ** 2))) if a.size else float("nan")


def write_report(calib_path, out_dir, *, grid: tuple[int, int] = (8, 6)) -> list[Path]:
    """Write the pictures and ``summary.txt`` into ``out_dir`` (created); returns the paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from gbscan.calibfile import load_calibration

    calib = load_calibration(calib_path)
    out = Path(out_dir)
    make_dir(out, "report folder")
    S, note = load_samples(calib_path, calib)
    res = calib.residuals or {}
    caps = res.get("captures") or []
    W, H = calib.camera.width, calib.camera.height
    written: list[Path] = []

    # per-capture error bars (from the YAML alone)
    if caps:
        fig, ax = plt.subplots(figsize=(max(6, 0.45 * len(caps)), 3.6))
        x = np.arange(len(caps))
        cr = [c.get("corner_rms_px", np.nan) if c.get("used") else np.nan for c in caps]
        sr = [c.get("stripe_rms_px", np.nan) if c.get("used") else np.nan for c in caps]
        ax.bar(x - 0.2, cr, 0.4, label="corner RMS (px)")
        ax.bar(x + 0.2, sr, 0.4, label="stripe RMS (camera px)")
        top = np.nanmax(cr + sr) if np.any(np.isfinite(cr + sr)) else 1.0
        for i, c in enumerate(caps):
            if not c.get("used"):
                ax.text(i, 0.05 * top, "dropped", rotation=90, ha="center", va="bottom", color="red", fontsize=8)
        ax.set_xticks(x, [c.get("capture", str(i)) for i, c in enumerate(caps)], rotation=60, fontsize=8)
        ax.set_ylabel("RMS residual, px")
        ax.set_title("Residuals per capture")
        ax.legend(fontsize=8)
        written.append(_savefig(fig, out / "per_capture.png"))

    cells_empty = None
    if S is not None:
        cuv, cres, cpose = S["corner_uv"], S["corner_residual_px"], S["corner_pose"]
        suv, sres, sk = S["stripe_uv"], S["stripe_residual_px"], S["stripe_index"]
        # residual field
        fig, ax = plt.subplots(figsize=(8, 6.3))
        scale = 0.05 * W / max(np.percentile(np.linalg.norm(cres, axis=1), 95), 1e-6)
        sub = np.random.default_rng(0).choice(len(suv), min(len(suv), 3000), replace=False) if len(suv) else []
        if len(sub):
            ax.quiver(suv[sub, 0], suv[sub, 1], sres[sub] * scale, np.zeros(len(sub)), color="tab:blue",
                      angles="xy", scale_units="xy", scale=1, width=0.0015, alpha=0.5, label="stripe (along row)")
        ax.quiver(cuv[:, 0], cuv[:, 1], cres[:, 0] * scale, cres[:, 1] * scale, color="tab:red", angles="xy",
                  scale_units="xy", scale=1, width=0.002, label="corner")
        ax.set_xlim(0, W), ax.set_ylim(H, 0), ax.set_aspect("equal")
        inl = S["stripe_inlier"] if "stripe_inlier" in S else np.ones(len(sres), bool)
        ax.set_title(f"Residuals x{scale:.0f} (corner RMS {_rms(np.linalg.norm(cres, axis=1)):.3f} px, "
                     f"stripe RMS {_rms(sres[inl]):.3f} px over inliers)")
        ax.legend(loc="lower right", fontsize=8)
        written.append(_savefig(fig, out / "residual_field.png"))
        # histograms
        fig, axs = plt.subplots(1, 2, figsize=(10, 3.6))
        lim = max(np.percentile(np.abs(cres), 99.5), 1e-3)
        axs[0].hist(cres[:, 0], bins=60, range=(-lim, lim), alpha=0.6, label="u")
        axs[0].hist(cres[:, 1], bins=60, range=(-lim, lim), alpha=0.6, label="v")
        axs[0].set_title(f"corner residuals (px), n={len(cres)}")
        axs[0].legend(fontsize=8)
        if len(sres):
            lim = max(np.percentile(np.abs(sres), 99.5), 1e-3)
            axs[1].hist(sres, bins=80, range=(-lim, lim), color="tab:blue")
        axs[1].set_title(f"stripe residuals (camera px), n={len(sres)}")
        written.append(_savefig(fig, out / "residual_histogram.png"))
        # coverage
        gx, gy = grid
        cnt, _, _ = np.histogram2d(cuv[:, 0], cuv[:, 1], bins=[gx, gy], range=[[0, W], [0, H]])
        cells_empty = int((cnt == 0).sum())
        fig, axs = plt.subplots(1, 2, figsize=(11, 4.2))
        axs[0].imshow(cnt.T, extent=(0, W, H, 0), cmap="Greens", alpha=0.6, aspect="equal")
        for j in np.unique(cpose):
            m = cpose == j
            axs[0].plot(cuv[m, 0], cuv[m, 1], ".", ms=2)
        axs[0].set_xlim(0, W), axs[0].set_ylim(H, 0)
        axs[0].set_title(f"corner coverage ({cells_empty} of {gx * gy} cells empty)")
        if len(suv):
            h2, _, _ = np.histogram2d(suv[:, 0], suv[:, 1], bins=[W // 16, H // 16], range=[[0, W], [0, H]])
            im = axs[1].imshow(h2.T, extent=(0, W, H, 0), cmap="viridis", aspect="equal")
            fig.colorbar(im, ax=axs[1], fraction=0.035, label="samples per 16x16 px")
        axs[1].set_title("stripe-boundary sample coverage")
        written.append(_savefig(fig, out / "coverage.png"))
        # plane residuals
        dist = S["stripe_plane_distance_mm"]
        ks = np.unique(sk) if len(sk) else np.zeros(0, int)
        per_plane = np.array([_rms(dist[sk == k]) for k in ks])
        fig, ax = plt.subplots(figsize=(9, 3.6))
        ax.plot(ks, per_plane, ".-", label="refined model (bundle)")
        if "plane_fit_index" in S:
            ax.plot(S["plane_fit_index"], S["plane_fit_rms_mm"], ".", alpha=0.6, label="initial free plane fit")
        ax.set_xlabel("boundary index k")
        ax.set_ylabel("RMS point-to-plane, mm")
        ax.set_title("Light-plane residuals")
        ax.legend(fontsize=8)
        written.append(_savefig(fig, out / "plane_residuals.png"))

    written.append(write_text_atomic(out / "summary.txt", "\n".join(summary_text(calib, S, note, cells_empty)) + "\n"))
    return written


def summary_text(calib, S: dict | None, note: str, cells_empty: int | None) -> list[str]:
    """Lines of ``summary.txt``: figures, worst captures and why, coverage, notes."""
    r = calib.residuals or {}
    K = calib.camera.K
    st = (calib.uncertainty or {}).get("camera_std", {})
    lines = [f"calibration: {calib.created.get('by', '?')} ({calib.created.get('date', '?')})",
             f"camera {calib.camera.width}x{calib.camera.height}: fx {K[0, 0]:.2f} ± {st.get('fx', float('nan')):.2f}, "
             f"fy {K[1, 1]:.2f} ± {st.get('fy', float('nan')):.2f}, cx {K[0, 2]:.2f} ± {st.get('cx', float('nan')):.2f}, "
             f"cy {K[1, 2]:.2f} ± {st.get('cy', float('nan')):.2f} px",
             f"light planes: {calib.n_planes}"]
    if calib.projector:
        lines.append(f"projector: fx {calib.projector['matrix'][0][0]:.1f} px, baseline "
                     f"{calib.projector.get('baseline_mm', float('nan')):.2f} mm")
    from .calibrate import depth_uncertainty_line

    depth = depth_uncertainty_line(calib.uncertainty)
    if depth:
        lines.append(depth)
    for key, unit in (("corner_rms_px", "px"), ("stripe_rms_px", "camera px"), ("stripe_rms_proj_px", "projector px"),
                      ("plane_rms_mm", "mm")):
        if key in r:
            lines.append(f"{key}: {r[key]} {unit}")
    caps = r.get("captures") or []
    used = [c for c in caps if c.get("used")]
    dropped = [c for c in caps if not c.get("used")]
    lines.append(f"captures: {len(used)} used, {len(dropped)} dropped")
    for c in dropped:
        lines.append(f"  dropped {c.get('capture')}: {c.get('reason', 'no reason recorded')}")
    if used:
        med_c = np.median([c.get("corner_rms_px", np.nan) for c in used])
        med_s = np.nanmedian([c.get("stripe_rms_px", np.nan) for c in used])
        score = [max(c.get("corner_rms_px", 0) / max(med_c, 1e-9), c.get("stripe_rms_px", 0) / max(med_s, 1e-9))
                 for c in used]
        lines.append("worst captures (RMS relative to the median capture):")
        for i in np.argsort(score)[::-1][:3]:
            c = used[i]
            why = []
            if c.get("corner_rms_px", 0) > 2 * med_c:
                why.append("corners fit badly (board moved between frames, bent board, or blur?)")
            if c.get("stripe_rms_px", 0) > 2 * med_s:
                why.append("stripe boundaries fit badly (projector defocus, reflections, board moved?)")
            if c.get("stripe_samples", 1) < 200:
                why.append(f"few stripe samples ({c.get('stripe_samples')}): board poorly lit by the projector")
            lines.append(f"  {c.get('capture')}: corner RMS {c.get('corner_rms_px')} px, stripe RMS "
                         f"{c.get('stripe_rms_px')} px, {score[i]:.1f}x the median; "
                         + ("; ".join(why) if why else "within the normal spread"))
    if cells_empty is not None and cells_empty > 0:
        lines.append(f"coverage: {cells_empty} image cells have no corners (see coverage.png); capture boards "
                     "there to pin the lens distortion down")
    if note:
        lines.append(f"note: {note}")
    return lines


def write_capture_previews(session_dir, run, out_dir) -> list[Path]:
    """Per capture a PNG: the white frame with its detected corners (green) and the boundary samples
    used, coloured by stripe residual (blue small .. red >= 0.5 px); dropped captures say why."""
    import cv2

    from gbscan.io import load_session, read_image_rgb

    session = load_session(session_dir)
    out = Path(out_dir)
    make_dir(out, "preview folder")
    S = run.samples
    used_names = list(S["used_captures"])
    written = []
    for i, cap in enumerate(run.captures):
        img = read_image_rgb(session.frame_path(i, "white"), what=f"capture {cap.name} white").copy()
        if cap.used:
            j = used_names.index(cap.name)
            m = S["stripe_pose"] == j
            err = np.clip(np.abs(S["stripe_residual_px"][m]) / 0.5, 0, 1)
            for (u, v), e in zip(S["stripe_uv"][m], err):
                img[int(round(v)), int(np.clip(round(u), 0, img.shape[1] - 1))] = (int(255 * e), 0, int(255 * (1 - e)))
            for u, v in S["corner_uv"][S["corner_pose"] == j]:
                cv2.circle(img, (int(round(u)), int(round(v))), 3, (0, 255, 0), 1, cv2.LINE_AA)
            text = f"{cap.name}: corner {cap.corner_rms_px:.3f} px, stripe {cap.stripe_rms_px:.3f} px"
        else:
            text = f"{cap.name}: DROPPED - {cap.reason}"[:90]
        cv2.putText(img, text, (5, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 0), 1, cv2.LINE_AA)
        written.append(write_png(out / f"{cap.name}.png", img))
    return written


def write_verify_previews(out_dir, poses, backgrounds) -> list[Path]:
    """One picture per checked pose (``gbcal verify --preview``): the scanned board's residuals to
    its fitted plane (mm, blue below / red above, symmetric scale) over the grey of the pose's
    white frame, titled with the pose's flatness and scale figures.

    poses : :class:`gbcal.verify.PoseCheck` list; backgrounds : matching (H, W, 3) uint8 RGB frames
    (or None)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    paths = []
    for pc, bg in zip(poses, backgrounds):
        res = pc.residual_mm
        if res is None:
            continue
        fig, ax = plt.subplots(figsize=(7.2, 5.4))
        if bg is not None:
            ax.imshow(np.asarray(bg).mean(axis=2), cmap="gray", vmin=0, vmax=255)
        finite = res[np.isfinite(res)]
        lim = max(0.2, 3.0 * float(np.sqrt(np.mean(finite ** 2)))) if finite.size else 0.2
        im = ax.imshow(np.ma.masked_invalid(res), cmap="coolwarm", vmin=-lim, vmax=lim, interpolation="nearest")
        fig.colorbar(im, ax=ax, shrink=0.8, label="distance to the board's plane (mm)")
        f = pc.flatness
        title = f"{pc.name}: RMS {f.rms_mm:.3f} mm, bow {f.bow_mm:.3f} mm, {f.distance_mm:.0f} mm away"
        if pc.scale is not None:
            title += f"\nsquares {pc.scale.measured_square_mm:.3f} mm ({100 * pc.scale.scale_error:+.2f} %)"
        ax.set_title(title, fontsize=9)
        ax.set_axis_off()
        paths.append(_savefig(fig, out / f"verify_{pc.name}.png"))
    return paths
