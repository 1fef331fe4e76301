"""The grid the ground plane is fitted on (:mod:`.ground_plane`): every ``stride``-th pixel of the nearness map from
``stride // 2`` on, its points drawn three at a time for the plane's hypotheses.

A camera frame's map scatters about the floor, and only part of it is measured: on the rendered walker scenes at
the board's default JPEG digit 4 with noise σ 4, the floor was found in 32 of 36 pairs without the near box (27 of
36 with it), and the floor left was warned of (``experiments/walker_floor.md``, "Samples from cell medians"). Three
nearby grid pixels, each off by its own noise, seldom make a plane with a walker's slope: the slope of a sample
spanning a few grid cells is as noisy as the floor's own is steep. On a noisy pair the samples are therefore drawn
from the medians of the measured pixels of each grid cell, where enough of it is measured (:func:`cell_medians`): a
cell on the floor holds a few dozen pixels whose median is one of the floor's, and a cell where the floor meets an
obstacle's foot takes the side most of its pixels lie on. Every test of a hypothesis, and the refits, still read
the grid's own pixels, so the rule's tests are the ones chosen on clean maps (sampling and scoring on the medians
both took a plant on a table for a floor on a tuned scene's camera frames, Jadeplant at digit 4).
"""

from __future__ import annotations

import math

import torch

__all__ = ["cell_medians", "sample_planes"]


def cell_medians(disparity: torch.Tensor, measured: torch.Tensor, stride: int,
                 min_measured_px: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(B, gh, gw)`` for each grid pixel (every ``stride``-th of ``disparity`` ``(B, 1, H, W)`` from
    ``stride // 2``) the lower median of the ``measured`` ``(B, 1, H, W)`` pixels of its cell (the ``stride`` ×
    ``stride`` block holding it, rows and columns from a multiple of ``stride``; 0 where fewer than
    ``min_measured_px``), and ``(B, gh, gw)`` bool whether a sample may be drawn there (that many measured, and a
    positive median). What the fit draws a noisy pair's samples from
    (:func:`svs_torch.segmentation.ground_plane.fit_ground_plane`: the torch path reads them here, the kernel makes
    the same values itself). Not differentiable."""
    b, _, h, w = disparity.shape
    offset = stride // 2
    gh, gw = -(-(h - offset) // stride), -(-(w - offset) // stride)
    # every cell whole: pad the bottom and right with unmeasured pixels
    pad = (0, gw * stride - w, 0, gh * stride - h)
    values = torch.nn.functional.pad(disparity[:, 0], pad)
    seen = torch.nn.functional.pad(measured[:, 0], pad)
    blocks = (lambda t: t.view(b, gh, stride, gw, stride).transpose(2, 3).reshape(b, gh, gw, stride * stride))
    values, seen = blocks(values), blocks(seen)
    median = torch.where(seen, values, math.nan).nanmedian(-1).values  # the lower median: a pixel's own value
    enough = seen.sum(-1) >= min_measured_px
    median = torch.where(enough, median, 0.0).to(disparity.dtype)
    return median, enough & (median > 0)


def sample_planes(d: torch.Tensor, measured: torch.Tensor, candidate: torch.Tensor, xs: torch.Tensor,
                  ys: torch.Tensor, draws: torch.Tensor) -> torch.Tensor:
    """``(B, N, 3)`` planes through three grid points of each pair (``d``, ``measured``, ``candidate`` ``(B, gh, gw)``,
    the grid's pixel columns ``xs`` ``(gw,)`` and rows ``ys`` ``(gh,)``), picked by the uniform ``draws`` ``(N, 5)``
    shared by all pairs: the first point is the pair's ``floor(u · count)``-th candidate; the other two lie within a
    window of an eighth of the grid's width and a sixth of its height around it, so that a floor that fills a strip
    of the view's bottom is sampled whole as often as it is hit (three points drawn over the lower rows all land on
    a floor seen over a fifth of them once in 125 samples). A sample with a point off the grid or unmeasured, or
    nearly collinear, gets NaN."""
    b, gh, gw = d.shape
    flat = candidate.flatten(1)
    count = flat.sum(-1)  # (B,)
    rank = (draws[:, 0].unsqueeze(0) * count.view(-1, 1)).long()  # (B, N)
    order = flat.to(torch.int64).cumsum(-1)  # the k-th candidate is where the running count reaches k + 1
    first = torch.searchsorted(order.contiguous(), rank + 1).clamp(max=gh * gw - 1)
    reach = torch.tensor([max(1, gw // 8), max(1, gh // 6)] * 2, dtype=torch.float64, device=d.device)
    offsets = ((draws[:, 1:] * 2 - 1) * reach).round().long().view(1, -1, 2, 2)  # (1, N, point, (dx, dy))
    column, row = (first % gw).unsqueeze(-1), (first // gw).unsqueeze(-1)
    column = torch.cat([column, column + offsets[..., 0]], -1)  # (B, N, 3)
    row = torch.cat([row, row + offsets[..., 1]], -1)
    inside = (column >= 0) & (column < gw) & (row >= 0) & (row < gh)  # (B, N, 3)
    index = row.clamp(0, gh - 1) * gw + column.clamp(0, gw - 1)
    seen = measured.flatten(1).gather(1, index.flatten(1)).view_as(index) & inside
    pd = d.flatten(1).gather(1, index.flatten(1)).view_as(index)
    px, py = xs[column.clamp(0, gw - 1)], ys[row.clamp(0, gh - 1)]
    matrix = torch.stack([px, py, torch.ones_like(px)], -1).double()  # (B, N, 3, 3)
    solution, info = torch.linalg.solve_ex(matrix, pd.double().unsqueeze(-1))
    solution = solution.squeeze(-1).to(d.dtype)
    # solve_ex reports exact singularity only; a near-collinear sample gives a wild plane, so test the area too.
    area = torch.linalg.det(matrix).abs()
    ok = (info == 0) & (area > 1.0) & (count.view(-1, 1) >= 1) & seen.all(-1) & torch.isfinite(solution).all(-1)
    return torch.where(ok.unsqueeze(-1), solution, math.nan)
