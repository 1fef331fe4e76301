"""The stages as the pipeline calls them: segmentation of a row-aligned pair again (the segmenters themselves:
:mod:`svs_torch.segmentation.stereo`), the feature images and SURF features, matching, and each pair's status from
what the stages found.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import torch
from torch import nn

from ..core.size_groups import replace_pairs
from ..core.types import (FundamentalResult, FundamentalStatus, Matches, Segmentation, SegmentationStatus,
                          StereoBatch, StereoSegmentation)
from ..depth.depth_types import DepthResult, NearestObstacle, ObstacleSide, RangeEstimate
from ..features.surf import SurfFeatures, extract_surf_features
from ..geometry.matching import match_sad
from ..geometry.rectification import Rectification, RectificationStatus, warp_rectified, warp_views
from ..segmentation.components import region_properties
from ..segmentation.interior import region_interiors
from ..segmentation.segment import SegmentationConfig
from ..segmentation.stereo import segment_same_size
from .config import MIN_CORRESPONDENCES, PipelineConfig, PipelineStatus


def _feature_images(batch: StereoBatch, seg: StereoSegmentation, config: PipelineConfig
                    ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The ``(2B, 1, H, W)`` images SURF runs on (left then right), smoothed where
    ``config.feature_smoothing_sigma_px`` says, and its detection mask (or None)."""
    if config.features_on == "masked":
        images, mask = torch.cat([seg.left.masked, seg.right.masked]), None
    else:
        images = torch.cat([batch.left, batch.right])
        mask = None if config.features_on == "image" else torch.cat([seg.left.kept_mask, seg.right.kept_mask])
    if config.feature_smoothing_sigma_px is not None:
        images = gaussian_smoothed(images, config.feature_smoothing_sigma_px)
    return images, mask


def warp_labels(labels: torch.Tensor, homographies: torch.Tensor) -> torch.Tensor:
    """Label images or masks ``(B, 1, H, W)`` warped by ``homographies`` ``(B, 3, 3)`` (original to warped pixels)
    by nearest neighbour, as exact small integers in float64 and rounded back: int64, 0 outside. Not
    differentiable."""
    return warp_rectified(labels.to(torch.float64), homographies.to(torch.float64), mode="nearest").round().long()


def warped_where(images: torch.Tensor, homographies: torch.Tensor, pick: torch.Tensor,
                 warp: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]) -> torch.Tensor:
    """``images`` ``(B, ...)`` with the pairs ``pick`` ``(B,)`` bool replaced by ``warp`` of their images and
    ``homographies`` ``(B, 3, 3)`` (:func:`warp_views`, :func:`warp_labels`), the others as they are: only those
    pairs are warped. A batch with one rectified pair warped all of its pairs to keep one: the dense stage and the
    near-surface, side and floor rules, six warps of 8 pairs at 320x240 where one of them was rectified (a row-
    aligned pair of the bench's real list), about 2 ms a pair of `estimate --pairs`. Each pair's warp is its own
    (kornia warps a batch pair by pair: the same values alone), so the result is the same. Gradients flow as
    through ``warp`` to the picked pairs' images and homographies, and straight to the others' images, as they did
    through the ``torch.where`` of a whole-batch warp: the hard dense stage and the differentiable pass
    (:func:`~svs_torch.pipeline.soft.differentiable_depth`) both warp this way."""
    if not bool(pick.any()):
        return images
    if bool(pick.all()):
        return warp(images, homographies)
    index = pick.nonzero().flatten()
    return images.index_copy(0, index, warp(images.index_select(0, index), homographies.index_select(0, index)))


def gaussian_smoothed(images: torch.Tensor, sigma_px: float) -> torch.Tensor:
    """``images`` ``(N, 1, H, W)`` in [0, 1] smoothed by a Gaussian of ``sigma_px`` pixels (±3σ, the border
    replicated), held to [0, 1]. Differentiable w.r.t. ``images``."""
    from kornia.filters import gaussian_blur2d  # imported here: kornia's import is slow and clean pairs never need it

    size = 2 * math.ceil(3 * sigma_px) + 1
    # Clamped: the kernel's weights sum to 1 only up to rounding, and a white pixel may come out at 1 + 2e-16,
    # which StereoBatch refuses (hypothesis found it on a 1×1 white pair).
    return gaussian_blur2d(images, (size, size), (sigma_px, sigma_px), border_type="replicate").clamp(0, 1)


def _features(images: torch.Tensor, mask: torch.Tensor | None, config: PipelineConfig
              ) -> tuple[SurfFeatures, SurfFeatures]:
    """SURF on left and right as one batch of 2B images; split back."""
    b = images.shape[0] // 2
    both = extract_surf_features(images, config.surf, mask)

    def half(sl: slice) -> SurfFeatures:
        kp = both.keypoints
        return SurfFeatures(type(kp)(kp.xy[sl], kp.scale[sl], kp.score[sl], kp.laplacian_sign[sl],
                                     kp.orientation[sl], kp.valid[sl]), both.descriptors[sl])

    return half(slice(0, b)), half(slice(b, 2 * b))


def _match(left: SurfFeatures, right: SurfFeatures, config: PipelineConfig) -> Matches:
    lk, rk = left.keypoints, right.keypoints
    return match_sad(
        left.descriptors, right.descriptors, lk.valid, rk.valid, max_ratio=config.max_ratio, mutual=config.mutual,
        laplacian_left=lk.laplacian_sign if config.laplacian_gate else None,
        laplacian_right=rk.laplacian_sign if config.laplacian_gate else None,
        xy_left=lk.xy, xy_right=rk.xy, epipolar_band_px=config.epipolar_band_px)


def _status(seg: StereoSegmentation, num_keypoints: torch.Tensor, fundamental: FundamentalResult,
            rectification: Rectification, depth: DepthResult, rectify: str, dense_rule: bool) -> torch.Tensor:
    """First failing stage per pair (checked from the last stage back, so earlier stages win).

    Under the dense rule the sparse stages are not needed to range a pair (they rectify it where its rows do
    not agree, and vouch that both views show one scene): a pair whose features, matches or RANSAC failed is
    still ranged on its raw rows (as ``rectify="auto"`` does for an aligned rig), with a stricter share of
    valid pixels, unless rectification is ``"required"``."""
    status = torch.full_like(fundamental.status, PipelineStatus.OK)
    sparse_fatal = not dense_rule or rectify == "required"
    checks = [
        (~depth.range.valid, PipelineStatus.NO_DENSE_DEPTH if dense_rule else PipelineStatus.NO_POSITIVE_DISPARITY),
        ((rectification.status != RectificationStatus.OK) & (rectify == "required"),
         PipelineStatus.DEGENERATE_RECTIFICATION),
    ]
    if sparse_fatal:
        checks += [
            ((fundamental.status != FundamentalStatus.OK), PipelineStatus.RANSAC_FAILED),
            (fundamental.status == FundamentalStatus.TOO_FEW_MATCHES, PipelineStatus.TOO_FEW_MATCHES),
            ((num_keypoints < MIN_CORRESPONDENCES).any(dim=1), PipelineStatus.TOO_FEW_KEYPOINTS),
        ]
    # Every slot: a left slot dropped as unmeasured (PipelineConfig.drop_unmeasured_below_share) leaves a gap.
    checks.append(((seg.left.kept_labels < 0).all(1) | (seg.right.kept_labels < 0).all(1)
                   | (seg.status != SegmentationStatus.OK), PipelineStatus.NO_OBJECTS))
    for failed, code in checks:
        status = torch.where(failed, torch.full_like(status, code), status)
    return status


def without_failed_pairs(depth: DepthResult, status: torch.Tensor) -> DepthResult:
    """``depth`` with every pair whose ``status`` is not OK left unranged: its range, objects and nearest obstacle
    not ``valid`` and zero, as their types say of what is not valid. A stage can fail after depth was measured
    (``rectify="required"`` with a degenerate rectification: the disparities are the raw points'), and a failed
    pair must not hand its distances to a reader who checks ``valid`` and not ``status``."""
    ok = status == PipelineStatus.OK
    if bool(ok.all()):
        return depth

    def kept(values: torch.Tensor, where: torch.Tensor) -> torch.Tensor:
        return torch.where(where, values, torch.zeros_like(values))

    r = depth.range
    depth_range = RangeEstimate(kept(r.d_min_px, ok), kept(r.d_max_px, ok), kept(r.r_min_m, ok), kept(r.r_max_m, ok),
                                kept(r.num_disparities, ok), r.valid & ok)
    objects = depth.objects
    if objects is not None:
        valid = objects.valid & ok[:, None]
        objects = dataclasses.replace(objects, valid=valid, depth_median_m=kept(objects.depth_median_m, valid),
                                      depth_low_m=kept(objects.depth_low_m, valid),
                                      depth_high_m=kept(objects.depth_high_m, valid))
    nearest = depth.nearest
    if nearest is not None:
        valid = nearest.valid & ok
        nearest = NearestObstacle(torch.where(valid, nearest.slot, torch.full_like(nearest.slot, -1)),
                                  kept(nearest.depth_m, valid),
                                  torch.where(valid, nearest.side, torch.full_like(nearest.side, ObstacleSide.NONE)),
                                  valid, None if nearest.surface_m is None else kept(nearest.surface_m, valid))
    return DepthResult(depth.disparities, depth.points, depth_range, objects, nearest)


def measured_labels(seg: StereoSegmentation, width_px: int, config: PipelineConfig) -> torch.Tensor:
    """The left labels ``(B, 1, H, W)`` :func:`~svs_torch.pipeline.estimate_obstacle_depth` measures each object
    over (``PipelineResult.object_labels``): the kept regions of a disparity-based segmenter cut to their interior
    (``PipelineConfig.region_interior_working_px``: working pixels of the dense stage, at least one input pixel
    each, for views ``width_px`` wide) under the dense rule, else ``seg``'s own left labels. A rival scored on the
    pipeline's segmentation measures the same pixels with these."""
    working_px = config.region_interior_working_px
    if working_px is None or config.depth.rule != "dense" or seg.from_disparity is None:
        return seg.left.labels
    radius = round(working_px * max(1.0, width_px / config.dense.working_width_px))
    return region_interiors(seg.left.labels, seg.left.kept_labels, radius, seg.from_disparity)


def _segment_row_aligned(batch: StereoBatch, seg: StereoSegmentation, aligned: torch.Tensor, H_right: torch.Tensor,
                         config: SegmentationConfig, network: nn.Module | None = None) -> StereoSegmentation:
    """``seg`` with the pairs ``aligned`` ``(B,)`` segmented again on their row-aligned pair (the right view warped
    by ``H_right`` ``(B, 3, 3)``; the left view is never warped by a row alignment), for the segmenters that
    measure a disparity along the rows: on a loosely mounted rig those rows disagree by a few pixels, the
    nearness map turns to noise and its kept regions to specks (tuned split at 320×240, per object: roll +2°
    Pipes 48 %, roll −2° Teddy 50 %; segmented again 98 % and 99.8 %, experiments/real_rig.py). The right view's
    regions are mapped back to its own pixels (nearest neighbour), so every map of the result stays in input
    pixels. Not differentiable."""
    index, b = aligned.nonzero().flatten(), batch.batch_size
    sub = batch.select(index)
    homographies = H_right.index_select(0, index).to(torch.float64)
    again = segment_same_size(dataclasses.replace(sub, right=warp_views(sub.right, homographies)), config, network)
    again = dataclasses.replace(again, right=_unwarped(again.right, sub.right, torch.linalg.inv(homographies)))
    return replace_pairs(seg, index, again, b, batch.size_hw)


def _unwarped(seg: Segmentation, image: torch.Tensor, homographies: torch.Tensor) -> Segmentation:
    """A right view's segmentation made on its warped image, mapped back by ``homographies`` (warped to input
    pixels) onto ``image``'s pixels: its maps by nearest neighbour, its regions measured again."""
    def back(mask: torch.Tensor) -> torch.Tensor:
        return warp_labels(mask, homographies)

    labels = back(seg.labels)
    kept = back(seg.kept_mask) > 0  # (the learned segmenter's and Otsu's labels hold every region, kept or not)
    return dataclasses.replace(seg, binary=back(seg.binary) > 0, opened=back(seg.opened) > 0, labels=labels,
                               regions=region_properties(labels, seg.num_regions, image.dtype), kept_mask=kept,
                               masked=image * kept.to(image.dtype))
