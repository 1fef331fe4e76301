"""Each pair's disparity search range: from the sparse inliers' disparities with a margin
(:func:`disparity_search_range`), or from a coarse match of the reduced pair (:func:`coarse_search_range`).
"""

from __future__ import annotations

from dataclasses import replace

import torch

from ..core.checks import check_dtype, check_finite, check_shape
from ..core.mask_reductions import all_true, count_along
from ..core.ordering import sort_last
from . import kernels
from .block_matching import dense_disparity_over_regions
from .cost_volume import _check_pair, _check_sizes
from .dense_config import DenseConfig, DisparityRange
from .pooling import _any_pool, mean_pool, reduction_factor

__all__ = ["coarse_search_range", "disparity_search_range"]


#: Per group ``(B, G)`` of :func:`_group_percentiles`: whether it bounds the range, its low, and its high without its
#: detached near tail.
_Trimmed = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


def _nearest_rank(ordered: torch.Tensor, count: torch.Tensor, q: float) -> torch.Tensor:
    """Nearest-rank quantile ``q`` of the first ``count`` entries of each sorted row of ``ordered`` ``(B, P)``."""
    if ordered.shape[1] == 0:
        return torch.zeros(ordered.shape[0], dtype=ordered.dtype, device=ordered.device)
    rank = ((count - 1).clamp_min(0).to(ordered.dtype) * q).round().long()
    return ordered.gather(1, rank.unsqueeze(1)).squeeze(1)


def _select_nearest_ranks(values: torch.Tensor, labels: torch.Tensor, slots: torch.Tensor,
                          q: tuple[float, ...]) -> tuple[torch.Tensor, list[torch.Tensor]] | None:
    """:func:`_nearest_rank` of each slot's members (``labels == slots[:, n]``, labels ``(B, P)``, slots
    ``(B, N)`` int64) by the compiled selection of :func:`svs_torch.depth.kernels.labelled_select` instead of a sort
    of every sample: the member counts ``(B, N)`` and one ``(B, N)`` float64 tensor per quantile (not defined
    where a count is 0). The kernel finds the members of rank ⌊p⌋ and ⌈p⌉ around ``p = q · (count − 1)``;
    the nearest rank (rounded in float64, as :func:`_nearest_rank` does) is one of the two. The same values
    as the sort, exactly; None without the kernel, or for values other than float32 without NaN."""
    if values.dtype != torch.float32 or values.requires_grad or not kernels.available("labelled_select"):
        return None  # (values with NaN: labelled_select gives None)
    fractions = torch.tensor(q, dtype=torch.float32, device=values.device)
    selected = kernels.labelled_select(values.contiguous(), labels, slots, fractions)
    if selected is None:
        return None
    count, below, above = selected
    position = fractions * (count - 1).clamp_min(0).unsqueeze(-1).to(torch.float32)  # the kernel's ⌊p⌋
    rank = ((count - 1).clamp_min(0).unsqueeze(-1).to(torch.float64)
            * torch.tensor(q, dtype=torch.float64)).round()
    chosen = torch.where(rank == position.floor().to(torch.float64), below, above).to(torch.float64)
    return count, list(chosen.unbind(-1))


def _checked_samples(disparity_px: torch.Tensor, valid: torch.Tensor, image_w: torch.Tensor) -> torch.Tensor:
    """:func:`disparity_search_range`'s checks; the samples in float64, detached."""
    b = check_shape(disparity_px, "disparity_px", ["B", "P"])["B"]
    check_shape(valid, "valid", list(disparity_px.shape))
    check_dtype(valid, "valid", "bool")
    # Unchecked before (an audit): a (B, 1) width gave (B, B) ranges in silence, a complex one failed deep inside,
    # complex samples lost their imaginary part with a warning.
    check_dtype(disparity_px, "disparity_px", "float|int")
    check_shape(image_w, "image_w", [b])
    check_dtype(image_w, "image_w", "int")
    values = disparity_px.detach().to(torch.float64)
    check_finite(values[valid], "disparity_px")  # where valid: an inf sample made a range from -2^63
    return values


def disparity_search_range(disparity_px: torch.Tensor, valid: torch.Tensor, image_w: torch.Tensor,
                           config: DenseConfig = DenseConfig(), extra_margin_px: float = 0.0,
                           min_count: int | None = None, groups: torch.Tensor | None = None,
                           tail_bin_px: float | None = None) -> DisparityRange:
    """Per-pair search range from sample disparities ``(B, P)`` (``valid`` ``(B, P)``: coarse dense pixels of
    the kept regions, or sparse inliers): their ``range_percentiles`` widened by
    ``max(range_margin_px, range_margin_fraction · span) + extra_margin_px`` on each side, clipped at 0 and to
    ``max_num_disparities`` around the centre. Pairs with fewer than ``min_count`` (default
    ``min_range_inliers``) samples search ``[0, fallback_max_disparity_fraction · width)``. D is the batch's
    widest range: every pair searches D disparities from its own minimum.

    ``groups`` ``(B, G, P)`` bool (optional): subsets of the samples, e.g. one per kept object. The percentiles
    are then taken within each group that has at least ``min_count`` samples and the pair's range is their
    union, so a small object at a different distance is not cut away as the outer percent of the pixels of a
    big one (measured: a 97-pixel far object of Middlebury Baby2 at 320 px was ranged at 7.5 m instead of
    11.5 m when the percentiles pooled both objects).

    ``tail_bin_px`` (optional, with ``config.in_view_detached_tail_share``): the samples' grid, e.g. the coarse
    pass's pixel. The range's ``in_view_top_px`` is then its top with each group's detached near tail left out
    (:func:`_detached_tail_ceiling`) and, with ``config.in_view_margin="object"``, each group's margin from its own
    span (:func:`_in_view_tops`), and with ``config.in_view_per_object`` and ``groups`` each group's own top too
    (``object_in_view_top_px``); the range searched keeps every sample. Not differentiable (integer ranges)."""
    values = _checked_samples(disparity_px, valid, image_w)
    enough_count = config.min_range_inliers if min_count is None else min_count
    percentiles = (config.range_percentiles[0] / 100, config.range_percentiles[1] / 100)
    share = config.in_view_detached_tail_share if tail_bin_px is not None else None
    object_groups = groups is not None
    if groups is None and share is not None:
        groups = valid.unsqueeze(1)  # the pair's samples as one group, to find its detached tail
    if groups is None:
        count, low, high, trimmed = *_pair_percentiles(disparity_px, values, valid, percentiles), None
    else:
        count, low, high, trimmed = _group_percentiles(disparity_px, values, valid, groups, percentiles,
                                                       enough_count, tail_bin_px, share)
    margin = _margin(low, high, config, extra_margin_px)
    group_tops = None if trimmed is None else _in_view_tops(trimmed, low, config, extra_margin_px)
    enough = count >= max(enough_count, 1)  # a minimum of 0 still needs a sample to take percentiles of
    fallback_high = (image_w.to(torch.float64) * config.fallback_max_disparity_fraction).clamp_min(2)
    low = torch.where(enough, (low - margin).floor().clamp_min(0), torch.zeros_like(low))
    high = torch.where(enough, (high + margin).ceil(), fallback_high.floor())
    high = torch.maximum(high, low + 1)
    span = (high - low + 1).clamp_max(config.max_num_disparities)
    # Around the centre, never past the view's width: no match lies there (a 1e30 px sample overflowed int32).
    low = torch.where(high - low + 1 > span, ((low + high) / 2 - span / 2).floor().clamp_min(0), low).minimum(image_w)
    span = span.clamp_min(2).long()
    num_disparities = int(span.max()) if span.numel() else 2
    in_view_top = object_tops = None
    if group_tops is not None:  # never above the range searched
        top = low + span - 1
        used = group_tops > -torch.inf
        pair_top = torch.where(used.any(dim=1), group_tops.amax(dim=1), 0.0)
        in_view_top = torch.where(enough, torch.minimum(pair_top.ceil(), top), top).long()
        if config.in_view_per_object and object_groups:
            object_tops = torch.where(enough.unsqueeze(1) & used, torch.minimum(group_tops.ceil(), top.unsqueeze(1)),
                                      in_view_top.unsqueeze(1).to(group_tops.dtype)).long()
    return DisparityRange(low.long(), num_disparities, span, in_view_top, object_tops)


def _in_view_tops(trimmed: _Trimmed, low: torch.Tensor, config: DenseConfig,
                  extra_margin_px: float) -> torch.Tensor:
    """Each group's top ``(B, G)`` of the disparities the in-view rule allows for, before it is capped at the
    range searched: its top without its detached near tail (``trimmed`` = used, low and trimmed high, ``(B, G)``
    each), widened by the margin rule; −inf for a group not used. ``config.in_view_margin`` ``"object"``: each
    group's margin from its own span, as if it were ranged alone; ``"pair"``: from the pair's span down to
    ``low``, so another object's far tail of wrong matches (or a far object) widens it. The pair's top is the
    highest (0 where no group is used)."""
    used, group_low, group_high = trimmed
    base = group_low if config.in_view_margin == "object" else low.unsqueeze(1).expand_as(group_low)
    return torch.where(used, group_high + _margin(base, group_high, config, extra_margin_px), -torch.inf)


def _margin(low: torch.Tensor, high: torch.Tensor, config: DenseConfig, extra_margin_px: float) -> torch.Tensor:
    """What the range adds on each side of the samples' ``low``–``high`` percentiles:
    ``max(range_margin_px, range_margin_fraction · span) + extra_margin_px``."""
    return torch.clamp_min((high - low) * config.range_margin_fraction, config.range_margin_px) + extra_margin_px


def _pair_percentiles(disparity_px: torch.Tensor, values: torch.Tensor, valid: torch.Tensor,
                      percentiles: tuple[float, float]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each pair's count of valid samples and their low and high nearest-rank percentiles (``values``: the
    samples in float64): by the compiled selection, or by sorting."""
    selected = _select_nearest_ranks(disparity_px.detach(), valid.long(),
                                     torch.ones(valid.shape[0], 1, dtype=torch.int64, device=valid.device),
                                     percentiles)
    if selected is not None:
        count, (low, high) = selected[0][:, 0], (v[:, 0] for v in selected[1])
    else:
        count = valid.sum(dim=1)
        ordered = sort_last(torch.where(valid, values, torch.full_like(values, torch.inf)))
        low = _nearest_rank(ordered, count, percentiles[0])
        high = _nearest_rank(ordered, count, percentiles[1])
    return count, low, high


def _group_percentiles(disparity_px: torch.Tensor, values: torch.Tensor, valid: torch.Tensor, groups: torch.Tensor,
                       percentiles: tuple[float, float], enough_count: int, tail_bin_px: float | None = None,
                       tail_share: float | None = None
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, _Trimmed | None]:
    """The union over each pair's groups of at least ``enough_count`` samples of their percentile ranges: the
    pair's count of samples in those groups, the lowest low and the highest high (0 where no group has enough).
    With ``tail_bin_px`` and ``tail_share`` also, per group ``(B, G)``, whether it is used, its low and its high
    once it leaves out its detached near tail (:func:`_detached_tail_ceiling`), else None."""
    check_shape(groups, "groups", [disparity_px.shape[0], "G", disparity_px.shape[1]])
    check_dtype(groups, "groups", "bool")
    inside = groups & valid.unsqueeze(1)  # (B, G, P)
    selected = None
    if groups.shape[1] and all_true(count_along(inside, 1) <= 1):  # disjoint groups (objects): one label each
        number = torch.arange(1, groups.shape[1] + 1, device=groups.device)
        member = (inside * number.view(1, -1, 1)).sum(dim=1)  # (B, P): the sample's group + 1, or 0
        selected = _select_nearest_ranks(disparity_px.detach(), member,
                                         number.expand(groups.shape[0], -1), percentiles)
    if selected is not None:
        group_count, (group_low, group_high) = selected
    else:
        group_count = count_along(inside, 2)
        ordered = sort_last(torch.where(inside, values.unsqueeze(1), torch.inf))
        group_low = _nearest_rank(ordered.flatten(0, 1), group_count.flatten(),
                                  percentiles[0]).view_as(group_count)
        group_high = _nearest_rank(ordered.flatten(0, 1), group_count.flatten(),
                                   percentiles[1]).view_as(group_count)
    used = group_count >= enough_count
    low = torch.where(used, group_low, torch.full_like(group_low, torch.inf)).amin(dim=1)
    high = torch.where(used, group_high, torch.full_like(group_high, -torch.inf)).amax(dim=1)
    count = torch.where(used.any(dim=1), group_count.sum(dim=1), torch.zeros_like(group_count[:, 0]))
    low, high = torch.where(used.any(dim=1), low, 0.0), torch.where(used.any(dim=1), high, 0.0)
    trimmed = None
    if tail_bin_px is not None and tail_share is not None:
        ceiling = _detached_tail_ceiling(values, inside, tail_bin_px, tail_share)
        trimmed = used, group_low, torch.minimum(group_high, ceiling)
    return count, low, high, trimmed


def _detached_tail_ceiling(values: torch.Tensor, inside: torch.Tensor, bin_px: float, share: float
                           ) -> torch.Tensor:
    """Per group ``(B, G)``: the ceiling of its samples ``values`` ``(B, P)`` (``inside`` ``(B, G, P)``) once a
    detached near tail is left out. The samples are binned by ``bin_px``; the lowest empty bin above the group's
    median bin with at most ``share`` of its samples above it ends the group (the ceiling is that bin's lower
    edge); ``inf`` where there is none. Why: a coarse pass over noisy frames (JPEG, sensor noise, a lighting
    change) finds a few percent of wrong matches, often in clusters far above the true disparities, enough to
    lift the 99th percentile two- or threefold (tuned PianoL at native size, JPEG digit 2: 35–87 against true
    8–26 working pixels), and an object near the left border then lies in the band the in-view rule leaves
    unranged (``DepthConfig.min_object_pixels_in_view``; measured: a Playroom object at JPEG digit 7, PianoL at
    native size, digits 2 and 3)."""
    b, g, _ = inside.shape
    if values.shape[1] == 0:
        return torch.full((b, g), torch.inf, dtype=torch.float64, device=values.device)
    wanted = inside.any(dim=1)
    bins = torch.where(wanted, values / bin_px, 0.0).nan_to_num(0.0, 0.0, 0.0).floor().clamp_min(0).long()  # (B, P)
    num_bins = int(bins.max()) + 2
    hist = torch.zeros(b, g, num_bins, dtype=torch.float64, device=values.device)
    hist.scatter_add_(2, bins.unsqueeze(1).expand(b, g, -1), inside.to(torch.float64))
    total = hist.sum(dim=2, keepdim=True)
    below = hist.cumsum(dim=2) - hist  # samples in lower bins
    above = total - below - hist  # samples in higher bins
    index = torch.arange(num_bins, device=values.device).view(1, 1, -1)
    median = ((below + hist) < total / 2).sum(dim=2, keepdim=True)  # the bin holding the median sample
    cut = (hist == 0) & (index > median) & (above <= share * total)
    high_bin = torch.where(cut, index, num_bins).amin(dim=2)
    return torch.where(high_bin < num_bins, high_bin.to(torch.float64) * bin_px, torch.inf)


def _unique_where_checked(inside: torch.Tensor, full: DisparityRange, min_count: int) -> torch.Tensor:
    """The coarse samples ``inside`` ``(B, 1, h, w)`` bool of a pass over ``full``, flattened ``(B, h·w)``; none
    for a pair with fewer than ``min_count`` of them, or under a quarter of them, where the right view holds every
    disparity searched (column ≥ the range's top). Left of that the border hides the candidates past the column,
    so a repeated pattern (a chessboard, tiles, a fence) that the uniqueness check rejects everywhere else is
    unique there at its farthest alias: a board shifted 8 px with a 32 px period, pixel for pixel the pair shifted
    40 px, was searched over [2, 14) only and ranged at 3.7 m, "OK", where 0.74 m fits it as well (smoothed by the
    retries, its right border's blur passed 128 of 1280 coarse pixels; an audit). Such a pair searches the fallback
    range, which the in-view rule leaves its left band out of. A real pair's left band holds about a quarter of
    the columns, not its samples' majority (none of the shared pairs at 320 px or native size changed)."""
    top = (full.min_disparity_px + (full.num_disparities if full.pair_num_disparities is None
                                    else full.pair_num_disparities) - 1)
    columns = torch.arange(inside.shape[-1], device=inside.device)
    checked = count_along((inside & (columns >= top.view(-1, 1, 1, 1))).flatten(1), 1, keepdim=True)
    inside = inside.flatten(1)
    return inside & (checked >= min_count) & (4 * checked >= count_along(inside, 1, keepdim=True))


def coarse_search_range(left: torch.Tensor, right: torch.Tensor, mask: torch.Tensor, image_hw: torch.Tensor,
                        config: DenseConfig = DenseConfig(), objects: torch.Tensor | None = None
                        ) -> DisparityRange:
    """The search range of each pair from a coarse pass: the images reduced ``f`` times (``f ≈ W /
    coarse_width_px``, box average), matched over the whole fallback range ``[0, fraction · W / f)`` inside
    the reduced kept regions, and the range of what survives the rejections, scaled back by ``f`` with an
    ``f``-pixel allowance for the coarse grid. This needs no sparse inlier (a pair whose features failed still
    gets a range) and is not fooled by a wrong same-row inlier. It costs about ``1 / f³`` of a full search.
    ``objects`` ``(B, N, H, W)`` bool (optional): one mask per kept object; the range is then the union of the
    objects' ranges (see ``groups`` of :func:`disparity_search_range`). Not differentiable (integer ranges)."""
    b = _check_pair(left, right, config)
    _, _, h, w = left.shape
    check_shape(mask, "mask", [b, 1, h, w])
    check_dtype(mask, "mask", "bool")
    image_hw = _check_sizes(image_hw, left)
    factor = reduction_factor(w, config.coarse_width_px, h)
    small_hw = torch.div(image_hw, factor, rounding_mode="floor").clamp_min(1)
    if objects is not None:
        check_shape(objects, "objects", [b, "N", h, w])
        check_dtype(objects, "objects", "bool")
    if factor > 1:
        left, right = mean_pool(left, factor), mean_pool(right, factor)
        mask = _any_pool(mask, factor)
        if objects is not None:
            objects = _any_pool(objects, factor)
    full = disparity_search_range(left.new_zeros(b, 0), mask.new_zeros(b, 0), small_hw[:, 1], config)
    # The coarse pass only bounds the search: plain block matching (no left band rule, no aggregation).
    plain = replace(config, whole_range_in_view=False, smoothing_penalties=None)
    coarse = dense_disparity_over_regions(left, right, mask, full, plain, small_hw)
    samples = (coarse.disparity_px * factor).flatten(1)
    inside = _unique_where_checked(coarse.valid & mask, full, config.min_range_pixels)
    groups = None if objects is None else objects.flatten(2)
    return disparity_search_range(samples, inside, image_hw[:, 1], config, extra_margin_px=factor,
                                  min_count=config.min_range_pixels, groups=groups, tail_bin_px=factor)
