"""The hard pipeline under ``torch.inference_mode``, and what keeps that invisible to its callers.

Why: at one pair a call (``guide``'s case) the pipeline is about 4 800 small torch operations, and their dispatch,
not their arithmetic, is most of its time. Inference mode skips the autograd and version-counter bookkeeping every
operation pays under ``no_grad``: one pair a call 33.5 → 31.1 ms on this project's 2-core machine (the two in turn,
medians of 60, the copy below included), the same values bit for bit (tensors made there are the same numbers, only
flagged; ``experiments/fixed_list_check.py``).

Tensors made in inference mode are "inference tensors": outside it they cannot be changed in place nor saved for
backward, so a caller that trains a segmenter against a hard result, or edits one, would fail far from the cause.
So nothing made there is handed out as is: :func:`plain_tensors` copies a result's inference tensors to ordinary
ones before it is returned, and tensors a process keeps between calls (cached tables, loaded networks) are made
outside inference mode even when first asked for inside it (:func:`outside_inference_mode`). A caller that is in
inference mode itself (``guide``'s loop, ``estimate --pairs``' chunks: they read the result and drop it) gets the
inference tensors as they are: the copy cost 1 ms a 320×240 pair at B = 1, 2 % of ``guide``'s frame.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import TypeVar

import torch

__all__ = ["outside_inference_mode", "plain_tensors"]

T = TypeVar("T")


def outside_inference_mode(function: Callable[..., T]) -> Callable[..., T]:
    """``function`` run with inference mode off: for the makers of tensors a process keeps and reuses (under a
    cache), which a later differentiable call may save for backward."""
    @functools.wraps(function)
    def made_plainly(*args, **kwargs):
        with torch.inference_mode(False):
            return function(*args, **kwargs)

    return made_plainly


def plain_tensors(tree: T) -> T:
    """``tree`` (nested dataclasses, named tuples, tuples, lists and dicts) with every inference tensor replaced by
    an ordinary copy; ordinary tensors and every other leaf are kept as they are (not copied). A tensor the tree
    holds in several places (a result's ``object_labels`` and its segmentation's labels, where no region was cut)
    is copied once and stays one tensor."""
    with torch.inference_mode(False):  # entered once: per tensor it cost half the copy's time
        return _plain(tree, {})


def _plain(tree, copies: dict):
    if isinstance(tree, torch.Tensor):
        if not tree.is_inference():
            return tree
        if id(tree) not in copies:
            copies[id(tree)] = (tree, tree.clone())  # the original kept too: its id is not reused meanwhile
        return copies[id(tree)][1]
    if dataclasses.is_dataclass(tree) and not isinstance(tree, type):
        changed = {f.name: _plain(getattr(tree, f.name), copies) for f in dataclasses.fields(tree) if f.init}
        if all(changed[name] is getattr(tree, name) for name in changed):
            return tree
        return dataclasses.replace(tree, **changed)
    if isinstance(tree, tuple):
        parts = [_plain(item, copies) for item in tree]
        if all(new is old for new, old in zip(parts, tree)):
            return tree
        return type(tree)(*parts) if hasattr(tree, "_fields") else type(tree)(parts)
    if isinstance(tree, list):
        return [_plain(item, copies) for item in tree]
    if isinstance(tree, dict):
        return {key: _plain(value, copies) for key, value in tree.items()}
    return tree
