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

import enum
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, NamedTuple

import torch

from . import kernels
from ..core.checks import InputError, check_dtype, check_shape
from ..core.ordering import argsort_last, sort_last
from ..geometry.rectification import map_points

__all__ = [
    "Accuracy", "DepthConfig", "DepthResult", "Disparities", "NearestObstacle", "ObjectDepths", "ObstacleSide",
    "PointDepths", "Quantiles", "RangeEstimate", "accuracy_percent", "estimate_depth", "estimate_range",
    "kept_region_lower_median", "labelled_quantile", "masked_lower_median", "masked_quantile", "nearest_obstacle",
    "object_depths", "point_depths", "rectified_disparity", "slot_labels",
]


class ObstacleSide(enum.IntEnum):
    """Which third of the image width an obstacle's centroid falls in; stored as int64 in tensors."""

    NONE = -1  # no obstacle (padding slot, or no valid object for the nearest)
    LEFT = 0
    CENTRE = 1
    RIGHT = 2


@dataclass(frozen=True)
class DepthConfig:
    """Options of :func:`estimate_depth`.

    Attributes:
        rule: how the pipeline ranges a pair. ``"dense"`` (the default): each kept object's depth is the
            median over its region's valid dense disparities (:mod:`svs_torch.depth.dense_objects`), R_min / R_max the
            nearest / farthest object. ``"paper"``: Eq. (5)–(8) over the sparse RANSAC inliers, objects from
            the inliers on each region. :func:`estimate_depth` itself is the sparse rule; the pipeline adds the
            dense one.
        percentiles: ``None`` for the paper's d_min/d_max (Eq. (5)–(6), min and max over the inliers), or
            ``(low, high)`` percentiles in [0, 100] (e.g. ``(10, 90)``) as robust stand-ins (``"paper"`` rule).
        object_percentiles: the ``(low, high)`` percentiles of each object's depth, besides its median; the low
            one of the nearest object is its nearest visible surface (``NearestObstacle.surface_m``).
        min_object_inliers: fewest valid inliers for an object's depth to count (``"paper"`` rule).
        min_object_pixels: fewest valid dense pixels for an object's depth to count (``"dense"`` rule).
        min_object_valid_fraction: least share of an object's region with valid dense disparities (``"dense"``
            rule) where the pair's geometry is verified (``PipelineResult.verified``: RANSAC found F and the
            dense map confirms enough of its inliers): both views show the same scene.
        min_object_valid_fraction_unverified: the same where it is not. Views of different scenes leave up to
            32 % of a region consistent by chance (``experiments/verify_views.py``, synthetic scenes; related
            Middlebury scenes up to 42 %), real pairs 47–98 % (a lighting-change scene 18 %, an occluding plant
            17 % at native size, both verified): with no geometry to vouch for the pair, an object with less is
            not ranged rather than ranged wrong.
        min_object_pixels_in_view: fewest valid dense pixels an object needs at columns where every disparity
            of the pair's search range still lands inside the right image (``x ≥ d_max``; ``"dense"`` rule).
            Nearer the left border a near surface's match can lie outside the right view, and the best visible
            candidate is then wrong: an object that lies wholly in that band has no pixel the right camera is
            sure to see, and is not ranged rather than ranged wrong (Middlebury Laundry at 320 px: a 38 px
            strip 3.6 m away on the left border was ranged at 11.3 m). 0 turns the check off. Unlike
            ``DenseConfig.whole_range_in_view`` it drops no pixel: an object with enough pixels in view keeps
            its median over all of them.
    """

    rule: Literal["dense", "paper"] = "dense"  # paper_table1.py: dense 98-99 % vs sparse extremes 74-84 %
    percentiles: tuple[float, float] | None = None  # Sec. 3.4, Eq. (5)–(6) when None
    object_percentiles: tuple[float, float] = (10.0, 90.0)
    min_object_inliers: int = 1
    min_object_pixels: int = 20
    min_object_valid_fraction: float = 0.1
    min_object_valid_fraction_unverified: float = 0.4  # verify_views.py: 0.3 ranged 10 of 64 synthetic mismatches
    min_object_pixels_in_view: int = 20  # paper_table1.py: changes only held-out Laundry at 320 px (R_max 0 -> 99 %)

    def __post_init__(self) -> None:
        if self.rule not in ("dense", "paper"):
            raise InputError(f"rule: expected 'dense' or 'paper', got {self.rule!r}")
        if isinstance(self.min_object_pixels_in_view, bool) or not isinstance(self.min_object_pixels_in_view, int) \
                or self.min_object_pixels_in_view < 0:
            raise InputError(f"min_object_pixels_in_view: expected an int >= 0, got {self.min_object_pixels_in_view!r}")


@dataclass(frozen=True)
class Disparities:
    """Rectified disparities ``disparity_px`` ``(B, K)`` (``x_left − x_right``), ``row_error_px`` ``(B, K)``
    (``y_left − y_right``, ≈ 0 when rectified) and ``valid`` ``(B, K)`` bool (input mask and both points mapped
    in front of the homographies' line at infinity); zeros where not valid. The sign of d is not checked here."""

    disparity_px: torch.Tensor
    row_error_px: torch.Tensor
    valid: torch.Tensor


@dataclass(frozen=True)
class PointDepths:
    """Per-correspondence depth ``depth_m`` ``(B, K)`` = ``f·B / (d + doffs)`` and ``valid`` ``(B, K)``
    (valid disparity with ``d + doffs > 0``); zeros where not valid."""

    depth_m: torch.Tensor
    valid: torch.Tensor


class Quantiles(NamedTuple):
    """``values`` ``(..., Q)`` (0 where not valid) and ``valid`` ``(...)`` bool (at least one element)."""

    values: torch.Tensor
    valid: torch.Tensor


@dataclass(frozen=True)
class RangeEstimate:
    """The pair's disparity and depth range (Sec. 3.4). All ``(B,)``; zeros where not ``valid``.

    Attributes:
        d_min_px, d_max_px: Eq. (6), (5) over the inliers with ``d + doffs > 0`` (or the chosen percentiles).
        r_min_m: Eq. (7), ``f·B / (d_max + doffs)``.
        r_max_m: Eq. (8), ``f·B / (d_min + doffs)``.
        num_disparities: int64, inliers that entered.
        valid: bool, at least one did.
    """

    d_min_px: torch.Tensor
    d_max_px: torch.Tensor
    r_min_m: torch.Tensor
    r_max_m: torch.Tensor
    num_disparities: torch.Tensor
    valid: torch.Tensor


class Accuracy(NamedTuple):
    """Eq. (9) ``percent`` (same shape as the inputs) and ``valid`` bool (``real > 0``, both finite)."""

    percent: torch.Tensor
    valid: torch.Tensor


@dataclass(frozen=True)
class ObjectDepths:
    """Depth of each kept region (N slots; slot n is ``region_labels[:, n]``). All ``(B, N)``.

    Attributes:
        label: int64 label of the slot, −1 for padding.
        area_px: int64 pixel count of the region in the label image.
        centroid_x_px: mean column of the region (pixel centres); 0 where the area is 0.
        side: :class:`ObstacleSide` of the centroid (thirds of the pair's width), NONE where the area is 0.
        num_inliers: int64, valid depths whose left point lies on the region.
        depth_median_m, depth_low_m, depth_high_m: median and ``object_percentiles`` of those depths;
            0 where not ``valid``.
        valid: bool, the slot holds a region with at least ``min_inliers`` valid depths.
        point_slot: ``(B, K)`` int64, the slot of each correspondence (−1: none or invalid depth).
        num_valid_px: ``(B, N)`` int64, valid dense-disparity pixels of the region when the depths come from the
            dense stage (:func:`svs_torch.depth.dense_objects.dense_object_depths`); None for the sparse rule.
        num_in_view_px: ``(B, N)`` int64, those of them at columns where the pair's whole disparity range lands
            inside the right image (``DepthConfig.min_object_pixels_in_view``); None for the sparse rule.
    """

    label: torch.Tensor
    area_px: torch.Tensor
    centroid_x_px: torch.Tensor
    side: torch.Tensor
    num_inliers: torch.Tensor
    depth_median_m: torch.Tensor
    depth_low_m: torch.Tensor
    depth_high_m: torch.Tensor
    valid: torch.Tensor
    point_slot: torch.Tensor
    num_valid_px: torch.Tensor | None = None
    num_in_view_px: torch.Tensor | None = None


@dataclass(frozen=True)
class NearestObstacle:
    """The valid object with the smallest median depth: ``slot`` ``(B,)`` int64 (−1 none), ``depth_m`` ``(B,)``
    (its median, 0 none), ``side`` ``(B,)`` int64 :class:`ObstacleSide`, ``valid`` ``(B,)`` bool, and
    ``surface_m`` ``(B,)``: its low depth percentile (``DepthConfig.object_percentiles[0]``), the nearest visible
    surface of that obstacle — what a walker would bump into first (0 none)."""

    slot: torch.Tensor
    depth_m: torch.Tensor
    side: torch.Tensor
    valid: torch.Tensor
    surface_m: torch.Tensor | None = None


@dataclass(frozen=True)
class DepthResult:
    """Everything :func:`estimate_depth` computes; ``objects`` and ``nearest`` are None without labels."""

    disparities: Disparities
    points: PointDepths
    range: RangeEstimate
    objects: ObjectDepths | None
    nearest: NearestObstacle | None


def _per_pair(value: float | torch.Tensor | None, like: torch.Tensor, name: str) -> torch.Tensor:
    """A scalar or ``(B,)`` calibration value as a ``(B, 1)`` column in ``like``'s dtype (None → 0)."""
    value = torch.as_tensor(0.0 if value is None else value, dtype=like.dtype, device=like.device)
    if value.dim() == 1 and value.shape[0] != like.shape[0] or value.dim() > 1:
        raise InputError(f"{name}: expected a scalar or ({like.shape[0]},), got {tuple(value.shape)}")
    return value.expand(like.shape[0]).reshape(-1, 1)


def _quantile_levels(percentiles: tuple[float, float], name: str) -> tuple[float, float]:
    low, high = (float(p) for p in percentiles)
    if not 0 <= low <= high <= 100:
        raise InputError(f"{name}: expected (low, high) with 0 <= low <= high <= 100, got {tuple(percentiles)}")
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
            points, in_front = map_points(H.to(points.dtype), points)
            valid &= in_front
        mapped.append(points)
    delta = torch.where(valid.unsqueeze(-1), mapped[0] - mapped[1], torch.zeros_like(mapped[0]))
    return Disparities(delta[..., 0], delta[..., 1], valid)


def point_depths(disparity_px: torch.Tensor, valid: torch.Tensor, focal_px: float | torch.Tensor,
                 baseline_m: float | torch.Tensor, doffs_px: float | torch.Tensor | None = None) -> PointDepths:
    """Depth ``Z = f·B / (d + doffs)`` (Eq. (7)–(8) per point) of disparities ``(B, K)``; ``focal_px``,
    ``baseline_m``, ``doffs_px`` scalars or ``(B,)`` (``StereoBatch`` fields; doffs 0 for the SVS)."""
    _check_values(disparity_px, "disparity_px", valid, "valid")
    denominator = disparity_px + _per_pair(doffs_px, disparity_px, "doffs_px")
    valid = valid & (denominator > 0)
    scale = _per_pair(focal_px, disparity_px, "focal_px") * _per_pair(baseline_m, disparity_px, "baseline_m")
    safe = torch.where(valid, denominator, torch.ones_like(denominator))
    depth = scale / safe
    # A depth that underflows to 0 or overflows to inf (an extreme but finite calibration) is no depth.
    valid = valid & torch.isfinite(depth) & (depth > 0)
    return PointDepths(torch.where(valid, depth, torch.zeros_like(safe)), valid)


def masked_lower_median(values: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Lower median (``torch.median``'s) over the last dimension where ``mask`` holds: ``(...,)`` values
    (0 where empty) and ``(...,)`` int64 counts. Not differentiable (ground-truth statistics)."""
    count = mask.sum(-1)
    ordered = sort_last(torch.where(mask, values, torch.full_like(values, torch.inf)))
    median = ordered.gather(-1, ((count - 1).clamp(min=0) // 2).unsqueeze(-1)).squeeze(-1)
    return torch.where(count > 0, median, torch.zeros_like(median)), count


def kept_region_lower_median(values: torch.Tensor, known: torch.Tensor, labels: torch.Tensor,
                             kept_labels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`masked_lower_median` of ``values`` ``(B, 1, H, W)`` over each kept region's pixels where ``known``
    holds: ``(B, N)`` medians (0 where empty) and counts, slot n for region ``kept_labels[:, n]`` (−1: none) of
    ``labels`` ``(B, 1, H, W)``. The true distance of a region (GT depth), used for the truth of evaluations."""
    b = values.shape[0]
    region = ((labels.reshape(b, 1, -1) == kept_labels.unsqueeze(-1)) & (kept_labels > 0).unsqueeze(-1)
              & known.reshape(b, 1, -1))  # (B, N, H·W)
    return masked_lower_median(values.reshape(b, 1, -1).expand_as(region), region)


def masked_quantile(values: torch.Tensor, valid: torch.Tensor, q: Sequence[float] | torch.Tensor) -> Quantiles:
    """Quantiles ``q`` (in [0, 1]) over the valid entries of the last dimension of ``values`` ``(..., K)``,
    linear interpolation between order statistics (numpy's default, ``torch.quantile``'s ``"linear"``).
    Differentiable w.r.t. ``values`` (the two neighbouring order statistics get the gradient)."""
    check_dtype(values, "values", "float")
    if valid.shape != values.shape:
        raise InputError(f"valid: expected the shape of values {tuple(values.shape)}, got {tuple(valid.shape)}")
    check_dtype(valid, "valid", "bool")
    q = torch.as_tensor(q, dtype=values.dtype, device=values.device).flatten()
    if not bool(((q >= 0) & (q <= 1)).all()):  # written so that NaN fails too
        raise InputError(f"q: expected quantiles in [0, 1], got {q.tolist()}")
    count = valid.sum(dim=-1, keepdim=True)  # (..., 1)
    shape = (*values.shape[:-1], q.numel())
    if values.shape[-1] == 0:
        return Quantiles(values.new_zeros(shape), count.squeeze(-1) > 0)
    ordered = sort_last(torch.where(valid, values, torch.full_like(values, torch.inf)))
    rank = torch.arange(values.shape[-1], device=values.device)
    ordered = torch.where(rank < count, ordered, torch.zeros_like(ordered))  # padding sorts last; zero it
    low, high = _ranks(count, q)  # (..., Q)
    return _interpolate_ranks(ordered.gather(-1, low), ordered.gather(-1, high), count, q)


def labelled_quantile(values: torch.Tensor, labels: torch.Tensor, slots: torch.Tensor,
                      q: Sequence[float] | torch.Tensor) -> Quantiles:
    """:func:`masked_quantile` of ``values`` ``(B, P)`` over each slot's entries, ``labels == slots[:, n]``, for
    the slots ``(B, N)`` (a slot ≤ 0 and a label ≤ 0 take no entry): ``values`` ``(B, N, Q)``, ``valid``
    ``(B, N)``. The same numbers as ``masked_quantile(values.unsqueeze(1).expand(B, N, P), labels == slots)``
    with one sort of ``(B, P)`` instead of one of ``(B, N, P)``: each slot's order statistics are read from
    the pair's sorted values at the places where its running count of members reaches the rank. Without
    gradients, for float32 CPU values without NaN, a compiled quickselect per slot finds the same order
    statistics (:mod:`svs_torch.core.kernels`). Differentiable w.r.t. ``values`` (the two neighbouring order
    statistics get the gradient)."""
    check_dtype(values, "values", "float")
    check_shape(labels, "labels", list(values.shape))
    check_dtype(labels, "labels", "int")
    check_shape(slots, "slots", [values.shape[0], "N"])
    check_dtype(slots, "slots", "int")
    q = torch.as_tensor(q, dtype=values.dtype, device=values.device).flatten()
    if not bool(((q >= 0) & (q <= 1)).all()):  # written so that NaN fails too (the kernel casts it to a rank)
        raise InputError(f"q: expected quantiles in [0, 1], got {q.tolist()}")
    b, p = values.shape
    shape = (b, slots.shape[1], q.numel())
    if p == 0 or slots.shape[1] == 0:
        return Quantiles(values.new_zeros(shape), torch.zeros(shape[:2], dtype=torch.bool, device=values.device))
    if not (values.requires_grad and torch.is_grad_enabled()):
        # The compiled selection (svs_torch/kernels/labelled_select.c): the same order statistics, O(P) per slot;
        # None for values with NaN (it orders by <), which the sort below puts last.
        selected = kernels.labelled_select(values, labels, slots, q)
        if selected is not None:
            count, below, above = selected
            return _interpolate_ranks(below, above, count.unsqueeze(-1), q)
    labelled = labels > 0
    keyed = torch.where(labelled, values, torch.full_like(values, torch.inf))
    order = argsort_last(keyed)
    ordered = keyed.gather(1, order)
    sorted_labels = torch.where(labelled, labels, torch.zeros_like(labels)).gather(1, order)
    member = (sorted_labels.unsqueeze(1) == slots.unsqueeze(-1)) & (slots > 0).unsqueeze(-1)  # (B, N, P)
    running = member.cumsum(dim=-1)  # members up to and including each sorted place
    count = running[..., -1:]  # (B, N, 1)
    low, high = _ranks(count, q)
    # The member of rank r sits where the running count first reaches r + 1.
    places = torch.searchsorted(running, torch.cat([low, high], dim=-1) + 1).clamp_max(p - 1)
    below, above = ordered.unsqueeze(1).expand(-1, shape[1], -1).gather(-1, places).chunk(2, dim=-1)
    return _interpolate_ranks(below, above, count, q)


def _ranks(count: torch.Tensor, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The ranks below and above quantile ``q`` among ``count`` sorted members."""
    position = q * (count - 1).clamp_min(0).to(q.dtype)
    return position.floor().long(), position.ceil().long()


def _interpolate_ranks(below: torch.Tensor, above: torch.Tensor, count: torch.Tensor,
                       q: torch.Tensor) -> Quantiles:
    """Linear interpolation between the order statistics ``below`` / ``above`` ``(..., Q)`` of quantile ``q``
    among ``count`` ``(..., 1)`` members (0 where there are none)."""
    position = q * (count - 1).clamp_min(0).to(q.dtype)
    fraction = position - position.floor()
    result = below + (above - below) * fraction
    present = count > 0
    return Quantiles(torch.where(present, result, torch.zeros_like(result)), present.squeeze(-1))


def estimate_range(disparity_px: torch.Tensor, valid: torch.Tensor, focal_px: float | torch.Tensor,
                   baseline_m: float | torch.Tensor, doffs_px: float | torch.Tensor | None = None,
                   percentiles: tuple[float, float] | None = None) -> RangeEstimate:
    """The paper's range of a pair from its inlier disparities ``(B, K)`` (Sec. 3.4, Eq. (5)–(8)).

    ``percentiles=None`` is the paper: d_max and d_min are the max and min (5)–(6). ``(low, high)`` uses those
    percentiles instead (robust to a wrong same-row match). Disparities with ``d + doffs ≤ 0`` are left out.
    """
    depths = point_depths(disparity_px, valid, focal_px, baseline_m, doffs_px)
    q = (0.0, 1.0) if percentiles is None else _quantile_levels(percentiles, "percentiles")
    d_min, d_max = masked_quantile(disparity_px, depths.valid, q).values.unbind(-1)  # Eq. (6), (5)
    present = depths.valid.any(dim=1)
    doffs = _per_pair(doffs_px, disparity_px, "doffs_px").squeeze(1)
    scale = (_per_pair(focal_px, disparity_px, "focal_px") * _per_pair(baseline_m, disparity_px, "baseline_m"))
    scale = scale.squeeze(1)

    def depth(d: torch.Tensor) -> torch.Tensor:  # d + doffs > 0 for every entered disparity, so for its stats
        safe = torch.where(present, d + doffs, torch.ones_like(d))
        return torch.where(present, scale / safe, torch.zeros_like(d))

    return RangeEstimate(d_min, d_max, depth(d_max), depth(d_min), depths.valid.sum(dim=1), present)


def accuracy_percent(real_m: torch.Tensor, estimated_m: torch.Tensor) -> Accuracy:
    """Eq. (9): ``(1 − |real − est| / real) · 100`` elementwise (broadcast); valid where ``real > 0`` and both
    are finite. Differentiable w.r.t. both where valid (not at ``real = est``, a kink)."""
    real_m, estimated_m = torch.broadcast_tensors(torch.as_tensor(real_m), torch.as_tensor(estimated_m))
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
    under = labels.reshape(b, -1).gather(1, flat)
    under = torch.where(inside, under, torch.zeros_like(under))  # 0: background, never a slot's label
    return (under.unsqueeze(-1) == region_labels.unsqueeze(1)) & (region_labels > 0).unsqueeze(1)


def slot_labels(region_labels: torch.Tensor) -> torch.Tensor:
    """``region_labels`` with every padding or background slot (label ≤ 0) set to −1, which no pixel of a label
    image holds (labels are ≥ 0, 0 background): ``labels == slot_labels(...)`` is then each slot's region in one
    comparison, without a second full-frame pass for ``& (region_labels > 0)``."""
    return torch.where(region_labels > 0, region_labels, -1)


def _region_geometry(labels: torch.Tensor, region_labels: torch.Tensor,
                     image_hw: torch.Tensor, dtype: torch.dtype) -> tuple[torch.Tensor, ...]:
    """Area ``(B, N)``, centroid column ``(B, N)`` and :class:`ObstacleSide` ``(B, N)`` of each slot's region."""
    members = labels == slot_labels(region_labels).view(*region_labels.shape, 1, 1)  # (B, N, H, W)
    # Counted as bytes into int32 (a bool sum goes through int64): 0.15 against 0.44 ms for 8 pairs of two
    # 320×240 slots; counts stay far below 2³¹.
    per_column = members.view(torch.uint8).sum(dim=2, dtype=torch.int32).long()  # (B, N, W)
    area = per_column.sum(dim=-1)
    columns = torch.arange(labels.shape[-1], device=labels.device, dtype=dtype)
    centroid = (per_column.to(dtype) * columns).sum(dim=-1) / area.clamp_min(1).to(dtype)
    width = image_hw[:, 1:].to(dtype)  # thirds of the pair's own width, in pixel-centre coordinates
    side = torch.where(centroid < width / 3 - 0.5, int(ObstacleSide.LEFT),
                       torch.where(centroid < 2 * width / 3 - 0.5, int(ObstacleSide.CENTRE), int(ObstacleSide.RIGHT)))
    return area, centroid, torch.where(area > 0, side, int(ObstacleSide.NONE))


def object_depths(labels: torch.Tensor, region_labels: torch.Tensor, points_left: torch.Tensor,
                  depths: PointDepths, image_hw: torch.Tensor | None = None,
                  percentiles: tuple[float, float] = (10.0, 90.0), min_inliers: int = 1) -> ObjectDepths:
    """Per-object depth: each correspondence goes to the region under its left point; per region, the median
    and ``percentiles`` of its depths.

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
    _check_values(depths.depth_m, "depths.depth_m", depths.valid, "depths.valid")
    check_shape(depths.depth_m, "depths.depth_m", list(points_left.shape[:2]))
    if image_hw is None:
        image_hw = torch.tensor([labels.shape[-2:]], device=labels.device).expand(labels.shape[0], 2)
    check_shape(image_hw, "image_hw", [labels.shape[0], 2])
    check_dtype(image_hw, "image_hw", "int")
    labels, region_labels = labels.long(), region_labels.long()
    area, centroid, side = _region_geometry(labels, region_labels, image_hw, depths.depth_m.dtype)
    member = _point_slots(labels, region_labels, points_left, image_hw) & depths.valid.unsqueeze(-1)
    member = member.transpose(1, 2)  # (B, N, K)
    q = (0.5, *_quantile_levels(percentiles, "percentiles"))
    stats = masked_quantile(depths.depth_m.unsqueeze(1).expand_as(member), member, q).values  # (B, N, 3)
    count = member.sum(dim=-1)
    valid = (region_labels > 0) & (area > 0) & (count >= max(min_inliers, 1))
    stats = torch.where(valid.unsqueeze(-1), stats, torch.zeros_like(stats))
    point_slot = torch.full(member.shape[::2], -1, dtype=torch.int64, device=member.device)  # (B, K)
    if member.shape[1] > 0:
        point_slot = torch.where(member.any(dim=1), member.to(torch.uint8).argmax(dim=1), point_slot)
    return ObjectDepths(torch.where(region_labels > 0, region_labels, -1), area, centroid, side, count,
                        *stats.unbind(-1), valid, point_slot)


def nearest_obstacle(objects: ObjectDepths) -> NearestObstacle:
    """The valid object with the smallest median depth, its depth and side (Sec. 3.4's warning to the user)."""
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
                   config: DepthConfig = DepthConfig()) -> DepthResult:
    """The depth stage: rectified disparities of the inliers ``(B, K)``, the pair's range (Eq. (5)–(8)) and,
    given ``labels`` and ``region_labels``, per-object depths and the nearest obstacle. Arguments as in
    :func:`rectified_disparity`, :func:`point_depths`, :func:`object_depths`."""
    if (labels is None) != (region_labels is None):
        raise InputError("region_labels: expected it together with labels (both or neither)")
    disparities = rectified_disparity(points_left, points_right, inliers, H_left, H_right)
    depths = point_depths(disparities.disparity_px, disparities.valid, focal_px, baseline_m, doffs_px)
    pair_range = estimate_range(disparities.disparity_px, disparities.valid, focal_px, baseline_m, doffs_px,
                                config.percentiles)
    if labels is None:
        return DepthResult(disparities, depths, pair_range, None, None)
    objects = object_depths(labels, region_labels, points_left, depths, image_hw, config.object_percentiles,
                            config.min_object_inliers)
    return DepthResult(disparities, depths, pair_range, objects, nearest_obstacle(objects))
