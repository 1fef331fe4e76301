"""``svs-depth calibrate``: a stereo rig's calibration file from chessboard pairs (OpenCV)."""

from __future__ import annotations

import argparse
import contextlib
import re
import sys

from .common import add_figure_option, check_outputs_apart, dumps_strict, positive_float

#: Fewer pairs than this used in the fit are warned of (the help asks for 10-20).
FEW_PAIRS = 10
MAX_SQUARE_M = 1.0  # geometry.chessboard.MAX_SQUARE_M (not imported: a parser must not import torch or cv2)
MIN_SQUARE_M = 0.001  # geometry.chessboard.MIN_SQUARE_M

HELP = "calibrate a stereo rig from chessboard pairs; writes the file for --calibration"

DESCRIPTION = """\
Calibrate a stereo rig once from pairs of images of a chessboard (both cameras see the whole board; 10-20
pairs, the board tilted and moved over the field): OpenCV finds the inner corners, calibrates each camera,
then the pair (R, T), and computes the rectification. The file (JSON) holds both cameras' K and distortion, R,
T (metres), R1, R2, P1, P2, Q, the image size, the errors, the board, the date and the version; give it to
estimate, eval, capture and guide as --calibration FILE: their pairs are then rectified with it and take their
focal length, baseline and doffs from it, instead of the paper's uncalibrated rectification and the SVS model.

Printed: the reprojection error (RMS, pixels) of each camera and of the stereo fit, the rectified pair's
row error on the chessboards: |y_left - y_right| of the matching corners after rectification (mean, max), and
the right camera's pose against the left's, what to remount a loose board by: its roll and its turns about its
y and x axes (degrees, as estimate --json's right_camera_roll_deg and right_camera_turn_deg read them from a
pair's rows) and where it sits (millimetres right, lower, ahead; --json: right_camera_offset_m).
A pair whose two views do not fit the others (the same view twice, two moments of a moving board) is left
out and named when the stereo fit is over 1 px (per 640 px of width) and it alone spoils it; a fit still over it,
or whose poses pin the focal length down only to over ±3 % (OpenCV's standard deviation of fx), is written with a
warning, and one that does not rectify its own chessboards or leaves the focal length loose by over ±10 % (a board
never tilted, or tilted a few degrees) is refused: tilt the board 15-30 degrees toward and away from the cameras
between pairs.
The baseline is in the unit of --square-m: measure the printed squares.
"""

EPILOG = """\
examples:
  svs-depth calibrate 'calib/left*.jpg' --board 9x6 --square-m 0.025 --out rig.json --figure rig.png
  svs-depth calibrate --pairs chessboards.txt --board 9x6 --square-m 0.025 --out rig.json --json
  svs-depth estimate left.jpg right.jpg --calibration rig.json
LEFT: left image files or quoted patterns (*, ?); each right image is the file of the same name with 'left'
replaced by 'right' (also Left/Right, LEFT/RIGHT), or where the name has none, its folder's ('calib/left/*.jpg'
beside calib/right/). --pairs: a list file, one 'LEFT RIGHT' per line.
exit status: 0 written; 2 bad arguments, unreadable images, or too few pairs with the board in both views (or
in too few poses); 1 the file or the figure cannot be written (a full disk: the option and the file named).
"""


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("calibrate", help=HELP, description=DESCRIPTION, epilog=EPILOG,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("left", nargs="*", metavar="LEFT", help="left chessboard images (files or patterns)")
    parser.add_argument("--pairs", metavar="LIST.txt", help="a list file with one 'LEFT RIGHT' per line instead")
    parser.add_argument("--board", default="9x6", metavar="COLSxROWS",
                        help="inner corners of the chessboard, columns x rows (default: 9x6, OpenCV's sample)")
    parser.add_argument("--square-m", type=square_metres, required=True,
                        help="side of one square of the board, metres, 0.001 to 1 (25 mm is 0.025; sets the scale "
                             "of the baseline)")
    parser.add_argument("--out", required=True, metavar="RIG.json", help="the calibration file to write")
    add_figure_option(parser, "figure: the first pair rectified, side by side, with its corners and epipolar lines")
    parser.add_argument("--json", action="store_true",
                        help="print the calibration file's content as one JSON line, with the pairs left out "
                             "('skipped': no board in both views; 'misfits': views that do not fit the others) "
                             "and the 'warnings', which the file does not hold")
    parser.set_defaults(func=run)


def parse_board(text: str) -> tuple[int, int]:
    """``"9x6"`` → (9, 6) inner corners (columns, rows), each 3 to 100 (OpenCV's corner finder needs 3)."""
    from ..core.errors import InputError

    match = re.fullmatch(r"\s*(\d+)\s*[xX×]\s*(\d+)\s*", text or "")
    if not match or min(int(match[1]), int(match[2])) < 3 or max(int(match[1]), int(match[2])) > 100:
        raise InputError(f"--board: expected inner corners as COLSxROWS, each 3 to 100, e.g. 9x6, got {text!r}")
    return int(match[1]), int(match[2])


def right_name(left: str) -> str | None:
    """The right image's path of a left image: the last 'left' (Left, LEFT) of the file name as 'right', or where
    the name has none, of the nearest folder's name that has one (left/01.jpg beside right/01.jpg: a rig's two
    folders, which were refused for a file name without 'left', an audit)."""
    from pathlib import Path

    parts = list(Path(left).parts)
    for index in range(len(parts) - 1, -1, -1):
        for old, new in (("left", "right"), ("Left", "Right"), ("LEFT", "RIGHT")):
            at = parts[index].rfind(old)
            if at >= 0:
                parts[index] = parts[index][:at] + new + parts[index][at + len(old):]
                return str(Path(*parts))
    return None


def pair_paths(args: argparse.Namespace) -> list[tuple[str, str, str]]:
    """The (left, right) files named by LEFT patterns or --pairs, each with what named them in an error: ``left``,
    or ``--pairs, line N of LIST``."""
    import glob
    import os

    from ..data import read_pair_list
    from ..data.pair_list import LINE_FORMS
    from ..core.errors import InputError
    from ..core.files import check_path_given

    if args.pairs is not None:  # --pairs "$LIST" with LIST unset: an empty name, not "neither"
        check_path_given(args.pairs, "--pairs", "a list file name")
    if bool(args.left) == bool(args.pairs):
        raise InputError("left, --pairs: give left images (files or patterns) or --pairs LIST.txt, "
                         + ("not both" if args.left else "got neither"))
    if args.pairs:
        sources = read_pair_list(args.pairs, "--pairs")
        bad = next((s for s in sources if s.problem or s.scene or s.right is None or s.focal_px is not None), None)
        if bad is not None:  # a focal length and baseline on a line are what calibrating finds, not an input
            # The list reader's message offers a calibration or a scene folder, which calibrate refuses (an audit).
            raise InputError(bad.problem.replace(LINE_FORMS, "'LEFT RIGHT' (two chessboard images)")
                             if bad.problem else f"--pairs: expected 'LEFT RIGHT' lines of chessboard images, got "
                                                 f"{bad.listed_at or bad.left}")
        return _once_each([(s.left, s.right, f"--pairs, {s.listed_at}") for s in sources])
    lefts: list[str] = []
    for pattern in args.left:
        found = sorted(glob.glob(pattern)) if glob.has_magic(pattern) else [pattern]
        if not found and os.path.isfile(pattern):  # 'left[1].jpg': a file's own name, read as a pattern (an audit)
            found = [pattern]
        if os.path.isdir(pattern):
            example = os.path.join(pattern, "*.jpg" if right_name(os.path.join(pattern, "x")) else "left*.jpg")
            raise InputError(f"left: {pattern!r} is a folder: expected left images, e.g. {example!r} (quoted), or "
                             "--pairs LIST.txt")
        if not found:
            raise InputError(f"left: no file matches {pattern!r}")
        lefts += found
    pairs = []
    for left in lefts:
        right = right_name(left)
        if right is None:
            raise InputError(f"left: {left!r} has no 'left' in its name or its folders' to find its right image "
                             "(use --pairs)")
        pairs.append((left, right, "left"))
    return _once_each(pairs)


def _once_each(pairs: list[tuple[str, str, str]]) -> list[tuple[str, str, str]]:
    """Each pair once (patterns that overlap, a line listed twice): a view counted twice is no new view of the board,
    and three copies of one view leave the stereo fit degenerate."""
    import os

    seen: set[tuple[str, str]] = set()
    unique = []
    for pair in pairs:
        key = (os.path.realpath(pair[0]), os.path.realpath(pair[1]))
        if key not in seen:
            seen.add(key)
            unique.append(pair)
    return unique


def _text(calibration, views, out: str, figure: str | None = None) -> list[str]:
    c = calibration
    board = c.board["inner_corners"]
    given = len(views.names) + len(views.skipped) + len(views.misfits)
    lines = [f"calibrated from {len(views.names)} of {given} pairs "
             f"({board[0]}x{board[1]} board, squares {c.board['square_m']:g} m), {c.image_wh[0]}x{c.image_wh[1]}",
             f"reprojection RMS: left {c.rms_left_px:.3f} px, right {c.rms_right_px:.3f} px, "
             f"stereo {c.rms_stereo_px:.3f} px; the poses pin each focal length down to ±{c.focal_sd_pct:.1f} %",
             f"rectified row error on the chessboards: mean {c.row_error_mean_px:.3f} px, max "
             f"{c.row_error_max_px:.3f} px ({board[0] * board[1]} corners x {len(views.names)} pairs)",
             f"rectified: focal {c.focal_px:.2f} px, baseline {c.baseline_m:.4f} m, doffs {c.doffs_px:.2f} px",
             _pose_line(right_camera_pose(c.R, c.T))]
    if views.skipped:
        lines.append(f"left out (board not found in both views): {', '.join(views.skipped)}")
    lines += [f"left out: {misfit}" for misfit in views.misfits]
    lines.append(f"wrote {out}" + (f"; figure written to {figure}" if figure else ""))  # as the others say it
    return lines


def right_camera_pose(R, T) -> dict:
    """The right camera against the left (``x_right = R·x_left + T``, OpenCV's ``stereoCalibrate``):
    ``right_camera_roll_deg`` and ``right_camera_turn_deg`` [about y, about x] with ``R = Rz(roll)·Ry(y)·Rx(x)``, the
    turns ``experiments/real_rig.py`` misaligns a right camera by (``K·R·K⁻¹`` takes an ideal right view's pixels
    to the camera's), so a positive roll turns its view clockwise on the screen, as estimate reads it from a pair's
    rows; and ``right_camera_offset_m``, its centre ``−Rᵀ·T`` in the left camera's axes (x right, y down, z ahead),
    metres."""
    import math

    import numpy as np

    R, T = np.asarray(R, dtype=np.float64), np.ravel(np.asarray(T, dtype=np.float64))
    about_y = -math.degrees(math.asin(max(-1.0, min(1.0, float(R[2, 0])))))
    about_x = math.degrees(math.atan2(R[2, 1], R[2, 2]))
    return {"right_camera_roll_deg": round(math.degrees(math.atan2(R[1, 0], R[0, 0])), 3),
            "right_camera_turn_deg": [round(about_y, 3), round(about_x, 3)],
            "right_camera_offset_m": [round(float(v), 5) for v in -R.T @ T]}


def _pose_line(pose: dict) -> str:
    """The text of :func:`right_camera_pose`: "right camera: its view rolled 0.2° anticlockwise, turned +0.2°
    about y, +0.4° about x; 83.2 mm right, 1.0 mm lower, 0.3 mm ahead of the left"."""
    roll, (about_y, about_x) = pose["right_camera_roll_deg"], pose["right_camera_turn_deg"]
    x, y, z = (v * 1000 for v in pose["right_camera_offset_m"])
    return (f"right camera: its view rolled {abs(roll):.1f}° {'clockwise' if roll >= 0 else 'anticlockwise'}, "
            f"turned {about_y:+.1f}° about y, {about_x:+.1f}° about x; {abs(x):.1f} mm "
            f"{'right' if x >= 0 else 'left'}, {abs(y):.1f} mm {'lower' if y >= 0 else 'higher'}, {abs(z):.1f} mm "
            f"{'ahead of' if z >= 0 else 'behind'} the left")


def _figure(calibration, views, images):
    """The first used pair rectified with its corners and epipolar lines (8-, 16-bit or float views, drawn as the
    corner finder saw them)."""
    from pathlib import Path

    import torch

    from ..geometry.calibration import rectify_with_calibration
    from ..geometry.chessboard import board_image_u8, rectified_corners
    from ..plotting.rectified import rectified_pair_figure
    from ..core.types import StereoBatch

    left, right = (torch.from_numpy(board_image_u8(image)).float().div(255).view(1, 1, *image.shape[:2])
                   for image in images)
    # The batch's focal and baseline are placeholders: rectify_with_calibration sets the calibration's.
    batch = rectify_with_calibration(StereoBatch.from_images(left, right, 1.0, 1.0), calibration)
    corners_left, corners_right = rectified_corners(calibration, views)
    return rectified_pair_figure(batch.left[0, 0].numpy(), batch.right[0, 0].numpy(), corners_left[0],
                                   corners_right[0], f"{Path(views.names[0]).name} rectified by the calibration: "
                                   f"RMS {calibration.rms_stereo_px:.2f} px, row error over all pairs mean "
                                   f"{calibration.row_error_mean_px:.2f} px", point_label="corner")


def _warnings(calibration, views) -> list[str]:
    """What the calibration written may get wrong: a poor fit, rows of its boards left apart, a focal length the
    poses leave loose (:func:`~svs_torch.geometry.chessboard.fit_doubts`), few pairs."""
    from ..geometry.chessboard import SAME_POSE_PX, count_poses, fit_doubts, good_stereo_rms_px

    warnings = []
    if doubts := fit_doubts(calibration):
        advice = ("no one pair explains it; check that each pair's two images were taken at the same moment, and "
                  "--board") if calibration.rms_stereo_px > good_stereo_rms_px(calibration.image_wh) else (
            "tilt the board toward and away from the cameras between pairs, not only move it")
        warnings.append(f"{'; '.join(doubts)}: distances from this file may be far off; {advice}")
    # Poses, not pairs: capture's frames of a board held still between grabs are one pose again and again (13 pairs
    # captured from the emulator's 13 boards were 7 poses, and no word: an audit)
    poses = count_poses(views.left)
    if poses < FEW_PAIRS:  # 3 of the shared pairs: focal 576 px, against 516 from all 13 (an audit)
        again = "" if poses == len(views.names) else (
            f" but {poses} poses of the board (the others show it where another pair does, within {SAME_POSE_PX:g} "
            "px: held still between grabs)")
        warnings.append(f"calibrated from {len(views.names)} pairs{again}: {FEW_PAIRS}-20 poses of the board across "
                        "the field give a steadier focal length and baseline")
    return warnings


def run(args: argparse.Namespace) -> int:
    from ..core.workers import imports_without_collection

    with imports_without_collection():  # see there: the imports' objects are frozen
        import cv2

        from ..geometry.calibration import write_calibration
        from ..geometry.chessboard import calibrate_stereo_rig, drop_misfit_pairs
        from ..core.checkout import code_version
        from ..plotting.figures import check_output_path, image_written_after
        from ..core.files import check_output_file
        from ..core.image_files import read_image_array

    board = parse_board(args.board)
    check_output_file(args.out, "--out", (".json",), "a .json")
    if args.figure:
        check_output_path(args.figure, args.figure_option)
    paths = pair_paths(args)
    inputs = [("--pairs list", args.pairs)] + [(f"{view} image of a pair", path) for pair in paths
                                                for view, path in zip(("left", "right"), pair[:2])]
    check_outputs_apart([("--out", args.out), (args.figure_option, args.figure)], inputs)

    def gray(path: str, name: str):
        image = read_image_array(path, name, gray=True)
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image

    source = "--pairs" if args.pairs else "left"  # the argument that named the files (a right one's too)
    views = drop_misfit_pairs(_board_views(paths, board, source, gray), args.square_m, board)
    calibration = calibrate_stereo_rig(views, args.square_m, board, f"svs_torch {code_version()}", source)
    warnings = _warnings(calibration, views)
    # Both files or neither: the figure is written first, so one the disk refuses leaves no calibration behind (one
    # that could not be written once replaced a rig's calibration and exited 1 without a report), but takes its
    # name only once the calibration is written, so a calibration that fails leaves an earlier figure as it was.
    staged = contextlib.nullcontext()
    if args.figure:
        first = next(pair for pair in paths if pair[0] == views.names[0])
        figure = _figure(calibration, views, (gray(first[0], first[2]), gray(first[1], first[2])))
        staged = image_written_after(args.figure, figure, args.figure_option)
    with staged:
        write_calibration(args.out, calibration)
    for warning in warnings:
        print(f"svs-depth calibrate: warning: {warning}", file=sys.stderr, flush=True)
    if args.json:
        print(dumps_strict({**calibration.to_json(), **right_camera_pose(calibration.R, calibration.T),
                            "skipped": views.skipped, "misfits": list(views.misfits),
                            "warnings": warnings, "out": args.out}), flush=True)
    else:
        print("\n".join(_text(calibration, views, args.out, args.figure)), flush=True)
    return 0


def _board_views(paths: list, board: tuple[int, int], source: str, gray):
    """The board's views in the ``(left, right, named_by)`` image ``paths`` (``gray`` reads one), with a progress
    bar: 20 pairs of a 12-MP camera take minutes, and were searched without a word (an audit of calibrate). One
    pair in memory at a time, counted once its boards were looked for; no summary line (the report says how many
    pairs were used, and an error's one line is all it says)."""
    from ..geometry.chessboard import collect_board_views
    from .progress import Progress

    progress = Progress(len(paths), "calibrate")

    def decoded():
        for left, right, named_by in paths:
            yield left, gray(left, named_by), gray(right, named_by)
            progress.update(1)

    try:
        return collect_board_views(decoded(), board, source)
    finally:
        progress.close(summary=False)


def square_metres(text: str) -> float:
    """argparse type of --square-m: MIN_SQUARE_M to MAX_SQUARE_M, refused before any chessboard is read."""
    value = positive_float(text)
    if value < MIN_SQUARE_M:
        raise argparse.ArgumentTypeError(f"expected the side of one square in metres, at least {MIN_SQUARE_M:g} "
                                         f"(1 mm; 25 mm is 0.025), got {text!r}")
    if value > MAX_SQUARE_M:
        raise argparse.ArgumentTypeError(f"expected the side of one square in metres, at most {MAX_SQUARE_M:g} "
                                         f"(25 mm is 0.025), got {text!r}")
    return value
