"""The linear algebra of the 8- and 7-point solvers on design matrices: the (weighted) least-squares null
vector, the two-dimensional null space by pivoted LU, the cubic det(αF₁ + (1 − α)F₂) = 0 and its real roots,
the rank-2 projection and the sign and scale of a fundamental matrix.
"""

from __future__ import annotations

import functools
import math

import torch

from ..core.checks import check_dtype, check_shape
from ..core.inference import outside_inference_mode

__all__ = ["DEGENERATE_PIVOT_RATIO", "MAX_ROOT_DETERMINANT", "SIGN_TIE_TOLERANCE", "enforce_rank2", "real_cubic_roots"]


#: A 7-point sample is degenerate when the smallest LU pivot of its (normalised) system is below this share of
#: the largest: the system then has rank < 7 (repeated points, or collinear points in one image, which admit a
#: whole family of rank-1 solutions ``a lᵀ`` — Hartley & Zisserman Sec. 11.9).
DEGENERATE_PIVOT_RATIO = 1e-9
#: A 7-point root is kept only if ``|det F| ≤`` this for the unit-norm F (``|det F| ≤ 0.19`` always): a check
#: that the closed-form root is accurate, not a tuning knob.
MAX_ROOT_DETERMINANT = 1e-7
#: The fast null-space solve is trusted when its 7×7 block's smallest LU pivot is above this share of the largest
#: (the solution error grows like the inverse ratio); other samples take the fully pivoted path.
_FAST_PIVOT_RATIO = 1e-3
#: The entry that fixes F's sign is the first, in row-major order, within this share of the largest magnitude. The
#: F of a rig that only translates (a parallel rig, a rectified pair) is skew-symmetric: its largest entries come in
#: pairs of equal magnitude and opposite sign, and the strictly largest one was picked by rounding, so the same
#: points in another order gave −F. Rounding moves an entry by ~1e-12 of F (float64), far below this tolerance.
SIGN_TIE_TOLERANCE = 1e-6


def _design_matrix(points_left: torch.Tensor, points_right: torch.Tensor) -> torch.Tensor:
    """Rows ``(x'x, x'y, x', y'x, y'y, y', x, y, 1)`` of ``A f = 0``: ``(..., K, 2)`` pairs → ``(..., K, 9)``."""
    ones = torch.ones_like(points_left[..., :1])
    left_h = torch.cat([points_left, ones], dim=-1)  # (..., K, 3)
    right_h = torch.cat([points_right, ones], dim=-1)
    return (right_h.unsqueeze(-1) * left_h.unsqueeze(-2)).flatten(-2)  # (..., K, 9)


def _fix_sign_and_scale(fundamental: torch.Tensor) -> torch.Tensor:
    """Unit Frobenius norm and a positive largest-magnitude entry (the first of entries tied within
    :data:`SIGN_TIE_TOLERANCE`), ``(..., 3, 3)``; zero matrices stay zero."""
    flat = fundamental.flatten(-2)
    norm = flat.norm(dim=-1, keepdim=True)
    nonzero = norm > 0
    magnitude = flat.abs()
    tied = magnitude >= magnitude.amax(-1, keepdim=True) * (1.0 - SIGN_TIE_TOLERANCE)
    largest = flat.gather(-1, tied.to(torch.uint8).argmax(-1, keepdim=True))  # argmax: the first of the ties
    sign = torch.where(largest < 0, -1.0, 1.0).to(flat.dtype)
    flat = torch.where(nonzero, flat * sign / torch.where(nonzero, norm, 1.0), 0.0)
    return flat.unflatten(-1, (3, 3))


def enforce_rank2(fundamental: torch.Tensor) -> torch.Tensor:
    """The closest rank-2 matrix in Frobenius norm (zero the smallest singular value), ``(..., 3, 3)`` float32 or
    float64, in its dtype.

    Differentiable where the singular values are distinct.

    Raises:
        InputError: ``fundamental`` of another shape or dtype (torch's SVD raised for an integer one, naming none).
    """
    check_shape(fundamental, "fundamental", [*(f"N{i}" for i in range(max(fundamental.dim() - 2, 0))), 3, 3])
    check_dtype(fundamental, "fundamental", "float")
    return _rank2(fundamental)


def _rank2(fundamental: torch.Tensor) -> torch.Tensor:
    """:func:`enforce_rank2` without its checks, for the solvers' own float64 matrices."""
    u, s, vh = torch.linalg.svd(fundamental)
    s = torch.cat([s[..., :2], torch.zeros_like(s[..., 2:])], dim=-1)
    return u @ torch.diag_embed(s) @ vh


def _denormalize(fundamental_normalised: torch.Tensor, transform_left: torch.Tensor,
                 transform_right: torch.Tensor) -> torch.Tensor:
    """``F = T_rightᵀ F_n T_left``: a model of normalised points back to pixels."""
    return transform_right.transpose(-1, -2) @ fundamental_normalised @ transform_left


def _eight_point_from_design(design: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Weighted least squares from design rows ``(..., K, 9)`` (float64): rank-2 F ``(..., 3, 3)``.

    Minimises ``Σ w_k (a_k · f)²`` over unit f: the eigenvector of ``AᵀWA`` with the smallest eigenvalue.
    """
    normal = (design * weights.unsqueeze(-1)).transpose(-1, -2) @ design  # (..., 9, 9)
    _, vectors = torch.linalg.eigh(normal)
    return _rank2(vectors[..., :, 0].unflatten(-1, (3, 3)))


@functools.lru_cache(maxsize=8)
@outside_inference_mode  # cached across calls: never an inference tensor
def _mixing_matrix(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """A fixed orthogonal 9×9 matrix (a Householder reflection with an irregular normal), cached per dtype/device."""
    normal = torch.tensor([1.0, -2.0, 3.0, 5.0, -7.0, 11.0, 13.0, -17.0, 19.0], dtype=torch.float64)
    normal = normal / normal.norm()
    reflection = torch.eye(9, dtype=torch.float64) - 2.0 * torch.outer(normal, normal)
    return reflection.to(dtype=dtype, device=device)


def _nullspace_pivoted(design: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Null space of ``(N, 7, 9)`` systems by LU with partial pivoting of ``Aᵀ = P L U`` (rows of Aᵀ = unknowns).

    ``A f = 0 ⇔ Lᵀ Pᵀ f = 0``, and ``null(Lᵀ) = [−L₁⁻ᵀ L₂ᵀ; I₂]`` for the unit lower-triangular top block
    L₁, whose entries are ≤ 1 by pivoting: accurate for every sample of rank 7. Returns the two vectors as
    rows ``(N, 2, 9)`` and full rank ``(N,)``.
    """
    lu, pivots, _ = torch.linalg.lu_factor_ex(design.transpose(-1, -2))  # (N, 9, 7); rank checked below
    permutation = torch.lu_unpack(lu, pivots, unpack_data=False)[0]  # (N, 9, 9)
    free = torch.linalg.solve_triangular(lu[..., :7, :7].transpose(-1, -2), -lu[..., 7:, :7].transpose(-1, -2),
                                         upper=True, unitriangular=True)  # (N, 7, 2)
    eye = torch.eye(2, dtype=lu.dtype, device=lu.device).expand(free.shape[0], 2, 2)
    return (permutation @ torch.cat([free, eye], dim=-2)).transpose(-1, -2), _full_rank(lu, DEGENERATE_PIVOT_RATIO)


def _full_rank(lu: torch.Tensor, ratio: float) -> torch.Tensor:
    """Whether the smallest LU pivot exceeds ``ratio`` × the largest (False for NaN) ``(N,)``."""
    pivot = lu.diagonal(dim1=-2, dim2=-1).abs()
    return pivot.amin(-1) > ratio * pivot.amax(-1)


def _nullspace_7(design: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Two orthonormal vectors spanning the null space of 7×9 systems ``(..., 7, 9)`` as rows ``(..., 2, 9)``,
    and full rank ``(...)``.

    Fast path: in mixed unknowns ``g = Qᵀf`` (Q a fixed reflection) the system is ``[B₁ B₂] g = 0`` with B₁
    7×7, so ``g = [−B₁⁻¹B₂; I₂]``: one batched LU solve, 2× faster than pivoting over all 9 unknowns and 30×
    faster than a batched SVD on CPU. Q keeps B₁ from being singular for a whole geometry (without it, every
    pencil holding an F with F₂₁ = F₂₂ = 0, e.g. vertical motion, would be). The few samples whose B₁ is
    ill-conditioned (small LU pivot ratio, ~2 %) are redone by :func:`_nullspace_pivoted`, so every
    non-degenerate sample is solved to full accuracy.
    """
    flat = design.reshape(-1, 7, 9)
    mixing = _mixing_matrix(design.dtype, design.device)
    mixed = flat @ mixing  # (N, 7, 9)
    lu, pivots, _ = torch.linalg.lu_factor_ex(mixed[..., :7])  # no exception: conditioning checked below
    free = torch.linalg.lu_solve(lu, pivots, -mixed[..., 7:])  # (N, 7, 2)
    eye = torch.eye(2, dtype=design.dtype, device=design.device).expand(free.shape[0], 2, 2)
    basis = torch.cat([free.transpose(-1, -2), eye], dim=-1) @ mixing.T  # f = Q g, as rows (N, 2, 9)
    full_rank = _full_rank(lu, _FAST_PIVOT_RATIO)
    if not bool(full_rank.all()):
        index = (~full_rank).nonzero().squeeze(-1)
        redone, redone_rank = _nullspace_pivoted(flat.index_select(0, index))
        basis = basis.index_copy(0, index, redone)
        full_rank = full_rank.index_copy(0, index, redone_rank)
    return _orthonormalize(basis).view(*design.shape[:-2], 2, 9), full_rank.view(design.shape[:-2])


def _orthonormalize(basis: torch.Tensor) -> torch.Tensor:
    """Gram–Schmidt on the two rows of ``(N, 2, 9)``: the two solved vectors can be long and nearly parallel,
    which would cluster the cubic's roots and cost digits; an orthonormal pencil keeps them apart."""
    first, second = basis.unbind(-2)
    first = first * (first * first).sum(-1, keepdim=True).rsqrt()
    second = second - (first * second).sum(-1, keepdim=True) * first
    second = second * (second * second).sum(-1, keepdim=True).rsqrt()
    return torch.stack([first, second], -2)


def _determinant(flat: torch.Tensor) -> torch.Tensor:
    """Determinants of row-major 3×3 matrices ``(..., 9)`` → ``(...)``, by the rule of Sarrus."""
    a, b, c, d, e, f, g, h, i = flat.unbind(-1)
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)


#: det(X + αD) is a cubic in α: its values at these 4 nodes determine it (solve with the inverse Vandermonde).
_CUBIC_NODES = (-1.0, 0.0, 1.0, 2.0)


def _cubic_from_values(values: torch.Tensor) -> torch.Tensor:
    """Coefficients ``(a, b, c, d)`` ``(..., 4)`` of the cubic with the given values ``(..., 4)`` at the nodes."""
    nodes = torch.tensor(_CUBIC_NODES, dtype=values.dtype, device=values.device)
    vandermonde = torch.stack([nodes ** 3, nodes ** 2, nodes, torch.ones_like(nodes)], -1)  # (4, 4)
    return values @ torch.linalg.inv(vandermonde).transpose(0, 1)


def real_cubic_roots(coefficients: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Real roots of ``a t³ + b t² + c t + d`` in closed form, batched.

    Args:
        coefficients: ``(..., 4)`` as ``(a, b, c, d)``; float64 recommended.

    Returns:
        roots ``(..., 3)`` and validity ``(..., 3)`` bool: three roots where the discriminant says three real
        ones (trigonometric form), else one (Cardano, written without cancellation); each polished by two
        Newton steps. Where ``a = 0`` no root is valid (the caller chooses the parametrisation that keeps
        ``|a|`` large). A double root may be returned twice. Values only (not meant for gradients).
    """
    scale = coefficients.abs().amax(-1, keepdim=True)
    coefficients = coefficients / torch.where(scale > 0, scale, 1.0)
    a, b, c, d = coefficients.unbind(-1)
    has_cubic = a != 0
    a_safe = torch.where(has_cubic, a, 1.0)
    p, q, r = b / a_safe, c / a_safe, d / a_safe
    # Depressed cubic t³ + P t + Q with α = t − p/3.
    big_p = q - p * p / 3.0
    big_q = 2.0 * p ** 3 / 27.0 - p * q / 3.0 + r
    discriminant = (big_q / 2.0) ** 2 + (big_p / 3.0) ** 3
    three = discriminant < 0  # implies P < 0
    m = 2.0 * torch.sqrt(torch.clamp(-big_p / 3.0, min=0.0))
    cos_3theta = torch.where(three, 3.0 * big_q / torch.where(three, big_p * m, 1.0), 0.0).clamp(-1.0, 1.0)
    theta = torch.acos(cos_3theta) / 3.0
    shifts = torch.tensor([0.0, -2.0 * math.pi / 3.0, -4.0 * math.pi / 3.0], dtype=a.dtype, device=a.device)
    trig = m.unsqueeze(-1) * torch.cos(theta.unsqueeze(-1) + shifts)  # (..., 3)
    # One real root: u = cbrt(−Q/2 − sign(Q)·√Δ) has no cancellation; t = u − P/(3u).
    sqrt_disc = torch.sqrt(torch.clamp(discriminant, min=0.0))
    w = -big_q / 2.0 - torch.where(big_q >= 0, sqrt_disc, -sqrt_disc)
    u = torch.sign(w) * w.abs().pow(1.0 / 3.0)
    single = torch.where(u != 0, u - big_p / (3.0 * torch.where(u != 0, u, 1.0)), 0.0)
    roots = torch.where(three.unsqueeze(-1), trig, single.unsqueeze(-1)) - (p / 3.0).unsqueeze(-1)
    for _ in range(2):
        value = ((a.unsqueeze(-1) * roots + b.unsqueeze(-1)) * roots + c.unsqueeze(-1)) * roots + d.unsqueeze(-1)
        slope = (3.0 * a.unsqueeze(-1) * roots + 2.0 * b.unsqueeze(-1)) * roots + c.unsqueeze(-1)
        roots = torch.where(slope != 0, roots - value / torch.where(slope != 0, slope, 1.0), roots)
    first_only = torch.tensor([True, False, False], device=a.device)
    valid = (three.unsqueeze(-1) | first_only) & has_cubic.unsqueeze(-1) & roots.isfinite()
    return torch.where(valid, roots, 0.0), valid


def _seven_point_from_design(design: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`_seven_point_normalized` from the design rows ``(..., 7, 9)`` of the sample."""
    basis, full_rank = _nullspace_7(design)  # (..., 2, 9)
    x = basis[..., 1, :]
    d = basis[..., 0, :] - x
    nodes = torch.tensor(_CUBIC_NODES, dtype=x.dtype, device=x.device).unsqueeze(-1)  # (4, 1)
    values = _determinant(x.unsqueeze(-2) + nodes * d.unsqueeze(-2))  # (..., 4)
    forward = _cubic_from_values(values)  # (α³, α², α, 1) coefficients
    reverse = forward[..., 0].abs() < forward[..., 3].abs()
    coefficients = torch.where(reverse.unsqueeze(-1), forward.flip(-1), forward)
    roots, valid = real_cubic_roots(coefficients)  # (..., 3)
    # forward: F = X + α D; reversed: F ∝ β X + D.
    big = torch.where(reverse.unsqueeze(-1), d, x).unsqueeze(-2)
    small = torch.where(reverse.unsqueeze(-1), x, d).unsqueeze(-2)
    solutions = big + roots.unsqueeze(-1) * small  # (..., 3, 9)
    norm = solutions.norm(dim=-1, keepdim=True)
    solutions = solutions / torch.where(norm > 0, norm, 1.0)
    valid = valid & full_rank.unsqueeze(-1) & (_determinant(solutions).abs() <= MAX_ROOT_DETERMINANT)
    return torch.where(valid.unsqueeze(-1), solutions, 0.0).unflatten(-1, (3, 3)), valid
