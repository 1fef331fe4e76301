"""The side said with an obstacle's distance is the side of the part that distance was measured on.

``guide`` warns of the nearest obstacle's nearest visible surface (its low depth percentile,
``NearestObstacle.surface_m``) and says its side (:class:`~svs_torch.depth.ObstacleSide`: the third of the width its
region's centroid falls in, or the centre for a region across the middle column). Where the nearness segmenter joins
two touching obstacles at different depths into one kept region, that centroid is the pair's: a box at 0.88 m in the
right third, joined to a box at 1.6 m over the middle, was said "Obstacle ahead" at 0.88 m, the right-hand box's
distance (a known fault of guide's, rendered in ``tests/pipeline/test_near_side.py``). A walker needs the side
of the part that distance belongs to.

So where an object's measured dense depths lie on two surfaces apart, its side is that of its near part, by the same
rule: at least :data:`MIN_FAR_SHARE` of its measured pixels at least :data:`FAR_PART_RATIO` times as far as its low
percentile, at most :data:`MAX_BETWEEN_SHARE` between that and :data:`NEAR_PART_RATIO` times it, and the near part
the pixels within that. An object ranged over its near surface (:mod:`svs_torch.pipeline.near_surface`) takes the
side of the pixels it was measured over. Elsewhere the side stays its region's: one surface (a box facing the
cameras: every measured pixel in the near part), or depths that change gradually across a turned front (a box turned
40° about its vertical axis: 31 % of its measured pixels between, 30 % far; the joined boxes above: 43 % near, none
between, 57 % far; rendered 320×240 scenes of :func:`~svs_torch.data.synthetic.render_obstacle_scenes`). Sides are
taken in the dense map's pixels (a rectified pair's, by ``H_left``). Not differentiable (a side is a decision).
"""

from __future__ import annotations

import dataclasses

import torch

from ..core.mask_reductions import count_along
from ..depth.dense_config import DenseDisparity
from ..depth.depth_types import DepthResult
from ..depth.sparse import column_sides
from .near_surface import _in_map_pixels

__all__ = []

#: The near part: measured pixels at most this many times as far as the object's low depth percentile.
NEAR_PART_RATIO = 1.1
#: The far part: measured pixels at least this many times as far as it (a surface at 0.88 m and one past 1.1 m).
FAR_PART_RATIO = 1.25
#: The far part holds at least this share of the object's measured pixels ...
MIN_FAR_SHARE = 0.25
#: ... and at most this share lies between the two (a turned front's depths run on between them).
MAX_BETWEEN_SHARE = 0.1
#: The near part reaches across the middle column where it does without this share of its pixels at either end: a
#: few stray pixels of the far box measured near (3 of the joined boxes' 9449, 80 columns left of the rest) do not.
STRAY_SHARE = 0.02


def near_part_sides(depth: DepthResult, dense: DenseDisparity, object_labels: torch.Tensor, rectified: torch.Tensor,
                    H_left: torch.Tensor, image_hw: torch.Tensor, focal_px: torch.Tensor, baseline_m: torch.Tensor,
                    doffs_px: torch.Tensor, cut: torch.Tensor | None = None) -> DepthResult:
    """``depth`` with each object's side that of its near part where it lies on two surfaces apart, or that of the
    pixels it was measured over where it was ``cut`` ``(B, N)`` to its near surface (module docstring), and the
    nearest obstacle's side its object's. ``dense``: the final dense map (in rectified pixels where ``rectified``
    ``(B,)``, by ``H_left`` ``(B, 3, 3)``); ``object_labels``: the labels the objects were measured over, input
    pixels; ``image_hw`` ``(B, 2)`` and the rig's ``focal_px``, ``baseline_m``, ``doffs_px`` ``(B,)``."""
    objects = depth.objects
    b, n = objects.label.shape
    # A screen: an object whose high percentile is under FAR_PART_RATIO times its low one has no far part to speak
    # of, and keeps its side without its pixels read (a frame of single obstacles pays nothing). The others are
    # taken one slot an image, (K, H, W), not every slot of every pair: 10 of 16 slots were screened out on the
    # shared pairs (B = 8), and (B, N, H, W) masks took 1 ms a pair, 3 % of the pipeline.
    apart = objects.depth_high_m >= FAR_PART_RATIO * objects.depth_low_m
    cut = torch.zeros_like(objects.valid) if cut is None else cut
    chosen = (objects.valid & (apart | cut) & (objects.label > 0)).nonzero()
    if n == 0 or chosen.shape[0] == 0:
        return depth
    pair, slot = chosen.unbind(1)
    rows, row_of = pair.unique(return_inverse=True)  # the pairs read, and each chosen slot's among them
    # index_select, not [pair, 0]: advanced indexing copied whole images 5x slower (12.6 of 34 ms over 40 pairs).
    map_labels = _in_map_pixels(object_labels[rows], rectified[rows], H_left[rows])[:, 0].index_select(0, row_of)
    disparity = dense.disparity_px.detach()[:, 0].index_select(0, pair)  # (K, H, W)
    denominator = disparity + doffs_px.detach().to(disparity.dtype)[pair].view(-1, 1, 1)  # f·B / distance
    scale = (focal_px.detach() * baseline_m.detach()).to(disparity.dtype)[pair].view(-1, 1, 1)
    region = map_labels == objects.label[pair, slot].view(-1, 1, 1)
    members = region & (dense.valid[:, 0].index_select(0, pair) & (denominator > 0))
    # Compared as disparities (f·B over each slot's bounds in metres): no division over the map.
    low = objects.depth_low_m.detach().to(disparity.dtype)[pair, slot].clamp_min(1e-12).view(-1, 1, 1)
    near = members & (denominator >= scale / (low * NEAR_PART_RATIO))
    total, near_count = count_along(members, (1, 2)), count_along(near, (1, 2))
    far_count = count_along(members & (denominator <= scale / (low * FAR_PART_RATIO)), (1, 2))
    two = ((near_count > 0) & (far_count >= MIN_FAR_SHARE * total)
           & (total - near_count - far_count <= MAX_BETWEEN_SHARE * total))
    cut = cut[pair, slot]
    if not bool((two | cut).any()):
        return depth
    part = torch.where(two.view(-1, 1, 1), near, region & cut.view(-1, 1, 1))
    side = objects.side.clone()
    per_column = count_along(part, 1)  # (K, W)
    part_side = column_sides(per_column, image_hw[pair, 1], disparity.dtype, STRAY_SHARE)[2]
    side[pair, slot] = torch.where(two | cut, part_side, side[pair, slot])
    objects = dataclasses.replace(objects, side=side)
    nearest = depth.nearest
    if nearest is not None:
        at_slot = side.gather(1, nearest.slot.clamp_min(0).view(b, 1)).view(b)
        nearest = dataclasses.replace(nearest, side=torch.where(nearest.valid, at_slot, nearest.side))
    return dataclasses.replace(depth, objects=objects, nearest=nearest)
