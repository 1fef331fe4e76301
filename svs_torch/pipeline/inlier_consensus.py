"""Objects whose dense depth their own inliers contradict: a repeated pattern aliased by the dense map.

A fence, a railing, a grate or a chessboard repeats itself along the rows, so the block matcher's cost has a
minimum at the true disparity and one a period away on either side. On a perfectly rectified, noise-free pair the
true one wins; on a loose rig's pair (the right view turned 0.5°) or a camera frame (JPEG, sensor noise) the minima
come out nearly equal, the uniqueness rule rejects most windows, and what survives, or the coarse retry at half the
width, where the period halves, can settle one period off. A grate at 1.5 m (12 px period) behind a right camera
turned ±0.5° was ranged "OK" at 3.75 m while all 35 of its RANSAC inliers read the true disparity within ±0.2 px
(``tests/pipeline/test_inlier_consensus.py``): SURF's descriptor spans more than one period and the pattern's ends,
and the inliers satisfy the pair's epipolar geometry.

So where an object holds many inliers that agree with each other to within one working pixel, its dense median
lies outside their quartiles by more than a few working pixels, and the map contradicts them where they lie, it is
ranged by its inliers (the paper's own measurement, Sec. 3.4) instead of by the dense map. On the rendered panels
of ``experiments/repeated_patterns.py`` this ranges 2 more of 36 as camera frames; it changes no row of the tuning
sets nor of the held-out split (``experiments/repeated_patterns.md``). It cannot reach a pattern with few inliers
(the ratio test rejects a match whose second best, a period away, is as good).
"""

from __future__ import annotations

import dataclasses

import torch

from ..depth.dense_config import DenseDisparity
from ..depth.dense_objects import inlier_agreement, range_from_objects
from ..depth.depth_types import DepthResult, ObjectDepths
from ..depth.quantiles import masked_quantile
from ..depth.sparse import nearest_obstacle

__all__ = ["MIN_CONSENSUS_INLIERS", "keep_inlier_ranged", "range_contradicted_by_inliers"]

#: Fewest inliers on an object for their consensus to overrule its dense map.
MIN_CONSENSUS_INLIERS = 10
#: Widest spread (inter-quartile range) of those inliers' disparities, working pixels, that counts as a consensus.
MAX_CONSENSUS_SPREAD = 1.0
#: Least distance of the dense median disparity from the inliers' quartiles, working pixels.
MIN_CONTRADICTION = 3.0


def range_contradicted_by_inliers(depth: DepthResult, dense: DenseDisparity, points_left: torch.Tensor,
                                  inliers: torch.Tensor, H_left: torch.Tensor, focal_px: torch.Tensor,
                                  baseline_m: torch.Tensor, doffs_px: torch.Tensor, working_px: float) -> DepthResult:
    """``depth`` (the dense rule's) with each valid object that its own inliers contradict ranged by them, and the
    pair's range and nearest obstacle taken again: the object's median and low / high depths become the median and
    10th / 90th percentile depths of its inliers within one working pixel of their median disparity.

    Contradicted: at least :data:`MIN_CONSENSUS_INLIERS` of ``inliers`` ``(B, K)`` bool lie on it
    (``depth.objects.point_slot``); their disparities (``depth.disparities``, the frame the dense map was measured
    in) have an inter-quartile range of at most :data:`MAX_CONSENSUS_SPREAD` working pixels (``working_px`` input
    pixels each); the dense median's disparity (``focal_px · baseline_m / depth − doffs_px``, each ``(B,)``) lies
    more than :data:`MIN_CONTRADICTION` working pixels outside their quartiles; and the dense map ``dense``
    confirms fewer than half of those of them it measured (:func:`~svs_torch.depth.dense_objects.inlier_agreement`,
    ``points_left`` ``(B, K, 2)`` mapped by ``H_left`` ``(B, 3, 3)`` into the map's frame).

    Gradients flow to the depths of the objects ranged either way (the inliers' through ``depth.points``); the
    decision has none."""
    objects, disparities, points = depth.objects, depth.disparities, depth.points
    n = objects.valid.shape[1]
    slot = objects.point_slot
    usable = inliers & disparities.valid & points.valid & (slot >= 0)
    member = (slot.unsqueeze(1) == torch.arange(n, device=slot.device).view(1, -1, 1)) & usable.unsqueeze(1)
    count = member.sum(-1)  # (B, N)
    contradicted = objects.valid & (count >= MIN_CONSENSUS_INLIERS)
    depth = dataclasses.replace(depth, objects=dataclasses.replace(objects, ranged_by_inliers=torch.zeros_like(
        contradicted)))  # every batch of the rule carries the flag, so retried pairs merge with the others
    if not bool(contradicted.any()):
        return depth
    values = disparities.disparity_px.unsqueeze(1).expand_as(member)
    low, median, high = masked_quantile(values, member, (0.25, 0.5, 0.75)).values.unbind(-1)
    scale = (focal_px * baseline_m).view(-1, 1).to(values.dtype)
    safe = torch.where(objects.valid, objects.depth_median_m, torch.ones_like(objects.depth_median_m))
    dense_d = scale / safe.to(values.dtype) - doffs_px.view(-1, 1).to(values.dtype)
    contradicted = (contradicted & (high - low <= MAX_CONSENSUS_SPREAD * working_px)
                    & (torch.maximum(low - dense_d, dense_d - high) > MIN_CONTRADICTION * working_px))
    if not bool(contradicted.any()):
        return depth
    # The inliers of the consensus: RANSAC keeps a repeated pattern's aliased matches too (on a surface facing the
    # rig they lie on the same rows), a period off on either side.
    consensus = member & ((values - median.unsqueeze(-1)).abs() <= MAX_CONSENSUS_SPREAD * working_px)
    # And the map contradicts them where they lie: it confirms fewer than half of those it measured. Where it
    # confirms them there, it is right and the object spans more than their surface (Wood2 at 320 px, see
    # experiments/repeated_patterns.md).
    agreeing, measured = inlier_agreement(dense, points_left, disparities, inliers, H_left, working_px)
    count_measured = (consensus & measured.unsqueeze(1)).sum(-1)
    count_agreeing = (consensus & agreeing.unsqueeze(1)).sum(-1)
    contradicted = contradicted & (2 * count_agreeing < count_measured)
    if not bool(contradicted.any()):
        return depth
    z = masked_quantile(points.depth_m.unsqueeze(1).expand_as(member), consensus, (0.5, 0.1, 0.9)).values
    z = z.to(objects.depth_median_m.dtype)

    def chosen(by_map: torch.Tensor, by_inliers: torch.Tensor) -> torch.Tensor:
        return torch.where(contradicted, by_inliers, by_map)

    objects = dataclasses.replace(objects, depth_median_m=chosen(objects.depth_median_m, z[..., 0]),
                                  depth_low_m=chosen(objects.depth_low_m, z[..., 1]),
                                  depth_high_m=chosen(objects.depth_high_m, z[..., 2]), ranged_by_inliers=contradicted)
    return DepthResult(disparities, points, range_from_objects(objects, focal_px, baseline_m, doffs_px), objects,
                       nearest_obstacle(objects))


def keep_inlier_ranged(hard: ObjectDepths, soft: ObjectDepths) -> ObjectDepths:
    """The differentiable pass's ``soft`` objects ``(B, N)`` with those the hard pipeline ranged by their inliers
    (``hard.ranged_by_inliers``) taking the hard depths and validity, straight-through: the soft pass recomputes
    depths from the dense map, which those objects' inliers overruled. No gradient reaches their depths."""
    if hard.ranged_by_inliers is None or not bool(hard.ranged_by_inliers.any()):
        return soft
    by_inliers = hard.ranged_by_inliers

    def taken(name: str) -> torch.Tensor:
        value = getattr(soft, name)
        return torch.where(by_inliers, getattr(hard, name).detach().to(value.dtype), value)

    return dataclasses.replace(soft, depth_median_m=taken("depth_median_m"), depth_low_m=taken("depth_low_m"),
                               depth_high_m=taken("depth_high_m"), valid=torch.where(by_inliers, hard.valid,
                                                                                     soft.valid))
