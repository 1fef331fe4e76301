"""The C kernels of the depth stage (the ``.c`` sources beside this file) and their wrappers, each the fast path of
a torch function of the stage that stays its reference: see :mod:`svs_torch.core.kernels` for how they are built,
cached and loaded, and what every wrapper promises."""

from __future__ import annotations

import ctypes

import torch

from ...core.checks import check_count, check_dtype, check_shape
from ...core.errors import InputError
from ...core.kernels import FLOAT, INT, POINTER, available, declare, load, on_cpu, rows_of
from ...core.kernels.checks import (canonical_bool, check_boxes, check_counts, check_image_hw, check_nonempty,
                                   check_number, check_row_fill, check_rows)
from ...core.mask_reductions import has_nan

__all__ = ["available", "block_match", "fill_invalid_rows", "labelled_select", "load", "object_depths",
           "region_medians", "sad_volume", "semi_global_columns", "semi_global_rows", "winner_statistics"]

declare({
    "block_match": ([POINTER] * 3 + [INT, FLOAT] + [INT] * 5 + [POINTER] * 5 + [FLOAT] * 3 + [INT]
                    + [POINTER, INT] + [POINTER] * 3 + [INT] * 2, ctypes.c_int),
    "fill_invalid_rows": ([POINTER] * 2 + [INT] * 2 + [POINTER] * 2 + [INT], ctypes.c_int),
    "labelled_select": ([POINTER] * 4 + [INT] * 4 + [POINTER] * 3 + [INT], ctypes.c_int),
    "region_medians": ([POINTER] * 2 + [INT] * 3 + [POINTER] * 2 + [INT], ctypes.c_int),
    "semi_global_columns": ([POINTER] + [INT] * 4 + [POINTER] * 3 + [INT], ctypes.c_int),
    "sad_volume": ([POINTER] * 2 + [INT] * 5 + [POINTER] * 4 + [INT], ctypes.c_int),
    "semi_global_rows": ([POINTER] + [INT] * 4 + [POINTER] * 6 + [INT], ctypes.c_int),
    "winner_statistics": ([POINTER] * 2 + [INT] * 4 + [POINTER] * 4 + [INT], ctypes.c_int),
    "object_depths": ([POINTER] * 3 + [INT] * 3 + [POINTER] * 2 + [INT] + [POINTER] * 3 + [INT, POINTER, INT]
                      + [POINTER] * 5 + [INT], ctypes.c_int),
})


#: Where :func:`block_match` takes its levels from (the C source's SOURCE_ constants).
BLOCK_MATCH_SOURCES = {"levels": 0, "raw": 1, "xsobel": 2}


#: Rows of output per task: enough to amortise the K rows each band sums before its window can slide, small
#: enough that one pair splits across threads (the B = 1 ``guide`` case).
BAND_ROWS = 48


def band_rows(height: int, batch: int, threads: int) -> int:
    """Rows per task for boxes up to ``height`` rows over ``batch`` pairs and ``threads`` threads: about
    :data:`BAND_ROWS`, but where the pairs are fewer than the threads, the bands of a pair are made a multiple of
    the threads, of equal height. Why: at B = 1 (``guide``) a 240-row view made 5 bands of 48 for 2 threads, and
    the one that took 3 set the call's time; 6 bands of 40 share it evenly (``tests/core/test_kernels.py``: the
    same values at any band height)."""
    if batch >= threads or height <= 0:
        return BAND_ROWS
    bands = -(-height // BAND_ROWS)
    bands = -(-bands // threads) * threads
    return max(1, -(-height // bands))


def block_match(left: torch.Tensor, right: torch.Tensor, texture: torch.Tensor | bool | None, window_size: int,
                boxes: torch.Tensor, min_disparity: torch.Tensor, counts: torch.Tensor, image_hw: torch.Tensor,
                lower_is_limit: torch.Tensor, uniqueness_ratio: float, lr_max_diff_px: float | None,
                texture_min: float, whole_range_in_view: bool, source: str = "levels",
                prefilter_cap: float = 0.0, mask: torch.Tensor | None = None, mask_margin_px: int = 0,
                best_cost: bool = False) -> tuple[torch.Tensor, ...] | None:
    """``svs_torch.depth.block_matching._match_box`` of every pair at its own box and range, the kernel's contract (see
    the C source). With ``source="levels"``: ``left``, ``right`` ``(B, H, W)`` float32 pre-filtered images holding
    whole numbers in [−255, 255] (:func:`svs_torch.depth.dense.quantize_levels`: then every cost is exact and the
    result is the torch path's bit for bit); ``texture`` ``(B, H, W)`` float32 |x-Sobel| of the left image, or
    None (no texture rule). With ``source="raw"`` or ``"xsobel"``: ``left``, ``right`` are the images themselves
    and the kernel makes the levels a row at a time, ``quantize_levels`` of the image or of its
    ``prefilter_xsobel`` at ``prefilter_cap``, the same values without whole pre-filtered images in memory, and
    ``texture`` is True (the texture rule, on the left image's clipped x-Sobel) or False / None;
    ``boxes`` ``(B, 4)`` x0, y0, width, height; ``min_disparity``, ``counts`` ``(B,)``; ``image_hw`` ``(B, 2)``;
    ``lower_is_limit`` ``(B,)`` bool; the rules' parameters as in :class:`svs_torch.depth.dense.DenseConfig`
    (``texture_min`` is the least window sum); ``mask`` ``(B, H, W)`` bool or None: where depth is wanted, then
    only the pixels within ``mask_margin_px`` columns of their row's mask span are computed
    (:func:`svs_torch.depth.dense.wanted_pixels`), each with the value the whole box gives it.

    Returns the disparity ``(B, H, W)`` float32 (0 where not valid) and ``valid`` ``(B, H, W)`` bool, and with
    ``best_cost`` each computed pixel's winning SAD (kept or not; +inf: no candidate; NaN where not computed);
    None when the kernel is not available or the inputs do not fit its contract."""
    if source not in BLOCK_MATCH_SOURCES:
        raise InputError(f"source: expected one of {sorted(BLOCK_MATCH_SOURCES)}, got {source!r}")
    levels = source == "levels"
    if (texture is True) if levels else isinstance(texture, torch.Tensor):
        raise InputError("texture: expected a tensor or None with source 'levels', a bool with the raw sources")
    tensors = (left, right, texture) if isinstance(texture, torch.Tensor) else (left, right)
    if not on_cpu(torch.float32, *tensors) or mask is not None and not on_cpu(torch.bool, mask):
        return None
    b, h, w = _check_block_match(left, right, texture, mask, window_size, boxes, min_disparity, counts, image_hw,
                                 lower_is_limit, uniqueness_ratio, lr_max_diff_px, texture_min, prefilter_cap,
                                 mask_margin_px)
    library = load("block_match")
    if library is None:
        return None
    left, right = left.contiguous(), right.contiguous()
    textured = texture is not None and texture is not False
    texture = texture.contiguous() if isinstance(texture, torch.Tensor) else None
    per_pair = [v.to(torch.int64).contiguous() for v in (boxes, min_disparity, counts, image_hw)]
    lower = lower_is_limit.to(torch.uint8).contiguous()
    if mask is not None:
        mask = mask.contiguous().view(torch.uint8)  # bool is one byte of 0 or 1: read as it is
    disparity = torch.zeros(b, h, w)
    valid = torch.zeros(b, h, w, dtype=torch.uint8)
    costs = torch.full((b, h, w), torch.nan) if best_cost else None
    threads = torch.get_num_threads()
    # The factors are made in double and rounded to float32, as torch does with a Python scalar.
    status = library.block_match(
        left.data_ptr(), right.data_ptr(), None if texture is None else texture.data_ptr(),
        BLOCK_MATCH_SOURCES[source], prefilter_cap, int(textured), b, h, w, window_size,
        *(v.data_ptr() for v in per_pair), lower.data_ptr(),
        1 + uniqueness_ratio if uniqueness_ratio > 0 else 0.0, -1.0 if lr_max_diff_px is None else lr_max_diff_px,
        texture_min, int(whole_range_in_view), None if mask is None else mask.data_ptr(), mask_margin_px,
        disparity.data_ptr(), valid.data_ptr(), None if costs is None else costs.data_ptr(), threads,
        band_rows(int(per_pair[0][:, 3].max()) if b else 0, b, threads))
    if status != 0:
        return None
    return (disparity, valid.bool()) if costs is None else (disparity, valid.bool(), costs)


#: The dense kernel keeps disparity indices in its 16-bit cost type (block_match.c): at most 65534 disparities.
MAX_DISPARITIES = 65534
MAX_WINDOW = 511  #: the largest SAD window (DenseConfig's, dense.working_window's): scratch grows with its square


def _check_block_match(left, right, texture, mask, window_size, boxes, min_disparity, counts, image_hw,
                       lower_is_limit, uniqueness_ratio, lr_max_diff_px, texture_min, prefilter_cap,
                       mask_margin_px) -> tuple[int, int, int]:
    """:func:`block_match`'s contract (see there), raising :class:`InputError`: returns B, H, W."""
    dims = check_shape(left, "left", ["B", "H", "W"])
    b, h, w = dims["B"], dims["H"], dims["W"]
    for tensor, name in ((right, "right"), (texture, "texture"), (mask, "mask")):
        if isinstance(tensor, torch.Tensor):
            check_shape(tensor, name, [b, h, w])
    check_nonempty(left, "left")
    if type(window_size) is not int or not 1 <= window_size <= MAX_WINDOW or window_size % 2 == 0:  # True ran as 1
        raise InputError(f"window_size: expected an odd int from 1 to {MAX_WINDOW}, got {window_size!r}")
    check_boxes(boxes, b, h, w)
    check_rows(min_disparity, "min_disparity", b)
    check_counts(counts, "counts", b, MAX_DISPARITIES)
    check_image_hw(image_hw, b, h, w)
    check_rows(lower_is_limit, "lower_is_limit", b, kinds="bool")
    check_number(uniqueness_ratio, "uniqueness_ratio", 0.0)
    if lr_max_diff_px is not None:
        check_number(lr_max_diff_px, "lr_max_diff_px", 0.0)
    check_number(texture_min, "texture_min")
    check_number(prefilter_cap, "prefilter_cap", 0.0)
    if not isinstance(mask_margin_px, int) or not 0 <= mask_margin_px < 2**31:  # column sums in int64
        raise InputError(f"mask_margin_px: expected an int from 0 to 2^31 - 1, got {mask_margin_px!r}")
    return b, h, w


def labelled_select(values: torch.Tensor, labels: torch.Tensor, slots: torch.Tensor, q: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """The order statistics of :func:`svs_torch.depth.quantiles.labelled_quantile` by selection (see the C source):
    ``values`` ``(B, P)`` float32 without NaN, ``labels`` ``(B, P)`` and ``slots`` ``(B, N)`` int64, quantiles
    ``q`` ``(Q,)`` float32. Returns ``(count, below, above)``: each slot's member count ``(B, N)`` and the
    members of rank ``floor`` / ``ceil`` of ``q · (count − 1)`` ``(B, N, Q)`` (0 for an empty slot); None when
    the kernel is not available or the inputs do not fit its contract."""
    dims = check_shape(values, "values", ["B", "P"])
    b, p = dims["B"], dims["P"]
    check_rows(labels, "labels", b, p)
    n = check_rows(slots, "slots", b, "N").shape[1]
    k = check_shape(q, "q", ["Q"])["Q"]
    if q.numel() and not bool(((q >= 0) & (q <= 1)).all()):  # NaN too: the kernel casts q · (count − 1) to int
        raise InputError(f"q: expected quantiles in [0, 1], got {q.tolist()}")
    if not (on_cpu(torch.float32, values, q) and on_cpu(torch.int64, labels, slots)):
        return None
    if has_nan(values):  # the selection orders by <, which NaN breaks: the torch path sorts them last
        return None
    library = load("labelled_select")
    if library is None:
        return None
    values, labels, slots, q = (t.contiguous() for t in (values, labels, slots, q))
    count = torch.empty(b, n, dtype=torch.int64)
    below, above = torch.empty(b, n, k), torch.empty(b, n, k)
    status = library.labelled_select(values.data_ptr(), labels.data_ptr(), slots.data_ptr(), q.data_ptr(), b, p, n,
                                     k, count.data_ptr(), below.data_ptr(), above.data_ptr(), torch.get_num_threads())
    return None if status != 0 else (count, below, above)


def region_medians(values: torch.Tensor, labels: torch.Tensor, num_labels: int
                   ) -> tuple[torch.Tensor, torch.Tensor] | None:
    """:func:`svs_torch.depth.quantiles.region_lower_median` by selection (see the C source): ``values`` ``(B, P)``
    float32 without NaN, ``labels`` ``(B, P)`` int64 in ``[0, num_labels]``. Returns each label's member count and lower
    median ``(B, num_labels)`` (0 for an empty label); None when the kernel is not available or the inputs do not
    fit its contract."""
    dims = check_shape(values, "values", ["B", "P"])
    b, p = dims["B"], dims["P"]
    check_rows(labels, "labels", b, p)
    check_count(num_labels, "num_labels", 0, most=max(p, 65536))  # a slot a label, as region_properties: 2^31 failed
    if not (on_cpu(torch.float32, values) and on_cpu(torch.int64, labels)):
        return None
    if labels.numel() and not (int(labels.min()) >= 0 and int(labels.max()) <= num_labels):
        raise InputError(f"labels: expected labels in [0, {num_labels}], got [{int(labels.min())}, "
                         f"{int(labels.max())}]")
    if has_nan(values):  # the selection orders by <, which NaN breaks: the torch path sorts them last
        return None
    library = load("region_medians")
    if library is None:
        return None
    values, labels = values.detach().contiguous(), labels.contiguous()
    count = torch.empty(b, num_labels, dtype=torch.int64)
    median = torch.empty(b, num_labels)
    status = library.region_medians(values.data_ptr(), labels.data_ptr(), b, p, num_labels, count.data_ptr(),
                                    median.data_ptr(), torch.get_num_threads())
    return None if status != 0 else (count, median)


def fill_invalid_rows(disparity: torch.Tensor, valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
    """:func:`svs_torch.depth.block_matching.fill_invalid_rows` in two passes per row (see the C source), bit for bit:
    ``disparity`` ``(..., W)`` float32, ``valid`` of its shape, bool. Returns the filled disparity and where a
    fill was possible; None when the kernel is not available or the inputs do not fit its contract."""
    check_row_fill(disparity, valid)
    if not (on_cpu(torch.float32, disparity) and on_cpu(torch.bool, valid)):
        return None
    library = load("fill_invalid_rows")
    if library is None:
        return None
    rows, width = rows_of(disparity)
    disparity, valid = disparity.contiguous(), valid.contiguous()
    filled, reachable = torch.empty_like(disparity), torch.empty_like(valid)
    status = library.fill_invalid_rows(disparity.data_ptr(), valid.data_ptr(), rows, width, filled.data_ptr(),
                                       reachable.data_ptr(), torch.get_num_threads())
    return None if status != 0 else (filled, reachable)


def semi_global_columns(costs: torch.Tensor, p1: torch.Tensor, p2: torch.Tensor) -> torch.Tensor | None:
    """``svs_torch.depth.semi_global._scan_columns_torch`` (see the C source), bit for bit: ``costs``
    ``(B, D, H, W)`` float32, ``p1``, ``p2`` ``(B,)`` float32. Returns the paths down and up the rows, summed;
    None when the kernel is not available or the inputs do not fit its contract."""
    dims = check_shape(costs, "costs", ["B", "D", "H", "W"])
    check_shape(p1, "p1", [dims["B"]])
    check_shape(p2, "p2", [dims["B"]])
    if dims["D"] < 1 or not on_cpu(torch.float32, costs, p1, p2):  # D = 0 crashed the kernel: the torch path's
        return None
    library = load("semi_global_columns")
    if library is None:
        return None
    costs, p1, p2 = costs.contiguous(), p1.contiguous(), p2.contiguous()
    out = torch.empty_like(costs)
    status = library.semi_global_columns(costs.data_ptr(), *costs.shape, p1.data_ptr(), p2.data_ptr(),
                                         out.data_ptr(), torch.get_num_threads())
    return None if status != 0 else out


def semi_global_rows(costs: torch.Tensor, p1: torch.Tensor, p2: torch.Tensor, columns: torch.Tensor
                     ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]] | None:
    """The rows' paths of :mod:`svs_torch.depth.semi_global` added to ``columns`` (:func:`semi_global_columns` of
    the same ``costs``), and the sum's winner (see the C source), bit for bit: ``costs``, ``columns``
    ``(B, D, H, W)`` float32, ``p1``, ``p2`` ``(B,)`` float32. Returns the aggregated volume and its (min, first
    index) over D, ``(B, H, W)`` each; None when the kernel is not available or the inputs do not fit its contract."""
    dims = check_shape(costs, "costs", ["B", "D", "H", "W"])
    check_shape(columns, "columns", list(costs.shape))
    check_shape(p1, "p1", [dims["B"]])
    check_shape(p2, "p2", [dims["B"]])
    if dims["D"] < 1 or not on_cpu(torch.float32, costs, p1, p2, columns):
        return None
    library = load("semi_global_rows")
    if library is None:
        return None
    costs, p1, p2, columns = costs.contiguous(), p1.contiguous(), p2.contiguous(), columns.contiguous()
    out = torch.empty_like(costs)
    low = costs.new_empty(dims["B"], dims["H"], dims["W"])
    best = torch.empty(dims["B"], dims["H"], dims["W"], dtype=torch.int64)
    status = library.semi_global_rows(costs.data_ptr(), *costs.shape, p1.data_ptr(), p2.data_ptr(), columns.data_ptr(),
                                      out.data_ptr(), low.data_ptr(), best.data_ptr(), torch.get_num_threads())
    return None if status != 0 else (out, (low, best))


def winner_statistics(costs: torch.Tensor, best: torch.Tensor, uniqueness: bool, right: bool
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor | None] | None:
    """``svs_torch.depth.winner._winner_stats_torch``'s statistics of the winners ``best`` ``(B, H, W)`` int64 in a
    volume ``costs`` ``(B, D, H, W)`` float32 (see the C source), bit for bit: the costs at best ∓ 1 (clamped), with
    ``uniqueness`` the least cost farther than 1 from best, with ``right`` the right view's winner; None when the
    kernel is not available or the inputs do not fit its contract."""
    dims = check_shape(costs, "costs", ["B", "D", "H", "W"])
    check_shape(best, "best", [dims["B"], dims["H"], dims["W"]])
    check_dtype(best, "best", "int")
    if best.numel() and not (int(best.min()) >= 0 and int(best.max()) < dims["D"]):
        raise InputError(f"best: expected indices in [0, {dims['D']}), got values from {int(best.min())} to "
                         f"{int(best.max())}")
    if dims["D"] < 1 or not (on_cpu(torch.float32, costs) and on_cpu(torch.int64, best)):
        return None
    library = load("winner_statistics")
    if library is None:
        return None
    costs, best = costs.contiguous(), best.contiguous()
    shape = (dims["B"], dims["H"], dims["W"])
    before, after = costs.new_empty(shape), costs.new_empty(shape)
    rival = costs.new_empty(shape) if uniqueness else None
    right_best = torch.empty(shape, dtype=torch.int64) if right else None
    status = library.winner_statistics(costs.data_ptr(), best.data_ptr(), *costs.shape, before.data_ptr(),
                                       after.data_ptr(), None if rival is None else rival.data_ptr(),
                                       None if right_best is None else right_best.data_ptr(), torch.get_num_threads())
    return None if status != 0 else (before, after, rival, right_best)


#: The bound on :func:`sad_volume`'s sums: below 2**24 every partial sum of whole numbers is exact in float32.
EXACT_SUM_LIMIT = 2.0**24


def sad_volume(left: torch.Tensor, right: torch.Tensor, height: int, width: int, window_size: int,
               outside: torch.Tensor | None) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor] | None] | None:
    """``svs_torch.depth.cost_volume._costs_in_cache`` (see the C source), bit for bit: ``left`` ``(B, height + K − 1,
    width + K − 1)`` and ``right`` ``(B, height + K − 1, width + K − 1 + D − 1)`` float32 crops, ``outside``
    ``(B, D, 1, width)`` bool or None. Returns the costs ``(B, D, height, width)`` and, with ``outside``, the winner
    (min cost, first index) ``(B, height, width)`` each; None when the kernel is not available or the crops do not
    fit its contract: whole finite numbers whose window sums stay below 2**24 (exact in float32 in any order)."""
    for name, value, least in (("window_size", window_size, 1), ("height", height, 0), ("width", width, 0)):
        check_count(value, name, least)  # 3.7 ran as 3, "5" failed late
    size = window_size
    b = check_shape(left, "left", ["B", height + size - 1, width + size - 1])["B"]
    d = right.shape[-1] - (width + size - 1) + 1 if right.dim() == 3 else 0
    if d < 1:
        raise InputError(f"right: expected (B, {height + size - 1}, {width + size - 1} + D - 1) with D >= 1, got "
                         f"{tuple(right.shape)}")
    check_shape(right, "right", [b, height + size - 1, width + size - 1 + d - 1])
    if outside is not None:
        check_shape(outside, "outside", [b, d, 1, width])
        check_dtype(outside, "outside", "bool")
    if height < 1 or width < 1 or not on_cpu(torch.float32, left, right):
        return None
    library = load("sad_volume")
    if library is None:
        return None
    largest = max(float(left.abs().max()), float(right.abs().max())) if b else 0.0
    # A window's sum is at most K² differences of 2 · largest; a sliding sum holds K + 1 more before it lets go.
    if not (2 * largest * (size * size + size + 1) < EXACT_SUM_LIMIT  # NaN and inf fail it too
            and bool((left == left.round()).all()) and bool((right == right.round()).all())):
        return None
    left, right = left.contiguous(), right.contiguous()
    costs = left.new_empty(b, d, height, width)
    winner = None
    if outside is not None:
        winner = (left.new_empty(b, height, width), torch.empty(b, height, width, dtype=torch.int64))
        outside = canonical_bool(outside).contiguous().view(torch.uint8)
    status = library.sad_volume(left.data_ptr(), right.data_ptr(), b, d, height, width, size,
                                None if outside is None else outside.data_ptr(), costs.data_ptr(),
                                None if winner is None else winner[0].data_ptr(),
                                None if winner is None else winner[1].data_ptr(), torch.get_num_threads())
    return None if status != 0 else (costs, winner)


def _check_box_rows(boxes: torch.Tensor, name: str, b: int, h: int, w: int) -> None:
    """Boxes ``(B, 4)`` int that :func:`object_depths` reads (its columns and rows outside the frame repeat the
    border) within the ``h`` × ``w`` map widened by its size on each side, as ``dense_object_depths`` asks: within
    ±2³¹ alone, a 20000-px box on a 6 × 6 map counted 4e8 members in 8 s and 3 GB, and one of 60000 would ask 36."""
    check_rows(boxes, name, b, 4)
    x0, y0, width, height = boxes.long().unbind(1)  # x0 >= -w first: 2 * w - x0 never overflows where it counts
    inside = (x0 >= -w) & (y0 >= -h) & (width >= 0) & (height >= 0) & (width <= 2 * w - x0) & (height <= 2 * h - y0)
    if not bool(inside.all()):
        raise InputError(f"{name}: expected (x0, y0, width, height) within the {w}x{h} map widened by its size on "
                         f"each side, got {boxes[~inside].tolist()[:4]}")


def object_depths(disparity: torch.Tensor, valid: torch.Tensor, labels: torch.Tensor, boxes: torch.Tensor,
                  slots: torch.Tensor, scale: torch.Tensor, doffs: torch.Tensor, in_view_from: torch.Tensor,
                  fill: bool, q: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """The statistics of :func:`svs_torch.depth.dense_objects.dense_object_depths`, each pair read once at its own box
    (see the C source): ``disparity`` ``(B, H, W)`` float32, ``valid`` ``(B, H, W)`` bool, ``labels``
    ``(B, H, W)`` int64; ``boxes`` ``(B, 4)`` x0, y0, width, height; ``slots`` ``(B, N)`` int64; ``scale``
    (focal · baseline) and ``doffs`` ``(B,)`` float32; ``in_view_from`` ``(B, N)`` int64, each slot's first frame
    column where the whole disparity range it is allowed lands inside the right image; ``fill``: fill invalid
    pixels from their row first; quantiles ``q`` ``(Q,)`` float32. Returns ``(count, measured, in_view, below,
    above)``: each slot's member count, its members that were valid before the fill and those of them at columns
    from its ``in_view_from`` on ``(B, N)``, and the members of rank ``floor`` / ``ceil`` of ``q · (count − 1)``
    ``(B, N, Q)``; None when the kernel is not available or the inputs do not fit its contract."""
    dims = check_shape(disparity, "disparity", ["B", "H", "W"])
    b, h, w = dims["B"], dims["H"], dims["W"]
    check_shape(valid, "valid", [b, h, w])
    check_shape(labels, "labels", [b, h, w])
    check_nonempty(disparity, "disparity")
    _check_box_rows(boxes, "boxes", b, h, w)
    check_rows(slots, "slots", b, "N")
    check_shape(scale, "scale", [b])
    check_shape(doffs, "doffs", [b])
    check_shape(in_view_from, "in_view_from", [b, slots.shape[1]])
    check_shape(q, "q", ["Q"])
    if q.numel() and not bool(((q >= 0) & (q <= 1)).all()):  # NaN too: the kernel casts q · (count − 1) to int
        raise InputError(f"q: expected quantiles in [0, 1], got {q.tolist()}")
    if not (on_cpu(torch.float32, disparity, scale, doffs, q) and on_cpu(torch.bool, valid)
            and on_cpu(torch.int64, labels, boxes, slots, in_view_from)):
        return None
    library = load("object_depths")
    if library is None:
        return None
    n, k = slots.shape[1], q.numel()
    disparity, labels, boxes, slots, scale, doffs, in_view_from, q = (
        t.contiguous() for t in (disparity, labels, boxes, slots, scale, doffs, in_view_from, q))
    valid = valid.contiguous().view(torch.uint8)
    count, measured, in_view = (torch.empty(b, n, dtype=torch.int64) for _ in range(3))
    below, above = torch.empty(b, n, k), torch.empty(b, n, k)
    status = library.object_depths(disparity.data_ptr(), valid.data_ptr(), labels.data_ptr(), b, h, w,
                                   boxes.data_ptr(), slots.data_ptr(), n, scale.data_ptr(), doffs.data_ptr(),
                                   in_view_from.data_ptr(), int(fill), q.data_ptr(), k, count.data_ptr(),
                                   measured.data_ptr(), in_view.data_ptr(), below.data_ptr(), above.data_ptr(),
                                   torch.get_num_threads())
    return None if status != 0 else (count, measured, in_view, below, above)

