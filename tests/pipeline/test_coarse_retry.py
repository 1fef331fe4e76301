"""The dense stage's coarse second pass (issue 33, item 1: camera frames): a pair whose dense map measured too little
of its kept regions is measured again at half the working width (``PipelineConfig.coarse_retry_below_share``).

The frames are experiments/real_rig.py's, with its seeds: MiddEval3 Pipes (the tuned split's seventh scene) at
320×240 with both views' contrast halved (``--contrast 0.5``, its tuning set for camera frames), JPEG at the board's
digits 7 and 8 after sensor noise σ 6 and 8.
"""

from __future__ import annotations

import dataclasses
import sys

import pytest
import torch
from conftest import REPO_ROOT

from svs_torch import InputError
from svs_torch.core.pair_trees import take_pairs
from svs_torch.depth import DepthConfig
from svs_torch.depth.dense_config import DenseConfig
from svs_torch.evaluation import evaluate_result
from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth
from svs_torch.pipeline.ranging import coarse_config, coarse_is_better

sys.path.insert(0, str(REPO_ROOT / "experiments"))

import real_rig  # noqa: E402

#: Pipes' index in the tuned split: real_rig.conditions seeds its noise with it.
PIPES_SCENE_INDEX = 6


@pytest.fixture(scope="module")
def pipes_frames(data_dir):
    """A batch of Pipes at half contrast: the clean pair, then digit 7 + σ 6 and digit 8 + σ 8."""
    scene = real_rig.resample(real_rig.load_scene(data_dir / "middlebury_eval3_Q" / "Pipes"), "320x240")
    scene = real_rig.dimmed(scene, 0.5)
    views = [v for v in real_rig.conditions(scene, PIPES_SCENE_INDEX)
             if v[0] in ("clean", "jpeg q7 + noise s6", "jpeg q8 + noise s8")]
    assert [v[0] for v in views] == ["clean", "jpeg q7 + noise s6", "jpeg q8 + noise s8"]
    return real_rig.stack_conditions(scene, views)


def _accuracy(batch, result) -> list[float]:
    return [e.acc_objects_pct for e in evaluate_result(batch, result)]


def test_noisy_pairs_ranged_wrong_are_measured_on_the_coarse_grid(pipes_frames):
    """Both noisy pairs are ranged and verified at the working width, but off (measured 93.3 and 72.6 %; 79.7
    and 72.0 % over the whole kept regions, before their interiors); the coarse pass measures them at 96.2 and
    91.3 %. The clean pair measures most of its pixels and is not measured again: its result is bit for bit the
    one without the pass. A noisy pair alone gets what it gets in the batch. (With the 7×7 nearness map these
    frames were chosen for: with the default's wider window for noisy pairs the working-width pass already
    measures the digit 7 pair at 96.9 %.)"""
    from conftest import seven_by_seven_nearness

    narrow = seven_by_seven_nearness()
    on = estimate_obstacle_depth(pipes_frames, network=narrow)
    off = estimate_obstacle_depth(pipes_frames, dataclasses.replace(PipelineConfig(), coarse_retry_below_share=None),
                                  network=narrow)
    acc_on, acc_off = _accuracy(pipes_frames, on), _accuracy(pipes_frames, off)
    assert on.coarse.tolist() == [False, True, True] and not bool(off.coarse.any())
    assert bool(on.verified.all()) and bool(off.verified.all())
    assert acc_off[1] < 94 and acc_off[2] < 80
    assert acc_on[1] > 95.5 and acc_on[2] > 90
    assert acc_on[0] == acc_off[0] > 97
    assert torch.equal(on.depth.objects.depth_median_m[0], off.depth.objects.depth_median_m[0])
    alone_batch = take_pairs(pipes_frames, torch.tensor([1]), 3)
    alone = estimate_obstacle_depth(alone_batch, network=narrow)
    assert bool(alone.coarse[0])
    assert torch.equal(alone.depth.objects.depth_median_m[0], on.depth.objects.depth_median_m[1])


def test_differentiable_depths_of_a_coarse_pair_are_the_hard_ones(pipes_frames, data_dir):
    """The differentiable pass (issue 31) recomputes a coarse pair on the coarse working grid (its winners
    picked on the aggregated volume, its sub-pixel fit on the plain costs, as the pass recomputes them), and a pair
    the smoothed retry measured at the coarse width through a blur of the coarse grid's σ (MiddEval3 Jadeplant at half
    contrast, digit 6 + σ 6: unranged at the working width, with the whole-view verification off, which verifies
    it before any retry): every object within 0.5 % of the hard value, with gradients to both images of that pair
    only. (Pipes with the 7×7 nearness map, which sends its noisy pair through the retry.)"""
    from conftest import seven_by_seven_nearness

    jadeplant = real_rig.dimmed(real_rig.resample(
        real_rig.load_scene(data_dir / "middlebury_eval3_Q" / "Jadeplant"), "320x240"), 0.5)
    views = [v for v in real_rig.conditions(jadeplant, 1) if v[0] == "jpeg q6 + noise s6"]  # its tuned index: 1
    # Jadeplant's coarse pass is aggregated by default (DenseConfig.retry_smoothing_penalties) and then needs no
    # blur; without the aggregation the blurred retry measures it.
    plain = DenseConfig(retry_smoothing_penalties=None)
    narrow = seven_by_seven_nearness()
    cases = [(take_pairs(pipes_frames, torch.tensor([0, 1]), 3), [False, True], [False, False], DenseConfig(), narrow),
             (real_rig.stack_conditions(jadeplant, views), [True], [False], DenseConfig(), None),
             (real_rig.stack_conditions(jadeplant, views), [True], [True], plain, None)]
    for batch, coarse, smoothed, dense, network in cases:
        batch = dataclasses.replace(batch, left=batch.left.clone().requires_grad_(),
                                    right=batch.right.clone().requires_grad_())
        result = estimate_obstacle_depth(batch, PipelineConfig(differentiable=True, verify_whole_view=False,
                                                               dense=dense), network=network)
        assert result.coarse.tolist() == coarse and result.smoothed.tolist() == smoothed
        objects, hard = result.depth.objects, result.hard_depth.objects
        last = len(coarse) - 1
        assert bool(objects.valid[last].all())
        relative = (objects.depth_median_m.detach() - hard.depth_median_m).abs() / hard.depth_median_m.clamp_min(
            1e-9)
        assert float(relative[objects.valid].max()) < 0.005
        objects.depth_median_m[last][objects.valid[last]].sum().backward()
        assert int((batch.left.grad[last] != 0).sum()) > 100 and int((batch.right.grad[last] != 0).sum()) > 100
        assert int((batch.left.grad[:last] != 0).sum()) == 0  # the loss holds the last pair only


def test_coarse_rule_never_adds_unverified_depths():
    """Kept: verified and as many objects; unverified as the first with as many. Refused: a verified first turned
    unverified, an object lost, or an unverified pass that ranges more (chance agreement reaching more objects)."""
    t, f = True, False
    verified_first = torch.tensor([t, f, t, t, f, f])
    ranged_first = torch.tensor([[t, f], [f, f], [t, t], [t, f], [t, f], [t, f]])
    verified_second = torch.tensor([t, t, f, t, f, f])
    ranged_second = torch.tensor([[t, t], [t, f], [t, t], [f, f], [t, f], [t, t]])
    assert coarse_is_better(verified_first, ranged_first, verified_second, ranged_second).tolist() == [
        t, t, f, f, t, f]


def test_coarse_config_halves_the_working_width_and_settings_are_checked():
    config = PipelineConfig()
    assert coarse_config(config).dense.working_width_px == config.dense.working_width_px // 2
    # Periods are looked for over the same stretch of the image: half as many coarse pixels. Was: the whole
    # longest period on the coarse grid, where a rendered scene's natural texture (synthetic-7 as JPEG digit 8
    # frames) read a period of 104 input pixels and its object was measured again over it.
    for name in ("coarse_retry_max_period_px", "alias_check_max_period_px"):
        assert getattr(coarse_config(config).depth, name) == getattr(config.depth, name) // 2
        for bad in (3, 1025, True, 64.0):  # the lag past which nothing is looked for, named when out of range
            with pytest.raises(InputError, match=name):
                DepthConfig(**{name: bad})
    assert PipelineConfig.paper().coarse_retry_below_share is None
    for bad in (0, 1.5, -0.1, True, "0.4"):
        with pytest.raises(InputError, match="coarse_retry_below_share"):
            PipelineConfig(coarse_retry_below_share=bad)
