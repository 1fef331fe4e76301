"""Per-pair take / put over nested results, against building the expected result pair by pair."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch

from svs_torch.core.pair_trees import put_pairs, take_pairs


class Inner(NamedTuple):
    values: torch.Tensor
    count: int


@dataclass(frozen=True)
class Outer:
    maps: torch.Tensor
    inner: Inner
    names: tuple[str, ...]
    shared: torch.Tensor  # not per pair (its first dimension is not the batch's): left alone


def _outer(batch: int, offset: float) -> Outer:
    return Outer(maps=torch.arange(batch * 6, dtype=torch.float32).view(batch, 1, 2, 3) + offset,
                 inner=Inner(torch.arange(batch * 2).view(batch, 2) + int(offset), 7),
                 names=tuple(f"p{i}" for i in range(batch)), shared=torch.zeros(3))


def test_take_then_put_matches_a_pair_by_pair_rebuild():
    whole, other = _outer(5, 0.0), _outer(5, 100.0)
    index = torch.tensor([3, 1])
    part = take_pairs(other, index, 5)
    assert part.names == ("p3", "p1") and part.inner.count == 7 and torch.equal(part.shared, torch.zeros(3))
    assert torch.equal(part.maps, other.maps[[3, 1]])
    merged = put_pairs(whole, index, part, 5)
    for i in range(5):
        source = other if i in (1, 3) else whole
        assert torch.equal(merged.maps[i], source.maps[i]) and torch.equal(merged.inner.values[i],
                                                                           source.inner.values[i])
    assert torch.equal(whole.maps, _outer(5, 0.0).maps)  # the original is not modified


def test_taking_every_pair_in_order_is_the_tree_itself():
    """Every pair in order (a second pass on a one-pair batch, as guide runs it) takes the tree as it is, no copy;
    any other index, even every pair in another order, takes copies."""
    whole = _outer(3, 0.0)
    assert take_pairs(whole, torch.arange(3), 3) is whole
    one = _outer(1, 0.0)
    assert take_pairs(one, torch.tensor([0]), 1) is one
    shuffled = take_pairs(whole, torch.tensor([2, 1, 0]), 3)
    assert shuffled is not whole and torch.equal(shuffled.maps, whole.maps.flip(0))
    part = take_pairs(whole, torch.tensor([0, 1]), 3)
    assert part.maps.data_ptr() != whole.maps.data_ptr()


def test_putting_every_pair_in_order_takes_the_parts_leaves_as_a_copy_would_give_them():
    """Every pair in order (a second pass kept for a one-pair batch, as guide runs it) gives ``part``'s per-pair
    leaves themselves, equal to what writing them into copies gives; ``tree``'s other leaves stay; a leaf of
    another shape is still broadcast into a copy of ``tree``'s; ``tree`` is never written to."""
    whole, other = _outer(2, 0.0), _outer(2, 100.0)
    merged = put_pairs(whole, torch.arange(2), other, 2)
    assert merged.maps is other.maps and merged.inner.values is other.inner.values
    assert merged.names == other.names and merged.shared is whole.shared and merged.inner.count == 7
    reference = put_pairs(whole, torch.tensor([1, 0]), take_pairs(other, torch.tensor([1, 0]), 2), 2)
    assert torch.equal(merged.maps, reference.maps) and torch.equal(merged.inner.values, reference.inner.values)
    narrow = Outer(other.maps, Inner(other.inner.values[:, :1], 7), other.names, other.shared)
    written = put_pairs(whole, torch.arange(2), narrow, 2)
    assert written.inner.values.shape == (2, 2)
    assert torch.equal(written.inner.values, other.inner.values[:, :1].expand(2, 2))
    fresh = _outer(2, 0.0)
    assert torch.equal(whole.maps, fresh.maps) and torch.equal(whole.inner.values, fresh.inner.values)
