"""The C kernels of the segmentation stage (the ``.c`` sources beside this file) and their wrappers, each the fast path
of a torch function of the stage that stays its reference: see :mod:`svs_torch.core.kernels` for how they are built,
cached and loaded, and what every wrapper promises."""

from __future__ import annotations

import ctypes
import math

import torch

from ...core.checks import check_count, check_dtype, check_instance, check_shape
from ...core.errors import InputError
from ...core.kernels import FLOAT, INT, POINTER, available, declare, load, on_cpu, rows_of
from ...core.kernels.checks import check_rows, settings_table
from ...core.mask_reductions import has_nan

__all__ = ["GROUND_PLANE_SETTINGS", "available", "find_runs", "gray_levels", "ground_plane_fit", "label_counts",
           "label_runs", "load", "median_filter", "nearness_split", "region_interiors", "shift_regions"]

declare({
    "find_runs": ([POINTER] * 2 + [INT] * 2 + [POINTER] * 3 + [INT], ctypes.c_int),
    "gray_levels": ([POINTER] + [INT] * 2 + [POINTER] * 2 + [INT], ctypes.c_int),
    "label_runs": ([POINTER] * 2 + [INT] * 5 + [POINTER] * 3 + [INT], ctypes.c_int),
    "label_counts": ([POINTER] * 2 + [INT] * 3 + [POINTER, INT], ctypes.c_int),
    "median_filter": ([POINTER] + [INT] * 4 + [POINTER, INT], ctypes.c_int),
    "shift_regions": ([POINTER] * 3 + [INT] * 4 + [POINTER, INT], ctypes.c_int),
    "region_interiors": ([POINTER] * 3 + [INT] * 5 + [FLOAT, POINTER, INT], ctypes.c_int),
    "ground_plane_fit": ([POINTER] * 7 + [INT] * 4 + [POINTER] * 5 + [INT] * 2, ctypes.c_int),
    "nearness_split": ([POINTER] * 2 + [INT] * 2 + [POINTER] * 2 + [FLOAT, INT] + [POINTER] * 2 + [INT], ctypes.c_int),
})


def find_runs(foreground: torch.Tensor, value: torch.Tensor | None = None
              ) -> tuple[torch.Tensor, torch.Tensor] | None:
    """:func:`svs_torch.segmentation.components._find_runs` in two passes per row (see the C source): the flat start and
    end (inclusive) positions ``(R,)`` int64 of the runs of ``foreground`` ``(..., W)`` bool in raster order, a run also
    ending where ``value`` (int64, its shape) changes. None when the kernel is not available or the inputs do not
    fit its contract."""
    check_instance(foreground, "foreground", torch.Tensor)
    if foreground.dim() < 1:
        raise InputError(f"foreground: expected (..., W), got {tuple(foreground.shape)}")
    if value is not None:
        check_shape(value, "value", list(foreground.shape))
    if not on_cpu(torch.bool, foreground) or value is not None and not on_cpu(torch.int64, value):
        return None
    library = load("find_runs")
    if library is None:
        return None
    rows, width = rows_of(foreground)
    foreground = foreground.contiguous()
    value = None if value is None else value.contiguous()
    value_ptr = 0 if value is None else value.data_ptr()
    counts = torch.empty(rows, dtype=torch.int64)
    threads = torch.get_num_threads()
    library.find_runs(foreground.data_ptr(), value_ptr, rows, width, counts.data_ptr(), 0, 0, threads)
    total = int(counts.sum())
    first = counts.cumsum(0) - counts  # each row's first output slot
    start, end = torch.empty(total, dtype=torch.int64), torch.empty(total, dtype=torch.int64)
    library.find_runs(foreground.data_ptr(), value_ptr, rows, width, first.data_ptr(), start.data_ptr(),
                      end.data_ptr(), threads)
    return start, end


def gray_levels(image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
    """:func:`svs_torch.segmentation.threshold.gray_levels` and :func:`~svs_torch.segmentation.threshold.gray_histogram`
    in one read of each image (see the C source): ``image`` ``(B, 1, H, W)`` float32 in [0, 1] → the uint8 levels
    ``(B, 1, H, W)`` and the histograms ``(B, 256)`` int64, the torch path's values. None when the kernel is not
    available or the input does not fit its contract."""
    check_shape(image, "image", ["B", 1, "H", "W"])
    if not on_cpu(torch.float32, image):
        return None
    library = load("gray_levels")
    if library is None:
        return None
    image = image.detach().contiguous()
    b = image.shape[0]
    levels = torch.empty(image.shape, dtype=torch.uint8)
    histogram = torch.empty(b, 256, dtype=torch.int64)
    status = library.gray_levels(image.data_ptr(), b, image[0].numel() if b else 0, levels.data_ptr(),
                                 histogram.data_ptr(), torch.get_num_threads())
    return None if status != 0 else (levels, histogram)


def _check_runs(start: torch.Tensor, end: torch.Tensor, batch: int, height: int, width: int,
                connectivity: int) -> None:
    """:func:`label_runs`' contract: runs inside the grid, in raster order, each within one row (as
    :func:`find_runs` gives them); the two int64 ``(R,)`` checks cost a few passes over R runs, not the grid."""
    if connectivity not in (4, 8):
        raise InputError(f"connectivity: expected 4 or 8, got {connectivity!r}")
    if not all(isinstance(v, int) and v >= 0 for v in (batch, height, width)):
        raise InputError(f"batch, height, width: expected non-negative ints, got {batch!r}, {height!r}, {width!r}")
    if batch * height * width >= 2**40:  # the label image it allocates: 2^40 int64 labels is 8 TiB
        raise InputError(f"batch, height, width: expected a grid under 2^40 pixels, got {batch} x {height} x {width}")
    r = check_shape(start, "start", ["R"])["R"]
    check_rows(end, "end", r)
    if r == 0 or not on_cpu(torch.int64, start, end):  # other dtypes are left to the torch path
        return
    row_start = start - start % width if width else start
    bad = ((start < 0) | (end < start) | (end >= batch * height * width) | (end >= row_start + width)).any()
    if bool(bad) or bool((start[1:] <= end[:-1]).any()):
        raise InputError(f"start, end: expected runs in raster order inside one row each of the {batch} x {height} x "
                         f"{width} grid (as find_runs gives them)")


def label_runs(start: torch.Tensor, end: torch.Tensor, batch: int, height: int, width: int, connectivity: int
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """:func:`svs_torch.segmentation.components._label_runs` and ``_paint`` by one union-find sweep per image (see the C
    source): from the runs' flat ``start`` and ``end`` ``(R,)`` int64 of a ``(batch, height, width)`` grid, each
    run's label ``(R,)``, each image's number of labels ``(batch,)`` and the label image ``(batch, 1, height,
    width)``, all int64. None when the kernel is not available or the inputs do not fit its contract."""
    _check_runs(start, end, batch, height, width, connectivity)
    if not on_cpu(torch.int64, start, end):
        return None
    library = load("label_runs")
    if library is None:
        return None
    start, end = start.contiguous(), end.contiguous()
    run_label = torch.empty_like(start)
    num_labels = torch.empty(batch, dtype=torch.int64)
    labels = torch.empty(batch, 1, height, width, dtype=torch.int64)
    status = library.label_runs(start.data_ptr(), end.data_ptr(), start.numel(), batch, height, width, connectivity,
                                run_label.data_ptr(), num_labels.data_ptr(), labels.data_ptr(),
                                torch.get_num_threads())
    return None if status != 0 else (run_label, num_labels, labels)



#: The largest window side :func:`median_filter` takes: over 7×7 each step of its tracked median reads all K² values
#: of the window (up to 7×7 a selection network runs instead), so a larger window is left to the torch path.
MAX_MEDIAN_WINDOW = 15


def label_counts(labels: torch.Tensor, flags: torch.Tensor, slots: int) -> torch.Tensor | None:
    """:func:`svs_torch.segmentation.nearness_regions._label_counts` in one pass a pair (see the C source):
    ``labels`` ``(B, P)`` int64 in ``[0, slots]``, ``flags`` ``(B, P)`` bool → ``(B, slots)`` int64, how many
    flagged pixels each label 1 … ``slots`` holds, the torch path's counts exactly. None when the kernel is not
    available or the inputs are of another kind; a label outside ``[0, slots]`` is named."""
    b = check_shape(labels, "labels", ["B", "P"])["B"]
    check_shape(flags, "flags", list(labels.shape))
    check_count(slots, "slots", 0)
    if not (on_cpu(torch.int64, labels) and on_cpu(torch.bool, flags)):
        return None
    library = load("label_counts")
    if library is None:
        return None
    labels, flags = labels.contiguous(), flags.contiguous()
    counts = torch.empty(b, slots, dtype=torch.int64)
    status = library.label_counts(labels.data_ptr(), flags.data_ptr(), b, labels.shape[1], slots, counts.data_ptr(),
                                  torch.get_num_threads())
    if status == -2:
        raise InputError(f"labels: expected labels in [0, {slots}], got values from {int(labels.min())} to "
                         f"{int(labels.max())}")
    return None if status != 0 else counts


def median_filter(image: torch.Tensor, window: int) -> torch.Tensor | None:
    """The ``window``-sided median of every pixel of ``image`` ``(B, 1, H, W)`` float32 over its window, edges
    replicated, the element of rank ``(window² − 1) / 2`` (``torch.median``'s; see the C source): the values of
    :func:`svs_torch.segmentation.nearness_denoise._median_filter`'s torch path. None when the kernel is not
    available or the input does not fit its contract (another dtype or device, NaN values, a window over
    ``MAX_MEDIAN_WINDOW``)."""
    dims = check_shape(image, "image", ["B", 1, "H", "W"])
    if not (isinstance(window, int) and window >= 1 and window % 2 == 1):
        raise InputError(f"window: expected an odd positive int, got {window!r}")
    if window > MAX_MEDIAN_WINDOW or not on_cpu(torch.float32, image):
        return None
    if image.numel() == 0 or has_nan(image):  # the tracking compares by <, which NaN breaks
        return None
    library = load("median_filter")
    if library is None:
        return None
    image = image.detach().contiguous()
    out = torch.empty_like(image)
    status = library.median_filter(image.data_ptr(), dims["B"], dims["H"], dims["W"], window, out.data_ptr(),
                                   torch.get_num_threads())
    return None if status != 0 else out


def shift_regions(labels: torch.Tensor, kept_labels: torch.Tensor, shift_px: torch.Tensor) -> torch.Tensor | None:
    """:func:`svs_torch.segmentation.nearness_regions.shift_regions_to_right` one row at a time (see the C source):
    ``labels`` ``(B, 1, H, W)`` int64, ``kept_labels`` ``(B, N)`` int64, ``shift_px`` ``(B, N)`` float32 → the
    right view's labels ``(B, 1, H, W)`` int64, the torch path's exactly. None when the kernel is not available or
    the inputs do not fit its contract (another dtype, or a shift that is not finite, which the torch path rounds
    to an integer its own way)."""
    dims = check_shape(labels, "labels", ["B", 1, "H", "W"])
    b, h, w = dims["B"], dims["H"], dims["W"]
    n = check_rows(kept_labels, "kept_labels", b, "N").shape[1]
    check_shape(shift_px, "shift_px", [b, n])
    if not (on_cpu(torch.int64, labels, kept_labels) and on_cpu(torch.float32, shift_px)):
        return None
    if not bool(shift_px.isfinite().all()):
        return None
    library = load("shift_regions")
    if library is None:
        return None
    labels, kept_labels, shift_px = (t.contiguous() for t in (labels, kept_labels, shift_px))
    out = torch.empty_like(labels)
    status = library.shift_regions(labels.data_ptr(), kept_labels.data_ptr(), shift_px.data_ptr(), b, h, w, n,
                                   out.data_ptr(), torch.get_num_threads())
    return None if status != 0 else out


def region_interiors(labels: torch.Tensor, kept_labels: torch.Tensor, radius_px: int, pairs: torch.Tensor,
                     min_share: float) -> torch.Tensor | None:
    """:func:`svs_torch.segmentation.interior.region_interiors` a pair at a time (see the C source): ``labels``
    ``(B, 1, H, W)`` int64, ``kept_labels`` ``(B, N)`` int64, ``radius_px`` an int >= 0, ``pairs`` ``(B,)`` bool,
    ``min_share`` a real number → the labels with the cut regions' borders set to 0, the torch path's exactly.
    None when the kernel is not available or the inputs do not fit its contract (another dtype, a share that is
    not a real number)."""
    dims = check_shape(labels, "labels", ["B", 1, "H", "W"])
    b, h, w = dims["B"], dims["H"], dims["W"]
    n = check_shape(kept_labels, "kept_labels", [b, "N"])["N"]
    check_shape(pairs, "pairs", [b])
    if isinstance(radius_px, bool) or not isinstance(radius_px, int) or radius_px < 0:
        raise InputError(f"radius_px: expected an int >= 0, got {radius_px!r}")
    if isinstance(min_share, bool) or not isinstance(min_share, (int, float)):
        return None
    if not on_cpu(torch.int64, labels, kept_labels) or not on_cpu(torch.bool, pairs):
        return None
    library = load("region_interiors")
    if library is None:
        return None
    labels, kept_labels = labels.contiguous(), kept_labels.contiguous()
    pair_bytes = pairs.contiguous().view(torch.uint8)  # nonzero is True, as torch reads a bool
    out = torch.empty_like(labels)
    status = library.region_interiors(labels.data_ptr(), kept_labels.data_ptr(), pair_bytes.data_ptr(), b, h, w, n,
                                      min(radius_px, max(h, w)), float(min_share), out.data_ptr(),
                                      torch.get_num_threads())
    return None if status != 0 else out


#: The settings :func:`ground_plane_fit` takes, in the order of its C source's ``enum``: the grid's stride, the
#: least span in map pixels, ``GroundPlaneConfig.tolerance_fraction``, the first sampled row ``(1 −
#: lower_rows_fraction) · H``, the tangents of the roll and pitch limits, the camera heights, the behind and inlier
#: shares, and the map's centre column and row.
GROUND_PLANE_SETTINGS = ("stride", "min_span_px", "tolerance_fraction", "lower_row", "tan_roll", "min_height_m",
                         "max_height_m", "tan_pitch", "max_behind_share", "min_share", "centre_x", "centre_y")


def ground_plane_fit(disparity: torch.Tensor, measured: torch.Tensor, baseline_m: torch.Tensor,
                     tolerance_px: torch.Tensor, focal_px: torch.Tensor | None, draws: torch.Tensor,
                     settings: dict[str, float], cells: torch.Tensor | None = None,
                     cell_min_px: int = 0) -> tuple[torch.Tensor, ...] | None:
    """:func:`svs_torch.segmentation.ground_plane.fit_ground_plane` a pair at a time (see the C source):
    ``disparity`` ``(B, 1, H, W)`` float32, ``measured`` ``(B, 1, H, W)`` bool; ``baseline_m`` and ``tolerance_px``
    (in the map's pixels) ``(B,)`` float32; ``focal_px`` ``(B,)`` float32 or None (no pitch limit); ``draws``
    ``(N, 5)`` float64 uniforms, the samples; ``settings`` every name of :data:`GROUND_PLANE_SETTINGS`; ``cells``
    ``(B,)`` bool or None: the pairs whose samples are drawn from their cells' medians over at least ``cell_min_px``
    measured pixels (:func:`svs_torch.segmentation.ground_plane_grid.cell_medians`). Returns the
    plane's coefficients ``(B, 3)``, found ``(B,)`` bool, the camera height ``(B,)`` and the mask ``(B, 1, H, W)``
    bool; None when the kernel is not available or the inputs do not fit its contract (a NaN focal length)."""
    dims = check_shape(disparity, "disparity", ["B", 1, "H", "W"])
    b, h, w = dims["B"], dims["H"], dims["W"]
    check_shape(measured, "measured", [b, 1, h, w])
    check_rows(baseline_m, "baseline_m", b, kinds="float")
    check_rows(tolerance_px, "tolerance_px", b, kinds="float")
    if focal_px is not None:
        check_rows(focal_px, "focal_px", b, kinds="float")
    if cells is not None:
        check_rows(cells, "cells", b, kinds="bool")
    check_count(cell_min_px, "cell_min_px")
    n = check_shape(draws, "draws", ["N", 5])["N"]
    check_dtype(draws, "draws", "float")
    table = settings_table(settings, GROUND_PLANE_SETTINGS, {"stride": 1})
    # The C code casts a draw times a count, and the lower row, to integers: undefined for NaN or past 2^63 (UBSan
    # "nan is outside the range of representable values of type 'long int'"); it squares the stride in int64.
    if not bool(((draws >= 0) & (draws <= 1)).all()):
        raise InputError("draws: expected uniforms in [0, 1] (torch.rand's)")
    for key, power in (("lower_row", 53), ("stride", 31)):
        if abs(settings[key]) > 2**power:
            raise InputError(f"settings[{key!r}]: expected a value within ±2^{power}, got {settings[key]!r}")
    floats = (disparity, baseline_m, tolerance_px) + (() if focal_px is None else (focal_px,))
    if (not (on_cpu(torch.float32, *floats) and on_cpu(torch.bool, measured) and on_cpu(torch.float64, draws))
            or focal_px is not None and bool(focal_px.isnan().any())
            or cells is not None and not on_cpu(torch.bool, cells)):
        return None
    library = load("ground_plane_fit")
    if library is None:
        return None
    disparity, measured, baseline_m, tolerance_px, draws = (
        t.contiguous() for t in (disparity, measured, baseline_m, tolerance_px, draws))
    focal = None if focal_px is None else focal_px.contiguous()
    cells = None if cells is None else cells.contiguous().view(torch.uint8)
    plane, height = torch.empty(b, 3), torch.empty(b)
    found, mask = torch.empty(b, dtype=torch.bool), torch.empty(b, 1, h, w, dtype=torch.bool)
    status = library.ground_plane_fit(disparity.data_ptr(), measured.view(torch.uint8).data_ptr(),
                                      baseline_m.data_ptr(), tolerance_px.data_ptr(),
                                      0 if focal is None else focal.data_ptr(), draws.data_ptr(), table.data_ptr(),
                                      b, h, w, n, plane.data_ptr(), found.data_ptr(), height.data_ptr(),
                                      mask.data_ptr(), 0 if cells is None else cells.data_ptr(), cell_min_px,
                                      torch.get_num_threads())
    return None if status != 0 else (plane, found, height, mask)


def nearness_split(disparity: torch.Tensor, exclude: torch.Tensor | None, clip_high: torch.Tensor,
                   clip_retry: torch.Tensor, min_near_share: float) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The split of :func:`svs_torch.segmentation.nearness_split.nearness_split` (see the C source): ``disparity``
    ``(B, P)`` float32, ``exclude`` ``(B, P)`` bool or None, the maps clipped at ``clip_high`` ``(B,)`` (their
    99.5th percentiles) and, where the split leaves less than ``min_near_share`` of the pixels near, at
    ``clip_retry`` ``(B,)`` (their 90th) instead. Returns the split ``(B,)`` float32 and which pairs' was taken again
    ``(B,)`` bool, the torch path's values; None when the kernel is not available or the inputs do not fit its
    contract (a value that is NaN or infinite, an empty map or batch)."""
    b, p = check_shape(disparity, "disparity", ["B", "P"]).values()
    if exclude is not None:
        check_shape(exclude, "exclude", [b, p])
    check_rows(clip_high, "clip_high", b, kinds="float")
    check_rows(clip_retry, "clip_retry", b, kinds="float")
    if not isinstance(min_near_share, (int, float)) or math.isnan(min_near_share):
        raise InputError(f"min_near_share: expected a number, got {min_near_share!r}")
    if (b == 0 or p == 0 or not on_cpu(torch.float32, disparity, clip_high, clip_retry)
            or exclude is not None and not on_cpu(torch.bool, exclude)):
        return None
    library = load("nearness_split")
    if library is None:
        return None
    disparity, clip_high, clip_retry = (t.detach().contiguous() for t in (disparity, clip_high, clip_retry))
    exclude = None if exclude is None else exclude.contiguous()
    split, retaken = torch.empty(b), torch.empty(b, dtype=torch.bool)
    left_out = 0 if exclude is None else exclude.view(torch.uint8).data_ptr()
    status = library.nearness_split(disparity.data_ptr(), left_out, b, p, clip_high.data_ptr(),
                                    clip_retry.data_ptr(), float(min_near_share), int(min_near_share > 0),
                                    split.data_ptr(), retaken.data_ptr(), torch.get_num_threads())
    return None if status != 0 else (split, retaken)
