"""A stereo rig's calibration: the file ``svs-depth calibrate`` writes, and rectifying pairs with it.

The uncalibrated path of the paper (Sec. 3.4) estimates F from each pair's own matches and rectifies with it;
a rig calibrated once with a chessboard (:mod:`svs_torch.geometry.chessboard`, OpenCV's ``calibrateCamera`` and
``stereoCalibrate``) is rectified instead by the fixed maps of ``cv2.stereoRectify``, which also give the focal
length, the baseline and the principal-point offset the depth needs: ``focal_px = P1[0, 0]``,
``baseline_m = −P2[0, 3] / P2[0, 0]`` (= |T| for a horizontal rig) and ``doffs_px = P2[0, 2] − P1[0, 2]``
(``StereoBatch``'s convention, cx_right − cx_left; OpenCV's Q gives Z = f·B / (d + cx_right − cx_left)).

The file is JSON (easy to read from users' scripts): both cameras' K and distortion, R, T (metres), R1, R2, P1,
P2, Q, the image size it was made at, the reprojection errors, the rectified row error and how far the focal
length is pinned down, the board, the date and the software version. A pair of another size with the same aspect
ratio (a rig calibrated at 640×480 and run at 320×240) is rectified with the matrices scaled to it
(:meth:`StereoCalibration.scaled_to`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os

import numpy as np
import torch
import torch.nn.functional as F

from ..core.camera import (CALIBRATION_RANGES, MAX_BASELINE_M, MAX_SIZE_PX, MIN_BASELINE_M,
                           calibration_value_expected)
from ..core.checks import InputError, check_instance
from ..core.files import atomic_output, display_path, path_kind, write_errors_named
from ..core.types import StereoBatch
from .calibration_fields import coefficients_field, finite_or_none, matrix_field, number_field

__all__ = ["BASELINE_RANGE_M", "FORMAT", "StereoCalibration", "check_baseline", "read_calibration",
           "rectify_with_calibration", "rectification_grids", "write_calibration"]

#: The file's ``format`` field: a JSON file without it is not a calibration of this package.
FORMAT = "svs-depth stereo calibration"
FORMAT_VERSION = 1
#: Two sizes have the same aspect ratio (a resized image of the same view) within this relative difference.
ASPECT_TOLERANCE = 0.01
#: The baselines a calibration file may hold, metres. A file in millimetres (a square given as 25 for 0.025 to an
#: older calibrate) read as an 83 m baseline: every distance 1000 times too far, in silence (an audit's find).
BASELINE_RANGE_M = (MIN_BASELINE_M, MAX_BASELINE_M)
#: The least share of each rectified view read inside its raw image. calibrate's (``cv2.stereoRectify``, alpha 0):
#: 100 %; hand edits, in silence (an audit): a doubled image_size_wh 68 % (0.31 m for 0.39), k1 = 2 49 % (0.94 m),
#: a huge distortion 0 % (black views: NO_OBJECTS, a clear path to a walker).
MIN_IN_VIEW_SHARE = 0.9
#: The largest calibration file read, bytes (one is about 4 kB; a 1 GB file was read whole, 2.3 GB, before refused).
MAX_FILE_BYTES = 1 << 20
_MATRICES = {"R": (3, 3), "R1": (3, 3), "R2": (3, 3), "P1": (3, 4), "P2": (3, 4), "Q": (4, 4)}


@dataclasses.dataclass(frozen=True)
class StereoCalibration:
    """A calibrated stereo rig (OpenCV's conventions: pixel centres at integers, x right, y down).

    Attributes:
        image_wh: (width, height) of the images the calibration was made at, pixels.
        K_left, K_right: ``(3, 3)`` camera matrices, pixels. dist_left, dist_right: distortion coefficients.
        R: ``(3, 3)``, T: ``(3,)`` metres: the right camera's pose, x_right = R·x_left + T.
        R1, R2: ``(3, 3)`` rectifying rotations; P1, P2: ``(3, 4)`` rectified projections; Q: ``(4, 4)``.
        rms_left_px, rms_right_px, rms_stereo_px: reprojection RMS of each camera's and the stereo calibration.
        row_error_mean_px, row_error_max_px: |y_left − y_right| of the matching corners after rectification.
        focal_sd_pct: how far the board's poses pin the focal length down: OpenCV's standard deviation of fx, % of
            fx, the larger camera's (NaN: a file written before it was recorded).
        board: the chessboard (``inner_corners`` [columns, rows], ``square_m``); pairs: the pairs used;
        created_utc, software: when and by what it was made.
    """

    image_wh: tuple[int, int]
    K_left: np.ndarray
    dist_left: np.ndarray
    K_right: np.ndarray
    dist_right: np.ndarray
    R: np.ndarray
    T: np.ndarray
    R1: np.ndarray
    R2: np.ndarray
    P1: np.ndarray
    P2: np.ndarray
    Q: np.ndarray
    rms_left_px: float = math.nan
    rms_right_px: float = math.nan
    rms_stereo_px: float = math.nan
    row_error_mean_px: float = math.nan
    row_error_max_px: float = math.nan
    focal_sd_pct: float = math.nan
    board: dict = dataclasses.field(default_factory=dict)
    pairs: tuple[str, ...] = ()
    created_utc: str = ""
    software: str = ""

    @property
    def focal_px(self) -> float:
        """Focal length of the rectified images, pixels (at ``image_wh``)."""
        return float(self.P1[0, 0])

    @property
    def baseline_m(self) -> float:
        """Distance between the rectified cameras' centres, metres (OpenCV: ``P2[0, 3] = −f·B``)."""
        return float(-self.P2[0, 3] / self.P2[0, 0])

    @property
    def doffs_px(self) -> float:
        """``cx_right − cx_left`` of the rectified images, pixels (0 with OpenCV's CALIB_ZERO_DISPARITY)."""
        return float(self.P2[0, 2] - self.P1[0, 2])

    def scaled_to(self, size_wh: tuple[int, int], name: str = "calibration") -> StereoCalibration:
        """The calibration of the same rig for images resized to ``size_wh`` (the same view, another resolution):
        K, P1, P2 and Q in the new pixels (pixel centres kept: x' = (x + 0.5)·s − 0.5); R, T, the distortion
        (in normalised coordinates) unchanged.

        Raises:
            InputError: naming ``name``, when ``size_wh`` has another aspect ratio (another field of view).
        """
        width, height = (int(v) for v in size_wh)
        if (width, height) == tuple(self.image_wh):
            return self
        sx, sy = width / self.image_wh[0], height / self.image_wh[1]
        if abs(sx - sy) > ASPECT_TOLERANCE * max(sx, sy):
            raise InputError(f"{name}: made at {self.image_wh[0]}x{self.image_wh[1]}, the pair is {width}x{height}: "
                             "expected the same aspect ratio (the same view at another resolution)")
        scale = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])
        P1, P2 = scale @ self.P1, scale @ self.P2
        # Q as cv2.stereoRectify gives it at the new size: the same 3-D point for a pixel's (x', y', d') as the old
        # Q for the old pixel (x = (x' + 0.5) / sx − 0.5, likewise y, d = d' / sx), up to the homogeneous scale.
        return dataclasses.replace(self, image_wh=(width, height), K_left=scale @ self.K_left,
                                   K_right=scale @ self.K_right, P1=P1, P2=P2, Q=_implied_q(P1, P2))

    def to_json(self) -> dict:
        """The file's content (see the module docstring); derived focal, baseline and doffs for users' scripts."""
        def listed(value: np.ndarray) -> list:
            return np.asarray(value, dtype=np.float64).tolist()

        return {
            "format": FORMAT, "format_version": FORMAT_VERSION, "image_size_wh": list(self.image_wh),
            "focal_px": self.focal_px, "baseline_m": self.baseline_m, "doffs_px": self.doffs_px,
            "rms_left_px": self.rms_left_px, "rms_right_px": self.rms_right_px, "rms_stereo_px": self.rms_stereo_px,
            "row_error_mean_px": self.row_error_mean_px, "row_error_max_px": self.row_error_max_px,
            "focal_sd_pct": self.focal_sd_pct,
            "board": self.board, "num_pairs": len(self.pairs), "pairs": list(self.pairs),
            "K_left": listed(self.K_left), "dist_left": listed(np.ravel(self.dist_left)),
            "K_right": listed(self.K_right), "dist_right": listed(np.ravel(self.dist_right)),
            "R": listed(self.R), "T_m": listed(np.ravel(self.T)),
            **{name: listed(getattr(self, name)) for name in ("R1", "R2", "P1", "P2", "Q")},
            "created_utc": self.created_utc, "software": self.software,
        }


def write_calibration(path: str | os.PathLike, calibration: StereoCalibration, name: str = "--out") -> None:
    """Write ``calibration`` as JSON to ``path`` whole (:func:`svs_torch.core.files.atomic_output`); an
    :class:`OSError` naming ``name`` and the file when it cannot be written."""
    check_instance(calibration, "calibration", StereoCalibration)
    text = json.dumps(finite_or_none(calibration.to_json()), indent=1, allow_nan=False) + "\n"
    with write_errors_named(name, path), atomic_output(path, "w", encoding="utf-8") as stream:
        stream.write(text)


def _parse(record: object, where: str) -> StereoCalibration:
    """A :class:`StereoCalibration` from the file's JSON, every field checked (one-line errors naming it)."""
    if not isinstance(record, dict) or record.get("format") != FORMAT:
        raise InputError(f"{where}: expected a JSON object with \"format\": \"{FORMAT}\" (svs-depth calibrate's "
                         "output)")
    version = record.get("format_version", FORMAT_VERSION)
    if not (isinstance(version, int) and not isinstance(version, bool) and 1 <= version <= FORMAT_VERSION):
        newer = isinstance(version, int) and not isinstance(version, bool) and version > FORMAT_VERSION
        raise InputError(f"{where}: expected 'format_version' 1 to {FORMAT_VERSION} (this svs_torch's), got "
                         f"{version!r}" + (": written by a newer svs_torch?" if newer else ""))
    if not (isinstance(record.get("pairs", []), list) and all(isinstance(p, str) for p in record.get("pairs", []))):
        raise InputError(f"{where}: expected 'pairs' as a list of the chessboard pairs' names")
    size = record.get("image_size_wh")
    if not (isinstance(size, list) and len(size) == 2 and all(isinstance(v, int) and not isinstance(v, bool)
                                                              and 0 < v <= MAX_SIZE_PX for v in size)):
        raise InputError(f"{where}: expected 'image_size_wh' as [width, height], two positive integers of at most "
                         f"{MAX_SIZE_PX} px")
    matrices = {key: matrix_field(record, key, shape, where) for key, shape in _MATRICES.items()}
    K_left, K_right = (matrix_field(record, key, (3, 3), where) for key in ("K_left", "K_right"))
    T = matrix_field(record, "T_m", (3,), where)
    calibration = StereoCalibration(
        image_wh=(size[0], size[1]), K_left=K_left, dist_left=coefficients_field(record, "dist_left", where),
        K_right=K_right, dist_right=coefficients_field(record, "dist_right", where), T=T, **matrices,
        **{key: number_field(record, key) for key in ("rms_left_px", "rms_right_px", "rms_stereo_px",
                                                 "row_error_mean_px", "row_error_max_px", "focal_sd_pct")},
        board=record.get("board") if isinstance(record.get("board"), dict) else {},
        pairs=tuple(record.get("pairs", [])),
        created_utc=str(record.get("created_utc", "")), software=str(record.get("software", "")))
    for key, K in (("K_left", K_left), ("K_right", K_right)):
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            raise InputError(f"{where}: expected '{key}' with positive focal lengths, got {K[0, 0]} and {K[1, 1]}")
    focal, baseline = calibration.focal_px, calibration.baseline_m  # (a focal of 1e30: views of one raw pixel each)
    if not (calibration_value_expected("focal_px", focal) is None and baseline > 0):
        raise InputError(f"{where}: expected P1, P2 of a left-right rig (P1[0][0] {CALIBRATION_RANGES['focal_px'][2]}, "
                         f"baseline -P2[0][3]/P2[0][0] over 0), got {focal:g} px, {baseline:g} m")
    check_baseline(calibration.baseline_m, where)
    _check_one_rig(calibration, record, where)
    _check_maps_in_view(calibration, where)
    return calibration


def _check_maps_in_view(calibration: StereoCalibration, where: str) -> None:
    """Refuse a lens centre far from the image's, or maps reading under :data:`MIN_IN_VIEW_SHARE` inside it."""
    width, height = calibration.image_wh
    for key in ("K_left", "K_right"):  # a lens's centre lies near the sensor's (an image size halved: at its corner)
        cx, cy = getattr(calibration, key)[:2, 2]
        if not (0.2 * width < cx < 0.8 * width and 0.2 * height < cy < 0.8 * height):
            raise InputError(f"{where}: '{key}' puts the lens centre at ({cx:.0f}, {cy:.0f}) px, far from the middle "
                             f"of its {width}x{height} image: a K or image_size_wh of another resolution?")
    small = (320, max(1, round(320 * height / width)))
    keeps_aspect = abs(small[1] * width / (small[0] * height) - 1) < ASPECT_TOLERANCE  # else the file's own size
    checked = calibration.scaled_to(small) if width > small[0] and keeps_aspect else calibration
    width, height = checked.image_wh
    for side, (map_x, map_y) in zip(("left", "right"), _rectification_maps(checked)):
        inside = float(((map_x >= -0.5) & (map_x <= width - 0.5) & (map_y >= -0.5) & (map_y <= height - 0.5)).mean())
        if not inside >= MIN_IN_VIEW_SHARE:
            raise InputError(f"{where}: its {side} camera's K, distortion and image_size_wh rectify only "
                             f"{100 * inside:.0f} % of the view from inside the image (calibrate's: all of it); "
                             "calibrate again rather than edit them")


def check_baseline(baseline_m: float, where: str) -> None:
    """Refuse a baseline outside :data:`BASELINE_RANGE_M` (a file in millimetres, a square typed too small)."""
    low, high = BASELINE_RANGE_M
    if not low <= baseline_m <= high:
        cause = "in millimetres (the board's square in mm)" if baseline_m > high else "of a square given too small"
        raise InputError(f"{where}: expected a baseline of {low * 1000:g} mm to {high:g} m, got {baseline_m:.6g} m: "
                         f"a calibration {cause}? Calibrate again with --square-m the side of one square in metres "
                         "(25 mm is 0.025)")


def _implied_q(P1: np.ndarray, P2: np.ndarray) -> np.ndarray:
    """OpenCV's reprojection matrix of two rectified camera matrices (``cv2.stereoRectify``'s Q): (x, y, d, 1)
    to 3-D, with Tx = P2[0, 3] / f the (negative) baseline of a left-right rig."""
    focal, tx = P1[0, 0], P2[0, 3] / P2[0, 0]
    return np.array([[1.0, 0.0, 0.0, -P1[0, 2]], [0.0, 1.0, 0.0, -P1[1, 2]], [0.0, 0.0, 0.0, focal],
                     [0.0, 0.0, -1.0 / tx, (P1[0, 2] - P2[0, 2]) / tx]])


def _check_one_rig(calibration: StereoCalibration, record: dict, where: str) -> None:
    """The file's parts describe one rig (a hand edit of one part alone is refused, not half applied): R, R1, R2
    rotations; P1 and P2 one rectified camera matrix; Q the reprojection matrix they give; |T| the baseline of
    P2; the summary values (``focal_px``, ``baseline_m``, ``doffs_px``, which nothing reads) those of P1 and P2."""
    for key in ("R", "R1", "R2"):
        R = getattr(calibration, key)
        if not (np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0):
            raise InputError(f"{where}: expected '{key}' as a rotation (orthonormal, determinant +1)")
    P1, P2 = calibration.P1, calibration.P2  # stereoRectify's form: else maps OpenCV refused (an internal error)
    zeros = [P[i, j] for P in (P1, P2) for i, j in ((0, 1), (1, 0), (1, 3), (2, 0), (2, 1), (2, 3))] + [P1[0, 3]]
    if not (all(v == 0 for v in zeros) and P1[2, 2] == P2[2, 2] == 1 and P1[1, 1] > 0 and all(
            math.isclose(P1[i, j], P2[i, j], rel_tol=1e-9) for i, j in ((0, 0), (1, 1), (1, 2)))):
        raise InputError(f"{where}: expected P1 and P2 with one focal length and one row centre (rectified views: "
                         f"[[f, 0, cx, 0 or -f*B], [0, f, cy, 0], [0, 0, 1, 0]]), got focal {P1[0, 0]:g} and "
                         f"{P2[0, 0]:g} px")
    Q, implied = calibration.Q, _implied_q(calibration.P1, calibration.P2)  # homogeneous: equal up to a scale
    if Q[2, 3] == 0 or not np.allclose(Q * (implied[2, 3] / Q[2, 3]), implied, rtol=1e-6, atol=1e-9):
        raise InputError(f"{where}: expected 'Q' as the reprojection matrix P1 and P2 give (OpenCV's "
                         "stereoRectify), got another")
    if not math.isclose(float(np.linalg.norm(calibration.T)), calibration.baseline_m, rel_tol=1e-6):
        raise InputError(f"{where}: expected |T_m| = the baseline of P2 ({calibration.baseline_m:.6g} m), got "
                         f"{float(np.linalg.norm(calibration.T)):.6g} m")
    for key in ("focal_px", "baseline_m", "doffs_px"):
        value, implied = record.get(key), getattr(calibration, key)  # _number: a 400-digit integer is no float
        if value is not None and not math.isclose(number_field(record, key), implied, rel_tol=1e-6, abs_tol=1e-9):
            raise InputError(f"{where}: '{key}' {value!r:.30} is not the {implied:.6g} its P1 and P2 give (they are "
                             "what rectifies; calibrate again rather than edit one value)")


def read_calibration(path: str | os.PathLike, name: str = "--calibration") -> StereoCalibration:
    """The calibration file ``path`` (written by :func:`write_calibration`).

    Raises:
        InputError: one line naming ``name`` and the file, for a missing or unreadable file, text that is not
            JSON, or a field that is missing or wrong (its name and what was expected).
    """
    where = f"{name}: {display_path(path)}"
    kind = path_kind(path, name)
    if kind != "file":
        raise InputError(f"{where}: expected a calibration file, got " +
                         {"missing": "no such file", "folder": "a folder"}.get(kind, "a special file"))
    try:
        with open(path, "rb") as stream:
            text = stream.read(MAX_FILE_BYTES + 1)
    except OSError as error:
        raise InputError(f"{where}: cannot read it: {error.strerror or error}") from None
    if len(text) > MAX_FILE_BYTES:
        raise InputError(f"{where}: expected a calibration file of at most {MAX_FILE_BYTES >> 20} MB (svs-depth "
                         "calibrate writes about 4 kB)")
    if text.lstrip().startswith((b"%YAML", b"<?xml", b"<opencv_storage")):
        raise InputError(f"{where}: an OpenCV FileStorage file (YAML/XML) is not read: expected svs-depth "
                         "calibrate's JSON (run it on the rig's chessboard pairs)")
    try:
        record = json.loads(text)  # bytes: UTF-8, and the BOMs of UTF-8 and UTF-16 that Windows editors write
    except (UnicodeDecodeError, ValueError) as error:
        raise InputError(f"{where}: expected a JSON calibration file ({' '.join(str(error).split())[:80]})") from None
    except RecursionError:  # lists nested thousands deep
        raise InputError(f"{where}: expected a JSON calibration file (nested too deep to be one)") from None
    try:
        return _parse(record, where)
    except RecursionError:  # deep, yet within what the JSON parser took
        raise InputError(f"{where}: expected a calibration's fields (lists nested too deep to be one)") from None


def rectification_grids(calibration: StereoCalibration, size_wh: tuple[int, int], dtype: torch.dtype,
                        device: torch.device | str = "cpu") -> torch.Tensor:
    """``(2, H, W, 2)`` sampling grids (left, right) for ``F.grid_sample`` (``align_corners=True``): where each
    rectified pixel is read in the raw image, from ``cv2.initUndistortRectifyMap`` of the calibration scaled to
    ``size_wh``. Not differentiable (fixed maps)."""
    scaled = calibration.scaled_to(size_wh)
    width, height = scaled.image_wh
    # align_corners=True: −1 and +1 are the centres of the first and last pixels, OpenCV's 0 and W − 1.
    grids = [torch.from_numpy(np.stack([2 * map_x / max(width - 1, 1) - 1, 2 * map_y / max(height - 1, 1) - 1], -1))
             for map_x, map_y in _rectification_maps(scaled)]
    return torch.stack(grids).to(device=device, dtype=dtype)


def _rectification_maps(calibration: StereoCalibration) -> list[tuple[np.ndarray, np.ndarray]]:
    """(map_x, map_y) of the left and right views at the calibration's own size: where each rectified pixel is
    read in the raw image (``cv2.initUndistortRectifyMap``, float32)."""
    import cv2

    return [cv2.initUndistortRectifyMap(K, dist, R, P, tuple(calibration.image_wh), cv2.CV_32FC1)
            for K, dist, R, P in ((calibration.K_left, calibration.dist_left, calibration.R1, calibration.P1),
                                  (calibration.K_right, calibration.dist_right, calibration.R2, calibration.P2))]


def rectify_with_calibration(batch: StereoBatch, calibration: StereoCalibration,
                             name: str = "--calibration") -> StereoBatch:
    """``batch`` rectified by the calibrated rig: both views remapped (bilinear, zeros outside the raw image,
    as ``cv2.remap``), focal, baseline and doffs from the calibration scaled to the pairs' size, ``calibrated``
    True. Every pair must fill the batch's tensors (rectify pairs of different sizes apart) and have no ground
    truth (a truth of the raw view would not hold for the rectified one).

    Differentiable w.r.t. ``batch.left`` and ``batch.right`` (a fixed bilinear resampling); not w.r.t. the
    calibration.

    Raises:
        InputError: naming ``name``, for a pair of another aspect ratio than the calibration's, a padded batch
            or a batch with ground truth.
    """
    check_instance(batch, "batch", StereoBatch)
    check_instance(calibration, "calibration", StereoCalibration)
    height, width = batch.size_hw
    if not bool((batch.image_hw == torch.tensor([height, width], device=batch.image_hw.device)).all()):
        raise InputError(f"{name}: expected pairs that fill the batch (rectify pairs of different sizes apart)")
    if batch.disparity_px is not None:
        raise InputError(f"{name}: expected pairs without ground truth (a scene folder brings its own calibration)")
    scaled = calibration.scaled_to((width, height), name)
    grids = rectification_grids(scaled, (width, height), batch.left.dtype, batch.left.device)
    b = batch.batch_size

    def remap(images: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
        # One grid for the whole batch: the rig is the same for every pair.
        return F.grid_sample(images, grid.expand(b, -1, -1, -1), mode="bilinear", padding_mode="zeros",
                             align_corners=True).clamp(0, 1)

    def filled(value: float) -> torch.Tensor:
        return torch.full((b,), value, dtype=batch.focal_px.dtype, device=batch.focal_px.device)

    return dataclasses.replace(
        batch, left=remap(batch.left, grids[0]), right=remap(batch.right, grids[1]), focal_px=filled(scaled.focal_px),
        baseline_m=filled(scaled.baseline_m), doffs_px=filled(scaled.doffs_px),
        calibrated=torch.ones(b, dtype=torch.bool, device=batch.calibrated.device))
