"""RANSAC's problem and its scoring: the normalised points and their Sampson monomials, the 7-point models of
a chunk of samples, and the truncated (MSAC), counted (RANSAC) or median (LMedS) score of every model.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from .epipolar_distance import _safe_ratio, _sampson_coefficients, _sampson_monomials
from .minimal_solvers import _design_matrix, _seven_point_from_design
from .point_pairs import normalize_points_hartley
from .ransac_sampling import _SAMPLE_SIZE, _preverification_rows, draw_minimal_samples

__all__ = []


#: Added to the float32 Sampson denominator (a sum of squares, expanded into monomials whose rounding can make it
#: slightly negative near an epipole): bounds the float32 rounding error of the expansion for normalised points,
#: so scores are never negative. It shrinks d² by a relative 1e-4/den, i.e. only near an epipole; the reported
#: inliers use the exact float64 distance.
_DENOMINATOR_GUARD = 1e-4
#: Scoring blocks hold about this many (hypothesis, point) entries: 4 MB float32 temporaries stay in cache;
#: larger blocks were slower on a 2-core machine, smaller ones pay Python overhead.
_SCORE_BLOCK_ENTRIES = 1 << 20


class _ScoringSet(NamedTuple):
    """Rows that models are scored on (all valid rows, or the pre-verification subset)."""

    numerator: torch.Tensor  # (B, 9, R) float32 monomials: x'ᵀFx = f · m
    denominator: torch.Tensor  # (B, 12, R) float32 monomials: Sampson denominator = g(F) · m
    median_offsets: torch.Tensor  # (B, 1, R) float32, LMedS only: 0 on valid rows, ±inf on padding
    median_rank: int  # LMedS only: the 1-based rank that is each pair's median after the offsets
    num_rows: torch.Tensor  # (B, 1) float64: each pair's own (valid) rows in the set


class _Problem(NamedTuple):
    """One batch, prepared once: normalised points (float64), transforms and scoring sets."""

    design: torch.Tensor  # (B, K, 9) float64 rows a with x'ᵀFx = a · f (normalised points), zero in padding
    quadratic: torch.Tensor  # (B, K, 12) float64 Sampson-denominator monomials (padding: exactly 1)
    transform_left: torch.Tensor  # (B, 3, 3), x_normalised = T x_px
    transform_right: torch.Tensor  # (B, 3, 3)
    valid: torch.Tensor  # (B, K) bool
    num_valid: torch.Tensor  # (B,) int64; the valid rows are the first num_valid rows of each pair
    threshold_sq: torch.Tensor  # (B,) float64, threshold² in normalised units
    full: _ScoringSet
    subset: _ScoringSet  # PREVERIFY_POINTS random valid rows per pair


def _scoring_set(numerator: torch.Tensor, denominator: torch.Tensor, valid: torch.Tensor) -> _ScoringSet:
    """A scoring set over rows with validity ``(B, R)``; LMedS offsets make one rank the median of every pair.

    Padding scores exactly 0; giving the first ``p_b`` padding rows −inf and the rest +inf shifts pair b's
    median (rank ``(n_b − 1)//2 + 1`` among its n_b valid rows) to the common rank ``k = max_b`` of those ranks
    when ``p_b = k − rank_b`` (always ≤ the pair's padding count), so one ``kthvalue`` serves the batch.
    """
    count = valid.sum(-1)
    rank = (count - 1).clamp(min=0) // 2 + 1
    common = int(rank.max()) if rank.numel() else 1
    padding_rank = (~valid).cumsum(-1) - 1
    below = (~valid) & (padding_rank < (common - rank).unsqueeze(-1))
    offsets = torch.where(valid, 0.0, torch.where(below, -math.inf, math.inf)).float().unsqueeze(1)
    return _ScoringSet(numerator, denominator, offsets, common, count.double().unsqueeze(-1))


def _normalize_shared_scale(points_left: torch.Tensor, points_right: torch.Tensor, valid: torch.Tensor
                            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Hartley normalisation with one scale s for both images of a pair (so ``d_normalised = s·d_px``)."""
    work = torch.float64
    mask = valid.unsqueeze(-1)
    left_px = torch.where(mask, points_left.to(work), 0.0)
    right_px = torch.where(mask, points_right.to(work), 0.0)
    _, t_left = normalize_points_hartley(left_px, valid.to(work))
    _, t_right = normalize_points_hartley(right_px, valid.to(work))
    scale = (t_left[:, 0, 0] * t_right[:, 0, 0]).sqrt()  # (B,)
    normalised, transforms = [], []
    for points, t in ((left_px, t_left), (right_px, t_right)):
        shift = t[:, :2, 2] / t[:, :1, 0] * scale.unsqueeze(-1)  # −centroid · s
        t = t.clone()
        t[:, :2, 2] = shift
        t[:, 0, 0] = t[:, 1, 1] = scale
        transforms.append(t)
        normalised.append(torch.where(mask, points * scale.view(-1, 1, 1) + shift.unsqueeze(1), 0.0))
    return normalised[0], normalised[1], transforms[0], transforms[1], scale


def _prepare(points_left: torch.Tensor, points_right: torch.Tensor, valid: torch.Tensor, threshold_px: float,
             pair_seeds: torch.Tensor) -> _Problem:
    """Normalise each pair and build the monomials and scoring sets, once per call; rows ``(B, K, 2)`` hold
    each pair's valid correspondences first."""
    left, right, t_left, t_right, scale = _normalize_shared_scale(points_left, points_right, valid)
    mask = valid.unsqueeze(-1)
    design = torch.where(mask, _design_matrix(left, right), 0.0)  # (B, K, 9)
    padding_row = torch.zeros(12, dtype=design.dtype, device=design.device)
    padding_row[11] = 1.0
    quadratic = torch.where(mask, _sampson_monomials(left, right), padding_row)  # (B, K, 12)
    numerator = design.transpose(1, 2).float().contiguous()  # (B, 9, K) for the float32 scoring products
    denominator = quadratic.transpose(1, 2).float().contiguous()  # (B, 12, K)
    rows = _preverification_rows(pair_seeds, valid)
    subset = _scoring_set(numerator.gather(2, rows.unsqueeze(1).expand(-1, 9, -1)),
                          denominator.gather(2, rows.unsqueeze(1).expand(-1, 12, -1)), valid.gather(1, rows))
    return _Problem(design=design, quadratic=quadratic, transform_left=t_left, transform_right=t_right,
                    valid=valid, num_valid=valid.sum(-1),
                    threshold_sq=(threshold_px * scale).square(),
                    full=_scoring_set(numerator, denominator, valid), subset=subset)


def _products(coefficients: torch.Tensor, monomials: torch.Tensor) -> torch.Tensor:
    """``(B, S, M)`` · ``(B, M, R)`` → ``(B, S, R)``, each entry Σ_m c_m · x_m summed in one fixed order (the C
    kernel's), so it is the same whatever B, S and R: a batched matrix product rounds an entry differently with R
    (its blocking), so a pair's float32 scores depended on the widest pair of its batch, and LMedS, whose medians
    on a few matches are near-exact fits 1e-15 apart, picked another model beside another pair."""
    out = coefficients[..., :1] * monomials[:, :1]
    for m in range(1, monomials.shape[1]):
        out += coefficients[..., m:m + 1] * monomials[:, m:m + 1]
    return out


def _score(rows: _ScoringSet, fundamental: torch.Tensor, usable: torch.Tensor, threshold_sq: torch.Tensor,
           scoring: str) -> torch.Tensor:
    """Loss of each model ``(B, S, 3, 3)`` (normalised coordinates) on ``rows`` → ``(B, S)`` float64, lower is
    better; inf where ``usable`` is False.

    Blocks of models are scored by two fixed-order products (:func:`_products`) and a few in-place passes, never
    materialising more than about ``_SCORE_BLOCK_ENTRIES`` distances.
    """
    b, s = usable.shape
    r = rows.numerator.shape[-1]
    coefficients_num = fundamental.flatten(-2).float()  # (B, S, 9)
    coefficients_den = _sampson_coefficients(fundamental, _DENOMINATOR_GUARD).float()  # (B, S, 12)
    threshold_sq = threshold_sq.float().view(-1, 1, 1)
    block = max(1, _SCORE_BLOCK_ENTRIES // max(1, b * r))
    losses = [torch.zeros(b, 0, dtype=torch.float64, device=usable.device)]
    for start in range(0, s, block):
        distance_sq = _products(coefficients_num[:, start:start + block], rows.numerator)  # (B, s', R)
        distance_sq = distance_sq.mul_(distance_sq).div_(
            _products(coefficients_den[:, start:start + block], rows.denominator))
        if scoring == "lmeds":
            loss = distance_sq.add_(rows.median_offsets).kthvalue(rows.median_rank, dim=-1).values
        elif scoring == "ransac":
            # Over the pair's own n rows: padding scores 0, an inlier of every model, and counting it (or
            # dividing by the batch's widest R) made the loss, so local optimisation's relative stop, depend on
            # the pair's batch neighbours.
            count = (distance_sq <= threshold_sq).sum(-1, dtype=torch.float32).double() - (r - rows.num_rows)
            # MSAC cost / t² < n + 1: the fraction only breaks ties between equal counts.
            tie = torch.minimum(distance_sq, threshold_sq, out=distance_sq).sum(-1) / threshold_sq.view(-1, 1)
            loss = tie.double() / (rows.num_rows + 1) - count
        else:
            loss = torch.minimum(distance_sq, threshold_sq, out=distance_sq).sum(-1)
        losses.append(loss.double())
    return torch.where(usable, torch.cat(losses, 1), math.inf)


def _solve_chunk(problem: _Problem, pair_seeds: torch.Tensor, first: int,
                 count: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Draw ``count`` samples per pair and solve them: models ``(B, 3·count, 3, 3)`` and validity ``(B, 3·count)``."""
    b = problem.valid.shape[0]
    ranks = draw_minimal_samples(pair_seeds, first, count, problem.num_valid)  # (B, M, 7), rank = row
    rows = ranks.flatten(1).unsqueeze(-1).expand(-1, -1, 9)  # (B, M·7, 9)
    design = problem.design.gather(1, rows).view(b, count, _SAMPLE_SIZE, 9)
    models, usable = _seven_point_from_design(design)  # (B, M, 3, 3, 3), (B, M, 3)
    return models.flatten(1, 2), usable.flatten(1)


def _sampson_sq(problem: _Problem, fundamental: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Squared Sampson distances ``(B, K)`` (normalised units, float64) of models ``(B, 3, 3)``, and the
    denominators; only meaningful on valid rows."""
    algebraic = (problem.design @ fundamental.flatten(-2).unsqueeze(-1)).squeeze(-1)
    denominator = (problem.quadratic @ _sampson_coefficients(fundamental).unsqueeze(-1)).squeeze(-1)
    denominator = denominator.clamp(min=0.0)  # a sum of squares; the expansion may round to −1e-16
    return _safe_ratio(algebraic.square(), denominator), denominator


def _select_pairs(problem: _Problem, index: torch.Tensor) -> _Problem:
    """The pairs at ``index`` (int64) of a prepared batch; scoring sets keep their common LMedS rank."""
    def pick(value):
        if isinstance(value, _ScoringSet):
            return value._replace(numerator=pick(value.numerator), denominator=pick(value.denominator),
                                  median_offsets=pick(value.median_offsets), num_rows=pick(value.num_rows))
        return value.index_select(0, index)

    return _Problem(*(pick(value) for value in problem))
