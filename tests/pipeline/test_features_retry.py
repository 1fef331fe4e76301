"""A pair the first run left unverified is run again with SURF on smoothed views
(``PipelineConfig.noisy_features_retry_sigma_px``, :mod:`svs_torch.pipeline.features_retry`; issue 33)."""

from __future__ import annotations

import dataclasses
import math
import sys

import cv2
import pytest
import torch
from conftest import REPO_ROOT

from svs_torch import InputError
from svs_torch.evaluation import evaluate_result
from svs_torch.pipeline import PipelineConfig, PipelineStatus, estimate_obstacle_depth
from svs_torch.pipeline.stages import gaussian_smoothed

sys.path.insert(0, str(REPO_ROOT / "experiments"))

import real_rig  # noqa: E402

SCENE = 11  # experiments/real_rig.py's rendered scene whose digit 8 frames SURF matched 6 times


@pytest.fixture(scope="module")
def loose_rig_frames():
    """Rendered scene 11 as a loose rig's JPEG digit 8 frames (``real_rig.py --loose-rig-digit 8``): the aligned
    pair, turned +2° (verified without the retry) and the combined misalignment, and the clean pair."""
    scene = real_rig.synthetic_scenes()[SCENE]
    frames = {name.split(" + ")[0]: (name, left, right)
              for name, left, right in real_rig.loose_rig_conditions(scene, SCENE, 8)}
    views = [frames[name] for name in ("aligned", "roll +2°", "combined")]
    return real_rig.stack_conditions(scene, [("clean", scene.left, scene.right), *views])


def test_unverified_noisy_frames_are_ranged_with_features_on_smoothed_views(loose_rig_frames):
    """Without the retry the aligned and the combined digit 8 frames are left without depth (6 and 16 matches);
    with it both are verified, ranged at >= 96 % per object and say so (``features_smoothed``). The clean pair
    and the turned one, verified by the first run, are not retried: their values are unchanged."""
    batch = loose_rig_frames
    without = estimate_obstacle_depth(batch, PipelineConfig(noisy_features_retry_sigma_px=None))
    result = estimate_obstacle_depth(batch, PipelineConfig())
    retried = torch.tensor([False, True, False, True])
    assert torch.equal(without.verified, ~retried)
    assert all(PipelineStatus(int(s)) == PipelineStatus.NO_DENSE_DEPTH for s in without.status[retried])
    assert torch.equal(result.features_smoothed, retried) and not bool(without.features_smoothed.any())
    assert bool(result.verified.all()) and bool((result.status == PipelineStatus.OK).all())
    assert bool((result.num_matches[retried] > without.num_matches[retried]).all())
    scores = evaluate_result(batch, result)
    assert all(scores[i].acc_objects_pct >= 96 for i in (1, 3))
    kept = ~retried
    assert torch.equal(result.depth.objects.depth_median_m[kept], without.depth.objects.depth_median_m[kept])


def test_the_retried_pairs_train_through_the_smoothed_views(loose_rig_frames):
    """With gradients on, a retried pair's depth is the hard one's (within 2 %) and its gradient reaches the image
    through the same smoothing its features were found on."""
    batch = loose_rig_frames.select([1])
    left = batch.left.clone().requires_grad_(True)
    result = estimate_obstacle_depth(dataclasses.replace(batch, left=left), PipelineConfig(differentiable=True))
    assert bool(result.features_smoothed[0])
    slot = int(result.depth.nearest.slot[0])
    soft = result.depth.objects.depth_median_m[0, slot]
    hard = float(result.hard_depth.objects.depth_median_m[0, slot])
    assert abs(float(soft.detach()) - hard) <= 0.02 * hard
    soft.backward()
    assert left.grad is not None and bool(left.grad.abs().sum() > 0)


@pytest.mark.parametrize("sigma", [0.6, 1.0, 2.5])
def test_gaussian_smoothed_is_opencv_s_gaussian_blur(sigma):
    image = torch.rand(1, 1, 37, 53, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    size = 2 * math.ceil(3 * sigma) + 1
    expected = cv2.GaussianBlur(image[0, 0].numpy(), (size, size), sigma, borderType=cv2.BORDER_REPLICATE)
    assert torch.allclose(gaussian_smoothed(image, sigma)[0, 0], torch.from_numpy(expected), atol=1e-9)


def test_the_retry_is_a_sigma_or_none_and_off_in_the_paper_preset():
    assert PipelineConfig.paper().noisy_features_retry_sigma_px is None
    assert PipelineConfig().noisy_features_retry_sigma_px == 1.5 and PipelineConfig().feature_smoothing_sigma_px is None
    for name in ("noisy_features_retry_sigma_px", "feature_smoothing_sigma_px"):
        for bad in (0.0, -1.0, float("nan"), "1", True):
            with pytest.raises(InputError, match=name):
                PipelineConfig(**{name: bad})
