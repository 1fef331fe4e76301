"""A stage called on its own with arguments no pipeline would pass: each is refused by name, not ranged in silence
and not failed inside torch (an audit of the stages' public functions, 2026-12-03)."""

from __future__ import annotations

import pytest
import torch

from svs_torch import InputError
from svs_torch.core.types import Matches, RegionProperties
from svs_torch.depth import estimate_depth, estimate_range, object_depths, point_depths, rectified_disparity
from svs_torch.depth.depth_types import PointDepths
from svs_torch.geometry.matched_points import gather_matched_points
from svs_torch.segmentation.segment import keep_largest_regions, keep_regions


def _disparities() -> tuple[torch.Tensor, torch.Tensor]:
    return torch.tensor([[20.0, 25.0, 30.0]]), torch.ones(1, 3, dtype=torch.bool)


@pytest.mark.parametrize("name, focal_px, baseline_m, doffs_px, expected", [
    # A negative focal length times a negative baseline ranged the pair at the positive one's distance.
    ("focal_px", -500.0, -0.1, 0.0, "focal_px: expected finite positive values, got -500.0"),
    ("focal_px", 0.0, 0.1, 0.0, "focal_px: expected finite positive values, got 0.0"),
    ("focal_px", float("nan"), 0.1, 0.0, "focal_px: expected finite positive values, got nan"),
    ("baseline_m", 500.0, -0.1, 0.0, "baseline_m: expected finite positive values, got -0.1"),
    ("baseline_m", 500.0, torch.tensor([float("inf")]), 0.0, "baseline_m: expected finite positive values, got inf"),
    ("doffs_px", 500.0, 0.1, float("nan"), "doffs_px: expected finite values, got nan"),
])
def test_depth_functions_refuse_a_calibration_no_rig_has(name, focal_px, baseline_m, doffs_px, expected):
    disparity, valid = _disparities()
    for call in (lambda: point_depths(disparity, valid, focal_px, baseline_m, doffs_px),
                 lambda: estimate_range(disparity, valid, focal_px, baseline_m, doffs_px),
                 lambda: estimate_depth(torch.zeros(1, 3, 2), torch.zeros(1, 3, 2), valid, focal_px, baseline_m,
                                        doffs_px)):
        with pytest.raises(InputError, match=expected.replace("(", r"\(")):
            call()
    # A negative doffs is a calibration (cameras turned towards each other), not an error.
    assert bool(point_depths(disparity, valid, 500.0, 0.1, -5.0).valid.all())


def test_object_depths_refuses_a_pair_size_past_its_label_image():
    """Points past a 10 x 10 label image took its border labels: an object at 4.63 m from a map of the wrong size."""
    labels = torch.ones(1, 1, 10, 10, dtype=torch.long)
    points = torch.tensor([[[50.0, 60.0], [5.0, 5.0]]])
    depths = PointDepths(torch.tensor([[4.0, 5.0]]), torch.ones(1, 2, dtype=torch.bool))
    with pytest.raises(InputError, match=r"image_hw: expected \(height, width\) rows with 1 <= height <= 10"):
        object_depths(labels, torch.tensor([[1]]), points, depths, image_hw=torch.tensor([[120, 160]]))
    inside = object_depths(labels, torch.tensor([[1]]), points, depths, image_hw=torch.tensor([[10, 10]]))
    assert inside.num_inliers.tolist() == [[1]] and inside.depth_median_m.tolist() == [[5.0]]


def test_gather_matched_points_refuses_indices_past_the_right_keypoints():
    xy_left, xy_right = torch.rand(1, 3, 2) * 50, torch.rand(1, 2, 2) * 50
    for idx, got in ((torch.tensor([[0, 5, -1]]), "got values in \\[-1, 5\\]"),
                     (torch.tensor([[0, -2, 1]]), "got values in \\[-2, 1\\]")):
        with pytest.raises(InputError, match=r"matches.idx: expected right keypoint indices in \[0, 2\) or -1 .*" + got):
            gather_matched_points(xy_left, xy_right, Matches(idx, torch.zeros(1, 3)))
    # With no right keypoints, a match was to the point (0, 0).
    with pytest.raises(InputError, match=r"indices in \[0, 0\) or -1"):
        gather_matched_points(xy_left, torch.zeros(1, 0, 2), Matches(torch.tensor([[0, -1, -1]]), torch.zeros(1, 3)))
    with pytest.raises(InputError, match="matches.idx: expected an int tensor, got torch.float32"):
        gather_matched_points(xy_left, xy_right, Matches(torch.zeros(1, 3), torch.zeros(1, 3)))
    points = gather_matched_points(xy_left, xy_right, Matches(torch.tensor([[1, -1, 0]]), torch.zeros(1, 3)))
    assert points.valid.tolist() == [[True, False, True]] and torch.equal(points.right[0, 0], xy_right[0, 1])


def _regions(slots: int) -> RegionProperties:
    return RegionProperties(area_px=torch.full((1, slots), 4), bbox_xyxy=torch.zeros(1, slots, 4, dtype=torch.long),
                            centroid_xy=torch.zeros(1, slots, 2), valid=torch.ones(1, slots, dtype=torch.bool))


@pytest.mark.parametrize("value, slots", [(10 ** 6, 2), (-7, 2), (1, 0)])
def test_keep_functions_refuse_labels_past_the_region_slots(value, slots):
    labels = torch.zeros(1, 1, 4, 4, dtype=torch.long)
    labels[0, 0, 1, 1] = value
    expected = rf"labels: expected values in \[0, {slots}\]"
    with pytest.raises(InputError, match=expected):
        keep_largest_regions(labels, _regions(slots), 1)
    with pytest.raises(InputError, match=expected):
        keep_regions(labels, _regions(slots), 1, keep="nearest", nearness=torch.zeros(1, slots))
    labels[0, 0, 1, 1] = min(slots, 1)
    assert keep_largest_regions(labels, _regions(slots), 1)[1].sum() == (slots > 0)


def test_rectified_disparity_refuses_a_homography_of_nan():
    """A NaN homography gave every row valid, of NaN disparity; None stays the identity (one view warped alone)."""
    points = torch.tensor([[[40.0, 10.0], [60.0, 20.0]]])
    valid = torch.ones(1, 2, dtype=torch.bool)
    shift = torch.eye(3).unsqueeze(0)
    shift[0, 0, 2] = 3.0
    for H_left, H_right, name in ((shift, torch.full((1, 3, 3), float("nan")), "H_right"),
                                  (torch.full((1, 3, 3), float("inf")), None, "H_left")):
        with pytest.raises(InputError, match=f"{name}: expected finite values"):
            rectified_disparity(points, points - 5, valid, H_left, H_right)
    alone = rectified_disparity(points, points - 5, valid, H_left=shift)
    assert alone.disparity_px.tolist() == [[8.0, 8.0]] and bool(alone.valid.all())


def test_rectify_uncalibrated_refuses_a_size_that_is_not_two_ints():
    """``image_hw`` as a tuple: 120.5 was cut to 120 in silence and NaN failed in torch's int conversion."""
    from svs_torch.geometry.rectification import rectify_uncalibrated

    F = torch.tensor([[[0.0, 0, 0], [0, 0, -1], [0, 1, 0]]])
    points = torch.rand(1, 8, 2) * 100
    for size in ((120.5, 160), (float("nan"), 160), (120, 160, 3), (True, 160)):
        with pytest.raises(InputError, match=r"image_hw: expected \(height, width\) as two ints"):
            rectify_uncalibrated(F, points, points - 3, torch.ones(1, 8, dtype=torch.bool), size)
    rectified = rectify_uncalibrated(F, points, points - 3, torch.ones(1, 8, dtype=torch.bool), (120, 160))
    assert torch.allclose(rectified.H_left, torch.eye(3).unsqueeze(0), atol=1e-6)


def test_dense_stage_names_the_inlier_arguments_as_passed():
    """Mismatched inlier arguments were refused as ``valid`` (or, under the default coarse range, not checked)."""
    from svs_torch.depth.dense import DenseConfig, estimate_dense_disparity

    left = torch.rand(1, 1, 24, 32, generator=torch.Generator().manual_seed(0))
    right = torch.roll(left, -2, dims=-1)
    mask = torch.ones(1, 1, 24, 32, dtype=torch.bool)
    for config in (DenseConfig(), DenseConfig(range_source="inliers")):
        with pytest.raises(InputError, match=r"inlier_valid: expected \(1, 3\)"):
            estimate_dense_disparity(left, right, mask, config, None, torch.zeros(1, 3), torch.ones(1, 4, dtype=bool))
        with pytest.raises(InputError, match="inlier_disparity_px: expected finite values where inlier_valid holds"):
            estimate_dense_disparity(left, right, mask, config, None, torch.tensor([[2.0, float("nan")]]),
                                     torch.ones(1, 2, dtype=torch.bool))
        with pytest.raises(InputError, match="inlier_disparity_px, inlier_valid: expected both or neither"):
            estimate_dense_disparity(left, right, mask, config, None, torch.zeros(1, 3))
    # NaN where not valid is padding, not an error.
    dense = estimate_dense_disparity(left, right, mask, DenseConfig(range_source="inliers"), None,
                                     torch.tensor([[2.0, 2.0, 2.0, float("nan")]]),
                                     torch.tensor([[True, True, True, False]]))
    assert dense.valid.any()


def test_an_inlier_disparity_past_the_view_leaves_its_pair_unmatched_and_the_others_as_alone():
    """Left alone at the last two stops: an inlier disparity of 1e30 px was refused as an internal
    ``min_disparity_px`` out of int32 range, failing the whole batch. A range from past the view's width finds no
    match (no right pixel lies there); the other pair's map is the one it gets alone."""
    from svs_torch.depth.dense import DenseConfig, estimate_dense_disparity

    left = torch.rand(2, 1, 24, 32, generator=torch.Generator().manual_seed(0))
    right = torch.roll(left, -2, dims=-1)
    mask = torch.ones(2, 1, 24, 32, dtype=torch.bool)
    config = DenseConfig(range_source="inliers")
    valid = torch.ones(2, 8, dtype=torch.bool)
    alone = estimate_dense_disparity(left[1:], right[1:], mask[1:], config, None, torch.full((1, 8), 2.0), valid[1:])
    for far in (1e30, 40.0):
        disparity = torch.tensor([[far] * 8, [2.0] * 8])
        dense = estimate_dense_disparity(left, right, mask, config, None, disparity, valid)
        assert not dense.valid[0].any()
        assert torch.equal(dense.valid[1], alone.valid[0])
        assert torch.equal(dense.disparity_px[1][alone.valid[0]], alone.disparity_px[0][alone.valid[0]])


def test_row_alignment_refuses_nan_points_and_an_empty_size():
    from svs_torch.geometry.row_alignment import fit_row_alignment

    points = torch.rand(1, 12, 2, generator=torch.Generator().manual_seed(1)) * 100
    valid = torch.ones(1, 12, dtype=torch.bool)
    size = torch.tensor([[120, 160]])
    bad = points.clone()
    bad[0, 3, 1] = float("nan")
    with pytest.raises(InputError, match="points_right: expected finite values where valid holds"):
        fit_row_alignment(points, bad, valid, size)
    with pytest.raises(InputError, match=r"image_hw: expected positive \(height, width\) per pair, got \[\[0, 0\]\]"):
        fit_row_alignment(points, points, valid, torch.tensor([[0, 0]]))
    with pytest.raises(InputError, match="image_hw: expected an int tensor"):
        fit_row_alignment(points, points, valid, size.float())
    valid[0, 3] = False  # a NaN point in a padding row is not looked at
    assert fit_row_alignment(points, bad, valid, size) is not None


def _three_regions():
    from svs_torch.segmentation import segment_images

    image = torch.zeros(1, 1, 60, 80)
    image[..., 5:25, 5:30] = image[..., 35:55, 40:75] = image[..., 30:40, 10:20] = 1  # areas 500, 700, 100
    return segment_images(image)


@pytest.mark.parametrize("arguments, expected", [
    # A (B, 1) candidate area was broadcast, and the 100-pixel region under min_area_px was kept (an audit).
    ({"candidate_area_px": torch.full((1, 1), 1000.0)}, r"candidate_area_px: expected \(1, 3\), got \(1, 1\)"),
    ({"candidate_area_px": torch.ones(1, 8)}, r"candidate_area_px: expected \(1, 3\), got \(1, 8\)"),
    ({"min_area_px": float("nan")}, r"min_area_px: expected a finite number in \[0, inf\), got nan"),  # kept none
    ({"min_area_px": "x"}, "min_area_px: expected a finite number"),
    ({"near_min_area_px": -1.0}, "near_min_area_px: expected a finite number"),
])
def test_keep_regions_refuses_areas_that_are_not_one_per_region(arguments, expected):
    seg = _three_regions()
    nearness = torch.tensor([[2.0, 1.0, 0.0]])
    assert keep_regions(seg.labels, seg.regions, 2, "nearest", 200.0, nearness)[0].tolist() == [[1, 3]]
    with pytest.raises(InputError, match=expected):
        keep_regions(seg.labels, seg.regions, 2, "nearest", nearness=nearness, **({"min_area_px": 200.0} | arguments))


def test_keep_regions_refuses_a_nan_nearness_of_a_region():
    """A NaN nearness ranked as no number does: kept before every measured region or after, by where it sorted, in
    silence (an audit)."""
    seg = _three_regions()
    with pytest.raises(InputError, match=r"nearness: expected finite values where regions.valid holds"):
        keep_regions(seg.labels, seg.regions, 2, "nearest", nearness=torch.tensor([[2.0, float("nan"), 0.0]]))


def test_masked_quantile_refuses_a_q_of_two_dimensions():
    """A (2, 2) q gave 4 quantiles in a row, not the shape asked for, in silence (an audit)."""
    from svs_torch.depth.quantiles import masked_quantile

    values = torch.arange(10.0).view(1, 10)
    assert masked_quantile(values, values >= 0, [0.5]).values.tolist() == [[4.5]]
    with pytest.raises(InputError, match=r"q: expected a number or one sequence of quantiles, got shape \(2, 2\)"):
        masked_quantile(values, values >= 0, [[0.1, 0.5], [0.9, 1.0]])


@pytest.mark.parametrize("valid, expected", [(lambda v: v[:, :1], r"regions.valid: expected \(1, 3\), got \(1, 1\)"),
                                             (lambda v: v.float(), "regions.valid: expected a bool tensor")])
def test_keep_functions_refuse_a_validity_that_is_not_one_bool_per_region(valid, expected):
    """A short regions.valid failed inside torch's gather, a float one in torch.where (an audit)."""
    import dataclasses

    seg = _three_regions()
    regions = dataclasses.replace(seg.regions, valid=valid(seg.regions.valid))
    for call in (lambda: keep_largest_regions(seg.labels, regions, 2),
                 lambda: keep_regions(seg.labels, regions, 2, "nearest", nearness=torch.zeros(1, 3))):
        with pytest.raises(InputError, match=expected):
            call()


@pytest.mark.parametrize("name, value", [("min_inliers", 10 ** 30), ("min_inliers", True), ("max_iterations", True),
                                         ("chunk_size", True)])
def test_ransac_refuses_counts_it_cannot_compare_or_that_are_flags(name, value):
    """min_inliers=10**30 raised OverflowError inside torch; True was taken as 1 (an audit)."""
    from svs_torch.geometry.ransac import estimate_fundamental_ransac

    left = torch.rand(1, 30, 2, generator=torch.Generator().manual_seed(0)) * 100
    with pytest.raises(InputError, match=f"{name}: expected an int"):
        estimate_fundamental_ransac(left, left - torch.tensor([5.0, 0.0]), torch.ones(1, 30, dtype=torch.bool),
                                    pair_seeds=torch.tensor([1]), **{name: value})


def test_accuracy_refuses_shapes_that_do_not_broadcast():
    """Eq. (9) of a (2,) truth and a (3,) estimate failed in torch's broadcast_tensors, naming neither (an audit)."""
    from svs_torch.depth import accuracy_percent

    assert accuracy_percent(torch.tensor([1.0, 2.0]), torch.tensor(2.0)).percent.tolist() == [0.0, 100.0]
    with pytest.raises(InputError, match=r"estimated_m: expected a shape that broadcasts with real_m's \(2,\), got "
                                         r"\(3,\)"):
        accuracy_percent(torch.tensor([1.0, 2.0]), torch.tensor([1.1, 2.0, 3.0]))
