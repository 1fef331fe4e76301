"""Small numeric pieces that several stages need with gradients that stay finite."""

from __future__ import annotations

import torch

__all__ = ["safe_sqrt", "sigmoid_per_pair"]


def safe_sqrt(value: torch.Tensor) -> torch.Tensor:
    """``sqrt(value)`` where it is positive, 0 elsewhere, with the subgradient 0 there: sqrt's derivative is
    infinite at 0, and a ``torch.where`` passes 0 · inf = NaN back into every element of the batch that shares
    the backward pass (an exact fit, a flat patch, an uncovered pair). Differentiable w.r.t. ``value``."""
    positive = value > 0
    return torch.where(positive, torch.where(positive, value, 1.0).sqrt(), 0.0)


def sigmoid_per_pair(value: torch.Tensor) -> torch.Tensor:
    """``torch.sigmoid`` of ``(B, ...)``, one pair at a time: torch computes a tensor's vectorised runs and its
    scalar tail differently (3-4 % of values an ulp apart), and the tail falls on other elements in a batch than
    alone, so a pair's values moved with the pairs batched with it (an audit). A pair alone (B = 1) is computed as
    before. Differentiable w.r.t. ``value``."""
    if value.dim() == 0 or value.shape[0] <= 1:
        return torch.sigmoid(value)
    return torch.cat([torch.sigmoid(part) for part in value.split(1)])
