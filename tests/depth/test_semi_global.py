"""Semi-global aggregation of the dense stage (svs_torch.depth.semi_global, DenseConfig.smoothing_penalties):
the C kernel against the torch path, both against a plain loop of Hirschmüller's Eq. (13), batch invariance,
and what it is for: a noisy textured plane measured where plain block matching loses it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from svs_torch.core.errors import InputError
from svs_torch.depth import kernels
from svs_torch.depth.block_matching import (block_match_sad, block_match_sad_noisy_pairs, block_match_sad_with_residual,
                                           dense_disparity_over_regions)
from svs_torch.depth.dense_config import DenseConfig, DisparityRange
from svs_torch.depth.semi_global import (_scan_columns_torch, pair_residual_levels, residual_reaches,
                                         semi_global_aggregate, semi_global_aggregate_with_winner)


def _volume(generator: torch.Generator, b: int = 3, d: int = 7, h: int = 11, w: int = 70) -> torch.Tensor:
    costs = (torch.rand(b, d, h, w, generator=generator) * 500).round()
    costs[0, 5:] = torch.inf  # past a pair's own count
    costs[1, :, :, :3] = torch.inf  # outside its region: the row paths start again
    costs[2, 2, 4, 5] = torch.inf  # one disparity outside the image
    costs[2, :, 6, 40:45] = torch.inf
    return costs


def _eq13(costs: np.ndarray, p1: float, p2: float, step: tuple[int, int]) -> np.ndarray:
    """One path of Hirschmüller's Eq. (13) by plain loops over one pair's (D, H, W) volume, ``step`` (dy, dx)."""
    d_count, h, w = costs.shape
    out = np.full_like(costs, np.inf)
    ys = range(h) if step[0] >= 0 else range(h - 1, -1, -1)
    xs = range(w) if step[1] >= 0 else range(w - 1, -1, -1)
    for y in ys:
        for x in xs:
            py, px = y - step[0], x - step[1]
            previous = out[:, py, px] if 0 <= py < h and 0 <= px < w else None
            low = np.min(previous) if previous is not None else np.inf
            for d in range(d_count):
                if not np.isfinite(low):
                    out[d, y, x] = costs[d, y, x]
                    continue
                near = min(previous[d - 1] if d > 0 else np.inf, previous[d + 1] if d + 1 < d_count else np.inf)
                best = min(previous[d], near + p1, low + p2)
                out[d, y, x] = costs[d, y, x] + (best - low)
    return out


def test_kernel_is_bit_identical_to_the_torch_path(generator):
    costs = _volume(generator)
    p1, p2 = torch.tensor([3.0, 0.0, 10.0]), torch.tensor([12.0, 0.0, 40.0])
    fused = kernels.semi_global_columns(costs, p1, p2)
    if fused is None:
        pytest.skip("no C compiler here")
    assert torch.equal(fused, _scan_columns_torch(costs, p1, p2))
    empty = kernels.semi_global_columns(costs[:0], p1[:0], p2[:0])
    assert empty is not None and empty.shape == (0, 7, 11, 70)


def test_rows_kernel_and_winner_are_bit_identical_to_the_torch_path(generator):
    """The rows' kernel (the row paths added to the columns' and the winner in one pass) against the torch path:
    the columns' scan of the transposed volume, the sum, ``min(dim=1)``; ties (a flat volume, no penalties) take
    the first disparity."""
    for costs, p1, p2 in ((_volume(generator), torch.tensor([3.0, 0.0, 10.0]), torch.tensor([12.0, 0.0, 40.0])),
                          (_volume(generator, d=40, h=9, w=37), torch.tensor([2.5, 1.0, 0.5]),
                           torch.tensor([9.0, 1.0, 8.0])),
                          (torch.zeros(2, 6, 5, 7), torch.zeros(2), torch.zeros(2))):
        columns = _scan_columns_torch(costs, p1, p2)
        fused = kernels.semi_global_rows(costs, p1, p2, columns)
        if fused is None:
            pytest.skip("no C compiler here")
        expected = columns + _scan_columns_torch(costs.transpose(-1, -2).contiguous(), p1, p2).transpose(-1, -2)
        minimum = expected.min(dim=1)
        assert torch.equal(fused[0], expected)
        assert torch.equal(fused[1][0], minimum.values) and torch.equal(fused[1][1], minimum.indices)
        aggregated, (low, index) = semi_global_aggregate_with_winner(costs, p1, p2)
        assert torch.equal(aggregated, expected) and torch.equal(index, minimum.indices)
    with pytest.raises(InputError, match=r"^columns: expected"):
        kernels.semi_global_rows(costs, p1, p2, columns[:, :, :-1])


def test_aggregation_is_eq13_summed_over_four_paths(generator):
    costs = _volume(generator, w=9)
    p1, p2 = torch.tensor([3.0, 5.0, 10.0]), torch.tensor([12.0, 5.0, 40.0])
    total = semi_global_aggregate(costs, p1, p2)
    for b in range(costs.shape[0]):
        volume = costs[b].double().numpy()
        paths = [_eq13(volume, float(p1[b]), float(p2[b]), step) for step in ((1, 0), (-1, 0), (0, 1), (0, -1))]
        expected = (paths[0] + paths[1]) + (paths[2] + paths[3])
        np.testing.assert_allclose(total[b].double().numpy(), expected, rtol=1e-6)


def test_zero_penalties_are_four_times_the_costs(generator):
    costs = _volume(generator)
    zero = torch.zeros(3)
    assert torch.equal(semi_global_aggregate(costs, zero, zero), 4 * costs)


@pytest.mark.parametrize("costs, p1, p2, name", [
    (torch.full((1, 2, 3, 3), float("nan")), torch.zeros(1), torch.zeros(1), "costs"),
    (-torch.ones(1, 2, 3, 3), torch.zeros(1), torch.zeros(1), "costs"),
    (torch.ones(2, 3, 3), torch.zeros(1), torch.zeros(1), "costs"),
    (torch.ones(1, 2, 3, 3), torch.zeros(2), torch.zeros(2), "p1"),
    (torch.ones(1, 2, 3, 3), torch.ones(1) * 2, torch.ones(1), "p1, p2"),
])
def test_bad_input_is_refused_by_name(costs, p1, p2, name):
    with pytest.raises(InputError, match=f"^{name}: "):
        semi_global_aggregate(costs, p1, p2)


@pytest.mark.parametrize("p1, p2, name, expected", [
    (torch.ones(1, dtype=torch.complex64), torch.ones(1), "p1", "int or float tensor"),  # NotImplementedError (ge_cpu)
    (torch.ones(1), torch.ones(1, dtype=torch.bool), "p2", "int or float tensor"),  # True taken as 1 in silence
    (torch.ones(1, device="meta"), torch.ones(1), "p1", "a tensor with values"),  # RuntimeError from a meta item()
])
def test_penalties_of_another_kind_or_device_are_refused_by_name(p1, p2, name, expected):
    with pytest.raises(InputError, match=f"^{name}: expected .*{expected}"):
        semi_global_aggregate(torch.ones(1, 2, 3, 3), p1, p2)
    with pytest.raises(InputError, match="^costs: expected a tensor with values"):  # both on meta, as the costs
        semi_global_aggregate(torch.ones(1, 2, 3, 3, device="meta"), p1.to("meta"), p2.to("meta"))


@pytest.mark.parametrize("penalties", [(-1.0, 2.0), (3.0, 2.0), (1.0, float("inf"))])
def test_config_refuses_bad_penalties(penalties):
    with pytest.raises(InputError, match="^smoothing_penalties: "):
        DenseConfig(smoothing_penalties=penalties)
    with pytest.raises(InputError, match="^smoothing_min_residual_levels: "):
        DenseConfig(smoothing_min_residual_levels=-1.0)


def test_residual_is_the_median_winner_cost_per_window_pixel():
    best = torch.tensor([[[9.0, 18.0, torch.inf], [27.0, 900.0, 0.0]]])
    wanted = torch.tensor([[[True, True, True], [True, False, False]]])
    assert pair_residual_levels(best, wanted, 3).tolist() == [2.0]
    assert pair_residual_levels(best, torch.zeros_like(wanted), 3).tolist() == [0.0]


@pytest.mark.parametrize("window_size", [1, 3, 7])
@pytest.mark.parametrize("whole", [True, False])
def test_residual_reaches_a_level_as_the_median_does(window_size, whole, generator):
    """The count (residual_reaches) against the median (pair_residual_levels ≥ level), every verdict: costs with
    +inf, NaN and unwanted pixels, odd and even counts, many equal values, a pair with no wanted pixel, and every
    level at and beside each pair's own residual (where a count one off would flip the verdict)."""
    best = torch.rand(6, 9, 13, generator=generator) * 60 * window_size ** 2
    best = best.round() if whole else best
    best[0, 0, :5] = torch.inf
    best[1, 2, 3] = torch.nan
    best[2] = best[2].round() % 5 * window_size ** 2  # runs of equal values
    wanted = torch.rand(6, 9, 13, generator=generator) < 0.8
    wanted[3, 0, 0] = ~wanted[3, 0, 0]  # one odd and one even count among the pairs
    wanted[4] = False
    residual = pair_residual_levels(best, wanted, window_size)
    levels = [0.0, 1.0, 30.0, *residual.tolist(), *(residual - 1e-3).tolist(), *(residual + 1e-3).tolist(),
              *torch.nextafter(residual, torch.full_like(residual, torch.inf)).tolist()]
    for level in levels:
        assert torch.equal(residual_reaches(best, wanted, window_size, level), residual >= level), level
    assert residual[4] == 0 and residual_reaches(best, wanted, window_size, 0.0)[4]


@pytest.mark.parametrize("best, wanted, window_size, name", [
    (torch.ones(2, 5, 6), torch.ones(2, 1, 6, dtype=torch.bool), 3, "wanted"),  # broadcast in silence
    (torch.ones(2, 5, 6), torch.ones(2, 5, 6), 3, "wanted"),  # NotImplementedError ("bitwise_and_cpu")
    (torch.ones(2, 5, 6, dtype=torch.int64), torch.ones(2, 5, 6, dtype=torch.bool), 3, "best_cost"),  # overflow
    (torch.ones(2, 30), torch.ones(2, 30, dtype=torch.bool), 3, "best_cost"),  # not (B, H, W), taken
    (torch.ones(2, 5, 6), torch.ones(2, 5, 6, dtype=torch.bool), 0, "window_size"),  # residuals of inf
    (torch.ones(2, 5, 6), torch.ones(2, 5, 6, dtype=torch.bool), True, "window_size"),  # a window of 1
])
def test_residual_names_a_bad_argument(best, wanted, window_size, name):
    with pytest.raises(InputError, match=f"^{name}: expected"):
        pair_residual_levels(best, wanted, window_size)


def test_whole_view_residual_is_the_fused_kernels_and_the_torch_paths():
    """:func:`block_match_sad_with_residual`: the map is :func:`block_match_sad`'s and the residual the median
    winning cost per window pixel, the same from the fused kernel and the torch path, pair by pair; a noisy pair's
    is above a clean one's; :func:`block_match_sad_noisy_pairs` (the nearness segmenter's noise gate) gives the
    same map and the residual's verdict at levels below, at and above it."""
    noisy_left, noisy_right = _noisy_plane(seed=10, sigma=0.04)
    clean_left, clean_right = _noisy_plane(seed=11, sigma=0.0)
    left, right = torch.cat([clean_left, noisy_left]), torch.cat([clean_right, noisy_right])
    config = DenseConfig(window_size=5)
    found, residual = block_match_sad_with_residual(left, right, 0, 16, config)
    eager, eager_residual = block_match_sad_with_residual(left, right, 0, 16, replace(config, kernel="torch"))
    plain = block_match_sad(left, right, 0, 16, config)
    assert torch.equal(found.disparity_px, plain.disparity_px) and torch.equal(found.valid, plain.valid)
    assert torch.equal(eager.disparity_px, plain.disparity_px) and torch.equal(eager.valid, plain.valid)
    assert torch.equal(residual, eager_residual)
    alone = block_match_sad_with_residual(noisy_left, noisy_right, 0, 16, config)[1]
    assert torch.equal(alone, residual[1:])
    assert float(residual[0]) == 0 < float(residual[1])  # the clean plane matches exactly
    for level in (0.0, float(residual[1]), float(residual[1]) + 0.01):
        gated, noisy = block_match_sad_noisy_pairs(left, right, 0, 16, level, config)
        assert torch.equal(noisy, residual >= level) and torch.equal(gated.disparity_px, plain.disparity_px)


def _noisy_plane(seed: int, sigma: float, shift_px: int = 6, h: int = 60, w: int = 96) -> tuple[torch.Tensor, ...]:
    """A weakly textured fronto-parallel plane at disparity ``shift_px``, independent noise in each view."""
    generator = torch.Generator().manual_seed(seed)
    texture = torch.nn.functional.avg_pool2d(torch.rand(1, 1, h, w + shift_px, generator=generator), 5, 1, 2)
    texture = 0.5 + 0.6 * (texture - texture.mean())
    left = texture[..., :w] + sigma * torch.randn(1, 1, h, w, generator=generator)
    right = texture[..., shift_px:] + sigma * torch.randn(1, 1, h, w, generator=generator)
    return left.clamp(0, 1), right.clamp(0, 1)


def test_smoothing_measures_a_noisy_plane_that_block_matching_loses():
    left, right = _noisy_plane(seed=3, sigma=0.03)
    mask = torch.zeros(1, 1, *left.shape[-2:], dtype=torch.bool)
    mask[..., 10:50, 25:85] = True
    search = DisparityRange(torch.zeros(1, dtype=torch.int64), 16)
    shares = {}
    for name, penalties in (("plain", None), ("smoothed", (4.0, 16.0))):
        config = DenseConfig(window_size=5, smoothing_penalties=penalties, smoothing_min_residual_levels=0.0)
        found = dense_disparity_over_regions(left, right, mask, search, config)
        right_ones = found.valid & mask & ((found.disparity_px - 6).abs() <= 1)
        shares[name] = (right_ones.sum() / mask.sum()).item()
    assert shares["smoothed"] > shares["plain"] + 0.2, shares


def test_a_pairs_smoothed_map_does_not_depend_on_its_batch():
    left, right = _noisy_plane(seed=5, sigma=0.03)
    other_left, other_right = _noisy_plane(seed=6, sigma=0.01)
    mask = torch.zeros(1, 1, *left.shape[-2:], dtype=torch.bool)
    mask[..., 20:40, 30:60] = True
    other_mask = torch.zeros_like(mask)
    other_mask[..., 5:58, 10:90] = True  # a larger box: the batch's shared crop is larger than the first pair's
    config = DenseConfig(window_size=5, smoothing_penalties=(4.0, 16.0), smoothing_min_residual_levels=0.0)
    alone = dense_disparity_over_regions(left, right, mask, DisparityRange(torch.tensor([0]), 12), config)
    batch = dense_disparity_over_regions(
        torch.cat([other_left, left]), torch.cat([other_right, right]), torch.cat([other_mask, mask]),
        DisparityRange(torch.tensor([2, 0]), 16, torch.tensor([14, 12])), config)
    assert torch.equal(batch.valid[1:], alone.valid)
    assert torch.equal(batch.disparity_px[1:], alone.disparity_px)


def test_clean_pairs_under_the_residual_gate_match_plain_block_matching():
    left, right = _noisy_plane(seed=7, sigma=0.0)
    mask = torch.ones(1, 1, *left.shape[-2:], dtype=torch.bool)
    search = DisparityRange(torch.zeros(1, dtype=torch.int64), 16)
    plain = dense_disparity_over_regions(left, right, mask, search, DenseConfig(window_size=5))
    gated = dense_disparity_over_regions(left, right, mask, search, DenseConfig(
        window_size=5, smoothing_penalties=(4.0, 16.0), smoothing_min_residual_levels=1e6))
    assert torch.equal(plain.valid, gated.valid) and torch.equal(plain.disparity_px, gated.disparity_px)


def test_the_fused_kernels_residual_gate_gives_the_torch_paths_map():
    """The fused kernel matches every pair and reports its residual; the noisy pair alone is matched again on
    the torch volume. The result is the torch path's, bit for bit, for the noisy and the clean pair."""
    noisy_left, noisy_right = _noisy_plane(seed=8, sigma=0.04)
    clean_left, clean_right = _noisy_plane(seed=9, sigma=0.0)
    left, right = torch.cat([clean_left, noisy_left]), torch.cat([clean_right, noisy_right])
    mask = torch.zeros(2, 1, *left.shape[-2:], dtype=torch.bool)
    mask[0, :, 5:55, 10:90] = True
    mask[1, :, 15:45, 20:70] = True
    search = DisparityRange(torch.tensor([0, 1]), 16, torch.tensor([16, 14]))
    config = DenseConfig(window_size=5, smoothing_penalties=(4.0, 16.0), smoothing_min_residual_levels=4.0)
    if not kernels.available():
        pytest.skip("no C compiler here")
    found = dense_disparity_over_regions(left, right, mask, search, config)
    eager = dense_disparity_over_regions(left, right, mask, search, replace(config, kernel="torch"))
    plain = dense_disparity_over_regions(left, right, mask, search, replace(config, smoothing_penalties=None))
    assert torch.equal(found.valid, eager.valid) and torch.equal(found.disparity_px, eager.disparity_px)
    assert torch.equal(found.valid[0], plain.valid[0]) and torch.equal(found.disparity_px[0], plain.disparity_px[0])
    assert not torch.equal(found.valid[1], plain.valid[1]), "the noisy pair was not aggregated"


def test_the_differentiable_pass_gives_an_aggregated_maps_values_with_gradients():
    """The aggregation picks the winners; the sub-pixel fit stays on the plain SAD costs, which the
    differentiable pass (svs_torch.pipeline.soft, step 1) recomputes from the images at those winners: the hard
    values (straight-through where a saturated fit hides the winner), with gradients to the images."""
    from svs_torch.pipeline.soft import _soft_disparity

    left, right = _noisy_plane(seed=10, sigma=0.04)
    mask = torch.zeros(1, 1, *left.shape[-2:], dtype=torch.bool)
    mask[..., 10:50, 25:85] = True
    search = DisparityRange(torch.zeros(1, dtype=torch.int64), 16)
    config = DenseConfig(window_size=5, smoothing_penalties=(4.0, 16.0), smoothing_min_residual_levels=0.0)
    hard = dense_disparity_over_regions(left, right, mask, search, config)
    plain = dense_disparity_over_regions(left, right, mask, search, replace(config, smoothing_penalties=None))
    assert int(hard.valid.sum()) > int(plain.valid.sum())
    image_hw = torch.tensor([list(left.shape[-2:])])
    image = left.clone().requires_grad_()
    soft = _soft_disparity(image, right, hard, mask, image_hw, config)
    assert torch.equal(soft[hard.valid].detach(), hard.disparity_px[hard.valid])
    soft[hard.valid].sum().backward()
    assert int((image.grad != 0).sum()) > 100


def test_noisy_pairs_are_aggregated_a_block_at_a_time_with_the_same_maps(monkeypatch):
    import svs_torch.depth.block_matching as block_matching

    pairs = [_noisy_plane(seed=20 + k, sigma=0.03 + 0.005 * k) for k in range(5)]
    left, right = torch.cat([p[0] for p in pairs]), torch.cat([p[1] for p in pairs])
    mask = torch.zeros(5, 1, *left.shape[-2:], dtype=torch.bool)
    for k in range(5):
        mask[k, :, 5 + 2 * k:45 + k, 10 + 3 * k:80] = True
    search = DisparityRange(torch.zeros(5, dtype=torch.int64), 16)
    config = DenseConfig(window_size=5, smoothing_penalties=(4.0, 16.0), smoothing_min_residual_levels=0.0)
    together = dense_disparity_over_regions(left, right, mask, search, config)
    monkeypatch.setattr(block_matching, "SMOOTH_BLOCK_PAIRS", 2)
    blocks = dense_disparity_over_regions(left, right, mask, search, config)
    assert torch.equal(together.valid, blocks.valid) and torch.equal(together.disparity_px, blocks.disparity_px)


def _featureless_box(seed: int, sigma: float, h: int = 64, w: int = 112, box_px: int = 14,
                     wall_px: int = 4) -> tuple[torch.Tensor, ...]:
    """A plain bright box (no texture, only each view's noise) at disparity ``box_px`` before a textured dark wall at
    ``wall_px``, and the box's mask in the left view (rows 16–47, columns 40–79)."""
    generator = torch.Generator().manual_seed(seed)
    wall = torch.nn.functional.avg_pool2d(torch.rand(1, 1, h, w + wall_px, generator=generator), 3, 1, 1)
    wall = 0.3 + 0.5 * (wall - wall.mean())
    views = []
    for shift_wall, shift_box in ((0, 0), (wall_px, box_px)):
        view = wall[..., shift_wall:shift_wall + w].clone()
        view[..., 16:48, 40 - shift_box:80 - shift_box] = 0.8
        views.append((view + sigma * torch.randn(1, 1, h, w, generator=generator)).clamp(0, 1))
    mask = torch.zeros(1, 1, h, w, dtype=torch.bool)
    mask[..., 16:48, 40:80] = True
    return views[0], views[1], mask


def test_the_intensities_cost_holds_a_featureless_box_at_its_own_disparity():
    """On an aggregated pair the x-Sobel of a plain box is its noise alone, and the columns' paths carry the wall's
    disparity from above and below into it; the intensities' SAD (``smoothing_intensity_weight``, OpenCV SGBM's
    quarter) holds the box's step against the wall, so more of the box is measured at its own disparity."""
    left, right, mask = _featureless_box(seed=30, sigma=0.03)
    search = DisparityRange(torch.zeros(1, dtype=torch.int64), 24)
    shares = {}
    for weight in (0.0, 0.25):
        config = DenseConfig(window_size=5, smoothing_penalties=(4.0, 16.0), smoothing_min_residual_levels=0.0,
                             smoothing_intensity_weight=weight)
        found = dense_disparity_over_regions(left, right, mask, search, config)
        on_box = found.valid & mask & ((found.disparity_px - 14).abs() <= 1)
        on_wall = found.valid & mask & ((found.disparity_px - 4).abs() <= 1)
        shares[weight] = (on_box.sum() / mask.sum()).item(), (on_wall.sum() / mask.sum()).item()
    # Measured: box 0.000 -> 0.346 of the mask, wall 0.871 -> 0.218.
    assert shares[0.25][0] > shares[0.0][0] + 0.2 and shares[0.25][1] < shares[0.0][1] - 0.3, shares


@pytest.mark.parametrize("weight", [-0.1, float("inf"), float("nan"), True, "0.25"])
def test_config_refuses_a_bad_intensity_weight(weight):
    with pytest.raises(InputError, match="^smoothing_intensity_weight: "):
        DenseConfig(smoothing_intensity_weight=weight)
