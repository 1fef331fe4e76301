"""The pipeline's last steps: whether to rectify (and with which homographies), then the dense depth over the
kept regions, measured again at half the working width where the first pass measured too few of a pair's kept
pixels, and retried on a smoothed pair left unfinished.
"""

from __future__ import annotations

import dataclasses

import torch

from ..core.mask_reductions import any_along
from ..core.pair_trees import put_pairs, take_pairs
from ..core.types import FundamentalResult, StereoBatch, StereoSegmentation
from ..depth.alias_choice import settle_repeated_objects
from ..depth.dense import estimate_dense_disparity, working_factor
from ..depth.dense_config import DenseConfig, DenseDisparity
from ..depth.dense_objects import (count_agreeing_inliers, dense_object_depths, range_from_objects,
                                   surface_pixels)
from ..depth.depth_types import DepthResult, Disparities, ObjectDepths
from ..depth.periodicity import object_periods
from ..depth.quantiles import masked_quantile
from ..depth.sparse import nearest_obstacle, slot_labels
from ..geometry.matched_points import MatchedPoints
from ..geometry.rectification import Rectification, RectificationStatus, warp_views
from ..geometry.row_alignment import fit_row_alignment
from ..segmentation.segment import kept_regions_mask
from .beyond_range import unrange_objects_beyond_search
from .config import PipelineConfig
from .stages import gaussian_smoothed, warp_labels, warped_where

__all__ = []


def _use_rectification(points_left: torch.Tensor, points_right: torch.Tensor, inliers: torch.Tensor,
                       rectification: Rectification, config: PipelineConfig) -> torch.Tensor:
    """``(B,)`` bool: pairs whose disparities are measured after rectification (see ``PipelineConfig.rectify``)."""
    usable = rectification.status == RectificationStatus.OK
    if config.rectify == "off":
        return torch.zeros_like(usable)
    if config.rectify == "required":
        return usable
    row_offset = (points_left[..., 1] - points_right[..., 1]).abs()
    median = masked_quantile(row_offset, inliers, [0.5]).values[:, 0]
    return usable & (median > config.row_tolerance_px)


def _rectifying_homographies(points: MatchedPoints, fundamental: FundamentalResult, rectification: Rectification,
                             image_hw: torch.Tensor, seeds: torch.Tensor, config: PipelineConfig,
                             focal_px: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """``(B,)`` bool rectified, the ``(B, 3, 3)`` left and right homographies the disparities are measured after
    (identity where not rectified): a row alignment of the right view where ``config.row_alignment`` finds one
    that matters (``rectify="auto"`` only; its keystone scaled by ``focal_px`` ``(B,)``), else F's rectification
    by :func:`_use_rectification`; and which pairs the row alignment rectified ``(B,)``, its inliers ``(B, K)``
    and its turns ``(B, 2)`` degrees (the differentiable pass refits it on them)."""
    rectified = _use_rectification(points.left, points.right, fundamental.inliers, rectification, config)
    identity = torch.eye(3, dtype=rectification.H_left.dtype, device=rectification.H_left.device
                         ).expand_as(rectification.H_left)
    pick = rectified.view(-1, 1, 1)
    H_left = torch.where(pick, rectification.H_left, identity)
    H_right = torch.where(pick, rectification.H_right, identity)
    if config.rectify != "auto" or config.row_alignment is None:
        return (rectified, H_left, H_right, torch.zeros_like(rectified), torch.zeros_like(points.valid),
                torch.zeros_like(H_left[:, 0, :2]))
    # The similarity is fitted to every match, not F's inliers: F of a few planar obstacles may be loose.
    alignment = fit_row_alignment(points.left, points.right, points.valid, image_hw, config.row_alignment, seeds,
                                  focal_px)
    # A keystone moves rows by under a pixel at 320×240 yet biases the disparity at the edges by about one.
    aligned = alignment.valid & ((alignment.correction_px > config.row_alignment.min_correction_px)
                                 | alignment.keystone)
    pick = aligned.view(-1, 1, 1)
    # keystone_deg is 0 wherever the alignment is not applied: a turn it reads makes it valid and applied.
    return (rectified | aligned, torch.where(pick, identity, H_left),
            torch.where(pick, alignment.H_right.to(H_right.dtype), H_right), aligned, alignment.inliers,
            alignment.keystone_deg.to(H_left.dtype))


def _dense_depth(batch: StereoBatch, seg: StereoSegmentation, sparse: DepthResult, fundamental_ok: torch.Tensor,
                 points_left: torch.Tensor, inliers: torch.Tensor, rectified: torch.Tensor, H_left: torch.Tensor,
                 H_right: torch.Tensor, object_labels: torch.Tensor, config: PipelineConfig
                 ) -> tuple[DepthResult, DenseDisparity, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The ``"dense"`` rule: SAD disparity over the kept regions of ``seg`` (in rectified pixels where the pair
    was rectified: images and labels warped by the same homographies) over each pair's range (a coarse pass, or
    the sparse inliers' disparities), then each object's depth statistics over its region in ``object_labels``
    ``(B, 1, H, W)`` (the kept regions' interiors, :func:`~svs_torch.pipeline.stages.measured_labels`, or
    ``seg``'s labels; ``sparse.objects`` holds their areas). Also returns whether the pair's geometry was
    verified (``fundamental_ok`` and enough inliers the dense map confirms) and the counts of agreeing and of
    measured inliers, ``(B,)`` each."""
    left, right, labels = batch.left, batch.right, seg.left.labels
    if bool(rectified.any()):  # (only the rectified pairs are warped: warped_where)
        left = warped_where(left, H_left, rectified, warp_views)
        right = warped_where(right, H_right, rectified, warp_views)
        # By nearest neighbour, as exact small integers in float64, with whether the pixel is in its object
        # (not a border pixel object_labels left out) in the lowest bit: one warp for both label images.
        coded = warped_where(labels * 2 + (object_labels == labels).long(), H_left, rectified, warp_labels)
        labels = coded // 2
        object_labels = torch.where(coded % 2 == 1, labels, torch.zeros_like(labels))
    # One mask per kept object, so the search range covers a small object as well as a big one.
    objects = labels == slot_labels(seg.left.kept_labels).view(batch.batch_size, -1, 1, 1)
    mask = any_along(objects, dim=1, keepdim=True)
    dense = estimate_dense_disparity(left, right, mask, config.dense, batch.image_hw,
                                     sparse.disparities.disparity_px, sparse.disparities.valid, objects)
    if config.depth.alias_check_min_period_peak is not None:  # a fence, railing or grate ranged on its own alias
        dense = settle_repeated_objects(left, right, objects, dense, config.depth.alias_check_min_period_peak,
                                        config.dense, batch.image_hw, config.depth.alias_check_max_period_px)
    agreeing, measured = _confirmed_inliers(dense, points_left, sparse.disparities, inliers, H_left, config)
    verified = fundamental_ok & _vouched(inliers.sum(1), agreeing, measured, config)
    if config.verify_whole_view:
        verified, agreeing, measured = _vouched_over_whole_view(
            left, right, batch.image_hw, sparse.disparities, points_left, inliers, H_left, fundamental_ok,
            (verified, agreeing, measured), config)
    weight = verified.to(batch.left.dtype)
    fraction = (weight * config.depth.min_object_valid_fraction
                + (1 - weight) * config.depth.min_object_valid_fraction_unverified)
    objects = dense_object_depths(dense, object_labels, sparse.objects, batch.focal_px, batch.baseline_m,
                                  batch.doffs_px, config.depth.object_percentiles, config.depth.min_object_pixels,
                                  config.dense.fill_invalid, fraction, config.depth.min_object_pixels_in_view,
                                  config.dense.in_view_own_min_valid_share, surface_pixels_of(dense, config))
    objects = unrange_objects_beyond_search(objects, sparse.objects.point_slot, sparse.disparities, inliers, dense)
    depth_range = range_from_objects(objects, batch.focal_px, batch.baseline_m, batch.doffs_px)
    depth = DepthResult(sparse.disparities, sparse.points, depth_range, objects, nearest_obstacle(objects))
    return depth, dense, verified, agreeing, measured


def surface_pixels_of(dense: DenseDisparity, config: PipelineConfig) -> torch.Tensor | None:
    """The pixels each object's nearest surface is measured over
    (:func:`~svs_torch.depth.dense_objects.surface_pixels`) where ``config.depth.surface_within_in_view_top`` asks
    for them; else None (every valid pixel)."""
    return surface_pixels(dense) if config.depth.surface_within_in_view_top else None


def _vouched(num_inliers: torch.Tensor, agreeing: torch.Tensor, measured: torch.Tensor,
             config: PipelineConfig) -> torch.Tensor:
    """``(B,)`` bool: the pairs whose RANSAC inliers ``(B,)`` the dense map confirms (``agreeing`` of the
    ``measured`` ones) well enough that both views show one scene (``PipelineConfig.verify_*``)."""
    vouched = agreeing >= config.verify_min_agreeing_inliers
    if config.verify_many_inliers is not None:  # a clipped or noisy view's dense map confirms few of many
        vouched = vouched | ((num_inliers >= config.verify_many_inliers)
                             & (agreeing >= config.verify_many_inliers_min_agreeing))
    if config.verify_unanimous_min_inliers is not None:  # a noisy map measures few inliers, and confirms them all
        vouched = vouched | ((num_inliers >= config.verify_unanimous_min_inliers)
                             & (agreeing >= config.verify_unanimous_min_agreeing) & (agreeing == measured))
    return vouched


def _confirmed_inliers(dense: DenseDisparity, points_left: torch.Tensor, disparities: Disparities,
                       inliers: torch.Tensor, H_left: torch.Tensor, config: PipelineConfig
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """The RANSAC inliers ``(B, K)`` the dense map confirms and those it measured, ``(B,)`` each: agreement within
    one working pixel (the dense map's own grid) between the sparse and the dense disparity."""
    height, width = dense.disparity_px.shape[-2:]
    return count_agreeing_inliers(dense, points_left, disparities, inliers, H_left,
                                  float(working_factor(width, config.dense, height)), return_measured=True)


def _vouched_over_whole_view(left: torch.Tensor, right: torch.Tensor, image_hw: torch.Tensor | None,
                             disparities: Disparities, points_left: torch.Tensor, inliers: torch.Tensor,
                             H_left: torch.Tensor, fundamental_ok: torch.Tensor,
                             verdict: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
                             config: PipelineConfig) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``verdict`` (verified, agreeing and measured inliers, ``(B,)`` each) with the pairs it leaves unverified
    whose F was found (``fundamental_ok`` ``(B,)``) checked again against a dense map of their whole (rectified)
    left view: where it vouches (:func:`_vouched`, the same rules), the pair is verified and its counts are that
    map's.

    Why: RANSAC's inliers lie anywhere in the view (``features_on="image"``), the dense map only near the kept
    regions. On a camera frame noise can make the segmenter keep small regions away from every inlier, so the
    map measures none of them and a real pair stays unverified and unranged (the tuned PianoL as JPEG digit 7
    or 8 frames: 25-29 inliers, none measured; over its whole view 15-27 measured, 11-26 confirmed). Views of
    different scenes stay apart (``experiments/verify_views.py``). Only pairs left unverified pay for the pass, so
    a clean pair's result is unchanged.
    """
    again = (fundamental_ok & ~verdict[0]).nonzero().flatten()
    if not len(again):
        return verdict
    pick = (lambda t: t.index_select(0, again))
    whole = torch.ones_like(pick(left), dtype=torch.bool)
    mine = take_pairs(disparities, again, left.shape[0])
    # Plain block matching even in the coarse retry: the map only confirms inliers, and an aggregated volume
    # would cost a whole view's (experiments/real_rig.md, "Semi-global aggregation of the coarse retry").
    plain = dataclasses.replace(config.dense, smoothing_penalties=None)
    dense = estimate_dense_disparity(pick(left), pick(right), whole, plain,
                                     None if image_hw is None else pick(image_hw), mine.disparity_px, mine.valid,
                                     whole)
    agreeing, measured = _confirmed_inliers(dense, pick(points_left), mine, pick(inliers), pick(H_left), config)
    vouched = _vouched(pick(inliers).sum(1), agreeing, measured, config)
    now = again[vouched]
    verified, agreeing_out, measured_out = (t.clone() for t in verdict)
    verified[now] = True
    agreeing_out[now], measured_out[now] = agreeing[vouched], measured[vouched]
    return verified, agreeing_out, measured_out


def _smoothed(batch: StereoBatch, sigma_working_px: float, config: DenseConfig) -> StereoBatch:
    """Both views smoothed by a Gaussian of ``sigma_working_px`` working pixels of the dense stage."""
    sigma = sigma_working_px * working_factor(batch.left.shape[-1], config, batch.left.shape[-2])
    return dataclasses.replace(batch, left=gaussian_smoothed(batch.left, sigma),
                               right=gaussian_smoothed(batch.right, sigma))


def unranged_kept_object(seg: StereoSegmentation, objects: ObjectDepths) -> torch.Tensor:
    """``(B,)`` bool: pairs with a kept region whose object got no depth."""
    kept = seg.left.kept_labels >= 0
    return (kept & ~objects.valid[:, :kept.shape[1]]).any(1)


def second_pass_is_better(verified_first: torch.Tensor, ranged_first: torch.Tensor, verified_second: torch.Tensor,
                          ranged_second: torch.Tensor) -> torch.Tensor:
    """``(b,)`` bool: the pairs whose second pass (of the smoothed or the exposure retry) replaces the first:
    verified and ranging more objects, or as many where the first was not verified (``verified_*`` ``(b,)`` bool,
    ``ranged_*`` ``(b, N)`` bool, each object's ``valid``). Only a verified second pass counts: views of different
    scenes are never verified, and a retry must not let their chance agreement reach the unverified share
    (experiments/verify_views.py)."""
    first, second = ranged_first.sum(1), ranged_second.sum(1)
    return verified_second & ((second > first) | (~verified_first & (second >= first)))


def coarse_config(config: PipelineConfig) -> PipelineConfig:
    """``config`` with the dense stage at half its working width (``PipelineConfig.coarse_retry_below_share``),
    aggregated with ``DenseConfig.retry_smoothing_penalties``, and periods looked for over the same stretch of
    the image (``DepthConfig``'s longest periods halved with the pixels: their whole count of coarse pixels spans
    twice the image, where a rendered scene's texture, synthetic-7 as JPEG digit 8 frames, read a period of 104
    input pixels)."""
    width = max(8, config.dense.working_width_px // 2)
    shorter = {name: max(4, getattr(config.depth, name) * width // config.dense.working_width_px)
               for name in ("coarse_retry_max_period_px", "alias_check_max_period_px")}
    return dataclasses.replace(
        config, depth=dataclasses.replace(config.depth, **shorter),
        dense=dataclasses.replace(config.dense, working_width_px=width,
                                  smoothing_penalties=config.dense.retry_smoothing_penalties))


def measured_share(objects: ObjectDepths) -> torch.Tensor:
    """``(B,)``: the share of the kept regions' pixels the dense map measured (0 without a kept region)."""
    area = objects.area_px.clamp_min(0).sum(1)
    return objects.num_valid_px.sum(1).to(torch.float64) / area.clamp_min(1).to(torch.float64)


def _second_pass(current: tuple, index: torch.Tensor, settings: PipelineConfig, sigma_working_px: float | None,
                 rule, batch: StereoBatch, seg: StereoSegmentation, sparse: DepthResult,
                 fundamental_ok: torch.Tensor, points_left: torch.Tensor, inliers: torch.Tensor,
                 rectified: torch.Tensor, H_left: torch.Tensor, H_right: torch.Tensor, object_labels: torch.Tensor
                 ) -> tuple[tuple, torch.Tensor]:
    """The pairs ``index`` of ``current`` (:func:`_dense_depth`'s result) measured again under ``settings``, on views
    smoothed by ``sigma_working_px`` (None: as they are); each kept where ``rule(verified_first, ranged_first,
    verified_second, ranged_second)`` ``(b,)`` bool says. Returns the merged result and the pairs replaced, a
    subset of ``index``. Only these pairs run again: a clean batch's pairs never pay for it."""
    b = batch.batch_size
    sub = (lambda tree: take_pairs(tree, index, b))
    views = sub(batch) if sigma_working_px is None else _smoothed(sub(batch), sigma_working_px, settings.dense)
    second = _dense_depth(views, sub(seg), sub(sparse), sub(fundamental_ok), sub(points_left), sub(inliers),
                          sub(rectified), sub(H_left), sub(H_right), sub(object_labels), settings)
    pick = rule(sub(current[2]), sub(current[0].objects.valid), second[2], second[0].objects.valid)
    if not bool(pick.any()):
        return current, index[:0]
    merged = put_pairs(current, index[pick], take_pairs(second, pick.nonzero().flatten(), len(index)), b)
    # The batch's deepest search (an int, not per pair).
    dense = dataclasses.replace(merged[1], num_disparities=max(current[1].num_disparities, second[1].num_disparities))
    return (merged[0], dense, *merged[2:]), index[pick]


def coarse_is_better(verified_first: torch.Tensor, ranged_first: torch.Tensor, verified_second: torch.Tensor,
                     ranged_second: torch.Tensor) -> torch.Tensor:
    """``(b,)`` bool: the pairs whose coarse pass (``PipelineConfig.coarse_retry_below_share``) replaces the first:
    verified and ranging every object the first did, or unverified as the first was and ranging as many (the same
    objects measured on a coarser grid: an unverified pair's chance agreement must not reach more objects,
    experiments/verify_views.py). Arguments as :func:`second_pass_is_better`'s."""
    first, second = ranged_first.sum(1), ranged_second.sum(1)
    return (verified_second & (second >= first)) | (~verified_first & ~verified_second & (second == first))


def drop_unmeasured_objects(batch: StereoBatch, seg: StereoSegmentation, depth: DepthResult,
                            below_share: float | None, nearer_below_share: float | None = None,
                            repeated: torch.Tensor | None = None
                            ) -> tuple[StereoSegmentation, DepthResult, torch.Tensor]:
    """The kept left regions whose dense map measured less than ``below_share`` of their pixels, dropped where
    another kept region of the pair was ranged on at least that share and their few pixels range them no nearer
    than it (or not at all) (``PipelineConfig.drop_unmeasured_below_share``). The slots ``repeated`` ``(B, N)`` bool
    marks (None: none; the repeated objects left unranged) are never dropped: a fence whose alias could not be told
    was seen, and stays listed with its aliases' distances (``DenseDisparity.repeated``).

    Returns ``seg`` with those slots of the left ``kept_labels`` set to −1 and the left ``kept_mask`` / ``masked``
    without them (the right view's segmentation, which the features were found on, is left as it was), ``depth``
    with those objects' ``label`` −1 and ``valid`` False and the range and nearest obstacle recomputed, and the
    label each dropped slot held ``(B, N)`` int64, −1 elsewhere (``PipelineResult.dropped_labels``: an evaluation
    still scores the region). Camera noise lets the segmenter keep a far or depth-straddling region whose
    dense map is mostly rejected (held-out Midd1 with JPEG digit 1: a 10.7 m region measured on 10 % of its pixels
    and ranged at 6.8 m beside the 4.1 m obstacle), and the few pixels kept are the wrong ones: a region the dense
    stage cannot measure is not an obstacle the pair can warn about, while one it measured is. A region ranged
    nearer than every measured one stays: dropped, it would move the warning to a farther object, and held-out
    scenes hold true near obstacles measured on under half their pixels (Lampshade2's 5 m lamp beside a 12.5 m
    wall). So the nearest obstacle and R_min do not change by this rule; R_max and the objects listed may. A pair
    whose every kept region was measured on too little keeps them all (each is ranged or not by its own share as
    before). A kept region the depth stage left unranged beside one it ranged is dropped whatever its share: one
    wholly in the left band where the right camera may not see it (``DepthConfig.min_object_pixels_in_view``;
    the tuned Jadeplant at native size, JPEG digit 6: a 2174-pixel region at x ≈ 114 beside a search range up to
    197 px, listed with no distance) is no obstacle the pair can range. ``below_share`` None drops nothing.

    ``nearer_below_share`` (None: unused) drops a region measured on less than it (and less than ``below_share``)
    even where its few pixels range it nearer than the measured one: under that share nearly every window was
    rejected, the region's range is mostly its row neighbours' disparities filled in, and noise ranges a far
    textureless region near (held-out Midd2 with JPEG digit 4: a 16 m wall measured on 11 % of its pixels, ranged
    at 2.65 m beside the 4.0 m obstacle). Only that rule can change the nearest obstacle."""
    objects = depth.objects
    kept = seg.left.kept_labels >= 0
    none = torch.full_like(seg.left.kept_labels, -1)
    if below_share is None or kept.shape[1] == 0:
        return seg, depth, none
    share = objects.num_valid_px.to(torch.float64) / objects.area_px.clamp_min(1).to(torch.float64)
    measured = kept & objects.valid & (share >= below_share)
    # The nearest measured object's depth: a region ranged nearer than it is kept unless nearly nothing was measured.
    nearest_measured = torch.where(measured, objects.depth_median_m, torch.inf).amin(1, keepdim=True)
    droppable = objects.depth_median_m >= nearest_measured
    if nearer_below_share is not None:
        droppable = droppable | (share < nearer_below_share)
    # An unranged region goes however much was measured: one in the band the right camera may not see
    # (DepthConfig.min_object_pixels_in_view), or too small to count.
    dropped = kept & (((share < below_share) & droppable) | ~objects.valid) & measured.any(1, keepdim=True)
    if repeated is not None:
        dropped &= ~repeated
    if not bool(dropped.any()):
        return seg, depth, none
    kept_labels = torch.where(dropped, none, seg.left.kept_labels)
    kept_mask = kept_regions_mask(seg.left.labels, kept_labels, seg.left.regions.area_px.shape[1])
    left = dataclasses.replace(seg.left, kept_labels=kept_labels, kept_mask=kept_mask,
                               masked=torch.where(kept_mask, seg.left.masked, torch.zeros_like(seg.left.masked)))
    label = torch.where(dropped, torch.full_like(objects.label, -1), objects.label)
    objects = dataclasses.replace(objects, label=label, valid=objects.valid & ~dropped)
    depth_range = range_from_objects(objects, batch.focal_px, batch.baseline_m, batch.doffs_px)
    depth = DepthResult(depth.disparities, depth.points, depth_range, objects, nearest_obstacle(objects))
    return dataclasses.replace(seg, left=left), depth, torch.where(dropped, seg.left.kept_labels, none)


def _dense_depth_with_retry(batch: StereoBatch, seg: StereoSegmentation, sparse: DepthResult,
                            fundamental_ok: torch.Tensor, points_left: torch.Tensor, inliers: torch.Tensor,
                            rectified: torch.Tensor, H_left: torch.Tensor, H_right: torch.Tensor,
                            object_labels: torch.Tensor, config: PipelineConfig
                            ) -> tuple[DepthResult, DenseDisparity, torch.Tensor, torch.Tensor, torch.Tensor,
                                       torch.Tensor, torch.Tensor]:
    """:func:`_dense_depth`, then two second passes, each over a few pairs:

    - **coarse** (``config.coarse_retry_below_share``): the pairs whose dense map measured too little of their
      kept regions are measured again at half the working width (:func:`coarse_config`), kept by
      :func:`coarse_is_better`. A noisy frame's x-Sobel SAD finds few unique windows at the working width, and
      the ones it finds are often wrong (ranged, verified, far off); a working pixel four times as large halves
      the noise, and a window twice as wide sees more texture. A pair no wider than the coarse working width
      gains nothing and is not measured again;
    - **smoothed** (``config.noisy_retry_sigma_px``): the pairs then left unverified or with a kept object unranged
      are measured again on views smoothed by a Gaussian (of that σ in working pixels, at the coarse width for
      the pairs that measured too little), kept by :func:`second_pass_is_better`.

    Also returns ``(B,)`` bool each: the pairs whose result was measured on smoothed views, and those measured at
    the coarse working width."""
    passes = (batch, seg, sparse, fundamental_ok, points_left, inliers, rectified, H_left, H_right, object_labels)
    current = _dense_depth(*passes, config)
    coarse, smoothed = torch.zeros_like(rectified), torch.zeros_like(rectified)
    settings = coarse_config(config)
    height, width = batch.left.shape[-2:]
    low = torch.zeros_like(rectified)
    if (config.coarse_retry_below_share is not None
            and working_factor(width, settings.dense, height) > working_factor(width, config.dense, height)):
        objects = current[0].objects
        low = (measured_share(objects) < config.coarse_retry_below_share) & (objects.area_px.sum(1) > 0)
        if config.depth.coarse_retry_max_period_peak is not None and bool(low.any()):
            # A repeated pattern aliases on the coarse grid, where its period halves (depth.periodicity); only the
            # pairs to retry are looked at, object by object.
            index = low.nonzero().flatten()
            kept_labels = seg.left.kept_labels[index]
            kept = seg.left.labels[index] == slot_labels(kept_labels).view(*kept_labels.shape, 1, 1)
            periods = object_periods(batch.left[index], kept, config.depth.coarse_retry_max_period_peak,
                                     config.dense, config.depth.coarse_retry_max_period_px)
            low = low.index_put((index,), (periods == 0).all(dim=1))
        if bool(low.any()):
            current, replaced = _second_pass(current, low.nonzero().flatten(), settings, None, coarse_is_better,
                                             *passes)
            coarse[replaced] = True
    if config.noisy_retry_sigma_px is None:
        return (*current, smoothed, coarse)
    retry = ~current[2] | unranged_kept_object(seg, current[0].objects)
    for group, group_settings in ((retry & ~low, config), (retry & low, settings)):
        if bool(group.any()):
            current, replaced = _second_pass(current, group.nonzero().flatten(), group_settings,
                                             config.noisy_retry_sigma_px, second_pass_is_better, *passes)
            smoothed[replaced] = True
            coarse[replaced] = group_settings is settings
    return (*current, smoothed, coarse)
