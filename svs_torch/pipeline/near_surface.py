"""An object whose kept region spans two surfaces far apart is measured over its nearer surface (issues 32 and 33).

Under camera noise the nearness segmenter can join a near obstacle and the wall behind it into one kept region
(the noise links their near-class pixels across the gap). Its dense disparities then fall into two separate
groups, and the median over the whole region is that of whichever surface holds more of its pixels: a box at 1.4 m
before a wall at 4 m is ranged at 4 m, or a mostly-wall region at 1.4 m, and a few pixels more on one side flip it
(rendered SVS scenes as JPEG digit 8 frames: 64–70 % per object where the map's own pixel errors are under half a
pixel). For a walker the obstacle is the near surface. So a kept object whose measured disparities split (Otsu)
into two groups at least :data:`MIN_DISPARITY_RATIO` times apart, each with :data:`MIN_CLASS_SHARE` of the
measured pixels, is cut to the pixels whose disparity (row-filled, as its depth is: ``DenseConfig.fill_invalid``)
lies in the near group, and ranged over them. Its truth in every experiment follows, since an object's true
distance is the median ground truth over the pixels it was measured over (``PipelineResult.object_labels``).

Two guards against noise, which also makes near groups: the near group's largest 8-connected piece holds at least
:data:`MIN_COHERENT_SHARE` of it and :data:`MIN_COHERENT_AREA_FRACTION` of the image (wrong matches scatter; a surface
is one piece), and its median disparity is at most :data:`MAX_INLIER_RATIO` times the pair's largest RANSAC inlier
disparity plus :data:`INLIER_MARGIN_PX` (a near surface the features saw nothing as near as is more likely a blob of
wrong matches: the tuned PianoL as a digit 8 frame, a coherent group at 62 px among true 13–17 px, inliers up to 19).
A pair rectified by the pipeline is left as it is: its map is in rectified pixels, its labels in input pixels.

Chosen on the tuning sets only, over three draws of the camera noise (``experiments/real_rig.py --noise-seed``;
``experiments/real_rig.md``, "Two surfaces in one kept region"). Not differentiable (a mask); the differentiable
pass measures over the same pixels (``PipelineResult.object_labels``).
"""

from __future__ import annotations

import dataclasses

import torch

from ..depth.block_matching import fill_invalid_rows
from ..depth.dense_config import DenseDisparity
from ..depth.dense_objects import dense_object_depths, range_from_objects
from ..depth.depth_types import DepthResult
from ..depth.quantiles import masked_lower_median
from ..depth.sparse import nearest_obstacle
from ..segmentation.components import connected_components_with_stats
from .config import PipelineConfig

__all__ = []

#: The two groups' mean disparities differ at least this many times (a depth ratio: a box at 1.9 m before a wall
#: at 4 m is 2.1); at 1.5 real objects spanning depth were cut (tuned split, 320×240: 98.83 → 98.70 %).
MIN_DISPARITY_RATIO = 2.0
#: Each group holds at least this share of the object's measured pixels.
MIN_CLASS_SHARE = 0.25
#: The near group's largest 8-connected piece holds at least this share of its pixels ...
MIN_COHERENT_SHARE = 0.5
#: ... and at least this share of the image (200 pixels at 320×240).
MIN_COHERENT_AREA_FRACTION = 200 / (320 * 240)
#: The near group's median disparity is at most this many times the pair's largest RANSAC inlier disparity ...
MAX_INLIER_RATIO = 1.25
#: ... plus this many pixels.
INLIER_MARGIN_PX = 2.0
#: Bins of each object's disparity histogram for Otsu's split.
HISTOGRAM_BINS = 64


def measure_near_surfaces(depth: DepthResult, dense: DenseDisparity, object_labels: torch.Tensor,
                          rectified: torch.Tensor, inliers: torch.Tensor, focal_px: torch.Tensor,
                          baseline_m: torch.Tensor, doffs_px: torch.Tensor, config: PipelineConfig
                          ) -> tuple[DepthResult, torch.Tensor, torch.Tensor]:
    """``depth`` with each two-surface object (module docstring) ranged over its near surface, the object labels it
    was then measured over ``(B, 1, H, W)`` and which objects were cut ``(B, N)`` bool. ``dense``: the final dense
    map, in input pixels where not ``rectified`` ``(B,)``; ``object_labels``: the labels the objects were measured
    over; ``inliers`` ``(B, K)`` bool: RANSAC's inliers among ``depth.disparities``; ``config``: the pipeline's
    (its depth rule's settings). An object keeps its validity: a near surface that cannot be ranged leaves the
    object as it was."""
    objects = depth.objects
    slots = torch.where(objects.valid, objects.label, torch.zeros_like(objects.label))
    cut = torch.zeros_like(objects.valid)
    if slots.shape[1] == 0 or not bool(((slots > 0) & ~rectified.view(-1, 1)).any()):
        return depth, object_labels, cut
    disparity, valid = dense.disparity_px.detach(), dense.valid
    # The pixels its depth is measured over: the row-filled map where the depth rule fills it.
    filled, reachable = (fill_invalid_rows(disparity[:, 0], valid[:, 0]) if config.dense.fill_invalid
                         else (disparity[:, 0], valid[:, 0]))
    sparse = depth.disparities
    known = inliers & sparse.valid & sparse.disparity_px.isfinite()
    top = torch.where(known, sparse.disparity_px.detach(), torch.zeros_like(sparse.disparity_px)).amax(1)
    limit = MAX_INLIER_RATIO * top + INLIER_MARGIN_PX  # (B,)
    least = max(1.0, MIN_COHERENT_AREA_FRACTION * object_labels.shape[-2] * object_labels.shape[-1])
    labels = object_labels
    for n in range(slots.shape[1]):  # a handful of objects, each over the whole batch
        slot = slots[:, n].view(-1, 1, 1, 1)
        member = (object_labels == slot) & (slot > 0) & ~rectified.view(-1, 1, 1, 1)
        threshold, split = _two_groups(disparity, member & valid, limit, least)
        cut[:, n] = split
        if bool(split.any()):
            far = member & split.view(-1, 1, 1, 1) & ~(reachable.unsqueeze(1)
                                                       & (filled.unsqueeze(1) > threshold.view(-1, 1, 1, 1)))
            labels = torch.where(far, torch.zeros_like(labels), labels)
    if not bool(cut.any()):
        return depth, object_labels, cut
    near = dense_object_depths(dense, labels, objects, focal_px, baseline_m, doffs_px,
                               config.depth.object_percentiles, config.depth.min_object_pixels,
                               config.dense.fill_invalid, 0.0, config.depth.min_object_pixels_in_view)
    # An object whose near surface cannot be ranged keeps its whole region and its depth.
    cut = cut & near.valid
    if not bool(cut.any()):
        return depth, object_labels, cut
    keep = torch.stack([~cut[:, n].view(-1, 1, 1) | (object_labels[:, 0] != slots[:, n].view(-1, 1, 1))
                        for n in range(slots.shape[1])]).all(0).unsqueeze(1)
    labels = torch.where(keep, object_labels, labels)
    # Its area is now the pixels it is measured over (estimate --json's measured_area_px).
    area = torch.stack([(labels == slots[:, n].view(-1, 1, 1, 1)).flatten(1).sum(1)
                        for n in range(slots.shape[1])], dim=1)
    merged = dataclasses.replace(objects, area_px=torch.where(cut, area, objects.area_px), **{
        name: torch.where(cut, getattr(near, name), getattr(objects, name))
        for name in ("depth_median_m", "depth_low_m", "depth_high_m", "num_valid_px", "num_in_view_px")})
    depth_range = range_from_objects(merged, focal_px, baseline_m, doffs_px)
    return DepthResult(depth.disparities, depth.points, depth_range, merged, nearest_obstacle(merged)), labels, cut


def _two_groups(disparity: torch.Tensor, member: torch.Tensor, limit: torch.Tensor, least: float
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """Otsu's split of each pair's ``member`` disparities ``(B, 1, H, W)`` and whether it makes two surfaces
    (module docstring): the threshold ``(B,)`` and ``(B,)`` bool."""
    b = disparity.shape[0]
    values, mask = disparity.flatten(1), member.flatten(1)
    count = mask.sum(1)
    low = torch.where(mask, values, torch.inf).amin(1)
    high = torch.where(mask, values, -torch.inf).amax(1)
    span = (high - low).clamp_min(1e-6)
    bins = ((values - low.view(-1, 1)) / span.view(-1, 1) * HISTOGRAM_BINS).floor().clamp(0, HISTOGRAM_BINS - 1)
    index = torch.where(mask, bins.long(), torch.zeros_like(bins, dtype=torch.long))
    histogram = torch.zeros(b, HISTOGRAM_BINS, dtype=torch.float64, device=disparity.device)
    histogram.scatter_add_(1, index, mask.to(torch.float64))
    centres = low.view(-1, 1).double() + (torch.arange(HISTOGRAM_BINS, device=disparity.device) + 0.5) \
        * span.view(-1, 1).double() / HISTOGRAM_BINS
    w0 = histogram.cumsum(1)
    s0 = (histogram * centres).cumsum(1)
    w1, s1 = w0[:, -1:] - w0, s0[:, -1:] - s0
    between = torch.where((w0 > 0) & (w1 > 0), (s0 * w1 - s1 * w0) ** 2 / (w0 * w1).clamp_min(1), 0.0)
    k = between.argmax(1, keepdim=True)
    threshold = (low.view(-1, 1).double() + (k + 1) * span.view(-1, 1).double() / HISTOGRAM_BINS).squeeze(1)
    threshold = threshold.to(disparity.dtype)
    near = mask & (values > threshold.view(-1, 1))
    far = mask & ~near
    n_near, n_far = near.sum(1), far.sum(1)
    mean_near = torch.where(near, values, 0.0).sum(1) / n_near.clamp_min(1)
    mean_far = torch.where(far, values, 0.0).sum(1) / n_far.clamp_min(1)
    split = ((n_near >= MIN_CLASS_SHARE * count) & (n_far >= MIN_CLASS_SHARE * count) & (n_near > 0)
             & (mean_near >= MIN_DISPARITY_RATIO * mean_far.clamp_min(1e-3)))
    if not bool(split.any()):
        return threshold, split
    median_near, _ = masked_lower_median(values, near)
    split = split & (median_near <= limit)
    if not bool(split.any()):
        return threshold, split
    _, _, properties = connected_components_with_stats(near.view_as(member))
    largest = properties.area_px.amax(1) if properties.area_px.shape[1] else torch.zeros_like(n_near)
    split = split & (largest >= MIN_COHERENT_SHARE * n_near) & (largest >= least)
    return threshold, split
