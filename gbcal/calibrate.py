"""A capture session -> a refined :class:`gbscan.calibfile.Calibration` (``gbcal calibrate``).

Stages (each prints progress lines through ``log``):

1. per capture: the board in ``white`` (:func:`gbcal.board.detect_with_reason`; a capture whose
   board is missing, cut, blurred or too dark is dropped with its reason), then the Gray-code
   frames -> sub-pixel stripe-boundary samples (:mod:`gbcal.planes`);
2. camera intrinsics and board poses from the corners (:func:`gbcal.intrinsics.calibrate_camera`,
   which also rejects outlier captures and degenerate, all-parallel capture sets);
3. boundary samples back-projected onto their boards -> one robust plane per boundary index ->
   the initial pinhole projector (:func:`gbcal.planes.projector_from_planes`);
4. bundle refinement of everything together (:mod:`gbcal.bundle`);
5. the calibration: planes of every boundary index seen, from the refined projector model.

:func:`save_run` writes ``calib.yaml`` and, beside it, ``calib.residuals.npz`` with every
residual sample (for ``gbcal report``); the yaml's ``residuals.samples`` names it.
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gbscan.calibfile import Calibration, save_calibration
from gbscan.errors import GBError
from gbscan.io import Session, load_session, read_image_rgb, save_npz
from gbscan.pattern import PatternSpec

from . import planes as pl
from .patterns import frame_names, n_gray_bits

#: Fewest usable captures for a rig calibration.
MIN_CAPTURES = 4


@dataclass
class CaptureInfo:
    """What happened to one capture (pose folder)."""

    name: str
    used: bool = False
    reason: str = ""
    n_corners: int = 0
    n_samples: int = 0
    corner_rms_px: float = float("nan")
    stripe_rms_px: float = float("nan")
    stripe_rms_proj_px: float = float("nan")


@dataclass
class CalibrationRun:
    """Everything one calibration produced: the calibration, the per-capture story, the samples."""

    calibration: Calibration
    captures: list[CaptureInfo]
    samples: dict            # arrays for the residuals .npz (see save_run)
    bundle: object           # gbcal.bundle.BundleResult
    timings: dict = field(default_factory=dict)


def pattern_of_session(session: Session) -> PatternSpec:
    """The pattern a session was captured with: ``session.yaml``'s ``pattern`` if present, else
    the default stripe width at the session's projector size; checked against the frame list."""
    d = session.extra.get("pattern")
    if isinstance(d, dict):
        try:
            spec = PatternSpec.from_dict(d)
        except (KeyError, TypeError, ValueError, GBError) as e:
            raise GBError(f"session {session.root}: 'pattern' must be {{width, height, stripe_px, markers[, "
                          f"marker_code]}} ({e})") from None
    else:
        spec = PatternSpec(*session.projector_size)
    if (spec.width, spec.height) != tuple(session.projector_size):
        raise GBError(f"session {session.root}: pattern size {spec.width}x{spec.height} differs from the "
                      f"projector size {session.projector_size[0]}x{session.projector_size[1]}")
    need = [n for n in frame_names(spec) if n != "stripes"]
    missing = [n for n in need if n not in session.frames]
    if missing:
        raise GBError(f"session {session.root}: frames {', '.join(missing[:4])} are not listed in session.yaml; "
                      f"a rig calibration needs white, black and the {n_gray_bits(spec)} Gray-code bits "
                      f"(+ inverses) of 'gbcal patterns' for stripe width {spec.stripe_px}")
    return spec


def _read(session: Session, pose: int, name: str) -> np.ndarray:
    return read_image_rgb(session.frame_path(pose, name), size=session.camera_size,
                          what=f"capture {session.poses[pose].name} frame '{name}'")


def calibrate_session(session_dir, *, model: str = "k1k2p1p2", loss: str = "soft_l1", f_scale_px: float = 0.5,
                      stripe_weight: float = 1.0, max_samples_per_capture: int = 20000,
                      min_captures: int = MIN_CAPTURES, log=None, seed: int = 0,
                      corner_refiner: str = "symmetric", camera_prior: Calibration | None = None,
                      camera_prior_name: str = "camera file") -> CalibrationRun:
    """Calibrate the rig from a capture session folder (module docstring).

    model : camera distortion model (:data:`gbcal.bundle.DIST_MODELS`).
    loss, f_scale_px : robust loss of the bundle and its scale (camera px).
    stripe_weight : weight of a boundary sample relative to a corner coordinate.
    max_samples_per_capture : boundary samples kept per capture (random, seeded), for speed.
    corner_refiner : :data:`gbcal.board.CORNER_REFINERS` (``symmetric``, the default, or
        ``cornersubpix``), recorded in the calibration's ``residuals``.
    camera_prior : a camera calibrated on its own (``gbcal camera``: ``camera``, ``residuals.model``
        and ``uncertainty.camera_std``), named ``camera_prior_name`` in messages.  The bundle then
        holds the camera to it within its standard deviations (:func:`gbcal.bundle.refine`), with
        that file's distortion model (``model`` is ignored): a camera calibrated with a big board
        close up pins fx, and so the depth scale, far better than the rig's small board does.
    Raises GBError for unreadable/missing/mis-sized frames, too few usable captures, or an
    unobservable capture set.
    """
    from .board import Board, check_refiner, detect_with_reason
    from .bundle import BundleData, refine, rodrigues, rotation_vector
    from .intrinsics import calibrate_camera

    log = log or (lambda s: print(s, file=sys.stderr, flush=True))
    check_refiner(corner_refiner)
    if camera_prior is not None:
        model = prior_model(camera_prior, camera_prior_name)
    t_start = time.perf_counter()
    timings = {}
    session = load_session(session_dir)
    spec = pattern_of_session(session)
    if camera_prior is not None and tuple(camera_prior.camera.size) != tuple(session.camera_size):
        c = camera_prior.camera
        raise GBError(f"{camera_prior_name} is for a {c.width}x{c.height} camera but session {session.root} was "
                      f"captured at {session.camera_size[0]}x{session.camera_size[1]}; calibrate the camera at "
                      "the resolution you scan with")
    board = Board(session.board_cols, session.board_rows, session.square_mm)
    names = [p.name for p in session.poses]
    captures = [CaptureInfo(n) for n in names]
    log(f"session {session.root}: {len(names)} captures, board {board}, camera "
        f"{session.camera_size[0]}x{session.camera_size[1]}, pattern {spec.n_stripes} stripes of {spec.stripe_px} px")

    # 1. per capture: board + boundary samples
    frames_needed = ["black"] + [f"gray_{b:02d}{s}" for b in range(n_gray_bits(spec)) for s in ("", "_inv")]
    detections, samples = [], []
    for i, name in enumerate(names):
        white = _read(session, i, "white")
        det, why = detect_with_reason(white, board, refiner=corner_refiner)
        if det is None:
            captures[i].reason = f"no usable board: {why}"
            detections.append(None)
            samples.append(None)
            log(f"  [{i + 1}/{len(names)}] {name}: dropped ({captures[i].reason})")
            continue
        frames = {"white": white}
        for fn in frames_needed:
            frames[fn] = _read(session, i, fn)
        dec = pl.gray_decode(frames, spec)
        bs = pl.gray_boundaries(dec, spec)
        detections.append(det)
        samples.append(bs)
        captures[i].n_corners = board.n_corners
        log(f"  [{i + 1}/{len(names)}] {name}: board found (edge width {det.sharpness_px:.1f} px), "
            f"{len(bs)} boundary samples on {np.unique(bs.index).size} boundaries")
    timings["captures_s"] = time.perf_counter() - t_start

    # 2. camera intrinsics and board poses
    t0 = time.perf_counter()
    found = sum(d is not None for d in detections)
    if found < min_captures:
        raise GBError(_too_few(found, min_captures, captures))
    cam_res = calibrate_camera(detections, board, session.camera_size, model=model, names=names)
    for i, v in enumerate(cam_res.views):
        if not v.used and detections[i] is not None:
            captures[i].reason = v.reason or "rejected by the camera calibration"
    used = [i for i, v in enumerate(cam_res.views) if v.used]
    if len(used) < min_captures:
        raise GBError(_too_few(len(used), min_captures, captures))
    cam0 = cam_res.camera
    timings["camera_s"] = time.perf_counter() - t0
    log(f"  camera (initial, {len(used)} captures): fx {cam0.K[0, 0]:.2f} fy {cam0.K[1, 1]:.2f} "
        f"cx {cam0.K[0, 2]:.2f} cy {cam0.K[1, 2]:.2f} px, corner RMS {cam_res.rms_px:.3f} px")

    # 3. samples on the boards -> planes -> projector
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    obj = board.object_points()
    c_pose, c_uv, c_xyz, s_pose, s_uv, s_k, s_p = [], [], [], [], [], [], []
    for j, i in enumerate(used):
        v = cam_res.views[i]
        bs = samples[i]
        p_cam, p_board = pl.backproject_to_board(cam0, bs.uv, v.R, v.t)
        keep = np.isfinite(p_board[:, 0]) & pl.on_board(p_board, board.cols, board.rows, board.square_mm)
        idx = np.flatnonzero(keep)
        if idx.size > max_samples_per_capture:
            idx = np.sort(rng.choice(idx, max_samples_per_capture, replace=False))
        c_pose.append(np.full(len(obj), j)), c_uv.append(detections[i].corners), c_xyz.append(obj)
        s_pose.append(np.full(idx.size, j)), s_uv.append(bs.uv[idx]), s_k.append(bs.index[idx])
        s_p.append(p_cam[idx])
        captures[i].n_samples = int(idx.size)
    s_pose = np.concatenate(s_pose).astype(np.int64)
    s_uv, s_k, s_p = np.concatenate(s_uv), np.concatenate(s_k).astype(np.int64), np.concatenate(s_p)
    fit = pl.fit_planes(s_p, s_k)
    if fit.index.size < 3:
        raise GBError(f"only {fit.index.size} light planes could be fitted from the board captures; the "
                      "stripes must be seen on boards at two or more different depths/tilts (are the "
                      "projector frames captured? is the board lit by the projector?)")
    keep = fit.sample_inlier
    rig0 = pl.projector_from_planes(spec.boundary_column(fit.index), fit.normal, fit.d,
                                    projector_size=(spec.width, spec.height), scene_point=s_p.mean(axis=0),
                                    camera=cam0)
    timings["planes_s"] = time.perf_counter() - t0
    log(f"  planes: {fit.index.size} boundaries fitted from {int(keep.sum())} samples "
        f"(median plane RMS {np.median(fit.rms_mm):.3f} mm, {int((~keep).sum())} outliers dropped); "
        f"initial projector fx {rig0.projector.K[0, 0]:.1f} cx {rig0.projector.K[0, 2]:.1f} px, "
        f"baseline {np.linalg.norm(rig0.t_cam_proj):.1f} mm")

    # 4. bundle
    t0 = time.perf_counter()
    data = BundleData(np.concatenate(c_pose).astype(np.int64), np.concatenate(c_uv), np.concatenate(c_xyz),
                      s_pose[keep], s_uv[keep], spec.boundary_column(s_k[keep]), len(used))
    rv0 = np.array([rotation_vector(cam_res.views[i].R) for i in used])
    tv0 = np.array([cam_res.views[i].t for i in used])
    prior = None
    if camera_prior is not None:
        prior = prior_arrays(camera_prior, model, camera_prior_name)
        # the session's own camera (corners alone) against the file: the sigma of their difference
        from .bundle import camera_unknowns

        cam_names, own = camera_unknowns(cam0, model)
        own_sd = np.array([float(cam_res.std.get(n, np.nan)) for n in cam_names])
        session_z = {n: round(float(v), 2) for n, v in zip(cam_names, (own - prior[0]) / np.hypot(own_sd, prior[1]))
                     if np.isfinite(v)}
        scale = max(float(cam_res.rms_px) / np.sqrt(2.0), 0.01)  # corner noise per coordinate
        log(f"  camera prior from {camera_prior_name}: fx {prior[0][0]:.2f} ± {prior[1][0]:.3f}, fy {prior[0][1]:.2f} "
            f"± {prior[1][1]:.3f} px (model {model}; corner noise {scale:.3f} px per coordinate)")
    res = refine(data, cam0, rv0, tv0, rig0, dist_model=model, loss=loss, f_scale_px=f_scale_px,
                 stripe_weight=stripe_weight, log=log, camera_prior=prior,
                 prior_scale_px=scale if prior is not None else 0.05)
    timings["bundle_s"] = time.perf_counter() - t0

    # 5. calibration
    rig = res.rig
    k_seen = np.unique(s_k[keep])
    cols = spec.boundary_column(k_seen)
    n, d = rig.column_planes(cols)
    # residual samples: distance of each sample's refined board point to its refined plane
    Rb = rodrigues(res.rvecs)
    sp_all = data.stripe_pose
    p_cam = np.empty((len(sp_all), 3))
    for j in range(len(used)):
        m = sp_all == j
        p_cam[m], _ = pl.backproject_to_board(rig.camera, data.stripe_uv[m], Rb[j], res.tvecs[j])
    n_s, d_s = rig.column_planes(data.stripe_column)
    plane_dist = np.einsum("ij,ij->i", n_s, p_cam) - d_s
    per = []
    for j, i in enumerate(used):
        c = captures[i]
        c.used = True
        rc = res.corner_residual_px[data.corner_pose == j]
        rs = res.stripe_residual_px[(sp_all == j) & res.stripe_inlier]
        rsp = res.stripe_residual_proj_px[(sp_all == j) & res.stripe_inlier]
        c.corner_rms_px = float(np.sqrt(np.mean(np.sum(rc ** 2, axis=1))))
        c.stripe_rms_px = float(np.sqrt(np.mean(rs ** 2))) if rs.size else float("nan")
        c.stripe_rms_proj_px = float(np.sqrt(np.mean(rsp ** 2))) if rsp.size else float("nan")
    for c in captures:
        e = {"capture": c.name, "used": c.used}
        if c.used:
            e.update(corners=c.n_corners, stripe_samples=c.n_samples, corner_rms_px=_r(c.corner_rms_px),
                     stripe_rms_px=_r(c.stripe_rms_px), stripe_rms_proj_px=_r(c.stripe_rms_proj_px))
        else:
            e["reason"] = c.reason
        per.append(e)
    rc_all = res.corner_residual_px
    inl = res.stripe_inlier
    residuals = {  # RMS over the inliers of the bundle; corner RMS is per corner (2D distance)
        "corner_rms_px": _r(np.sqrt(np.mean(np.sum(rc_all ** 2, axis=1)))),
        "stripe_rms_px": _r(np.sqrt(np.mean(res.stripe_residual_px[inl] ** 2))),
        "stripe_rms_proj_px": _r(np.sqrt(np.mean(res.stripe_residual_proj_px[inl] ** 2))),
        "plane_rms_mm": _r(np.sqrt(np.mean(plane_dist[inl] ** 2))),
        "corners": int(len(rc_all)), "stripe_samples": int(inl.sum()),
        "stripe_outliers": int((~inl).sum()) + int((~keep).sum()),
        "captures_used": len(used), "captures_total": len(names),
        "camera_model": model, "corner_refiner": corner_refiner, "loss": loss, "f_scale_px": f_scale_px,
        "stripe_weight": stripe_weight,
        **({"camera_prior": {"file": camera_prior_name, "session_z": session_z,
                             "z": {k: round(float(v), 3) for k, v in res.info["camera_prior_z"].items()}}}
           if prior is not None else {}),
        "stripe_residual_unit": "camera px along the row (projector px / |d column / d u|)",
        "captures": per,
    }
    std = res.std
    n_std_deg, d_std_mm = res.plane_std(cols)
    depth_at_mm, depth_std = depth_uncertainty(res, obj)
    uncertainty = {
        "camera_std": {k: _g(std[k]) for k in ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3") if k in std},
        "projector_std": {k.replace("proj_", ""): _g(v) for k, v in std.items() if k.startswith("proj_")},
        "baseline_std_mm": _g(std.get("baseline_mm", float("nan"))),
        "plane_normal_std_deg": {"median": _g(np.median(n_std_deg)), "max": _g(np.max(n_std_deg))},
        "plane_d_std_mm": {"median": _g(np.median(d_std_mm)), "max": _g(np.max(d_std_mm))},
        "depth_std_mm": {"distance_mm": round(depth_at_mm, 1),
                         "centre": _g(depth_std[0]) if np.isfinite(depth_std[0]) else None,  # None: not lit
                         "max": _g(np.nanmax(depth_std)) if np.isfinite(depth_std).any() else None},
        "residual_sigma": {k: _g(v) for k, v in res.sigma.items()},
        "note": "1-sigma from (J^T W J)^-1, W = inverse variance of each residual kind (inliers); depth_std_mm: "
                "a scanned point's depth at the boards' median distance, at the image centre and the worst of a "
                "5x5 grid over the lit image (mostly a scale error: distance x std(fx) / fx)",
    }
    projector = {
        "model": "pinhole",
        "width": int(spec.width), "height": int(spec.height),
        "matrix": rig.projector.K.tolist(),
        "R_cam_proj": rig.R_cam_proj.tolist(),
        "t_cam_proj": rig.t_cam_proj.tolist(),
        "baseline_mm": float(np.linalg.norm(rig.t_cam_proj)),
        "unobserved": "vertical stripes observe columns only: matrix fy, cy and the centre's position "
                      "along the projector y axis are conventions, not measurements",
    }
    calib = Calibration(rig.camera, k_seen, cols, n, d, pattern=spec, projector=projector,
                        created={"tool": "gbcal calibrate", "session": str(session.root)},
                        residuals=residuals, uncertainty=uncertainty)
    capture_of_pose = np.array([names[i] for i in used])
    arrays = {
        "image_size": np.array(session.camera_size, np.int64),
        "capture_names": np.array(names),
        "used_captures": capture_of_pose,
        "corner_pose": data.corner_pose, "corner_uv": data.corner_uv,
        "corner_residual_px": res.corner_residual_px,
        "stripe_pose": sp_all, "stripe_uv": data.stripe_uv, "stripe_index": s_k[keep],
        "stripe_residual_px": res.stripe_residual_px,
        "stripe_residual_proj_px": res.stripe_residual_proj_px,
        "stripe_inlier": res.stripe_inlier,
        "stripe_plane_distance_mm": plane_dist,
        "plane_index": k_seen, "plane_normal_std_deg": n_std_deg, "plane_d_std_mm": d_std_mm,
        "plane_fit_index": fit.index, "plane_fit_rms_mm": fit.rms_mm, "plane_fit_n": fit.n_inliers,
        "board_rvec": res.rvecs, "board_tvec": res.tvecs,
    }
    timings["total_s"] = time.perf_counter() - t_start
    return CalibrationRun(calib, captures, arrays, res, timings)


def save_run(path, run: CalibrationRun) -> tuple[Path, Path]:
    """Write ``path`` (the calibration YAML) and ``<stem>.residuals.npz`` beside it, atomically;
    if the YAML cannot be written the .npz is removed again.  Returns both paths."""
    path = Path(path)
    npz = path.with_name(path.stem + ".residuals.npz")
    existed = npz.exists()
    save_npz(npz, **run.samples)
    run.calibration.residuals["samples"] = npz.name
    try:
        save_calibration(path, run.calibration)
    except BaseException:
        if not existed:
            npz.unlink(missing_ok=True)
        raise
    return path, npz


def load_camera_prior(path, model: str | None = None) -> tuple[Calibration, str]:
    """A camera file for ``camera_prior`` (``gbcal camera``'s, or a whole rig's) and its distortion
    model, read strictly; GBError when ``model`` is given and differs from the file's."""
    from gbscan.calibfile import load_calibration

    cam = load_calibration(path, require_planes=False)
    m = prior_model(cam, f"camera file {path}")
    if model is not None and model != m:
        raise GBError(f"--model {model} differs from the model camera file {path} was calibrated with ({m}); "
                      "leave --model out to use the file's")
    return cam, m


def prior_model(camera_file: Calibration, name: str) -> str:
    """The distortion model a camera file was calibrated with, checked: ``residuals.model``
    (``gbcal camera``) or ``residuals.camera_model`` (a whole rig's ``gbcal calibrate``, whose
    camera can be reused too)."""
    from .bundle import DIST_MODELS

    r = camera_file.residuals or {}
    m = r.get("model", r.get("camera_model"))
    if m not in DIST_MODELS:
        raise GBError(f"{name}: residuals.model must name the camera's distortion model ({', '.join(DIST_MODELS)}), "
                      f"got {m!r}; write the file with 'gbcal camera'")
    return m


def prior_arrays(camera_file: Calibration, model: str, name: str) -> tuple[np.ndarray, np.ndarray]:
    """``(mu, sigma)`` of the bundle's camera unknowns (fx, fy, cx, cy, then ``model``'s free
    distortion terms) from a camera file's ``camera`` and ``uncertainty.camera_std``."""
    from .bundle import camera_unknowns

    names, mu = camera_unknowns(camera_file.camera, model)
    std = (camera_file.uncertainty or {}).get("camera_std") or {}
    try:
        sd = np.array([float(std[n]) for n in names])
    except (KeyError, TypeError, ValueError):
        raise GBError(f"{name}: uncertainty.camera_std must give the standard deviation of each of "
                      f"{', '.join(names)}; write the file with 'gbcal camera'") from None
    if not np.all(np.isfinite(sd) & (sd > 0)):
        raise GBError(f"{name}: uncertainty.camera_std must be positive and finite for {', '.join(names)}")
    return mu, sd


def depth_uncertainty(res, board_xyz: np.ndarray) -> tuple[float, np.ndarray]:
    """(distance mm, (26,) mm): the 1-sigma depth uncertainty a scan inherits from the
    calibration (:meth:`gbcal.bundle.BundleResult.depth_std`) at the median distance of the
    board centres, for the image centre (first) and a 5x5 grid over 10-90 % of the image (NaN
    where the projector does not light that point)."""
    from .bundle import rodrigues

    centre_b = np.asarray(board_xyz, np.float64).mean(axis=0)
    R = rodrigues(np.asarray(res.rvecs, np.float64))
    z = np.einsum("pij,j->pi", R, centre_b)[:, 2] + np.asarray(res.tvecs)[:, 2]
    dist = float(np.median(z))
    cam = res.rig.camera
    f = np.linspace(0.1, 0.9, 5)
    gu, gv = np.meshgrid(f * (cam.width - 1), f * (cam.height - 1))
    q = np.concatenate([[[(cam.width - 1) / 2, (cam.height - 1) / 2]], np.stack([gu.ravel(), gv.ravel()], 1)])
    return dist, res.depth_std(q, dist)


def depth_uncertainty_line(uncertainty: dict | None) -> str:
    """The sentence ``gbcal calibrate`` and ``gbcal report`` print for a calibration's
    ``uncertainty.depth_std_mm`` ("" when it has none)."""
    ds = (uncertainty or {}).get("depth_std_mm") or {}
    if ds.get("centre") is None:
        return ""
    mx = ds.get("max")
    return (f"depth uncertainty of a scan at {ds['distance_mm']:.0f} mm (the boards' median distance): "
            f"± {ds['centre']:.3f} mm at the image centre" + (f", ± {mx:.3f} mm at most" if mx else "")
            + " (1 sigma; mostly the scale, from fx: more poses, a bigger board or steeper tilts narrow it)")


def summary_lines(run: CalibrationRun) -> list[str]:
    """The human summary ``gbcal calibrate`` prints."""
    cal = run.calibration
    K = cal.camera.K
    st = cal.uncertainty.get("camera_std", {})
    r = cal.residuals
    used = [c for c in run.captures if c.used]
    out = [f"captures: {len(used)} used of {len(run.captures)}"]
    for c in run.captures:
        if not c.used:
            out.append(f"  dropped {c.name}: {c.reason}")
    out.append(f"corner RMS {r['corner_rms_px']:.3f} px over {r['corners']} corners ({r.get('corner_refiner', '?')} "
               f"refinement); stripe RMS "
               f"{r['stripe_rms_px']:.3f} px ({r['stripe_rms_proj_px']:.3f} projector px, "
               f"{r['plane_rms_mm']:.3f} mm from the planes) over {r['stripe_samples']} boundary samples")
    out.append(f"camera fx {K[0, 0]:.2f} ± {st.get('fx', float('nan')):.2f}  fy {K[1, 1]:.2f} ± "
               f"{st.get('fy', float('nan')):.2f}  cx {K[0, 2]:.2f} ± {st.get('cx', float('nan')):.2f}  "
               f"cy {K[1, 2]:.2f} ± {st.get('cy', float('nan')):.2f} px; distortion "
               + " ".join(f"{v:+.4f}" for v in cal.camera.dist))
    pj = cal.projector or {}
    ps = cal.uncertainty.get("projector_std", {})
    out.append(f"projector fx {pj['matrix'][0][0]:.1f} ± {ps.get('fx', float('nan')):.1f}  cx "
               f"{pj['matrix'][0][2]:.1f} ± {ps.get('cx', float('nan')):.1f} px; baseline "
               f"{pj['baseline_mm']:.2f} ± {cal.uncertainty.get('baseline_std_mm', float('nan')):.2f} mm; "
               f"{cal.n_planes} light planes (boundaries {cal.plane_index[0]}..{cal.plane_index[-1]}, normals ± "
               f"{cal.uncertainty.get('plane_normal_std_deg', {}).get('max', float('nan')):.4f} deg at most)")
    pr = r.get("camera_prior")
    if pr:
        far = {k: v for k, v in (pr.get("session_z") or {}).items() if abs(v) > 3.0}
        out.append(f"camera held to {pr['file']} (within its standard deviations)" + (
            "; the session disagrees with it on " + ", ".join(f"{k} ({v:+.1f} sigma)" for k, v in far.items())
            + ": was the lens refocused or zoomed since the camera was calibrated?" if far else ""))
    line = depth_uncertainty_line(cal.uncertainty)
    if line:
        out.append(line)
    worst = sorted(used, key=lambda c: -c.stripe_rms_px if np.isfinite(c.stripe_rms_px) else 0)[:1]
    if worst:
        out.append(f"worst capture: {worst[0].name} (corner RMS {worst[0].corner_rms_px:.3f} px, stripe RMS "
                   f"{worst[0].stripe_rms_px:.3f} px)")
    return out


def _too_few(n: int, need: int, captures: list[CaptureInfo]) -> str:
    why = "; ".join(f"{c.name}: {c.reason}" for c in captures if c.reason)[:600]
    return (f"too few usable captures: {n} (need at least {need}, 10-20 recommended with the board at varied "
            f"tilts and distances){'; dropped ' + why if why else ''}")


def _r(x) -> float:
    return float(f"{float(x):.6g}")


def _g(x) -> float:
    return float(f"{float(x):.6g}")
