"""any_along: torch's ``any`` over a dimension of a bool mask, the same answer by a byte maximum."""

from __future__ import annotations

import pytest
import torch

from svs_torch.core.mask_reductions import any_along


@pytest.mark.parametrize("dim", [0, 1, -1, -2])
@pytest.mark.parametrize("keepdim", [False, True])
def test_any_along_equals_torch_any(generator, dim, keepdim):
    """Sparse, dense, all-False and all-True masks, contiguous or not."""
    mask = torch.rand(4, 3, 9, 11, generator=generator) > 0.97
    mask[1] = False
    mask[2, 0] = True
    for case in (mask, mask.transpose(-1, -2), mask[:, :, ::2, 1:]):
        found = any_along(case, dim, keepdim)
        assert found.dtype == torch.bool
        assert torch.equal(found, case.any(dim=dim, keepdim=keepdim))
        assert torch.equal(found.view(torch.uint8), case.any(dim=dim, keepdim=keepdim).view(torch.uint8))


def test_any_along_empty_and_other_dtypes():
    """An empty dimension is False everywhere (``amax`` alone would refuse it); a non-bool tensor gets torch's
    ``any``."""
    assert torch.equal(any_along(torch.zeros(2, 0, 3, dtype=torch.bool), 1), torch.zeros(2, 3, dtype=torch.bool))
    assert any_along(torch.zeros(0, 4, dtype=torch.bool), 1).shape == (0,)
    values = torch.tensor([[0.0, 2.0], [0.0, 0.0]])
    assert torch.equal(any_along(values, 1), torch.tensor([True, False]))
