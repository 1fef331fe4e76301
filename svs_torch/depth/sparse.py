"""Depth of the obstacles from the rectified inliers (paper Sec. 3.4, Eq. (5)–(9)).

After rectification (:mod:`svs_torch.geometry.rectification`) a match's disparity is ``d = x_left − x_right`` (pixels;
positive in front: ``x_right = x_left − d``). The paper ranges a pair from the extreme disparities of its
inliers: ``d_max = max dᵢ`` (5), ``d_min = min dᵢ`` (6), ``R_min = f·B / d_max`` (7), ``R_max = f·B / d_min``
(8), with Middlebury's ``doffs`` added to d where the data has it, and scores an estimate by
``Acc = (1 − |real − est| / real) · 100`` (9).

Raw extremes are fragile: on a (nearly) rectified pair RANSAC cannot reject a wrong match that lies on the
right row, and one such match sets d_max or d_min (``../shared/REFERENCE.md``, "Pitfalls"). So the range can
use percentiles instead of min/max, and :func:`object_depths` gives each segmented obstacle its own median
depth; :func:`nearest_obstacle` names the closest one and its side (left / centre / right third).

Denominators ``d + doffs ≤ 0`` are masked, never divided by: every result carries a validity mask.
Differentiable w.r.t. the points, disparities, focal length and baseline where valid (min/max/percentiles
pass gradients to the selected or interpolated elements); masks, counts, label lookup and sides are not.
"""

from __future__ import annotations

import torch

from ..core.checks import (InputError, check_dtype, check_finite, check_instance, check_percentiles, check_real,
                           check_shape)
from ..core.kernels.checks import check_image_hw
from ..core.mask_reductions import count_along
from ..geometry.rectification import map_points
from .depth_types import (Accuracy, DepthConfig, DepthResult, Disparities, NearestObstacle, ObjectDepths, ObstacleSide,
                          PointDepths, RangeEstimate)
from .quantiles import masked_quantile

__all__ = [
    "accuracy_percent", "estimate_depth", "estimate_range", "nearest_obstacle", "object_depths", "point_depths",
    "column_sides", "rectified_disparity", "slot_labels"
]


def _per_pair(value: float | torch.Tensor | None, like: torch.Tensor, name: str,
              positive: bool = False) -> torch.Tensor:
    """A scalar or ``(B,)`` calibration value as a ``(B, 1)`` column in ``like``'s dtype (None → 0), finite and,
    with ``positive``, above 0: a negative focal length times a negative baseline ranged a pair at a plausible
    3.28 m, and a zero or NaN one left it unranged without a word (an audit; ``StereoBatch`` refuses both)."""
    # A string, a complex or a meta tensor raised from torch.as_tensor, a bool (tensor) was taken as 1 and a complex
    # tensor lost its imaginary part, none naming the argument (an audit).
    refused = isinstance(value, bool) or isinstance(value, torch.Tensor) and (
        value.dtype == torch.bool or value.dtype.is_complex or value.is_meta)
    try:
        column = None if refused else torch.as_tensor(0.0 if value is None else value, dtype=like.dtype,
                                                      device=like.device)
    except (TypeError, ValueError, RuntimeError):
        column = None
    if column is None:
        raise InputError(f"{name}: expected a real number or a ({like.shape[0]},) real tensor, got {value!r}")
    value = column
    if value.dim() == 1 and value.shape[0] != like.shape[0] or value.dim() > 1:
        raise InputError(f"{name}: expected a scalar or ({like.shape[0]},), got {tuple(value.shape)}")
    check_finite(value, name, positive=positive)
    return value.expand(like.shape[0]).reshape(-1, 1)


def _quantile_levels(percentiles: tuple[float, float], name: str) -> tuple[float, float]:
    check_percentiles(percentiles, name)
    low, high = (float(p) for p in percentiles)
    return low / 100, high / 100


def _check_values(values: torch.Tensor, name: str, valid: torch.Tensor, valid_name: str) -> None:
    check_shape(values, name, ["B", "K"])
    check_dtype(values, name, "float")
    check_shape(valid, valid_name, list(values.shape))
    check_dtype(valid, valid_name, "bool")


def rectified_disparity(points_left: torch.Tensor, points_right: torch.Tensor, valid: torch.Tensor,
                        H_left: torch.Tensor | None = None, H_right: torch.Tensor | None = None) -> Disparities:
    """Disparities of correspondences ``(B, K, 2)`` (pixels, ``valid`` ``(B, K)``) after the rectifying
    homographies ``(B, 3, 3)`` (``Rectification.H_left``/``H_right``; None = identity, for a rectified rig).
    Differentiable w.r.t. the points and homographies."""
    for name, points in (("points_left", points_left), ("points_right", points_right)):
        check_shape(points, name, ["B", "K", 2])
        check_dtype(points, name, "float")
    if points_left.shape != points_right.shape:
        raise InputError(f"points_right: expected {tuple(points_left.shape)}, got {tuple(points_right.shape)}")
    check_shape(valid, "valid", list(points_left.shape[:2]))
    check_dtype(valid, "valid", "bool")
    valid = valid.clone()
    mapped = []
    for name, H, points in (("H_left", H_left, points_left), ("H_right", H_right, points_right)):
        if H is not None:
            check_shape(H, name, [points.shape[0], 3, 3])
            check_dtype(H, name, "float")
            check_finite(H, name)  # a NaN one gave every row valid, of NaN disparity
            points, in_front = map_points(H.to(points.dtype), points)
            valid &= in_front
        mapped.append(points)
    delta = torch.where(valid.unsqueeze(-1), mapped[0] - mapped[1], torch.zeros_like(mapped[0]))
    return Disparities(delta[..., 0], delta[..., 1], valid)


def point_depths(disparity_px: torch.Tensor, valid: torch.Tensor, focal_px: float | torch.Tensor,
                 baseline_m: float | torch.Tensor, doffs_px: float | torch.Tensor | None = None) -> PointDepths:
    """Depth ``Z = f·B / (d + doffs)`` (Eq. (7)–(8) per point) of disparities ``(B, K)``; ``focal_px``,
    ``baseline_m``, ``doffs_px`` scalars or ``(B,)`` (``StereoBatch`` fields; doffs 0 for the SVS), finite, focal
    length and baseline above 0.
    Differentiable w.r.t. ``disparity_px`` and the calibration where valid; ``valid`` is not. A point counts where
    ``d + doffs > 0``, a hard selection: at doffs 0 (the SVS's) a point of d = 0 enters at any doffs above 0, so
    a depth taken over the points (a median) steps there and its gradient w.r.t. doffs is that of the points
    selected (an audit: gradcheck w.r.t. doffs fails exactly at 0)."""
    _check_values(disparity_px, "disparity_px", valid, "valid")
    return _depths(disparity_px, valid, *_calibration(disparity_px, focal_px, baseline_m, doffs_px))


def _calibration(disparity_px: torch.Tensor, focal_px: float | torch.Tensor, baseline_m: float | torch.Tensor,
                 doffs_px: float | torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """``f·B`` and ``doffs`` as ``(B, 1)`` columns, each value checked once (:func:`_per_pair`)."""
    scale = (_per_pair(focal_px, disparity_px, "focal_px", positive=True)
             * _per_pair(baseline_m, disparity_px, "baseline_m", positive=True))
    return scale, _per_pair(doffs_px, disparity_px, "doffs_px")


def _depths(disparity_px: torch.Tensor, valid: torch.Tensor, scale: torch.Tensor, doffs: torch.Tensor) -> PointDepths:
    """:func:`point_depths` of checked arguments, with :func:`_calibration`'s columns."""
    denominator = disparity_px + doffs
    valid = valid & (denominator > 0)
    safe = torch.where(valid, denominator, torch.ones_like(denominator))
    depth = scale / safe
    # A depth that underflows to 0 or overflows to inf (an extreme but finite calibration) is no depth.
    valid = valid & torch.isfinite(depth) & (depth > 0)
    return PointDepths(torch.where(valid, depth, torch.zeros_like(safe)), valid)


def estimate_range(disparity_px: torch.Tensor, valid: torch.Tensor, focal_px: float | torch.Tensor,
                   baseline_m: float | torch.Tensor, doffs_px: float | torch.Tensor | None = None,
                   percentiles: tuple[float, float] | None = None, min_in_front_share: float = 0.0
                   ) -> RangeEstimate:
    """The paper's range of a pair from its inlier disparities ``(B, K)`` (Sec. 3.4, Eq. (5)–(8)).

    ``percentiles=None`` is the paper: d_max and d_min are the max and min (5)–(6). ``(low, high)`` uses those
    percentiles instead (robust to a wrong same-row match). Disparities with ``d + doffs ≤ 0`` are left out, and a
    pair with no more than ``min_in_front_share`` of its inliers in front of the rig is not ranged (``valid``
    False). The default 0 is the paper's letter, any one inlier in front; the pipeline passes
    ``DepthConfig.min_in_front_share`` (0.5 outside the paper preset).
    Differentiable w.r.t. ``disparity_px`` (the selected or interpolated ones) and, for the depths, the
    calibration; ``num_disparities`` and ``valid`` are not.
    """
    _check_values(disparity_px, "disparity_px", valid, "valid")
    scale, doffs = _calibration(disparity_px, focal_px, baseline_m, doffs_px)
    depths = _depths(disparity_px, valid, scale, doffs)
    q = (0.0, 1.0) if percentiles is None else _quantile_levels(percentiles, "percentiles")
    d_min, d_max = masked_quantile(disparity_px, depths.valid, q).values.unbind(-1)  # Eq. (6), (5)
    in_front = depths.valid.sum(dim=1)
    check_real(min_in_front_share, "min_in_front_share", 0.0, 1.0)
    present = (in_front > 0) & (in_front > min_in_front_share * valid.sum(dim=1))
    scale, doffs = scale.squeeze(1), doffs.squeeze(1)

    def depth(d: torch.Tensor) -> torch.Tensor:  # d + doffs > 0 for every entered disparity, so for its stats
        safe = torch.where(present, d + doffs, torch.ones_like(d))
        return torch.where(present, scale / safe, torch.zeros_like(d))

    return RangeEstimate(d_min, d_max, depth(d_max), depth(d_min), in_front, present)


def accuracy_percent(real_m: torch.Tensor, estimated_m: torch.Tensor) -> Accuracy:
    """Eq. (9): ``(1 − |real − est| / real) · 100`` elementwise (broadcast); valid where ``real > 0`` and both
    are finite. Not floored: an estimate over twice the truth is below 0 (a loss that keeps its gradient), where
    the evaluation's :func:`svs_torch.evaluation.accuracy_pct` counts it 0 %, as it counts a missing one.
    Differentiable w.r.t. both where valid (not at ``real = est``, a kink)."""
    real_m, estimated_m = torch.as_tensor(real_m), torch.as_tensor(estimated_m)
    try:
        real_m, estimated_m = torch.broadcast_tensors(real_m, estimated_m)
    except RuntimeError:  # torch's "The size of tensor a (2) must match ..." named neither (an audit)
        raise InputError(f"estimated_m: expected a shape that broadcasts with real_m's {tuple(real_m.shape)}, got "
                         f"{tuple(estimated_m.shape)}") from None
    valid = (real_m > 0) & torch.isfinite(real_m) & torch.isfinite(estimated_m)
    safe_real = torch.where(valid, real_m, torch.ones_like(real_m))
    safe_est = torch.where(valid, estimated_m, torch.ones_like(estimated_m))
    percent = (1 - (safe_real - safe_est).abs() / safe_real) * 100
    return Accuracy(torch.where(valid, percent, torch.zeros_like(percent)), valid)


def _point_slots(labels: torch.Tensor, region_labels: torch.Tensor, points: torch.Tensor,
                 image_hw: torch.Tensor) -> torch.Tensor:
    """``(B, K, N)`` bool: the left point lies on the pixel (nearest pixel centre) of slot n's region."""
    b, _, height, width = labels.shape
    column, row = torch.round(points.detach()).long().unbind(-1)  # (B, K)
    inside = (column >= 0) & (row >= 0) & (column < image_hw[:, 1:]) & (row < image_hw[:, :1])
    flat = (row.clamp(0, height - 1) * width + column.clamp(0, width - 1))
    under = labels.flatten(1).gather(1, flat)  # (flatten: reshape(b, -1) fails for an empty batch)
    under = torch.where(inside, under, torch.zeros_like(under))  # 0: background, never a slot's label
    return (under.unsqueeze(-1) == region_labels.unsqueeze(1)) & (region_labels > 0).unsqueeze(1)


def slot_labels(region_labels: torch.Tensor) -> torch.Tensor:
    """``region_labels`` with every padding or background slot (label ≤ 0) set to −1, which no pixel of a label
    image holds (labels are ≥ 0, 0 background): ``labels == slot_labels(...)`` is then each slot's region in one
    comparison, without a second full-frame pass for ``& (region_labels > 0)``. Not differentiable (integer
    labels)."""
    return torch.where(region_labels > 0, region_labels, -1)


def _region_geometry(labels: torch.Tensor, region_labels: torch.Tensor,
                     image_hw: torch.Tensor, dtype: torch.dtype) -> tuple[torch.Tensor, ...]:
    """Area ``(B, N)``, centroid column ``(B, N)`` and :class:`ObstacleSide` ``(B, N)`` of each slot's region: the
    third of the width its centroid falls in, or the centre where the region reaches across the image's middle
    column (in the walker's path, whatever its centroid: a wall over the whole view, kept over its left half-and-more,
    was said "on the left at 0.9 metres", an audit)."""
    members = labels == slot_labels(region_labels).view(*region_labels.shape, 1, 1)  # (B, N, H, W)
    # Counted as bytes into int32 (a bool sum goes through int64): 0.15 against 0.44 ms for 8 pairs of two
    # 320×240 slots.
    per_column = count_along(members, 2)  # (B, N, W)
    return column_sides(per_column, image_hw[:, 1:], dtype)


def column_sides(per_column: torch.Tensor, width: torch.Tensor, dtype: torch.dtype, stray_share: float = 0.0
                 ) -> tuple[torch.Tensor, ...]:
    """Area ``(...)``, centroid column and :class:`ObstacleSide` of pixel sets given by their counts per column
    ``per_column`` ``(..., W)`` (int), in pairs ``width`` px wide (broadcast to ``(...)``): the third of the width
    the centroid falls in, or the centre where the set reaches across the middle column, its ends taken without
    ``stray_share`` of its pixels each (0: every pixel counts); NONE where it holds none. The regions' rule
    (:func:`_region_geometry`) and the near parts' (:mod:`svs_torch.pipeline.near_side`)."""
    area = per_column.sum(dim=-1)
    columns = torch.arange(per_column.shape[-1], device=per_column.device, dtype=dtype)
    centroid = (per_column.to(dtype) * columns).sum(dim=-1) / area.clamp_min(1).to(dtype)
    width = width.to(dtype)  # thirds of the pair's own width, in pixel-centre coordinates
    side = torch.where(centroid < width / 3 - 0.5, int(ObstacleSide.LEFT),
                       torch.where(centroid < 2 * width / 3 - 0.5, int(ObstacleSide.CENTRE), int(ObstacleSide.RIGHT)))
    # The first column past the strays on the left and the last before those on the right (with none: the first
    # and last columns holding any), counted in float64: whole counts exact far past any image's.
    running, total = per_column.cumsum(dim=-1).double(), area.unsqueeze(-1).double()
    first = (running <= stray_share * total).sum(dim=-1)
    last = (running < (1 - stray_share) * total).sum(dim=-1)
    middle = (width - 1) / 2  # the pair's middle column, in pixel-centre coordinates
    side = torch.where((first <= middle) & (last >= middle), int(ObstacleSide.CENTRE), side)
    return area, centroid, torch.where(area > 0, side, int(ObstacleSide.NONE))


def object_depths(labels: torch.Tensor, region_labels: torch.Tensor, points_left: torch.Tensor,
                  depths: PointDepths, image_hw: torch.Tensor | None = None,
                  percentiles: tuple[float, float] = (10.0, 90.0), min_inliers: int = 1,
                  statistics: bool = True) -> ObjectDepths:
    """Per-object depth: each correspondence goes to the region under its left point; per region, the median
    and ``percentiles`` of its depths (``statistics=False``: zeros, every slot invalid, for a caller that only
    wants the slots' geometry and inlier counts). Its depths are differentiable w.r.t. ``depths.depth_m`` (the
    order statistics they interpolate), nothing else is (``points_left`` is rounded to a pixel).

    Args:
        labels: ``(B, 1, H, W)`` int64 label image of the left view, 0 background (``Segmentation.labels``).
        region_labels: ``(B, N)`` int64 label of each slot, −1 padding (``Segmentation.kept_labels``; for a
            contiguous 1..N image, ``torch.arange(1, N + 1).expand(B, N)``).
        points_left: ``(B, K, 2)`` left points in the ORIGINAL (unrectified) pixels, where ``labels`` lives.
        depths: :class:`PointDepths` of the same correspondences.
        image_hw: ``(B, 2)`` each pair's (height, width) before padding; default the label image's.
        percentiles: low and high percentiles in [0, 100]; min_inliers: fewest depths for a valid object.
    """
    check_shape(labels, "labels", ["B", 1, "H", "W"])
    check_dtype(labels, "labels", "int")
    check_shape(region_labels, "region_labels", [labels.shape[0], "N"])
    check_dtype(region_labels, "region_labels", "int")
    check_shape(points_left, "points_left", [labels.shape[0], "K", 2])
    check_dtype(points_left, "points_left", "float|int")  # a complex one failed in its rounding (an audit)
    check_instance(depths, "depths", PointDepths)  # None failed on .depth_m (an audit)
    _check_values(depths.depth_m, "depths.depth_m", depths.valid, "depths.valid")
    check_shape(depths.depth_m, "depths.depth_m", list(points_left.shape[:2]))
    if image_hw is None:
        image_hw = torch.tensor([labels.shape[-2:]], device=labels.device).expand(labels.shape[0], 2)
    # Within the label image: a size past it ranged an object from the labels' border pixels (an audit).
    check_image_hw(image_hw, *labels.shape[:1], *labels.shape[-2:])
    labels, region_labels = labels.long(), region_labels.long()
    area, centroid, side = _region_geometry(labels, region_labels, image_hw, depths.depth_m.dtype)
    member = _point_slots(labels, region_labels, points_left, image_hw) & depths.valid.unsqueeze(-1)
    member = member.transpose(1, 2)  # (B, N, K)
    q = (0.5, *_quantile_levels(percentiles, "percentiles"))
    count = member.sum(dim=-1)
    valid = (region_labels > 0) & (area > 0) & (count >= max(min_inliers, 1))
    if statistics:
        stats = masked_quantile(depths.depth_m.unsqueeze(1).expand_as(member), member, q).values  # (B, N, 3)
    else:
        stats = depths.depth_m.new_zeros((*member.shape[:2], 3))
        valid = torch.zeros_like(valid)
    stats = torch.where(valid.unsqueeze(-1), stats, torch.zeros_like(stats))
    point_slot = torch.full(member.shape[::2], -1, dtype=torch.int64, device=member.device)  # (B, K)
    if member.shape[1] > 0:
        point_slot = torch.where(member.any(dim=1), member.to(torch.uint8).argmax(dim=1), point_slot)
    return ObjectDepths(torch.where(region_labels > 0, region_labels, -1), area, centroid, side, count,
                        *stats.unbind(-1), valid, point_slot)


def nearest_obstacle(objects: ObjectDepths) -> NearestObstacle:
    """The valid object with the smallest median depth, its depth and side (Sec. 3.4's warning to the user).
    Ranked by the median, not by the near surface then said: noise pulls a far wall's low percentile near, and that
    rule named walls 4-9 m away as obstacles under 2 m (``experiments/nearest_rule.md``). Differentiable w.r.t.
    the chosen object's ``depth_median_m`` and ``depth_low_m`` (a gather); the slot, side and validity are not."""
    check_instance(objects, "objects", ObjectDepths)  # None or a dict failed on .valid (an audit)
    candidates = torch.where(objects.valid, objects.depth_median_m, torch.inf)
    sides = objects.side
    if candidates.shape[1] == 0:  # no slot at all: one empty candidate keeps the reductions defined
        candidates = candidates.new_full((candidates.shape[0], 1), torch.inf)
        sides = torch.full_like(candidates, int(ObstacleSide.NONE), dtype=torch.int64)
    depth, slot = candidates.min(dim=1)
    valid = torch.isfinite(depth)
    side = sides.gather(1, slot.unsqueeze(1)).squeeze(1)
    surface = torch.zeros_like(depth)
    if objects.depth_low_m.shape[1] > 0:
        surface = torch.where(valid, objects.depth_low_m.gather(1, slot.unsqueeze(1)).squeeze(1), surface)
    return NearestObstacle(torch.where(valid, slot, -1), torch.where(valid, depth, torch.zeros_like(depth)),
                           torch.where(valid, side, int(ObstacleSide.NONE)), valid, surface)


def estimate_depth(points_left: torch.Tensor, points_right: torch.Tensor, inliers: torch.Tensor,
                   focal_px: float | torch.Tensor, baseline_m: float | torch.Tensor,
                   doffs_px: float | torch.Tensor | None = None, H_left: torch.Tensor | None = None,
                   H_right: torch.Tensor | None = None, labels: torch.Tensor | None = None,
                   region_labels: torch.Tensor | None = None, image_hw: torch.Tensor | None = None,
                   config: DepthConfig = DepthConfig(), statistics: bool = True) -> DepthResult:
    """The depth stage: rectified disparities of the inliers ``(B, K)``, the pair's range (Eq. (5)–(8)) and,
    given ``labels`` and ``region_labels``, per-object depths and the nearest obstacle. Arguments as in
    :func:`rectified_disparity`, :func:`point_depths`, :func:`object_depths`. ``statistics=False`` (the dense
    rule, which measures them again: :mod:`svs_torch.pipeline.ranging`) leaves the range and the objects' depths
    zero and invalid, and makes only the disparities, the depths and each slot's geometry and inlier count.
    Differentiable w.r.t. the points, homographies and calibration where valid, as its parts are (module
    docstring); masks, counts, slots and sides are not."""
    if (labels is None) != (region_labels is None):
        raise InputError("region_labels: expected it together with labels (both or neither)")
    check_instance(config, "config", DepthConfig)  # a dict failed on its first field, deep in the statistics
    check_dtype(inliers, "inliers", "bool")  # (rectified_disparity would name it 'valid')
    disparities = rectified_disparity(points_left, points_right, inliers, H_left, H_right)
    depths = point_depths(disparities.disparity_px, disparities.valid, focal_px, baseline_m, doffs_px)
    if statistics:
        pair_range = estimate_range(disparities.disparity_px, disparities.valid, focal_px, baseline_m, doffs_px,
                                    config.percentiles, config.min_in_front_share)
    else:
        zeros = depths.depth_m.new_zeros(depths.depth_m.shape[0])
        pair_range = RangeEstimate(zeros, zeros, zeros, zeros, torch.zeros_like(zeros, dtype=torch.int64),
                                   torch.zeros_like(zeros, dtype=torch.bool))
    if labels is None:
        return DepthResult(disparities, depths, pair_range, None, None)
    objects = object_depths(labels, region_labels, points_left, depths, image_hw, config.object_percentiles,
                            config.min_object_inliers, statistics)
    return DepthResult(disparities, depths, pair_range, objects, nearest_obstacle(objects))
