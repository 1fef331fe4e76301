"""Learned obstacle segmentation: find what is near, not what is bright (the paper's "next step", Sec. 5).

Otsu on intensity (:mod:`svs_torch.segmentation`) keeps the brightest large regions, often a wall. Here:

- **Truth** (:func:`obstacle_truth`): the obstacles of a pair with ground-truth disparity are the Otsu threshold of
  its valid GT disparity (near against far), a 5×5 opening and the two largest regions, with the same threshold,
  morphology and component code as the paper's stage; the nearest obstacle's distance is the median GT depth
  over the nearer of those regions.
- **Network** (:class:`ObstacleNet`, ~80k parameters, torch only): a small U-Net with a global-context bottleneck
  over stereo features at a working width of 160 px (:func:`stereo_features`: both images, and the soft-argmin
  SAD disparity of :func:`svs_torch.depth.dense.soft_block_match`, absolute and relative to the image's median), giving
  per-pixel obstacle logits (:func:`predict_obstacle_logits`).
- **Segmenter** (:func:`segment_stereo_learned`): the probability thresholded, the same opening, components and
  two largest regions; the same :class:`~svs_torch.core.types.StereoSegmentation` as
  :func:`~svs_torch.segmentation.segment_stereo`, so the rest of the pipeline is unchanged
  (``SegmentationConfig.segmenter``: ``"otsu"``, ``"learned"`` = the shipped weights, ``"learned:PATH"``).
- **Soft path** (:func:`soft_object_depths`): soft masks ``sigmoid(logit / T)`` gated by the hard kept regions
  become soft region weights; each object's disparity is the weighted mean of the soft-argmin disparity, its
  depth ``f·B / (d + doffs)``; the nearest obstacle is the smallest. Gradients reach the logits (hence the
  network) and both images. The weighted mean stands in for the hard stage's median (a median passes gradient to
  one pixel only); on an object of one depth both agree.

Weights are written by ``experiments/train_segmentation.py`` with their configuration and the split they were
trained on (:func:`save_obstacle_net`); the shipped file lives in ``svs_torch/segmentation/weights/``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from ..core.checks import (InputError, check_dtype, check_image, check_instance, check_positive_scalar, check_real,
                           check_shape)
from ..core.numerics import per_pair
from ..core.types import Segmentation, SegmentationStatus, StereoBatch, StereoSegmentation
from ..depth.dense_config import DenseConfig
from ..depth.quantiles import kept_region_lower_median
from ..depth.soft_dense import soft_block_match
from .components import connected_components_with_stats
from .ground_plane import GroundPlaneConfig, fit_ground_plane
from .morphology import open_binary, structuring_element
from .network import (ObstacleNet, ObstacleNetConfig, _disparity_levels, check_finite_logits, predict_obstacle_logits,
                      stereo_features)
from .network_files import SHIPPED_WEIGHTS, cached_obstacle_net, load_obstacle_net, save_obstacle_net
from .segment import SegmentationConfig, _status, keep_largest_regions
from .threshold import gray_histogram, gray_levels_and_histogram, otsu_threshold_level

if TYPE_CHECKING:  # (nearness imports this module)
    from .nearness import NearnessNet

__all__ = [
    "ObstacleNet", "ObstacleNetConfig", "ObstacleTruth", "SHIPPED_WEIGHTS", "SoftObjectDepths", "cached_obstacle_net",
    "load_obstacle_net", "mask_iou", "obstacle_truth", "predict_obstacle_logits", "save_obstacle_net",
    "segment_learned", "segment_stereo_learned", "soft_nearest_depth", "soft_object_depths", "stereo_features"
]


# ----------------------------------------------------------------------------------------------------- truth
@dataclass(frozen=True)
class ObstacleTruth:
    """Truth obstacles of B pairs from their ground-truth disparity (N = ``num_keep`` slots).

    Attributes:
        near: ``(B, 1, H, W)`` bool, valid GT disparity above its Otsu threshold.
        opened: ``(B, 1, H, W)`` bool, ``near`` after the opening.
        labels: ``(B, 1, H, W)`` int64 components of ``opened``; kept_labels ``(B, N)`` int64 (−1: none).
        kept_mask: ``(B, 1, H, W)`` bool, the union of the kept regions: the truth mask.
        region_depth_m: ``(B, N)`` lower-median GT depth over each kept region's pixels with a known depth.
        region_valid: ``(B, N)`` bool, the slot holds a region with at least one such pixel.
        nearest_m: ``(B,)`` the smallest valid ``region_depth_m`` (0 where none); nearest_valid ``(B,)`` bool.
    """

    near: torch.Tensor
    opened: torch.Tensor
    labels: torch.Tensor
    kept_labels: torch.Tensor
    kept_mask: torch.Tensor
    region_depth_m: torch.Tensor
    region_valid: torch.Tensor
    nearest_m: torch.Tensor
    nearest_valid: torch.Tensor


def obstacle_truth(batch: StereoBatch, config: SegmentationConfig = SegmentationConfig(),
                   floor: GroundPlaneConfig | None = None) -> ObstacleTruth:
    """The truth obstacles (module docstring) with ``config``'s element, connectivity and ``num_keep``; with
    ``floor``, a walker's truth: the ground plane of the true disparity (:mod:`.ground_plane`, fitted to the valid
    pixels at the nearness segmenter's working width) is not an obstacle and is left out of the split.

    Depths need a calibrated pair (:meth:`StereoBatch.ground_truth_depth_m`); an uncalibrated one still gets its
    masks, with ``nearest_valid`` False. Not differentiable.

    Raises:
        InputError: the batch has no ground-truth disparity.
    """
    check_instance(batch, "batch", StereoBatch)
    check_instance(config, "config", SegmentationConfig)
    if batch.disparity_px is None:
        raise InputError("batch: expected ground-truth disparity (disparity_px), got none")
    valid = batch.disparity_valid
    if floor is not None:
        check_instance(floor, "floor", GroundPlaneConfig)  # a DenseConfig failed deep in the fit (an audit)
        from .nearness import NearnessNetConfig  # (nearness imports this module)
        factor = NearnessNetConfig().working_factor(batch.left.shape[-1])
        valid = valid & ~fit_ground_plane(batch.disparity_px.nan_to_num(0.0, 0.0, 0.0), valid, batch.baseline_m,
                                          floor, factor, focal_px=batch.focal_px).mask
    levels = _disparity_levels(batch.disparity_px, valid)
    level = otsu_threshold_level(gray_histogram(levels, ~valid))
    near = valid & (levels > level.to(torch.uint8).view(-1, 1, 1, 1))
    element = structuring_element(config.kernel_shape, config.kernel_size, device=near.device)
    opened = open_binary(near, element)
    labels, _, regions = connected_components_with_stats(opened, config.connectivity, batch.left.dtype)
    kept_labels, kept_mask = keep_largest_regions(labels, regions, config.num_keep)
    depth, known = batch.ground_truth_depth_m()
    region_depth, count = kept_region_lower_median(depth, known, labels, kept_labels)
    region_valid = count > 0
    nearest = torch.where(region_valid, region_depth, torch.inf).amin(1)
    nearest_valid = torch.isfinite(nearest)
    return ObstacleTruth(near, opened, labels, kept_labels, kept_mask, region_depth, region_valid,
                         torch.where(nearest_valid, nearest, 0.0), nearest_valid)


def mask_iou(mask: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Intersection over union ``(B,)`` of two ``(B, 1, H, W)`` bool masks; 1 where both are empty. Not
    differentiable (counts of bool masks)."""
    check_shape(mask, "mask", ["B", 1, "H", "W"])
    check_shape(truth, "truth", list(mask.shape))
    check_dtype(mask, "mask", "bool")  # a float one failed deep inside, an int one was met bit by bit (an audit)
    check_dtype(truth, "truth", "bool")
    inter = (mask & truth).flatten(1).sum(1)
    union = (mask | truth).flatten(1).sum(1)
    return torch.where(union > 0, inter / union.clamp(min=1), 1.0)


# ------------------------------------------------------------------------------------------------- segmenter
def segment_learned(image: torch.Tensor, logits: torch.Tensor, config: SegmentationConfig = SegmentationConfig(),
                    probability_threshold: float = 0.5) -> Segmentation:
    """The hard segmentation of images ``(B, 1, H, W)`` from their obstacle logits ``(B, 1, H, W)``: probability
    above ``probability_threshold``, ``config``'s opening, components and ``num_keep`` largest regions.

    ``threshold`` holds the probability threshold and ``threshold_level`` it on the 0–255 scale; ``binary`` is
    the thresholded probability. Status as the Otsu stage's: ``UNIFORM_IMAGE`` for a one-level image (no
    information), ``NO_FOREGROUND`` when nothing survives the opening. Not differentiable: the mask is hard, and
    ``masked`` (the image times it) carries the image's gradient inside the kept mask only.

    Raises:
        InputError: naming the argument, for images or logits of another shape or kind, a ``config`` that is not a
            :class:`SegmentationConfig`, or a ``probability_threshold`` outside (0, 1) (0 and 1 raised
            ValueError and ZeroDivisionError from the logit, NaN kept nothing in silence: an audit).
    """
    dims = check_image(image, "image")
    check_shape(logits, "logits", [dims["B"], 1, dims["H"], dims["W"]])
    check_dtype(logits, "logits", "float")
    check_instance(config, "config", SegmentationConfig)
    check_real(probability_threshold, "probability_threshold", 0.0, 1.0, low_open=True, high_open=True)
    b = dims["B"]
    binary = logits.detach() > math.log(probability_threshold / (1 - probability_threshold))
    element = structuring_element(config.kernel_shape, config.kernel_size, device=image.device)
    opened = open_binary(binary, element)
    labels, num_regions, regions = connected_components_with_stats(opened, config.connectivity, image.dtype)
    kept_labels, kept_mask = keep_largest_regions(labels, regions, config.num_keep)
    uniform = (gray_levels_and_histogram(image)[1] > 0).sum(1) == 1
    threshold = torch.full((b,), probability_threshold, dtype=image.dtype, device=image.device)
    return Segmentation(threshold=threshold, threshold_level=(threshold * 255).round().long(), binary=binary,
                        opened=opened, labels=labels, num_regions=num_regions, regions=regions,
                        kept_labels=kept_labels, kept_mask=kept_mask, masked=image * kept_mask.to(image.dtype),
                        status=_status(uniform, opened))


def segment_stereo_learned(batch: StereoBatch, config: SegmentationConfig = SegmentationConfig(segmenter="learned"),
                           net: ObstacleNet | NearnessNet | None = None, left_logits: torch.Tensor | None = None
                           ) -> StereoSegmentation:
    """Segment both views of every pair with the network: the drop-in for
    :func:`~svs_torch.segmentation.segment_stereo` (same structure, same ``config`` fields).

    The network is ``net``, or loaded from ``config.segmenter`` (:func:`load_obstacle_net`). The right view is
    segmented as the left view of the mirrored pair (both images flipped and swapped: right columns stay at
    ``x − d``), one batch of 2B; ``left_logits`` ``(B, 1, H, W)`` (the left views' logits, already computed by
    the caller, e.g. with gradients) leaves only the right views to the network. Not differentiable but for
    ``masked``, which carries the images' gradients inside the kept masks only; the network trains through
    :func:`soft_object_depths`.
    """
    check_instance(batch, "batch", StereoBatch)
    check_instance(config, "config", SegmentationConfig)
    if net is None:
        net = cached_obstacle_net(config.segmenter)
    if not isinstance(net, ObstacleNet):
        from .nearness import segment_stereo_nearness
        return segment_stereo_nearness(batch, config, net, left_logits)
    b = batch.batch_size
    with torch.no_grad():
        if left_logits is None:
            logits = predict_obstacle_logits(net, torch.cat([batch.left, batch.right.flip(-1)]),
                                             torch.cat([batch.right, batch.left.flip(-1)]))
        else:
            check_shape(left_logits, "left_logits", list(batch.left.shape))
            check_finite_logits(left_logits, "left_logits")
            logits = torch.cat([left_logits.detach().to(batch.left.dtype),
                                predict_obstacle_logits(net, batch.right.flip(-1), batch.left.flip(-1))])
    check_finite_logits(logits.view(2, b, -1).transpose(0, 1), "network")
    threshold = net.config.probability_threshold
    left = segment_learned(batch.left, logits[:b], config, threshold)
    right = segment_learned(batch.right, logits[b:].flip(-1), config, threshold)
    status = torch.where(left.status != SegmentationStatus.OK, left.status, right.status)
    return StereoSegmentation(left=left, right=right, status=status)


# ------------------------------------------------------------------------------------------------- soft path
@dataclass(frozen=True)
class SoftObjectDepths:
    """Soft per-object depths of B pairs, N kept regions.

    Attributes:
        weights: ``(B, N, H, W)`` soft region weights, ``sigmoid(logit / T)`` inside kept region n, 0 outside.
        disparity_px: ``(B, N)`` weighted mean disparity of each region (0 where not ``valid``).
        depth_m: ``(B, N)`` ``f·B / (disparity + doffs)`` (0 where not ``valid``).
        valid: ``(B, N)`` bool, a kept region with positive weight and ``disparity + doffs > 0``.
        nearest_m: ``(B,)`` the smallest valid depth (0 where none); nearest_valid ``(B,)`` bool.
    """

    weights: torch.Tensor
    disparity_px: torch.Tensor
    depth_m: torch.Tensor
    valid: torch.Tensor
    nearest_m: torch.Tensor
    nearest_valid: torch.Tensor


def soft_object_depths(logits: torch.Tensor, segmentation: Segmentation, disparity_px: torch.Tensor,
                       focal_px: torch.Tensor, baseline_m: torch.Tensor, doffs_px: torch.Tensor,
                       mask_temperature: float = 1.0) -> SoftObjectDepths:
    """Soft region weights → weighted mean disparity per kept region → depth → nearest obstacle.

    Args:
        logits: ``(B, 1, H, W)`` obstacle logits; ``segmentation``: the hard :class:`Segmentation` of the same
            view, whose kept regions gate the weights (which regions are kept carries no gradient, as in
            :mod:`svs_torch.segmentation.soft`).
        disparity_px: ``(B, 1, H, W)`` e.g. :func:`~svs_torch.depth.dense.soft_block_match`'s.
        focal_px, baseline_m, doffs_px: ``(B,)`` calibration at this image size.
        mask_temperature: ``T`` of ``sigmoid(logit / T)``; ``→ 0`` gives the hard regions (a weighted mean over
            them), so the result tends to the hard regions' mean disparity.

    Returns:
        :class:`SoftObjectDepths`, differentiable w.r.t. ``logits``, ``disparity_px`` and the calibration
        (``focal_px``, ``baseline_m``, ``doffs_px``: the depths, not the weights or mean disparities), ``nearest_m``
        through the nearest object only.
    """
    dims = check_shape(logits, "logits", ["B", 1, "H", "W"])
    check_dtype(logits, "logits", "float")
    # One view's: a StereoSegmentation (or None) raised AttributeError on .labels (an audit).
    check_instance(segmentation, "segmentation", Segmentation)
    check_shape(disparity_px, "disparity_px", list(logits.shape))
    check_dtype(disparity_px, "disparity_px", "float")
    check_shape(segmentation.labels, "segmentation.labels", list(logits.shape))
    for name, value in (("focal_px", focal_px), ("baseline_m", baseline_m), ("doffs_px", doffs_px)):
        check_shape(value, name, [dims["B"]])  # a (3,) calibration for 2 pairs failed deep in a broadcast
    if bool(torch.isnan(logits).any()):  # NaN logits left every object invalid in silence
        raise InputError("logits: expected numbers, got NaN")
    check_positive_scalar(mask_temperature, "mask_temperature")
    b, n = dims["B"], segmentation.kept_labels.shape[1]
    kept = segmentation.kept_labels.view(b, n, 1, 1)
    region = (segmentation.labels == kept) & (kept > 0)  # (B, N, H, W)
    # Only the kept regions' disparities count: a NaN or inf outside them (a caller's own map) made 0 · NaN = NaN, in
    # every object of the pair and in the logits' gradient, so in a shared network's (an audit). Inside, refused.
    inside = region.any(dim=1, keepdim=True)
    if not bool(torch.isfinite(disparity_px.detach()[inside]).all()):
        raise InputError("disparity_px: expected finite values over the kept regions, got NaN or inf")
    values = torch.where(inside, disparity_px, torch.zeros_like(disparity_px))
    weights = per_pair(torch.sigmoid, logits / mask_temperature) * region  # batched as alone
    total = weights.flatten(2).sum(-1)  # (B, N)
    has = region.flatten(2).any(-1) & (total > 0)
    mean = (weights * values).flatten(2).sum(-1) / torch.where(has, total, 1.0)
    denominator = mean + doffs_px.view(b, 1)
    valid = has & (denominator > 0)
    depth = torch.where(valid, (focal_px * baseline_m).view(b, 1) / torch.where(valid, denominator, 1.0), 0.0)
    nearest = torch.where(valid, depth, torch.inf).amin(1) if n else depth.new_full((b,), torch.inf)
    nearest_valid = torch.isfinite(nearest)
    return SoftObjectDepths(weights, torch.where(valid, mean, 0.0), depth, valid,
                            torch.where(nearest_valid, nearest, 0.0), nearest_valid)


def soft_nearest_depth(batch: StereoBatch, logits: torch.Tensor, segmentation: Segmentation, num_disparities: int,
                       mask_temperature: float = 1.0, disparity_temperature: float = 0.003,
                       dense: DenseConfig = DenseConfig()) -> SoftObjectDepths:
    """The whole soft path on the left views of ``batch``: :func:`~svs_torch.depth.dense.soft_block_match` over
    ``[0, num_disparities)`` then :func:`soft_object_depths`. Differentiable w.r.t. ``logits``, both images and
    the batch's calibration (its depths);
    as both temperatures ``→ 0`` it tends to the mean winner-takes-all disparity over each hard kept region."""
    check_instance(batch, "batch", StereoBatch)
    check_instance(segmentation, "segmentation", Segmentation)
    # By its name here: soft_block_match's refusal named its own "temperature" (an audit).
    check_positive_scalar(disparity_temperature, "disparity_temperature")
    disparity = soft_block_match(batch.left, batch.right, 0, num_disparities, disparity_temperature, dense)
    return soft_object_depths(logits, segmentation, disparity, batch.focal_px, batch.baseline_m, batch.doffs_px,
                              mask_temperature)
