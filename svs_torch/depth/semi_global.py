"""Semi-global aggregation of the dense stage's SAD volume (Hirschmüller 2008), for pairs whose matching is noisy.

Block matching decides each pixel from its own window; on camera frames (JPEG with sensor noise, issue 33) the
windows of a weakly textured surface lose their minimum to noise, the uniqueness and left–right rules reject
them, and a kept region is ranged from whichever of its surfaces kept some texture. OpenCV's ``StereoSGBM`` keeps
such surfaces measured by adding, along 4–8 straight paths through each pixel, a penalty P1 for a disparity
step of 1 and P2 for a larger one (Hirschmüller's Eq. (13)):

    L_r(p, d) = C(p, d) + min(L_r(p − r, d), L_r(p − r, d ± 1) + P1, min_k L_r(p − r, k) + P2) − min_k L_r(p − r, k)

and deciding on S(p, d) = Σ_r L_r(p, d). Here 4 paths (along the rows and the columns, both ways), with P1 and P2
in units of the pair's own matching residual: the median, over the pixels where depth is wanted, of the best
SAD per window pixel. A clean pair's residual is small and its penalties with it; noise raises both. The
volume's +inf costs (disparities outside the image or the pair's range) stay +inf, and a path starts again where
a whole column of the volume is +inf (outside the pair's own region), so that a pair's result never depends on
its batch.

Hard path only (the winner and its rejections follow on the aggregated volume); not differentiable here.
"""

from __future__ import annotations

import torch

from ..core.checks import InputError, check_count, check_device, check_dtype, check_shape
from ..core.mask_reductions import count_along
from . import kernels

__all__ = ["pair_residual_levels", "residual_reaches", "semi_global_aggregate", "semi_global_aggregate_with_winner"]


def _scan_columns_torch(costs: torch.Tensor, p1: torch.Tensor, p2: torch.Tensor) -> torch.Tensor:
    """The paths down and up the rows of ``costs`` ``(B, D, H, W)``, summed (the C kernel's reference)."""
    p1, p2 = p1.view(-1, 1, 1), p2.view(-1, 1, 1)
    height = costs.shape[-2]
    inf = torch.full_like(costs[:, :1, 0], torch.inf)

    def path(rows: range) -> torch.Tensor:
        out = torch.empty_like(costs)
        previous = None
        for y in rows:
            cost = costs[:, :, y]  # (B, D, W)
            if previous is None:
                current = cost.clone()
            else:
                low = previous.min(dim=1, keepdim=True).values
                neighbours = torch.minimum(torch.cat([previous[:, 1:], inf], 1), torch.cat([inf, previous[:, :-1]], 1))
                best = torch.minimum(torch.minimum(previous, neighbours + p1), low + p2)
                current = cost + torch.where(torch.isfinite(low), best - low, torch.zeros_like(best))
            out[:, :, y] = current
            previous = current
        return out

    return path(range(height)) + path(range(height - 1, -1, -1))


def _scan_columns(costs: torch.Tensor, p1: torch.Tensor, p2: torch.Tensor) -> torch.Tensor:
    found = kernels.semi_global_columns(costs, p1, p2)
    return _scan_columns_torch(costs, p1, p2) if found is None else found


def semi_global_aggregate(costs: torch.Tensor, p1: torch.Tensor, p2: torch.Tensor) -> torch.Tensor:
    """S(p, d) of the module docstring: the 4 paths' sum, ``(B, D, H, W)`` like ``costs`` (+inf where not searched).

    Args:
        costs: ``(B, D, H, W)`` float SAD costs, +inf where a disparity is not searched; a column +inf at every d
            is outside the region (the paths start again after it).
        p1, p2: ``(B,)`` each pair's penalties, in the costs' units, 0 <= p1 <= p2 (both 0: S = 4 C, the same
            winner and verdicts as no aggregation).

    Returns:
        The columns' paths (down + up) plus the rows' (right + left), in that order. No gradients (the C kernel
        where it runs, else the torch path; the same values bit for bit).
    """
    return semi_global_aggregate_with_winner(costs, p1, p2)[0]


def semi_global_aggregate_with_winner(costs: torch.Tensor, p1: torch.Tensor, p2: torch.Tensor
                                      ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
    """:func:`semi_global_aggregate` and its winner-takes-all: (the minimum over D, its first index), ``(B, H, W)``
    each, as ``S.min(dim=1)``. The C kernels where they run (the rows' paths added to the columns' and the winner
    taken in the same pass, without a transposed copy of the volume), else the torch path; the same values bit
    for bit. Arguments and checks as :func:`semi_global_aggregate`'s. No gradients (computed under
    ``torch.no_grad``; the index is int64)."""
    dims = check_shape(costs, "costs", ["B", "D", "H", "W"])
    check_dtype(costs, "costs", "float")  # int64 costs failed converting +inf deep inside
    if costs.is_meta:  # its minimum is read on the host: a RuntimeError from a meta item() (an audit)
        raise InputError("costs: expected a tensor with values, got one on the meta device")
    for name, value in (("p1", p1), ("p2", p2)):
        check_shape(value, name, [dims["B"]])
        # A complex one raised NotImplementedError from the comparison below, a meta one a RuntimeError from its
        # bool(), and a bool one was taken as 1 in silence (an audit).
        check_dtype(value, name, "int|float")
        check_device(value, name, costs, "the costs'")
    if costs.numel() and not bool(costs.min() >= 0):  # one pass: the minimum is NaN where any cost is
        raise InputError("costs: expected SAD costs >= 0 (or +inf where not searched), got NaN or negative values")
    if not (bool((p1 >= 0).all()) and bool((p2 >= p1).all())):
        raise InputError(f"p1, p2: expected 0 <= p1 <= p2 for every pair, got {p1.tolist()}, {p2.tolist()}")
    p1, p2 = p1.to(costs.dtype), p2.to(costs.dtype)
    if costs.numel() == 0:  # (with D = 0 the winner is +inf at index 0, as a pixel with every cost +inf)
        shape = (dims["B"], dims["H"], dims["W"])
        return costs.detach().clone(), (costs.new_full(shape, torch.inf),
                                        torch.zeros(shape, dtype=torch.int64, device=costs.device))
    with torch.no_grad():
        columns = _scan_columns(costs, p1, p2)
        found = kernels.semi_global_rows(costs, p1, p2, columns)
        if found is not None:
            return found
        rows = _scan_columns(costs.transpose(-1, -2).contiguous(), p1, p2).transpose(-1, -2)
        aggregated = columns + rows
        return aggregated, aggregated.min(dim=1)


def pair_residual_levels(best_cost: torch.Tensor, wanted: torch.Tensor, window_size: int) -> torch.Tensor:
    """Each pair's matching residual ``(B,)``: the median over ``wanted`` ``(B, H, W)`` bool of the finite
    winner costs ``best_cost`` ``(B, H, W)`` (window SADs of whole levels), per window pixel; 0 where a pair has
    no such pixel. Differentiable w.r.t. ``best_cost`` (``nanmedian``: the median pixel gets the gradient)."""
    # Unchecked before (an audit): a wanted of another shape was broadcast, a float one or int costs failed deep
    # inside, a window of 0 gave residuals of inf and True a window of 1.
    check_shape(wanted, "wanted", list(check_shape(best_cost, "best_cost", ["B", "H", "W"]).values()))
    check_dtype(best_cost, "best_cost", "float")
    check_dtype(wanted, "wanted", "bool")
    check_count(window_size, "window_size", least=1)
    # |cost| < inf is isfinite (NaN compares false) in one comparison where isfinite takes four passes; the NaN a
    # scalar, not a filled volume: the two lines took 4.7 ms for 8 pairs at 320 × 240 (one thread), now 3.4.
    finite = wanted & (best_cost.abs() < torch.inf)
    values = torch.where(finite, best_cost, torch.nan).flatten(1)
    median = values.nanmedian(dim=1).values
    return torch.where(finite.flatten(1).any(1), median, torch.zeros_like(median)) / window_size ** 2


def residual_reaches(best_cost: torch.Tensor, wanted: torch.Tensor | None, window_size: int, level: float
                     ) -> torch.Tensor:
    """``pair_residual_levels(best_cost, wanted, window_size) >= level`` ``(B,)`` bool, bit for bit, without the
    median: for a gate that needs only which pairs reach ``level``. ``wanted`` None: every pixel. Not
    differentiable (a verdict).

    Why it holds: x ↦ x / window_size² (float32) is monotone, so the costs under ``level`` after the division are
    the smallest ones, and the lower median (rank (n − 1) / 2 of the n finite wanted costs) reaches ``level``
    exactly when at most (n − 1) / 2 of them are under it. A count, where ``nanmedian`` selects: 8 real 320×240
    pairs' winning costs, one thread, 8.1 → 1.7 ms (the nearness segmenter's noise gate, each batch)."""
    dims = check_shape(best_cost, "best_cost", ["B", "H", "W"])
    if wanted is not None:
        check_shape(wanted, "wanted", list(dims.values()))
        check_dtype(wanted, "wanted", "bool")
    check_dtype(best_cost, "best_cost", "float")
    check_count(window_size, "window_size", least=1)
    with torch.no_grad():
        counted, under = best_cost.abs() < torch.inf, best_cost / window_size ** 2 < level  # NaN, +inf: not under
        if wanted is not None:
            counted, under = counted & wanted, under & wanted
        counted, under = count_along(counted.flatten(1), 1), count_along(under.flatten(1), 1)
        return torch.where(counted > 0, under <= (counted - 1) // 2, torch.zeros_like(counted, dtype=best_cost.dtype)
                           >= level)
