"""Does the calibration still hold?  Scan the flat checkerboard and measure it.

SESSION is a capture session folder (every pose_NNN/ in it is checked, the board from its
session.yaml) or one pose folder.  Each pose needs white.png (the board's corners) and
stripes.png (the scanning pattern on it), as 'gbcal patterns' and the guided capture name them.
Take fresh poses at the rig (scripts/guided_calibration.py with a few poses, or any session
captured since), then:

  gbcal verify NEW_SESSION --calib calib.yaml [--preview DIR] [--json verify.json] [--strict]

Per pose: the scanned board's flatness (residual RMS to a robust plane, and its bow: the
peak-to-valley of the curvature left over, mm) and its scale (the detected corners cast on the
scanned plane, their spacing against the square size).  A moved camera or projector, a changed
focus or zoom shows as scale (a 1 % focal length error: about -1 %) or bow (a wrong lens
distortion: 1-6 mm); a sound calibration measures within 0.05 % and 0.06 mm.  --strict exits 3
when a finding says to calibrate again.
"""
from __future__ import annotations

HELP = "does the calibration still hold: scan the flat board, measure its flatness and squares"

#: exit status of --strict when a finding says to calibrate again
WARN_EXIT = 3


def add_arguments(p):
    p.add_argument("session", metavar="SESSION", help="capture session folder, or one pose folder")
    p.add_argument("--calib", required=True, metavar="YAML", help="the calibration file to check")
    p.add_argument("--board", metavar="COLSxROWS", help="inner corners (default: from session.yaml)")
    p.add_argument("--square-mm", type=float, help="square size in mm (default: from session.yaml)")
    p.add_argument("--preview", metavar="DIR", help="write a residual picture per pose into DIR")
    p.add_argument("--json", metavar="FILE", help="also write the figures and findings as JSON")
    p.add_argument("--strict", action="store_true", help=f"exit with status {WARN_EXIT} on a finding")


def _poses(args):
    """(board, [pose folders]) from SESSION and the board options."""
    from pathlib import Path

    from gbscan.errors import GBError
    from gbscan.io import load_session

    from ..board import Board, parse_board

    root = Path(args.session)
    if not root.is_dir():
        raise GBError(f"{root} is not a folder (expected a capture session or one pose folder)")
    session = root if (root / "session.yaml").is_file() else \
        root.parent if (root.parent / "session.yaml").is_file() else None
    board = None
    if session is not None:
        s = load_session(session)
        board = Board(s.board_cols, s.board_rows, s.square_mm)
        poses = list(s.poses) if session == root else [root]
    else:
        poses = [root]
    if args.board or args.square_mm is not None:
        if args.board is None and board is None:
            raise GBError("--square-mm needs --board COLSxROWS (no session.yaml gives the board)")
        cols_rows = args.board or f"{board.cols}x{board.rows}"
        board = parse_board(cols_rows, args.square_mm if args.square_mm is not None else board.square_mm)
    if board is None:
        raise GBError(f"{root} has no session.yaml: give --board COLSxROWS and --square-mm")
    for pose in poses:
        for name in ("white.png", "stripes.png"):
            if not (pose / name).is_file():
                raise GBError(f"pose {pose} has no {name} (each pose needs white.png and stripes.png, as "
                              "'gbcal patterns' names the frames)")
    return board, poses


def run(args) -> int:
    import json

    from gbscan.calibfile import load_calibration
    from gbscan.commands.scan import _check_output, _check_preview_dir
    from gbscan.errors import GBError
    from gbscan.io import read_image_rgb, write_text_atomic
    from gbscan.scan import Scanner

    from ..board import detect_with_reason
    from ..verify import check_pose, findings

    json_path = _check_output(args.json, (".json",), "--json")
    preview = _check_preview_dir(args.preview)
    board, poses = _poses(args)
    cal = load_calibration(args.calib)
    scanner = Scanner(cal)
    size = cal.camera.size
    checks, whites, skipped = [], [], []
    print(f"checking {args.calib} on {len(poses)} pose(s) of a {board}")
    for pose in poses:
        white = read_image_rgb(pose / "white.png", size=size, what="white frame")
        det, why = detect_with_reason(white, board)
        if det is None:
            skipped.append((pose.name, f"board not found in white.png ({why})"))
            print(f"  {pose.name}: skipped, board not found in white.png ({why})")
            continue
        scan = scanner.scan(read_image_rgb(pose / "stripes.png", size=size, what="pattern frame"))
        try:
            pc = check_pose(pose.name, scan.xyz, scan.valid, cal.camera.rays(det.corners), det.corners,
                            board.cols, board.rows, board.square_mm)
        except GBError as e:
            skipped.append((pose.name, str(e)))
            print(f"  {pose.name}: skipped, {e}")
            continue
        f, sc = pc.flatness, pc.scale
        print(f"  {pose.name}: plane {f.distance_mm:.0f} mm from the camera, tilt {f.tilt_deg:.0f} deg, {f.n_points} points: RMS "
              f"{f.rms_mm:.3f} mm, bow {f.bow_mm:.3f} mm; squares {sc.measured_square_mm:.3f} mm "
              f"({100 * sc.scale_error:+.2f} %)")
        checks.append(pc)
        whites.append(white)
    if not checks:
        raise GBError(f"no pose could be checked ({'; '.join(f'{n}: {w}' for n, w in skipped)})")
    found = findings(checks)
    for x in found:
        print(f"warn: {x.text}")
    if not found:
        print(f"the calibration holds: {len(checks)} pose(s) within the figures of a sound calibration")
    if preview is not None:
        from ..report import write_verify_previews

        preview.mkdir(exist_ok=True)
        for p in write_verify_previews(preview, checks, whites):
            print(f"wrote {p}")
    if json_path is not None:
        d = {"calib": str(args.calib), "board": {"cols": board.cols, "rows": board.rows, "square_mm": board.square_mm},
             "poses": [pc.to_dict() for pc in checks], "skipped": [{"pose": n, "why": w} for n, w in skipped],
             "findings": [{"key": x.key, "level": x.level, "text": x.text} for x in found]}
        write_text_atomic(json_path, json.dumps(d, indent=1) + "\n")
        print(f"wrote {json_path}")
    return WARN_EXIT if args.strict and found else 0
