"""The winner of each pixel's costs and its verification: winner takes all, the rejections (flat, ambiguous,
on the range's inner edge), the right view's own winner and the left-right check, and the equiangular
sub-pixel fit.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from . import kernels
from .dense_config import DenseConfig

__all__ = ["equiangular_offset"]


def equiangular_offset(before: torch.Tensor, best: torch.Tensor, after: torch.Tensor) -> torch.Tensor:
    """Sub-pixel offset in [−0.5, 0.5] of a V-shaped minimum through three costs (Shimizu & Okutomi 2001).
    Differentiable w.r.t. the three costs (zero gradient where the offset is clamped or the rise is 0)."""
    rise = 2 * (torch.maximum(before, after) - best)
    safe = torch.where(rise > 0, rise, torch.ones_like(rise))
    return torch.where(rise > 0, (before - after) / safe, torch.zeros_like(rise)).clamp(-0.5, 0.5)


class _WinnerStats(NamedTuple):
    """Per left pixel of the matched box, ``(B, h, w)`` each: the winner-takes-all ``best`` index over D (the
    first on ties) and its cost, the costs at ``best ∓ 1`` (clamped to the range), the least cost farther than
    1 px from ``best`` (``rival``, +inf if none; None when not needed) and the right view's winner
    (``right_best``, see :func:`_right_winner`; None when not needed)."""

    best_cost: torch.Tensor
    best: torch.Tensor
    before: torch.Tensor
    after: torch.Tensor
    rival: torch.Tensor | None
    right_best: torch.Tensor | None
    fit_cost: torch.Tensor | None = None  # the sub-pixel fit's winner cost where it is not best_cost (aggregation)


def _winner_neighbours(best: torch.Tensor, num_disparities: int) -> torch.Tensor:
    """``(B, 3, h, w)``: the indices best − 1, best, best + 1 of the winners ``best`` ``(B, h, w)``, clamped to
    the range (gather them from a ``(B, D, h, w)`` volume for the costs the sub-pixel fit reads)."""
    neighbours = best.unsqueeze(1) + torch.tensor([-1, 0, 1], device=best.device).view(1, 3, 1, 1)
    return neighbours.clamp(0, num_disparities - 1)


def _winner_stats_torch(costs: torch.Tensor, minimum: tuple[torch.Tensor, torch.Tensor], uniqueness: bool,
                        right: bool, compiled: bool = True) -> _WinnerStats:
    """:class:`_WinnerStats` from the cost volume ``(B, D, h, w)`` (+inf where not searched) and its WTA
    ``minimum`` (found by :func:`_cost_volume`). ``costs`` is read, and restored after the uniqueness rival
    writes into it. ``compiled``: the C kernel :func:`svs_torch.depth.kernels.winner_statistics` where it runs
    (the same values bit for bit, one read of the volume for each statistic), else the torch operations below."""
    num_disparities = costs.shape[1]
    best_cost, best = minimum  # (B, h, w)
    found = kernels.winner_statistics(costs, best, uniqueness, right) if compiled and not costs.requires_grad else None
    if found is not None:
        return _WinnerStats(best_cost, best, *found)
    neighbours = _winner_neighbours(best, num_disparities)
    near = costs.gather(1, neighbours)
    rival = None
    if uniqueness:  # the best cost farther than 1 px from the winner, without copying the volume
        costs.scatter_(1, neighbours, torch.inf)
        rival = costs.min(dim=1).values
        costs.scatter_(1, neighbours, near)
    return _WinnerStats(best_cost, best, near[:, 0], near[:, 2], rival, _right_winner(costs) if right else None)


def _winner(stats: _WinnerStats, num_disparities: int, config: DenseConfig, lower_is_limit: torch.Tensor,
            counts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The sub-pixel offset of each winner and the uniqueness / range-edge verdict, ``(B, h, w)`` each."""
    best_cost, best, before, after = stats.best_cost, stats.best, stats.before, stats.after
    interior = (best > 0) & (best < num_disparities - 1) & torch.isfinite(before) & torch.isfinite(after)
    fit_cost = best_cost if stats.fit_cost is None else stats.fit_cost
    offset = torch.where(interior, equiangular_offset(before, fit_cost, after), torch.zeros_like(best_cost))
    ok = torch.isfinite(best_cost) & (best < counts.view(-1, 1, 1) - 1)
    ok &= (best > 0) | lower_is_limit.view(-1, 1, 1)  # a winner on the range's inner edge is unreliable
    if config.uniqueness_ratio > 0:
        ok &= stats.rival > (1 + config.uniqueness_ratio) * best_cost
    return offset, ok


def _right_winner(costs: torch.Tensor) -> torch.Tensor:
    """The right view's WTA index from the left volume, ``C_R(x_r, d) = C_L(x_r + d, d)`` (a shear), as a
    running minimum over d: ``(B, h, w)`` int64 indexed by the left-crop column ``j = x_r + d_lo − x0``; −1
    where every candidate is +inf. Ties keep the smaller d, as ``argmin`` does."""
    width = costs.shape[-1]
    best_cost = costs[:, 0].clone()
    best = torch.zeros(best_cost.shape, dtype=torch.int64, device=costs.device)
    for k in range(1, costs.shape[1]):
        candidate = costs[:, k, :, k:]  # column j + k of disparity k
        current = best_cost[..., :width - k]
        better = candidate < current
        torch.minimum(current, candidate, out=current)
        best[..., :width - k].masked_fill_(better, k)
    return best.masked_fill_(~torch.isfinite(best_cost), -1)


def _left_right_consistent(best: torch.Tensor, right_best: torch.Tensor, max_diff: float,
                           first_column: int = 0) -> torch.Tensor:
    """Left pixel j with index k is consistent when the right winner at left-crop column j − k is within
    ``max_diff`` of k (``StereoBM`` disp12MaxDiff on integer disparities). ``best`` ``(B, h, w)`` holds the
    crop's columns from ``first_column`` on; ``right_best`` every column of the crop."""
    w = best.shape[-1]
    column = torch.arange(first_column, first_column + w, device=best.device) - best  # (B, h, w)
    inside = column >= 0
    seen = right_best.gather(-1, column.clamp_min(0))
    return inside & (seen >= 0) & ((seen - best).abs() <= max_diff)
