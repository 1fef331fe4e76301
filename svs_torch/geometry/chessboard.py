"""Calibrate a stereo rig from chessboard pairs with OpenCV, the well-kept library for it.

Per pair: ``findChessboardCorners`` in both views, refined by ``cornerSubPix``; pairs where either view misses the
board are left out (and counted). Then each camera alone (``calibrateCamera``), the two together with those
intrinsics fixed (``stereoCalibrate``, ``CALIB_FIX_INTRINSIC``: the mono fits have more freedom per view, and the
stereo step then only estimates R and T, as OpenCV's stereo_calib sample and the shared set's MANIFEST do), and the
rectification (``stereoRectify`` with ``CALIB_ZERO_DISPARITY`` and ``alpha=0``: the rectified images hold only
valid pixels, so no black border enters the segmentation's threshold). The board's square size in metres sets the
unit of T, hence of the baseline and of every depth.

A pair whose two views do not fit the others (the same image twice, the board moved between the two shots)
spoils the whole fit; :func:`drop_misfit_pairs` finds and leaves out such pairs where the fit is poor.

Reported, as OpenCV computes them: the RMS reprojection error of each camera and of the stereo fit (pixels), and
the rectified pair's row error: |y_left − y_right| of the matching corners mapped by the rectification
(``undistortPoints`` with R1, P1 / R2, P2), mean and maximum, pixels. None of this is differentiable.
"""

from __future__ import annotations

import datetime
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from ..core.checks import InputError
from .calibration import StereoCalibration, _check_maps_in_view, check_baseline

__all__ = ["BoardViews", "GOOD_FOCAL_SD_PCT", "GOOD_STEREO_RMS_PX", "MAX_FOCAL_SD_PCT", "MAX_SQUARE_M", "MIN_PAIRS",
           "board_image_u8", "calibrate_stereo_rig", "collect_board_views", "count_poses", "drop_misfit_pairs",
           "find_board_corners",
           "fit_doubts", "good_row_error_px", "good_stereo_rms_px", "rectified_corners"]

#: Fewest pairs with the board found in both views: each view gives the intrinsics 2 constraints, and OpenCV
#: warns below 3; a usable calibration wants 10–20 views across the field.
MIN_PAIRS = 3
#: The largest square side taken, metres: a board of larger squares is no printed chessboard, and a side in
#: millimetres typed as metres (25 for 0.025) gave an 83 m baseline in silence.
MAX_SQUARE_M = 1.0
#: The smallest: a 9x6 board of 1 mm squares is 1 cm wide; 1e-20 m squares ended in an OpenCV assertion (an audit).
MIN_SQUARE_M = 0.001
#: The fewest pixels along a square's side in which the board is looked for: OpenCV's finder asserts on a 16x12
#: image, and finds no 9x6 board at 24x18.
MIN_SQUARE_PX = 4
#: A stereo fit whose reprojection RMS is above this, pixels, is looked at pair by pair (:func:`drop_misfit_pairs`):
#: OpenCV's sample pairs fit to 0.2 px, while one pair whose views are not one moment of one board (the same view
#: twice, a view of another pose) ruined the whole fit (13.6 px, a 0.19 m baseline for 0.083) and was written in
#: silence (an audit).
GOOD_STEREO_RMS_PX = 1.0
#: A fit whose chessboards' rows, rectified, lie farther apart than this on average (pixels per 640 of width) is
#: warned of: the shared set's and its subsets' calibrations 0.06-0.14 px; five pairs of one pose moved across the
#: field, never tilted, 0.70-0.95 px with focal 870 px for 516 and baselines up to 0.124 m for 0.083 (an audit).
GOOD_ROW_ERROR_PX = 0.5
#: A fit whose focal length the board's poses pin down only to more than this, % (OpenCV's standard deviation of fx,
#: :attr:`StereoCalibration.focal_sd_pct`), is warned of; over :data:`MAX_FOCAL_SD_PCT` refused. Measured: the shared
#: set 0.08 % (any 3-5 of its pairs, each camera alone, under 1.3 %); twelve synthetic poses tilted up to ±11° 1.3 %
#: (focal within 1 %), up to ±6° 4.1 % (8 % off: 0.864 m for 0.80), up to ±3° 12 % (rectified focal 1707 px for
#: 612: 1.65 m for 0.80, "OK", an audit), rows and RMS not telling the ±6° fit at all.
GOOD_FOCAL_SD_PCT = 3.0
MAX_FOCAL_SD_PCT = 10.0
#: The longest side, pixels, of the view the board is looked for in: a larger capture (a phone's 4000x3000) is
#: searched in a copy resampled to it, and the corners found are refined in the full view, in windows grown with
#: the scale. Why: OpenCV's finder found the board in 5 of 12 views of the shared pairs enlarged to 4000x3000 (each
#: miss 1.2-1.8 s) and calibrate refused them ("found in both views of 1 of 6 pairs ... check --board"), where the
#: same views at 1000x750 gave all 12 (an audit); all 13 pairs then calibrate to the 640x480 set's focal within
#: 0.2 % and baseline within 0.1 %.
FIND_MAX_SIDE_PX = 1280
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
_STEREO_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-6)


@dataclass(frozen=True)
class BoardViews:
    """The board's corners found in the pairs: ``left``, ``right`` lists of ``(N, 2)`` float32 arrays (the same
    corner order in both views), ``names`` of the pairs used, ``skipped`` names of pairs without the board in
    both views, ``image_wh`` the pairs' size, ``misfits`` the pairs :func:`drop_misfit_pairs` left out, each
    ``"name (why)"``."""

    left: list[np.ndarray]
    right: list[np.ndarray]
    names: list[str]
    skipped: list[str]
    image_wh: tuple[int, int]
    misfits: tuple[str, ...] = ()

    def without(self, whys: dict[int, str]) -> BoardViews:
        """These views without the pairs ``index`` of ``whys``, each left out for its ``why`` (in pair order)."""
        keep = [i for i in range(len(self.names)) if i not in whys]
        return BoardViews([self.left[i] for i in keep], [self.right[i] for i in keep], [self.names[i] for i in keep],
                          self.skipped, self.image_wh,
                          self.misfits + tuple(f"{self.names[i]} ({whys[i]})" for i in sorted(whys)))


def find_board_corners(image: np.ndarray, board: tuple[int, int]) -> np.ndarray | None:
    """The ``board = (columns, rows)`` inner corners of a chessboard in a uint8 gray ``image``, ``(N, 2)``
    float32 refined to sub-pixel, or None when the whole board is not found (:func:`board_image_u8` converts
    other captures). Raises InputError naming ``image`` for any other array (OpenCV's error named none)."""
    if not (isinstance(image, np.ndarray) and image.dtype == np.uint8 and image.ndim == 2):
        kind = f"{image.dtype} {image.shape}" if isinstance(image, np.ndarray) else type(image).__name__
        raise InputError(f"image: expected a 2-D uint8 gray numpy array (board_image_u8 converts one), got {kind}")
    if min(image.shape) < (min(board) + 1) * MIN_SQUARE_PX or max(image.shape) < (max(board) + 1) * MIN_SQUARE_PX:
        return None  # no board fits (and OpenCV's finder asserts on a 16x12 image)
    scale = max(1.0, max(image.shape) / FIND_MAX_SIDE_PX)
    seen = image if scale == 1.0 else cv2.resize(image, (round(image.shape[1] / scale), round(image.shape[0] / scale)),
                                                 interpolation=cv2.INTER_AREA)
    found, corners = cv2.findChessboardCorners(seen, board,
                                               flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not found:
        return None
    if seen is not image:  # pixel centres kept: x = (x_seen + 0.5) * s - 0.5
        factors = np.array([image.shape[1] / seen.shape[1], image.shape[0] / seen.shape[0]], np.float32)
        corners = ((corners + 0.5) * factors - 0.5).astype(np.float32)
    # OpenCV's samples refine in a 23x23 window (half-size 11) at 640x480; on a smaller board image such a window
    # takes in the next corners and pulls an edge corner off by pixels, so it is kept within a third of the
    # nearest spacing of two corners along the board's longer side, whichever way --board names it (measured along
    # OpenCV's rows alone, 6x9 for a 9x6 board refined in 11 px windows: stereo RMS 0.42 px for 0.20, an audit).
    grid = corners.reshape(board[1], board[0], 2)  # OpenCV's order: rows of board[0] corners
    spacing = float(np.linalg.norm(np.diff(grid, axis=1 if board[0] >= board[1] else 0), axis=-1).min())
    corners = corners.reshape(-1, 1, 2)
    half = int(np.clip(round(spacing / 3), 2, round(11 * scale)))
    refined = cv2.cornerSubPix(image, corners, (half, half), (-1, -1), _SUBPIX_CRITERIA)
    return refined.reshape(-1, 2).astype(np.float32)


def board_image_u8(image: np.ndarray) -> np.ndarray:
    """A board image as the corner finder sees it: gray uint8, a 16-bit or float capture stretched to 0–255 (its
    darkest to its brightest level)."""
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if image.dtype != np.uint8:  # 16-bit (or float) captures: to the 8-bit range the detector expects
        image = cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    return image


def collect_board_views(pairs: Sequence[tuple[str, np.ndarray, np.ndarray]], board: tuple[int, int],
                        name: str = "pairs") -> BoardViews:
    """The board in every ``(name, left image, right image)`` pair (see :class:`BoardViews`).

    Raises:
        InputError: naming ``name`` (the argument the pairs came from), for pairs of different sizes, or fewer than
            :data:`MIN_PAIRS` pairs with the board in both views.
    """
    left, right, names, skipped, size = [], [], [], [], None
    seen = [0, 0]  # views with the board, left and right
    for pair_name, image_left, image_right in pairs:
        image_left, image_right = board_image_u8(image_left), board_image_u8(image_right)
        wh = (image_left.shape[1], image_left.shape[0])
        if size is None:
            size = wh
            least = ((board[0] + 1) * MIN_SQUARE_PX, (board[1] + 1) * MIN_SQUARE_PX)  # (either way round)
            if min(size) < min(least) or max(size) < max(least):  # (16x12: an OpenCV assertion, an audit)
                raise InputError(f"{name}: {pair_name} is {size[0]}x{size[1]} px, too small to find a {board[0]}x"
                                 f"{board[1]} board in: expected at least {max(least)}x{min(least)} px "
                                 f"({MIN_SQUARE_PX} px a square)")
        for view, image in (("left", image_left), ("right", image_right)):
            if (image.shape[1], image.shape[0]) != size:
                raise InputError(f"{name}: expected every image at {size[0]}x{size[1]} (one rig, one size), got "
                                 f"{image.shape[1]}x{image.shape[0]} in the {view} view of {pair_name}")
        corners = (find_board_corners(image_left, board), find_board_corners(image_right, board))
        seen = [count + (found is not None) for count, found in zip(seen, corners)]
        if corners[0] is None or corners[1] is None:
            skipped.append(pair_name)
            continue
        left.append(corners[0])
        right.append(corners[1])
        names.append(pair_name)
    if len(names) < MIN_PAIRS:
        # The board in enough views of one camera: not --board but the other camera (covered, dark, aimed aside).
        hint = f": it is in {seen[0]} left and {seen[1]} right views, and both cameras must see the whole board" \
            if max(seen) >= MIN_PAIRS else " (check --board: inner corners, columns x rows)" if skipped else ""
        raise InputError(f"{name}: the {board[0]}x{board[1]} board was found in both views of {len(names)} of "
                         f"{len(names) + len(skipped)} pairs; expected at least {MIN_PAIRS}{hint}")
    _check_views_differ(left, right, names, name)
    return BoardViews(left, right, names, skipped, size)


#: Corners within this many pixels of another pair's (median over the board) show the same pose of the board.
SAME_POSE_PX = 1.0


def _check_views_differ(left: list[np.ndarray], right: list[np.ndarray], names: list[str], name: str) -> None:
    """At least :data:`MIN_PAIRS` poses of the board, and two cameras apart. Why: copies of one pair under other
    names, or the same image as both views, made OpenCV's fit degenerate, and the error blamed swapped cameras."""
    same_image = [n for n, a, b in zip(names, left, right) if np.median(np.linalg.norm(a - b, axis=-1)) < SAME_POSE_PX]
    if len(same_image) == len(names):
        raise InputError(f"{name}: the left and right views show the board at the same pixels in every pair (e.g. "
                         f"{same_image[0]}): expected two cameras' images, LEFT and RIGHT from each camera")
    poses = count_poses(left)
    if poses < MIN_PAIRS:
        raise InputError(f"{name}: the board is in {poses} pose(s) over {len(names)} pairs (copies of one "
                         f"pair?); expected at least {MIN_PAIRS}: move and tilt the board between pairs")


def count_poses(left: list[np.ndarray]) -> int:
    """How many poses of the board the left views' corners show: a view whose corners lie within
    :data:`SAME_POSE_PX` of an earlier one's (median over the board) is that pose again."""
    poses: list[np.ndarray] = []
    for corners in left:
        if all(np.median(np.linalg.norm(corners - pose, axis=-1)) >= SAME_POSE_PX for pose in poses):
            poses.append(corners)
    return len(poses)


def rectified_corners(calibration: StereoCalibration, views: BoardViews) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Every pair's corners mapped into the rectified images, left and right lists of ``(N, 2)``."""
    out: tuple[list[np.ndarray], list[np.ndarray]] = ([], [])
    cameras = ((calibration.K_left, calibration.dist_left, calibration.R1, calibration.P1),
               (calibration.K_right, calibration.dist_right, calibration.R2, calibration.P2))
    for side, corners, (K, dist, R, P) in zip(out, (views.left, views.right), cameras):
        for points in corners:
            side.append(cv2.undistortPoints(points.reshape(-1, 1, 2), K, dist, R=R, P=P).reshape(-1, 2))
    return out


def calibrate_stereo_rig(views: BoardViews, square_m: float, board: tuple[int, int], software: str = "",
                         name: str = "pairs") -> StereoCalibration:
    """OpenCV's mono, stereo calibration and rectification of ``views`` (see the module docstring).

    Args:
        views: :func:`collect_board_views`' corners.
        square_m: the side of one square of the board, metres (the unit of T, the baseline and every depth).
        board: (columns, rows) of inner corners.
        software: the version string recorded in the file.
        name: the argument the pairs came from, for errors.
    """
    if not (math.isfinite(square_m) and MIN_SQUARE_M <= square_m <= MAX_SQUARE_M):
        raise InputError(f"--square-m: expected the side of one square in metres, {MIN_SQUARE_M:g} to {MAX_SQUARE_M:g} "
                         f"(25 mm is 0.025), got {square_m:g}")
    columns, rows = board
    size = views.image_wh
    rms_left, K_left, dist_left, rms_right, K_right, dist_right, rms_stereo, R, T, _, focal_sd_pct = _fit(
        views, square_m, board)
    R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(K_left, dist_left, K_right, dist_right, size, R, T,
                                                flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
    calibration = StereoCalibration(
        image_wh=size, K_left=K_left, dist_left=dist_left.ravel(), K_right=K_right, dist_right=dist_right.ravel(),
        R=R, T=T.ravel(), R1=R1, R2=R2, P1=P1, P2=P2, Q=Q, rms_left_px=float(rms_left),
        rms_right_px=float(rms_right), rms_stereo_px=float(rms_stereo), focal_sd_pct=focal_sd_pct,
        board={"inner_corners": [columns, rows], "square_m": square_m}, pairs=tuple(views.names),
        created_utc=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"), software=software)
    if calibration.baseline_m <= 0:
        # A poor fit says as little of the cameras' order: two of five pairs of mismatched views were blamed on
        # swapped cameras (an audit).
        poor = (f" Or, the fit being poor (stereo RMS {rms_stereo:.1f} px), do some pairs' two views show the board "
                f"at different moments?") if rms_stereo > good_stereo_rms_px(size) else ""
        other_rig = None if poor else _not_left_right(R, T)  # (a poor fit's pose says as little)
        raise InputError(f"{name}: {other_rig}" if other_rig else f"{name}: the right camera is to the left of the "
                         f"left one (P2[0][3] > 0): are LEFT and RIGHT swapped?{poor}")
    # Refused here, not by every later read of the file; a good fit's baseline is out of range by its --square-m.
    check_baseline(calibration.baseline_m, "--square-m" if rms_stereo <= good_stereo_rms_px(size) else name)
    rectified_left, rectified_right = rectified_corners(calibration, views)
    rows_apart = np.abs(np.concatenate(rectified_left)[:, 1] - np.concatenate(rectified_right)[:, 1])
    calibration = _rectifying(_with_row_error(calibration, rows_apart), name)
    if calibration.focal_sd_pct > MAX_FOCAL_SD_PCT:
        raise InputError(f"{name}: the board's poses leave the focal length undetermined (±{focal_sd_pct:.0f} %, focal "
                         f"{calibration.focal_px:.0f} px): tilt the board toward and away from the cameras between "
                         "pairs, by 15-30 degrees, not only move it across the field")
    return calibration


def _not_left_right(R: np.ndarray, T: np.ndarray) -> str | None:
    """What a good fit with no left-right baseline found, from the right camera's pose against the left's (that of
    calibrate's report), or None where its right camera sits to the left: swapped images. Why: a right camera
    mounted upside down and a rig mounted on its side (a vertical baseline) were both called swapped (an audit)."""
    roll = math.degrees(math.atan2(R[1, 0], R[0, 0]))
    x, y, _ = (-R.T @ np.ravel(T)) * 1000  # its centre in the left camera's axes (x right, y down), millimetres
    if abs(roll) > 90:  # stereoRectify splits the roll between the views, and past 90° the baseline turns vertical
        return (f"the right camera's view is rolled {abs(roll):.0f}° against the left's (mounted upside down?): "
                "mount both cameras the same way up")
    if abs(y) > abs(x):
        return (f"the right camera sits {abs(y):.0f} mm {'below' if y > 0 else 'above'} the left, {abs(x):.0f} mm "
                "beside it: expected the cameras side by side (is the rig mounted on its side?)")
    return None


def _rectifying(calibration: StereoCalibration, name: str) -> StereoCalibration:
    """``calibration``, refused where it does not rectify its own views as every read of its file would. Why: poses
    that only move the board across the field, never tilted, leave the focal length free; four such pairs of the
    shared set fitted to 0.34 px with focal 3868 px (516), a row error of 2.3 px, and a file no command read."""
    try:
        _check_maps_in_view(calibration, name)
    except InputError:
        # (then written with a warning, yet read by nothing)
        poor = calibration.rms_stereo_px > good_stereo_rms_px(calibration.image_wh)
        # (Poses never tilted fit poorly too: twelve tilted up to ±1° to 3.2 px, the advice blaming sync alone.)
        why = (f"the fit is poor (stereo RMS {calibration.rms_stereo_px:.1f} px): check that each pair's two images "
               "were taken at the same moment, --board, and that the board is tilted toward and away from the "
               "cameras between pairs") if poor else (
            "the poses of the board leave the cameras undetermined; tilt it toward and away from the cameras between "
            "pairs, not only move it across the field")
        raise InputError(f"{name}: the fit does not rectify its own views (focal {calibration.focal_px:.0f} px, rows "
                         f"{calibration.row_error_mean_px:.1f} px apart on the boards): {why}") from None
    return calibration


def good_stereo_rms_px(image_wh: tuple[int, int]) -> float:
    """:data:`GOOD_STEREO_RMS_PX` for an image ``image_wh`` wide (pixels per 640 of width, at least that), as the row
    error's. Why: the shared pairs enlarged to a phone's 4000x3000 fit to 1.47 px (0.24 px per 640, where they fit
    to 0.20 px at 640x480) and were written with "distances from this file may be far off" (an audit)."""
    return GOOD_STEREO_RMS_PX * max(1.0, image_wh[0] / 640)


def good_row_error_px(calibration: StereoCalibration) -> float:
    """:data:`GOOD_ROW_ERROR_PX` for the calibration's image width (pixels per 640 of width, at least that)."""
    return GOOD_ROW_ERROR_PX * max(1.0, calibration.image_wh[0] / 640)


def fit_doubts(calibration: StereoCalibration) -> list[str]:
    """Why distances from ``calibration`` may be far off, each a clause naming its measure: a stereo reprojection
    RMS over :func:`good_stereo_rms_px`, rectified rows apart over :func:`good_row_error_px`, a focal length pinned
    down only to over :data:`GOOD_FOCAL_SD_PCT`. Empty for a good fit (and for a measure a file does not hold)."""
    doubts = []
    if calibration.rms_stereo_px > good_stereo_rms_px(calibration.image_wh):  # (NaN: not recorded, not doubted)
        doubts.append(f"the stereo reprojection RMS is {calibration.rms_stereo_px:.2f} px (a rig calibrates under "
                      f"{good_stereo_rms_px(calibration.image_wh):g} px)")
    if calibration.row_error_mean_px > good_row_error_px(calibration):
        doubts.append(f"the chessboards' rows lie {calibration.row_error_mean_px:.2f} px apart after rectification "
                      f"(a rig's within {good_row_error_px(calibration):g} px)")
    if calibration.focal_sd_pct > GOOD_FOCAL_SD_PCT:
        doubts.append(f"the board's poses pin the focal length down only to ±{calibration.focal_sd_pct:.1f} % (a "
                      f"rig's within {GOOD_FOCAL_SD_PCT:g} %)")
    return doubts


def _with_row_error(calibration: StereoCalibration, rows_apart: np.ndarray) -> StereoCalibration:
    from dataclasses import replace

    return replace(calibration, row_error_mean_px=float(rows_apart.mean()), row_error_max_px=float(rows_apart.max()))


def _fit(views: BoardViews, square_m: float, board: tuple[int, int]) -> tuple:
    """Each camera's fit, then the pair's with those intrinsics fixed (the module docstring): ``(rms_left, K_left,
    dist_left, rms_right, K_right, dist_right, rms_stereo, R, T, pair_errors, focal_sd_pct)``, ``pair_errors`` each
    pair's reprojection error in the stereo fit, pixels (the larger of its two views'), ``focal_sd_pct`` that of
    :attr:`~svs_torch.geometry.calibration.StereoCalibration.focal_sd_pct`."""
    columns, rows = board
    grid = np.zeros((rows * columns, 3), np.float32)
    grid[:, :2] = np.mgrid[0:columns, 0:rows].T.reshape(-1, 2) * square_m  # the corners' order in OpenCV
    objects = [grid] * len(views.names)
    (rms_left, K_left, dist_left, *_, sd_left, _, _), (rms_right, K_right, dist_right, *_, sd_right, _, _) = (
        cv2.calibrateCameraExtended(objects, corners, views.image_wh, None, None)
        for corners in (views.left, views.right))
    # fx's standard deviation, % of fx, the larger camera's: how far the poses pin the focal length down.
    focal_sd_pct = 100 * max(float(sd[0, 0]) / float(K[0, 0]) for sd, K in ((sd_left, K_left), (sd_right, K_right)))
    rms_stereo, K_left, dist_left, K_right, dist_right, R, T, *_, per_view = cv2.stereoCalibrateExtended(
        objects, views.left, views.right, K_left, dist_left, K_right, dist_right, views.image_wh, None, None,
        criteria=_STEREO_CRITERIA, flags=cv2.CALIB_FIX_INTRINSIC)
    pair_errors = np.asarray(per_view).reshape(len(views.names), 2).max(1)
    return rms_left, K_left, dist_left, rms_right, K_right, dist_right, rms_stereo, R, T, pair_errors, focal_sd_pct


def drop_misfit_pairs(views: BoardViews, square_m: float, board: tuple[int, int]) -> BoardViews:
    """``views`` without the pairs whose two views do not fit the others. While the stereo fit's RMS is above
    :func:`good_stereo_rms_px`, the fit is made without each pair in turn; the pair whose absence at least halves
    the RMS is left out (named in ``misfits`` with both RMS), and the rest looked at again, down to
    :data:`MIN_PAIRS`. Where no single pair does, the pairs whose own reprojection error in the fit is over twice
    the median are left out together if that halves it. A fit neither explains is left as it is (then the command
    warns). Costs one fit per pair, only when the fit is poor."""
    fit = _fit(views, square_m, board)
    rms, errors = fit[6], fit[9]
    good = good_stereo_rms_px(views.image_wh)
    while rms > good and len(views.names) > MIN_PAIRS:
        trials = [_fit(views.without({i: ""}), square_m, board) for i in range(len(views.names))]
        index = int(np.argmin([trial[6] for trial in trials]))
        if trials[index][6] <= rms / 2:
            views = views.without({index: f"its views do not fit the other pairs: stereo RMS {rms:.2f} px with it, "
                                          f"{trials[index][6]:.2f} px without"})
            rms, errors = trials[index][6], trials[index][9]
            continue
        # Two or more such pairs: none alone halves the RMS (two of 13 wrote a 0.23 m baseline for 0.083, an audit).
        # Each pair's own error in the fit singles them out: those over twice the median go together.
        outliers = [i for i in range(len(views.names)) if errors[i] > max(2 * np.median(errors), good)]
        if not outliers or len(views.names) - len(outliers) < MIN_PAIRS:
            break
        fit = _fit(views.without(dict.fromkeys(outliers, "")), square_m, board)
        if fit[6] > rms / 2:
            break
        views = views.without({i: f"its views do not fit the other pairs: its error {errors[i]:.2f} px, the pairs' "
                                  f"median {np.median(errors):.2f}; stereo RMS {rms:.2f} px with the {len(outliers)} "
                                  f"such pairs, {fit[6]:.2f} px without" for i in outliers})
        rms, errors = fit[6], fit[9]
    return views
