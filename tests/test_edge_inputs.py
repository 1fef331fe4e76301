"""Edge inputs of the Python API that an audit of its public calls (and the kernel fuzz run at a larger scale) found,
pinned down: each was a raw error from deep inside torch (or Python), or a silent wrong answer. The docstring of
each test says which."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest
import torch

from svs_torch import (InputError, estimate_fundamental_ransac, estimate_obstacle_depth,
                       extract_surf_features, match_sad)
from svs_torch.data.synthetic import random_obstacle_scenes
from svs_torch.depth.soft_dense import soft_block_match
from svs_torch.evaluation import evaluate_result, measure_stereo_metrics
from svs_torch.evaluation.metrics import accuracy_pct
from svs_torch.pipeline import PipelineConfig
from svs_torch.segmentation.soft import soft_segment_images


@pytest.fixture(scope="module")
def scenes():
    return random_obstacle_scenes(3, 2, size_wh=(96, 72), generator=torch.Generator().manual_seed(5))


# ------------------------------------------------------------------------------------------------- B = 0
def test_an_empty_batch_gives_empty_results(generator):
    """Was: IndexError / 'cannot reshape tensor of 0 elements' from match_sad, soft_block_match and
    measure_stereo_metrics on a batch of no pairs."""
    descriptors, valid = torch.rand(0, 5, 64, generator=generator), torch.ones(0, 5, dtype=torch.bool)
    matches = match_sad(descriptors, descriptors, valid, valid)
    assert matches.idx.shape == (0, 5) and matches.cost.shape == (0, 5)
    images = torch.rand(0, 1, 12, 20, generator=generator)
    assert soft_block_match(images, images, 0, 8, 0.1).shape == (0, 1, 12, 20)
    metrics = measure_stereo_metrics(images, images > 0, images, images > 0)
    assert metrics.bad_pct.shape == (0, 4) and metrics.density.shape == (0,)
    # A layouts audit: four more took 'cannot reshape tensor of 0 elements' (reshape(b, -1) with b = 0).
    from svs_torch.depth import PointDepths, estimate_depth, kept_region_lower_median, object_depths
    from svs_torch.evaluation import disparity_map_errors
    labels, kept = torch.zeros(0, 1, 8, 8, dtype=torch.int64), torch.zeros(0, 2, dtype=torch.int64)
    points, known = torch.zeros(0, 5, 2), torch.zeros(0, 5, dtype=torch.bool)
    assert object_depths(labels, kept, points, PointDepths(torch.zeros(0, 5), known)).depth_median_m.shape == (0, 2)
    assert estimate_depth(points, points, known, 100.0, 0.1, labels=labels, region_labels=kept).objects.valid.shape \
        == (0, 2)
    maps, mask = torch.zeros(0, 1, 8, 8), torch.zeros(0, 1, 8, 8, dtype=torch.bool)
    assert kept_region_lower_median(maps, mask, labels, kept)[0].shape == (0, 2)
    assert disparity_map_errors(maps, mask, maps, mask, mask).count.shape == (0,)


def test_stage_errors_name_the_argument_the_caller_passed():
    """A layouts audit: a uint8 'valid' or 'truth_valid' was named 'mask' (the bool the caller gave right), a
    uint8 'inliers' was named 'valid'; maps of no rows failed with an IndexError."""
    from svs_torch.depth import estimate_depth
    from svs_torch.evaluation import disparity_map_errors
    maps, mask = torch.rand(1, 1, 4, 4), torch.ones(1, 1, 4, 4, dtype=torch.bool)
    for name, args in (("valid", (maps, mask.byte(), maps, mask, mask)), ("truth_valid", (maps, mask, maps, mask.byte(),
                                                                                         mask))):
        with pytest.raises(InputError, match=f"^{name}: expected a bool tensor"):
            disparity_map_errors(*args)
    points = torch.rand(1, 5, 2)
    with pytest.raises(InputError, match="^inliers: expected a bool tensor"):
        estimate_depth(points, points, torch.ones(1, 5, dtype=torch.uint8), 100.0, 0.1)
    empty, none = torch.rand(2, 1, 0, 16), torch.ones(2, 1, 0, 16, dtype=torch.bool)
    with pytest.raises(InputError, match=r"disparity_px: expected maps of at least 1x1 pixels, got 16x0"):
        measure_stereo_metrics(empty, none, empty, none)


# ------------------------------------------------------------------------------------------------- wrong types
def test_match_sad_names_mixed_descriptor_dtypes(generator):
    """Was: RuntimeError from cdist ('expected scalar type Float but found Double')."""
    valid = torch.ones(1, 4, dtype=torch.bool)
    with pytest.raises(InputError, match="desc_right: expected the dtype of desc_left, torch.float32, got "
                                         "torch.float64"):
        match_sad(torch.rand(1, 4, 64, generator=generator),
                  torch.rand(1, 4, 64, generator=generator, dtype=torch.float64), valid, valid)


def test_a_seed_passed_as_the_generator_is_refused(generator):
    """Was: TypeError from torch.randint ('received an invalid combination of arguments')."""
    points = torch.rand(1, 10, 2, generator=generator)
    with pytest.raises(InputError, match="generator: expected a torch.Generator or None"):
        estimate_fundamental_ransac(points, points, torch.ones(1, 10, dtype=torch.bool), generator=5)
    with pytest.raises(InputError, match="generator: expected a torch.Generator or None"):
        random_obstacle_scenes(1, 1, size_wh=(48, 36), generator=7)


def test_surf_names_an_array_and_answers_a_strided_view_as_its_copy(scenes):
    """Was: AttributeError ''numpy.ndarray' object has no attribute 'dim''; and a transposed-back view of an image
    gave slightly different keypoints than the same pixels stored in order."""
    image = scenes.batch.left
    with pytest.raises(InputError, match=r"image: expected a torch.Tensor of shape \(B, 1, H, W\), got ndarray"):
        extract_surf_features(image.numpy())
    with pytest.raises(InputError, match=r"mask: expected a torch.Tensor of shape \(3, 1, 72, 96\), got ndarray"):
        extract_surf_features(image, mask=image.numpy() > 0)
    strided = image.transpose(-1, -2).contiguous().transpose(-1, -2)
    assert not strided.is_contiguous()
    ours, theirs = extract_surf_features(strided), extract_surf_features(image)
    assert torch.equal(ours.keypoints.xy, theirs.keypoints.xy)
    assert torch.equal(ours.descriptors, theirs.descriptors)


def test_select_counts_negative_indices_from_the_end_and_names_a_bad_one(scenes):
    """Was: IndexError from index_select for select([-1]) (a list's last item), and for an index past the end."""
    batch = scenes.batch
    assert torch.equal(batch.select([-1]).left, batch.select([2]).left)
    assert torch.equal(batch.select(torch.tensor([0, -2])).left, batch.select([0, 1]).left)
    with pytest.raises(InputError, match=r"index: expected pair indices in \[-3, 3\), got \[3\]"):
        batch.select([3])
    with pytest.raises(InputError, match=r"index: expected a \(3,\) bool mask, got \(2,\)"):
        batch.select(torch.tensor([True, False]))


def test_evaluate_result_refuses_a_result_of_another_batch(scenes):
    """Was: RuntimeError 'The size of tensor a (3) must match the size of tensor b (1)' from the scoring."""
    result = estimate_obstacle_depth(scenes.batch.select([0]))
    with pytest.raises(InputError, match=r"result: expected the result of a run on batch \(3 pairs of 96x72\), "
                                         r"got 1 pairs of 96x72"):
        evaluate_result(scenes.batch, result)
    with pytest.raises(InputError, match="px_scale: expected 1 values, one per pair, got 2"):
        evaluate_result(scenes.batch.select([0]), result, px_scale=[1.0, 1.0])


def test_map_and_inlier_scores_refuse_a_result_of_another_batch(scenes):
    """Was: the sparse and dense disparity errors and the map metrics scored pair 0's result against pair 1's
    truth in silence, or answered None, {} or [] (as for a pair without truth) for a result of another size."""
    from svs_torch.data import resize_stereo_batch
    from svs_torch.evaluation import dense_disparity_errors, dense_map_metrics, object_map_metrics
    from svs_torch.evaluation import sparse_disparity_errors

    result = estimate_obstacle_depth(scenes.batch.select([0]))
    larger = resize_stereo_batch(scenes.batch.select([1]), (128, 96))
    for score in (sparse_disparity_errors, dense_disparity_errors, dense_map_metrics, object_map_metrics):
        with pytest.raises(InputError, match=r"result: expected the result of a run on batch \(3 pairs of 96x72\), "
                                             r"got 1 pairs of 96x72"):
            score(scenes.batch, result)
        if score is not sparse_disparity_errors:  # the inliers' points carry no image size
            with pytest.raises(InputError, match=r"batch \(1 pairs of 128x96\), got 1 pairs of 96x72"):
                score(larger, result)
    assert sparse_disparity_errors(scenes.batch.select([0]), result) is not None


# ------------------------------------------------------------------------------------------------- silent answers
@pytest.mark.parametrize("real", [0.0, -1.0, float("nan"), float("inf")])
def test_accuracy_needs_a_finite_positive_true_distance(real):
    """Was: ZeroDivisionError for 0, and 300 % for a true distance of −1 m against an estimate of 1 m."""
    with pytest.raises(InputError, match="real: expected a finite positive distance"):
        accuracy_pct(real, 1.0)
    assert accuracy_pct(np.float32(2.0), 1.9) == pytest.approx(95.0)


def test_a_nan_threshold_is_refused_not_turned_into_nan_masks(scenes):
    """Was: soft_segment_images(image, threshold=NaN) returned NaN masks without a word."""
    image = scenes.batch.left
    with pytest.raises(InputError, match="threshold: expected finite values, got nan"):
        soft_segment_images(image, torch.full((3,), float("nan")))



# ------------------------------------------------------------------------------------------------- kernel fuzz finds
def test_descriptors_refuse_a_keypoint_scale_that_is_not_finite_and_positive(scenes):
    """Found by the kernel fuzz (SVS_FUZZ_SCALE=40): a valid keypoint of scale -inf passed the border's memory check
    (its patch lay -inf px beyond the image) and overflowed math.ceil."""
    from svs_torch.features.descriptor import describe_surf

    keypoints = extract_surf_features(scenes.batch.left).keypoints
    for bad in (-float("inf"), float("nan"), 0.0, -1.0):
        scale = torch.where(keypoints.valid, keypoints.scale, 0.0)
        scale[0, 0] = bad
        with pytest.raises(InputError, match="keypoints.scale: expected finite positive scales at valid keypoints"):
            describe_surf(scenes.batch.left, dataclasses.replace(keypoints, scale=scale))


def test_match_sad_refuses_nan_descriptors_in_valid_rows(generator):
    """Found by the kernel fuzz (SVS_FUZZ_SCALE=40): a NaN descriptor row won the torch path's mutual check (NaN is
    argmin's least) while the kernel ignored it, so the two paths matched differently. Padding may hold anything."""
    left = torch.rand(1, 3, 4, generator=generator)
    right = torch.rand(1, 1, 4, generator=generator)
    left[0, 2, 3] = float("nan")
    with pytest.raises(InputError, match="desc_left: expected finite descriptors in valid rows"):
        match_sad(left, right, torch.ones(1, 3, dtype=torch.bool), torch.ones(1, 1, dtype=torch.bool), mutual=True)
    matches = match_sad(left, right, torch.tensor([[True, True, False]]), torch.ones(1, 1, dtype=torch.bool))
    assert matches.idx.shape == (1, 3) and matches.idx[0, 2] == -1


# ------------------------------------------------------------------------------------------------- images with grad
def test_the_hard_block_matchers_take_images_that_require_grad(scenes):
    """Found by the docstring audit of gradients: block_match_sad, dense_disparity_over_regions,
    coarse_search_range and estimate_dense_disparity raised 'minimum(): functions with out=... arguments don't
    support automatic differentiation' when an image required grad (a training loop's views). They are winner
    takes all: the answer is the one without gradients, and carries none."""
    from svs_torch.depth.dense import (DisparityRange, block_match_sad, coarse_search_range,
                                       dense_disparity_over_regions, estimate_dense_disparity)

    batch = scenes.batch
    left, right = batch.left.clone().requires_grad_(True), batch.right.clone().requires_grad_(True)
    mask = (scenes.object_ids > 0).view_as(batch.left)
    search = DisparityRange(torch.zeros(batch.batch_size, dtype=torch.int64), 32)
    calls = {
        "block_match_sad": lambda a, b: block_match_sad(a, b, 0, 32).disparity_px,
        "dense_disparity_over_regions": lambda a, b: dense_disparity_over_regions(a, b, mask, search).disparity_px,
        "coarse_search_range": lambda a, b: coarse_search_range(a, b, mask, batch.image_hw).min_disparity_px,
        "estimate_dense_disparity": lambda a, b: estimate_dense_disparity(a, b, mask).disparity_px,
    }
    for name, call in calls.items():
        with_grad = call(left, right)
        assert not with_grad.requires_grad, name
        assert torch.equal(with_grad, call(batch.left, batch.right)), name


# ------------------------------------------------------------------------------------------------- wrong containers
def _wrong_container_calls():
    from svs_torch.data import collate_stereo_batches, resize_stereo_batch
    from svs_torch.data.calibration import calibration_record
    from svs_torch.depth.dense import block_match_sad
    from svs_torch.evaluation import dense_map_metrics, object_truth, with_nominal_calibration
    from svs_torch.evaluation.disparity_errors import dense_disparity_errors
    from svs_torch.evaluation.overrides import apply_overrides
    from svs_torch.evaluation.report import csv_table
    from svs_torch.evaluation.stereo_metrics import measured_regions
    from svs_torch.pipeline import PipelineConfig, segment_pair
    from svs_torch.segmentation import SegmentationConfig
    from svs_torch.segmentation.learned import segment_stereo_learned

    image = torch.rand(1, 1, 24, 32, generator=torch.Generator().manual_seed(0))
    return [
        ("batch: expected a StereoBatch, got Tensor", lambda b: segment_pair(image, b.segmentation_config)),
        ("config: expected a SegmentationConfig, got PipelineConfig", lambda b: segment_pair(b.batch,
                                                                                              PipelineConfig())),
        ("batch: expected a StereoBatch, got str", lambda b: resize_stereo_batch("left.png", (32, 24))),
        ("batches[1]: expected a StereoBatch, got Tensor", lambda b: collate_stereo_batches([b.batch, image])),
        ("batches: expected a sequence of at least one StereoBatch, got one StereoBatch",
         lambda b: collate_stereo_batches(b.batch)),
        ("batch: expected a StereoBatch, got dict", lambda b: calibration_record({}, 0, "calib.txt")),
        ("result: expected a PipelineResult, got NoneType", lambda b: dense_map_metrics(b.batch, None)),
        ("result: expected a PipelineResult, got StereoBatch", lambda b: measured_regions(b.batch)),
        ("result: expected a PipelineResult, got NoneType", lambda b: dense_disparity_errors(b.batch, None)),
        ("segmentation: expected a Segmentation, got NoneType", lambda b: object_truth(b.batch, None)),
        ("batch: expected a StereoBatch, got Tensor", lambda b: with_nominal_calibration(image)),
        ("config: expected a PipelineConfig, got dict", lambda b: apply_overrides({}, {"seed": 1})),
        ("store: expected a ResultStore, got str", lambda b: csv_table("sweep.sqlite")),
        ("batch: expected a StereoBatch, got Tensor", lambda b: segment_stereo_learned(image, b.segmentation_config)),
        ("config: expected a DenseConfig, got PipelineConfig", lambda b: block_match_sad(image, image, 0, 8,
                                                                                          PipelineConfig())),
        ("network: expected an ObstacleNet for segmenter 'learned', got Linear", lambda b: estimate_obstacle_depth(
            b.batch, PipelineConfig(segmentation=SegmentationConfig(segmenter="learned")),
            network=torch.nn.Linear(2, 2))),
    ]


@pytest.mark.parametrize("index", range(16))
def test_a_wrong_container_is_named(index, scenes):
    """Found by calling each public function that takes a batch, a result, a configuration or a results store with
    something else (or a network of another kind): each was an AttributeError ('str' object has no attribute
    'size_hw', 'Linear' object has no attribute 'config') from inside."""
    message, call = _wrong_container_calls()[index]

    class Arguments:
        batch = scenes.batch
        segmentation_config = PipelineConfig().segmentation

    with pytest.raises(InputError, match=re.escape(message)):
        call(Arguments)


def test_the_library_calls_an_api_audit_found_unchecked():
    """Found by an audit of the Python API (each a silent wrong result or a deep error before)."""
    import dataclasses

    from svs_torch.core.types import StereoBatch
    from svs_torch.data import collate_stereo_batches
    from svs_torch.data.camera_frames import camera_frames
    from svs_torch.depth.dense import estimate_dense_disparity
    from svs_torch.depth.quantiles import kept_region_lower_median, masked_lower_median
    from svs_torch.segmentation.components import connected_components_with_stats
    from svs_torch.segmentation.segment import SegmentationConfig, keep_largest_regions, keep_regions
    from svs_torch.segmentation.soft import soft_segment_images

    mask = torch.zeros(1, 1, 20, 20, dtype=torch.bool)
    mask[0, 0, 2:5, 2:5] = mask[0, 0, 10:18, 10:18] = True
    labels, _, regions = connected_components_with_stats(mask)
    for message, call in [
        ("keep: expected 'largest', 'nearest' or 'nearest_first', got 'Largest'",  # ran as "nearest_first"
         lambda: keep_regions(labels, regions, 1, "Largest")),
        ("num_keep: expected an int from 0 to 255, got -1", lambda: keep_largest_regions(labels, regions, -1)),  # kept L - 1
        ("labels: expected an int tensor", lambda: keep_regions(labels.float(), regions, 1)),
        ("nearness: expected (1, 2), got (3)", lambda: keep_regions(labels, regions, 1, "nearest",
                                                                    nearness=torch.zeros(3))),
        ("mask: expected a bool tensor", lambda: masked_lower_median(torch.rand(2, 5), torch.ones(2, 5))),
        ("labels: expected (2, 1, 4, 4), got (3, 1, 4, 4)", lambda: kept_region_lower_median(
            torch.rand(2, 1, 4, 4), torch.ones(2, 1, 4, 4, dtype=torch.bool), torch.ones(3, 1, 4, 4, dtype=torch.long),
            torch.ones(2, 1, dtype=torch.long))),
        # 0-255 by mistake came out as all-white frames
        ("images: expected values in [0, 1], got min", lambda: camera_frames(torch.rand(2, 1, 8, 8) * 255 + 1, 4, 4.0,
                                                                            torch.Generator().manual_seed(0))),
        ("config.method: the soft segmentation relaxes Otsu's threshold ('otsu'), got 'canny'",
         lambda: soft_segment_images(torch.rand(1, 1, 16, 16), config=SegmentationConfig(method="canny"))),
        ("left: expected at least one pair, got an empty batch", lambda: estimate_dense_disparity(
            torch.rand(0, 1, 8, 8), torch.rand(0, 1, 8, 8), torch.ones(0, 1, 8, 8, dtype=torch.bool))),
    ]:
        with pytest.raises(InputError, match=re.escape(message)):
            call()
    assert camera_frames(torch.rand(0, 1, 8, 8), 4, 4.0, torch.Generator()).shape == (0, 1, 8, 8)
    batch = StereoBatch.from_images(torch.rand(3, 1, 8, 8), torch.rand(3, 1, 8, 8), 276.0, 0.1075)
    image_hw = batch.image_hw.clone()
    image_hw[1] = 0
    with pytest.raises(InputError, match=re.escape("image_hw: expected (height, width) rows with 1 <= height <= 8 "
                                                   "and 1 <= width <= 8 (the image tensors' size), got [0, 0]")):
        dataclasses.replace(batch, image_hw=image_hw)  # a later stage blamed left's "0x0" images
    image_hw[1] = torch.tensor([8, 9])
    with pytest.raises(InputError, match=re.escape("image_hw: expected (height, width) rows with 1 <= height <= 8 "
                                                   "and 1 <= width <= 8 (the image tensors' size), got [8, 9]")):
        dataclasses.replace(batch, image_hw=image_hw)  # the paper's path ranged such a pair in silence
    truth, known = torch.rand(3, 1, 8, 8), torch.ones(3, 1, 8, 8, dtype=torch.bool)
    truth[2, 0, 3, 3], known[1, 0, 3, 3] = float("inf"), False
    truth[1, 0, 3, 3] = float("nan")  # unknown: allowed
    with pytest.raises(InputError, match=re.escape("disparity_px: expected finite values where disparity_valid holds, "
                                                   "got NaN or inf for pair(s) [2] of 3")):
        dataclasses.replace(batch, disparity_px=truth, disparity_valid=known)  # scoring blamed "truth_px"
    known[2, 0, 3, 3] = False
    assert dataclasses.replace(batch, disparity_px=truth, disparity_valid=known).disparity_px is truth
    broken = batch.left.clone()
    broken[2, 0, 1, 1] = float("nan")
    with pytest.raises(InputError, match=re.escape("left: expected values in [0, 1], got NaN (image 2 of 3)")):
        collate_stereo_batches([dataclasses.replace(batch, left=broken)])  # which of a bulk run's pairs?
