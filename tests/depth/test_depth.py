"""Depth stage: the paper's Eq. (5)–(9) on hand-made numbers, masking, robust statistics, per-object depth and
the nearest obstacle, against synthetic scenes with exact ground truth."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from svs_torch import InputError
from svs_torch.core.ordering import argsort_last, sort_last
from svs_torch.data.synthetic import random_obstacle_scenes
from svs_torch.depth.depth_types import DepthConfig, ObstacleSide, PointDepths
from svs_torch.depth.quantiles import (kept_region_lower_median, labelled_quantile, masked_lower_median,
                                       masked_quantile, region_lower_median)
from svs_torch.depth.sparse import (accuracy_percent, estimate_depth, estimate_range, nearest_obstacle, object_depths,
                                    point_depths, rectified_disparity)

F64 = torch.float64


def test_paper_range_equations_by_hand(dtype):
    """Eq. (5)–(8): d_max = 40, d_min = 10 → R_min = f·B/40, R_max = f·B/10 (f = 500 px, B = 0.1 m)."""
    disparity = torch.tensor([[10.0, 20.0, 40.0, 99.0], [25.0, 0.0, 0.0, 0.0]], dtype=dtype)
    valid = torch.tensor([[True, True, True, False], [True, False, False, False]])
    result = estimate_range(disparity, valid, 500.0, 0.1)
    assert result.d_max_px.dtype == dtype
    assert result.d_max_px.tolist() == [40.0, 25.0] and result.d_min_px.tolist() == [10.0, 25.0]
    assert torch.allclose(result.r_min_m, torch.tensor([1.25, 2.0], dtype=dtype))
    assert torch.allclose(result.r_max_m, torch.tensor([5.0, 2.0], dtype=dtype))
    assert result.num_disparities.tolist() == [3, 1] and result.valid.tolist() == [True, True]
    # Middlebury's doffs adds to every disparity: Z = f·B / (d + doffs); per-pair calibration as (B,) tensors.
    shifted = estimate_range(disparity, valid, torch.tensor([500.0, 1000.0], dtype=dtype),
                             torch.tensor([0.1, 0.2], dtype=dtype), doffs_px=10.0)
    assert torch.allclose(shifted.r_min_m, torch.tensor([50 / 50, 200 / 35], dtype=dtype))
    assert torch.allclose(shifted.r_max_m, torch.tensor([50 / 20, 200 / 35], dtype=dtype))


def test_non_positive_disparities_are_masked_not_divided():
    disparity = torch.tensor([[-3.0, 0.0, 8.0], [-1.0, 0.0, -7.0], [-5.0, 0.0, 2.0]], dtype=F64)
    valid = torch.ones(3, 3, dtype=torch.bool)
    depths = point_depths(disparity, valid, 400.0, 0.1, doffs_px=torch.tensor([0.0, 0.0, 6.0], dtype=F64))
    assert depths.valid.tolist() == [[False, False, True], [False, False, False], [True, True, True]]
    assert torch.isfinite(depths.depth_m).all() and (depths.depth_m[~depths.valid] == 0).all()
    assert torch.allclose(depths.depth_m[2], 40.0 / torch.tensor([1.0, 6.0, 8.0], dtype=F64))
    result = estimate_range(disparity, valid, 400.0, 0.1)
    assert result.valid.tolist() == [True, False, True] and result.num_disparities.tolist() == [1, 0, 1]
    assert result.d_min_px.tolist() == [8.0, 0.0, 2.0] and result.r_max_m[1] == 0 and result.r_min_m[1] == 0
    assert torch.isfinite(result.r_min_m).all() and torch.isfinite(result.r_max_m).all()


def test_a_pair_mostly_behind_the_rig_is_not_ranged_unless_the_papers_letter():
    """``min_in_front_share``: swapped views put nearly every inlier at d + doffs ≤ 0, and the paper's rule then
    ranged the pair from its few stray matches in front; over half must lie in front (the default setting), or
    any one under the paper's letter (0, the paper preset's)."""
    disparity = torch.tensor([[-9.0, -8.0, -7.0, 30.0, -6.0], [5.0, 6.0, -1.0, -2.0, 0.0],
                              [5.0, 6.0, 7.0, -2.0, -3.0]], dtype=F64)
    valid = torch.ones(3, 5, dtype=torch.bool)
    valid[1, 4] = False  # two of four in front: exactly half
    assert estimate_range(disparity, valid, 400.0, 0.1).valid.tolist() == [True, True, True]
    guarded = estimate_range(disparity, valid, 400.0, 0.1, min_in_front_share=0.5)
    assert guarded.valid.tolist() == [False, False, True] and guarded.r_min_m[:2].tolist() == [0.0, 0.0]
    assert guarded.num_disparities.tolist() == [1, 2, 3]
    assert estimate_range(disparity, valid, 400.0, 0.1, min_in_front_share=0.49).valid.tolist() == [False, True, True]
    assert DepthConfig().min_in_front_share == 0.5
    with pytest.raises(InputError, match="min_in_front_share"):
        DepthConfig(min_in_front_share=1.5)
    with pytest.raises(InputError, match="min_in_front_share"):
        estimate_range(disparity, valid, 400.0, 0.1, min_in_front_share=-0.1)


def test_swapped_views_are_not_ranged_by_the_paper_rule_unless_the_preset():
    """The audit's case: the cameras' cables swapped. ``--range paper`` leaves the pair unranged; the paper preset
    keeps the paper's letter (any one inlier in front) and, with a 1 px Sampson threshold, ranges it from a stray
    inlier, far nearer than the true obstacles. MATLAB's 0.1 px (the preset's) keeps no inlier in front here."""
    from svs_torch import PipelineConfig, PipelineStatus, StereoBatch, estimate_obstacle_depth
    from dataclasses import replace

    scenes = random_obstacle_scenes(1, 2, generator=torch.Generator().manual_seed(3))
    batch = scenes.batch
    swapped = StereoBatch.from_images(batch.right, batch.left, batch.focal_px, batch.baseline_m, calibrated=True)
    assert estimate_obstacle_depth(swapped, PipelineConfig.paper()).status.tolist() == [
        PipelineStatus.NO_POSITIVE_DISPARITY]
    loose = replace(PipelineConfig.paper(), ransac_threshold_px=1.0)
    paper = estimate_obstacle_depth(swapped, loose)
    assert paper.status.tolist() == [PipelineStatus.OK]
    assert float(paper.depth.nearest.depth_m[0]) < 0.5 * float(scenes.object_depth_m.min())
    guarded = replace(loose, depth=DepthConfig(rule="paper"))
    result = estimate_obstacle_depth(swapped, guarded)
    assert result.status.tolist() == [PipelineStatus.NO_POSITIVE_DISPARITY]
    assert not bool(result.depth.nearest.valid.any())
    assert estimate_obstacle_depth(batch, guarded).status.tolist() == [PipelineStatus.OK]


def test_robust_percentiles_ignore_a_same_row_outlier(generator):
    """One wrong match on the right row (REFERENCE.md pitfall) sets the paper's d_max; the 10th/90th
    percentiles stay near the true range."""
    disparity = 20 + 2 * torch.rand(1, 60, generator=generator, dtype=F64)
    disparity[0, 7] = 129.0
    valid = torch.ones(1, 60, dtype=torch.bool)
    paper = estimate_range(disparity, valid, 276.0, 0.1075)
    robust = estimate_range(disparity, valid, 276.0, 0.1075, percentiles=(10, 90))
    assert paper.d_max_px.item() == 129.0
    assert 20 < robust.d_max_px.item() < 22 and 20 < robust.d_min_px.item() < 22
    expected = np.percentile(disparity[0].numpy(), [10, 90])
    assert np.allclose([robust.d_min_px.item(), robust.d_max_px.item()], expected)


def test_masked_quantile_matches_numpy_per_row(generator):
    values = torch.randn(5, 3, 17, generator=generator, dtype=F64)
    valid = torch.rand(5, 3, 17, generator=generator) > 0.4
    valid[0, 0] = False
    valid[0, 1] = False
    valid[0, 1, 3] = True
    q = [0.0, 0.1, 0.5, 0.9, 1.0]
    result = masked_quantile(values, valid, q)
    assert result.values.shape == (5, 3, 5) and result.valid.shape == (5, 3)
    for index in np.ndindex(5, 3):
        row = values[index][valid[index]].numpy()
        if row.size == 0:
            assert not result.valid[index] and (result.values[index] == 0).all()
        else:
            assert np.allclose(result.values[index].numpy(), np.quantile(row, q))
    assert masked_quantile(values[..., :0], valid[..., :0], q).values.shape == (5, 3, 5)
    with pytest.raises(InputError, match="q: expected quantiles in"):
        masked_quantile(values, valid, [1.5])


@pytest.mark.parametrize("labels_dtype, kept_dtype, name", [
    (torch.int64, torch.bool, "kept_labels"),  # True read as label 1: slots of other regions, in silence
    (torch.int64, torch.complex64, "kept_labels"),  # NotImplementedError ("gt_cpu") from deep inside
    (torch.float32, torch.int64, "labels"),  # taken; a fractional label matched no slot, in silence
])
def test_kept_region_lower_median_names_labels_that_are_not_int(labels_dtype, kept_dtype, name):
    labels = torch.tensor([[1, 2], [2, 0]]).view(1, 1, 2, 2)
    with pytest.raises(InputError, match=f"^{name}: expected an int tensor"):
        kept_region_lower_median(torch.rand(1, 1, 2, 2), torch.ones(1, 1, 2, 2, dtype=torch.bool),
                                 labels.to(labels_dtype), torch.tensor([[2, 1]]).to(kept_dtype))


def test_region_lower_median_names_values_that_are_not_real():
    labels = torch.ones(1, 4, dtype=torch.int64)
    for values in (torch.ones(1, 4, dtype=torch.complex64), torch.ones(1, 4, dtype=torch.bool)):  # sort failed; taken
        with pytest.raises(InputError, match="^values: expected a float or int tensor"):
            region_lower_median(values, labels, 1)


@pytest.mark.parametrize("dtype", [torch.int64, torch.int32, torch.uint8, torch.float32, F64])
def test_masked_lower_median_is_torch_median_per_row_for_every_dtype_it_takes(generator, dtype):
    # Integer values (a KITTI map's raw uint16 levels, pixel counts) raised "value cannot be converted to type
    # int64_t without overflow" from deep inside: the masked entries were filled with inf.
    values = (torch.rand(4, 9, generator=generator) * 200).to(dtype)
    mask = torch.rand(4, 9, generator=generator) > 0.4
    mask[0] = False
    median, count = masked_lower_median(values, mask)
    assert median.dtype == dtype and count.tolist() == mask.sum(1).tolist()
    for row in range(4):
        expected = values[row][mask[row]].median() if mask[row].any() else torch.zeros((), dtype=dtype)
        assert median[row] == expected, row
    assert masked_lower_median(values[:, :0], mask[:, :0])[0].dtype == dtype
    with pytest.raises(InputError, match="values: expected a float32 or float64 tensor, got torch.float16"):
        masked_lower_median(values.half(), mask)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_labelled_quantile_equals_masked_quantile_per_slot(generator, dtype):
    """One sort per pair gives each slot's order statistics exactly as a masked sort per slot does: ties
    (whole-number values), labels of no slot, padded (−1) and repeated slots, empty slots and empty rows."""
    for trial in range(12):
        p, n = (int(torch.randint(0, high, (1,), generator=generator)) for high in (60, 4))
        values = torch.randint(0, 9, (3, p), generator=generator).to(dtype)
        if trial % 2:
            values = values + torch.rand(3, p, generator=generator, dtype=dtype)
        labels = torch.randint(-1, 5, (3, p), generator=generator)
        slots = torch.randint(-1, 5, (3, n), generator=generator)
        q = [0.5, 0.1, 0.9, 0.0, 1.0]
        result = labelled_quantile(values, labels, slots, q)
        member = (labels.unsqueeze(1) == slots.unsqueeze(-1)) & (slots > 0).unsqueeze(-1) & (labels > 0).unsqueeze(1)
        expected = masked_quantile(values.unsqueeze(1).expand_as(member).contiguous(), member, q)
        assert torch.equal(result.values, expected.values) and torch.equal(result.valid, expected.valid)


def test_labelled_quantile_gradients(generator):
    values = torch.rand(2, 15, generator=generator, dtype=F64).requires_grad_()
    labels = torch.randint(0, 3, (2, 15), generator=generator)
    slots = torch.tensor([[1, 2], [2, -1]])
    assert torch.autograd.gradcheck(lambda v: labelled_quantile(v, labels, slots, [0.5, 0.1, 0.9]).values,
                                    (values,))


def test_numpy_sorts_equal_torch_sort(generator):
    """The numpy-backed sorts give torch.sort's values (NaN and inf last), ints too; through gradients."""
    values = torch.randn(4, 7, 33, generator=generator)
    values[0, 0, :5] = float("nan")
    values[1, 2, 3] = float("inf")
    for tensor in (values, values.double(), torch.randint(-5, 5, (3, 40), generator=generator)):
        ours, theirs = sort_last(tensor), tensor.sort(dim=-1).values
        assert torch.equal(ours.isnan(), theirs.isnan()) and torch.equal(ours.nan_to_num(), theirs.nan_to_num())
        assert torch.equal(tensor.gather(-1, argsort_last(tensor)).nan_to_num(), sort_last(tensor).nan_to_num())
    differentiable = torch.randn(3, 9, generator=generator, dtype=F64).requires_grad_()
    assert torch.autograd.gradcheck(sort_last, (differentiable,))
    assert torch.equal(sort_last(torch.zeros(2, 0)), torch.zeros(2, 0))


def test_accuracy_equation_9():
    real = torch.tensor([2.0, 2.0, 1.0, 0.0, 4.0], dtype=F64)
    estimated = torch.tensor([1.9, 2.1, 1.0, 1.0, float("inf")], dtype=F64)
    accuracy = accuracy_percent(real, estimated)
    assert torch.allclose(accuracy.percent[:3], torch.tensor([95.0, 95.0, 100.0], dtype=F64))
    assert accuracy.valid.tolist() == [True, True, True, False, False] and (accuracy.percent[3:] == 0).all()


def test_rectified_disparity_applies_homographies():
    left = torch.tensor([[[100.0, 50.0], [200.0, 80.0], [300.0, 10.0]]], dtype=F64)
    right = left - torch.tensor([12.0, 0.0], dtype=F64)
    valid = torch.tensor([[True, True, False]])
    plain = rectified_disparity(left, right, valid)
    assert plain.disparity_px.tolist() == [[12.0, 12.0, 0.0]] and plain.row_error_px.abs().max() == 0
    shift = torch.tensor([[[1.0, 0, 3.0], [0, 1, -2.0], [0, 0, 1]]], dtype=F64)
    shifted = rectified_disparity(left, right, valid, H_left=shift, H_right=torch.eye(3, dtype=F64)[None])
    assert shifted.disparity_px.tolist() == [[15.0, 15.0, 0.0]] and shifted.row_error_px.tolist() == [[-2, -2, 0]]
    behind = torch.tensor([[[1.0, 0, 0], [0, 1, 0], [-0.008, 0, 1]]], dtype=F64)  # w ≤ 0 from x = 125 on
    masked = rectified_disparity(left, right, torch.ones(1, 3, dtype=torch.bool), H_right=behind)
    assert masked.valid.tolist() == [[True, False, False]]


def _two_region_labels() -> torch.Tensor:
    """A 30×60 left label image: label 3 in columns 2–15 (left third), label 7 in columns 44–57 (right third)."""
    labels = torch.zeros(1, 1, 30, 60, dtype=torch.int64)
    labels[..., 5:25, 2:16] = 3
    labels[..., 5:25, 44:58] = 7
    return labels


def test_object_depths_by_hand():
    labels = _two_region_labels()
    region_labels = torch.tensor([[7, 3, -1]])  # slots in the segmentation's order, padded
    points = torch.tensor([[[5.0, 10.0], [8.2, 20.4], [10.0, 6.0], [50.0, 10.0], [52.0, 24.0],
                            [30.0, 15.0], [-4.0, 10.0], [12.0, 12.0]]], dtype=F64)
    depth = torch.tensor([[1.0, 2.0, 3.0, 1.5, 1.7, 0.5, 0.4, 9.0]], dtype=F64)
    valid = torch.tensor([[True, True, True, True, True, True, True, False]])
    objects = object_depths(labels, region_labels, points, PointDepths(depth, valid), percentiles=(0, 100))
    assert objects.label.tolist() == [[7, 3, -1]]
    assert objects.num_inliers.tolist() == [[2, 3, 0]] and objects.valid.tolist() == [[True, True, False]]
    assert objects.area_px.tolist() == [[280, 280, 0]]
    assert torch.allclose(objects.centroid_x_px, torch.tensor([[50.5, 8.5, 0.0]], dtype=F64))
    assert objects.side.tolist() == [[ObstacleSide.RIGHT, ObstacleSide.LEFT, ObstacleSide.NONE]]
    assert torch.allclose(objects.depth_median_m, torch.tensor([[1.6, 2.0, 0.0]], dtype=F64))
    assert objects.depth_low_m.tolist() == [[1.5, 1.0, 0.0]] and objects.depth_high_m.tolist() == [[1.7, 3.0, 0.0]]
    assert objects.point_slot.tolist() == [[1, 1, 1, 0, 0, -1, -1, -1]]
    nearest = nearest_obstacle(objects)
    assert nearest.slot.tolist() == [0] and nearest.depth_m.tolist() == [1.6]
    assert nearest.side.tolist() == [ObstacleSide.RIGHT] and nearest.valid.tolist() == [True]
    # A minimum inlier count drops the right object; then the left one is the nearest.
    strict = object_depths(labels, region_labels, points, PointDepths(depth, valid), min_inliers=3)
    assert strict.valid.tolist() == [[False, True, False]]
    assert nearest_obstacle(strict).side.tolist() == [ObstacleSide.LEFT]


def test_centre_side_and_no_obstacle():
    labels = torch.zeros(2, 1, 30, 60, dtype=torch.int64)
    labels[0, :, 10:20, 25:35] = 1
    region_labels = torch.tensor([[1], [1]])
    points = torch.tensor([[[30.0, 15.0]], [[30.0, 15.0]]], dtype=F64)
    depths = PointDepths(torch.tensor([[2.0], [2.0]], dtype=F64), torch.ones(2, 1, dtype=torch.bool))
    objects = object_depths(labels, region_labels, points, depths)
    assert objects.side.tolist() == [[ObstacleSide.CENTRE], [ObstacleSide.NONE]]
    nearest = nearest_obstacle(objects)
    assert nearest.valid.tolist() == [True, False] and nearest.slot.tolist() == [0, -1]
    assert nearest.side.tolist() == [ObstacleSide.CENTRE, ObstacleSide.NONE] and nearest.depth_m.tolist() == [2, 0]


def test_an_obstacle_reaching_across_the_middle_is_ahead_whatever_its_centroid():
    """Found by an audit of guide's words: a wall over the whole view, kept over columns 0-174 of 320 (its centroid
    in the left third), was said "Stop. Obstacle on the left at 0.9 metres"; a walker told so steps right, into it.
    A region wholly in the left third and a post in the right keep their thirds; a padded pair's middle is its own."""
    labels = torch.zeros(2, 1, 24, 320, dtype=torch.int64)
    labels[0, :, :, 0:175] = 1  # across the middle column (159.5): ahead
    labels[0, :, :, 0:90] = 2  # wholly in the left third
    labels[0, :, :, 230:240] = 3  # a post in the right third
    labels[1, :, :, 0:85] = 1  # a pair 160 px wide in a 320 px batch: across its own middle (79.5)
    region_labels = torch.tensor([[1, 2, 3], [1, -1, -1]])
    points = torch.tensor([[[100.0, 5.0]], [[50.0, 5.0]]], dtype=F64)
    depths = PointDepths(torch.tensor([[0.99], [0.99]], dtype=F64), torch.ones(2, 1, dtype=torch.bool))
    objects = object_depths(labels, region_labels, points, depths, image_hw=torch.tensor([[24, 320], [24, 160]]))
    assert objects.side.tolist() == [[ObstacleSide.CENTRE, ObstacleSide.LEFT, ObstacleSide.RIGHT],
                                     [ObstacleSide.CENTRE, ObstacleSide.NONE, ObstacleSide.NONE]]


def _sample_object_points(scenes, num_points: int, generator: torch.Generator) -> tuple[torch.Tensor, ...]:
    """Exact correspondences on the obstacles: left pixel centres drawn on object pixels, right = x − d."""
    ids = scenes.object_ids.flatten(1)
    index = torch.multinomial((ids > 0).double(), num_points, replacement=True, generator=generator)  # (B, K)
    width = scenes.object_ids.shape[-1]
    left = torch.stack([index % width, index // width], -1).to(F64)
    disparity = scenes.batch.disparity_px.flatten(1).double().gather(1, index)
    right = left - torch.stack([disparity, torch.zeros_like(disparity)], -1)
    return left, right


def test_object_depths_on_synthetic_scenes(generator):
    scenes = random_obstacle_scenes(3, 2, size_wh=(320, 240), generator=generator)
    batch = scenes.batch
    left, right = _sample_object_points(scenes, 200, generator)
    inliers = torch.ones(left.shape[:2], dtype=torch.bool)
    region_labels = torch.tensor([[1, 2]]).expand(3, 2)
    result = estimate_depth(left, right, inliers, batch.focal_px.double(), batch.baseline_m.double(),
                            batch.doffs_px.double(), labels=scenes.object_ids, region_labels=region_labels,
                            image_hw=batch.image_hw, config=DepthConfig(percentiles=(10, 90)))
    truth = scenes.object_depth_m.double()
    assert result.objects.valid.all()
    assert ((result.objects.depth_median_m - truth).abs() / truth).max() < 0.01
    # The pair's range spans the two obstacles (only obstacle points were sampled).
    assert torch.allclose(result.range.r_min_m, truth.amin(1), rtol=0.01)
    assert torch.allclose(result.range.r_max_m, truth.amax(1), rtol=0.01)
    nearest = truth.argmin(1)
    assert torch.equal(result.nearest.slot, nearest)
    centre_x = scenes.object_bbox_xyxy[..., [0, 2]].double().mean(-1).gather(1, nearest.unsqueeze(1)).squeeze(1)
    expected_side = (centre_x >= 320 / 3).long() + (centre_x >= 2 * 320 / 3).long()
    assert torch.equal(result.nearest.side, expected_side)
    assert torch.allclose(result.nearest.depth_m, truth.amin(1), rtol=0.01)


def test_batched_equals_per_pair_and_padding_is_ignored(generator):
    scenes = random_obstacle_scenes(3, 2, size_wh=(160, 120), generator=generator)
    left, right = _sample_object_points(scenes, 40, generator)
    inliers = torch.rand(left.shape[:2], generator=generator) > 0.2
    region_labels = torch.tensor([[2, 1, -1]]).expand(3, 3)
    args = dict(focal_px=scenes.batch.focal_px.double(), baseline_m=scenes.batch.baseline_m.double())
    batched = estimate_depth(left, right, inliers, labels=scenes.object_ids, region_labels=region_labels, **args)
    for i in range(3):
        single = estimate_depth(left[i:i + 1], right[i:i + 1], inliers[i:i + 1], labels=scenes.object_ids[i:i + 1],
                                region_labels=region_labels[i:i + 1], focal_px=args["focal_px"][i:i + 1],
                                baseline_m=args["baseline_m"][i:i + 1])
        assert torch.allclose(single.objects.depth_median_m[0], batched.objects.depth_median_m[i])
        assert torch.equal(single.range.r_min_m[0], batched.range.r_min_m[i])
        assert torch.equal(single.nearest.slot[0], batched.nearest.slot[i])
    garbage = torch.rand(3, 9, 2, generator=generator, dtype=F64) * 100
    padded = estimate_depth(torch.cat([left, garbage], 1), torch.cat([right, garbage - 50], 1),
                            torch.cat([inliers, torch.zeros(3, 9, dtype=torch.bool)], 1),
                            labels=scenes.object_ids, region_labels=region_labels, **args)
    for field in ("depth_median_m", "depth_low_m", "depth_high_m", "num_inliers"):
        assert torch.equal(getattr(padded.objects, field), getattr(batched.objects, field))
    assert torch.equal(padded.range.r_max_m, batched.range.r_max_m)
    assert (padded.objects.point_slot[:, 40:] == -1).all()


def test_gradients():
    disparity = torch.tensor([[10.0, 14.0, 23.0, 31.0, 40.0]], dtype=F64, requires_grad=True)
    valid = torch.tensor([[True, True, True, False, True]])

    def ranges(disparity: torch.Tensor, focal: torch.Tensor) -> tuple[torch.Tensor, ...]:
        result = estimate_range(disparity, valid, focal, 0.1, percentiles=(20, 70))
        return result.r_min_m, result.r_max_m

    focal = torch.tensor([500.0], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(ranges, (disparity, focal))
    assert torch.autograd.gradcheck(lambda d: point_depths(d, valid, 500.0, 0.1, 2.0).depth_m, (disparity,))


def test_empty_sets():
    """K = 0 correspondences and N = 0 region slots give invalid results, not errors."""
    labels = _two_region_labels()
    empty_points = torch.zeros(1, 0, 2, dtype=F64)
    result = estimate_depth(empty_points, empty_points, torch.zeros(1, 0, dtype=torch.bool), 500.0, 0.1,
                            labels=labels, region_labels=torch.tensor([[3, 7]]))
    assert result.range.valid.tolist() == [False] and result.objects.num_inliers.tolist() == [[0, 0]]
    assert result.objects.area_px.tolist() == [[280, 280]] and result.nearest.valid.tolist() == [False]
    points = torch.tensor([[[5.0, 10.0]]], dtype=F64)
    no_slots = estimate_depth(points, points - torch.tensor([4.0, 0.0], dtype=F64), torch.ones(1, 1, dtype=torch.bool),
                              500.0, 0.1, labels=labels, region_labels=torch.zeros(1, 0, dtype=torch.int64))
    assert no_slots.objects.valid.shape == (1, 0) and no_slots.objects.point_slot.tolist() == [[-1]]
    assert no_slots.nearest.slot.tolist() == [-1] and no_slots.nearest.side.tolist() == [ObstacleSide.NONE]
    assert no_slots.range.r_min_m.tolist() == [12.5]


@pytest.mark.parametrize("name, value", [
    ("focal_px", "300"),  # TypeError "new(): invalid data type 'str'" from torch.as_tensor
    ("focal_px", 300 + 0j),  # TypeError "must be real number, not complex"
    ("focal_px", True),  # a focal length of 1 px, in silence
    ("baseline_m", torch.ones(2, dtype=torch.bool)),  # a baseline of 1 m, in silence
    ("baseline_m", torch.full((2,), 0.1 + 0j)),  # imaginary part dropped with a warning
    ("doffs_px", torch.zeros(2, device="meta")),  # NotImplementedError "Cannot copy out of meta tensor"
])
def test_a_calibration_value_that_is_not_real_is_named(name, value):
    calibration = {"focal_px": 300.0, "baseline_m": 0.1, "doffs_px": 0.0, name: value}
    with pytest.raises(InputError, match=f"^{name}: expected a real number or a \\(2,\\) real tensor"):
        point_depths(torch.ones(2, 5), torch.ones(2, 5, dtype=torch.bool), **calibration)


def test_object_depths_names_complex_points():
    """They raised NotImplementedError ("round_vml_cpu" not implemented for 'ComplexFloat') from deep inside."""
    labels = torch.ones(1, 1, 4, 4, dtype=torch.int64)
    depths = PointDepths(torch.ones(1, 2), torch.ones(1, 2, dtype=torch.bool))
    with pytest.raises(InputError, match="^points_left: expected a float or int tensor"):
        object_depths(labels, torch.tensor([[1]]), torch.ones(1, 2, 2, dtype=torch.complex64), depths)


def test_input_errors():
    points = torch.zeros(2, 5, 2)
    with pytest.raises(InputError, match=r"points_right: expected \(B, K, 2\), got \(2, 5, 3\)"):
        rectified_disparity(points, torch.zeros(2, 5, 3), torch.ones(2, 5, dtype=torch.bool))
    with pytest.raises(InputError, match="valid: expected a bool tensor"):
        point_depths(torch.zeros(2, 5), torch.ones(2, 5), 500.0, 0.1)
    with pytest.raises(InputError, match=r"focal_px: expected a scalar or \(2,\)"):
        point_depths(torch.zeros(2, 5), torch.ones(2, 5, dtype=torch.bool), torch.ones(3), 0.1)
    with pytest.raises(InputError, match="region_labels: expected it together with labels"):
        estimate_depth(points, points, torch.ones(2, 5, dtype=torch.bool), 500.0, 0.1,
                       labels=torch.zeros(2, 1, 4, 4, dtype=torch.int64))
    # A library user's audit: a dict as the config raised "'dict' object has no attribute 'percentiles'".
    with pytest.raises(InputError, match="^config: expected a DepthConfig, got dict$"):
        estimate_depth(points, points, torch.ones(2, 5, dtype=torch.bool), 500.0, 0.1, config={})
    with pytest.raises(InputError, match=r"percentiles: expected \(low, high\) with 0 <= low <= high <= 100"):
        estimate_range(torch.zeros(2, 5), torch.ones(2, 5, dtype=torch.bool), 500.0, 0.1, percentiles=(90, 10))
    with pytest.raises(InputError, match=r"labels: expected \(B, 1, H, W\)"):
        object_depths(torch.zeros(2, 4, 4, dtype=torch.int64), torch.ones(2, 1, dtype=torch.int64), points,
                      PointDepths(torch.zeros(2, 5), torch.ones(2, 5, dtype=torch.bool)))


def test_without_statistics_only_the_depths_and_the_slots_geometry_are_made(generator):
    # The dense rule measures the objects' depths again (svs_torch.pipeline.ranging): it asks for everything but
    # the sparse statistics, which then stay zero and invalid; what it keeps is the same as with them.
    scenes = random_obstacle_scenes(2, 2, size_wh=(160, 120), generator=generator)
    left, right = _sample_object_points(scenes, 40, generator)
    inliers = torch.rand(left.shape[:2], generator=generator) > 0.2
    args = dict(labels=scenes.object_ids, region_labels=torch.tensor([[2, 1, -1]]).expand(2, 3),
                focal_px=scenes.batch.focal_px.double(), baseline_m=scenes.batch.baseline_m.double())
    full = estimate_depth(left, right, inliers, **args)
    lean = estimate_depth(left, right, inliers, statistics=False, **args)
    assert bool(full.objects.valid.any()) and bool(full.range.valid.all())
    for name, fields in (("disparities", ("disparity_px", "row_error_px", "valid")), ("points", ("depth_m", "valid"))):
        for field in fields:
            assert torch.equal(getattr(getattr(full, name), field), getattr(getattr(lean, name), field))
    for field in ("label", "area_px", "centroid_x_px", "side", "num_inliers", "point_slot"):
        assert torch.equal(getattr(full.objects, field), getattr(lean.objects, field))
    assert not lean.objects.valid.any() and not lean.range.valid.any() and not lean.nearest.valid.any()
    assert not lean.objects.depth_median_m.any() and not lean.range.r_min_m.any()


def test_the_object_statistics_name_a_container_of_another_kind():
    """Found by an audit of the library called by hand: nearest_obstacle given None or a dict failed on .valid,
    range_from_objects given None on .depth_median_m, object_depths given None for its depths on .depth_m,
    dense_object_depths given a (disparity, valid) tuple for its
    dense map on .disparity_px and None for its objects on .label (each an AttributeError naming no argument)."""
    from svs_torch.depth.dense_objects import dense_object_depths, range_from_objects
    for objects in (None, {}):
        with pytest.raises(InputError, match=f"^objects: expected an ObjectDepths, got {type(objects).__name__}$"):
            nearest_obstacle(objects)
    with pytest.raises(InputError, match="^objects: expected an ObjectDepths, got NoneType$"):
        range_from_objects(None, 300.0, 0.1)
    disparity, valid = torch.ones(1, 1, 4, 5), torch.ones(1, 1, 4, 5, dtype=torch.bool)
    with pytest.raises(InputError, match="^depths: expected a PointDepths, got NoneType$"):
        object_depths(torch.ones(1, 1, 4, 5, dtype=torch.int64), torch.tensor([[1]]), torch.zeros(1, 3, 2), None)
    with pytest.raises(InputError, match="^dense: expected a DenseDisparity, got tuple$"):
        dense_object_depths((disparity, valid), torch.ones(1, 1, 4, 5, dtype=torch.int64), None, 300.0, 0.1)
