"""Optional ``torch.compile`` for the memory-bound kernels (box-filter Hessian, maxima, descriptor arithmetic).

Eager torch pays one memory pass per elementwise op; inductor fuses a chain into one pass. Compiled and eager
paths compute the same values; the eager one stays the default and the reference.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

__all__ = ["maybe_compiled"]

_CACHE: dict[Callable, Callable] = {}


def maybe_compiled(function: Callable, compiled: bool) -> Callable:
    """``function`` itself, or its ``torch.compile(dynamic=True)`` version, compiled once per process (inductor
    also keeps its code on disk, so a later process reuses it)."""
    if not compiled:
        return function
    if function not in _CACHE:
        _CACHE[function] = torch.compile(function, dynamic=True)
    return _CACHE[function]
