"""Padding is never data: a batch of pairs of different sizes is run as groups of one size, each cropped to its
own ``image_hw``, and the groups' results are put back in batch order, padded to the batch's tensor size.

Why: a pair padded to the batch's largest size would bring its black border into every stage that looks past
its own pixels — Otsu's histogram, the opening at the border, SURF's box filters and border margins, the dense
stage's working resolution — and its result would depend on which other pairs share its batch (issue 29: Teddy's
per-object accuracy 97.3 % alone, 49.8 % batched with larger scenes). Cropping each group to its own size gives
every pair exactly the pixels it has when run alone, so a pair's result does not depend on the batch; within a
group every stage is batched as before, and a list of pairs of one size (e.g. ``--size 320x240``) is one group.

The merge pads every tensor of a group's result to the largest shape over the groups (spatial maps to the
batch's ``(H, W)``) with the neutral value of its kind (0, False, −1 for indices and kept labels), so the merged
result has the shapes a single batched run would have.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import TypeVar

import torch
import torch.nn.functional as F

from .pair_trees import take_pairs
from .types import StereoBatch

__all__ = ["size_groups", "same_size_indices", "crop_batch", "merge_groups", "replace_pairs", "run_by_size"]

T = TypeVar("T")

#: Integer fields whose padding means "none" rather than 0: match indices (−1 unmatched) and kept region labels
#: (−1 where an image has fewer regions).
_NONE_IS_MINUS_ONE = frozenset({"idx", "kept_labels"})


def size_groups(image_hw: torch.Tensor) -> list[tuple[torch.Tensor, tuple[int, int]]]:
    """The pairs of each distinct ``(height, width)``, in order of first appearance: a list of (int64 indices of
    the pairs, (height, width)). ``image_hw``: ``(B, 2)`` int64."""
    return [(torch.tensor(indices, dtype=torch.int64, device=image_hw.device), hw)
            for indices, hw in same_size_indices(image_hw.tolist())]


def same_size_indices(sizes_hw: Sequence[Sequence[int]], max_pixels: int | None = None
                      ) -> list[tuple[list[int], tuple[int, int]]]:
    """The positions of each distinct ``(height, width)`` among ``sizes_hw``, in order of first appearance; with
    ``max_pixels``, each size's positions cut into consecutive runs of at most that many left-view pixels (at least
    one pair a run).

    The command line batches listed pairs by it (``estimate --pairs``, ``eval``): pairs of one size are one batch,
    never padded to another's size. Why: the pipeline runs each size alone anyway, but the padded batch and the
    result merged back to its size cost (largest height) x (largest width) a pair; an 8000 x 10 and a 10 x 8000
    pair in one list took 7.9 GB and 28 s (0.3 GB and 0.6 s alone), and ended the run in a smaller memory.
    Why ``max_pixels`` (the pipeline's chunk): the pipeline runs a larger batch in chunks anyway, but returns one
    result merged over all of them, its maps and masks held until every pair is reported: four 3000 x 2000 pairs
    in one ``--batch-size`` took 2.9 GB, 1.7 GB more than one, and a batch of eight 12-megapixel camera frames
    would take about 10 GB (an audit)."""
    order: dict[tuple[int, int], list[int]] = {}
    for index, hw in enumerate(sizes_hw):
        order.setdefault((int(hw[0]), int(hw[1])), []).append(index)
    runs = []
    for hw, indices in order.items():
        step = _chunk_pairs(hw, max_pixels)
        runs += [(indices[start:start + step], hw) for start in range(0, len(indices), step)]
    return runs


def crop_batch(batch: StereoBatch, height: int, width: int) -> StereoBatch:
    """The batch's spatial tensors cut to ``height × width`` at the top left (where each pair sits when padded);
    calibration, ``image_hw`` and names unchanged. Views, not copies."""
    if batch.size_hw == (height, width):
        return batch
    fields = {}
    for field in dataclasses.fields(batch):
        value = getattr(batch, field.name)
        if isinstance(value, torch.Tensor) and value.dim() == 4:
            value = value[..., :height, :width]
        fields[field.name] = value
    return StereoBatch(**fields)


def _fill_value(name: str, tensor: torch.Tensor) -> float | bool | int:
    if tensor.dtype == torch.bool:
        return False
    if not tensor.dtype.is_floating_point and name in _NONE_IS_MINUS_ONE:
        return -1
    return 0


def _merge_tensors(name: str, parts: list[torch.Tensor], order: torch.Tensor | None, size_hw: tuple[int, int],
                   group_hw: list[tuple[int, int]]) -> torch.Tensor:
    ndim = parts[0].dim()
    target = [max(part.shape[d] for part in parts) for d in range(ndim)]
    spatial = ndim == 4 and all(tuple(part.shape[-2:]) == hw for part, hw in zip(parts, group_hw))
    if spatial:
        target[-2:] = size_hw
    padded = []
    for part in parts:
        pad: list[int] = []
        for d in reversed(range(1, ndim)):
            pad += [0, target[d] - part.shape[d]]
        if any(pad):
            part = F.pad(part, pad, value=_fill_value(name, part))
        padded.append(part)
    # Rows come out group by group; ``order`` sends each back to its place in the batch (chunks of one size group
    # come out in batch order already: one copy, not two).
    merged = torch.cat(padded)
    return merged if order is None else merged.index_select(0, order)


def _merge(name: str, parts: list, order: torch.Tensor | None, size_hw: tuple[int, int],
           group_hw: list[tuple[int, int]], memo: dict):
    """``parts`` (one result leaf of each group) merged; ``memo`` keeps a tensor that every group's result holds in
    several places (a segmentation's one mask as its binary, opened and kept masks) one merged tensor, as each
    group's result had it: merged once, not once per place."""
    first = parts[0]
    if isinstance(first, torch.Tensor):
        if first.dim() == 0:
            return first
        key = (tuple(id(part) for part in parts), _fill_value(name, first))  # the parts live until the merge ends
        if key not in memo:
            memo[key] = _merge_tensors(name, parts, order, size_hw, group_hw)
        return memo[key]
    if first is None:
        return None

    def merged(child: str, items: list):
        return _merge(child, items, order, size_hw, group_hw, memo)

    if dataclasses.is_dataclass(first):
        return type(first)(**{f.name: merged(f.name, [getattr(p, f.name) for p in parts])
                              for f in dataclasses.fields(first) if f.init})
    if isinstance(first, tuple) and hasattr(first, "_fields"):  # a NamedTuple of tensors (e.g. MatchedPoints)
        return type(first)(*(merged(f, [getattr(p, f) for p in parts]) for f in first._fields))
    if isinstance(first, (tuple, list)) and first and not isinstance(first[0], str):
        return type(first)(merged(name, list(items)) for items in zip(*parts))
    if isinstance(first, dict):  # stage timings: the batch's time is the groups' sum
        return {key: sum(p[key] for p in parts) for key in first}
    if isinstance(first, bool) or not isinstance(first, (int, float)):
        return first  # settings shared by every group (the range rule's name, flags)
    return max(parts)  # a batch-wide size, e.g. the dense stage's largest disparity count


def merge_groups(results: list[T], indices: list[torch.Tensor], size_hw: tuple[int, int],
                 group_hw: list[tuple[int, int]]) -> T:
    """One result for the whole batch from the results of its size groups (``indices[g]``: the batch rows of group
    ``g``; ``group_hw[g]``: its size). Tensors are padded as the module docstring says and put back in batch order;
    nested dataclasses are merged field by field."""
    rows = torch.cat(indices)
    order = torch.empty(len(rows), dtype=torch.int64, device=rows.device)
    order[rows] = torch.arange(len(order), device=order.device)
    in_order = bool((order == torch.arange(len(order), device=order.device)).all())
    return _merge("", results, None if in_order else order, size_hw, group_hw, {})


def replace_pairs(tree: T, index: torch.Tensor, part: T, num_pairs: int, size_hw: tuple[int, int]) -> T:
    """``tree`` (the result of ``num_pairs`` pairs filling ``size_hw``) with its pairs ``index`` replaced by
    ``part``'s, in that order: a second pass on some pairs, whose tensors may differ from the first's in their
    other dimensions (keypoints, regions), so both are padded as :func:`merge_groups` pads."""
    rest = torch.ones(num_pairs, dtype=torch.bool, device=index.device).index_fill(0, index, False)
    rest = rest.nonzero().flatten()
    if len(rest) == 0:
        return part
    return merge_groups([take_pairs(tree, rest, num_pairs), part], [rest, index], size_hw, [size_hw] * 2)


def run_by_size(batch: StereoBatch, run: Callable[[StereoBatch], T], max_pixels: int | None = None) -> T:
    """``run(batch)``, where each size group of the batch is run alone, cropped to its own size, and the results are
    merged back in batch order. A batch whose pairs all fill its tensors is one call, with nothing copied.

    ``max_pixels``: the most left-view pixels one call gets; a larger group runs as consecutive chunks of whole
    pairs (at least one pair a chunk). Why: every stage's intermediates grow with the batch, and once they
    outgrow the CPU's caches each elementwise pass costs more per pair (on 2 cores, the same 128 pairs of
    320×240 in batches of 32: 14.8 ms a pair; in one call of 128: 17.7 ms; in chunks of 32: 16.3 ms). A pair's
    result does not depend on its batch, so chunks change nothing but the time and the peak memory."""
    groups = size_groups(batch.image_hw)
    chunked = []
    for index, hw in groups:
        step = _chunk_pairs(hw, max_pixels)
        chunked += [(index[start:start + step], hw) for start in range(0, len(index), step)]
    if len(chunked) <= 1 and all(hw == batch.size_hw for _, hw in groups):  # one call (or an empty batch)
        return run(batch)
    results, indices, group_hw = [], [], []
    for index, (height, width) in chunked:
        part = batch if len(chunked) == 1 else batch.select(index)
        results.append(run(crop_batch(part, height, width)))
        indices.append(index)
        group_hw.append((height, width))
    return merge_groups(results, indices, batch.size_hw, group_hw)


def _chunk_pairs(size_hw: tuple[int, int], max_pixels: int | None) -> int:
    """Pairs of ``size_hw`` a chunk of at most ``max_pixels`` left-view pixels holds (at least one)."""
    if max_pixels is None:
        return 1 << 62
    return max(1, max_pixels // max(1, size_hw[0] * size_hw[1]))
