"""Obstacle depth from the dense disparity over each kept region (the product's range rule; Sec. 3.4 in spirit).

The paper's Eq. (5)–(8) take R_min / R_max as the extremes over the sparse inliers. Here each kept object's
distance is the median of ``Z = f·B / (d + doffs)`` over the valid dense disparities of its region
(:mod:`svs_torch.depth.dense`), with a low and a high percentile and the count of valid pixels; R_min / R_max are the
nearest and the farthest kept object, and the nearest obstacle's low percentile is its nearest visible surface.
The same definition is used for the ground truth (``svs_torch`` experiments: the median GT depth over the same
pixels, the kept region's interior under ``PipelineConfig.region_interior_working_px``), so the two are directly
comparable by Eq. (9).

Only the pixels inside each pair's searched box are read (``DenseDisparity.crop_xywh``): the rest is invalid.
Differentiable w.r.t. ``disparity_px``, focal length and baseline where valid (median and percentiles pass
gradients to the order statistics they interpolate); masks and counts are not.
"""

from __future__ import annotations

import dataclasses

import torch

from ..core.checks import InputError, check_dtype, check_instance, check_percentiles, check_shape
from ..core.kernels.checks import check_nonempty, check_rows
from ..core.mask_reductions import count_along
from ..geometry.rectification import apply_homography
from . import kernels
from .block_matching import fill_invalid_rows
from .cost_volume import crop_index
from .dense_config import DenseDisparity
from .depth_types import Disparities, ObjectDepths, RangeEstimate
from .quantiles import Quantiles, _interpolate_ranks, labelled_quantile

__all__ = ["count_agreeing_inliers", "dense_object_depths", "range_from_objects", "surface_pixels"]


def _per_pair(value: torch.Tensor | float, b: int, like: torch.Tensor, name: str) -> torch.Tensor:
    value = torch.as_tensor(value, dtype=like.dtype, device=like.device)
    if value.dim() == 0:
        value = value.expand(b)
    check_shape(value, name, [b])
    return value


def _check_inputs(dense: DenseDisparity, labels: torch.Tensor, objects: ObjectDepths,
                  percentiles: tuple[float, float]) -> tuple[int, float, float]:
    """:func:`dense_object_depths`' arguments checked: the batch size and the two percentiles."""
    check_instance(dense, "dense", DenseDisparity)  # a (disparity, valid) tuple failed on .disparity_px (an audit)
    check_instance(objects, "objects", ObjectDepths)
    disparity = dense.disparity_px
    dims = check_shape(disparity, "dense.disparity_px", ["B", 1, "H", "W"])
    b, h, w = dims["B"], dims["H"], dims["W"]
    check_shape(dense.valid, "dense.valid", [b, 1, h, w])
    check_dtype(dense.valid, "dense.valid", "bool")
    check_nonempty(disparity, "dense.disparity_px")
    check_rows(dense.crop_xywh, "dense.crop_xywh", b, 4)
    _check_boxes_in_frame(dense.crop_xywh, h, w)
    check_rows(dense.min_disparity_px, "dense.min_disparity_px", b)
    check_rows(dense.pair_num_disparities, "dense.pair_num_disparities", b)
    check_shape(labels, "labels", list(disparity.shape))
    check_dtype(labels, "labels", "int")
    check_rows(objects.label, "objects.label", b, "N")
    check_percentiles(percentiles, "percentiles")
    low, high = (float(p) for p in percentiles)
    return b, low, high


def _check_boxes_in_frame(boxes: torch.Tensor, h: int, w: int) -> None:
    """Each searched box (x0, y0, width, height) within the ``h`` × ``w`` map widened by its own size on every
    side (a box may reach past the frame, whose border repeats there): one 4e7 px wide on an 8 × 16 map was counted
    320 million valid pixels (4.4 GB), and x0 = -2^63 overflowed the kernel's arithmetic."""
    x0, y0, width, height = boxes.long().unbind(1)
    inside = ((x0 >= -w) & (y0 >= -h) & (width >= 0) & (height >= 0) & (width <= 2 * w - x0)
              & (height <= 2 * h - y0))
    if not bool(inside.all()):
        raise InputError(f"dense.crop_xywh: expected boxes (x0, y0, width, height) within the {w}x{h} map widened "
                         f"by its size on each side, got {boxes[~inside].tolist()[:4]}")


def _compiled_statistics(dense: DenseDisparity, labels: torch.Tensor, slots: torch.Tensor, scale: torch.Tensor,
                         doffs: torch.Tensor, in_view_from: torch.Tensor, fill_invalid: bool, q: torch.Tensor
                         ) -> tuple[Quantiles, torch.Tensor, torch.Tensor] | None:
    """The compiled path (``depth/kernels/object_depths.c``): each pair read once at its own box, the same
    statistics bit for bit, where the torch path pads every pair to the batch's largest box (B = 128: twice the
    time a pair of B = 32). Each object's (median, low, high) depths (and whether it had a member), valid and
    in-view counts; None where the kernel does not run."""
    b = dense.disparity_px.shape[0]
    fused = kernels.object_depths(dense.disparity_px[:, 0], dense.valid[:, 0], labels[:, 0].long(), dense.crop_xywh,
                                  slots, scale.view(b), doffs.view(b), in_view_from, fill_invalid, q)
    if fused is None:
        return None
    members, count, in_view, below, above = fused
    return _interpolate_ranks(below, above, members.unsqueeze(-1), q), count, in_view


def _statistics(dense: DenseDisparity, labels: torch.Tensor, slots: torch.Tensor, focal: torch.Tensor,
                baseline: torch.Tensor, doffs: torch.Tensor, in_view_from: torch.Tensor, fill_invalid: bool,
                q: torch.Tensor) -> tuple[Quantiles, torch.Tensor, torch.Tensor]:
    """Each object's depth quantiles ``q`` over its pixels of ``dense`` (and whether it had any), its measured
    count and those in view: compiled where no gradient is asked for, else in torch; the same numbers."""
    gradients = torch.is_grad_enabled() and any(t.requires_grad for t in (dense.disparity_px, focal, baseline, doffs))
    if not gradients:
        fused = _compiled_statistics(dense, labels, slots, focal * baseline, doffs, in_view_from, fill_invalid, q)
        if fused is not None:
            return fused
    return _torch_statistics(dense, labels, slots, focal, baseline, doffs, q, fill_invalid, in_view_from)


def _surface_low(stats: torch.Tensor, dense: DenseDisparity, surface_valid: torch.Tensor, arguments: tuple,
                 q: torch.Tensor) -> torch.Tensor:
    """``stats`` ``(B, N, 3)`` with the low percentile ``q[1]`` taken again over ``surface_valid``'s pixels (filled
    as ``dense.valid``'s are), for each object that has a measured pixel among them: the fill reaches across
    objects, so one with none would take its neighbours' depths. ``arguments``: the rest of :func:`_statistics`'."""
    check_shape(surface_valid, "surface_valid", list(dense.disparity_px.shape))
    check_dtype(surface_valid, "surface_valid", "bool")
    surface, measured, _ = _statistics(dataclasses.replace(dense, valid=surface_valid), *arguments, q[1:2])
    low = torch.where(measured > 0, surface.values[..., 0], stats[..., 1])
    return torch.stack([stats[..., 0], low, stats[..., 2]], dim=-1)


def surface_pixels(dense: DenseDisparity) -> torch.Tensor | None:
    """``(B, 1, H, W)`` bool: the valid pixels of ``dense`` an object's low depth percentile, its nearest visible
    surface, is taken over (``DepthConfig.surface_within_in_view_top``): those at or below the pair's in-view top
    ``dense.in_view_top_px`` (half a pixel above it allowed for the sub-pixel fit). None where the map has no such
    top or no valid pixel lies above it: then every valid pixel counts.

    Why: two noisy frames in a row widen a pair's search range (the coarse pass's detached near tail of wrong
    matches, which the in-view top leaves out), and the dense map then holds wrong matches far above the object's
    true disparity on over a tenth of its pixels. Its median stays right, its 10th depth percentile does not: a box
    1.25 m away said at 0.96 and 0.69 m, a false "Stop" (experiments/guide_confirm.md, "The digit 8 walks' false
    messages traced"). The median and the high percentile stay over every pixel: cut there too, the tuned scenes'
    medians moved by up to 0.1 point of accuracy, both ways."""
    if dense.in_view_top_px is None:
        return None
    b = check_shape(dense.disparity_px, "dense.disparity_px", ["B", 1, "H", "W"])["B"]
    check_shape(dense.valid, "dense.valid", list(dense.disparity_px.shape))
    check_rows(dense.in_view_top_px, "dense.in_view_top_px", b)
    top = dense.in_view_top_px.to(dense.disparity_px.dtype).view(-1, 1, 1, 1) + 0.5
    surface = dense.valid & (dense.disparity_px.detach() <= top)
    return None if torch.equal(surface, dense.valid) else surface


def dense_object_depths(dense: DenseDisparity, labels: torch.Tensor, objects: ObjectDepths,
                        focal_px: torch.Tensor | float, baseline_m: torch.Tensor | float,
                        doffs_px: torch.Tensor | float = 0.0, percentiles: tuple[float, float] = (10.0, 90.0),
                        min_valid_px: int = 20, fill_invalid: bool = True,
                        min_valid_fraction: float | torch.Tensor = 0.0, min_in_view_px: int = 0,
                        min_own_view_valid_share: float = 0.0, surface_valid: torch.Tensor | None = None
                        ) -> ObjectDepths:
    """Per-object depth from dense disparity; differentiable w.r.t. ``dense.disparity_px`` and the calibration.

    Args:
        dense: :class:`~svs_torch.depth.dense.DenseDisparity` of the left view ``(B, 1, H, W)``.
        labels: ``(B, 1, H, W)`` int64 left label image in the same pixels as ``dense`` (warped with the left
            homography when the pair was rectified).
        objects: the slots to fill (:func:`~svs_torch.depth.object_depths` over the sparse inliers gives their
            labels, areas, sides and inlier counts; those are kept).
        focal_px, baseline_m, doffs_px: scalars or ``(B,)``.
        percentiles: low and high percentiles in [0, 100] besides the median.
        min_valid_px: fewest valid dense pixels for an object's depth to count.
        min_valid_fraction: least share of the region's pixels with a valid dense disparity for its depth to
            count, a scalar or ``(B,)``: views that do not show the same scene (a swapped or frozen camera) leave
            most pixels inconsistent, and such an object is not ranged rather than ranged wrong.
        min_in_view_px: fewest valid pixels an object needs at columns ``x ≥ d_max`` of its pair, where every
            disparity searched lands inside the right image (``DepthConfig.min_object_pixels_in_view``; ``d_max``:
            the range's top, ``dense.in_view_top_px`` below it, or the object's own ``dense.object_in_view_top_px``
            where at least ``min_own_view_valid_share`` of its pixels from there on are valid: :func:`_trusted_from`);
            0: no check. The statistics are still over all the object's pixels.
        fill_invalid: give the region's invalid pixels the disparity of their row neighbours
            (:func:`~svs_torch.depth.block_matching.fill_invalid_rows`) before taking the statistics, so that the median
            is over the whole region, as the truth is, and not only over its well-textured part.
        surface_valid: ``(B, 1, H, W)`` bool or None: the pixels the low percentile is taken over
            (:func:`surface_pixels`), for each object with a measured pixel among them (filled as ``dense.valid`` is);
            None: the valid ones, as the median.

    Returns:
        ``objects`` with ``depth_median_m``, ``depth_low_m``, ``depth_high_m``, ``valid`` from the dense pixels
        and ``num_valid_px``, ``num_in_view_px`` ``(B, N)`` int64 set.
    """
    b, low, high = _check_inputs(dense, labels, objects, percentiles)
    disparity = dense.disparity_px
    focal = _per_pair(focal_px, b, disparity, "focal_px").view(b, 1)
    baseline = _per_pair(baseline_m, b, disparity, "baseline_m").view(b, 1)
    doffs = _per_pair(doffs_px, b, disparity, "doffs_px").view(b, 1)
    slots = objects.label  # (B, N), −1 padding
    q = torch.tensor([0.5, low / 100, high / 100], dtype=disparity.dtype, device=disparity.device)
    in_view_from = _trusted_from(dense, labels, slots, min_own_view_valid_share)
    arguments = (labels, slots, focal, baseline, doffs, in_view_from, fill_invalid)
    stats, count, in_view = _statistics(dense, *arguments, q)
    stats = stats.values if surface_valid is None else _surface_low(stats.values, dense, surface_valid, arguments, q)
    count = torch.where(slots > 0, count, 0)
    in_view = torch.where(slots > 0, in_view, 0)
    fraction = _per_pair(min_valid_fraction, b, disparity, "min_valid_fraction").view(b, 1)
    valid = (slots > 0) & (count >= max(min_valid_px, 1)) & (count >= fraction * objects.area_px)
    if min_in_view_px > 0:
        valid &= in_view >= min_in_view_px
    stats = torch.where(valid.unsqueeze(-1), stats, torch.zeros_like(stats))
    median, depth_low, depth_high = stats.unbind(-1)
    return dataclasses.replace(objects, depth_median_m=median, depth_low_m=depth_low, depth_high_m=depth_high,
                               valid=valid, num_valid_px=count, num_in_view_px=in_view)


def _in_view_from(dense: DenseDisparity, num_slots: int) -> torch.Tensor:
    """``(B, N)`` int64: the pair's first column where every disparity of its range lands inside the right image
    (``x − d_max ≥ 0``; ``d_max`` without noise's detached wrong matches where ``dense.in_view_top_px`` says), for
    each of its ``num_slots`` objects."""
    top = dense.min_disparity_px + dense.pair_num_disparities - 1
    if dense.in_view_top_px is not None:
        top = torch.minimum(top, dense.in_view_top_px)
    return top.clamp_min(0).long().unsqueeze(1).expand(-1, num_slots).contiguous()


def _trusted_from(dense: DenseDisparity, labels: torch.Tensor, slots: torch.Tensor, min_share: float
                  ) -> torch.Tensor:
    """Each object's first column in view ``(B, N)``: the pair's (:func:`_in_view_from`), or the object's own from
    ``dense.object_in_view_top_px`` where that lies below it and at least ``min_share`` of its pixels
    (``labels == slots``) from its own first column on are valid. Why: an object the right camera cannot see at all
    (wholly in the band its true disparity leaves out of view) still gets coarse matches, wrong and small, so its
    own top is low; the dense matcher's checks then reject most of its pixels (a near strip on the left border: a
    third valid; a far box seen there: 0.93–1.00, camera frames and a ±30 % gain included;
    experiments/real_rig.md, "Each object's own in-view top")."""
    num_slots = slots.shape[1]
    shared = _in_view_from(dense, num_slots)
    if dense.object_in_view_top_px is None:
        return shared
    if dense.object_in_view_top_px.shape != shared.shape:
        raise InputError(f"dense.object_in_view_top_px: expected one column per object slot ({num_slots}), got "
                         f"shape {tuple(dense.object_in_view_top_px.shape)}")
    own = torch.minimum(shared, dense.object_in_view_top_px.clamp_min(0).long())
    lowered = (own < shared) & (slots > 0)
    if min_share <= 0 or not bool(lowered.any()):
        return own
    pairs = lowered.any(dim=1).nonzero().flatten()  # only the pairs with a lowered object pay for the count
    pair_labels, valid = labels[pairs, 0], dense.valid[pairs, 0]
    columns = torch.arange(labels.shape[-1], device=labels.device).view(1, 1, -1)
    share = []
    for n in range(num_slots):  # a handful of objects
        band = (pair_labels == slots[pairs, n].view(-1, 1, 1)) & (columns >= own[pairs, n].view(-1, 1, 1))
        share.append(count_along(band & valid, (1, 2)) / count_along(band, (1, 2)).clamp_min(1))
    trusted = torch.ones_like(lowered).index_copy(0, pairs, torch.stack(share, dim=1) >= min_share)
    return torch.where(lowered & ~trusted, shared, own)


def _torch_statistics(dense: DenseDisparity, labels: torch.Tensor, slots: torch.Tensor, focal: torch.Tensor,
                      baseline: torch.Tensor, doffs: torch.Tensor, q: torch.Tensor, fill_invalid: bool,
                      in_view_from: torch.Tensor) -> tuple[Quantiles, torch.Tensor, torch.Tensor]:
    """:func:`dense_object_depths`' statistics ``(B, N, Q)``, measured counts ``(B, N)`` and those of them at
    frame columns from ``in_view_from`` ``(B, N)`` on, in torch (the differentiable path): every pair cropped to
    the batch's largest box."""
    disparity = dense.disparity_px
    b = disparity.shape[0]
    x0, y0, width, height = dense.crop_xywh.unbind(1)
    size_w, size_h = int(width.max()) if b else 0, int(height.max()) if b else 0
    # One index for the three crops (clamped reads, as crop_box makes them).
    index = crop_index(x0, y0, size_h, size_w, disparity.shape[-2:]).flatten(1)  # (B, P)
    crop_d = disparity.flatten(1).gather(1, index)
    # Positions past a pair's own box repeat its border pixels (clamped reads): they must not count.
    inside = ((torch.arange(size_h, device=disparity.device).view(1, -1, 1) < height.view(-1, 1, 1))
              & (torch.arange(size_w, device=disparity.device).view(1, 1, -1) < width.view(-1, 1, 1))).flatten(1)
    crop_ok = dense.valid.flatten(1).gather(1, index) & inside
    crop_labels = torch.where(inside, labels.long().flatten(1).gather(1, index), 0)
    measured = crop_ok
    if fill_invalid:
        filled, reachable = fill_invalid_rows(crop_d.view(b, size_h, size_w), crop_ok.view(b, size_h, size_w))
        crop_d, crop_ok = filled.flatten(1), reachable.flatten(1)
    denominator = crop_d + doffs
    crop_ok = crop_ok & (denominator > 0)
    depth = focal * baseline / torch.where(crop_ok, denominator, torch.ones_like(denominator))
    # A depth that underflows to 0 or overflows to inf (an extreme but finite calibration) is no depth.
    crop_ok = crop_ok & torch.isfinite(depth) & (depth > 0)
    depth = torch.where(crop_ok, depth, torch.zeros_like(denominator))  # (B, P)
    stats = labelled_quantile(depth, torch.where(crop_ok, crop_labels, torch.zeros_like(crop_labels)), slots, q)
    measured_labels = torch.where(crop_ok & measured, crop_labels, torch.zeros_like(crop_labels))
    # The frame column of each crop position (clamped, as the reads are): in view from in_view_from on.
    columns = (x0.view(-1, 1) + torch.arange(size_w, device=disparity.device)).clamp(0, disparity.shape[-1] - 1)
    # One compare and count per slot (a handful of objects) instead of a (B, N, P) volume of compares.
    count, count_in_view = [], []
    for n in range(slots.shape[1]):
        member = measured_labels == slots[:, n:n + 1]
        in_view = (columns >= in_view_from[:, n:n + 1]).view(b, 1, size_w).expand(b, size_h, size_w).flatten(1)
        count.append(member.sum(dim=1))
        count_in_view.append((member & in_view).sum(dim=1))
    if not count:
        return stats, torch.zeros_like(slots), torch.zeros_like(slots)
    return stats, torch.stack(count, dim=1), torch.stack(count_in_view, dim=1)


def count_agreeing_inliers(dense: DenseDisparity, points_left: torch.Tensor, disparities: Disparities,
                           inliers: torch.Tensor, H_left: torch.Tensor | None = None,
                           tolerance_px: float | torch.Tensor = 1.0, return_measured: bool = False
                           ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """How many RANSAC inliers the dense map confirms: ``(B,)`` int64, the inliers whose sparse disparity lies
    within ``tolerance_px`` of the dense disparity at their left point, where that pixel is valid; with
    ``return_measured`` (as ``torch.unique``'s ``return_counts``), also how many lie at a valid pixel, agreeing or
    not, ``(B,)`` int64 (``PipelineConfig.verify_unanimous_min_inliers``).

    Two independent measurements agree there: the sparse match (SURF, SAD, RANSAC's F) and the dense block
    matcher's winner at that pixel. Between views of one scene most inliers on the kept regions agree; between
    views of different scenes RANSAC can still fit some F to a dozen chance matches, but their disparities are
    chance too and the dense map confirms almost none (``experiments/verify_views.py``: at most 5 on 1966
    pairs of unrelated real views, at most 1 on 64 synthetic ones, 7 or more on 197 of 199 real and synthetic
    pairs).

    Args:
        dense: :class:`~svs_torch.depth.dense.DenseDisparity` of the left view (rectified pixels where the pair was
            rectified).
        points_left: ``(B, K, 2)`` left points of the correspondences, input pixels.
        disparities: their :class:`~svs_torch.depth.Disparities` (rectified by the same homographies).
        inliers: ``(B, K)`` bool, RANSAC's inliers.
        H_left: ``(B, 3, 3)`` the left homography the dense map was measured after; None: the identity.
        tolerance_px: largest disagreement counted as agreement, a scalar or ``(B,)``, input pixels.

    Not differentiable (a count).
    """
    check_shape(points_left, "points_left", ["B", "K", 2])
    check_shape(inliers, "inliers", list(points_left.shape[:2]))
    check_dtype(inliers, "inliers", "bool")
    disparity = dense.disparity_px
    b, (height, width) = disparity.shape[0], disparity.shape[-2:]
    xy, usable = points_left, inliers & disparities.valid
    if H_left is not None:
        xy, in_front = apply_homography(H_left, points_left.to(H_left.dtype))
        usable = usable & in_front
    # The pixel holding each point (pixel centres at whole coordinates, as keypoints are).
    column, row = xy[..., 0].round(), xy[..., 1].round()
    usable = usable & (column >= 0) & (column < width) & (row >= 0) & (row < height)
    index = torch.where(usable, row * width + column, torch.zeros_like(row)).long()
    dense_d = disparity.flatten(1).gather(1, index)
    measured = dense.valid.flatten(1).gather(1, index) & usable
    tolerance = _per_pair(tolerance_px, b, disparity, "tolerance_px").view(b, 1)
    agree = measured & ((dense_d - disparities.disparity_px.to(dense_d.dtype)).abs() <= tolerance)
    return (agree.sum(dim=1), measured.sum(dim=1)) if return_measured else agree.sum(dim=1)


def range_from_objects(objects: ObjectDepths, focal_px: torch.Tensor | float, baseline_m: torch.Tensor | float,
                       doffs_px: torch.Tensor | float = 0.0, order_by: torch.Tensor | None = None) -> RangeEstimate:
    """R_min / R_max as the nearest / farthest valid object's median depth ``(B,)``; d_max / d_min their
    disparities ``f·B / R − doffs``; ``num_disparities`` the valid dense pixels (or inliers) that entered.
    ``order_by`` ``(B, N)`` (optional): the depths that choose the nearest and farthest object, if not the medians
    (the differentiable pass chooses on the hard ones, so that R_min is the object the hard pipeline named).
    Differentiable w.r.t. the nearest and farthest valid ``objects.depth_median_m`` and the calibration;
    ``num_disparities`` and ``valid`` are not."""
    check_instance(objects, "objects", ObjectDepths)  # None failed on .depth_median_m (an audit)
    median = objects.depth_median_m
    b = median.shape[0]
    valid = objects.valid
    present = valid.any(dim=1)
    if median.shape[1] == 0:
        nearest = farthest = median.new_zeros(b)
    elif order_by is None:
        nearest = torch.where(valid, median, torch.full_like(median, torch.inf)).amin(dim=1)
        farthest = torch.where(valid, median, torch.full_like(median, -torch.inf)).amax(dim=1)
    else:
        check_shape(order_by, "order_by", list(median.shape))
        near_slot = torch.where(valid, order_by, torch.inf).argmin(dim=1, keepdim=True)
        far_slot = torch.where(valid, order_by, -torch.inf).argmax(dim=1, keepdim=True)
        nearest, farthest = median.gather(1, near_slot).squeeze(1), median.gather(1, far_slot).squeeze(1)
    r_min = torch.where(present, nearest, torch.zeros_like(nearest))
    r_max = torch.where(present, farthest, torch.zeros_like(farthest))
    scale = _per_pair(focal_px, b, median, "focal_px") * _per_pair(baseline_m, b, median, "baseline_m")
    doffs = _per_pair(doffs_px, b, median, "doffs_px")

    def disparity(depth: torch.Tensor) -> torch.Tensor:
        return torch.where(present, scale / torch.where(present, depth, torch.ones_like(depth)) - doffs,
                           torch.zeros_like(depth))

    counts = objects.num_valid_px if objects.num_valid_px is not None else objects.num_inliers
    used = torch.where(valid, counts, torch.zeros_like(counts)).sum(dim=1)
    return RangeEstimate(disparity(r_max), disparity(r_min), r_min, r_max, used, present)
