"""Which alias of a repeated pattern is the object (a fence, a railing, a grate)?

Over a pattern that repeats along the rows every window's SAD has a minimum at the true disparity and one a period
away on either side. Which one passes the uniqueness rule is left to the sensor noise, JPEG and a loose rig's small
turn and scale, window by window, and an object's median over its windows can land periods off: on rendered panels
as a loose rig's camera frames, the pipeline ranged a 1.5 m panel of 8 px bars at 0.50 m and a 2.0 m checker at
0.54 m (``experiments/repeated_patterns.md``). The object as a whole does not repeat: its ends meet what lies
beside it, and shifted by a period, a period's width of its columns at one end is compared with the background.
The mean SAD over the whole object, shift by shift, is least at the true disparity, where the object's ends are in
view (a fragment of a panel has none, and its least shift is as much a matter of noise as its windows'). Two
measurements of the alias, then: where the median of the object's windows lies within half a period of the whole
object's shift, they agree, and the object is matched again over that period, where no other alias lies and the
uniqueness rule passes the windows it rejected for their aliases; where they disagree, neither is trusted and the
object's pixels are dropped: a walker is told no distance rather than a wrong one. So are they where no end tells
the whole object's alias from the others (a board filling both views fits every alias alike). Such an object is
still one the walker faces: the distances its aliases would give (:func:`alias_depths_m`) are what can be said of
it, the nearest of them the nearest it can be.
"""

from __future__ import annotations

import dataclasses

import torch
import torch.nn.functional as F

from ..core.checks import check_dtype, check_shape
from .cost_volume import prefilter_xsobel
from .dense import dense_disparity_in_range, working_factor, working_range
from .dense_config import DenseConfig, DenseDisparity, RepeatedObjects
from .periodicity import MAX_PERIOD_PX, object_periods
from .pooling import mean_pool
from .quantiles import masked_quantile

__all__ = ["alias_depths_m", "nearest_alias_depth_m", "remeasure_on_alias", "settle_aliases", "settle_repeated_objects",
           "whole_object_disparity"]

#: Shifts per slice of the difference volume: ``B × H × SHIFTS_PER_SLICE × W`` floats at a time.
SHIFTS_PER_SLICE = 16
#: Least share of an object's pixels whose match must lie inside the right view for a shift to count.
MIN_IN_VIEW_SHARE = 0.5
#: How much more an alias half a period or more away must cost than the whole object's best shift, over the pixels
#: in view at every shift, for the two to be told apart, in units of the object's mean |x-Sobel|: a board rolled
#: across both views ties to the rounding (``tests/pipeline/test_degenerate_views.py``); 0.001-0.003 ranged the
#: same rendered panels, 0.01 four fewer on the board's camera frames (experiments/repeated_patterns.md).
MIN_ALIAS_MARGIN = 0.002


def _shift_costs(left: torch.Tensor, right: torch.Tensor, objects: torch.Tensor, num_shifts: int
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """Two ``(B, N, num_shifts)`` costs from one difference volume, for d = 0 … num_shifts − 1: the mean
    ``|left(x) − right(x − d)|`` over each object's pixels whose match lies in view, inf where fewer than
    :data:`MIN_IN_VIEW_SHARE` of them do; and the same over the pixels whose match lies in view at every shift
    (columns ≥ num_shifts − 1), the same pixels for all, where a pattern's aliases cost alike to the rounding, inf
    where an object has none. ``left``, ``right`` ``(B, H, W)``; ``objects`` ``(B, N, H, W)`` float (1 inside).

    Over the box holding every object only, the right view's shifted copies read as one strided view
    (``unfold``), not gathered: a panel's box is a fifth of a 320 × 240 view, and the gather had cost 25 ms."""
    b, n = objects.shape[:2]
    area = objects.sum((2, 3))
    occupied = objects.sum(dim=(0, 1)) > 0
    rows, columns = occupied.any(dim=1).nonzero().flatten(), occupied.any(dim=0).nonzero().flatten()
    if num_shifts == 0 or len(rows) == 0:
        return left.new_full((b, n, num_shifts), torch.inf), left.new_full((b, n, num_shifts), torch.inf)
    top, bottom, first, end = int(rows[0]), int(rows[-1]) + 1, int(columns[0]), int(columns[-1]) + 1
    left, objects = left[:, top:bottom, first:end], objects[:, :, top:bottom, first:end]
    # The right view's columns first − (num_shifts − 1) … end − 1, zero left of the image (masked below): window j
    # of the unfolded band is the right view shifted by num_shifts − 1 − j.
    start = first - (num_shifts - 1)
    band = F.pad(right[:, top:bottom, max(start, 0):end], (max(-start, 0), 0))
    windows = band.unfold(-1, end - first, 1).flip(2).transpose(1, 2)  # (B, num_shifts, h, w): shift d at d
    source = torch.arange(first, end, device=left.device).view(1, -1) - torch.arange(num_shifts, device=left.device
                                                                                    ).view(-1, 1)
    in_view = (source >= 0).to(left.dtype)  # (num_shifts, w)
    # The columns in view at every shift: there in_view is 1, and the volume's products are the same.
    in_common = objects * in_view[-1]
    flat_objects, flat_common, common_count = objects.flatten(2), in_common.flatten(2), in_common.sum((2, 3))
    every, common = [], []
    for slot in range(0, num_shifts, SHIFTS_PER_SLICE):  # slices of the volume, not a loop over pairs
        part = slice(slot, min(num_shifts, slot + SHIFTS_PER_SLICE))
        difference = ((left.unsqueeze(1) - windows[:, part]).abs() * in_view[part].unsqueeze(1)).flatten(2)
        total = torch.bmm(flat_objects, difference.transpose(1, 2))  # (B, N, S)
        count = torch.einsum("bnhw,sw->bns", objects, in_view[part])
        enough = count >= MIN_IN_VIEW_SHARE * area.unsqueeze(2)
        every.append(torch.where(enough, total / count.clamp_min(1), torch.inf))
        total = torch.bmm(flat_common, difference.transpose(1, 2))
        common.append(torch.where(common_count.unsqueeze(2) > 0, total / common_count.clamp_min(1).unsqueeze(2),
                                  torch.inf))
    return torch.cat(every, dim=2), torch.cat(common, dim=2)


def _told_from_aliases(common: torch.Tensor, left: torch.Tensor, masks: torch.Tensor, best: torch.Tensor,
                       period: torch.Tensor) -> torch.Tensor:
    """``(B, N)`` bool: each object's ``best`` shift ``(B, N)`` costs less, by :data:`MIN_ALIAS_MARGIN` of the
    object's mean |x-Sobel|, than every shift half a ``period`` ``(B, N)`` or more away (working pixels; the
    pre-filtered ``left`` ``(B, h, w)``, ``masks`` ``(B, N, h, w)``). Both costs are ``common``'s ``(B, N, D)``,
    summed over the pixels in view at every shift (:func:`_shift_costs`), so that a rolled board's aliases do not
    differ by the columns each leaves in view (0.3-0.7 % of its energy), and weighed against the object's energy,
    not its best cost, which a pattern matched exactly has about 0 at every alias."""
    shifts = torch.arange(common.shape[2], device=left.device).view(1, 1, -1)
    rival = torch.where((shifts - best.unsqueeze(2)).abs() >= period.unsqueeze(2) / 2, common, torch.inf).amin(2)
    own = common.gather(2, best.unsqueeze(2)).squeeze(2)
    energy = (masks * left.abs().unsqueeze(1)).sum((2, 3)) / masks.sum((2, 3)).clamp_min(1e-12)
    return torch.isfinite(own) & (rival - own > MIN_ALIAS_MARGIN * energy)


def whole_object_disparity(left: torch.Tensor, right: torch.Tensor, objects: torch.Tensor,
                           min_disparity_px: torch.Tensor, num_disparities: torch.Tensor,
                           config: DenseConfig = DenseConfig(), period_px: torch.Tensor | None = None
                           ) -> tuple[torch.Tensor, torch.Tensor]:
    """The disparity of each whole object: the shift, within the range the dense map searched, that makes the mean SAD
    of the x-Sobel pre-filtered views (``config.prefilter_cap``) over the object's pixels least, at the dense
    stage's working width (one working pixel's resolution). With ``period_px`` ``(B, N)`` (input pixels, 0: none),
    a shift whose cost another shift half a period or more away (searched or not, up to the fallback range) comes
    within :data:`MIN_ALIAS_MARGIN` of the object's mean x-Sobel magnitude, both over the pixels in view at every
    shift, is not told from that alias and is not valid: a pattern with no end in view (a board filling both views)
    fits every alias alike.

    Args:
        left, right: ``(B, 1, H, W)`` float, the views the dense map was measured on (rectified where it was).
        objects: ``(B, N, H, W)`` bool, one mask per kept object.
        min_disparity_px, num_disparities: ``(B,)`` int64, the range searched, ``[min, min + num)`` input pixels
            (:attr:`DenseDisparity.min_disparity_px`, :attr:`DenseDisparity.pair_num_disparities`).
        config: the dense stage's settings (working width, pre-filter cap).

    Returns:
        ``disparity_px`` ``(B, N)`` float, input pixels (NaN for an object without pixels or without a shift in
        its searched range with half of them in view), and ``valid`` ``(B, N)`` bool (such a shift, told from its
        aliases). Not differentiable (an argmin).
    """
    check_shape(objects, "objects", [left.shape[0], "N", *left.shape[-2:]])
    check_dtype(objects, "objects", "bool")
    factor = working_factor(left.shape[-1], config, left.shape[-2])
    left, right, masks = left.detach(), right.detach(), objects.to(left.dtype)
    if factor > 1:
        left, right, masks = mean_pool(left, factor), mean_pool(right, factor), mean_pool(masks, factor)
    check_shape(min_disparity_px, "min_disparity_px", [left.shape[0]])
    check_shape(num_disparities, "num_disparities", [left.shape[0]])
    low, top = working_range(min_disparity_px, num_disparities, factor)
    # Rivals are looked for past the range searched too, over the dense stage's whole fallback range: a range
    # narrowed to one alias (the coarse pass's, over a pattern with no end in view) holds no rival.
    fallback = int(config.fallback_max_disparity_fraction * left.shape[-1])
    num_shifts = max(int(top.max()), fallback) if top.numel() else 0
    left_f = prefilter_xsobel(left, config.prefilter_cap)[:, 0]
    right_f = prefilter_xsobel(right, config.prefilter_cap)[:, 0]
    every, common = _shift_costs(left_f, right_f, masks, num_shifts)
    shifts = torch.arange(num_shifts, device=left.device)
    searched = (shifts >= low.view(-1, 1)) & (shifts < top.view(-1, 1))
    costs = torch.where(searched.unsqueeze(1), every, torch.inf)
    if num_shifts == 0:
        return (costs.new_full(costs.shape[:2], torch.nan),
                torch.zeros(costs.shape[:2], dtype=torch.bool, device=costs.device))
    best = costs.min(dim=2)
    fitted = torch.isfinite(best.values) & (masks.sum((2, 3)) > 0)
    valid = fitted
    if period_px is not None:
        check_shape(period_px, "period_px", list(objects.shape[:2]))
        valid = valid & ((period_px <= 0) | _told_from_aliases(common, left_f, masks, best.indices,
                                                               period_px / factor))
    return torch.where(fitted, best.indices * factor, torch.nan).to(left.dtype), valid


def remeasure_on_alias(left: torch.Tensor, right: torch.Tensor, objects: torch.Tensor, dense: DenseDisparity,
                       disparity_px: torch.Tensor, period_px: torch.Tensor, config: DenseConfig = DenseConfig(),
                       image_hw: torch.Tensor | None = None) -> DenseDisparity:
    """``dense`` with each repeated object measured again over one period about its whole-object alias.

    Where ``period_px`` ``(B, N)`` (input pixels) is positive, object n of pair b (``objects`` ``(B, N, H, W)``
    bool) is matched again (:func:`~svs_torch.depth.dense.dense_disparity_in_range`) over ``disparity_px[b, n]
    ± period / 2`` within the range ``dense`` searched, where no other alias lies, so that the uniqueness rule
    passes the windows it rejected for their aliases; its pixels then take that pass's values, valid or not. The
    other objects and pairs keep ``dense``'s. One batched pass over every (pair, object) row, not a loop.
    ``left``, ``right``: ``(B, 1, H, W)``, the views ``dense`` was measured on. Not differentiable."""
    check_shape(objects, "objects", [dense.valid.shape[0], "N", *dense.valid.shape[-2:]])
    check_shape(disparity_px, "disparity_px", list(objects.shape[:2]))
    check_shape(period_px, "period_px", list(objects.shape[:2]))
    pair, slot = (period_px > 0).nonzero(as_tuple=True)
    if len(pair) == 0:
        return dense
    half = period_px[pair, slot].to(torch.float64) / 2
    centre = disparity_px[pair, slot].to(torch.float64)
    first, end = dense.min_disparity_px[pair], (dense.min_disparity_px + dense.pair_num_disparities)[pair]
    low = torch.maximum(first, (centre - half).ceil().long())
    top = torch.minimum(end, (centre + half).floor().long() + 1)
    inside = objects[pair, slot].unsqueeze(1)
    hw = None if image_hw is None else image_hw[pair]
    part = dense_disparity_in_range(left[pair], right[pair], inside, low, (top - low).clamp_min(1), config, hw)
    # The objects of a pair are disjoint: the rows of one pair add up without overlap.
    shape = dense.valid.shape
    covered = torch.zeros(shape, device=inside.device).index_add_(0, pair, inside.to(torch.float32)) > 0
    found = torch.zeros(shape, device=inside.device).index_add_(0, pair, (inside & part.valid).to(torch.float32))
    values = torch.zeros_like(dense.disparity_px).index_add_(
        0, pair, torch.where(inside & part.valid, part.disparity_px, 0.0).to(dense.disparity_px.dtype))
    valid = torch.where(covered, found > 0, dense.valid)
    return dataclasses.replace(dense, valid=valid, disparity_px=torch.where(covered, values, dense.disparity_px))


def settle_aliases(left: torch.Tensor, right: torch.Tensor, objects: torch.Tensor, dense: DenseDisparity,
                   disparity_px: torch.Tensor, valid: torch.Tensor, period_px: torch.Tensor,
                   config: DenseConfig = DenseConfig(), image_hw: torch.Tensor | None = None) -> DenseDisparity:
    """``dense`` with each repeated object (``period_px`` ``(B, N)`` positive, input pixels) settled on one alias
    (module docstring): where the median of its valid pixels in ``dense`` lies within half a period of its whole-
    object disparity ``disparity_px`` ``(B, N)`` where ``valid`` ``(B, N)`` (:func:`whole_object_disparity`),
    measured again over that period (:func:`remeasure_on_alias`); elsewhere (the two disagree, the whole object's
    alias is not told, or none of its pixels is valid) its pixels are dropped. The other objects and pairs keep
    ``dense``'s; its ``repeated`` holds the periods, the whole-object disparities and which objects were settled
    (:class:`~svs_torch.depth.dense_config.RepeatedObjects`). Arguments as :func:`remeasure_on_alias`'s. Not
    differentiable."""
    check_shape(objects, "objects", [dense.valid.shape[0], "N", *dense.valid.shape[-2:]])
    check_shape(disparity_px, "disparity_px", list(objects.shape[:2]))
    check_shape(valid, "valid", list(objects.shape[:2]))
    check_shape(period_px, "period_px", list(objects.shape[:2]))
    # The windows' median of the repeated pairs' objects only: a batch of native-size pairs sorted whole would
    # hold every pixel of every object.
    index = (period_px > 0).any(dim=1).nonzero().flatten()
    inside = objects[index].flatten(2) & dense.valid[index].flatten(2)
    median = masked_quantile(dense.disparity_px[index].flatten(2).expand(-1, objects.shape[1], -1), inside, [0.5])
    near = median.valid & ((median.values[..., 0] - disparity_px[index]).abs() < period_px[index] / 2)
    agree = valid & torch.zeros_like(valid).index_put((index,), near)
    disagree = ((period_px > 0) & ~agree).view(*objects.shape[:2], 1, 1)
    dropped = (objects & disagree).any(dim=1, keepdim=True)
    fitted = disparity_px.isfinite()
    repeated = RepeatedObjects(period_px, torch.where(fitted, disparity_px, 0.0), fitted, agree)
    dense = dataclasses.replace(dense, valid=dense.valid & ~dropped, repeated=repeated,
                                disparity_px=torch.where(dropped, 0.0, dense.disparity_px))
    return remeasure_on_alias(left, right, objects, dense, disparity_px, torch.where(agree, period_px, 0), config,
                              image_hw)


def settle_repeated_objects(left: torch.Tensor, right: torch.Tensor, objects: torch.Tensor, dense: DenseDisparity,
                            min_period_peak: float, config: DenseConfig = DenseConfig(),
                            image_hw: torch.Tensor | None = None, max_period_px: int = MAX_PERIOD_PX
                            ) -> DenseDisparity:
    """``dense`` with each kept object (``objects`` ``(B, N, H, W)`` bool) that repeats itself along the rows (a
    peak of at least ``min_period_peak``, a period under ``max_period_px`` working pixels,
    :func:`~svs_torch.depth.periodicity.object_periods`) settled on its alias or dropped (:func:`settle_aliases`);
    ``repeated`` set for every pair. The period test costs about 1.5 ms a 320 × 240 pair; each object of a
    repeated pair is then tested on its own, and only the repeated objects are matched again. ``left``,
    ``right``: ``(B, 1, H, W)``, the views ``dense`` was measured on. Not differentiable."""
    periods = object_periods(left, objects, min_period_peak, config, max_period_px)
    index = (periods > 0).any(dim=1).nonzero().flatten()
    none = RepeatedObjects.none(objects, left.dtype)
    if len(index) == 0:
        return dataclasses.replace(dense, repeated=none)
    found, told = whole_object_disparity(left[index], right[index], objects[index], dense.min_disparity_px[index],
                                         dense.pair_num_disparities[index], config, periods[index])
    # NaN: no shift fitted (whole_object_disparity), as for the pairs not tested.
    centres = found.new_full(objects.shape[:2], torch.nan).index_put((index,), found)
    valid = none.settled.index_put((index,), told)
    return settle_aliases(left, right, objects, dense, centres, valid, periods, config, image_hw)


def alias_depths_m(dense: DenseDisparity, focal_px: torch.Tensor, baseline_m: torch.Tensor,
                   doffs_px: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The distances each repeated object's aliases would give: its whole-object disparity plus or minus whole
    periods, within the range ``dense`` searched (``dense.repeated``; none without it), nearest first, by
    ``Z = f·B / (d + doffs)`` (Sec. 3.5, Eq. (7)) in the units of ``baseline_m``.

    Args:
        dense: a :class:`~svs_torch.depth.dense_config.DenseDisparity` with ``repeated``.
        focal_px, baseline_m: ``(B,)``; doffs_px: ``(B,)`` or None (0).

    Returns:
        ``depth_m`` ``(B, N, K)`` and ``valid`` ``(B, N, K)`` bool (K: the most aliases any object has; depth 0
        where not valid). Not differentiable (the periods and shifts are whole pixels found by argmins).
    """
    num_pairs = dense.valid.shape[0]
    check_shape(focal_px, "focal_px", [num_pairs])
    check_shape(baseline_m, "baseline_m", [num_pairs])
    if doffs_px is not None:
        check_shape(doffs_px, "doffs_px", [num_pairs])
    repeated = dense.repeated
    if repeated is None:
        shape = (dense.valid.shape[0], 0, 0)
        return focal_px.new_zeros(shape), torch.zeros(shape, dtype=torch.bool, device=focal_px.device)
    period = repeated.period_px.to(torch.float64)
    found = repeated.disparity_px.to(torch.float64)
    usable = (repeated.period_px > 0) & repeated.fitted
    period, found = torch.where(usable, period, 1.0), torch.where(usable, found, 0.0)
    low = dense.min_disparity_px.to(torch.float64).view(-1, 1)
    top = low + dense.pair_num_disparities.to(torch.float64).view(-1, 1)  # exclusive
    # The largest alias below the top first: the nearest distance first.
    highest = found + torch.floor((top - 1 - found) / period) * period
    counts = torch.where(usable, ((highest - low) / period).floor() + 1, 0.0)
    count = int(counts.max()) if counts.numel() else 0
    steps = torch.arange(count, dtype=torch.float64, device=period.device)
    disparity = highest.unsqueeze(-1) - steps * period.unsqueeze(-1)
    doffs = torch.zeros_like(low) if doffs_px is None else doffs_px.to(torch.float64).view(-1, 1)
    total = disparity + doffs.unsqueeze(-1)
    valid = usable.unsqueeze(-1) & (disparity >= low.unsqueeze(-1)) & (total > 0)
    depth = (focal_px.to(torch.float64) * baseline_m.to(torch.float64)).view(-1, 1, 1) / torch.where(valid, total, 1.0)
    return torch.where(valid, depth, 0.0).to(focal_px.dtype), valid


def nearest_alias_depth_m(dense: DenseDisparity, unranged: torch.Tensor, focal_px: torch.Tensor,
                          baseline_m: torch.Tensor, doffs_px: torch.Tensor | None = None) -> torch.Tensor:
    """How near each pair's ``unranged`` repeated objects (``(B, N)`` bool) may be: the nearest of their aliases'
    distances (:func:`alias_depths_m`, same arguments), 0 where one has no alias to bound it (its shift was not
    found: it may be anywhere), NaN where a pair has none. ``(B,)``; not differentiable."""
    depth_m, valid = alias_depths_m(dense, focal_px, baseline_m, doffs_px)
    check_shape(unranged, "unranged", [dense.valid.shape[0], depth_m.shape[1]])
    per_object = torch.where(valid, depth_m, torch.inf).amin(-1) if depth_m.shape[-1] else depth_m.sum(-1)
    per_object = torch.where(valid.any(-1), per_object, 0.0)
    nearest = torch.where(unranged.to(torch.bool), per_object, torch.inf).amin(-1) if unranged.shape[1] else \
        per_object.new_full((unranged.shape[0],), torch.inf)
    return torch.where(torch.isinf(nearest), torch.nan, nearest)
