"""Matched point pairs as the epipolar solvers take them: their checks and Hartley's normalisation.
"""

from __future__ import annotations

import math

import torch

from ..core.checks import InputError, check_dtype, check_shape
from ..core.numerics import safe_sqrt

__all__ = ["normalize_points_hartley"]


def _check_pair(points_left: torch.Tensor, points_right: torch.Tensor, spec: list) -> None:
    check_shape(points_left, "points_left", spec)
    check_dtype(points_left, "points_left", "float")
    check_shape(points_right, "points_right", spec)
    check_dtype(points_right, "points_right", "float")
    if points_left.shape != points_right.shape:
        raise InputError(f"points_right: expected the shape of points_left {tuple(points_left.shape)}, "
                         f"got {tuple(points_right.shape)}")


def _point_spec(points: torch.Tensor, count: str | int) -> list:
    """A shape spec ``(..., count, 2)`` with one letter per leading dimension of ``points``."""
    leading = [f"N{i}" for i in range(max(points.dim() - 2, 0))]
    return [*leading, count, 2]


def normalize_points_hartley(points: torch.Tensor,
                             weights: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Hartley normalisation: centroid to the origin, mean distance from it √2 (H&Z Sec. 4.4.4).

    Args:
        points: ``(..., K, 2)`` pixels.
        weights: optional ``(..., K)`` non-negative weights; 0 excludes a point (padding).

    Returns:
        normalised points ``(..., K, 2)`` (dimensionless) and the transforms ``T`` ``(..., 3, 3)`` with
        ``x_normalised = T x``. Where every weight is 0 or all points coincide, the scale is 1 (T only
        translates): such a set is degenerate for every solver and is flagged there.

    Differentiable w.r.t. ``points`` and ``weights`` (where the spread is non-zero).

    Raises:
        InputError: ``points`` not ``(..., K, 2)`` float32 / float64 (integer pixels gave an integer T, its scale
            truncated to 0), ``weights`` not ``(..., K)`` float or bool.
    """
    check_shape(points, "points", _point_spec(points, "K"))
    check_dtype(points, "points", "float")
    if weights is not None:
        check_shape(weights, "weights", list(points.shape[:-1]))
        check_dtype(weights, "weights", "float|bool")
    if weights is None:
        weights = torch.ones_like(points[..., 0])
    weights = weights.to(points.dtype)
    total = weights.sum(-1, keepdim=True)  # (..., 1)
    has_weight = total > 0
    total_safe = torch.where(has_weight, total, torch.ones_like(total))
    centroid = (points * weights.unsqueeze(-1)).sum(-2) / total_safe  # (..., 2)
    offsets = points - centroid.unsqueeze(-2)
    distance_sq = offsets.square().sum(-1)
    distance = safe_sqrt(distance_sq)  # sqrt has an infinite derivative at 0
    mean_distance = (distance * weights).sum(-1, keepdim=True) / total_safe  # (..., 1)
    spread = mean_distance > 0
    scale = torch.where(spread, math.sqrt(2.0) / torch.where(spread, mean_distance, 1.0), 1.0)  # (..., 1)
    normalised = offsets * scale.unsqueeze(-1)
    transform = torch.zeros(*points.shape[:-2], 3, 3, dtype=points.dtype, device=points.device)
    transform[..., 0, 0] = scale[..., 0]
    transform[..., 1, 1] = scale[..., 0]
    transform[..., :2, 2] = -centroid * scale
    transform[..., 2, 2] = 1.0
    return normalised, transform
