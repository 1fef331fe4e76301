"""Objects the dense stage could not have measured: their RANSAC inliers lie nearer than the disparities it searched.

The dense search range comes from a coarse pass (``DenseConfig.range_source``) bounded by
``fallback_max_disparity_fraction`` of the width: an obstacle nearer than that (0.37 m by the SVS model at 320 × 240)
has no true match inside it, and the dense map fills its region with wrong ones. A textured box 110 px of disparity
away (0.27 m) pasted before Teddy's view shifted 20 px was ranged "OK" at 1.45 m, both its kept regions measured
over a range searched up to 95 px while all 23 of their inliers read 110 px (an audit). Such an object gets no depth.
"""

from __future__ import annotations

import dataclasses

import torch

from ..depth.dense_config import DenseDisparity
from ..depth.depth_types import Disparities, ObjectDepths

__all__ = ["MIN_BEYOND_INLIERS", "inliers_beyond_search", "unrange_objects_beyond_search"]

#: Fewest inliers beyond the range searched, and at least half of an object's, that leave it without a depth.
MIN_BEYOND_INLIERS = 3


def inliers_beyond_search(disparities: Disparities, inliers: torch.Tensor, dense: DenseDisparity) -> torch.Tensor:
    """``(B, K)`` bool: the ``inliers`` with a valid disparity (``disparities``, the frame the dense map was measured
    in) past the range ``dense`` searched, ``[min, min + count)``; what this rule and ``estimate``'s report of a
    too-near obstacle (``svs_torch.cli.too_near``) both count. Not differentiable (a bool mask)."""
    top = (dense.min_disparity_px + dense.pair_num_disparities).to(disparities.disparity_px.dtype)
    return inliers & disparities.valid & (disparities.disparity_px > top[:, None])


def unrange_objects_beyond_search(objects: ObjectDepths, point_slot: torch.Tensor, disparities: Disparities,
                                  inliers: torch.Tensor, dense: DenseDisparity) -> ObjectDepths:
    """``objects`` ``(B, N)`` with every object that holds at least :data:`MIN_BEYOND_INLIERS` inliers, and at least
    half of its inliers, whose disparity (``disparities``, the frame the dense map was measured in) exceeds the
    range ``dense`` searched made invalid, its depths 0. ``point_slot`` ``(B, K)``: each correspondence's object
    slot (−1 none); ``inliers`` ``(B, K)`` bool. Gradients pass through to the depths of the objects kept; the
    decision itself has none."""
    usable = inliers & disparities.valid & (point_slot >= 0)
    beyond = inliers_beyond_search(disparities, inliers, dense) & (point_slot >= 0)
    member = point_slot.unsqueeze(-1) == torch.arange(objects.valid.shape[1], device=point_slot.device)
    count = (member & usable.unsqueeze(-1)).sum(1)
    far = (member & beyond.unsqueeze(-1)).sum(1)
    unreachable = objects.valid & (far >= MIN_BEYOND_INLIERS) & (2 * far >= count)
    if not bool(unreachable.any()):
        return objects
    valid = objects.valid & ~unreachable

    def zeroed(value: torch.Tensor) -> torch.Tensor:
        return torch.where(valid, value, torch.zeros_like(value))

    return dataclasses.replace(objects, valid=valid, depth_median_m=zeroed(objects.depth_median_m),
                               depth_low_m=zeroed(objects.depth_low_m), depth_high_m=zeroed(objects.depth_high_m))
