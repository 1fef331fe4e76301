"""The side said with a distance is that of the part it was measured on (:mod:`svs_torch.pipeline.near_side`)."""

from __future__ import annotations

import dataclasses
import sys

import pytest
import torch
from conftest import REPO_ROOT

from svs_torch.capture.guide import STOP, WarningPolicy
from svs_torch.cli.guide_floor import FloorMemory
from svs_torch.data.synthetic import render_obstacle_scenes
from svs_torch.depth.depth_types import ObstacleSide
from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth

sys.path.insert(0, str(REPO_ROOT / "experiments"))

import real_rig  # noqa: E402


def _guide_ranges(depths_m, centres_m, sizes_m, yaw_deg=None):
    """One rendered 320×240 pair ranged as ``guide`` ranges it (its configuration, no floor in view)."""
    scenes = render_obstacle_scenes(torch.tensor([depths_m]), torch.tensor([centres_m]), torch.tensor([sizes_m]),
                                    generator=torch.Generator().manual_seed(0),
                                    object_yaw_deg=None if yaw_deg is None else torch.tensor([[yaw_deg]]))
    with torch.inference_mode():
        return estimate_obstacle_depth(scenes.batch, PipelineConfig().for_guide())


def test_two_touching_boxes_in_one_region_are_said_on_the_side_of_the_nearer():
    """A known fault of guide's: a box at 0.88 m in the right third, touching one at 1.6 m over the middle, is kept as
    one region; guide said "Obstacle ahead" (the region reaches across the middle column) at 0.88 m, the right box's
    distance. Its side is now the right box's; the distances stay as they were."""
    result = _guide_ranges([1.6, 0.88], [[-0.24, 0.0], [0.22, 0.0]], [[0.9, 0.6], [0.25, 0.4]])
    objects = result.depth.objects
    assert objects.valid.sum().item() == 1 and float(objects.depth_median_m.max()) > 1.5  # one region over both
    nearest, along, _ = FloorMemory().nearest(result, 0.0)  # what guide warns on
    assert along == "axis" and abs(float(nearest.surface_m[0]) - 0.88) < 0.02
    side = ObstacleSide(int(nearest.side[0])).name.lower()
    assert side == "right"
    assert WarningPolicy.message(STOP, float(nearest.surface_m[0]), side) == "Stop. Obstacle on the right at 0.8 metres"


@pytest.mark.parametrize("centre_x_m, yaw_deg, side", [(0.0, None, ObstacleSide.CENTRE), (0.25, None, ObstacleSide.RIGHT),
                                                       (-0.25, None, ObstacleSide.LEFT), (0.05, 40.0, ObstacleSide.CENTRE)])
def test_one_box_keeps_its_region_s_side(centre_x_m, yaw_deg, side):
    """One box facing the cameras (every measured pixel near its low percentile), or turned 40° (its depths run on
    from its near edge to its far one, none of them a second surface): the side of its whole region, as before."""
    result = _guide_ranges([1.0], [[centre_x_m, 0.0]], [[0.4, 0.5]], yaw_deg)
    assert result.depth.objects.side.tolist()[0][0] == side and result.depth.nearest.side.tolist() == [side]


def test_an_object_ranged_over_its_near_surface_takes_that_surface_s_side():
    """A rendered box joined by camera noise to the wall behind it (test_near_surface's digit 8 frame of scene 8) is
    ranged over the box (near_surface); its side was still the whole region's, the centre, where the box is on the
    left."""
    scenes = real_rig.synthetic_scenes()
    frame = [v for v in real_rig.conditions(scenes[8], 8, noise_seed=2) if v[0] == "jpeg q8 + noise s8"]
    batch = real_rig.stack_conditions(scenes[8], frame)
    base = PipelineConfig()
    result = estimate_obstacle_depth(batch, dataclasses.replace(
        base, dense=dataclasses.replace(base.dense, smoothing_intensity_weight=0.0)))
    assert result.near_surface.tolist() == [[False, True]]
    assert result.depth.objects.side.tolist() == [[ObstacleSide.CENTRE, ObstacleSide.LEFT]]
