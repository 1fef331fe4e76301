"""The hard pipeline's inference mode kept invisible: results and cached tables hold ordinary tensors."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from test_pair_trees import Inner  # a named tuple of a tensor and a count

from svs_torch.core.inference import outside_inference_mode, plain_tensors


@dataclass(frozen=True)
class Outer:
    maps: torch.Tensor
    inner: Inner
    parts: list
    named: dict
    kept: torch.Tensor


def test_plain_tensors_copies_inference_tensors_only_and_keeps_their_values():
    ordinary = torch.arange(3.0)
    with torch.inference_mode():
        tree = Outer(maps=torch.ones(2, 3) * 2, inner=Inner(torch.arange(4), 7), parts=[torch.zeros(2), "name"],
                     named={"a": torch.full((1,), 5.0)}, kept=ordinary)
    assert tree.maps.is_inference() and tree.inner.values.is_inference()
    plain = plain_tensors(tree)
    leaves = [plain.maps, plain.inner.values, plain.parts[0], plain.named["a"], plain.kept]
    assert not any(leaf.is_inference() for leaf in leaves)
    assert plain.kept is ordinary and plain.inner.count == 7 and plain.parts[1] == "name"
    assert torch.equal(plain.maps, torch.full((2, 3), 2.0)) and torch.equal(plain.inner.values, torch.arange(4))
    plain.maps[0, 0] = 9.0  # an inference tensor refuses in-place changes outside inference mode
    weight = torch.ones(2, 3, requires_grad=True)
    (weight * plain.maps).sum().backward()  # and being saved for backward
    assert torch.equal(weight.grad, plain.maps)


def test_a_tensor_held_twice_is_copied_once_and_stays_shared():
    """A result's ``object_labels`` is its segmentation's labels where no region was cut: one copy, one tensor."""
    with torch.inference_mode():
        labels = torch.arange(6).view(2, 3)
        tree = Outer(maps=labels, inner=Inner(labels, 1), parts=[labels], named={}, kept=torch.zeros(1))
    plain = plain_tensors(tree)
    assert not plain.maps.is_inference() and plain.inner.values is plain.maps and plain.parts[0] is plain.maps
    assert not plain.kept.is_inference() and plain.kept is not plain.maps


def test_a_tree_without_inference_tensors_is_returned_as_is():
    tree = Outer(maps=torch.ones(1), inner=Inner(torch.ones(1), 1), parts=[], named={}, kept=torch.ones(1))
    assert plain_tensors(tree).maps is tree.maps and plain_tensors(tree).inner is tree.inner


def test_outside_inference_mode_makes_ordinary_tensors_inside_it():
    @outside_inference_mode
    def table() -> torch.Tensor:
        return torch.eye(3)

    with torch.inference_mode():
        made = table()
        assert torch.is_inference_mode_enabled()  # restored after the call
    assert not made.is_inference()
