"""A repeated pattern the dense map aliased a period off is ranged by its own inliers
(:mod:`svs_torch.pipeline.inlier_consensus`), and only where the map contradicts them where they lie."""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest
import torch

from svs_torch.cli import main
from svs_torch.core.types import StereoBatch
from svs_torch.data.rig_deviation import RigDeviation, deviate_view
from svs_torch.depth.dense_config import DenseDisparity
from svs_torch.depth.dense_objects import range_from_objects
from svs_torch.depth.depth_types import DepthResult, Disparities, ObjectDepths, PointDepths
from svs_torch.depth.sparse import nearest_obstacle
from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth
from svs_torch.pipeline.inlier_consensus import range_contradicted_by_inliers

HEIGHT, WIDTH, FOCAL_PX, BASELINE_M = 240, 320, 300.0, 0.1


def grate_pair(roll_deg: float, disparity_px: int = 20, period_px: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """A grate (crossing bars, ``period_px``) 120 × 140 px at ``disparity_px`` before a textured wall at 5 px, its
    right view turned by ``roll_deg`` (a loose rig): float32 views in [0, 1]."""
    rng = np.random.default_rng(1)

    def texture(sigma: float) -> np.ndarray:
        t = cv2.GaussianBlur(rng.random((HEIGHT, WIDTH + 64)).astype(np.float32), (0, 0), sigma)
        return (t - t.min()) / (t.max() - t.min())

    wall = texture(1.5) * 0.5 + 0.25
    left, right = wall[:, 32:32 + WIDTH].copy(), wall[:, 37:37 + WIDTH].copy()
    rows, cols = np.mgrid[0:HEIGHT, 0:WIDTH + 64]
    bars = ((cols % period_px) < period_px // 3) | ((rows % period_px) < period_px // 3)
    paint = 0.15 + 0.7 * bars.astype(np.float32) + 0.03 * texture(0.7)
    for view, shift in ((left, 0), (right, disparity_px)):
        view[60:200, 100 - shift:220 - shift] = paint[60:200, 132:252]
    return left, deviate_view(right, RigDeviation(roll_deg=roll_deg), FOCAL_PX)


def batch_of(pairs: list[tuple[np.ndarray, np.ndarray]]) -> StereoBatch:
    n = len(pairs)
    return StereoBatch(torch.from_numpy(np.stack([p[0] for p in pairs])).unsqueeze(1),
                       torch.from_numpy(np.stack([p[1] for p in pairs])).unsqueeze(1), torch.full((n,), FOCAL_PX),
                       torch.full((n,), BASELINE_M), torch.zeros(n), torch.ones(n, dtype=torch.bool),
                       torch.tensor([[HEIGHT, WIDTH]] * n))


def without_rule(config: PipelineConfig) -> PipelineConfig:
    return dataclasses.replace(config, depth=dataclasses.replace(config.depth, inliers_overrule_aliased=False))


def test_a_grate_behind_a_turned_right_camera_is_ranged_by_its_inliers():
    """Was: the grate at 1.5 m behind a right camera turned ±0.5° (row-aligned, then measured on the coarse grid,
    where its 12 px period halves) was ranged "OK" at 3.75 m, one period off, while its inliers all read 20 px."""
    batch = batch_of([grate_pair(0.5), grate_pair(-0.5)])
    truth_m = FOCAL_PX * BASELINE_M / 20
    result = estimate_obstacle_depth(batch, PipelineConfig())
    assert result.status.tolist() == [0, 0]
    np.testing.assert_allclose(result.depth.nearest.depth_m.numpy(), truth_m, rtol=0.02)
    slot = result.depth.nearest.slot
    assert result.depth.objects.ranged_by_inliers[torch.arange(2), slot].all()
    aliased = estimate_obstacle_depth(batch, without_rule(PipelineConfig()))
    assert (aliased.depth.nearest.depth_m > 2 * truth_m).all()  # what the rule mends
    assert aliased.depth.objects.ranged_by_inliers is None
    # One call, as training runs it: the object its inliers ranged keeps the hard depth (no aliased soft one).
    soft = estimate_obstacle_depth(batch, PipelineConfig(differentiable=True))
    torch.testing.assert_close(soft.depth.nearest.depth_m.detach(), result.depth.nearest.depth_m)


def test_estimate_json_says_which_objects_its_inliers_ranged(tmp_path, capsys):
    left, right = grate_pair(0.5)
    paths = [tmp_path / "left.png", tmp_path / "right.png"]
    for path, view in zip(paths, (left, right)):
        cv2.imwrite(str(path), np.rint(view * 255).astype(np.uint8))
    code = main(["estimate", *map(str, paths), "--focal-px", str(FOCAL_PX), "--baseline-m", str(BASELINE_M), "--json"])
    report = json.loads(capsys.readouterr().out)
    assert code == 0 and report["status"] == "OK" and abs(report["nearest_m"] - 1.5) < 0.03
    assert [o["ranged_by_inliers"] for o in report["objects"] if o["depth_m"] == report["nearest_m"]] == [True]
    main(["estimate", *map(str, paths), "--focal-px", str(FOCAL_PX), "--baseline-m", str(BASELINE_M)])
    assert "by its inliers" in capsys.readouterr().out


def depth_with(inlier_px: list[float], map_px: float, map_at_inliers_px: float | None = None):
    """One pair, one object: inliers at ``inlier_px`` on it, a dense map reading ``map_px`` over the object (its
    median) and ``map_at_inliers_px`` (default the same) at the inliers' own pixels."""
    k = len(inlier_px)
    disparity = torch.tensor([inlier_px], dtype=torch.float64)
    xy = torch.stack([torch.arange(k, dtype=torch.float64) * 2 + 10, torch.full((k,), 20.0)], -1).unsqueeze(0)
    scale = FOCAL_PX * BASELINE_M
    points = PointDepths(scale / disparity, torch.ones(1, k, dtype=torch.bool))
    dense_map = torch.full((1, 1, 40, 60), map_px, dtype=torch.float64)
    dense_map[0, 0, 20, 10:10 + 2 * k:2] = map_px if map_at_inliers_px is None else map_at_inliers_px
    dense = DenseDisparity(dense_map, torch.ones_like(dense_map, dtype=torch.bool), torch.zeros(1), 64,
                           torch.tensor([[0, 0, 60, 40]]), torch.tensor([64]))
    one = torch.ones(1, 1)
    objects = ObjectDepths(torch.ones(1, 1, dtype=torch.long), torch.full((1, 1), 500), one * 30, torch.ones(1, 1,
                           dtype=torch.long), torch.full((1, 1), k), one * scale / map_px, one * scale / map_px * 0.9,
                           one * scale / map_px * 1.1, torch.ones(1, 1, dtype=torch.bool),
                           torch.zeros(1, k, dtype=torch.long))
    objects = dataclasses.replace(objects, **{f: getattr(objects, f).double() for f in
                                              ("depth_median_m", "depth_low_m", "depth_high_m")})
    depth = DepthResult(Disparities(disparity, torch.zeros_like(disparity), torch.ones(1, k, dtype=torch.bool)),
                        points, range_from_objects(objects, torch.tensor([FOCAL_PX]), torch.tensor([BASELINE_M]),
                                                   torch.zeros(1)), objects, nearest_obstacle(objects))
    return depth, dense, xy, torch.ones(1, k, dtype=torch.bool)


def ranged(depth, dense, xy, inliers) -> DepthResult:
    return range_contradicted_by_inliers(depth, dense, xy, inliers, torch.eye(3, dtype=torch.float64)[None],
                                         torch.tensor([FOCAL_PX]), torch.tensor([BASELINE_M]), torch.zeros(1), 1.0)


def test_the_rule_overrules_only_a_map_that_contradicts_a_consensus_where_it_lies():
    consensus = [20.0 + 0.05 * i for i in range(-5, 6)]
    out = ranged(*depth_with(consensus, 8.0))  # the map aliased everywhere: overruled
    assert bool(out.objects.ranged_by_inliers[0, 0])
    assert abs(float(out.nearest.depth_m[0]) - 1.5) < 0.01 and abs(float(out.range.r_min_m[0]) - 1.5) < 0.01
    # With two aliased inliers among them (RANSAC keeps a period's aliases too), over the consensus only.
    out = ranged(*depth_with(consensus + [8.0, 32.0], 8.0))
    low, high = float(out.objects.depth_low_m[0, 0]), float(out.objects.depth_high_m[0, 0])
    assert 30 / 20.25 <= low < high <= 30 / 19.75  # not 0.94 m nor 3.75 m
    kept = [(depth_with(consensus, 8.0, map_at_inliers_px=20.0), 8.0),  # the map confirms them where they lie
            (depth_with(consensus[:4], 8.0), 8.0),  # too few
            (depth_with([20.0] * 6 + [12.0] * 6, 8.0), 8.0),  # no consensus
            (depth_with(consensus, 18.5), 18.5)]  # within a few pixels of them
    for case, map_px in kept:
        out = ranged(*case)
        assert not bool(out.objects.ranged_by_inliers[0, 0])
        assert float(out.objects.depth_median_m[0, 0]) == pytest.approx(FOCAL_PX * BASELINE_M / map_px, rel=1e-6)
