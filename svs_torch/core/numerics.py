"""Small numeric pieces that several stages need with gradients that stay finite."""

from __future__ import annotations

import torch

__all__ = ["safe_sqrt"]


def safe_sqrt(value: torch.Tensor) -> torch.Tensor:
    """``sqrt(value)`` where it is positive, 0 elsewhere, with the subgradient 0 there: sqrt's derivative is
    infinite at 0, and a ``torch.where`` passes 0 · inf = NaN back into every element of the batch that shares
    the backward pass (an exact fit, a flat patch, an uncovered pair). Differentiable w.r.t. ``value``."""
    positive = value > 0
    return torch.where(positive, torch.where(positive, value, 1.0).sqrt(), 0.0)
