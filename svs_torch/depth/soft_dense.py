"""The differentiable variant of the block matching: a soft-argmin over the same cost volume.
"""

from __future__ import annotations

import torch

from ..core.checks import InputError
from .block_matching import _check_pair, _check_range
from .cost_volume import _cost_volume, _prefilter
from .dense_config import DenseConfig

__all__ = ["soft_block_match"]


def soft_block_match(left: torch.Tensor, right: torch.Tensor, min_disparity_px: torch.Tensor | int,
                     num_disparities: int, temperature: float, config: DenseConfig = DenseConfig()) -> torch.Tensor:
    """Differentiable dense disparity ``(B, 1, H, W)``: the soft-argmin ``Σ_d d · softmax(−C(d) / T)`` over the
    SAD cost volume of :func:`block_match_sad` (costs as window means, so ``temperature`` is in intensity units
    of the pre-filtered images). As ``temperature → 0`` it tends to the winner-takes-all disparity (without the
    rejections and sub-pixel fit). Candidates whose right pixel leaves the image get no weight; a pixel with none
    at all gets ``min_disparity_px``.

    Gradients flow to both images (through the pre-filter, the absolute differences and the softmax) and are
    defined wherever no difference is exactly zero.
    """
    b = _check_pair(left, right, config)
    minimum = _check_range(min_disparity_px, num_disparities, b, left.device)
    if not temperature > 0:
        raise InputError(f"temperature: expected a positive number, got {temperature!r}")
    h, w = left.shape[-2:]
    zeros = torch.zeros(b, dtype=torch.int64, device=left.device)
    costs, inside, _ = _cost_volume(_prefilter(left, config), _prefilter(right, config), zeros, zeros, h, w,
                                    minimum, num_disparities, torch.full((b,), w, device=left.device), config)
    costs = costs / config.window_size ** 2
    logits = torch.where(inside, -costs / temperature, torch.full_like(costs, -torch.inf))
    any_inside = inside.any(dim=1)  # (B, 1, w)
    logits = torch.where(any_inside.unsqueeze(1), logits, torch.zeros_like(logits))
    weights = torch.softmax(logits, dim=1)
    values = (minimum.view(-1, 1) + torch.arange(num_disparities, device=left.device)).to(costs.dtype)
    expected = (weights * values.view(b, num_disparities, 1, 1)).sum(dim=1, keepdim=True)  # b may be 0
    return torch.where(any_inside.unsqueeze(1), expected, values[:, :1].view(b, 1, 1, 1).expand_as(expected))
