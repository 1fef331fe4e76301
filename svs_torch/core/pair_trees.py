"""Per-pair selection in nested results: the pairs of a batch's result (dataclasses, named tuples and tuples of
tensors whose first dimension is the pair) taken out, or put back after a second pass on some pairs."""

from __future__ import annotations

import dataclasses

import torch

__all__ = ["map_pairs", "put_pairs", "take_pairs"]


def map_pairs(fn, num_pairs: int, *trees):
    """Apply ``fn`` to the per-pair leaves of nested dataclasses / tuples (tensors whose first dimension is the
    pair, and tuples of names, one per pair); every other leaf is taken from the first tree."""
    first = trees[0]
    if isinstance(first, torch.Tensor):
        return fn(*trees) if first.dim() >= 1 and first.shape[0] == num_pairs else first
    if dataclasses.is_dataclass(first) and not isinstance(first, type):
        return dataclasses.replace(first, **{f.name: map_pairs(fn, num_pairs, *(getattr(t, f.name) for t in trees))
                                             for f in dataclasses.fields(first) if f.init})
    if isinstance(first, tuple) and first and all(isinstance(v, str) for v in first) and len(first) == num_pairs:
        return tuple(fn(*(list(t) for t in trees)))
    if isinstance(first, tuple):
        parts = [map_pairs(fn, num_pairs, *items) for items in zip(*trees)]
        return type(first)(*parts) if hasattr(first, "_fields") else tuple(parts)
    return first


def _every_pair(index: torch.Tensor, num_pairs: int) -> bool:
    """Whether ``index`` ``(b,)`` is every pair of ``num_pairs`` in order."""
    return len(index) == num_pairs and bool((index == torch.arange(num_pairs, device=index.device)).all())


def take_pairs(tree, index: torch.Tensor, num_pairs: int):
    """The pairs ``index`` ``(b,)`` of a nested result (see :func:`map_pairs`): ``tree`` itself, not a copy, where
    ``index`` is every pair in order (a second pass on a batch of one pair, as ``guide`` runs it: copying the
    result's tree leaf by leaf cost about 3 ms a frame on the frames that take three such passes)."""
    if _every_pair(index, num_pairs):
        return tree
    return map_pairs(lambda t: t[index] if isinstance(t, torch.Tensor) else [t[i] for i in index.tolist()],
                     num_pairs, tree)


def put_pairs(tree, index: torch.Tensor, part, num_pairs: int):
    """``tree`` with its pairs ``index`` replaced by ``part``'s (same order): where ``index`` is every pair in
    order (a second pass kept for a batch of one pair, as ``guide`` runs it), ``part``'s per-pair leaves
    themselves, not copies written into clones of ``tree``'s (a coarse retry's result, kept: 0.23 → 0.09 ms)."""
    def copied(whole, piece):
        if isinstance(whole, list):  # names
            for j, i in enumerate(index.tolist()):
                whole[i] = piece[j]
            return whole
        whole = whole.clone()
        whole[index] = piece
        return whole

    def shared(whole, piece):  # a leaf of another shape or dtype is written as before (broadcast, or refused)
        same = isinstance(whole, list) or (piece.shape == whole.shape and piece.dtype == whole.dtype)
        return piece if same else copied(whole, piece)

    return map_pairs(shared if _every_pair(index, num_pairs) else copied, num_pairs, tree, part)
