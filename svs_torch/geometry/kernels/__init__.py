"""The C kernels of the geometry stage (the ``.c`` sources beside this file) and their wrappers, each the fast path of
a torch function of the stage that stays its reference: see :mod:`svs_torch.core.kernels` for how they are built,
cached and loaded, and what every wrapper promises."""

from __future__ import annotations

import ctypes

import torch

from ...core.checks import check_shape
from ...core.errors import InputError
from ...core.kernels import FLOAT, INT, POINTER, available, declare, load, on_cpu
from ...core.kernels.checks import check_nonempty, check_number, check_rows, settings_table

__all__ = ["MAX_HYPOTHESES", "MAX_LK_ITERATIONS", "RANSAC_SETTINGS", "ROW_ALIGNMENT_SETTINGS", "available",
           "check_hypotheses", "lk_refine", "load", "ransac_fundamental", "rectify_parallel", "row_alignment_cost",
           "row_alignment_fit", "sad_nearest"]

#: The most samples a fit may draw for one pair (RANSAC's 7-point and the row alignment's 3-match hypotheses):
#: 2^20 covers a 7-point fit at a fifth of inliers with confidence 0.999 (about 540 000); more is a number that
#: never ends (2^31 with confidence 1 ran for minutes), refused instead.
MAX_HYPOTHESES = 2**20
#: The most Gauss–Newton steps a refinement may take (8 by default); a C int underneath, where 2^64 + 1 ran as 1,
#: and 2^31 − 1 steps ran for minutes.
MAX_LK_ITERATIONS = 1000


def check_hypotheses(value: float, name: str) -> None:
    """InputError naming ``name`` unless ``value`` is at most :data:`MAX_HYPOTHESES` (its lower bound and type are
    checked with the other settings)."""
    if value > MAX_HYPOTHESES:
        raise InputError(f"{name}: expected at most {MAX_HYPOTHESES} (2^20) samples per pair, got {value!r}")


declare({
    "lk_refine": ([POINTER, POINTER] + [INT] * 4 + [POINTER] * 4 + [INT, FLOAT, POINTER, POINTER, INT],
                  None),
    "ransac_fundamental": ([POINTER] * 5 + [INT] * 2 + [POINTER] * 4 + [INT], ctypes.c_int),
    "rectify_parallel": ([POINTER] * 5 + [INT] * 3 + [ctypes.c_double] * 2 + [INT] + [POINTER] * 7 + [INT], None),
    "row_alignment_cost": ([POINTER] * 5 + [INT] * 3 + [ctypes.c_double, POINTER, INT], ctypes.c_int),
    "row_alignment_fit": ([POINTER] * 7 + [INT] * 2 + [POINTER] * 6 + [INT], ctypes.c_int),
    "sad_nearest": ([POINTER] * 8 + [FLOAT] + [INT] * 4 + [POINTER] * 4 + [INT], ctypes.c_int),
})


def lk_refine(left: torch.Tensor, right: torch.Tensor, left_xy: torch.Tensor, right_xy: torch.Tensor,
              radius: torch.Tensor, active: torch.Tensor, iterations: int, max_shift_px: float
              ) -> tuple[torch.Tensor, torch.Tensor] | None:
    """``svs_torch.geometry.lk_refinement._refine_lk``'s Gauss–Newton refinement, one match at a time (see the C
    source): ``left``, ``right`` ``(B, 1, H, W)`` float32; ``left_xy``, ``right_xy`` ``(B, K, 2)``, ``radius`` ``(B,
    K)`` float32; ``active`` ``(B, K)`` bool, the rows to refine. Returns the refined right points ``(B, K, 2)`` and
    the weighted NCC at them ``(B, K)`` (0 for inactive rows), or None when the kernel is not available or the
    inputs do not fit its contract."""
    tensors = (left, right, left_xy, right_xy, radius)
    dims = check_shape(left, "left", ["B", 1, "H", "W"])
    b, h, w = dims["B"], dims["H"], dims["W"]
    check_shape(right, "right", [b, 1, h, w])
    k = check_shape(left_xy, "left_xy", [b, "K", 2])["K"]
    check_shape(right_xy, "right_xy", [b, k, 2])
    check_shape(radius, "radius", [b, k])
    check_rows(active, "active", b, k, kinds="bool")
    check_nonempty(left, "left")
    if not isinstance(iterations, int) or not 0 <= iterations <= MAX_LK_ITERATIONS:  # a C int: 2^64 + 1 ran as 1
        raise InputError(f"iterations: expected an int from 0 to {MAX_LK_ITERATIONS}, got {iterations!r}")
    check_number(max_shift_px, "max_shift_px", 0.0)
    # The kernel indexes an image with 32-bit offsets, and clamps a sample at the float32 (W - 1, H - 1), which
    # past 2^24 rounds up to W (a 2 x (2^25 + 4) pair read past the image's end, ASan: heap-buffer-overflow).
    if (not (on_cpu(torch.float32, *tensors) and on_cpu(torch.bool, active))
            or h * w >= 2**31 or max(h, w) > 2**24):
        return None
    library = load("lk_refine")
    if library is None:
        return None
    left, right, left_xy, right_xy, radius, active = (t.contiguous() for t in (*tensors, active))
    refined, correlation = torch.empty(b, k, 2), torch.empty(b, k)
    library.lk_refine(left.data_ptr(), right.data_ptr(), b, h, w, k, left_xy.data_ptr(), right_xy.data_ptr(),
                      radius.data_ptr(), active.data_ptr(), iterations, max_shift_px, refined.data_ptr(),
                      correlation.data_ptr(), torch.get_num_threads())
    return refined, correlation


def sad_nearest(desc_left: torch.Tensor, desc_right: torch.Tensor, valid_left: torch.Tensor,
                valid_right: torch.Tensor, sign_left: torch.Tensor | None = None,
                sign_right: torch.Tensor | None = None, y_left: torch.Tensor | None = None,
                y_right: torch.Tensor | None = None, band_px: float | None = None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """Nearest neighbours by SAD (see the C source): ``desc_left`` ``(B, K, D)``, ``desc_right`` ``(B, K2, D)``
    float32; a candidate pair needs ``valid_left`` ``(B, K)`` and ``valid_right`` ``(B, K2)`` (bool), equal
    ``sign_left`` / ``sign_right`` (int64, optional) and, given ``band_px``, ``|y_left − y_right| ≤ band_px``
    (float32 ``(B, K)``, ``(B, K2)``), as :func:`svs_torch.geometry.matching._allowed`. Returns ``(best, second,
    best_index, back)``: each left row's smallest and second-smallest allowed distance ``(B, K)`` (+inf if
    none), the index of the smallest, and each right descriptor's nearest left row ``(B, K2)``; None when the
    kernel is not available or the inputs do not fit its contract."""
    signs = sign_left is not None
    band = band_px is not None
    dims = check_shape(desc_left, "desc_left", ["B", "K", "D"])
    b, k, d = dims["B"], dims["K"], dims["D"]
    k2 = check_shape(desc_right, "desc_right", [b, "K2", d])["K2"]
    check_rows(valid_left, "valid_left", b, k, kinds="bool")
    check_rows(valid_right, "valid_right", b, k2, kinds="bool")
    if signs != (sign_right is not None) or band and (y_left is None or y_right is None):
        raise InputError("sign_left, sign_right, y_left, y_right: expected both signs or neither, and both rows "
                         "given a band_px")
    for tensor, name, rows in ((sign_left, "sign_left", k), (sign_right, "sign_right", k2)):
        if signs:
            check_rows(tensor, name, b, rows)
    for tensor, name, rows in ((y_left, "y_left", k), (y_right, "y_right", k2)):
        if band:
            check_rows(tensor, name, b, rows, kinds="float")
    if band:
        check_number(band_px, "band_px", 0.0)
    if (not (on_cpu(torch.float32, desc_left, desc_right) and on_cpu(torch.bool, valid_left, valid_right))
            or signs and not on_cpu(torch.int64, sign_left, sign_right)
            or band and not on_cpu(torch.float32, y_left, y_right)):
        return None
    library = load("sad_nearest")
    if library is None:
        return None
    inputs = [t.contiguous() if t is not None else None for t in (
        desc_left, desc_right, valid_left, valid_right, sign_left if signs else None, sign_right if signs else None,
        y_left if band else None, y_right if band else None)]
    pointers = [0 if t is None else t.data_ptr() for t in inputs]
    best, second = torch.empty(b, k), torch.empty(b, k)
    best_index, back = torch.empty(b, k, dtype=torch.int64), torch.empty(b, k2, dtype=torch.int64)
    status = library.sad_nearest(*pointers, band_px if band else 0.0, b, k, k2, d, best.data_ptr(),
                                 second.data_ptr(), best_index.data_ptr(), back.data_ptr(), torch.get_num_threads())
    return None if status != 0 else (best, second, best_index, back)


def row_alignment_cost(params: torch.Tensor, left_y: torch.Tensor, right_x: torch.Tensor, right_y: torch.Tensor,
                       valid: torch.Tensor, threshold_px: float) -> torch.Tensor | None:
    """``svs_torch.geometry.row_alignment._msac_cost`` in one pass per hypothesis (see the C source): ``params``
    ``(B, M, 3)`` float64 (a, b, t_y), NaN where a sample was degenerate; ``left_y``, ``right_x``, ``right_y``
    ``(B, K)`` float64; ``valid`` ``(B, K)`` bool. Returns the cost ``(B, M)`` float64 (+inf for a degenerate
    hypothesis), or None when the kernel is not available or the inputs do not fit its contract."""
    dims = check_shape(params, "params", ["B", "M", 3])
    b, m = dims["B"], dims["M"]
    k = check_shape(left_y, "left_y", [b, "K"])["K"]
    for tensor, name in ((right_x, "right_x"), (right_y, "right_y")):
        check_rows(tensor, name, b, k, kinds="float")
    check_rows(valid, "valid", b, k, kinds="bool")
    check_number(threshold_px, "threshold_px", 0.0)
    if not (on_cpu(torch.float64, params, left_y, right_x, right_y) and on_cpu(torch.bool, valid)):
        return None
    library = load("row_alignment_cost")
    if library is None:
        return None
    params, left_y, right_x, right_y, valid = (t.contiguous() for t in (params, left_y, right_x, right_y, valid))
    cost = torch.empty(b, m, dtype=torch.float64)
    status = library.row_alignment_cost(params.data_ptr(), left_y.data_ptr(), right_x.data_ptr(), right_y.data_ptr(),
                                        valid.data_ptr(), b, m, k, float(threshold_px), cost.data_ptr(),
                                        torch.get_num_threads())
    return None if status != 0 else cost


def rectify_parallel(F: torch.Tensor, points_left: torch.Tensor, points_right: torch.Tensor, inliers: torch.Tensor,
                     image_hw: torch.Tensor, min_inliers: int, max_area_scale: float, max_rotation_deg: float
                     ) -> tuple[torch.Tensor, ...] | None:
    """``svs_torch.geometry.rectification.rectify_uncalibrated`` with ``x_alignment="parallel"``, one pair in one
    pass (see the C source): ``F`` ``(B, 3, 3)`` float32 or float64; ``points_left``, ``points_right`` ``(B, K, 2)``
    of F's dtype; ``inliers`` ``(B, K)`` bool; ``image_hw`` ``(B, 2)`` int64, each at least 1; the config's limits.
    Returns ``(H_left, H_right, status, num_inliers, epipole_left, epipole_right, rms_row_error_px)`` as
    :class:`~svs_torch.geometry.rectification.Rectification` holds them (float tensors in F's dtype), or None when
    the kernel is not available or the inputs do not fit its contract."""
    b = check_shape(F, "F", ["B", 3, 3])["B"]
    k = check_shape(points_left, "points_left", [b, "K", 2])["K"]
    check_shape(points_right, "points_right", [b, k, 2])
    check_rows(inliers, "inliers", b, k, kinds="bool")
    check_rows(image_hw, "image_hw", b, 2)
    if not isinstance(min_inliers, int):
        raise InputError(f"min_inliers: expected an int, got {min_inliers!r}")
    for value, name in ((max_area_scale, "max_area_scale"), (max_rotation_deg, "max_rotation_deg")):
        if not isinstance(value, (int, float)):  # any float: inf is no limit, NaN fails every pair as in torch
            raise InputError(f"{name}: expected a number, got {value!r}")
    dtype = F.dtype
    if (dtype not in (torch.float32, torch.float64) or not on_cpu(dtype, F, points_left, points_right)
            or not on_cpu(torch.bool, inliers) or not on_cpu(torch.int64, image_hw)
            or bool((image_hw < 1).any())):
        return None
    library = load("rectify_parallel")
    if library is None:
        return None
    f64 = torch.float64
    F, points_left, points_right = (t.to(f64).contiguous() for t in (F, points_left, points_right))
    inliers, image_hw = inliers.contiguous(), image_hw.contiguous()
    H_left, H_right = torch.empty(b, 3, 3, dtype=f64), torch.empty(b, 3, 3, dtype=f64)
    epipole_left, epipole_right = torch.empty(b, 3, dtype=f64), torch.empty(b, 3, dtype=f64)
    rms = torch.empty(b, dtype=f64)
    status, num_inliers = torch.empty(b, dtype=torch.int64), torch.empty(b, dtype=torch.int64)
    library.rectify_parallel(F.data_ptr(), points_left.data_ptr(), points_right.data_ptr(), inliers.data_ptr(),
                             image_hw.data_ptr(), b, k, max(-2**62, min(min_inliers, 2**62)),  # an int64 either way
                             float(max_area_scale), float(max_rotation_deg),
                             int(dtype == torch.float32), H_left.data_ptr(), H_right.data_ptr(),
                             epipole_left.data_ptr(), epipole_right.data_ptr(), rms.data_ptr(), status.data_ptr(),
                             num_inliers.data_ptr(), torch.get_num_threads())
    return (H_left.to(dtype), H_right.to(dtype), status, num_inliers, epipole_left.to(dtype), epipole_right.to(dtype),
            rms.to(dtype))


#: The settings :func:`row_alignment_fit` takes, in the order of its C source's ``enum``: those of
#: :class:`~svs_torch.geometry.row_alignment.RowAlignmentConfig` (the roll limit in radians; ``keystone_min_deg``
#: unused without focal lengths).
ROW_ALIGNMENT_SETTINGS = ("threshold_px", "num_hypotheses", "min_inliers", "min_inlier_share", "min_gain",
                          "min_gain_share", "max_roll_rad", "max_scale_change", "max_shift_fraction",
                          "keystone_min_deg", "keystone_min_t")


def row_alignment_fit(points_left: torch.Tensor, points_right: torch.Tensor, valid: torch.Tensor,
                      image_hw: torch.Tensor, pair_seeds: torch.Tensor, focal_px: torch.Tensor | None,
                      settings: dict[str, float]) -> tuple[torch.Tensor, ...] | None:
    """``svs_torch.geometry.row_alignment.fit_row_alignment``'s similarity, and whether a keystone reads, one pair
    at a time (see the C source): ``points_left``, ``points_right`` ``(B, K, 2)`` float64 pixels; ``valid`` ``(B,
    K)`` bool; ``image_hw`` ``(B, 2)`` int64, each at least 1; ``pair_seeds`` ``(B,)`` int64; ``focal_px`` ``(B,)``
    float64 or None (no keystone reading); ``settings`` every name of :data:`ROW_ALIGNMENT_SETTINGS`. Returns
    ``(H_right (B, 3, 3), inliers (B, K) bool before the acceptance, accepted (B,) bool, their count (B,) int64,
    correction_px (B,), reads_turn (B,) bool)``, or None when the kernel is not available or the inputs do not fit
    its contract."""
    dims = check_shape(points_left, "points_left", ["B", "K", 2])
    b, k = dims["B"], dims["K"]
    check_shape(points_right, "points_right", [b, k, 2])
    check_rows(valid, "valid", b, k, kinds="bool")
    check_rows(image_hw, "image_hw", b, 2)
    check_rows(pair_seeds, "pair_seeds", b)
    if focal_px is not None:
        check_rows(focal_px, "focal_px", b, kinds="float")
    table = settings_table(settings, ROW_ALIGNMENT_SETTINGS, {"num_hypotheses": 1, "min_inliers": 0, "min_gain": 0})
    check_hypotheses(settings["num_hypotheses"], "settings['num_hypotheses']")
    floats = (points_left, points_right) if focal_px is None else (points_left, points_right, focal_px)
    if (not (on_cpu(torch.float64, *floats) and on_cpu(torch.bool, valid) and on_cpu(torch.int64, image_hw, pair_seeds))
            or bool((image_hw < 1).any())):
        return None
    library = load("row_alignment_fit")
    if library is None:
        return None
    points_left, points_right, valid, image_hw, pair_seeds = (
        t.contiguous() for t in (points_left, points_right, valid, image_hw, pair_seeds))
    focal = None if focal_px is None else focal_px.contiguous()
    homography, correction = torch.empty(b, 3, 3, dtype=torch.float64), torch.empty(b, dtype=torch.float64)
    inliers, accepted, turn = (torch.empty(*shape, dtype=torch.bool) for shape in ((b, k), (b,), (b,)))
    count = torch.empty(b, dtype=torch.int64)
    status = library.row_alignment_fit(points_left.data_ptr(), points_right.data_ptr(), valid.data_ptr(),
                                       image_hw.data_ptr(), pair_seeds.data_ptr(),
                                       0 if focal is None else focal.data_ptr(), table.data_ptr(), b, k,
                                       homography.data_ptr(), inliers.data_ptr(), accepted.data_ptr(),
                                       count.data_ptr(), correction.data_ptr(), turn.data_ptr(),
                                       torch.get_num_threads())
    return None if status != 0 else (homography, inliers, accepted, count, correction, turn)


#: The settings :func:`ransac_fundamental` takes, in the order of its C source's ``enum`` (each a number; the flags
#: 0 or 1; ``scoring`` 0 for MSAC, 1 for RANSAC's count).
RANSAC_SETTINGS = ("threshold_px", "confidence", "max_iterations", "chunk_size", "scoring", "local_optimization",
                   "preverification", "polish", "lo_steps", "lo_window", "lo_tolerance", "polish_steps",
                   "polish_window", "degenerate_pivot", "fast_pivot", "max_root_determinant", "guard",
                   "preverify_points", "preverify_keep_ratio", "sign_tie")
#: The settings that count something: whole numbers, at least 1 (the steps at least 0).
_RANSAC_COUNTS = {"max_iterations": 1, "chunk_size": 1, "lo_steps": 0, "polish_steps": 0, "preverify_points": 1,
                  "preverify_keep_ratio": 1}


def ransac_fundamental(points_left: torch.Tensor, points_right: torch.Tensor, valid: torch.Tensor,
                       pair_seeds: torch.Tensor, settings: dict[str, float]
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """``svs_torch.geometry.ransac.estimate_fundamental_ransac``'s search, one pair at a time start to finish (see
    the C source): ``points_left``, ``points_right`` ``(B, K, 2)`` float64 pixels, finite where ``valid`` ``(B,
    K)`` (bool); ``pair_seeds`` ``(B,)`` int64; ``settings`` every name of :data:`RANSAC_SETTINGS`. Returns F ``(B,
    3, 3)`` float64 in pixels (unit norm, zero where none was found), found ``(B,)`` bool, the hypotheses drawn
    ``(B,)`` int64 and the inliers ``(B, K)`` bool; None when the kernel is not available or the inputs do not fit
    its contract."""
    dims = check_shape(points_left, "points_left", ["B", "K", 2])
    b, k = dims["B"], dims["K"]
    check_shape(points_right, "points_right", [b, k, 2])
    check_rows(valid, "valid", b, k, kinds="bool")
    check_rows(pair_seeds, "pair_seeds", b)
    values = settings_table(settings, RANSAC_SETTINGS, _RANSAC_COUNTS, low=0.0)
    check_hypotheses(settings["max_iterations"], "settings['max_iterations']")
    if not (on_cpu(torch.float64, points_left, points_right) and on_cpu(torch.bool, valid)
            and on_cpu(torch.int64, pair_seeds)):
        return None
    library = load("ransac_fundamental")
    if library is None:
        return None
    points_left, points_right, valid, pair_seeds = (t.contiguous() for t in (points_left, points_right, valid,
                                                                             pair_seeds))
    fundamental, iterations = torch.empty(b, 3, 3, dtype=torch.float64), torch.empty(b, dtype=torch.int64)
    found, inliers = torch.empty(b, dtype=torch.bool), torch.empty(b, k, dtype=torch.bool)
    status = library.ransac_fundamental(points_left.data_ptr(), points_right.data_ptr(), valid.data_ptr(),
                                        pair_seeds.data_ptr(), values.data_ptr(), b, k, fundamental.data_ptr(),
                                        found.data_ptr(), iterations.data_ptr(), inliers.data_ptr(),
                                        torch.get_num_threads())
    return None if status != 0 else (fundamental, found, iterations, inliers)
