"""Both views of every pair segmented by the segmenter a :class:`~svs_torch.segmentation.segment.SegmentationConfig`
names (:func:`segment_pair`): Otsu (the paper, Sec. 3.2) or a learned one, with its shipped or named weights. The
pipeline's segmentation stage, and what :func:`~svs_torch.segmentation.segment.segment_stereo` runs for a segmenter
other than Otsu."""

from __future__ import annotations

import torch
from torch import nn

from ..core.checks import InputError, check_instance
from ..core.size_groups import run_by_size
from ..core.types import StereoBatch, StereoSegmentation
from .learned import segment_stereo_learned
from .network import ObstacleNet
from .network_files import cached_obstacle_net
from .segment import SegmentationConfig, segment_stereo_otsu

__all__ = ["check_network", "segment_pair", "segment_same_size", "segmenter_network"]


def segment_pair(batch: StereoBatch, config: SegmentationConfig, network: nn.Module | None = None,
                 left_logits: torch.Tensor | None = None) -> StereoSegmentation:
    """Both views of every pair segmented by ``config.segmenter``: Otsu (the paper, Sec. 3.2; or Canny by
    ``config.method``) or the learned segmenter (:mod:`svs_torch.segmentation.learned`; ``network``, or the
    weights ``config.segmenter`` names; ``left_logits``: the left views' logits, already computed); the same
    structure. Not differentiable (each view's ``masked`` carries its image's gradient inside the kept mask only).
    Each pair is segmented on its own ``image_hw`` pixels (pairs of different sizes as groups of one size,
    :mod:`svs_torch.core.size_groups`): padding never enters a threshold's histogram or a region; ``left_logits``
    are for a batch whose pairs fill its tensors."""
    check_instance(batch, "batch", StereoBatch)
    check_instance(config, "config", SegmentationConfig)
    if batch.batch_size == 0:
        raise InputError("batch: expected at least one pair, got an empty batch")
    if network is not None:
        check_network(network, config.segmenter)
    if left_logits is None:
        return run_by_size(batch, lambda group: segment_same_size(group, config, network))
    if config.segmenter == "otsu":
        raise InputError("left_logits: given, but config.segmenter is 'otsu', which reads none")
    if not bool((batch.image_hw == torch.tensor(batch.size_hw, device=batch.image_hw.device)).all()):
        raise InputError("left_logits: expected a batch whose pairs all fill its tensors (one size); pass none to "
                         "segment a padded batch pair by pair size")
    return segment_same_size(batch, config, network, left_logits)


def segment_same_size(batch: StereoBatch, config: SegmentationConfig, network: nn.Module | None = None,
                      left_logits: torch.Tensor | None = None) -> StereoSegmentation:
    """:func:`segment_pair` of a batch whose pairs fill its tensors (one size). Not differentiable (each view's
    ``masked`` carries its image's gradient inside the kept mask only)."""
    check_instance(batch, "batch", StereoBatch)
    check_instance(config, "config", SegmentationConfig)
    if config.segmenter == "otsu":  # already one size group: segment_stereo would group it again
        return segment_stereo_otsu(batch, config)
    return segment_stereo_learned(batch, config, segmenter_network(batch, config, network), left_logits)


def segmenter_network(batch: StereoBatch, config: SegmentationConfig, network: nn.Module | None) -> nn.Module:
    """The learned segmenter's network on the batch's device: ``network`` (which must be there already: moving
    a caller's module would move the parameters its optimiser holds) or the cached weights of
    ``config.segmenter``, moved and frozen."""
    check_instance(batch, "batch", StereoBatch)
    check_instance(config, "config", SegmentationConfig)
    if network is None:
        # Frozen: a differentiable run takes gradients to the images through it, never into the shared cache. Moved
        # and frozen only when it is not already (walking the module cost 0.3 ms a call, paid at guide's B = 1).
        cached = cached_obstacle_net(config.segmenter)
        parameters = list(cached.parameters())
        if parameters and parameters[0].device != batch.left.device:
            with torch.inference_mode(False):  # moved in place, and kept: never inference tensors (core.inference)
                cached = cached.to(batch.left.device)
        if any(p.requires_grad for p in parameters):
            cached.requires_grad_(False)
        return cached
    check_network(network, config.segmenter)
    device = next(network.parameters()).device
    if device != batch.left.device:
        raise InputError(f"network: expected its parameters on the batch's device {batch.left.device}, got {device}")
    return network


def check_network(network: object, segmenter: str) -> None:
    """A caller's network must be the kind its segmenter runs: a NearnessNet, or an ObstacleNet (whose ``config``
    the learned segmenter's features read); not one for Otsu, which has none."""
    from .nearness import NearnessNet

    check_instance(network, "network", nn.Module)
    if segmenter == "otsu":
        raise InputError("network: given, but config.segmentation.segmenter is 'otsu' (use a learned one)")
    nearness = segmenter.startswith("nearness")
    if not isinstance(network, NearnessNet if nearness else ObstacleNet):
        expected = "a NearnessNet" if nearness else "an ObstacleNet"
        raise InputError(f"network: expected {expected} for segmenter {segmenter!r}, got {type(network).__name__}")
