"""Small numeric pieces that several stages need with gradients that stay finite."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

__all__ = ["per_pair", "safe_sqrt"]


def safe_sqrt(value: torch.Tensor) -> torch.Tensor:
    """``sqrt(value)`` where it is positive, 0 elsewhere, with the subgradient 0 there: sqrt's derivative is
    infinite at 0, and a ``torch.where`` passes 0 · inf = NaN back into every element of the batch that shares
    the backward pass (an exact fit, a flat patch, an uncovered pair). Differentiable w.r.t. ``value``."""
    positive = value > 0
    return torch.where(positive, torch.where(positive, value, 1.0).sqrt(), 0.0)


def per_pair(function: Callable[..., Any], value: torch.Tensor, *more: torch.Tensor,
             split: bool = True) -> Any:
    """``function`` (an elementwise op, or one along a dim other than 0: ``torch.sigmoid``, a softmax over dim 1) of
    ``(B, ...)``, one pair at a time: torch computes a tensor's vectorised runs and its scalar tail differently
    (a sigmoid's or an exp's values an ulp apart), and the tail falls on other elements in a batch than alone, so a
    pair's values moved with the pairs batched with it (an audit). A pair alone (B = 1) is computed as before.
    ``more``: further ``(B, ...)`` arguments of ``function``, split with ``value``; ``split=False``: the whole batch
    in one call. A ``function`` that returns a tuple of tensors gets each concatenated. Differentiable as ``function``
    is."""
    if not split or value.dim() == 0 or value.shape[0] <= 1:
        return function(value, *more)
    parts = [function(*pair) for pair in zip(value.split(1), *(m.split(1) for m in more))]
    return tuple(map(torch.cat, zip(*parts))) if isinstance(parts[0], tuple) else torch.cat(parts)
