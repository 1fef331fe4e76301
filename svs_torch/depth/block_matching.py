"""Hard SAD block matching (:func:`block_match_sad`, :func:`dense_disparity_over_regions`): the fused C kernel
(``depth/kernels/block_match.c``) where it runs, else the torch path of :mod:`.cost_volume` and :mod:`.winner`,
bit for bit the same; and the row fill of invalid pixels (:func:`fill_invalid_rows`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import torch

from ..core.checks import InputError, check_dtype, check_instance, check_shape
from ..core.kernels.checks import check_counts, check_row_fill
from ..core.mask_reductions import any_along
from . import kernels
from .cost_volume import (_box_sum, _check_pair, _check_range, _check_sizes, _cost_volume, _gather_crop, crop_box,
                          prefilter_xsobel, quantize_levels, region_crop_boxes, wanted_pixels)
from .dense_config import DenseConfig, DenseDisparity, DisparityRange
from .semi_global import pair_residual_levels, residual_reaches, semi_global_aggregate_with_winner
from .winner import _WinnerStats, _left_right_consistent, _winner, _winner_neighbours, _winner_stats_torch

__all__ = ["block_match_sad", "block_match_sad_noisy_pairs", "block_match_sad_with_residual",
           "dense_disparity_over_regions", "fill_invalid_rows", "valid_row_neighbours"]

#: Noisy pairs matched again and aggregated together (:func:`_smooth_noisy_pairs`); their maps do not depend on it.
SMOOTH_BLOCK_PAIRS = 4


def _noisy_pairs(best_cost: torch.Tensor, computed: torch.Tensor, config: DenseConfig) -> torch.Tensor:
    """Whether each pair's matching residual over its ``computed`` pixels (winner costs ``best_cost``, ``(B, h, w)``
    each) reaches ``config.smoothing_min_residual_levels`` with at least one such pixel, ``(B,)`` bool: the one gate
    of the torch path (:func:`_smooth`) and the fused kernel's (:func:`_smooth_noisy_pairs`). Counted
    (:func:`~svs_torch.depth.semi_global.residual_reaches`, the verdicts of the median bit for bit), as the
    nearness segmenter's gate is: 8 coarse retries' maps, one thread, 1.47 → 0.46 ms."""
    level = config.smoothing_min_residual_levels
    return residual_reaches(best_cost, computed, config.window_size, level) & computed.flatten(1).any(1)


def _smooth(costs: torch.Tensor, minimum: tuple[torch.Tensor, torch.Tensor], config: DenseConfig,
            counts: torch.Tensor, extra: int, region: tuple[torch.Tensor, torch.Tensor],
            intensity_costs: Callable[[torch.Tensor], torch.Tensor] | None = None
            ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
    """``costs`` ``(B, D, h, w)`` and their winner, semi-globally aggregated for the pairs whose residual over
    ``region`` = (wanted ``(B, h, w − 2 extra)`` bool, own box ``(B, 4)`` relative to the box) reaches
    ``config.smoothing_min_residual_levels`` (:mod:`.semi_global`). Each noisy pair is aggregated over its own
    box only, widened by its own count − 1 columns (what its left–right check reads), so that its values never
    depend on its batch. ``intensity_costs``: the intensities' SAD volume of the pairs it is given the index of,
    added to theirs times ``config.smoothing_intensity_weight`` before the aggregation (its docstring)."""
    wanted, own = region
    core = slice(extra, costs.shape[-1] - extra)
    noisy = _noisy_pairs(minimum[0][..., core], wanted, config)
    if not bool(noisy.any()):
        return costs, minimum
    residual = pair_residual_levels(minimum[0][..., core], wanted, config.window_size)  # the penalties' unit
    index = noisy.nonzero().squeeze(1)
    all_noisy = len(index) == len(costs)
    # The aggregation only reads its volume: the whole batch's is not copied, nor masked where every pair's box
    # fills the shared one (a pair alone, B = 1). One pair's aggregated pass over a 200×160 box and 64 disparities
    # took 80 ms with the copy and the mask, 60 without (the same maps).
    picked, reach = costs if all_noisy else costs[index], counts[index].view(-1, 1, 1) - 1
    x0, y0, width, height = (v.view(-1, 1, 1) for v in own[index].unbind(1))
    rows = torch.arange(costs.shape[-2], device=costs.device).view(1, -1, 1) - y0
    cols = torch.arange(costs.shape[-1], device=costs.device).view(1, 1, -1) - extra - x0
    inside = (rows >= 0) & (rows < height) & (cols >= -reach) & (cols < width + reach)
    if not bool(inside.all()):
        picked = picked.masked_fill(~inside.unsqueeze(1), torch.inf)
    if intensity_costs is not None:
        # In place on the fresh intensity volume: the same two float32 operations (the weight's product, then the
        # sum), without two more volumes (a noisy 320x240 frame's coarse retry, 52 x 115 x 262: 1.8 -> 0.7 ms).
        picked = intensity_costs(index).mul_(config.smoothing_intensity_weight).add_(picked)
        # The penalties in units of the summed costs' residual, over the same wanted pixels.
        residual = residual.index_copy(0, index, pair_residual_levels(
            picked.amin(dim=1)[..., core], wanted[index], config.window_size))
    scale = residual[index] * config.window_size ** 2
    p1, p2 = (factor * scale for factor in config.smoothing_penalties)
    aggregated, winner = semi_global_aggregate_with_winner(picked, p1, p2)
    if all_noisy:
        return aggregated, winner
    return costs.index_copy(0, index, aggregated), tuple(m.index_copy(0, index, w) for m, w in zip(minimum, winner))


def _winner_stats(left: torch.Tensor, right: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor, height: int,
                  width: int, min_disparity: torch.Tensor, num_disparities: int, image_w: torch.Tensor,
                  config: DenseConfig, counts: torch.Tensor, extra: int = 0,
                  region: tuple[torch.Tensor, torch.Tensor] | None = None,
                  intensities: tuple[torch.Tensor, torch.Tensor] | None = None) -> _WinnerStats:
    """:class:`_WinnerStats` of the box at (x0, y0) from the torch cost volume. The box's first and last
    ``extra`` columns serve only the right view's winner: the left statistics are of the columns between
    (``right_best`` is of them all). With ``region`` and ``config.smoothing_penalties``, noisy pairs' costs
    are aggregated first (:func:`_smooth`), with ``intensities`` (the views' 8-bit levels before the pre-filter)
    their SAD added (``config.smoothing_intensity_weight``)."""
    uniqueness, right_check = config.uniqueness_ratio > 0, config.lr_max_diff_px is not None
    costs, _, minimum = _cost_volume(left, right, x0, y0, height, width, min_disparity, num_disparities, image_w,
                                     config, counts)
    plain = costs
    if region is not None and config.smoothing_penalties is not None:
        # Without the counts: no winner, no +inf mask (the x-Sobel costs it is added to carry the +inf already).
        intensity_costs = None if intensities is None else (lambda index: _cost_volume(
            intensities[0][index], intensities[1][index], x0[index], y0[index], height, width, min_disparity[index],
            num_disparities, image_w[index], config)[0])
        costs, minimum = _smooth(costs, minimum, config, counts, extra, region, intensity_costs)
    stats = _winner_stats_torch(costs, minimum, uniqueness, right_check, compiled=config.kernel != "torch")
    if costs is not plain:
        # The aggregation picks the winner and makes the verdicts; the sub-pixel fit stays on the plain SAD
        # costs at winner − 1, winner, winner + 1 (equal to the aggregated ones / 4 where nothing was
        # aggregated), which the differentiable pass recomputes from the images (pipeline.soft, step 1).
        near = plain.gather(1, _winner_neighbours(stats.best, num_disparities))
        stats = stats._replace(before=near[:, 0], after=near[:, 2], fit_cost=near[:, 1])
    core = slice(extra, width - extra)
    return _WinnerStats(*(None if t is None else t[..., core] for t in stats[:5]), stats.right_best,
                        None if stats.fit_cost is None else stats.fit_cost[..., core])


def _compiled(left: torch.Tensor, right: torch.Tensor, config: DenseConfig) -> bool:
    """Whether the hard path may run the fused C kernel (:func:`_match_compiled`): float32 CPU images without
    gradients, and ``config.kernel`` allows it."""
    return (config.kernel != "torch" and left.dtype == torch.float32 and left.device.type == "cpu"
            and not (torch.is_grad_enabled() and (left.requires_grad or right.requires_grad)))


def _match_compiled(left: torch.Tensor, right: torch.Tensor, boxes: torch.Tensor, search: DisparityRange,
                    image_hw: torch.Tensor, config: DenseConfig, lower_is_limit: torch.Tensor,
                    mask: torch.Tensor | None = None, best_cost: bool = False) -> tuple[torch.Tensor, ...] | None:
    """:func:`_match_box` of each pair at its own box ``(B, 4)`` (x0, y0, width, height) and its own range, by
    the fused C kernel of :mod:`svs_torch.depth.kernels`, straight to the full-frame disparity and validity
    ``(B, 1, H, W)``: the same values bit for bit (a pair's result never depends on its batch), without the
    batch's shared box, the groups of ranges or the scatter back; with ``mask`` ``(B, 1, H, W)`` only at its
    :func:`wanted_pixels`; with ``best_cost`` also each computed pixel's winning cost ``(B, H, W)`` (NaN
    elsewhere). None when the kernel cannot run here (then the torch path does; ``kernel="c"`` makes that an
    error)."""
    if not _compiled(left, right, config):
        return None
    counts = search.pair_num_disparities
    if counts is None:
        counts = torch.full_like(search.min_disparity_px, search.num_disparities)
    size = config.window_size
    # The kernel pre-filters (x-Sobel, clip, quantize_levels) and takes the texture a crop row at a time, the
    # torch path's values: whole pre-filtered frames cost passes over every pair, most of it outside the kept
    # regions (the dense stage on the shared Middlebury scenes at B = 32, 2 threads, interleaved: 3.0-3.2 ->
    # 2.9 ms a pair).
    found = kernels.block_match(
        left[:, 0], right[:, 0], config.texture_threshold > 0, size, boxes, search.min_disparity_px, counts,
        image_hw, lower_is_limit, config.uniqueness_ratio, config.lr_max_diff_px,
        config.texture_threshold * size ** 2, config.whole_range_in_view,
        source="xsobel" if config.prefilter == "xsobel" else "raw", prefilter_cap=config.prefilter_cap,
        mask=None if mask is None else mask[:, 0], mask_margin_px=config.margin_px, best_cost=best_cost)
    if found is None:
        if config.kernel == "c":
            raise InputError("kernel: 'c' asks for the compiled dense kernel, which is not available here "
                             "(no C compiler, or SVS_TORCH_KERNELS=torch); use 'auto' or 'torch'")
        return None
    return (found[0].unsqueeze(1), found[1].unsqueeze(1), *found[2:])


def _match_box(left: torch.Tensor, right: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor, height: int,
               width: int, search: DisparityRange, image_hw: torch.Tensor, config: DenseConfig,
               lower_is_limit: torch.Tensor, region: tuple[torch.Tensor, torch.Tensor] | None = None
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Disparity ``(B, height, width)``, validity and the winning cost (+inf: no candidate) of the box at (x0, y0)
    of the images. The volume spans D − 1 extra columns on each side so the right view's winner (left–right
    check) sees every candidate. ``region``: see :func:`_winner_stats`."""
    sobel = prefilter_xsobel(left, config.prefilter_cap)
    aggregated = region is not None and config.smoothing_penalties is not None
    intensities = ((quantize_levels(left), quantize_levels(right))
                   if aggregated and config.smoothing_intensity_weight > 0 and config.prefilter == "xsobel" else None)
    if config.prefilter == "xsobel":
        left, right = sobel, prefilter_xsobel(right, config.prefilter_cap)
    # StereoBM's levels: the matched values in whole 1/255 intensity steps (its pre-filter is uint8). The SAD
    # costs are then whole numbers, exact in float32 (at most K² · 255 < 2²⁴) whatever the order of the sums,
    # so the C kernel's running sums give the torch path's costs bit for bit.
    left, right = quantize_levels(left), quantize_levels(right)
    num_disparities = search.num_disparities
    extra = num_disparities - 1 if config.lr_max_diff_px is not None else 0
    counts = search.pair_num_disparities
    if counts is None:
        counts = torch.full_like(search.min_disparity_px, num_disparities)
    # The extra columns serve only the right view's winner: every per-pixel verdict is made on the box itself.
    stats = _winner_stats(left, right, x0 - extra, y0, height, width + 2 * extra, search.min_disparity_px,
                          num_disparities, image_hw[:, 1], config, counts, extra, region, intensities)
    best = stats.best
    offset, ok = _winner(stats, num_disparities, config, lower_is_limit, counts)
    if config.lr_max_diff_px is not None:
        ok &= _left_right_consistent(best, stats.right_best, config.lr_max_diff_px, extra)
    if config.texture_threshold > 0:
        radius = config.window_size // 2
        texture = _gather_crop(sobel.abs(), y0 - radius, x0 - radius, height + 2 * radius, width + 2 * radius)
        ok &= _box_sum(texture, config.window_size).squeeze(1) >= config.texture_threshold * config.window_size ** 2
    disparity = search.min_disparity_px.view(-1, 1, 1).to(offset.dtype) + best.to(offset.dtype) + offset
    rows = y0.view(-1, 1, 1) + torch.arange(height, device=left.device).view(1, -1, 1)
    cols = x0.view(-1, 1, 1) + torch.arange(width, device=left.device).view(1, 1, -1)
    ok &= (rows >= 0) & (rows < image_hw[:, :1, None]) & (cols >= 0) & (cols < image_hw[:, 1:, None])
    if config.whole_range_in_view:  # the pair's largest disparity must still land inside the right image
        ok &= cols >= (search.min_disparity_px + counts - 1).view(-1, 1, 1)
    return torch.where(ok, disparity, torch.zeros_like(disparity)), ok, stats.best_cost


def fill_invalid_rows(disparity: torch.Tensor, valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Fill each invalid pixel of ``(..., W)`` rows (float or int; ``valid`` of its shape, bool) from the nearest
    valid pixels to its left and right: their mean where they agree within 1 px (a textureless patch inside one
    surface), otherwise the smaller disparity (an occlusion is background: Hirschmüller 2008, Sec. 3.5); one side
    only where the other has none. Returns the filled disparity and where a fill was possible (``valid`` or a valid
    pixel in the row). Differentiable w.r.t. ``disparity``; without gradients a C kernel: the same values."""
    check_row_fill(disparity, valid)
    if not (disparity.requires_grad and torch.is_grad_enabled()):
        done = kernels.fill_invalid_rows(disparity, valid)
        if done is not None:
            return done
    width = disparity.shape[-1]
    left_index, right_index, from_left, from_right = valid_row_neighbours(disparity, valid)
    has_left, has_right = left_index >= 0, right_index < width
    agree = (from_left - from_right).abs() <= 1
    both = torch.where(agree, (from_left + from_right) / 2, torch.minimum(from_left, from_right))
    filled = torch.where(has_left & has_right, both, torch.where(has_left, from_left, from_right))
    reachable = valid | has_left | has_right
    return torch.where(valid, disparity, torch.where(reachable, filled, torch.zeros_like(filled))), reachable


def valid_row_neighbours(disparity: torch.Tensor, valid: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """For each pixel of ``(..., W)`` rows: the column of the nearest ``valid`` pixel at or left of it (−1: none)
    and at or right of it (W: none), and their disparities (the row's end pixel's where there is none): what
    :func:`fill_invalid_rows` fills from, and what a rule on the runs of invalid pixels between them reads.
    Differentiable w.r.t. ``disparity`` through the two gathered disparities; the int64 columns are not."""
    width = disparity.shape[-1]
    index = torch.arange(width, device=disparity.device).expand_as(disparity)
    left_index = torch.where(valid, index, -1).cummax(dim=-1).values
    right_index = torch.where(valid, index, width).flip(-1).cummin(dim=-1).values.flip(-1)
    return (left_index, right_index, disparity.gather(-1, left_index.clamp(0, width - 1)),
            disparity.gather(-1, right_index.clamp(0, width - 1)))


def block_match_sad(left: torch.Tensor, right: torch.Tensor, min_disparity_px: torch.Tensor | int,
                    num_disparities: int, config: DenseConfig = DenseConfig(),
                    image_hw: torch.Tensor | None = None) -> DenseDisparity:
    """Dense SAD block matching of whole images ``(B, 1, H, W)`` over the disparities
    ``[min_disparity_px, min_disparity_px + num_disparities)`` (an int or ``(B,)`` int64 per pair).

    Pixels whose right match ``x − d`` leaves the image for every candidate, and the rejections of the module
    docstring, are invalid. ``image_hw`` ``(B, 2)`` gives each pair's size before padding (default: all of it).
    Not differentiable (winner takes all); see :func:`soft_block_match`."""
    return _match_whole(left, right, min_disparity_px, num_disparities, config, image_hw, best_cost=False)[0]


def block_match_sad_with_residual(left: torch.Tensor, right: torch.Tensor, min_disparity_px: torch.Tensor | int,
                                  num_disparities: int, config: DenseConfig = DenseConfig(),
                                  image_hw: torch.Tensor | None = None) -> tuple[DenseDisparity, torch.Tensor]:
    """:func:`block_match_sad` and each pair's matching residual ``(B,)``: the median winning SAD per window pixel
    over its pixels with a candidate, in 8-bit levels of the pre-filtered images
    (:func:`~svs_torch.depth.semi_global.pair_residual_levels`, the gate of ``DenseConfig.smoothing_penalties``).
    The tuned Middlebury scenes at the nearness segmenter's settings (7×7 at 320 px wide): clean 1.9–7.5 levels,
    as camera frames from JPEG digit 3 with σ 3 on 8.7–13.4 at 320×240. Not differentiable."""
    found, best_cost = _match_whole(left, right, min_disparity_px, num_disparities, config, image_hw, best_cost=True)
    return found, pair_residual_levels(best_cost, torch.ones_like(best_cost, dtype=torch.bool), config.window_size)


def block_match_sad_noisy_pairs(left: torch.Tensor, right: torch.Tensor, min_disparity_px: torch.Tensor | int,
                                num_disparities: int, min_residual_levels: float, config: DenseConfig = DenseConfig(),
                                image_hw: torch.Tensor | None = None) -> tuple[DenseDisparity, torch.Tensor]:
    """:func:`block_match_sad` and which pairs' matching residual (:func:`block_match_sad_with_residual`'s) reaches
    ``min_residual_levels``, ``(B,)`` bool: the same verdicts, counted instead of taking the median
    (:func:`~svs_torch.depth.semi_global.residual_reaches`). Not differentiable."""
    found, best_cost = _match_whole(left, right, min_disparity_px, num_disparities, config, image_hw, best_cost=True)
    return found, residual_reaches(best_cost, None, config.window_size, min_residual_levels)


@torch.no_grad()  # winner takes all: no gradient (soft_block_match has one); out= ops refuse grad
def _match_whole(left: torch.Tensor, right: torch.Tensor, min_disparity_px: torch.Tensor | int, num_disparities: int,
                 config: DenseConfig, image_hw: torch.Tensor | None, best_cost: bool
                 ) -> tuple[DenseDisparity, torch.Tensor | None]:
    """:func:`block_match_sad` and every pixel's winning cost ``(B, H, W)`` (+inf: no candidate), which the
    fused kernel writes only when asked (``best_cost``; None otherwise) and the torch path always has."""
    b = _check_pair(left, right, config)
    minimum = _check_range(min_disparity_px, num_disparities, left, config.lr_max_diff_px is not None)
    h, w = left.shape[-2:]
    image_hw = _check_sizes(image_hw, left)
    zeros = torch.zeros(b, dtype=torch.int64, device=left.device)
    search = DisparityRange(minimum, num_disparities)
    box = torch.tensor([[0, 0, w, h]], device=left.device).expand(b, 4)
    counts = torch.full_like(minimum, num_disparities)
    found = _match_compiled(left, right, box, search, image_hw, config, minimum <= 0, best_cost=best_cost)
    if found is not None:
        return (DenseDisparity(found[0], found[1], minimum, num_disparities, box.clone(), counts),
                found[2] if best_cost else None)
    disparity, ok, winning = _match_box(left, right, zeros, zeros, h, w, search, image_hw, config,
                                        lower_is_limit=minimum <= 0)
    return DenseDisparity(disparity.unsqueeze(1), ok.unsqueeze(1), minimum, num_disparities, box.clone(),
                          counts), winning


def _smooth_noisy_pairs(left: torch.Tensor, right: torch.Tensor, mask: torch.Tensor, search: DisparityRange,
                        config: DenseConfig, image_hw: torch.Tensor, found: tuple[torch.Tensor, ...]
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """The fused kernel's map ``found`` (disparity, valid, best cost), with the pairs whose residual reaches
    ``config.smoothing_min_residual_levels`` matched again on the torch cost volume, aggregated (:func:`_smooth`):
    the values the torch path alone gives, without a volume for the clean pairs."""
    disparity, valid, best_cost = found
    noisy = _noisy_pairs(best_cost, ~best_cost.isnan(), config)
    if not bool(noisy.any()):
        return disparity, valid
    counts = search.pair_num_disparities
    every = replace(config, smoothing_min_residual_levels=0.0)
    # A block of pairs at a time: each holds its volume several times over while it is aggregated (about 30 MB a
    # pair at 320×240 and 64 disparities, times 6), so a bulk run's noisy batch is not held all at once.
    for block in noisy.nonzero().squeeze(1).split(SMOOTH_BLOCK_PAIRS):
        part = _over_regions(
            left[block], right[block], mask[block],
            DisparityRange(search.min_disparity_px[block], search.num_disparities,
                           None if counts is None else counts[block]), every, image_hw[block], fused=False)
        disparity = disparity.index_copy(0, block, part.disparity_px)
        valid = valid.index_copy(0, block, part.valid)
    return disparity, valid


def dense_disparity_over_regions(left: torch.Tensor, right: torch.Tensor, mask: torch.Tensor,
                                 search: DisparityRange, config: DenseConfig = DenseConfig(),
                                 image_hw: torch.Tensor | None = None) -> DenseDisparity:
    """Dense SAD disparity of the left view, computed only near each pair's ``mask`` ``(B, 1, H, W)`` bool (the
    kept regions: :func:`wanted_pixels`, each row's mask span and ``config.margin_px`` either side) and only over
    ``search``; elsewhere invalid. A pixel's value is the one a whole-frame match gives it.

    Args:
        left, right: ``(B, 1, H, W)`` images (rectified, or a rig whose rows already agree).
        mask: where depth is wanted (``Segmentation.kept_mask`` of the left view).
        search: :class:`DisparityRange`, e.g. from :func:`disparity_search_range`; config: the :class:`DenseConfig`.
        image_hw: ``(B, 2)`` each pair's size before padding.

    Returns:
        :class:`DenseDisparity`. Not differentiable (see :func:`soft_block_match`).
    """
    return _over_regions(left, right, mask, search, config, image_hw)


@torch.no_grad()  # winner takes all: no gradient (soft_block_match has one); out= ops refuse grad
def _over_regions(left: torch.Tensor, right: torch.Tensor, mask: torch.Tensor, search: DisparityRange,
                  config: DenseConfig, image_hw: torch.Tensor | None, fused: bool = True) -> DenseDisparity:
    """:func:`dense_disparity_over_regions`; ``fused=False`` skips the fused kernel (the noisy pairs' torch cost
    volume, :func:`_smooth_noisy_pairs`, whose window sums may still run compiled)."""
    b = _check_pair(left, right, config)
    check_shape(mask, "mask", [b, 1, *left.shape[-2:]])
    check_dtype(mask, "mask", "bool")
    check_instance(search, "search", DisparityRange)
    minimum = _check_range(search.min_disparity_px, search.num_disparities, left, config.lr_max_diff_px is not None)
    if search.pair_num_disparities is not None:
        check_counts(search.pair_num_disparities, "search.pair_num_disparities", b, search.num_disparities)
    h, w = left.shape[-2:]
    image_hw = _check_sizes(image_hw, left)
    x0, y0, height, width, own = region_crop_boxes(mask, config.margin_px, image_hw)
    search = DisparityRange(minimum, search.num_disparities, search.pair_num_disparities)
    counts = search.pair_num_disparities
    counts = torch.full_like(minimum, search.num_disparities) if counts is None else counts
    some = any_along(mask.flatten(1), dim=1)
    smoothing = config.smoothing_penalties is not None
    found = None if not fused else _match_compiled(
        left, right, torch.where(some.view(-1, 1), own, torch.zeros_like(own)), search, image_hw, config, minimum <= 0,
        mask, best_cost=smoothing)
    if found is not None:
        disparity, valid = found[:2]
        if smoothing:
            disparity, valid = _smooth_noisy_pairs(left, right, mask, search, config, image_hw, found)
        return DenseDisparity(disparity, valid, minimum, search.num_disparities, own, counts)
    wanted = some.view(-1, 1, 1) & crop_box(wanted_pixels(mask, config.margin_px), x0, y0, height, width)[:, 0]
    own_in_box = own - torch.stack([x0, y0, torch.zeros_like(x0), torch.zeros_like(y0)], 1)
    disparity, ok, _ = _match_box(left, right, x0, y0, height, width, search, image_hw, config,
                                  lower_is_limit=minimum <= 0, region=(wanted, own_in_box))
    ok &= wanted
    rows = y0.view(-1, 1, 1) + torch.arange(height, device=left.device).view(1, -1, 1)
    cols = x0.view(-1, 1, 1) + torch.arange(width, device=left.device).view(1, 1, -1)
    own_x0, own_y0, own_w, own_h = (v.view(-1, 1, 1) for v in own.unbind(1))
    ok &= (rows >= own_y0) & (rows < own_y0 + own_h) & (cols >= own_x0) & (cols < own_x0 + own_w)
    disparity = torch.where(ok, disparity, torch.zeros_like(disparity))
    full = torch.zeros(b, h * w, dtype=disparity.dtype, device=left.device)
    full_ok = torch.zeros(b, h * w, dtype=torch.bool, device=left.device)
    index = ((y0.view(-1, 1, 1) + torch.arange(height, device=left.device).view(1, -1, 1)) * w
             + x0.view(-1, 1, 1) + torch.arange(width, device=left.device).view(1, 1, -1)).reshape(b, -1)
    full.scatter_(1, index, disparity.reshape(b, -1))
    full_ok.scatter_(1, index, ok.reshape(b, -1))
    return DenseDisparity(full.view(b, 1, h, w), full_ok.view(b, 1, h, w), minimum, search.num_disparities, own,
                          counts)
