"""The whole obstacle-ranging pipeline on a stereo batch: segmentation → SURF → SAD matching → RANSAC →
rectification → depth (paper Sec. 3.2–3.4), every stage on all B pairs at once.

One frozen :class:`PipelineConfig` drives it; sweeps use ``dataclasses.replace``. Every failure is per pair and
named in :class:`PipelineStatus`; one bad pair never stops the batch.
"""

from __future__ import annotations

import dataclasses
import time

import torch
from torch import nn

from ..core.checks import InputError, check_instance, check_stereo_views, checked_images
from ..core.inference import plain_tensors
from ..core.size_groups import run_by_size
from ..core.types import FundamentalResult, FundamentalStatus, Matches, StereoBatch, StereoSegmentation
from ..depth.depth_types import DepthResult
from ..depth.sparse import estimate_depth
from ..geometry.lk_refinement import refine_matched_points
from ..geometry.matched_points import gather_matched_points
from ..geometry.ransac import estimate_fundamental_ransac
from ..geometry.rectification import rectify_uncalibrated, warp_views
from ..geometry.soft import geometry_straight_through
from ..segmentation.network import check_finite_logits, predict_obstacle_logits
from ..segmentation.segment import SegmentationConfig
from ..segmentation.stereo import check_network, segment_same_size, segmenter_network
from .along_floor import along_floor
from .config import PipelineConfig, PipelineResult
from .exposure import match_exposure
from .exposure_retry import retry_with_exposure
from .features_retry import features_smoothed, retry_with_smoothed_features
from .near_side import near_part_sides
from .near_surface import measure_near_surfaces
from .ranging import (_dense_depth_with_retry, _rectifying_homographies, _smoothed, coarse_config,
                      drop_unmeasured_objects, surface_pixels_of)
from .soft import differentiable_depth
from .stages import (_feature_images, _features, _match, _segment_row_aligned, _status, gaussian_smoothed,
                     measured_labels, without_failed_pairs)

__all__ = ["CHUNK_PIXELS", "estimate_obstacle_depth"]

#: The most left-view pixels one pass of the pipeline takes: a larger batch runs in consecutive chunks of whole pairs
#: (:func:`svs_torch.core.size_groups.run_by_size`), each pair's result unchanged. 32 pairs of 320×240: on this
#: project's 2-core machine the time a pair falls from B = 1 to 32 and rose again beyond, as the stages'
#: intermediates outgrew the caches (``svs-depth bench``'s batch scaling).
CHUNK_PIXELS = 32 * 320 * 240


def estimate_obstacle_depth(batch: StereoBatch, config: PipelineConfig = PipelineConfig(),
                            network: nn.Module | None = None) -> PipelineResult:
    """Range the obstacles of every pair of a stereo batch.

    Args:
        batch: :class:`~svs_torch.core.types.StereoBatch` (calibration: ``focal_px``, ``baseline_m``, ``doffs_px``).
        config: :class:`PipelineConfig`.
        network: the segmenter's network on the batch's device, of the kind ``config.segmentation.segmenter``
            runs: a :class:`~svs_torch.segmentation.nearness.NearnessNet` for ``"nearness"`` (the default) or an
            :class:`~svs_torch.segmentation.learned.ObstacleNet` for ``"learned"``, e.g. from
            :func:`~svs_torch.segmentation.learned.load_obstacle_net`; refused under ``"otsu"``. None: the weights
            that setting names.

    Returns:
        :class:`PipelineResult`. With ``config.differentiable`` (False by default) the hard pipeline runs
        detached: images or calibration that require gradients are detached, and nothing in the result carries
        a graph. With ``differentiable=True`` the hard pipeline still makes every discrete decision, and
        ``result.depth`` (each object's ``depth_median_m`` / ``depth_low_m`` / ``depth_high_m``, the nearest
        obstacle's ``depth_m`` and ``surface_m``, the range) is recomputed differentiably w.r.t. both images,
        the calibration and the parameters of ``network`` (:mod:`svs_torch.pipeline.soft`); ``.valid`` masks
        are the hard ones, and ``result.hard_depth`` holds the hard values. The image gradient is a surrogate:
        the recomputation reads the images rounded to 1/255 levels with the gradient of the unrounded ones
        (straight-through), so finite differences below a level see none. Under ``torch.no_grad()`` (a validation
        loss) ``result.depth`` holds the same recomputed values, bit for bit, not the hard ones (band means: medians
        within 0.5 % of them, :mod:`svs_torch.pipeline.soft`). Called in ``torch.inference_mode()``,
        the hard result's tensors are inference tensors (:mod:`svs_torch.core.inference`); otherwise ordinary ones.

    Each pair is ranged on its own ``image_hw`` pixels only: pairs of different sizes padded into one batch run as
    groups of one size, each cropped to its size (:mod:`svs_torch.core.size_groups`), so a pair's result is the same
    whatever else shares its batch; the result's maps are padded back to the batch's size.

    Raises:
        InputError: naming the argument, for a batch of no pair (a pipeline result of no pair has nothing to
            report; SURF, block matching and RANSAC take B = 0, segmentation and the dense stage refuse it by
            name), a config or network of the wrong kind, or images and calibration the
            stages refuse (a ``config`` with no differentiable path is refused when it is made).
    """
    check_instance(batch, "batch", StereoBatch)
    check_instance(config, "config", PipelineConfig)
    if batch.batch_size == 0:
        raise InputError("batch: expected at least one stereo pair, got an empty batch")
    if network is not None:
        check_network(network, config.segmentation.segmenter)
    if config.differentiable:
        return run_by_size(batch, lambda group: _estimate_group(group, config, network), max_pixels=CHUNK_PIXELS)
    # Nothing to differentiate: each run in inference mode (its ops' bookkeeping is most of a one-pair call's time),
    # and what it returns copied to ordinary tensors (svs_torch.core.inference). The chunks of a large batch are
    # merged outside it: the merge's concatenations are then ordinary tensors already, not copied a second time.
    # A caller already in inference mode (guide's loop) asked for inference tensors: no copy (1 ms a 320x240 pair).
    def run_hard(group: StereoBatch) -> PipelineResult:
        with torch.inference_mode():
            return _estimate_group(group, config, network)

    result = run_by_size(_detached(batch), run_hard, max_pixels=CHUNK_PIXELS)
    return result if torch.is_inference_mode_enabled() else plain_tensors(result)


def _detached(batch: StereoBatch) -> StereoBatch:
    """The batch with every tensor detached (the hard path takes no gradients; a tensor that requires them would
    make the in-place stages raise)."""
    if not any(isinstance(v, torch.Tensor) and v.requires_grad for v in vars(batch).values()):
        return batch
    return dataclasses.replace(batch, **{k: v.detach() for k, v in vars(batch).items()
                                         if isinstance(v, torch.Tensor)})


def _estimate_group(batch: StereoBatch, config: PipelineConfig, network: nn.Module | None) -> PipelineResult:
    """:func:`estimate_obstacle_depth` on a batch whose pairs all fill its tensors: :func:`_estimate_once`, then
    the pairs it left unverified once more with SURF on smoothed views (``config.noisy_features_retry_sigma_px``),
    then the pairs still unfinished whose views' exposures differ once more with them matched
    (``config.exposure_retry``)."""
    run = (lambda pairs, settings: _estimate_once(pairs, settings, network))
    first = retry_with_smoothed_features(batch, run(batch, config), config, run)
    return retry_with_exposure(batch, first, config, run)


def _estimate_once(batch: StereoBatch, config: PipelineConfig, network: nn.Module | None) -> PipelineResult:
    """The hard pipeline without gradients, then, under ``config.differentiable``, the differentiable depths."""
    matched = torch.zeros(batch.batch_size, dtype=torch.bool, device=batch.left.device)
    # Before every stage, with gradients (issue 33: two boards, two exposures); else a right camera's one-sided clip.
    exposure = config.exposure if config.exposure is not None else config.exposure_right_clipped
    if exposure is not None:
        left, right, matched = match_exposure(batch.left, batch.right, batch.image_hw, exposure)
        batch = dataclasses.replace(batch, left=left, right=right)
    logits = None
    if config.differentiable and config.segmentation.segmenter != "otsu":
        # The left views' logits once, with gradients: the hard segmentation thresholds them (detached).
        net = segmenter_network(batch, config.segmentation, network)
        logits = predict_obstacle_logits(net, batch.left, batch.right, config.segmentation.ground, batch.baseline_m,
                                         batch.focal_px, config.segmentation.camera_frames)
        check_finite_logits(logits, "network")
    hard = _detached(batch)
    check_stereo_views(hard.left, hard.right)  # once here: the stages then take the two views as checked
    with torch.no_grad(), checked_images(hard.left, hard.right):
        result = dataclasses.replace(_estimate_hard(hard, config, network, logits), exposure_matched=matched,
                                     features_smoothed=features_smoothed(batch.batch_size, config, batch.left.device))
    if not config.differentiable:
        return result
    if logits is not None and bool(result.row_aligned.any()):
        logits = _row_aligned_logits(batch, result, logits, segmenter_network(batch, config.segmentation, network),
                                     config.segmentation)
    left, right = batch.left, batch.right
    if config.noisy_retry_sigma_px is not None and bool(result.smoothed.any()):
        # The pairs the hard stage measured on smoothed views are differentiated through the same (linear) blur, of
        # a σ in working pixels of the grid each was measured on.
        for on_coarse, settings in ((False, config), (True, coarse_config(config))):
            group = result.smoothed & (result.coarse == on_coarse)
            if bool(group.any()):
                blurred = _smoothed(batch, config.noisy_retry_sigma_px, settings.dense)
                pick = group.view(-1, 1, 1, 1)
                left, right = torch.where(pick, blurred.left, left), torch.where(pick, blurred.right, right)
    H_left, H_right = _differentiable_homographies(batch, result, config)
    depth = differentiable_depth(
        left, right, result.object_labels, logits, result.rectified, H_left, H_right,
        result.dense, result.depth, batch.focal_px, batch.baseline_m, batch.doffs_px, batch.image_hw,
        config.depth.object_percentiles, config.dense, result.coarse, coarse_config(config).dense,
        surface_pixels_of(result.dense, config))
    return dataclasses.replace(result, depth=depth, hard_depth=result.depth, H_left=H_left, H_right=H_right)


def _row_aligned_logits(batch: StereoBatch, result: PipelineResult, logits: torch.Tensor, net: nn.Module,
                        segmentation: SegmentationConfig = SegmentationConfig()) -> torch.Tensor:
    """``logits`` with the rows of the pairs the hard pass segmented again on their row-aligned views
    (:func:`~svs_torch.pipeline.stages._segment_row_aligned`) made likewise, with gradients to both images: what
    the hard segmentation thresholded (the alignment itself is a constant here; ``segmentation``: its floor and
    noise gate)."""
    index = result.row_aligned.nonzero().flatten()
    warped = warp_views(batch.right.index_select(0, index), result.H_right.index_select(0, index).detach())
    return logits.index_copy(0, index, predict_obstacle_logits(net, batch.left.index_select(0, index), warped,
                                                               segmentation.ground,
                                                               batch.baseline_m.index_select(0, index),
                                                               batch.focal_px.index_select(0, index),
                                                               segmentation.camera_frames))


def _differentiable_homographies(batch: StereoBatch, result: PipelineResult, config: PipelineConfig
                                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """The hard pass's homographies, with gradients to the images through the refined matches and F's refit and
    Hartley's rectification, or the row alignment's refit, where the pair was rectified by them
    (:mod:`svs_torch.geometry.soft`); the identity of unrectified pairs is a constant."""
    dtype = batch.left.dtype
    # Recorded by the hard pass (_rectifying_homographies): which pairs each homography source rectified.
    from_rows, row_inliers = result.row_aligned, result.row_alignment_inliers
    from_F = result.rectified & ~from_rows
    if not bool((from_F | from_rows).any()):
        return result.H_left.to(dtype), result.H_right.to(dtype)
    left, right = batch.left, batch.right
    if config.features_on == "masked":  # the views the matches were refined on
        left = left * result.segmentation.left.kept_mask.to(dtype)
        right = right * result.segmentation.right.kept_mask.to(dtype)
    if config.feature_smoothing_sigma_px is not None:  # ... smoothed as SURF's were (stages._feature_images)
        left = gaussian_smoothed(left, config.feature_smoothing_sigma_px)
        right = gaussian_smoothed(right, config.feature_smoothing_sigma_px)
    points, refine = result.points, config.refine_matches
    scale = result.features_left.keypoints.scale
    if refine is None:
        radius, moved = torch.ones_like(scale), torch.zeros_like(points.valid)
    else:
        radius = (refine.radius_scales * scale).clamp(refine.min_radius_px, refine.max_radius_px)
        unrefined = gather_matched_points(result.features_left.keypoints.xy, result.features_right.keypoints.xy,
                                          result.matches)
        moved = points.valid & (points.right != unrefined.right).any(dim=-1)
    return geometry_straight_through(left, right, points.left, points.right, radius, moved,
                                     result.fundamental.inliers, result.fundamental.F, from_F, row_inliers,
                                     from_rows, result.H_left, result.H_right, batch.image_hw, config.rectification,
                                     batch.focal_px, result.row_alignment_turn_deg)


def _fundamental_ok(fundamental: FundamentalResult, matches: Matches, config: PipelineConfig) -> torch.Tensor:
    """``(B,)`` bool: RANSAC found F with enough inliers, and a share of the matches, for the sparse stage to vouch
    for the pair (``PipelineConfig.verify_min_inliers``, ``verify_min_inlier_share``)."""
    return ((fundamental.status == FundamentalStatus.OK) & (fundamental.num_inliers >= config.verify_min_inliers)
            & (fundamental.num_inliers >= config.verify_min_inlier_share * matches.valid.sum(1)))


def _dense_rule(batch: StereoBatch, seg: StereoSegmentation, depth: DepthResult, fundamental_ok: torch.Tensor,
                points_left: torch.Tensor, inliers: torch.Tensor, rectified: torch.Tensor, H_left: torch.Tensor,
                H_right: torch.Tensor, object_labels: torch.Tensor, config: PipelineConfig) -> tuple:
    """The dense range rule's stages after the sparse one: the dense depth with its second passes, the kept regions
    it could not measure dropped, the two-surface objects measured over their near surface, and each side said of
    the part measured (:mod:`~svs_torch.pipeline.near_side`). Returns the
    segmentation, depth and object labels after them, then the dense map and the verified, agreeing, measured,
    smoothed, coarse and near-surface flags and the dropped slots' labels (:class:`PipelineResult`'s fields of
    those names)."""
    depth, dense, verified, agreeing, measured, smoothed, coarse = _dense_depth_with_retry(
        batch, seg, depth, fundamental_ok, points_left, inliers, rectified, H_left, H_right, object_labels, config)
    # a fence left unranged as its alias was not told stays listed (depth.alias_choice.alias_depths_m)
    repeated = None if dense.repeated is None else dense.repeated.unranged(depth.objects.valid)
    seg, depth, dropped = drop_unmeasured_objects(batch, seg, depth, config.drop_unmeasured_below_share,
                                                  config.drop_unmeasured_nearer_below_share, repeated)
    near = None
    if config.measure_near_surface:
        depth, object_labels, near = measure_near_surfaces(depth, dense, object_labels, rectified, H_left, inliers,
                                                           batch.focal_px, batch.baseline_m, batch.doffs_px, config)
    # The side said with a distance is that of the part it was measured on (a region over two touching boxes).
    depth = near_part_sides(depth, dense, object_labels, rectified, H_left, batch.image_hw, batch.focal_px,
                            batch.baseline_m, batch.doffs_px, near)
    return seg, depth, object_labels, dense, verified, agreeing, measured, smoothed, coarse, dropped, near


def _estimate_hard(batch: StereoBatch, config: PipelineConfig, network: nn.Module | None,
                   left_logits: torch.Tensor | None = None) -> PipelineResult:
    """The hard pipeline (no gradients) on a batch whose pairs all fill its tensors."""
    timings: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(stage: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        timings[stage] = timings.get(stage, 0.0) + now - clock  # segmentation may run twice (row-aligned pairs)
        clock = now

    seg = segment_same_size(batch, config.segmentation, network, left_logits)
    lap("segmentation")
    images, detect_mask = _feature_images(batch, seg, config)
    left, right = _features(images, detect_mask, config)
    lap("features")
    matches = _match(left, right, config)
    points = gather_matched_points(left.keypoints.xy, right.keypoints.xy, matches)
    b = batch.batch_size
    points, matches = refine_matched_points(images[:b], images[b:], points, matches, left.keypoints.scale,
                                            config.refine_matches)
    lap("matching")
    seeds = torch.full((batch.batch_size,), config.seed, dtype=torch.int64, device=batch.left.device)
    fundamental = estimate_fundamental_ransac(
        points.left, points.right, points.valid, threshold_px=config.ransac_threshold_px,
        confidence=config.ransac_confidence, max_iterations=config.ransac_max_iterations,
        scoring=config.ransac_scoring, pair_seeds=seeds)
    lap("ransac")
    rectification = rectify_uncalibrated(fundamental.F, points.left, points.right, fundamental.inliers,
                                         batch.image_hw, config.rectification)
    rectified, H_left, H_right, row_aligned, row_inliers, turn = _rectifying_homographies(
        points, fundamental, rectification, batch.image_hw, seeds, config, batch.focal_px)
    lap("rectification")
    if config.segmentation.segmenter != "otsu" and bool(row_aligned.any()):  # they measure along rows: again
        seg = _segment_row_aligned(batch, seg, row_aligned, H_right, config.segmentation, network)
        lap("segmentation")
    object_labels = measured_labels(seg, batch.left.shape[-1], config)  # the dense search keeps whole regions
    depth = estimate_depth(
        points.left, points.right, fundamental.inliers, batch.focal_px, batch.baseline_m, batch.doffs_px,
        H_left=H_left, H_right=H_right, statistics=config.depth.rule != "dense",  # the dense rule measures them
        labels=object_labels, region_labels=seg.left.kept_labels, image_hw=batch.image_hw, config=config.depth)
    dense = verified = agreeing = measured = smoothed = coarse = dropped = near = None
    if config.depth.rule == "dense":
        (seg, depth, object_labels, dense, verified, agreeing, measured, smoothed, coarse, dropped,
         near) = _dense_rule(batch, seg, depth, _fundamental_ok(fundamental, matches, config), points.left,
                             fundamental.inliers, rectified, H_left, H_right, object_labels, config)
    lap("depth")
    num_keypoints = torch.stack([left.keypoints.valid.sum(1), right.keypoints.valid.sum(1)], dim=1)
    status = _status(seg, num_keypoints, fundamental, rectification, depth, config.rectify, dense is not None)
    return PipelineResult(
        status=status, depth=without_failed_pairs(depth, status),
        floor=along_floor(batch, seg, depth, status, dense, object_labels, rectified, H_left, config),
        segmentation=seg, features_left=left, features_right=right, matches=matches, points=points,
        fundamental=fundamental, num_keypoints=num_keypoints, rectification=rectification, rectified=rectified,
        dense=dense, range_rule=config.depth.rule, num_matches=matches.valid.sum(1), near_surface=near,
        num_inliers=fundamental.num_inliers, timings_s=timings, verified=verified, num_agreeing_inliers=agreeing,
        num_measured_inliers=measured, H_left=H_left, H_right=H_right, smoothed=smoothed, row_aligned=row_aligned,
        row_alignment_inliers=row_inliers, row_alignment_turn_deg=turn, coarse=coarse, dropped_labels=dropped,
        object_labels=object_labels, focal_px=batch.focal_px, baseline_m=batch.baseline_m, doffs_px=batch.doffs_px)
