"""The winner's statistics of a cost volume (svs_torch.depth.winner._winner_stats_torch, read on the noisy pairs'
aggregated volume): the C kernel (svs_torch.depth.kernels.winner_statistics) against the torch operations bit for
bit, NaN and +inf included, both against plain loops, and the winners it refuses."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from svs_torch.core.errors import InputError
from svs_torch.depth import kernels
from svs_torch.depth.winner import _winner_stats_torch

pytestmark = pytest.mark.skipif(not kernels.available("winner_statistics"), reason="no C compiler")


def _volume(generator: torch.Generator, b: int, d: int, h: int, w: int) -> torch.Tensor:
    costs = (torch.rand(b, d, h, w, generator=generator) * 500).round()
    costs[torch.rand(b, d, h, w, generator=generator) < 0.15] = math.inf  # outside the image or the range
    costs[..., min(2, w - 1)] = math.inf  # a column outside the pair's region
    costs[0, :, 0, 0] = 7.0  # ties: the first index wins
    return costs


def _same(a: torch.Tensor | None, b: torch.Tensor | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return torch.equal(a.isnan(), b.isnan()) and torch.equal(a.nan_to_num(-1.0), b.nan_to_num(-1.0))


@pytest.mark.parametrize("b, d, h, w", [(1, 64, 40, 150), (3, 5, 7, 9), (2, 1, 3, 4), (1, 3, 1, 1), (2, 2, 4, 5)])
def test_kernel_is_bit_identical_to_the_torch_operations(generator, b, d, h, w):
    costs = _volume(generator, b, d, h, w)
    if b > 1:
        costs[1, :, 0, 0] = math.nan  # a NaN anywhere makes a minimum NaN, as torch.minimum's
        costs[1, 0, 0, 1] = math.nan
    minimum = costs.min(dim=1)
    for uniqueness in (False, True):
        for right in (False, True):
            fused = _winner_stats_torch(costs.clone(), minimum, uniqueness, right, compiled=True)
            eager = _winner_stats_torch(costs.clone(), minimum, uniqueness, right, compiled=False)
            assert all(_same(x, y) for x, y in zip(fused, eager))


def test_statistics_are_those_of_plain_loops(generator):
    costs = _volume(generator, 2, 9, 3, 20)
    minimum = costs.min(dim=1)
    stats = _winner_stats_torch(costs, minimum, True, True, compiled=True)
    volume, best = costs.numpy(), minimum.indices.numpy()
    d_count, width = volume.shape[1], volume.shape[-1]
    for b in range(2):
        for y in range(3):
            for x in range(width):
                k = best[b, y, x]
                assert stats.before[b, y, x] == volume[b, max(k - 1, 0), y, x]
                assert stats.after[b, y, x] == volume[b, min(k + 1, d_count - 1), y, x]
                far = [volume[b, d, y, x] for d in range(d_count) if abs(d - k) > 1]
                assert stats.rival[b, y, x] == (min(far) if far else np.inf)
                right = [volume[b, d, y, x + d] if x + d < width else np.inf for d in range(d_count)]
                expected = int(np.argmin(right)) if np.isfinite(min(right)) else -1
                assert stats.right_best[b, y, x] == expected


def test_winners_outside_the_volume_are_refused():
    costs = torch.rand(1, 4, 2, 3)
    with pytest.raises(InputError, match=r"^best: expected indices in \[0, 4\), got values from 0 to 4"):
        kernels.winner_statistics(costs, torch.tensor([[[0, 1, 4], [0, 0, 0]]]), True, True)
    with pytest.raises(InputError, match=r"^best: expected \(1, 2, 3\)"):
        kernels.winner_statistics(costs, torch.zeros(1, 3, 2, dtype=torch.int64), True, True)
