"""Distances of point pairs to a fundamental matrix's epipolar geometry: Sampson's first-order distance and
the symmetric distance to the epipolar lines, and the monomials RANSAC scores with.
"""

from __future__ import annotations

import math

import torch

from ..core.checks import check_dtype, check_shape
from ..core.numerics import safe_sqrt
from .point_pairs import _check_pair, _point_spec

__all__ = ["sampson_distance", "symmetric_epipolar_distance"]


def _epipolar_terms(points_left: torch.Tensor, points_right: torch.Tensor,
                    fundamental: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``x'ᵀFx`` and the squared gradient norms of the two epipolar lines, each ``(..., K)``."""
    ones = torch.ones_like(points_left[..., :1])
    left_h = torch.cat([points_left, ones], -1)  # (..., K, 3)
    right_h = torch.cat([points_right, ones], -1)
    line_right = left_h @ fundamental.transpose(-1, -2)  # F x, the epipolar line in the right image
    line_left = right_h @ fundamental  # Fᵀ x', the epipolar line in the left image
    algebraic = (right_h * line_right).sum(-1)
    return algebraic, line_right[..., :2].square().sum(-1), line_left[..., :2].square().sum(-1)


def _sampson_monomials(points_left: torch.Tensor, points_right: torch.Tensor) -> torch.Tensor:
    """Quadratic monomials ``(..., K, 12)`` of the Sampson denominator (see :func:`_sampson_coefficients`).

    The last entry is 0 here; callers set it to 1 on padding rows, whose denominator is then exactly 1.
    """
    x, y = points_left.unbind(-1)
    xr, yr = points_right.unbind(-1)
    return torch.stack([x * x, x * y, y * y, x, y, xr * xr, xr * yr, yr * yr, xr, yr, torch.ones_like(x),
                        torch.zeros_like(x)], -1)


def _sampson_coefficients(fundamental: torch.Tensor, guard: float = 0.0) -> torch.Tensor:
    """Coefficients ``(..., 12)``: ``(Fx)₁² + (Fx)₂² + (Fᵀx')₁² + (Fᵀx')₂² + guard = g · m(x, x')``.

    With :func:`_design_matrix` rows a (``x'ᵀFx = a · f``), the squared Sampson distance of many models and
    points is two matrix products, ``(a·f)² / (m·g)``, with no per-point 3×3 products.
    """
    f00, f01, f02, f10, f11, f12, f20, f21, _ = fundamental.flatten(-2).movedim(-1, 0)
    return torch.stack([
        f00 * f00 + f10 * f10, 2 * (f00 * f01 + f10 * f11), f01 * f01 + f11 * f11,
        2 * (f00 * f02 + f10 * f12), 2 * (f01 * f02 + f11 * f12),
        f00 * f00 + f01 * f01, 2 * (f00 * f10 + f01 * f11), f10 * f10 + f11 * f11,
        2 * (f00 * f20 + f01 * f21), 2 * (f10 * f20 + f11 * f21),
        f02 * f02 + f12 * f12 + f20 * f20 + f21 * f21 + guard, torch.ones_like(f00)], -1)


def _safe_ratio(numerator: torch.Tensor, denominator: torch.Tensor) -> torch.Tensor:
    """``n / d`` for ``d ≥ 0``, with 0/0 → 0 and n/0 → inf, and finite gradients everywhere else."""
    positive = denominator > 0
    ratio = numerator / torch.where(positive, denominator, 1.0)
    at_zero = torch.where(numerator == 0, 0.0, math.inf).to(numerator.dtype)
    return torch.where(positive, ratio, at_zero)


def _check_distance_args(points_left: torch.Tensor, points_right: torch.Tensor, fundamental: torch.Tensor) -> None:
    _check_pair(points_left, points_right, _point_spec(points_left, "K"))
    check_shape(fundamental, "fundamental", [*(f"N{i}" for i in range(fundamental.dim() - 2)), 3, 3])
    check_dtype(fundamental, "fundamental", "float")


def sampson_distance(points_left: torch.Tensor, points_right: torch.Tensor, fundamental: torch.Tensor,
                     squared: bool = False) -> torch.Tensor:
    """First-order geometric (Sampson) error of correspondences under F (H&Z Eq. 11.9).

    ``d² = (x'ᵀFx)² / ((Fx)₁² + (Fx)₂² + (Fᵀx')₁² + (Fᵀx')₂²)``: the distance in pixels, in the joint 4-D
    image space, from the correspondence to the nearest one that satisfies F exactly.

    Args:
        points_left, points_right: ``(..., K, 2)`` pixels.
        fundamental: ``(..., 3, 3)``; leading dimensions broadcast with the points'.
        squared: return ``d²`` (px²; MATLAB's DistanceThreshold is on this) instead of d (px).

    Returns:
        ``(..., K)``; a point whose lines are undefined (at both epipoles) gets 0 if it satisfies
        ``x'ᵀFx = 0`` and inf otherwise. Differentiable w.r.t. the points and F elsewhere.
    """
    _check_distance_args(points_left, points_right, fundamental)
    algebraic, grad_right, grad_left = _epipolar_terms(points_left, points_right, fundamental)
    distance_sq = _safe_ratio(algebraic.square(), grad_right + grad_left)
    return distance_sq if squared else safe_sqrt(distance_sq)


def symmetric_epipolar_distance(points_left: torch.Tensor, points_right: torch.Tensor, fundamental: torch.Tensor,
                                squared: bool = False) -> torch.Tensor:
    """Symmetric epipolar distance (H&Z Eq. 11.10): ``d(x', Fx)² + d(x, Fᵀx')²``, distances to the lines.

    Args and returns as :func:`sampson_distance`: ``(..., K)``, px (or px² with ``squared``); differentiable
    w.r.t. the points and F away from the epipoles. Where both lines have similar gradient norms it is about
    4× the squared Sampson distance (``e²/a + e²/b`` vs ``e²/(a + b)``), i.e. twice the Sampson distance.
    """
    _check_distance_args(points_left, points_right, fundamental)
    algebraic, grad_right, grad_left = _epipolar_terms(points_left, points_right, fundamental)
    algebraic_sq = algebraic.square()
    distance_sq = _safe_ratio(algebraic_sq, grad_right) + _safe_ratio(algebraic_sq, grad_left)
    return distance_sq if squared else safe_sqrt(distance_sq)
