"""A thin pole nearer than everything else is warned of (issue 32, item 2; experiments/thin_obstacles.md): the
nearness segmenter keeps a region under its least area where it is the nearest (``near_min_area_fraction``)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from svs_torch.data.synthetic import render_obstacle_scenes
from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth


def _pole_beside_a_box(width_m: float, depth_m: float, offset_m: float, seed: int):
    """A 1.6 m pole ``width_m`` wide at ``depth_m``, a 0.8 m box at 2.4 m on its other side, the wall at 4 m."""
    return render_obstacle_scenes(torch.tensor([[depth_m, 2.4]]),
                                  torch.tensor([[[offset_m, 0.0], [0.45 if offset_m < 0 else -0.45, 0.1]]]),
                                  torch.tensor([[[width_m, 1.6], [0.8, 0.8]]]),
                                  generator=torch.Generator().manual_seed(seed), texture_contrast=0.5).batch


@pytest.mark.parametrize("offset_m", [-0.1, 0.3])
def test_a_thin_near_pole_is_the_nearest_obstacle(offset_m):
    batch = _pole_beside_a_box(0.03, 1.6, offset_m, seed=1)  # 5 px wide at 320x240
    config = PipelineConfig()
    nearest = estimate_obstacle_depth(batch, config).depth.nearest
    assert bool(nearest.valid[0]) and abs(float(nearest.depth_m[0]) - 1.6) < 0.1  # the pole, not the box at 2.4
    assert abs(float(nearest.surface_m[0]) - 1.6) < 0.1  # guide's warning distance
    # Without the rule the pole (under the least area of 0.3 % of the image) is dropped for the box.
    off = dataclasses.replace(config, segmentation=dataclasses.replace(config.segmentation,
                                                                       near_min_area_fraction=0.0))
    assert abs(float(estimate_obstacle_depth(batch, off).depth.nearest.depth_m[0]) - 2.4) < 0.1
