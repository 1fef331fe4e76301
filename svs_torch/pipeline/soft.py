"""The differentiable pass of :func:`~svs_torch.pipeline.estimate_obstacle_depth` (``differentiable=True``):
the same estimator as the hard pipeline, softened only where a hard step blocks gradients.

The hard pipeline runs first, without gradients, and makes every discrete decision: the kept regions, each
pair's search range and crop box, RANSAC's inliers, the rectification choice and homographies, the dense
stage's winners and rejections, the row fill's sources, the verification. This pass then recomputes the
continuous quantities from the images (and the segmenter's logits) given those decisions:

1. **Dense disparity** at the pixels that reach an object's statistics: the SAD costs at the hard winner and
   its two neighbours, from the images with gradients (same pre-filter, same 1/255 levels: rounded values,
   identity gradient), then the same equiangular sub-pixel fit (:func:`subpixel_disparity`). The values are
   the hard stage's, bit for bit; the gradient reaches both images through the costs. Where the hard winner
   came from a semi-globally aggregated volume (:mod:`svs_torch.depth.semi_global`), its sub-pixel fit is
   still on the plain costs; where that fit's value is not the hard one (a fit saturated at ±0.5), the hard value
   is kept, straight-through.
2. **Row fill** of invalid pixels as the hard stage does (:func:`~svs_torch.depth.block_matching.fill_invalid_rows`,
   whose torch path is differentiable), with the hard validity as the mask; none where ``DenseConfig.fill_invalid``
   is off, as none in the hard statistics.
3. **Object depth** as a *band mean* (:func:`band_mean`): each quantile the hard stage reports (median, low and
   high percentile) is replaced by the weighted mean of the object's depths whose hard rank lies within
   ``BAND_HALF_WIDTH`` of it (always with the two order statistics it interpolates), so the gradient reaches
   every pixel of that band rather than the one or two a median interpolates. The low percentile's band is
   ranked over the pixels the hard stage took it over (``DepthConfig.surface_within_in_view_top``), filled from
   them as the hard stage filled them. The weights are the segmenter's probabilities (sigmoid of its logits)
   over the hard kept regions, 1 for Otsu: the estimator is the same, and gradients reach the network's weights.
   Measured on the 28 held-out scenes (320×240 and native, Otsu and learned): every median within 0.41 % of the
   hard one; the 10th / 90th percentiles, over a long tail of far pixels, within 0.5 % for 95–100 % / 87–95 % of
   the objects. The nearest obstacle and R_min / R_max are the objects the hard pipeline named, with these soft
   values (a discrete choice this pass never makes again).

4. **Geometry**: pairs rectified from F are warped by the hard homographies carrying gradients to both images
   (:mod:`~svs_torch.geometry.soft`: the LK-refined matches, F refitted by the weighted 8-point on RANSAC's
   inliers, Hartley's rectification of it, each straight-through onto the hard values); the warp is
   differentiable in the images and the homographies. Row-aligned pairs' similarities are refitted on the
   alignment's inliers the same way.
"""

from __future__ import annotations

import dataclasses

import torch

from ..core.checks import InputError, check_count, check_dtype, check_dtypes, check_shape
from ..core.numerics import per_pair
from ..depth.block_matching import fill_invalid_rows
from ..depth.cost_volume import prefilter_xsobel
from ..depth.dense import working_factor, working_window
from ..depth.dense_config import DenseConfig, DenseDisparity
from ..depth.depth_types import DepthResult, ObjectDepths
from ..depth.pooling import mean_pool
from ..depth.winner import equiangular_offset
from ..geometry.rectification import warp_rectified, warp_views
from .soft_slots import nearest_at_hard_slot, range_at_hard_slots
from .stages import warp_labels, warped_where

__all__ = ["BAND_HALF_WIDTH", "band_mean", "differentiable_depth", "quantize_straight_through", "soft_dense_depth",
           "subpixel_disparity"]

#: Half width of each quantile's band, as a share of the object's pixels: the median becomes the weighted mean
#: of the depths ranked 49–51 % (a hundred pixels of a 5000-pixel object).
#: ``experiments/differentiable_agreement.py`` on the 28 held-out scenes at 320×240 (default): medians within 0.5 %
#: of the hard ones for 85 % of objects at a half width of 0.05, 98 % at 0.02, 100 % at 0.01 (largest difference
#: 0.15 %): an object's depths are often spread or bimodal around its median, so a wide band's mean is not it.
BAND_HALF_WIDTH = 0.01


def quantize_straight_through(image: torch.Tensor) -> torch.Tensor:
    """``round(255 · image)`` (the hard stage's :func:`~svs_torch.depth.dense.quantize_levels`, the same values bit for
    bit) with the gradient of ``255 · image``: a straight-through rounding, so the costs built on it pass
    gradients to the images. ``image`` float32 or float64, as the hard stage's: a uint8 one's ``255 · image`` wrapped
    around modulo 256 in silence (2 became 254), a bool one's was 0 / 255 (an audit)."""
    check_dtype(image, "image", "float")
    scaled = image * 255
    return torch.round(scaled).detach() + (scaled - scaled.detach())


def _window_costs(left: torch.Tensor, right: torch.Tensor, pixels: torch.Tensor, disparities: torch.Tensor,
                  window_size: int) -> torch.Tensor:
    """SAD costs ``(P, C)`` of the left pixels ``pixels`` ``(P, 3)`` (pair, row, column) of images ``(B, 1, H, W)``
    at the integer disparities ``(P, C)``: ``Σ_window |L(y+v, x+u) − R(y+v, x+u−d)|``, every read clamped to the
    frame (replicate border), as the hard stage's crops read. Differentiable w.r.t. both images.

    Both images are padded by replicating their borders far enough that every read lands inside, so one flat
    index per window pixel serves the left read and, shifted by ``d``, the right one (no clamp per read)."""
    b, _, h, w = left.shape
    radius = window_size // 2
    reach = int(disparities.max()) if disparities.numel() else 0
    pad_left = radius + max(reach, 0) + 1
    pad_right = radius + max(-int(disparities.min()) if disparities.numel() else 0, 0) + 1
    padding = (pad_left, pad_right, radius, radius)
    stride = w + pad_left + pad_right
    left_flat = torch.nn.functional.pad(left, padding, mode="replicate").reshape(-1)
    right_flat = torch.nn.functional.pad(right, padding, mode="replicate").reshape(-1)
    offsets = torch.arange(window_size, device=left.device)
    window = (offsets.view(-1, 1) * stride + offsets).flatten()  # (K²,) from the window's top-left
    corner = (pixels[:, 0] * (h + 2 * radius) + pixels[:, 1]) * stride + pixels[:, 2] + pad_left - radius
    index = corner.view(-1, 1) + window  # (P, K²)
    # index_select rather than advanced indexing: 3x faster forward and backward on this CPU.
    # Sizes spelled out, not -1: a pair with no kept object gives P = 0, where -1 is ambiguous.
    left_values = left_flat.index_select(0, index.flatten()).view(index.shape[0], 1, index.shape[1])  # (P, 1, K²)
    right_index = (index.unsqueeze(1) - disparities.unsqueeze(-1)).flatten()
    right_values = right_flat.index_select(0, right_index).view(*disparities.shape, index.shape[1])  # (P, C, K²)
    return (left_values - right_values).abs().sum(dim=-1)


def _check_fit_shapes(left: torch.Tensor, right: torch.Tensor, pixels: torch.Tensor, winner: torch.Tensor,
                      min_disparity_px: torch.Tensor, image_w: torch.Tensor, window_size: int,
                      costs: torch.Tensor | None) -> None:
    """:func:`subpixel_disparity`'s shapes, window and pixels named: called by hand, each of another shape (pixels
    without their pair column, a winner or bounds of another length, a pixel outside the images) failed in an
    index deep inside torch, and an even or zero window was taken (an audit)."""
    b, h, w = check_shape(left, "left", ["B", 1, "H", "W"]).values()
    check_shape(right, "right", [b, 1, h, w])
    p = check_shape(pixels, "pixels", ["P", 3])["P"]
    check_shape(winner, "winner", [p])
    for name, value in (("min_disparity_px", min_disparity_px), ("image_w", image_w)):
        check_shape(value, name, [b])
        check_dtype(value, name, "int")
    if costs is not None:
        check_shape(costs, "costs", [p, 3])
    check_count(window_size, "window_size", least=1)
    if window_size % 2 == 0:
        raise InputError(f"window_size: expected an odd int >= 1, got {window_size!r}")
    if p and not bool(((pixels >= 0) & (pixels < torch.tensor([b, h, w], device=pixels.device))).all()):
        raise InputError(f"pixels: expected (pair, row, column) rows inside the images' (B, H, W) = ({b}, {h}, {w})")


def subpixel_disparity(left: torch.Tensor, right: torch.Tensor, pixels: torch.Tensor, winner: torch.Tensor,
                       min_disparity_px: torch.Tensor, image_w: torch.Tensor, window_size: int,
                       costs: torch.Tensor | None = None) -> torch.Tensor:
    """The hard stage's sub-pixel disparity ``(P,)`` at ``pixels`` ``(P, 3)`` (pair, row, column) given its
    integer winner ``(P,)`` int64: ``winner + offset``, the equiangular (V) fit through the SAD costs at
    ``winner − 1, winner, winner + 1`` of the pre-filtered images ``(B, 1, H, W)`` (or given as ``costs``
    ``(P, 3)``); offset 0 where the hard stage has no interior fit (the winner at its pair's ``min_disparity_px``
    ``(B,)``, or a neighbour's right pixel outside the pair's width ``image_w`` ``(B,)``). Differentiable w.r.t.
    both images (the winner is a constant)."""
    check_dtypes(left=(left, "float"), right=(right, "float"), pixels=(pixels, "int"), winner=(winner, "int"))
    _check_fit_shapes(left, right, pixels, winner, min_disparity_px, image_w, window_size, costs)
    if costs is None:
        costs = _window_costs(left, right, pixels, winner.unsqueeze(1) + torch.arange(-1, 2, device=left.device),
                              window_size)
    width, minimum = image_w[pixels[:, 0]], min_disparity_px[pixels[:, 0]]
    interior = ((winner > minimum) & (pixels[:, 2] - winner - 1 >= 0) & (pixels[:, 2] - winner + 1 < width))
    offset = equiangular_offset(costs[:, 0], costs[:, 1], costs[:, 2])
    return winner.to(left.dtype) + torch.where(interior, offset, torch.zeros_like(offset))


def _fit_at_winners(left: torch.Tensor, right: torch.Tensor, pixels: torch.Tensor, disparity: torch.Tensor,
                    minimum: torch.Tensor, counts: torch.Tensor, image_w: torch.Tensor, window_size: int
                    ) -> torch.Tensor:
    """:func:`subpixel_disparity` at the hard stage's integer winners, recovered from its sub-pixel disparity
    ``(P,)``: ``winner + offset`` with the offset in [−0.5, 0.5], so the winner is the nearest integer except where
    the offset is ±0.5 (a tie of the winner with a neighbour) or within round-off of it; there the winner is the
    least cost (first on ties) of the two integers around the value, inside the pair's range [``minimum``,
    ``minimum + counts``) and the right view, found without gradients."""
    with torch.no_grad():
        winner = disparity.round().long()
        near_half = ((disparity - winner).abs() > 0.5 - 1e-3).nonzero().squeeze(1)
        if near_half.numel():
            candidates = disparity[near_half].floor().long().unsqueeze(1) + torch.arange(2, device=left.device)
            at = pixels[near_half]
            costs = _window_costs(left, right, at, candidates, window_size)
            pair, right_x = at[:, 0:1], at[:, 2:3] - candidates
            usable = ((candidates >= minimum[pair]) & (candidates < (minimum + counts)[pair]) & (right_x >= 0)
                      & (right_x < image_w[pair]))
            costs = torch.where(usable, costs, torch.full_like(costs, torch.inf))
            winner[near_half] = candidates.gather(1, costs.argmin(dim=1, keepdim=True)).squeeze(1)
    return subpixel_disparity(left, right, pixels, winner, minimum, image_w, window_size)


def _soft_disparity(left: torch.Tensor, right: torch.Tensor, dense: DenseDisparity, wanted: torch.Tensor,
                    image_hw: torch.Tensor, config: DenseConfig) -> torch.Tensor:
    """The dense map ``(B, 1, H, W)``: the hard values everywhere, recomputed with gradients at the valid pixels
    of ``wanted`` ``(B, 1, H, W)`` (on the working grid the hard stage matched on, then enlarged as it is)."""
    height, width = left.shape[-2:]
    factor = working_factor(width, config, height)
    if factor > 1:
        left, right = mean_pool(left, factor), mean_pool(right, factor)
    if config.prefilter == "xsobel":
        left, right = prefilter_xsobel(left, config.prefilter_cap), prefilter_xsobel(right, config.prefilter_cap)
    left, right = quantize_straight_through(left), quantize_straight_through(right)
    h, w = left.shape[-2:]
    hard = dense.disparity_px[..., ::factor, ::factor][..., :h, :w] / factor
    pick = (wanted & dense.valid)[..., ::factor, ::factor][..., :h, :w]
    if factor > 1:  # a working pixel is wanted when any pixel of its block is
        pick = pick | torch.nn.functional.max_pool2d(
            (wanted & dense.valid)[..., :h * factor, :w * factor].to(left.dtype), factor).bool()
    pixels = pick[:, 0].nonzero()  # (P, 3) pair, row, column
    small_w = torch.div(image_hw[:, 1], factor, rounding_mode="floor").clamp_min(1)
    minimum = torch.div(dense.min_disparity_px, factor, rounding_mode="floor")
    counts = torch.div(dense.pair_num_disparities, factor, rounding_mode="floor")
    values = hard[:, 0][pixels.unbind(1)]
    soft = _fit_at_winners(left, right, pixels, values, minimum, counts, small_w, working_window(width, config))
    # The recomputed values equal the hard ones (bit for bit) except where the winner came from an aggregated volume
    # (DenseConfig.retry_smoothing_penalties) and its plain fit saturates at ±0.5: the winner recovered from the
    # value may then be its neighbour, a step of about a pixel, or the same winner a fraction of a thousandth off.
    # There the hard value is kept, straight-through, as hard + (soft − soft): exactly it. A tolerance of 1e-3 let
    # the latter through, and the depths then differed from those under no_grad, which read the hard map (an audit).
    values = values.to(soft.dtype)
    soft = torch.where(soft.detach() != values, values + (soft - soft.detach()), soft)
    flat = hard.detach().to(soft.dtype).flatten()
    index = (pixels[:, 0] * h + pixels[:, 1]) * w + pixels[:, 2]
    small = flat.index_put((index,), soft).view(-1, 1, h, w)
    grown = (small * factor).repeat_interleave(factor, dim=-2).repeat_interleave(factor, dim=-1)
    grown = torch.nn.functional.pad(grown, (0, width - grown.shape[-1], 0, height - grown.shape[-2]))
    return torch.where(dense.valid, grown, torch.zeros_like(grown))


def band_mean(values: torch.Tensor, weights: torch.Tensor, band: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Weighted mean of ``values`` ``(B, P)`` over each band ``(B, M, P)`` bool with ``weights`` ``(B, P)``:
    ``(B, M)`` and whether the band had any weight. Differentiable w.r.t. values and weights (the band is a
    constant). ``values`` float32 or float64: float16's sums overflowed (20 000 depths of 8 m: a mean of inf).
    Mismatched shapes or a float band failed in torch's broadcasting or ``where`` (an audit): refused by name."""
    b, p = check_shape(values, "values", ["B", "P"]).values()
    check_shape(weights, "weights", [b, p])
    check_shape(band, "band", [b, "M", p])
    check_dtypes(values=(values, "float"), band=(band, "bool"))
    members = band.to(values.dtype) * weights.unsqueeze(1)
    total = members.sum(dim=-1)
    some = total > 0
    # Only the band's values count: a NaN outside it made 0 · NaN = NaN (an audit).
    inside = torch.where(band, values.unsqueeze(1), torch.zeros_like(members))
    mean = (members * inside).sum(dim=-1) / torch.where(some, total, torch.ones_like(total))
    return mean, some


def _bands(depth: torch.Tensor, members: torch.Tensor, slots: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """``(B, N, Q, P)`` bool: each slot's members (``members == slots[:, n]``, ``(B, P)``) whose rank among them
    by ``depth`` ``(B, P)`` lies in ``[⌊(q − h)(n − 1)⌋, ⌈(q + h)(n − 1)⌉]``, h = ``BAND_HALF_WIDTH``: a band that
    always holds the two order statistics the hard quantile interpolates (no gradient)."""
    with torch.no_grad():
        b, p = depth.shape
        position = torch.arange(p, device=depth.device).expand(b, p)
        bands = []
        for n in range(slots.shape[1]):
            member = members == slots[:, n:n + 1]  # (B, P)
            order = torch.where(member, depth, torch.full_like(depth, torch.inf)).argsort(dim=1)
            rank = torch.empty_like(position).scatter_(1, order, position)
            last = (member.sum(dim=1, keepdim=True) - 1).clamp_min(0).to(torch.float64)  # (B, 1)
            low = ((q - BAND_HALF_WIDTH).clamp(0, 1) * last).floor().long()  # (B, Q)
            high = ((q + BAND_HALF_WIDTH).clamp(0, 1) * last).ceil().long()
            bands.append(member.unsqueeze(1) & (rank.unsqueeze(1) >= low.unsqueeze(-1))
                         & (rank.unsqueeze(1) <= high.unsqueeze(-1)))
        if not bands:
            return torch.zeros(b, 0, q.numel(), p, dtype=torch.bool, device=depth.device)
        return torch.stack(bands, dim=1)


def _fill_sources(valid: torch.Tensor, needed: torch.Tensor) -> torch.Tensor:
    """The valid pixels each ``needed`` invalid pixel of ``(..., W)`` rows is filled from (its nearest valid
    pixel either side, :func:`~svs_torch.depth.block_matching.fill_invalid_rows`), or-ed into ``needed``."""
    width = valid.shape[-1]
    index = torch.arange(width, device=valid.device).expand_as(valid)
    left_index = torch.where(valid, index, -1).cummax(dim=-1).values
    right_index = torch.where(valid, index, width).flip(-1).cummin(dim=-1).values.flip(-1)
    fill = needed & ~valid
    counts = torch.zeros(needed.shape, dtype=torch.int32, device=needed.device)
    for source in (left_index, right_index):
        usable = fill & (source >= 0) & (source < width)
        # Added, not written: several filled pixels share a source, and a plain scatter's order is not defined.
        counts = counts.scatter_add(-1, torch.where(usable, source, index), usable.to(torch.int32))
    return needed | (counts > 0)


def _filled(disparity: torch.Tensor, valid: torch.Tensor, fill: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """``disparity`` with its invalid pixels filled from their rows where ``fill`` (``DenseConfig.fill_invalid``,
    as the hard statistics take them), and where it is defined."""
    return fill_invalid_rows(disparity, valid) if fill else (disparity, valid)


def _ranked_bands(dense: DenseDisparity, valid: torch.Tensor, in_box: torch.Tensor, scale: torch.Tensor,
                  doffs: torch.Tensor, labels: torch.Tensor, slots: torch.Tensor, q: torch.Tensor, fill: bool
                  ) -> tuple[torch.Tensor, ...]:
    """Without gradients, from the hard map filled from its ``valid`` pixels ``(B, 1, H, W)`` where ``fill``: the
    filled disparity ``(B, 1, H, W)``, which pixels count ``(B, P)``, each slot's bands of quantiles ``q``
    (:func:`_bands`, ``(B, N, Q, P)``), the pixels those depend on, fill sources included ``(B, 1, H, W)``, and
    each pixel's slot label where it counts ``(B, P)`` (0 elsewhere)."""
    with torch.no_grad():
        filled, reachable = _filled(dense.disparity_px, valid, fill)
        ok = (reachable & in_box).flatten(1) & (filled.flatten(1) + doffs > 0)
        depth = torch.where(ok, scale / torch.where(ok, filled.flatten(1) + doffs, 1.0), 0.0)
        ok &= torch.isfinite(depth) & (depth > 0)
        members = torch.where(ok, labels.flatten(1), torch.zeros_like(labels.flatten(1)))
        bands = _bands(depth.to(torch.float64), members, slots, q)
        needed = bands.any(dim=(1, 2)).view_as(valid)
        needed = _fill_sources(valid, needed) if fill else needed
    return filled, ok, bands, needed, members


def _measured_per_slot(members: torch.Tensor, valid: torch.Tensor, slots: torch.Tensor) -> torch.Tensor:
    """Each slot's measured (not filled) pixels ``(B, N)``, as the hard statistics count them: its ``members``
    ``(B, P)`` (:func:`_ranked_bands`) that are ``valid`` ``(B, 1, H, W)``."""
    measured = [((members == slots[:, n:n + 1]) & valid.flatten(1)).sum(1) for n in range(slots.shape[1])]
    return torch.stack(measured, 1) if measured else torch.zeros_like(slots)


def _band_means(disparity: torch.Tensor, dense: DenseDisparity, ranked: tuple, valid: torch.Tensor,
                scale: torch.Tensor, doffs: torch.Tensor, weights: torch.Tensor, fill: bool
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """Each band's weighted mean depth ``(B, N, Q)`` and whether it had weight, from the soft ``disparity``
    filled from ``valid`` as the hard map was where ``fill`` (``ranked``: :func:`_ranked_bands`' result for that
    mask)."""
    filled, ok, bands = ranked[:3]
    if disparity.requires_grad or disparity.dtype != dense.disparity_px.dtype:
        filled, _ = _filled(disparity, valid, fill)
    # Pair by pair: batched, a pair's sums over its pixels (bands, calibration gradients) moved with the batch's size.
    means, some = per_pair(lambda s, d, f, o, w, band: band_mean(torch.where(o, s / torch.where(o, f + d, 1.0), 0.0),
                                                                 w.to(s.dtype), band),
                           scale, doffs, filled.flatten(1), ok, weights.flatten(1), bands.flatten(1, 2))
    b, n, k = bands.shape[:3]
    return means.view(b, n, k), some.view(b, n, k)


def soft_dense_depth(left: torch.Tensor, right: torch.Tensor, labels: torch.Tensor, weights: torch.Tensor,
                     dense: DenseDisparity, hard: DepthResult, focal_px: torch.Tensor, baseline_m: torch.Tensor,
                     doffs_px: torch.Tensor, image_hw: torch.Tensor, percentiles: tuple[float, float],
                     config: DenseConfig, coarse: torch.Tensor | None = None,
                     coarse_config: DenseConfig | None = None, surface_valid: torch.Tensor | None = None
                     ) -> DepthResult:
    """``hard`` (the dense rule's :class:`~svs_torch.depth.DepthResult`) with each object's median, low and high
    depth, the nearest obstacle and the range recomputed as the module docstring says, from images ``(B, 1, H,
    W)`` (rectified where the hard stage rectified), the left ``labels`` and pixel ``weights`` in the same
    pixels, and the hard ``dense`` map. Differentiable w.r.t. the images, ``weights`` and the calibration;
    validity and counts are the hard ones. The pairs ``coarse`` ``(B,)`` bool were measured under
    ``coarse_config`` (half the working width: ``PipelineConfig.coarse_retry_below_share``), the rest under
    ``config``. ``surface_valid`` ``(B, 1, H, W)`` bool (optional): the pixels the low percentile is taken over
    where an object has a measured pixel among them, as the hard stage took it
    (:func:`~svs_torch.depth.dense_objects.dense_object_depths`)."""
    b = left.shape[0]
    # In the images' dtype, as the hard stage's depths are (a float64 calibration with float32 images made every
    # soft depth float64 beside the hard ones' float32); the cast keeps the calibration's gradients.
    focal_px, baseline_m, doffs_px = (v.to(left.dtype) for v in (focal_px, baseline_m, doffs_px))
    slots = hard.objects.label
    x0, y0, box_w, box_h = (v.view(-1, 1, 1, 1) for v in dense.crop_xywh.unbind(1))
    rows = torch.arange(left.shape[-2], device=left.device).view(1, 1, -1, 1)
    cols = torch.arange(left.shape[-1], device=left.device).view(1, 1, 1, -1)
    in_box = (rows >= y0) & (rows < y0 + box_h) & (cols >= x0) & (cols < x0 + box_w)
    scale = (focal_px * baseline_m).view(b, 1)
    doffs = doffs_px.view(b, 1)
    q = torch.tensor([0.5, percentiles[0] / 100, percentiles[1] / 100], dtype=torch.float64, device=left.device)
    fill = config.fill_invalid
    ranked = _ranked_bands(dense, dense.valid, in_box, scale, doffs, labels, slots, q, fill)
    needed = ranked[3]
    if surface_valid is not None:  # the nearest surface's band, over its own filled pixels
        surface = _ranked_bands(dense, surface_valid, in_box, scale, doffs, labels, slots, q[1:2], fill)
        needed = needed | surface[3]
    if coarse is not None and bool(coarse.any()):  # each pair on the working grid its hard map was measured on
        disparity = dense.disparity_px
        for group, settings in ((~coarse, config), (coarse, coarse_config)):
            group = group.view(-1, 1, 1, 1)
            if bool((needed & group).any()):
                part = _soft_disparity(left, right, dense, needed & group, image_hw, settings)
                disparity = torch.where(group, part, disparity)
    else:
        disparity = _soft_disparity(left, right, dense, needed, image_hw, config)
    means, some = _band_means(disparity, dense, ranked, dense.valid, scale, doffs, weights, fill)
    valid = hard.objects.valid & some.all(dim=-1)
    if surface_valid is not None:
        surface_means, surface_some = _band_means(disparity, dense, surface, surface_valid, scale, doffs, weights,
                                                  fill)
        # As the hard statistics: where the object has a measured pixel there (the fill reaches across objects).
        measured = _measured_per_slot(surface[4], surface_valid, slots)
        low = torch.where(surface_some[..., 0] & (measured > 0), surface_means[..., 0], means[..., 1])
        means = torch.stack([means[..., 0], low, means[..., 2]], dim=-1)
    median, low, high = torch.where(valid.unsqueeze(-1), means, torch.zeros_like(means)).unbind(-1)
    soft: ObjectDepths = dataclasses.replace(hard.objects, depth_median_m=median, depth_low_m=low, depth_high_m=high,
                                             valid=valid)
    ranged = range_at_hard_slots(hard.objects, soft, focal_px, baseline_m, doffs_px)
    return DepthResult(hard.disparities, hard.points, ranged, soft, nearest_at_hard_slot(hard.nearest, soft))


def differentiable_depth(left: torch.Tensor, right: torch.Tensor, labels: torch.Tensor,
                         logits: torch.Tensor | None, rectified: torch.Tensor, H_left: torch.Tensor,
                         H_right: torch.Tensor, dense: DenseDisparity, hard: DepthResult, focal_px: torch.Tensor,
                         baseline_m: torch.Tensor, doffs_px: torch.Tensor, image_hw: torch.Tensor,
                         percentiles: tuple[float, float], config: DenseConfig, coarse: torch.Tensor | None = None,
                         coarse_config: DenseConfig | None = None, surface_valid: torch.Tensor | None = None
                         ) -> DepthResult:
    """:func:`soft_dense_depth` of a pipeline's batch: images ``(B, 1, H, W)``, the left ``labels`` and obstacle
    ``logits`` (None: every kept pixel weighs 1, the Otsu segmenter) in input pixels, warped by the hard homographies
    ``(B, 3, 3)`` where ``rectified`` ``(B,)`` (the hard stage's choice), as the dense stage warps them; the pairs
    ``coarse`` on ``coarse_config``'s working grid; ``surface_valid`` (optional): the map's pixels the low
    percentile is taken over (:func:`soft_dense_depth`). Differentiable w.r.t. both images, the logits, the
    calibration and the homographies."""
    weights = torch.ones_like(left) if logits is None else torch.sigmoid(logits).to(left.dtype)
    if bool(rectified.any()):  # only the rectified pairs warped, as the hard dense stage does (warped_where)
        H_left, H_right = H_left.to(left.dtype), H_right.to(left.dtype)
        left = warped_where(left, H_left, rectified, warp_views)
        right = warped_where(right, H_right, rectified, warp_views)
        weights = warped_where(weights, H_left, rectified, warp_rectified)
        labels = warped_where(labels, H_left.detach(), rectified, warp_labels)
    return soft_dense_depth(left, right, labels, weights, dense, hard, focal_px, baseline_m, doffs_px, image_hw,
                            percentiles, config, coarse, coarse_config, surface_valid)
