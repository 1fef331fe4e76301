"""What a user training through estimate_obstacle_depth(..., differentiable=True) relies on (an audit, which found
them holding): one bad pair in a batch neither changes the other pairs' depths and gradients nor makes any gradient
non-finite, and reports its own status; the depths pass a float64 gradcheck w.r.t. the calibration and the logits;
the same call gives the same gradients twice; nothing keeps the graph once the caller lets go of it."""

from __future__ import annotations

import copy
import dataclasses
import gc
import weakref

import pytest
import torch

from svs_torch.data import collate_stereo_batches
from svs_torch.data.synthetic import random_obstacle_scenes
from svs_torch.pipeline import PipelineConfig, PipelineStatus, estimate_obstacle_depth
from svs_torch.segmentation.network_files import load_obstacle_net

SIZE_WH = (128, 96)


def _good_pairs(count: int, dtype: torch.dtype = torch.float32, size_wh: tuple[int, int] = SIZE_WH) -> list:
    generator = torch.Generator().manual_seed(3)
    return [random_obstacle_scenes(1, 2, size_wh=size_wh, depth_range_m=(0.8, 2.0), noise_std=0.01,
                                   generator=generator, dtype=dtype).batch for _ in range(count)]


def _bad(kind: str, pair):
    left, right = pair.left, pair.right
    views = {"zeros": (torch.zeros_like(left), torch.zeros_like(right)),
             "ones": (torch.ones_like(left), torch.ones_like(right)),
             "right_is_left": (left, left.clone()),
             "saturated": ((4 * left).clamp(0, 1), (4 * right).clamp(0, 1))}[kind]
    return dataclasses.replace(pair, left=views[0], right=views[1])


def _per_pair_loss(pairs: list, config: PipelineConfig, network=None):
    """Each pair's summed valid medians plus its nearest obstacle's surface, with images that require grad."""
    batch = collate_stereo_batches(pairs)
    left, right = batch.left.clone().requires_grad_(), batch.right.clone().requires_grad_()
    result = estimate_obstacle_depth(dataclasses.replace(batch, left=left, right=right), config, network=network)
    objects, nearest = result.depth.objects, result.depth.nearest
    per_pair = (torch.where(objects.valid, objects.depth_median_m, 0.0).sum(1)
                + torch.where(nearest.valid, nearest.surface_m, 0.0))
    return result, per_pair, (left, right)


@pytest.mark.parametrize("kind", ["zeros", "ones", "right_is_left", "saturated"])
def test_a_bad_pair_leaves_the_others_gradients_and_its_own_finite(kind):
    net = copy.deepcopy(load_obstacle_net()).requires_grad_(True)
    config = PipelineConfig(differentiable=True, segmentation=dataclasses.replace(
        PipelineConfig().segmentation, segmenter="learned"))
    good = _good_pairs(3)

    def gradients(fourth):
        result, per_pair, images = _per_pair_loss(good + [fourth], config, net)
        inputs = [*images, *net.parameters()]
        others = torch.autograd.grad(per_pair[:3].sum(), inputs, retain_graph=True, allow_unused=True)
        every = torch.autograd.grad(per_pair.sum(), inputs, allow_unused=True)
        return result, per_pair.detach(), others, every

    _, base_values, base_others, _ = gradients(good[0])
    result, values, others, every = gradients(_bad(kind, good[0]))
    assert result.status[:3].tolist() == [PipelineStatus.OK] * 3 and result.status[3] != PipelineStatus.OK
    assert torch.equal(values[:3], base_values[:3])
    assert values[3] == 0 and all(g is None or bool(torch.isfinite(g).all()) for g in every)
    assert int((every[0][3] != 0).sum()) == 0 and int((every[1][3] != 0).sum()) == 0  # a failed pair: exactly zero
    for found, expected in zip(others, base_others):
        torch.testing.assert_close(found, expected, rtol=1e-5, atol=1e-7)


def _float64_depths(config: PipelineConfig, network=None):
    """The depths of two small float64 pairs as a function of their calibration (doffs 0.5 px: at 0 a pixel of
    disparity 0 enters an object's statistics as doffs moves, a true step)."""
    batch = collate_stereo_batches(_good_pairs(2, torch.float64, (96, 72)))
    batch = dataclasses.replace(batch, doffs_px=torch.full_like(batch.doffs_px, 0.5))

    def depths(focal_px=batch.focal_px, baseline_m=batch.baseline_m, doffs_px=batch.doffs_px):
        result = estimate_obstacle_depth(dataclasses.replace(batch, focal_px=focal_px, baseline_m=baseline_m,
                                                             doffs_px=doffs_px), config, network=network)
        objects = result.depth.objects
        assert int(objects.valid.sum()) >= 3 and bool(result.depth.nearest.valid.all())
        values = [torch.where(objects.valid, v, 0.0).flatten() for v in (objects.depth_median_m, objects.depth_low_m,
                                                                          objects.depth_high_m)]
        return torch.cat([*values, result.depth.range.r_min_m, result.depth.nearest.depth_m])

    return batch, depths


def test_depths_pass_a_float64_gradcheck_in_the_calibration():
    batch, depths = _float64_depths(PipelineConfig(differentiable=True))
    calibration = tuple(v.clone().requires_grad_() for v in (batch.focal_px, batch.baseline_m, batch.doffs_px))
    assert torch.autograd.gradcheck(depths, calibration, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_depths_pass_a_float64_gradcheck_in_the_learned_logits():
    net = copy.deepcopy(load_obstacle_net()).double()
    shift = torch.zeros(1, dtype=torch.float64)
    forward = net.forward
    net.forward = lambda features: forward(features) + shift  # a logit offset: the weights' output
    _, depths = _float64_depths(PipelineConfig(differentiable=True, segmentation=dataclasses.replace(
        PipelineConfig().segmentation, segmenter="learned")), net)

    def with_shift(offset):
        nonlocal shift
        shift = offset
        return depths()

    offset = torch.zeros(1, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(with_shift, (offset,), eps=1e-6, atol=1e-5, rtol=1e-4)
    assert float(torch.autograd.grad(with_shift(offset).sum(), offset)[0].abs()) > 0


def test_the_same_call_gives_the_same_gradients_and_releases_its_graph():
    config = PipelineConfig(differentiable=True)
    pairs = _good_pairs(2)

    def step():
        result, per_pair, images = _per_pair_loss(pairs, config)
        per_pair.sum().backward()
        return [image.grad for image in images], weakref.ref(images[0]), weakref.ref(result.depth.objects.depth_median_m)

    first, *_ = step()
    second, image_ref, depth_ref = step()
    assert all(torch.equal(a, b) for a, b in zip(first, second)) and int((first[0] != 0).sum()) > 100
    gc.collect()
    assert image_ref() is None and depth_ref() is None  # no cache or result held the graph or its leaves
