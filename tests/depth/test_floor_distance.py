"""Distances ahead along the floor (svs_torch.depth.floor_distance): the geometry read from the floor's plane in
disparity, checked against a camera posed by hand, and the objects' distances against scenes built from the world's
side (a wall standing on the floor, the renderer's walker scenes)."""

from __future__ import annotations

import math

import pytest
import torch

from svs_torch.depth.dense_config import DenseDisparity
from svs_torch.depth.depth_types import ObjectDepths
from svs_torch.depth.floor_distance import floor_distances, floor_geometry

FOCAL_PX, BASELINE_M, H, W = 276.0, 0.1075, 120, 160


def posed_camera(height_m: float, pitch_deg: float, roll_deg: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The floor's unit normal (down) and the unit vector ahead along it, in the frame of a camera pitched down by
    ``pitch_deg`` and rolled by ``roll_deg`` (x right, y down, z along the axis), built by rotating the world."""
    pitch, roll = math.radians(pitch_deg), math.radians(roll_deg)
    # world: x right, y down, z ahead; the camera's axes are the world's turned down about x, then about its axis.
    turn_x = torch.tensor([[1, 0, 0], [0, math.cos(pitch), math.sin(pitch)], [0, -math.sin(pitch), math.cos(pitch)]],
                          dtype=torch.float64)  # its columns: the camera's axes in the world (z: (0, sin θ, cos θ))
    turn_z = torch.tensor([[math.cos(roll), -math.sin(roll), 0], [math.sin(roll), math.cos(roll), 0], [0, 0, 1]],
                          dtype=torch.float64)
    to_camera = (turn_x @ turn_z).T  # world vectors into the camera's frame
    return to_camera @ torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), to_camera @ torch.tensor(
        [0.0, 0.0, 1.0], dtype=torch.float64)


def plane_coefficients(height_m: float, normal: torch.Tensor) -> torch.Tensor:
    """``a, b, c`` of the floor's ``d = a·x + b·y + c`` at the pixels of an H × W view (from ``Z·(n·r) = h``)."""
    cx, cy = (W - 1) / 2, (H - 1) / 2
    a, b = BASELINE_M * normal[0] / height_m, BASELINE_M * normal[1] / height_m
    c = BASELINE_M * FOCAL_PX * normal[2] / height_m - a * cx - b * cy
    return torch.stack([a, b, c]).view(1, 3).to(torch.float32)


def rig(b: int = 1) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return torch.full((b,), FOCAL_PX), torch.full((b,), BASELINE_M), torch.zeros(b)


@pytest.mark.parametrize("height_m,pitch_deg,roll_deg", [(1.3, 20.0, 0.0), (1.0, 30.0, 5.0), (1.6, 10.0, -8.0)])
def test_the_camera_s_height_and_pitch_and_the_way_ahead_are_read_from_the_floor_s_plane(height_m, pitch_deg,
                                                                                          roll_deg):
    normal, ahead = posed_camera(height_m, pitch_deg, roll_deg)
    focal, baseline, doffs = rig()
    floor = floor_geometry(plane_coefficients(height_m, normal), torch.tensor([True]), focal, baseline, doffs, (H, W))
    assert bool(floor.found[0])
    assert float(floor.camera_height_m[0]) == pytest.approx(height_m, rel=1e-4)
    # the axis's angle below the floor's horizontal: the pitch, whatever the roll about the axis
    assert float(floor.pitch_deg[0]) == pytest.approx(pitch_deg, abs=1e-3)
    assert torch.allclose(floor.ahead[0].double(), ahead / ahead.norm(), atol=1e-5)


def test_a_floor_not_found_or_a_rig_without_a_baseline_has_no_geometry():
    normal, _ = posed_camera(1.3, 20.0, 0.0)
    coefficients = plane_coefficients(1.3, normal).expand(3, 3)
    focal, baseline, doffs = rig(3)
    floor = floor_geometry(coefficients, torch.tensor([True, False, True]), focal,
                           torch.tensor([BASELINE_M, BASELINE_M, 0.0]), doffs, (H, W))
    assert floor.found.tolist() == [True, False, False]
    assert (floor.camera_height_m[1:] == 0).all() and (floor.pitch_deg[1:] == 0).all() and (floor.ahead[1:] == 0).all()


def upright_wall(height_m: float, pitch_deg: float, roll_deg: float, ahead_m: float) -> torch.Tensor:
    """``(1, 1, H, W)`` the disparity of a wall standing across the floor ``ahead_m`` ahead (the points ``P`` with
    ``P · u = ahead_m``) as the posed camera sees it: ``Z = ahead_m / (r · u)``."""
    _, ahead = posed_camera(height_m, pitch_deg, roll_deg)
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    rays = torch.stack([(xs - (W - 1) / 2) / FOCAL_PX, (ys - (H - 1) / 2) / FOCAL_PX, torch.ones_like(xs)], -1)
    depth = ahead_m / (rays @ ahead)
    return (FOCAL_PX * BASELINE_M / depth).view(1, 1, H, W).to(torch.float32)


def one_object(labels: torch.Tensor) -> ObjectDepths:
    one = torch.ones(1, 1, dtype=torch.int64)
    zero = torch.zeros(1, 1)
    return ObjectDepths(label=one, area_px=labels.flatten(1).sum(1, keepdim=True), centroid_x_px=zero, side=one,
                        num_inliers=one, depth_median_m=zero, depth_low_m=zero, depth_high_m=zero,
                        valid=torch.ones(1, 1, dtype=torch.bool), point_slot=torch.full((1, 4), -1))


@pytest.mark.parametrize("height_m,pitch_deg,roll_deg", [(1.3, 20.0, 0.0), (1.0, 30.0, 6.0)])
def test_every_part_of_a_wall_standing_on_the_floor_is_as_far_ahead_as_its_foot(height_m, pitch_deg, roll_deg):
    """The camera's axis depth of an upright wall 1.1 m ahead spreads over 0.15 m; its distance ahead along the
    floor is 1.1 m at every pixel, so its median and both percentiles are."""
    normal, _ = posed_camera(height_m, pitch_deg, roll_deg)
    disparity = upright_wall(height_m, pitch_deg, roll_deg, 1.1)
    labels = torch.zeros(1, 1, H, W, dtype=torch.int64)
    labels[..., 10:110, 40:120] = 1
    dense = DenseDisparity(disparity_px=disparity, valid=torch.ones_like(disparity, dtype=torch.bool),
                           min_disparity_px=torch.zeros(1, dtype=torch.int64), num_disparities=64,
                           crop_xywh=torch.tensor([[0, 0, W, H]]), pair_num_disparities=torch.tensor([64]))
    focal, baseline, doffs = rig()
    floor = floor_geometry(plane_coefficients(height_m, normal), torch.tensor([True]), focal, baseline, doffs, (H, W))
    out = floor_distances(floor, dense, labels, one_object(labels), focal, baseline, doffs,
                          torch.tensor([False]), torch.eye(3).unsqueeze(0))
    axis = (FOCAL_PX * BASELINE_M / disparity)[labels.bool()]
    assert float(axis.max() - axis.min()) > 0.12  # what the camera's axis says of it
    for statistic in (out.objects.depth_median_m, out.objects.depth_low_m, out.objects.depth_high_m):
        assert float(statistic[0, 0]) == pytest.approx(1.1, rel=2e-3)
    assert bool(out.nearest.valid[0]) and float(out.nearest.surface_m[0]) == pytest.approx(1.1, rel=2e-3)
    # a homography-rectified pair's pixels are taken back to the input's first: a shift of 3 rows moves them back
    shifted = torch.tensor([[[1.0, 0, 0], [0, 1, 3], [0, 0, 1]]])
    moved = DenseDisparity(disparity_px=torch.roll(disparity, 3, dims=2), valid=dense.valid,
                           min_disparity_px=dense.min_disparity_px, num_disparities=64, crop_xywh=dense.crop_xywh,
                           pair_num_disparities=dense.pair_num_disparities)
    out = floor_distances(floor, moved, torch.roll(labels, 3, dims=2), one_object(labels), focal, baseline, doffs,
                          torch.tensor([True]), shifted)
    assert float(out.objects.depth_median_m[0, 0]) == pytest.approx(1.1, rel=2e-3)


def test_without_a_floor_no_object_has_a_distance_ahead():
    normal, _ = posed_camera(1.3, 20.0, 0.0)
    disparity = upright_wall(1.3, 20.0, 0.0, 1.1)
    labels = torch.ones(1, 1, H, W, dtype=torch.int64)
    dense = DenseDisparity(disparity_px=disparity, valid=torch.ones_like(disparity, dtype=torch.bool),
                           min_disparity_px=torch.zeros(1, dtype=torch.int64), num_disparities=64,
                           crop_xywh=torch.tensor([[0, 0, W, H]]), pair_num_disparities=torch.tensor([64]))
    focal, baseline, doffs = rig()
    floor = floor_geometry(plane_coefficients(1.3, normal), torch.tensor([False]), focal, baseline, doffs, (H, W))
    out = floor_distances(floor, dense, labels, one_object(labels), focal, baseline, doffs, torch.tensor([False]),
                          torch.eye(3).unsqueeze(0))
    assert not bool(out.objects.valid.any()) and not bool(out.nearest.valid.any())
    assert float(out.objects.depth_median_m.abs().sum()) == 0.0


def test_the_pipeline_says_how_far_ahead_a_heap_on_a_rendered_floor_lies():
    """Guide's configuration on a rendered walker's view (a camera 1.3 m over the floor pitched 20°, a heap of rocks
    and a box): the floor is found at the rendered height and pitch, and each kept object's distance ahead matches
    the renderer's own (its ``depth · (cos θ − sin θ · (y − cy) / f)`` over the object's pixels) within 5 %, where
    the camera's axis depth of the heap's nearest part is 25 % farther."""
    from svs_torch.data.synthetic import render_obstacle_scenes
    from svs_torch.pipeline import PipelineConfig, PipelineStatus, estimate_obstacle_depth

    pitch = math.radians(20.0)
    scenes = render_obstacle_scenes(torch.tensor([[1.6]]), torch.tensor([[[0.5, 0.2]]]), torch.tensor([[[0.4, 0.5]]]),
                                    generator=torch.Generator().manual_seed(3), floor_height_m=1.3,
                                    camera_pitch_deg=20.0, heaps=torch.tensor([[-0.3, 1.2, 0.45, 0.35]]))
    result = estimate_obstacle_depth(scenes.batch, PipelineConfig().for_guide())
    assert int(result.status[0]) == PipelineStatus.OK
    floor = result.floor.floor
    assert bool(floor.found[0])
    assert float(floor.camera_height_m[0]) == pytest.approx(1.3, rel=0.08)
    assert float(floor.pitch_deg[0]) == pytest.approx(20.0, abs=3.0)
    h = scenes.depth_m.shape[-2]
    rows = torch.arange(h, dtype=torch.float32).view(1, 1, h, 1)
    true_ahead = scenes.depth_m * (math.cos(pitch) - math.sin(pitch) * (rows - (h - 1) / 2) / scenes.batch.focal_px)
    objects, ahead = result.depth.objects, result.floor.objects
    checked = 0
    for slot, label in enumerate(objects.label[0].tolist()):
        if label < 0 or not bool(objects.valid[0, slot]):
            continue
        on = result.object_labels == label
        assert bool(ahead.valid[0, slot])
        assert float(ahead.depth_median_m[0, slot]) == pytest.approx(float(true_ahead[on].median()), rel=0.05)
        assert float(ahead.depth_low_m[0, slot]) == pytest.approx(float(true_ahead[on].quantile(0.1)), rel=0.05)
        checked += 1
    assert checked == 2
    heap_slot = int(result.floor.nearest.slot[0])
    on = result.object_labels == int(objects.label[0, heap_slot])
    assert float((on & scenes.heap_mask).sum()) > 0.9 * float(on.sum())  # the heap is nearest along the floor
    assert float(objects.depth_low_m[0, heap_slot]) > 1.25 * float(true_ahead[on].quantile(0.1))


def test_a_camera_pitched_as_worn_looks_ahead_as_the_posed_one():
    from svs_torch.depth.floor_distance import pitched_camera

    _, ahead = posed_camera(1.3, 20.0, 0.0)
    floor = pitched_camera(20.0, 2)
    assert floor.found.tolist() == [True, True] and floor.pitch_deg.tolist() == [20.0, 20.0]
    assert torch.allclose(floor.ahead.double(), ahead.expand(2, 3), atol=1e-6)


@pytest.mark.parametrize("call, message", [
    (lambda: floor_geometry(torch.zeros(2, 3), torch.ones(2), *rig(2), (H, W)), "found: expected a bool tensor"),
    (lambda: floor_geometry(torch.zeros(2, 3), torch.ones(2, dtype=torch.bool), torch.ones(3), *rig(2)[1:], (H, W)),
     "focal_px: expected (2)"),
    (lambda: floor_geometry(torch.zeros(1, 3), torch.ones(1, dtype=torch.bool), *rig(), (H, -1)),
     "image_hw: expected (height, width)"),
    (lambda: __import__("svs_torch.depth.floor_distance", fromlist=["x"]).refit_floor_plane(
        torch.zeros(1, 1, 4, 4), torch.ones(1, 1, 4, 5, dtype=torch.bool), torch.zeros(1, 3),
        torch.ones(1, dtype=torch.bool), torch.ones(1)), "on_plane: expected (1, 1, 4, 4)"),
    (lambda: __import__("svs_torch.depth.floor_distance", fromlist=["x"]).pitched_camera(90.0, 1),
     "pitch_deg: expected a finite number in (-90, 90)"),
])
def test_bad_arguments_are_refused_by_name(call, message):
    from svs_torch.core.errors import InputError

    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")):
        call()


def test_the_nearest_part_ahead_leaves_out_matches_above_the_in_view_top():
    """A wall 1.1 m ahead whose map holds noise's wrong matches far above the pair's in-view top on 15 % of its
    pixels: its nearest part ahead is measured over the map's own pixels at or below that top (chosen on the map's
    disparities, not the distances ahead), as the depth's is, so it stays 1.1 m; over every pixel it came near."""
    normal, _ = posed_camera(1.3, 20.0, 0.0)
    disparity = upright_wall(1.3, 20.0, 0.0, 1.1)
    top = int(disparity.max().ceil())
    disparity[..., 40:52] = 3 * top  # 12 of the object's 80 columns
    labels = torch.zeros(1, 1, H, W, dtype=torch.int64)
    labels[..., 10:110, 40:120] = 1
    dense = DenseDisparity(disparity_px=disparity, valid=torch.ones_like(disparity, dtype=torch.bool),
                           min_disparity_px=torch.zeros(1, dtype=torch.int64), num_disparities=4 * top,
                           crop_xywh=torch.tensor([[0, 0, W, H]]), pair_num_disparities=torch.tensor([4 * top]),
                           in_view_top_px=torch.tensor([top]))
    focal, baseline, doffs = rig()
    floor = floor_geometry(plane_coefficients(1.3, normal), torch.tensor([True]), focal, baseline, doffs, (H, W))
    outs = [floor_distances(floor, dense, labels, one_object(labels), focal, baseline, doffs, torch.tensor([False]),
                            torch.eye(3).unsqueeze(0), surface_within_in_view_top=within) for within in (True, False)]
    assert float(outs[0].nearest.surface_m[0]) == pytest.approx(1.1, rel=2e-3)
    assert float(outs[1].nearest.surface_m[0]) < 0.5
    assert float(outs[0].objects.depth_median_m[0, 0]) == float(outs[1].objects.depth_median_m[0, 0])
