"""Block averages and block ORs at an integer factor, bit for bit ``avg_pool2d`` and a max-pool, faster: the
dense stage's working resolution and its coarse search.
"""

from __future__ import annotations

import torch

from ..core.checks import InputError

__all__ = ["mean_pool", "reduction_factor"]


def _block_slices(images: torch.Tensor, factor: int) -> list[torch.Tensor]:
    """The ``factor²`` strided slices of ``images`` ``(..., H, W)`` (cut to whole blocks), one per offset of a
    ``factor × factor`` block, in row-major order: a block's pixels are the same place of every slice."""
    if isinstance(factor, bool) or not isinstance(factor, int) or not 1 <= factor <= min(images.shape[-2:]):
        # factor² slices: a factor of 3000 on a 4x4 image took 49 s and 3.6 GB before failing
        raise InputError(f"factor: expected an int from 1 to the images' smaller side "
                         f"{min(images.shape[-2:])}, got {factor!r}")
    height, width = images.shape[-2] // factor * factor, images.shape[-1] // factor * factor
    images = images[..., :height, :width]
    return [images[..., i::factor, j::factor] for i in range(factor) for j in range(factor)]


def mean_pool(images: torch.Tensor, factor: int) -> torch.Tensor:
    """``F.avg_pool2d(images, factor)`` bit for bit (the same float sums in the same row-major order, then one
    division), from the block slices: on this CPU 4–5× faster than ``avg_pool2d`` at factor 2. Differentiable
    w.r.t. ``images`` (linear; rows and columns past the last whole block get zero gradient)."""
    first, *rest = _block_slices(images, factor)
    total = first
    for part in rest:
        total = total + part
    return total / (factor * factor)


def _any_pool(mask: torch.Tensor, factor: int) -> torch.Tensor:
    """``F.max_pool2d(mask.float(), factor) > 0`` for a bool mask: whether any pixel of each block is set, by
    OR-ing the block slices as bytes (on this CPU 20× faster than max-pooling a float copy). The OR of 0/1
    bytes is 0 or 1, a bool's own bytes: viewed as bool, not converted (as :func:`any_along` does)."""
    first, *rest = _block_slices(mask.view(torch.uint8), factor)
    found = first
    for part in rest:
        found = found | part
    return found.view(torch.bool)


def reduction_factor(width_px: int, target_width_px: float, height_px: int | None = None) -> int:
    """The integer factor that reduces images ``width_px`` wide to about ``target_width_px``: at least 1, and at
    most ``height_px`` when given, so that a strip a few rows high keeps a row (it was reduced to none)."""
    factor = max(1, round(width_px / target_width_px))
    return factor if height_px is None else max(1, min(factor, height_px))
