"""The floor is not an obstacle (issue 32): the nearness segmenter's ground plane on real scenes with a floor
(the shared KITTI street pairs, Middlebury Motorcycle), through the whole pipeline, with gradients."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from conftest import assert_differentiable_depths_are_the_hard_ones

from svs_torch.data import load_stereo_pair, resize_stereo_batch
from svs_torch.evaluation import with_nominal_calibration
from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth
from svs_torch.segmentation.ground_plane import GroundPlaneConfig, fit_ground_plane
from svs_torch.segmentation.learned import obstacle_truth
from svs_torch.segmentation.nearness import NearnessNetConfig

SCENES = ("kitti/stereo2015_training/image_2/000000_10.png", "kitti/stereo2012_training/colored_0/000000_10.png",
          "middlebury_eval3_Q/Motorcycle")


def scene(data_dir, relative: str, width: int = 320):
    path = data_dir / relative
    batch = with_nominal_calibration(load_stereo_pair(path if path.is_file() else path))
    h, w = batch.size_hw
    return resize_stereo_batch(batch, (width, round(h * width / w)))


def true_floor(batch) -> torch.Tensor:
    """The ground plane of the true disparity: the floor a walker's truth leaves out."""
    factor = NearnessNetConfig().working_factor(batch.left.shape[-1])
    plane = fit_ground_plane(batch.disparity_px.nan_to_num(0.0, 0.0, 0.0), batch.disparity_valid, batch.baseline_m,
                             GroundPlaneConfig(), factor)
    assert bool(plane.found.all())
    return plane.mask


def with_ground(config: PipelineConfig, ground: GroundPlaneConfig | None) -> PipelineConfig:
    return dataclasses.replace(config, segmentation=dataclasses.replace(config.segmentation, ground=ground))


@pytest.mark.parametrize("relative", SCENES)
def test_the_floor_is_not_kept_where_it_was(data_dir, relative):
    batch = scene(data_dir, relative)
    floor = true_floor(batch)
    on = estimate_obstacle_depth(batch, with_ground(PipelineConfig(), GroundPlaneConfig()))
    off = estimate_obstacle_depth(batch, with_ground(PipelineConfig(), None))

    def floor_kept(result):  # pixels of the true floor kept (KITTI's truth is sparse: counted where it has one)
        return float((result.segmentation.left.kept_mask & floor).sum())

    # Without the rule the floor (the road) is the near side the segmenter keeps: a fifth of the view or more.
    assert floor_kept(off) > 0.2 * float(floor.sum())
    assert floor_kept(on) < 0.15 * floor_kept(off)  # Motorcycle: 13 % (the floor between its wheels, in shade)
    assert bool(on.depth.nearest.valid[0])  # and something that is not the floor is ranged


def test_the_camera_height_of_a_street_pair_is_a_cars(data_dir):
    """KITTI's camera is 1.65 m above the road (its rig's published setup); the plane of the measured disparity
    gives it from the baseline alone."""
    batch = scene(data_dir, SCENES[0])
    config = NearnessNetConfig()
    from svs_torch.segmentation.nearness import measure_nearness_disparity

    measured = measure_nearness_disparity(batch.left, batch.right, config)
    plane = fit_ground_plane(measured.disparity_px, measured.measured, batch.baseline_m, GroundPlaneConfig(),
                             config.working_factor(batch.left.shape[-1]))
    assert bool(plane.found[0]) and 1.5 < float(plane.camera_height_m[0]) < 1.95


def test_the_walkers_truth_leaves_the_floor_out(data_dir):
    batch = scene(data_dir, SCENES[2])
    issue, walker = obstacle_truth(batch), obstacle_truth(batch, floor=GroundPlaneConfig())
    floor = true_floor(batch)
    assert float((issue.kept_mask & floor).sum()) > 0.2 * float(issue.kept_mask.sum())
    assert not bool((walker.kept_mask & floor).any())


def test_gradients_flow_through_the_pipeline_with_the_floor_left_out(data_dir):
    batch = scene(data_dir, SCENES[2], width=160)
    config = dataclasses.replace(with_ground(PipelineConfig(), GroundPlaneConfig()), differentiable=True)
    left, right = batch.left.clone().requires_grad_(), batch.right.clone().requires_grad_()
    result = estimate_obstacle_depth(dataclasses.replace(batch, left=left, right=right), config)
    hard = estimate_obstacle_depth(batch, with_ground(PipelineConfig(), GroundPlaneConfig()))
    # The floor left out is a constant of the hard pass: the same regions are kept as without gradients.
    assert torch.equal(result.segmentation.left.kept_mask, hard.segmentation.left.kept_mask)
    assert bool(result.segmentation.left.kept_mask.any())
    assert_differentiable_depths_are_the_hard_ones(result, left, right)


def test_the_paper_preset_and_the_other_segmenters_never_look_for_a_floor():
    assert PipelineConfig.paper().segmentation.ground is None


def test_guides_settings_are_a_camera_frames_and_the_floor_left_out_with_its_own_settings():
    """``SegmentationConfig.with_floor`` / ``for_guide``: what ``--floor on|off`` and ``svs-depth guide`` (and its
    benchmark) run: the floor's own settings kept where given, else the defaults; off: none; guide: camera frames."""
    from svs_torch.segmentation.segment import SegmentationConfig

    base = PipelineConfig().segmentation
    assert base.ground is None and not base.camera_frames
    assert base.with_floor(True).ground == GroundPlaneConfig() and base.with_floor(False).ground is None
    own = dataclasses.replace(base, ground=GroundPlaneConfig(max_camera_height_m=2.0))
    assert own.with_floor(True).ground.max_camera_height_m == 2.0
    guide = own.for_guide()
    assert guide.camera_frames and guide.ground.max_camera_height_m == 2.0
    assert base.for_guide(floor_left_out=False) == dataclasses.replace(base, camera_frames=True)
    assert isinstance(guide, SegmentationConfig) and guide.segmenter == base.segmenter
