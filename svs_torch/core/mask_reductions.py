"""``any`` over a dimension of a bool mask through a byte maximum.

On CPU, torch's bool reductions run a generic loop: on this project's 2-core reference machine (AMD EPYC,
torch 2.13) ``mask.any(dim=-1)`` over a batch of 8 masks of 320×240 takes 1.5 ms, ``mask.any(dim=-2)`` 0.6 ms
and ``mask.flatten(1).any(dim=1)`` 0.47 ms, against 0.12, 0.08 and 0.01 ms for ``amax`` of the same bytes
(``uint8``, vectorised). The pipeline reduces whole-frame masks several times a batch (each image's status,
the kept objects' union, the crop boxes of the dense stage). torch stores a bool as the byte 0 or 1, so the
maximum byte is that same byte of the answer, and viewing it as bool costs nothing (converting it with
``.bool()`` or ``!= 0`` would cost 0.3 ms more).

Masks carry no gradient: nothing here is differentiable.
"""

from __future__ import annotations

import torch

__all__ = ["any_along"]


def any_along(mask: torch.Tensor, dim: int, keepdim: bool = False) -> torch.Tensor:
    """``mask.any(dim=dim, keepdim=keepdim)`` for a bool ``mask``, as the maximum of its bytes (see the
    module's note); an empty ``dim`` gives False as ``any`` does (``amax`` refuses it)."""
    if mask.dtype != torch.bool or mask.shape[dim] == 0:
        return mask.any(dim=dim, keepdim=keepdim)
    return mask.view(torch.uint8).amax(dim=dim, keepdim=keepdim).view(torch.bool)
