"""depth.alias_choice: the alias of a repeated pattern its whole region matches, and the object settled on it."""

from __future__ import annotations

import dataclasses
import cv2
import numpy as np
import pytest
import torch

from svs_torch.core.errors import InputError
from svs_torch.depth.alias_choice import (alias_depths_m, remeasure_on_alias, settle_aliases, settle_repeated_objects,
                                          whole_object_disparity)
from svs_torch.depth.dense import dense_disparity_in_range
from svs_torch.depth.dense_config import DenseConfig, DenseDisparity, RepeatedObjects

HEIGHT, WIDTH = 120, 200
TOLD = torch.tensor([[True]])  # the whole object's alias told apart
PANEL_ROWS, PANEL_COLUMNS = slice(20, 100), slice(70, 150)


def panel_pair(disparity: int = 20, period: int = 8, wall_disparity: int = 5, seed: int = 0
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A panel of vertical bars (``period`` px) at ``disparity`` before a textured wall at ``wall_disparity``:
    left and right views ``(1, 1, H, W)`` and the panel's mask in the left view ``(1, 1, H, W)`` bool."""
    wall = cv2.GaussianBlur(np.random.default_rng(seed).random((HEIGHT, WIDTH + 64)).astype(np.float32), (0, 0), 2.0)
    columns = np.arange(WIDTH)

    def view(panel_shift: int, wall_shift: int) -> np.ndarray:  # the right view sees x + d of the left scene
        image = 0.25 + 0.5 * wall[:, 32 + wall_shift:32 + wall_shift + WIDTH]
        u = columns + panel_shift - PANEL_COLUMNS.start
        inside = (u >= 0) & (u < PANEL_COLUMNS.stop - PANEL_COLUMNS.start)
        paint = 0.15 + 0.7 * ((u // (period // 2)) % 2)
        rows = image[PANEL_ROWS]
        rows[:, inside] = paint[inside]
        return image

    mask = np.zeros((HEIGHT, WIDTH), dtype=bool)
    mask[PANEL_ROWS, PANEL_COLUMNS] = True
    as_tensor = (lambda a: torch.from_numpy(np.ascontiguousarray(a))[None, None])
    return as_tensor(view(0, 0)), as_tensor(view(disparity, wall_disparity)), as_tensor(mask)


def dense_map(disparity: torch.Tensor, valid: torch.Tensor, low: int = 0, count: int = 48) -> DenseDisparity:
    return DenseDisparity(torch.where(valid, disparity, 0.0), valid, torch.tensor([low]), count,
                          torch.tensor([[0, 0, WIDTH, HEIGHT]]), torch.tensor([count]))


def test_the_whole_panel_matches_best_at_its_own_disparity_not_a_period_off():
    """Every window inside the bars matches as well a period (8 px) away; the whole panel does not, since its ends
    then meet the wall."""
    left, right, mask = panel_pair(disparity=20, period=8)
    config = DenseConfig()
    found, valid = whole_object_disparity(left, right, mask, torch.tensor([0]), torch.tensor([48]), config)
    assert bool(valid[0, 0]) and float(found[0, 0]) == 20.0
    # Searched only past the truth, it picks the nearest alias there: the range bounds the choice.
    found, _ = whole_object_disparity(left, right, mask, torch.tensor([24]), torch.tensor([24]), config)
    assert float(found[0, 0]) == 28.0
    # Two objects of one pair: the panel and a wall patch, each its own.
    wall = torch.zeros_like(mask)
    wall[..., 5:60, 10:50] = True
    found, valid = whole_object_disparity(left, right, torch.cat([mask, wall], 1), torch.tensor([0]),
                                          torch.tensor([48]), config)
    assert found[0].tolist() == [20.0, 5.0] and valid.all()
    # An empty object is not valid, and has no shift at all (NaN, not a shift of 0 its aliases would be counted from).
    found, valid = whole_object_disparity(left, right, torch.zeros_like(mask), torch.tensor([0]), torch.tensor([48]))
    assert not valid.any() and bool(found.isnan().all())


def test_a_pattern_with_no_end_in_view_has_no_alias_told():
    """Bars rolled across both views (the pattern wrapping round, no end anywhere): every alias fits alike, so with
    its period the whole object's shift is not valid, even searched over one alias only (the aliases outside the
    range searched count as rivals); the ended panel's is."""
    columns = np.mgrid[0:HEIGHT, 0:WIDTH][1]
    board = torch.from_numpy((0.2 + 0.6 * ((columns // 4) % 2)).astype(np.float32))[None, None]
    rolled = torch.roll(board, -20, dims=-1)
    whole = torch.ones(1, 1, HEIGHT, WIDTH, dtype=torch.bool)
    _, valid = whole_object_disparity(board, rolled, whole, torch.tensor([0]), torch.tensor([48]), DenseConfig(),
                                      torch.tensor([[8]]))
    assert not bool(valid[0, 0])
    _, valid = whole_object_disparity(board, rolled, whole, torch.tensor([16]), torch.tensor([8]), DenseConfig(),
                                      torch.tensor([[8]]))
    assert not bool(valid[0, 0])
    left, right, mask = panel_pair(disparity=20, period=8)
    found, valid = whole_object_disparity(left, right, mask, torch.tensor([0]), torch.tensor([48]), DenseConfig(),
                                          torch.tensor([[8]]))
    assert bool(valid[0, 0]) and float(found[0, 0]) == 20.0


def test_an_object_whose_windows_agree_with_its_whole_region_is_measured_again_over_one_period():
    """The windows' median on the right alias, with few of them valid: matched again over 20 ± 4 px, where no
    other alias lies, most of the panel is measured, at 20."""
    left, right, mask = panel_pair(disparity=20, period=8)
    sparse = mask & (torch.rand(mask.shape, generator=torch.Generator().manual_seed(0)) < 0.05)
    dense = dense_map(torch.full(mask.shape, 20.0), sparse)
    settled = settle_aliases(left, right, mask, dense, torch.tensor([[20.0]]), TOLD, torch.tensor([[8]]))
    measured = settled.valid & mask
    assert measured.sum() > 0.6 * mask.sum()
    assert float(settled.disparity_px[measured].median()) == pytest.approx(20.0, abs=0.25)
    assert not (settled.valid & ~mask).any()  # nothing outside the object is added
    assert settled.repeated.settled.tolist() == [[True]]


def test_the_distances_an_unsettled_objects_aliases_give_lie_whole_periods_apart_nearest_first():
    """A shift of 20 px, period 8, searched over [4, 44): the aliases 36, 28, 20, 12 and 4 px, read as distances
    f·B / (d + doffs); an object that does not repeat, or whose whole region fitted no shift, has none."""
    dense = dataclasses.replace(dense_map(torch.zeros(1, 1, HEIGHT, WIDTH), torch.zeros(1, 1, HEIGHT, WIDTH,
                                                                                         dtype=torch.bool), 4, 40),
                                repeated=RepeatedObjects(torch.tensor([[8, 0, 8]]), torch.tensor([[20.0, 9.0, 0.0]]),
                                                         torch.tensor([[True, True, False]]),
                                                         torch.tensor([[False, False, False]])))
    depth_m, valid = alias_depths_m(dense, torch.tensor([100.0]), torch.tensor([0.1]), torch.tensor([2.0]))
    assert valid.tolist() == [[[True] * 5, [False] * 5, [False] * 5]]
    assert depth_m[0, 0].tolist() == pytest.approx([10.0 / (d + 2) for d in (36, 28, 20, 12, 4)])
    # A negative doffs puts the aliases nearest the range's bottom behind the rig: not a distance.
    _, valid = alias_depths_m(dense, torch.tensor([100.0]), torch.tensor([0.1]), torch.tensor([-13.0]))
    assert valid[0, 0].tolist() == [True, True, True, False, False]
    # Without the check (no ``repeated``), no object has any.
    depth_m, valid = alias_depths_m(dense_map(torch.zeros(1, 1, HEIGHT, WIDTH), dense.valid), torch.tensor([100.0]),
                                    torch.tensor([0.1]))
    assert valid.shape == (1, 0, 0)


def test_an_object_whose_windows_lie_on_another_alias_is_dropped_and_the_rest_kept():
    left, right, mask = panel_pair(disparity=20, period=8)
    outside = torch.zeros_like(mask)
    outside[..., 5:15, 10:60] = True
    dense = dense_map(torch.full(mask.shape, 28.0), mask | outside)
    settled = settle_aliases(left, right, mask, dense, torch.tensor([[20.0]]), TOLD, torch.tensor([[8]]))
    assert not (settled.valid & mask).any() and bool((settled.valid == outside).all())
    # What was settled is kept: the period, the whole object's shift, and that it was not settled.
    assert settled.repeated.period_px.tolist() == [[8]] and settled.repeated.disparity_px.tolist() == [[20.0]]
    assert settled.repeated.fitted.tolist() == [[True]] and settled.repeated.settled.tolist() == [[False]]
    # Windows on the whole object's alias, but that alias not told apart from the others: dropped too.
    on_alias = dense_map(torch.full(mask.shape, 20.0), mask | outside)
    untold = settle_aliases(left, right, mask, on_alias, torch.tensor([[20.0]]), ~TOLD, torch.tensor([[8]]))
    assert not (untold.valid & mask).any() and bool((untold.valid == outside).all())
    # Not repeated (period 0): unchanged.
    same = settle_aliases(left, right, mask, dense, torch.tensor([[20.0]]), TOLD, torch.tensor([[0]]))
    assert torch.equal(same.valid, dense.valid) and torch.equal(same.disparity_px, dense.disparity_px)


def test_remeasure_settles_each_object_of_a_batch_on_its_own_rows():
    """Two pairs, the second with two objects; only the rows with a period are matched again, each over its own
    alias: the batch is one call, not a loop."""
    left_a, right_a, mask_a = panel_pair(disparity=20, period=8, seed=1)
    left_b, right_b, mask_b = panel_pair(disparity=30, period=12, seed=2)
    wall = torch.zeros_like(mask_a)
    wall[..., 5:15, 10:60] = True
    left, right = torch.cat([left_a, left_b]), torch.cat([right_a, right_b])
    objects = torch.cat([torch.cat([mask_a, torch.zeros_like(mask_a)], 1), torch.cat([mask_b, wall], 1)])
    empty = torch.zeros(2, 1, HEIGHT, WIDTH, dtype=torch.bool)
    dense = DenseDisparity(torch.zeros(2, 1, HEIGHT, WIDTH), empty, torch.tensor([0, 0]), 48,
                           torch.tensor([[0, 0, WIDTH, HEIGHT]] * 2), torch.tensor([48, 48]))
    settled = remeasure_on_alias(left, right, objects, dense, torch.tensor([[20.0, 0.0], [30.0, 5.0]]),
                                 torch.tensor([[8, 0], [12, 0]]))
    for pair, (mask, truth) in enumerate(((mask_a, 20.0), (mask_b, 30.0))):
        measured = settled.valid[pair:pair + 1] & mask
        assert measured.sum() > 0.6 * mask.sum()
        assert float(settled.disparity_px[pair:pair + 1][measured].median()) == pytest.approx(truth, abs=0.25)
    assert not (settled.valid[1:] & wall).any()  # the wall had no period: not matched


def test_dense_disparity_in_range_measures_only_the_range_given():
    left, right, mask = panel_pair(disparity=20, period=8)
    result = dense_disparity_in_range(left, right, mask, torch.tensor([16]), torch.tensor([9]))
    measured = result.valid & mask
    assert measured.sum() > 0.6 * mask.sum()
    assert float(result.disparity_px[measured].median()) == pytest.approx(20.0, abs=0.25)
    assert int(result.min_disparity_px[0]) == 16 and int(result.pair_num_disparities[0]) == 9
    # Over a range without the truth or an alias, nothing outside it is found.
    beside = dense_disparity_in_range(left, right, mask, torch.tensor([22]), torch.tensor([4]))
    found = beside.disparity_px[beside.valid]
    assert len(found) > 0 and bool(((found >= 21.5) & (found <= 26.0)).all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_repeated_disparities_follow_the_views_dtype_whether_or_not_an_object_repeats(dtype):
    """A float64 batch where nothing repeated got ``repeated.disparity_px`` in float32 (the default dtype), the one
    float32 tensor of a float64 pipeline result (a library user's audit); a repeated panel's was float64."""
    left, right, panel = panel_pair(disparity=20, period=8)
    wall = torch.zeros_like(panel)
    wall[..., 5:15, 10:60] = True
    for mask in (wall, panel):
        views = left.to(dtype), right.to(dtype)
        dense = dense_disparity_in_range(*views, mask, torch.tensor([0]), torch.tensor([48]))
        repeated = settle_repeated_objects(*views, mask, dense, 0.5).repeated
        assert repeated.disparity_px.dtype == dtype and dense.disparity_px.dtype == dtype
    assert repeated.period_px.tolist() == [[8]]  # the panel repeats: the other branch ran too


@pytest.mark.parametrize("call, name", [
    (lambda l, r, m: dense_disparity_in_range(l, r, m, torch.tensor([1.5]), torch.tensor([9])), "min_disparity_px"),
    (lambda l, r, m: dense_disparity_in_range(l, r, m, torch.tensor([0]), torch.tensor([9, 9])), "num_disparities"),
    (lambda l, r, m: whole_object_disparity(l, r, m[0], torch.tensor([0]), torch.tensor([9])), "objects"),
    (lambda l, r, m: whole_object_disparity(l, r, m.float(), torch.tensor([0]), torch.tensor([9])), "objects"),
    (lambda l, r, m: settle_aliases(l, r, m, dense_map(torch.zeros(m.shape), m), torch.zeros(1, 2), TOLD,
                                    torch.zeros(1, 1)), "disparity_px"),
    (lambda l, r, m: whole_object_disparity(l, r, m, torch.tensor([0]), torch.tensor([9]), DenseConfig(),
                                            torch.zeros(2, 1)), "period_px"),
    (lambda l, r, m: alias_depths_m(dense_map(torch.zeros(m.shape), m), torch.tensor([1.0, 2.0]), torch.tensor([0.1])),
     "focal_px"),
])
def test_bad_arguments_are_named(call, name):
    left, right, mask = panel_pair()
    with pytest.raises(InputError, match=name):
        call(left, right, mask)
