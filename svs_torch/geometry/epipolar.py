"""Epipolar geometry: fundamental-matrix solvers and distances (paper Sec. 3.3 (3)).

Convention everywhere: ``x_rightᵀ F x_left = 0`` with x = (column, row, 1) in pixels, so ``F x_left`` is the
epipolar line of a left point in the right image. F is stored row-major as ``f = (F00, F01, …, F22)``; one
correspondence gives the row ``(x'x, x'y, x', y'x, y'y, y', x, y, 1)`` of the linear system ``A f = 0``
(Hartley & Zisserman, *Multiple View Geometry*, 2nd ed., Sec. 11.1).

Every function is batched over arbitrary leading dimensions ``(...)``. Solvers work in float64 internally and
return the input's dtype. Returned fundamental matrices have unit Frobenius norm and a fixed sign (their
largest-magnitude entry is positive; of entries tied within ``SIGN_TIE_TOLERANCE``, as a translation's skew-symmetric
F's are, the first in row-major order), so equal models compare equal.

Differentiable: :func:`fundamental_8point` (w.r.t. points and weights, through ``eigh`` and ``svd``; defined
where the two smallest eigenvalues of ``AᵀWA`` and the singular values of F differ), :func:`enforce_rank2`,
:func:`sampson_distance` and :func:`symmetric_epipolar_distance` (w.r.t. points and F, away from epipoles),
:func:`normalize_points_hartley`. :func:`fundamental_7point` returns values only: root selection is discrete.
"""

from __future__ import annotations

import torch

from ..core.checks import InputError, check_dtype, check_shape
from .epipolar_distance import sampson_distance, symmetric_epipolar_distance
from .minimal_solvers import (_denormalize, _design_matrix, _eight_point_from_design, _fix_sign_and_scale,
                              _seven_point_from_design, enforce_rank2, real_cubic_roots)
from .point_pairs import _check_pair, _point_spec, normalize_points_hartley

__all__ = [
    "enforce_rank2", "fundamental_7point", "fundamental_8point", "normalize_points_hartley", "real_cubic_roots",
    "sampson_distance", "symmetric_epipolar_distance"
]


def _eight_point_normalized(points_left: torch.Tensor, points_right: torch.Tensor,
                            weights: torch.Tensor) -> torch.Tensor:
    """:func:`_eight_point_from_design` for already normalised points ``(..., K, 2)``."""
    return _eight_point_from_design(_design_matrix(points_left, points_right), weights)


def fundamental_8point(points_left: torch.Tensor, points_right: torch.Tensor,
                       weights: torch.Tensor | None = None) -> torch.Tensor:
    """Normalised 8-point algorithm, weighted least squares (H&Z Alg. 11.1), batched.

    Args:
        points_left, points_right: ``(..., K, 2)`` pixels, K ≥ 8 (points with weight > 0).
        weights: optional ``(..., K)`` non-negative weights (0 = ignore, e.g. padding or outliers).

    Returns:
        ``(..., 3, 3)`` rank-2 F with ``x_rightᵀ F x_left ≈ 0``, unit Frobenius norm, sign fixed, dtype of the
        input. With fewer than 8 weighted points in general position the minimiser is not unique and the
        result is one arbitrary member of the solution family.

    Differentiable w.r.t. the points and ``weights`` (gradcheck in float64).
    """
    _check_pair(points_left, points_right, _point_spec(points_left, "K"))
    if weights is not None:
        check_shape(weights, "weights", list(points_left.shape[:-1]))
        check_dtype(weights, "weights", "float|bool")
    if points_left.shape[-2] < 8:
        raise InputError(f"points_left: expected at least 8 points, got {points_left.shape[-2]}")
    dtype = points_left.dtype
    work = torch.float64
    weights = torch.ones_like(points_left[..., 0]) if weights is None else weights
    weights = weights.to(work)
    if not bool((weights >= 0).all()):  # NaN fails it too
        raise InputError("weights: expected non-negative finite weights (NaN or a negative weight found)")
    # A NaN point failed to converge deep in an eigen-solver: the points that count must be finite, and a
    # padding point (weight 0) is read as 0 (0 · NaN is NaN; 0 · a finite row is the 0 it gave before).
    counts = (weights > 0).unsqueeze(-1)
    points_left, points_right = (torch.where(counts, points.to(work), 0.0) for points in (points_left, points_right))
    if not bool(torch.cat([points_left, points_right], -1).isfinite().all()):
        raise InputError("points_left, points_right: expected finite coordinates where the weight is > 0")
    left, t_left = normalize_points_hartley(points_left, weights)
    right, t_right = normalize_points_hartley(points_right, weights)
    fundamental = _denormalize(_eight_point_normalized(left, right, weights), t_left, t_right)
    return _fix_sign_and_scale(fundamental).to(dtype)


def _seven_point_normalized(points_left: torch.Tensor,
                            points_right: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The 7-point solutions for normalised points ``(..., 7, 2)`` (float64): ``(..., 3, 3, 3)``, ``(..., 3)``.

    F lies in the pencil ``X + α D`` (``X = F2``, ``D = F1 − F2``) of the system's 2-D null space, and
    ``det F = 0`` is a cubic in α (H&Z Sec. 11.1.2); its coefficients are interpolated from the determinant at
    4 values of α (fewer operations than cofactor expansions). When ``|det D| < |det X|`` the reversed cubic in
    β = 1/α (F ∝ βX + D) is solved instead, so the leading coefficient is never the smaller end. Solutions have
    unit Frobenius norm (sign not fixed); degenerate samples and inaccurate roots are invalid.
    """
    return _seven_point_from_design(_design_matrix(points_left, points_right))


def fundamental_7point(points_left: torch.Tensor,
                       points_right: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The minimal 7-point solver: up to three F per sample (paper Sec. 3.3 (3); H&Z Sec. 11.1.2).

    Args:
        points_left, points_right: ``(..., 7, 2)`` pixels.

    Returns:
        F ``(..., 3, 3, 3)`` (solution, row, column), each unit Frobenius norm, sign fixed, zeros where invalid;
        and validity ``(..., 3)`` bool. A degenerate sample (rank < 7: repeated points, collinear points in one
        image) has no valid solution. Each sample is Hartley-normalised on its own; float64 inside.

    Values only: root selection is discrete, so this is not meant for gradients.
    """
    _check_pair(points_left, points_right, _point_spec(points_left, 7))
    work = torch.float64
    left, t_left = normalize_points_hartley(points_left.to(work))
    right, t_right = normalize_points_hartley(points_right.to(work))
    solutions, valid = _seven_point_normalized(left, right)
    solutions = _denormalize(solutions, t_left.unsqueeze(-3), t_right.unsqueeze(-3))
    solutions = torch.where(valid[..., None, None], _fix_sign_and_scale(solutions), 0.0)
    return solutions.to(points_left.dtype), valid
