"""The objects the hard pipeline named (the nearest obstacle, R_min's and R_max's), carried into the differentiable
pass (:mod:`svs_torch.pipeline.soft`) with its soft depths: a discrete choice that pass never makes again."""

from __future__ import annotations

import dataclasses

import torch

from ..depth.dense_objects import range_from_objects
from ..depth.depth_types import NearestObstacle, ObjectDepths, RangeEstimate


def range_at_hard_slots(hard: ObjectDepths, objects: ObjectDepths, focal_px: torch.Tensor, baseline_m: torch.Tensor,
                        doffs_px: torch.Tensor) -> RangeEstimate:
    """R_min / R_max of the objects the hard pipeline ranged nearest and farthest (chosen on ``hard``'s medians and
    validity), their depths taken from the soft ``objects`` where that object's bands have members (else the hard
    ones, straight-through), as :func:`nearest_at_hard_slot` takes the nearest. Why: chosen again on the soft
    medians, R_min named the other object of a near tie and its gradient trained it (found by an audit: 1.500153
    against 1.500189 m, the slot the hard pipeline and ``nearest`` did not name)."""
    median = torch.where(objects.valid, objects.depth_median_m, hard.depth_median_m.to(objects.depth_median_m.dtype))
    taken = dataclasses.replace(objects, depth_median_m=median, valid=hard.valid,
                                num_valid_px=hard.num_valid_px, num_inliers=hard.num_inliers)
    return range_from_objects(taken, focal_px, baseline_m, doffs_px, order_by=hard.depth_median_m)


def nearest_at_hard_slot(hard: NearestObstacle, objects: ObjectDepths) -> NearestObstacle:
    """The hard pipeline's nearest obstacle (its slot, side and validity: a discrete decision, which this pass
    never makes again) with its depth and surface taken from the soft ``objects`` at that slot, where that slot's
    band has members (else the hard values, straight-through). Why: choosing the nearest again on the soft medians
    flipped the warned side when two objects were within a few hundredths of a millimetre (found by an audit:
    1 of 96 near ties), and the gradient then trained the other object."""
    slot = hard.slot.clamp(min=0).unsqueeze(1)
    soft_valid = objects.valid.gather(1, slot).squeeze(1) if objects.valid.shape[1] else torch.zeros_like(hard.valid)
    taken = hard.valid & soft_valid

    def at_slot(values: torch.Tensor, fallback: torch.Tensor | None) -> torch.Tensor | None:
        if fallback is None or values.shape[1] == 0:
            return fallback
        return torch.where(taken, values.gather(1, slot).squeeze(1), fallback.to(values.dtype))

    return NearestObstacle(hard.slot, at_slot(objects.depth_median_m, hard.depth_m), hard.side, hard.valid,
                           at_slot(objects.depth_low_m, hard.surface_m))
