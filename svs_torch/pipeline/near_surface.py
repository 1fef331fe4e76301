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
A pair the pipeline rectified (a loose rig without a calibration) is split in rectified pixels, where its map is:
its labels warped there as the dense stage warps them, the near group's pixels measured there, and the input pixels
whose rectified position lies in the near group kept in the labels it reports (``PipelineResult.object_labels``).

Chosen on the tuning sets only, over three draws of the camera noise (``experiments/real_rig.py --noise-seed``;
``experiments/real_rig.md``, "Two surfaces in one kept region"). Not differentiable (a mask); the differentiable
pass measures over the same pixels (``PipelineResult.object_labels``).
"""

from __future__ import annotations

import dataclasses

import torch

from ..core.pair_trees import put_pairs, take_pairs
from ..depth.block_matching import fill_invalid_rows
from ..depth.dense_config import DenseDisparity
from ..depth.dense_objects import dense_object_depths, range_from_objects
from ..depth.depth_types import DepthResult
from ..depth.quantiles import masked_lower_median
from ..depth.sparse import nearest_obstacle
from ..segmentation.components import connected_components_with_stats
from ..segmentation.threshold import otsu_threshold_level
from .config import PipelineConfig
from .ranging import surface_pixels_of
from .stages import warp_labels, warped_where

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
#: The screen over a quarter of the pixels asks this share of the groups' least share and of the ratio's excess
#: over 1 (0.2 and 1.8 for 0.25 and 2): an object it lets through is tested again over every pixel.
SCREEN_SLACK = 0.8


def measure_near_surfaces(depth: DepthResult, dense: DenseDisparity, object_labels: torch.Tensor,
                          rectified: torch.Tensor, H_left: torch.Tensor, inliers: torch.Tensor, focal_px: torch.Tensor,
                          baseline_m: torch.Tensor, doffs_px: torch.Tensor, config: PipelineConfig
                          ) -> tuple[DepthResult, torch.Tensor, torch.Tensor]:
    """``depth`` with each two-surface object (module docstring) ranged over its near surface, the object labels it
    was then measured over ``(B, 1, H, W)`` (input pixels) and which objects were cut ``(B, N)`` bool. ``dense``: the
    final dense map, in input pixels, or in rectified pixels where ``rectified`` ``(B,)`` (by ``H_left``
    ``(B, 3, 3)``); ``object_labels``: the labels the objects were measured over, input pixels; ``inliers``
    ``(B, K)`` bool: RANSAC's inliers among ``depth.disparities``; ``config``: the pipeline's (its depth rule's
    settings). An object keeps its validity: a near surface that cannot be ranged leaves the object as it was."""
    objects = depth.objects
    slots = torch.where(objects.valid, objects.label, torch.zeros_like(objects.label))
    cut = torch.zeros_like(objects.valid)
    if slots.shape[1] == 0 or not bool((slots > 0).any()):
        return depth, object_labels, cut
    map_labels = _in_map_pixels(object_labels, rectified, H_left)
    disparity, valid = dense.disparity_px.detach(), dense.valid
    sparse = depth.disparities
    known = inliers & sparse.valid & sparse.disparity_px.isfinite()
    # A zero column (no keypoints asked for: SurfConfig.max_keypoints = 0) keeps amax defined.
    known_px = torch.where(known, sparse.disparity_px.detach(), torch.zeros_like(sparse.disparity_px))
    top = torch.cat([known_px, known_px.new_zeros(known_px.shape[0], 1)], dim=1).amax(1)
    limit = MAX_INLIER_RATIO * top + INLIER_MARGIN_PX  # (B,)
    least = max(1.0, MIN_COHERENT_AREA_FRACTION * object_labels.shape[-2] * object_labels.shape[-1])
    position = _slot_positions(map_labels, slots)  # (B, 1, H, W): each pixel's object, N for none
    threshold, cut = _split_objects(disparity, valid, position, slots.shape[1], limit, least)
    if not bool(cut.any()):
        return depth, object_labels, cut
    # Only the pairs with an object to cut are measured again: a bulk batch's other pairs do not pay for them.
    b, n = slots.shape
    pairs = cut.any(1).nonzero().flatten()
    sub = (lambda tree: take_pairs(tree, pairs, b))
    # The pixels its depth is measured over: the row-filled map where the depth rule fills it.
    filled, reachable = ((fill_invalid_rows if config.dense.fill_invalid else _unfilled)(sub(disparity)[:, 0],
                                                                                          sub(valid)[:, 0]))
    cut_labels = (lambda which: _cut_labels(sub(position), sub(map_labels), which, sub(threshold), filled,
                                            reachable))
    near = dense_object_depths(sub(dense), cut_labels(sub(cut)), sub(objects), sub(focal_px), sub(baseline_m),
                               sub(doffs_px), config.depth.object_percentiles, config.depth.min_object_pixels,
                               config.dense.fill_invalid, 0.0, config.depth.min_object_pixels_in_view,
                               config.dense.in_view_own_min_valid_share, surface_pixels_of(sub(dense), config))
    # An object whose near surface cannot be ranged keeps its whole region and its depth.
    part = sub(cut) & near.valid
    if not bool(part.any()):
        return depth, object_labels, torch.zeros_like(cut)
    labels = object_labels.index_copy(0, pairs, _in_input_pixels(cut_labels(part), sub(map_labels),
                                                                 sub(object_labels), sub(rectified), sub(H_left)))
    cut, near = torch.zeros_like(cut).index_copy(0, pairs, part), put_pairs(objects, pairs, near, b)
    # Its area is now the pixels it is measured over (estimate --json's measured_area_px), counted in input pixels
    # (the positions above are in the map's, which differ only where a pair was rectified).
    if bool(rectified.any()):
        position = _slot_positions(object_labels, slots)
    inside = (position < n).flatten(1) & (labels > 0).flatten(1)
    key = torch.arange(b, device=slots.device).view(-1, 1) * n + position.clamp(max=n - 1).flatten(1)
    area = torch.bincount(key[inside], minlength=b * n).view(b, n)
    merged = dataclasses.replace(objects, area_px=torch.where(cut, area, objects.area_px), **{
        name: torch.where(cut, getattr(near, name), getattr(objects, name))
        for name in ("depth_median_m", "depth_low_m", "depth_high_m", "num_valid_px", "num_in_view_px")})
    depth_range = range_from_objects(merged, focal_px, baseline_m, doffs_px)
    return DepthResult(depth.disparities, depth.points, depth_range, merged, nearest_obstacle(merged)), labels, cut


def _unfilled(disparity: torch.Tensor, valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The map as it is, where the depth rule does not fill it (``DenseConfig.fill_invalid`` False)."""
    return disparity, valid


def _cut_labels(position: torch.Tensor, object_labels: torch.Tensor, cut: torch.Tensor, threshold: torch.Tensor,
                filled: torch.Tensor, reachable: torch.Tensor) -> torch.Tensor:
    """``object_labels`` ``(b, 1, H, W)`` without the pixels of each ``cut`` ``(b, N)`` object whose (filled)
    disparity is not above its ``threshold`` ``(b, N)``: the object cut to its near surface."""
    n = cut.shape[1]
    slot = position.clamp(max=n - 1).flatten(1)
    near = reachable.unsqueeze(1) & (filled.unsqueeze(1) > threshold.gather(1, slot).view_as(position))
    far = (position < n) & cut.gather(1, slot).view_as(position) & ~near
    return torch.where(far, torch.zeros_like(object_labels), object_labels)


def _split_objects(disparity: torch.Tensor, valid: torch.Tensor, position: torch.Tensor, n: int, limit: torch.Tensor,
                   least: float) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`_two_groups` over every pixel for the objects a screen over every other row and column, with looser
    bounds, lets through: most objects of most frames show one surface, and the whole test over every object took
    2 ms a camera frame (the thresholds ``(B, n)``, 0 where not tested, and the objects split)."""
    _, candidate = _two_groups(*(t[..., ::2, ::2] for t in (disparity, valid, position)), n, limit, least / 4,
                               screen=True)
    threshold = torch.zeros(candidate.shape, dtype=disparity.dtype, device=disparity.device)
    if not bool(candidate.any()):
        return threshold, candidate
    pairs = candidate.any(1).nonzero().flatten()
    sub = (lambda t: t.index_select(0, pairs))
    position = sub(position)
    screened = torch.where(sub(candidate).gather(1, position.clamp(max=n - 1).flatten(1)).view_as(position),
                           position, n)
    part_threshold, part = _two_groups(sub(disparity), sub(valid), screened, n, sub(limit), least)
    return threshold.index_copy(0, pairs, part_threshold), torch.zeros_like(candidate).index_copy(0, pairs, part)


def _in_map_pixels(object_labels: torch.Tensor, rectified: torch.Tensor, H_left: torch.Tensor) -> torch.Tensor:
    """``object_labels`` ``(B, 1, H, W)`` in the dense map's pixels: warped by ``H_left`` (nearest) where
    ``rectified``, exactly as :func:`svs_torch.pipeline.ranging._dense_depth` warps the labels it measures over."""
    return warped_where(object_labels, H_left, rectified, warp_labels)


def _in_input_pixels(cut_map_labels: torch.Tensor, map_labels: torch.Tensor, object_labels: torch.Tensor,
                     rectified: torch.Tensor, H_left: torch.Tensor) -> torch.Tensor:
    """The input-pixel labels of objects cut in the map's pixels (``cut_map_labels`` ``(b, 1, H, W)``, from
    ``map_labels``, :func:`_in_map_pixels` of ``object_labels``): as they are where not ``rectified``; else
    ``object_labels`` without each pixel whose rectified position (``H_left``, nearest) held its label before the
    cut and holds none after it."""
    if not bool(rectified.any()):
        return cut_map_labels
    # Both label images back in one warp: the label before the cut, and in the lowest bit whether it stayed.
    coded = map_labels * 2 + (cut_map_labels == map_labels).long()
    # inv_ex: a rectified pair's homography is invertible; a hostile one must not stop the batch here.
    back = warped_where(coded, torch.linalg.inv_ex(H_left.to(torch.float64)).inverse, rectified, warp_labels)
    lost = (back // 2 == object_labels) & (back % 2 == 0) & (object_labels > 0)
    kept = torch.where(lost, torch.zeros_like(object_labels), object_labels)
    return torch.where(rectified.view(-1, 1, 1, 1), kept, cut_map_labels)


def _slot_positions(object_labels: torch.Tensor, slots: torch.Tensor) -> torch.Tensor:
    """``(B, 1, H, W)`` int64: the slot n of ``slots`` ``(B, N)`` whose object each pixel of ``object_labels``
    belongs to, N where none (a slot ≤ 0 holds none)."""
    b, n = slots.shape
    size = int(object_labels.max()) + 2 if object_labels.numel() else 2
    table = torch.full((b, size), n, dtype=torch.long, device=slots.device)
    # A slot holding no object writes to the last column, which no label reads.
    columns = torch.where(slots > 0, slots, torch.full_like(slots, size - 1)).long()
    table.scatter_(1, columns, torch.arange(n, device=slots.device).expand(b, n).contiguous())
    table[:, -1] = n
    return table.gather(1, object_labels.flatten(1).clamp(0, size - 2)).view_as(object_labels)


def _two_groups(disparity: torch.Tensor, valid: torch.Tensor, position: torch.Tensor, n: int, limit: torch.Tensor,
                least: float, screen: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Otsu's split of each object's measured disparities (``disparity``, ``valid`` ``(B, 1, H, W)``; the object of
    each pixel ``position``, one of ``n`` or ``n`` for none) and whether it makes two surfaces (module docstring):
    the thresholds and ``(B, n)`` bool. One pass over the objects' measured pixels for every object; only the
    objects that pass the groups' shares and ratio are looked at again, over the whole view (rare). ``screen``: the
    groups' shares and ratio only, each bound a fifth looser (:data:`SCREEN_SLACK`)."""
    b = disparity.shape[0]
    keys = b * n
    values, where_ = disparity.flatten(1), position.flatten(1)
    pair, pixel = (valid.flatten(1) & (where_ < n)).nonzero(as_tuple=True)
    key = pair * n + where_[pair, pixel]
    v = values[pair, pixel]
    count = torch.bincount(key, minlength=keys)
    threshold = _otsu_by_key(v, key, keys)
    near = v > threshold[key]
    n_near = torch.bincount(key, weights=near.double(), minlength=keys)
    n_far = count - n_near
    sum_near = torch.bincount(key, weights=torch.where(near, v, 0.0).double(), minlength=keys)
    mean_near = sum_near / n_near.clamp_min(1)
    mean_far = (torch.bincount(key, weights=v.double(), minlength=keys) - sum_near) / n_far.clamp_min(1)
    slack = SCREEN_SLACK if screen else 1.0
    share, ratio = MIN_CLASS_SHARE * slack, 1 + (MIN_DISPARITY_RATIO - 1) * slack
    split = ((n_near >= share * count) & (n_far >= share * count) & (n_near > 0)
             & (mean_near >= ratio * mean_far.clamp_min(1e-3))).view(b, n)
    threshold = threshold.view(b, n)
    if screen:
        return threshold, split
    for slot in range(n):  # the candidates only: the near group's median and its largest piece
        if not bool(split[:, slot].any()):
            continue
        group = (position == slot) & valid & (disparity > threshold[:, slot].view(-1, 1, 1, 1))
        median_near, _ = masked_lower_median(values, group.flatten(1))
        _, _, properties = connected_components_with_stats(group)
        largest = properties.area_px.amax(1) if properties.area_px.shape[1] else torch.zeros_like(median_near)
        n_group = group.flatten(1).sum(1)
        split[:, slot] &= ((median_near <= limit) & (largest >= MIN_COHERENT_SHARE * n_group) & (largest >= least))
    return threshold, split


def _otsu_by_key(values: torch.Tensor, key: torch.Tensor, keys: int) -> torch.Tensor:
    """Otsu's threshold ``(keys,)`` of the ``values`` under each ``key`` (1-D, the same length): the upper edge of
    the bin :func:`~svs_torch.segmentation.threshold.otsu_threshold_level` picks in a histogram of
    :data:`HISTOGRAM_BINS` bins between the key's least and greatest value."""
    low = values.new_full((keys,), torch.inf).scatter_reduce(0, key, values, "amin")
    high = values.new_full((keys,), -torch.inf).scatter_reduce(0, key, values, "amax")
    span = (high - low).clamp_min(1e-6)
    bins = ((values - low[key]) / span[key] * HISTOGRAM_BINS).floor().clamp(0, HISTOGRAM_BINS - 1).long()
    histogram = torch.bincount(key * HISTOGRAM_BINS + bins, minlength=keys * HISTOGRAM_BINS).view(keys, -1)
    level = otsu_threshold_level(histogram)
    return (low.double() + (level + 1) * span.double() / HISTOGRAM_BINS).to(values.dtype)
