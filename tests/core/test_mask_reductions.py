"""any_along, all_along, any_true, all_true, count_along, has_nan: torch's ``any``, ``all``, ``sum`` and NaN test of a
mask or values, the same answers by a byte maximum, minimum or sum, or one maximum."""

from __future__ import annotations

import pytest
import torch

from svs_torch.core.mask_reductions import all_along, all_true, any_along, any_true, count_along, has_nan


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


@pytest.mark.parametrize("dim", [0, 1, -1, (1, 2), (2, 3)])
@pytest.mark.parametrize("keepdim", [False, True])
def test_count_along_equals_torch_sum(generator, dim, keepdim):
    """Bytes summed into int32: the int64 counts of ``sum``, contiguous or not, all-False, all-True, an empty
    dimension; a non-bool tensor takes torch's ``sum``."""
    mask = torch.rand(4, 3, 9, 11, generator=generator) > 0.4
    mask[1] = False
    mask[2] = True
    for case in (mask, mask.transpose(-1, -2), mask[:, :, ::2, 1:], torch.zeros(4, 0, 9, 11, dtype=torch.bool)):
        found = count_along(case, dim, keepdim)
        assert found.dtype == torch.int64 and torch.equal(found, case.sum(dim=dim, keepdim=keepdim))
    values = torch.tensor([[0.5, 2.0], [1.0, 0.0]])
    assert torch.equal(count_along(values, 1), values.sum(1))


@pytest.mark.parametrize("dim", [0, 1, -1])
def test_all_along_equals_torch_all(generator, dim):
    mask = torch.rand(4, 3, 9, 11, generator=generator) > 0.03
    mask[1] = True
    for case in (mask, mask.transpose(-1, -2), mask[:, :, ::2, 1:]):
        found = all_along(case, dim)
        assert found.dtype == torch.bool and torch.equal(found, case.all(dim=dim))
    assert torch.equal(all_along(torch.zeros(2, 0, 3, dtype=torch.bool), 1), torch.ones(2, 3, dtype=torch.bool))


def test_whole_mask_tests_equal_torchs(generator):
    """Whole masks, contiguous or not, all-False, all-True, one pixel, empty; other dtypes take torch's test."""
    mask = torch.zeros(2, 1, 24, 32, dtype=torch.bool)
    cases = [mask, ~mask, torch.rand(2, 1, 24, 32, generator=generator) > 0.5, mask[..., ::3, 1:],
             torch.zeros(0, 5, dtype=torch.bool), (~mask).transpose(-1, -2)]
    one = mask.clone()
    one[1, 0, 23, 31] = True
    cases.append(one)
    for case in cases:
        assert any_true(case) is bool(case.any()) and all_true(case) is bool(case.all())
    assert any_true(torch.tensor([0, 2])) and not all_true(torch.tensor([0, 2]))


def test_has_nan_equals_isnan_any():
    nan, inf = float("nan"), float("inf")
    for values in (torch.tensor([1.0, nan, 3.0]), torch.tensor([inf, -inf, 0.0]), torch.full((3, 4), nan)[:, ::2],
                   torch.zeros(0), torch.tensor([[0.0, 1.0], [nan, 2.0]]).t(), torch.tensor([1, 2]),
                   torch.tensor([-inf, nan], dtype=torch.float64)):
        assert has_nan(values) is bool(values.isnan().any())
