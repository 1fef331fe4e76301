"""A second run, with SURF on smoothed views, for the pairs the first run left unverified (issue 33, item 1:
camera frames).

Why: a JPEG frame of the board's lowest quality (digit 8, OpenCV quality 20) with the sensor's noise (σ 8 levels)
has more blobs of noise and of 8×8 blocks than of the scene at SURF's finest scales, and their descriptors differ
between the two cameras' frames. The ratio test then keeps few matches (rendered SVS scenes: 6–16 of 250–400
keypoints a view), RANSAC too few inliers to verify the pair, and it was left without depth
(``NO_DENSE_DEPTH``) where OpenCV's SGBM ranged it. Smoothing both views by a Gaussian of σ 1 px before SURF
(``PipelineConfig.feature_smoothing_sigma_px``) leaves the scene's blobs and removes most of the noise's: the same
pairs matched 18–39 times and were ranged at 98–99 % per object. The retry's σ, 1.5 px, was chosen on the tuning
sets (``PipelineConfig.noisy_features_retry_sigma_px``; ``experiments/real_rig.md``, "A loose rig's camera
frames"). Only the features and the matches' refinement see the smoothed views; the segmentation and the dense
depth (which has its own smoothed retry, ``PipelineConfig.noisy_retry_sigma_px``) run on the views as they are.

Why a retry and not always: a clean or mildly compressed pair is verified by the first run, and its features on
the views as they are are the finer ones. The second result is kept only where it is verified and ranges as many
objects as the first or more (:func:`~svs_torch.pipeline.ranging.second_pass_is_better`): views of two different
scenes are never verified (``experiments/verify_views.py``), so the retry cannot let them through.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import torch

from ..core.pair_trees import take_pairs
from ..core.size_groups import replace_pairs
from ..core.types import StereoBatch
from .config import PipelineConfig, PipelineResult
from .ranging import second_pass_is_better

__all__ = []


def retry_with_smoothed_features(batch: StereoBatch, result: PipelineResult, config: PipelineConfig,
                                 run: Callable[[StereoBatch, PipelineConfig], PipelineResult]) -> PipelineResult:
    """``result`` with the pairs it left unverified run again by ``run`` with ``feature_smoothing_sigma_px`` set to
    ``config.noisy_features_retry_sigma_px``, where that second result is better (module docstring). ``batch``: the
    pairs ``result`` was computed on (one size group, filling its tensors). Differentiable where ``run`` is."""
    sigma = config.noisy_features_retry_sigma_px
    if sigma is None or config.feature_smoothing_sigma_px is not None or result.verified is None:
        return result
    index = (~result.verified).nonzero().flatten()
    if len(index) == 0:
        return result
    second = run(batch.select(index), dataclasses.replace(config, feature_smoothing_sigma_px=sigma))
    pick = second_pass_is_better(result.verified.index_select(0, index),
                                 result.depth.objects.valid.index_select(0, index), second.verified,
                                 second.depth.objects.valid)
    if not bool(pick.any()):
        return result
    return replace_pairs(result, index[pick], take_pairs(second, pick.nonzero().flatten(), len(index)),
                         batch.batch_size, batch.size_hw)


def features_smoothed(batch_size: int, config: PipelineConfig, device: torch.device) -> torch.Tensor:
    """``(B,)`` bool: whether a run under ``config`` found its features on smoothed views
    (``PipelineResult.features_smoothed``)."""
    return torch.full((batch_size,), config.feature_smoothing_sigma_px is not None, dtype=torch.bool, device=device)
