"""Dense SAD block matching over the obstacles, batched over B pairs (the depth stage's measurement, Sec. 3.4).

The paper ranges a pair from the extreme disparities of its sparse RANSAC inliers (Eq. (5)–(8)); one wrong
inlier then decides R_min or R_max, and a few dozen keypoints estimate an object's median poorly
(``../shared/REFERENCE.md``, "Pitfalls"). This stage measures a disparity at every pixel of the kept regions
instead, the way OpenCV's ``StereoBM`` does (Konolige 1997):

1. **Pre-filter** both images: the x-Sobel response clipped to ``±prefilter_cap`` (``StereoBM``'s default
   ``PREFILTER_XSOBEL``), which removes the exposure offset between the two cameras; or raw intensities. The
   hard path matches them in whole 1/255 steps, as ``StereoBM``'s 8-bit pre-filter does
   (:func:`quantize_levels`): its costs are then exact integers, which lets the fused C kernel
   (:mod:`svs_torch.depth.kernels`) use running sums and still equal the torch path bit for bit.
2. **Cost**: for each disparity d of a per-pair range ``[d_lo, d_lo + D)``, the sum of absolute differences
   over a square window, ``C(x, y, d) = Σ_window |L(x, y) − R(x − d, y)|`` — box sums by separable pooling.
3. **Winner takes all**, then rejections (each marks the pixel invalid, never guesses): the window's mean
   |pre-filtered left| below ``texture_threshold`` (flat), the best cost not ``uniqueness_ratio`` below every
   cost farther than 1 px from it (ambiguous), a winner on the inner edge of the range (the true minimum may lie
   outside), and a left–right check: the right view's own winner at ``x − d`` must agree within
   ``lr_max_diff_px`` (occlusions, mismatches).
4. **Sub-pixel** by the equiangular (V) fit through the costs at d − 1, d, d + 1 — SAD costs are V-shaped near
   their minimum, where a parabola biases towards integers (Shimizu & Okutomi 2001).

Work is done only where it is needed: each pair's crop is the bounding box of its kept regions plus
``margin_px`` (one shared crop size for the batch, each pair at its own offset), and the disparity range comes
from the sparse inliers' disparities with a margin (:func:`disparity_search_range`), so the cost volume is
``B × D × crop`` rather than ``B × D_max × H × W``.

The hard path (WTA, rejections) is not differentiable. :func:`soft_block_match` is: a soft-argmin over the same
cost volume with a temperature, whose gradients reach both images.
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch
import torch.nn.functional as F

from ..core.checks import InputError, check_dtype, check_finite_where, check_shape
from . import kernels
from .block_matching import _compiled, block_match_sad, dense_disparity_over_regions
from .cost_volume import (_check_pair, _check_sizes, crop_box, crop_index, prefilter_xsobel, quantize_levels,
                          region_crop_boxes, wanted_pixels)
from .dense_config import DenseConfig, DenseDisparity, DisparityRange
from .pooling import _any_pool, mean_pool, reduction_factor
from .search_range import coarse_search_range, disparity_search_range
from .soft_dense import soft_block_match
from .winner import equiangular_offset

__all__ = [
    "DenseConfig", "DenseDisparity", "DisparityRange", "block_match_sad", "coarse_search_range", "crop_box",
    "crop_index", "dense_disparity_in_range", "dense_disparity_over_regions", "disparity_search_range",
    "equiangular_offset",
    "estimate_dense_disparity", "mean_pool", "prefilter_xsobel", "quantize_levels", "region_crop_boxes",
    "soft_block_match", "wanted_pixels", "working_factor", "working_range", "working_window"
]


#: Pairs whose disparity counts differ by less than this factor share one cost volume (:func:`_match_in_groups`).
GROUP_RATIO = 1.5


def _reduce(left: torch.Tensor, right: torch.Tensor, mask: torch.Tensor, image_hw: torch.Tensor,
            factor: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Images box-averaged ``factor`` times, the mask by any-pooling, each pair's size floored."""
    if factor == 1:
        return left, right, mask, image_hw
    return (mean_pool(left, factor), mean_pool(right, factor), _any_pool(mask, factor),
            torch.div(image_hw, factor, rounding_mode="floor").clamp_min(1))


def _enlarge(dense: DenseDisparity, factor: int, height: int, width: int) -> DenseDisparity:
    """A reduced-resolution result on the full ``height × width`` grid: each working pixel covers a
    ``factor × factor`` block, disparities scaled by ``factor``; rows and columns past the reduced grid are
    invalid."""
    if factor == 1:
        return dense

    def grow(value: torch.Tensor) -> torch.Tensor:
        grown = value.repeat_interleave(factor, dim=-2).repeat_interleave(factor, dim=-1)
        grown = grown[..., :height, :width]
        return F.pad(grown, (0, width - grown.shape[-1], 0, height - grown.shape[-2]))

    top, object_top = ((None if t is None else (t + 1) * factor - 1)  # as min + count - 1
                       for t in (dense.in_view_top_px, dense.object_in_view_top_px))
    return DenseDisparity(grow(dense.disparity_px * factor), grow(dense.valid), dense.min_disparity_px * factor,
                          dense.num_disparities * factor, dense.crop_xywh * factor,
                          dense.pair_num_disparities * factor, top, object_top)


def working_factor(width_px: int, config: DenseConfig = DenseConfig(), height_px: int | None = None) -> int:
    """The integer factor :func:`estimate_dense_disparity` reduces images ``width_px`` wide (and ``height_px``
    high, when given) by: about ``width_px / config.working_width_px``, at least 1 and at most the height, so that
    a strip a few rows high keeps a row (it was reduced to none and failed the batch): one working pixel is this
    many input pixels."""
    return reduction_factor(width_px, config.working_width_px, height_px)


def working_window(width_px: int, config: DenseConfig = DenseConfig()) -> int:
    """The window side :func:`estimate_dense_disparity` matches images ``width_px`` wide with, working pixels:
    ``config.window_size``, or with ``config.scale_window`` where the images are matched unreduced and wider than
    ``config.working_width_px`` (353–479 px: the integer factor rounds to 1), the odd side nearest ``window_size ·
    width_px / working_width_px``. Why: there a fixed window spans up to a third less of the scene than at 320 px
    with the same noise per pixel (a reduced pair's box average has averaged it); on the tuned scenes resampled to
    448×336 as camera frames a 13-pixel window ranged objects better than a 9-pixel one, at 320×240 worse
    (experiments/real_rig.md, "The window at the working width")."""
    if not config.scale_window or working_factor(width_px, config) > 1:  # reduced: the box average took the noise
        return config.window_size
    scaled = config.window_size * width_px / config.working_width_px
    return min(max(config.window_size, 2 * round((scaled - 1) / 2) + 1), kernels.MAX_WINDOW)


def estimate_dense_disparity(left: torch.Tensor, right: torch.Tensor, mask: torch.Tensor,
                             config: DenseConfig = DenseConfig(), image_hw: torch.Tensor | None = None,
                             inlier_disparity_px: torch.Tensor | None = None,
                             inlier_valid: torch.Tensor | None = None,
                             objects: torch.Tensor | None = None) -> DenseDisparity:
    """The dense stage of the pipeline: reduce to ``working_width_px``, find each pair's search range (a coarse
    pass, or the sparse inliers' disparities ``(B, K)`` with ``inlier_valid``), match over the kept regions
    ``mask`` ``(B, 1, H, W)`` with :func:`working_window`'s window, and return the disparity on the input grid (in
    input pixels).

    ``min_disparity_px``, ``num_disparities`` and ``crop_xywh`` of the result are in input pixels too (the
    working range times the factor). ``objects`` ``(B, N, H, W)`` bool (optional): one mask per kept object,
    so the coarse range covers every object (see :func:`coarse_search_range`). Not differentiable (see
    :func:`soft_block_match`).
    """
    b = _check_pair(left, right, config)
    if b == 0:  # its search range is a reduction over the batch's pairs
        raise InputError("left: expected at least one pair, got an empty batch")
    check_shape(mask, "mask", [b, 1, *left.shape[-2:]])
    check_dtype(mask, "mask", "bool")
    if objects is not None:
        check_shape(objects, "objects", [b, "N", *left.shape[-2:]])
        check_dtype(objects, "objects", "bool")
    if inlier_disparity_px is not None or inlier_valid is not None:  # named as passed (an audit: as valid, and
        # under the default coarse range source not checked at all)
        if inlier_disparity_px is None or inlier_valid is None:
            raise InputError("inlier_disparity_px, inlier_valid: expected both or neither")
        check_shape(inlier_disparity_px, "inlier_disparity_px", [b, "K"])
        check_dtype(inlier_disparity_px, "inlier_disparity_px", "float")
        check_shape(inlier_valid, "inlier_valid", list(inlier_disparity_px.shape))
        check_dtype(inlier_valid, "inlier_valid", "bool")
        check_finite_where(inlier_disparity_px, "inlier_disparity_px", inlier_valid, "inlier_valid")
    height, width = left.shape[-2:]
    image_hw = _check_sizes(image_hw, left)
    factor = working_factor(width, config, height)
    small_left, small_right, small_mask, small_hw = _reduce(left, right, mask, image_hw, factor)
    if config.range_source == "coarse" or inlier_disparity_px is None:
        small_objects = None
        if objects is not None:
            small_objects = objects if factor == 1 else _any_pool(objects, factor)
        search = coarse_search_range(small_left, small_right, small_mask, small_hw, config, small_objects)
    else:
        search = disparity_search_range(inlier_disparity_px / factor, inlier_valid, small_hw[:, 1], config)
    dense = _match_at_working_width(small_left, small_right, small_mask, search, config, small_hw, width, factor)
    if search.in_view_top_px is not None:
        dense = replace(dense, in_view_top_px=search.in_view_top_px, object_in_view_top_px=search.object_in_view_top_px)
    return _enlarge(dense, factor, height, width)


def dense_disparity_in_range(left: torch.Tensor, right: torch.Tensor, mask: torch.Tensor,
                             min_disparity_px: torch.Tensor, num_disparities: torch.Tensor,
                             config: DenseConfig = DenseConfig(), image_hw: torch.Tensor | None = None
                             ) -> DenseDisparity:
    """:func:`estimate_dense_disparity` over a range given rather than found: each pair's ``[min_disparity_px,
    min_disparity_px + num_disparities)`` ``(B,)`` int64, input pixels (widened to whole working pixels). A
    range narrower than a repeated pattern's period holds one alias only (:mod:`~svs_torch.depth.alias_choice`).
    Not differentiable."""
    b = _check_pair(left, right, config)
    check_shape(mask, "mask", [b, 1, *left.shape[-2:]])
    check_dtype(mask, "mask", "bool")
    for value, name in ((min_disparity_px, "min_disparity_px"), (num_disparities, "num_disparities")):
        check_shape(value, name, [b])
        check_dtype(value, name, "int")
    height, width = left.shape[-2:]
    image_hw = _check_sizes(image_hw, left)
    factor = working_factor(width, config, height)
    small_left, small_right, small_mask, small_hw = _reduce(left, right, mask, image_hw, factor)
    low, top = working_range(min_disparity_px, num_disparities, factor)
    counts = (top - low).clamp_min(1)
    search = DisparityRange(low, int(counts.max()) if b else 1, counts)
    return _enlarge(_match_at_working_width(small_left, small_right, small_mask, search, config, small_hw, width,
                                            factor), factor, height, width)


def working_range(min_disparity_px: torch.Tensor, num_disparities: torch.Tensor, factor: int
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """A range of input pixels ``[min, min + num)`` ``(B,)`` each as whole working pixels ``[low, top)``, widened
    to cover it: ``low = ⌊max(min, 0) / factor⌋``, ``top = ⌈(min + num) / factor⌉``."""
    low = torch.div(min_disparity_px.clamp_min(0), factor, rounding_mode="floor")
    return low, torch.div(min_disparity_px + num_disparities + factor - 1, factor, rounding_mode="floor")


def _match_at_working_width(left: torch.Tensor, right: torch.Tensor, mask: torch.Tensor, search: DisparityRange,
                            config: DenseConfig, image_hw: torch.Tensor, width: int, factor: int) -> DenseDisparity:
    """:func:`_match_in_groups` of the reduced views with the settings of the working width for views ``width``
    input pixels wide reduced ``factor`` times: no semi-global aggregation past ``config.smoothing_max_reduction``
    (the box average has already averaged the noise), and :func:`working_window`'s window (after any coarse pass,
    which matches with its own)."""
    if factor > config.smoothing_max_reduction:
        config = replace(config, smoothing_penalties=None)
    config = replace(config, window_size=working_window(width, config))
    return _match_in_groups(left, right, mask, search, config, image_hw)


def _match_in_groups(left: torch.Tensor, right: torch.Tensor, mask: torch.Tensor, search: DisparityRange,
                     config: DenseConfig, image_hw: torch.Tensor) -> DenseDisparity:
    """:func:`dense_disparity_over_regions` on groups of pairs whose disparity counts are within a factor
    ``GROUP_RATIO`` of each other: the torch path's shared cost volume is as deep as its widest range, so a
    single pair with a wide range would otherwise make every pair of the batch pay for it (measured: 2.5–10×
    per pair at B = 8 on mixed Middlebury scenes). A loop over a few groups, never over pairs; results are the
    same as one call, since a pair's result never depends on its batch. The compiled path needs no groups: it
    matches each pair over its own range."""
    counts = search.pair_num_disparities
    if counts is None or left.shape[0] == 1 or (_compiled(left, right, config) and kernels.available()):
        # The compiled path matches each pair over its own range already.
        return dense_disparity_over_regions(left, right, mask, search, config, image_hw)
    group = (counts.clamp_min(1).to(torch.float64).log() / math.log(GROUP_RATIO)).floor().long()
    keys = group.unique()
    if keys.numel() == 1:
        return dense_disparity_over_regions(left, right, mask, search, config, image_hw)
    b, _, h, w = left.shape
    disparity = left.new_zeros(b, 1, h, w)
    valid = torch.zeros(b, 1, h, w, dtype=torch.bool, device=left.device)
    boxes = torch.zeros(b, 4, dtype=torch.int64, device=left.device)
    for key in keys:
        index = (group == key).nonzero().flatten()
        own = counts[index]
        part = dense_disparity_over_regions(
            left[index], right[index], mask[index],
            DisparityRange(search.min_disparity_px[index], int(own.max()), own), config, image_hw[index])
        disparity[index], valid[index], boxes[index] = part.disparity_px, part.valid, part.crop_xywh
    return DenseDisparity(disparity, valid, search.min_disparity_px, search.num_disparities, boxes, counts)
