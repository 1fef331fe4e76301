"""The dense stage's SAD cost volume (svs_torch.depth.cost_volume._costs_in_cache, the volume the semi-global
aggregation of noisy pairs reads whole): the C kernel (svs_torch.depth.kernels.sad_volume) against the torch loop
bit for bit, both against window sums by numpy, and the crops the kernel leaves to the torch loop."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from svs_torch.core.errors import InputError
from svs_torch.depth import kernels
from svs_torch.depth.cost_volume import _costs_in_cache

pytestmark = pytest.mark.skipif(not kernels.available("sad_volume"), reason="no C compiler")


def _crops(generator: torch.Generator, b: int, d: int, h: int, w: int, k: int, high: int = 255
           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Whole levels in [-high, high] (the matched x-Sobel levels), and a random ``outside`` mask."""
    left = torch.randint(-high, high + 1, (b, 1, h + k - 1, w + k - 1), generator=generator).float()
    right = torch.randint(-high, high + 1, (b, 1, h + k - 1, w + k - 1 + d - 1), generator=generator).float()
    return left, right, torch.rand(b, d, 1, w, generator=generator) < 0.3


def _numpy_volume(left: torch.Tensor, right: torch.Tensor, d: int, h: int, w: int, k: int) -> np.ndarray:
    """costs[b, j, y, x] = the K x K window sum of |left - right shifted by D - 1 - j|, by numpy's window views."""
    l, r = left[:, 0].double().numpy(), right[:, 0].double().numpy()
    out = np.empty((l.shape[0], d, h, w))
    for j in range(d):
        start = d - 1 - j
        diff = np.abs(l - r[:, :, start:start + w + k - 1])
        out[:, j] = np.lib.stride_tricks.sliding_window_view(diff, (k, k), axis=(1, 2)).sum(axis=(-1, -2))
    return out


@pytest.mark.parametrize("b, d, h, w, k", [(1, 64, 70, 90, 9), (3, 17, 40, 33, 5), (2, 1, 1, 1, 1), (2, 5, 70, 3, 7),
                                           (1, 3, 33, 65, 3)])
def test_kernel_is_bit_identical_to_the_torch_loop(generator, b, d, h, w, k):
    left, right, outside = _crops(generator, b, d, h, w, k)
    for mask in (None, outside):
        fused = _costs_in_cache(left, right, h, w, d, k, mask, compiled=True)
        eager = _costs_in_cache(left, right, h, w, d, k, mask, compiled=False)
        assert torch.equal(fused[0], eager[0])
        if mask is None:
            assert fused[1] is None and eager[1] is None
            np.testing.assert_array_equal(fused[0].double().numpy(), _numpy_volume(left, right, d, h, w, k))
        else:
            assert torch.equal(fused[1][0], eager[1][0]) and torch.equal(fused[1][1], eager[1][1])
            assert bool(fused[0].masked_select(mask.expand(-1, -1, h, -1)).isinf().all())


def test_ties_take_the_first_disparity(generator):
    """Levels 0 / 1 make many equal costs: the winner is the first index, as ``min(dim=1)`` and the torch loop."""
    left, right, outside = _crops(generator, 2, 20, 30, 40, 3, high=1)
    fused = _costs_in_cache(left, right, 30, 40, 20, 3, outside, compiled=True)
    eager = _costs_in_cache(left, right, 30, 40, 20, 3, outside, compiled=False)
    assert torch.equal(fused[1][1], eager[1][1])
    assert torch.equal(fused[1][1], fused[0].min(dim=1).indices)


@pytest.mark.parametrize("spoil", ["fraction", "nan", "inf", "huge"])
def test_crops_the_kernel_cannot_sum_exactly_go_to_the_torch_loop(generator, spoil):
    """Window sums are exact in float32 only for whole numbers below 2**24: other crops are the torch loop's."""
    left, right, outside = _crops(generator, 1, 6, 12, 14, 3)
    left[0, 0, 4, 5] = {"fraction": 0.5, "nan": math.nan, "inf": math.inf, "huge": 2.0**23}[spoil]
    assert kernels.sad_volume(left[:, 0], right[:, 0], 12, 14, 3, outside) is None
    fused = _costs_in_cache(left, right, 12, 14, 6, 3, outside, compiled=True)
    eager = _costs_in_cache(left, right, 12, 14, 6, 3, outside, compiled=False)
    torch.testing.assert_close(fused[0], eager[0], equal_nan=True, rtol=0, atol=0)
    assert torch.equal(fused[1][1], eager[1][1])


def test_wrapper_refuses_crops_of_another_size():
    with pytest.raises(InputError, match=r"^left: expected"):
        kernels.sad_volume(torch.rand(1, 5, 6), torch.rand(1, 5, 9), 4, 5, 3, None)
    with pytest.raises(InputError, match=r"^right: expected \(B, 6, 6 \+ D - 1\)"):
        kernels.sad_volume(torch.rand(1, 6, 6), torch.rand(1, 6, 5), 4, 4, 3, None)
    with pytest.raises(InputError, match=r"^outside: expected"):
        kernels.sad_volume(torch.rand(1, 6, 6), torch.rand(1, 6, 8), 4, 4, 3, torch.zeros(1, 2, 1, 5, dtype=torch.bool))
