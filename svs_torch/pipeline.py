"""The whole obstacle-ranging pipeline on a stereo batch: segmentation → SURF → SAD matching → RANSAC →
rectification → depth (paper Sec. 3.2–3.4), every stage on all B pairs at once.

One frozen :class:`PipelineConfig` drives it; sweeps use ``dataclasses.replace``. Every failure is per pair and
named in :class:`PipelineStatus`; one bad pair never stops the batch.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import time
from dataclasses import dataclass, field
from typing import Literal

import torch
from torch import nn

from .checks import InputError, check_instance
from .dense import DenseConfig, DenseDisparity, estimate_dense_disparity, working_factor
from .dense_depth import count_agreeing_inliers, dense_object_depths, range_from_objects
from .depth import DepthConfig, DepthResult, estimate_depth, masked_quantile, nearest_obstacle, slot_labels
from .detector import SurfConfig
from .features import SurfFeatures, extract_surf_features
from .learned_segmentation import _cached_obstacle_net, predict_obstacle_logits, segment_stereo_learned
from .mask_reductions import any_along
from .matching import (MatchedPoints, MatchRefinementConfig, gather_matched_points, match_sad,
                       refine_matched_points)
from .ransac import estimate_fundamental_ransac
from .row_alignment import RowAlignmentConfig, fit_row_alignment
from .rectification import (Rectification, RectificationConfig, RectificationStatus, rectify_uncalibrated,
                             warp_rectified)
from .segmentation import SegmentationConfig, segment_stereo
from .pair_trees import put_pairs, take_pairs
from .size_groups import run_by_size
from .soft_geometry import geometry_straight_through
from .soft_pipeline import differentiable_depth
from .types import FundamentalResult, FundamentalStatus, Matches, SegmentationStatus, StereoBatch, StereoSegmentation

__all__ = ["PipelineConfig", "PipelineResult", "PipelineStatus", "estimate_obstacle_depth", "segment_pair"]

#: A fundamental matrix needs 7 correspondences (Sec. 3.3 (3)).
MIN_CORRESPONDENCES = 7


class PipelineStatus(enum.IntEnum):
    """Per-pair outcome of the whole pipeline; the first stage that failed names it."""

    OK = 0
    NO_OBJECTS = 1  # segmentation kept no region (blank, saturated or textureless image)
    TOO_FEW_KEYPOINTS = 2  # fewer than 7 keypoints in the left or right image
    TOO_FEW_MATCHES = 3  # fewer than 7 matches
    RANSAC_FAILED = 4  # every sample degenerate, or too few inliers
    DEGENERATE_RECTIFICATION = 5  # epipole in the image, singular F, or a wildly distorting homography
    NO_POSITIVE_DISPARITY = 6  # no inlier with d + doffs > 0: nothing to range
    NO_DENSE_DEPTH = 7  # dense rule: no kept object has enough valid dense disparities (flat, occluded)


@dataclass(frozen=True)
class PipelineConfig:
    """Settings of every stage; the defaults are the best measured configuration, ``paper()`` the paper's MATLAB
    defaults. Each nested config documents its own fields.

    Attributes:
        segmentation: by default the nearness segmenter (:mod:`svs_torch.nearness_segmentation`: the near side
            of the pair's measured disparity, corrected by a small network; the nearest region first, then the
            largest). ``paper()``: Sec. 3.2 (Otsu, 5×5 opening, the two largest regions); ``method="canny"`` for
            the paper's comparison row; ``segmenter="learned"`` for the network of issue 13.
        surf: Sec. 3.3 (1), MATLAB ``detectSURFFeatures`` defaults except ``metric_threshold`` 100 (1000 in
            ``paper()``): more keypoints on small frames, and the refinement's correlation gate removes the
            weak ones that do not hold.
        features_on: ``"masked"`` detects and describes on the masked obstacle images (the paper, ``paper()``);
            ``"mask"`` detects only inside the kept regions but on the unmasked images, so the
            artificial edge between an obstacle and the blacked-out background makes no keypoints, and a right
            view segmented a little differently (another exposure, a turned camera) keeps its matches;
            ``"image"`` (the default) uses the whole images (no segmentation gate).
        max_ratio: SAD ratio test, Sec. 3.3 (2): 0.8 (Lowe's); MATLAB ``matchFeatures`` MaxRatio 0.6 in ``paper()``.
        mutual: keep only mutual nearest neighbours (MATLAB ``Unique``).
        laplacian_gate: match only keypoints with the same Laplacian sign (Bay et al. Sec. 4.3).
        epipolar_band_px: optional |y_left − y_right| limit on candidates, pixels (a nearly rectified rig).
        refine_matches: :class:`~svs_torch.matching.MatchRefinementConfig`: sub-pixel Lucas–Kanade refinement of
            each matched right point on the images the features were found on, with a correlation gate; None:
            the keypoints as detected (the paper).
        ransac_threshold_px: Sampson-distance inlier threshold, pixels, Sec. 3.3 (3).
        ransac_confidence: stop when an all-inlier 7-point sample was drawn with this probability.
        ransac_max_iterations: 7-point samples per pair at most.
        ransac_scoring: ``"ransac"`` keeps the model with the most inliers (the paper's rule), ``"msac"`` the
            lowest truncated Sampson cost (more accurate on the same samples; the default), ``"lmeds"`` the least
            median (MATLAB's default method).
        rectify: ``"required"`` rectifies from F before measuring disparity and fails the pair when that is
            degenerate (the paper, Sec. 3.4); ``"auto"`` ranges the raw points when the inliers already lie on
            the same rows (median |y_left − y_right| ≤ ``row_tolerance_px``: a mechanically parallel rig like
            the SVS, where an F fitted to a few nearly planar obstacles would only add shear) or when F cannot
            rectify, and rectifies otherwise; ``"off"`` always measures x_left − x_right on the raw points.
        row_tolerance_px: see ``rectify="auto"``, pixels.
        row_alignment: :class:`~svs_torch.row_alignment.RowAlignmentConfig`: under ``rectify="auto"``, a right
            view whose matches fit a roll / vertical shift / scale of the right camera that moves some image
            corner's row by more than its ``min_correction_px`` is aligned by that similarity instead (before
            the projective rule): a loosely mounted second board (``experiments/real_rig.py``). None: off.
        rectification: :class:`~svs_torch.rectification.RectificationConfig`.
        depth: :class:`~svs_torch.depth.DepthConfig`: the range rule (``"dense"``, the default, or the paper's
            ``"paper"``: min/max over the inliers, or robust percentiles).
        dense: :class:`~svs_torch.dense.DenseConfig`, the dense SAD stage of the ``"dense"`` rule.
        verify_min_inliers, verify_min_inlier_share, verify_min_agreeing_inliers: under the dense rule, the
            sparse stage vouches that both views show one scene (``PipelineResult.verified``; the dense stage
            then accepts an object on ``depth.min_object_valid_fraction`` of its pixels instead of the stricter
            ``min_object_valid_fraction_unverified``) only when RANSAC found F with at least this many inliers,
            making at least this share of the matches, of which at least this many have the disparity the dense
            map measures at their pixel (within one working pixel,
            :func:`~svs_torch.dense_depth.count_agreeing_inliers`). 7-point RANSAC fits some F to a dozen chance
            matches between unrelated views, but the dense map confirms at most 5 of them, against 7 or more on
            197 of 199 real and synthetic pairs (``experiments/verify_views.py``: 1966 pairs of unrelated
            Middlebury / KITTI views and 64 synthetic ones; the two others, Flowerpots and Reindeer squeezed to
            320×240, keep every object: each has 40 % of its region measured). With ``features_on="mask"``:
            at most 2 on the unrelated views, 9 or more on 198 of 199 (the one left has no F), 7 objects of the
            unrelated views ranged, as before.
        seed: RANSAC seed; every pair uses it, so a pair's result does not depend on its batch.
        differentiable: after the hard pipeline (run without gradients: it makes every discrete decision), a
            differentiable pass recomputes each object's depth from the images and the segmenter's logits
            given those decisions (:mod:`svs_torch.soft_pipeline`): ``PipelineResult.depth`` then carries
            gradients to both images and to the network's weights, and ``hard_depth`` keeps the hard values.
            Needs the ``"dense"`` range rule.
        noisy_retry_sigma_px: under the dense rule, a pair the sparse stage did not verify (or with a kept object
            unranged) is measured again on both views smoothed by a Gaussian of this σ (working pixels), and that
            second measurement is kept where it is verified and ranges more objects (or as many, the first not
            verified): JPEG frames with sensor noise leave the x-Sobel SAD few unique windows and the SURF
            matches few inliers the map confirms, while a clean pair is verified and never retried. None: off.

    ``PipelineConfig.paper()`` is the paper's pipeline with MATLAB's defaults and Eq. (5)–(8) as the range rule
    (Table 1's "proposed" row).
    """

    # The nearness segmenter, the nearest region first then the largest, regions of 0.3 % of the image at least
    # (both cameras' measured pixels): the best rule keeping by nearness on the train scenes
    # (experiments/select_nearness_rule.md; the rule alone, experiments/validate_nearness.md; issue 32).
    # Below 17.5 % of the view accepted by the block matcher, Otsu instead: views of two scenes
    # (experiments/nearness_fallback.md).
    segmentation: SegmentationConfig = field(default_factory=lambda: SegmentationConfig(
        segmenter="nearness", keep="nearest_first", min_area_fraction=0.003, min_measured_share=0.175))
    # MetricThreshold 100 rather than MATLAB's 1000, ratio 0.8 rather than 0.6, matches refined: the best measured
    # (experiments/surf_vs_sift.py and fundamental_vs_opencv.py --config; see the README's "Precise geometry").
    surf: SurfConfig = field(default_factory=lambda: SurfConfig(metric_threshold=100.0))
    # real_rig.py, tuned 320x240: the right view turned / shifted / brighter segments differently, and the masked
    # images' artificial region borders then lose half the matches (roll 2 deg: 164 -> 72 on Aloe); "mask" keeps them.
    # With the nearness segmenter the right view's regions are the left ones moved by their disparity, and a turned
    # or shifted right camera puts its obstacles elsewhere: whole images kept or raised the accuracy of every
    # real_rig.py condition on the tuned scenes at 320x240 (roll 2 deg: 46 / 19 -> 81 / 84 %, shift 3 %: 26 / 39 ->
    # 83 / 83 %, clean and JPEG unchanged).
    features_on: Literal["masked", "mask", "image"] = "image"  # the paper (Sec. 3.3 (1)): "masked"
    max_ratio: float = 0.8  # Lowe's ratio; MATLAB matchFeatures MaxRatio is 0.6 (the paper preset)
    mutual: bool = False  # MATLAB matchFeatures Unique = false
    laplacian_gate: bool = True  # SURF's sign check, Bay et al. Sec. 4.3
    epipolar_band_px: float | None = None  # pixels; None: no band
    refine_matches: MatchRefinementConfig | None = field(default_factory=MatchRefinementConfig)
    ransac_threshold_px: float = 1.0  # pixels, Sampson distance
    ransac_confidence: float = 0.99  # MATLAB / OpenCV default
    ransac_max_iterations: int = 1024  # 7-point samples per pair
    ransac_scoring: Literal["ransac", "msac", "lmeds"] = "msac"  # Sec. 3.3 (3) keeps the most inliers
    rectify: Literal["auto", "required", "off"] = "auto"  # Sec. 3.4, uncalibrated rectification
    row_tolerance_px: float = 1.0
    # experiments/real_rig.py: roll 2 deg / shift 3 % of the right view at 320x240 lost 27-50 points per object.
    row_alignment: RowAlignmentConfig | None = field(default_factory=RowAlignmentConfig)
    rectification: RectificationConfig = field(default_factory=RectificationConfig)
    depth: DepthConfig = field(default_factory=DepthConfig)
    dense: DenseConfig = field(default_factory=DenseConfig)
    # experiments/verify_views.py: the dense map's confirmation separates real pairs (>= 7 agreeing inliers, 197 of
    # 199) from unrelated views (<= 5); 15 inliers left 7 real pairs unverified and verified 15 unrelated ones.
    verify_min_inliers: int = 0
    verify_min_inlier_share: float = 0.5
    verify_min_agreeing_inliers: int = 6
    seed: int = 0
    differentiable: bool = False  # issue 31: the hard pipeline's decisions, the depths recomputed with gradients
    # experiments/real_rig.py, tuned 320x240: JPEG digit 7 + sigma 6 68.8 -> 88.1 %, digit 8 + sigma 8 58.7 -> 78.4 %.
    noisy_retry_sigma_px: float | None = 1.0

    def __post_init__(self) -> None:
        if self.features_on not in ("masked", "mask", "image"):
            raise InputError(f"features_on: expected 'masked', 'mask' or 'image', got {self.features_on!r}")
        if self.rectify not in ("auto", "required", "off"):
            raise InputError(f"rectify: expected 'auto', 'required' or 'off', got {self.rectify!r}")
        if not 0 < self.max_ratio <= 1:
            raise InputError(f"max_ratio: expected a ratio in (0, 1], got {self.max_ratio!r}")
        for name in ("verify_min_inliers", "verify_min_agreeing_inliers"):
            if not (isinstance(getattr(self, name), int) and getattr(self, name) >= 0):
                raise InputError(f"{name}: expected an integer >= 0, got {getattr(self, name)!r}")
        if not (isinstance(self.seed, int) and -2**63 <= self.seed < 2**63):
            raise InputError(f"seed: expected a 64-bit integer, got {self.seed!r}")  # the RANSAC seeds are int64
        if self.differentiable not in (True, False):
            raise InputError(f"differentiable: expected a bool, got {self.differentiable!r}")
        if self.differentiable and self.depth.rule != "dense":
            raise InputError(f"differentiable: needs depth.rule 'dense' (the paper's rule ranges from extreme "
                             f"inliers, nothing to differentiate), got {self.depth.rule!r}")
        if self.noisy_retry_sigma_px is not None and not self.noisy_retry_sigma_px > 0:
            raise InputError(f"noisy_retry_sigma_px: expected a σ > 0 or None, got {self.noisy_retry_sigma_px!r}")
        if not 0 <= self.verify_min_inlier_share <= 1:
            raise InputError(f"verify_min_inlier_share: expected a share in [0, 1], got "
                             f"{self.verify_min_inlier_share!r}")

    @classmethod
    def paper(cls) -> PipelineConfig:
        """The paper's pipeline exactly as published (Sec. 3.2–3.4): MATLAB's SURF, matching and RANSAC
        defaults, and R_min / R_max as the extremes over the RANSAC inliers (Eq. (5)–(8))."""
        return cls(segmentation=SegmentationConfig(), surf=SurfConfig(), features_on="masked", max_ratio=0.6,
                   refine_matches=None, row_alignment=None, depth=DepthConfig(rule="paper"), noisy_retry_sigma_px=None)


@dataclass(frozen=True)
class PipelineResult:
    """Per-pair results of :func:`estimate_obstacle_depth` (B pairs).

    Attributes:
        status: :class:`PipelineStatus` ``(B,)`` int64.
        segmentation: the :class:`~svs_torch.types.StereoSegmentation`.
        features_left, features_right: :class:`~svs_torch.features.SurfFeatures` of each side.
        matches: left-to-right :class:`~svs_torch.types.Matches`.
        points: :class:`~svs_torch.matching.MatchedPoints` ``(B, K, 2)``: the matched points F is fitted to (the
            right points refined to sub-pixel under ``refine_matches``), rows as in ``matches``.
        fundamental: :class:`~svs_torch.types.FundamentalResult` over the matched rows (row k = left keypoint k).
        rectification: :class:`~svs_torch.rectification.Rectification` computed from F (its homographies are
            the identity where its status is not OK).
        rectified: ``(B,)`` bool, pairs whose disparities were measured after rectification.
        depth: :class:`~svs_torch.depth.DepthResult`: the pair's R_min / R_max, per-object depths of the kept
            left regions and the nearest obstacle, by ``config.depth.rule`` (``range_rule``).
        dense: :class:`~svs_torch.dense.DenseDisparity` of the left view (in rectified pixels where
            ``rectified``), None under the ``"paper"`` rule.
        range_rule: ``"dense"`` or ``"paper"``: the rule that produced ``depth``.
        num_keypoints: ``(B, 2)`` int64, valid keypoints left and right.
        num_matches, num_inliers: ``(B,)`` int64.
        timings_s: wall time of each stage for the whole batch, seconds.
        verified: ``(B,)`` bool, under the dense rule: the sparse stage vouches that both views show one scene
            (``PipelineConfig.verify_min_inliers`` …); None under the ``"paper"`` rule.
        num_agreeing_inliers: ``(B,)`` int64, the RANSAC inliers whose disparity the dense map confirms
            (:func:`~svs_torch.dense_depth.count_agreeing_inliers`); None under the ``"paper"`` rule.
        hard_depth: under ``PipelineConfig.differentiable``, the hard pipeline's :class:`DepthResult` (``depth``
            is then the differentiable one); None otherwise.
        H_left, H_right: ``(B, 3, 3)``, the homographies the disparities were measured after: F's rectification
            or the right view's row alignment where ``rectified``, the identity elsewhere. Under
            ``differentiable``, F's rectifications carry gradients to both images (``svs_torch.soft_geometry``).
        smoothed: ``(B,)`` bool, under the dense rule: pairs whose dense depth comes from the second pass on
            smoothed views (``PipelineConfig.noisy_retry_sigma_px``); None under the ``"paper"`` rule.
        row_aligned: ``(B,)`` bool, pairs rectified by the right view's row alignment rather than F's
            rectification; row_alignment_inliers ``(B, K)`` bool, the matches the row alignment's similarity fits
            (where ``row_aligned``; all False without a row alignment).
    """

    status: torch.Tensor
    segmentation: StereoSegmentation
    features_left: SurfFeatures
    features_right: SurfFeatures
    matches: Matches
    points: MatchedPoints
    fundamental: FundamentalResult
    rectification: Rectification
    rectified: torch.Tensor
    depth: DepthResult
    dense: DenseDisparity | None
    range_rule: str
    num_keypoints: torch.Tensor
    num_matches: torch.Tensor
    num_inliers: torch.Tensor
    timings_s: dict[str, float]
    verified: torch.Tensor | None = None
    num_agreeing_inliers: torch.Tensor | None = None
    hard_depth: DepthResult | None = None
    H_left: torch.Tensor | None = None
    H_right: torch.Tensor | None = None
    smoothed: torch.Tensor | None = None
    row_aligned: torch.Tensor | None = None
    row_alignment_inliers: torch.Tensor | None = None


def _feature_images(batch: StereoBatch, seg: StereoSegmentation, config: PipelineConfig
                    ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The ``(2B, 1, H, W)`` images SURF runs on (left then right) and its detection mask (or None)."""
    if config.features_on == "masked":
        return torch.cat([seg.left.masked, seg.right.masked]), None
    images = torch.cat([batch.left, batch.right])
    if config.features_on == "image":
        return images, None
    return images, torch.cat([seg.left.kept_mask, seg.right.kept_mask])


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
    checks.append(((seg.left.kept_labels[:, 0] < 0) | (seg.right.kept_labels[:, 0] < 0)
                   | (seg.status != SegmentationStatus.OK), PipelineStatus.NO_OBJECTS))
    for failed, code in checks:
        status = torch.where(failed, torch.full_like(status, code), status)
    return status


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
                             image_hw: torch.Tensor, seeds: torch.Tensor, config: PipelineConfig
                             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(B,)`` bool rectified, the ``(B, 3, 3)`` left and right homographies the disparities are measured after
    (identity where not rectified): a row alignment of the right view where ``config.row_alignment`` finds one
    that matters (``rectify="auto"`` only), else F's rectification by :func:`_use_rectification`; and which pairs
    the row alignment rectified ``(B,)`` and its inliers ``(B, K)`` (the differentiable pass refits it on them)."""
    rectified = _use_rectification(points.left, points.right, fundamental.inliers, rectification, config)
    identity = torch.eye(3, dtype=rectification.H_left.dtype, device=rectification.H_left.device
                         ).expand_as(rectification.H_left)
    pick = rectified.view(-1, 1, 1)
    H_left = torch.where(pick, rectification.H_left, identity)
    H_right = torch.where(pick, rectification.H_right, identity)
    if config.rectify != "auto" or config.row_alignment is None:
        return rectified, H_left, H_right, torch.zeros_like(rectified), torch.zeros_like(points.valid)
    # The similarity is fitted to every match, not F's inliers: F of a few planar obstacles may be loose.
    alignment = fit_row_alignment(points.left, points.right, points.valid, image_hw, config.row_alignment, seeds)
    aligned = alignment.valid & (alignment.correction_px > config.row_alignment.min_correction_px)
    pick = aligned.view(-1, 1, 1)
    return (rectified | aligned, torch.where(pick, identity, H_left),
            torch.where(pick, alignment.H_right.to(H_right.dtype), H_right), aligned, alignment.inliers)


def _dense_depth(batch: StereoBatch, seg: StereoSegmentation, sparse: DepthResult, fundamental_ok: torch.Tensor,
                 points_left: torch.Tensor, inliers: torch.Tensor, rectified: torch.Tensor, H_left: torch.Tensor,
                 H_right: torch.Tensor, config: PipelineConfig
                 ) -> tuple[DepthResult, DenseDisparity, torch.Tensor, torch.Tensor]:
    """The ``"dense"`` rule: SAD disparity over the kept regions (in rectified pixels where the pair was
    rectified: images and labels warped by the same homographies) over each pair's range (a coarse pass, or
    the sparse inliers' disparities), then each object's depth statistics over its region. Also returns
    whether the pair's geometry was verified (``fundamental_ok`` and enough inliers the dense map confirms)
    and that count of agreeing inliers, ``(B,)`` each."""
    left, right, labels = batch.left, batch.right, seg.left.labels
    if bool(rectified.any()):
        pick = rectified.view(-1, 1, 1, 1)
        left = torch.where(pick, warp_rectified(left, H_left), left)
        right = torch.where(pick, warp_rectified(right, H_right), right)
        # Labels by nearest neighbour (never blended), as exact small integers in float64.
        warped = warp_rectified(labels.to(torch.float64), H_left.to(torch.float64), mode="nearest").round().long()
        labels = torch.where(pick, warped, labels)
    # One mask per kept object, so the search range covers a small object as well as a big one.
    objects = labels == slot_labels(seg.left.kept_labels).view(batch.batch_size, -1, 1, 1)
    mask = any_along(objects, dim=1, keepdim=True)
    dense = estimate_dense_disparity(left, right, mask, config.dense, batch.image_hw,
                                     sparse.disparities.disparity_px, sparse.disparities.valid, objects)
    # Agreement within one working pixel (the dense map's own grid) between the sparse and the dense disparity.
    agreeing = count_agreeing_inliers(dense, points_left, sparse.disparities, inliers, H_left,
                                      float(working_factor(batch.left.shape[-1], config.dense)))
    verified = fundamental_ok & (agreeing >= config.verify_min_agreeing_inliers)
    weight = verified.to(batch.left.dtype)
    fraction = (weight * config.depth.min_object_valid_fraction
                + (1 - weight) * config.depth.min_object_valid_fraction_unverified)
    objects = dense_object_depths(dense, labels, sparse.objects, batch.focal_px, batch.baseline_m, batch.doffs_px,
                                  config.depth.object_percentiles, config.depth.min_object_pixels,
                                  config.dense.fill_invalid, fraction, config.depth.min_object_pixels_in_view)
    depth_range = range_from_objects(objects, batch.focal_px, batch.baseline_m, batch.doffs_px)
    depth = DepthResult(sparse.disparities, sparse.points, depth_range, objects, nearest_obstacle(objects))
    return depth, dense, verified, agreeing


def _smoothed(batch: StereoBatch, sigma_working_px: float, config: DenseConfig) -> StereoBatch:
    """Both views smoothed by a Gaussian of ``sigma_working_px`` working pixels of the dense stage."""
    from kornia.filters import gaussian_blur2d  # imported here: kornia's import is slow and clean pairs never retry

    sigma = sigma_working_px * working_factor(batch.left.shape[-1], config)
    size = 2 * math.ceil(3 * sigma) + 1
    # Clamped: the kernel's weights sum to 1 only up to rounding, and a white pixel may come out at 1 + 2e-16,
    # which StereoBatch refuses (hypothesis found it on a 1×1 white pair).
    blur = (lambda image: gaussian_blur2d(image, (size, size), (sigma, sigma), border_type="replicate").clamp(0, 1))
    return dataclasses.replace(batch, left=blur(batch.left), right=blur(batch.right))


def _dense_depth_with_retry(batch: StereoBatch, seg: StereoSegmentation, sparse: DepthResult,
                            fundamental_ok: torch.Tensor, points_left: torch.Tensor, inliers: torch.Tensor,
                            rectified: torch.Tensor, H_left: torch.Tensor, H_right: torch.Tensor,
                            config: PipelineConfig
                            ) -> tuple[DepthResult, DenseDisparity, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`_dense_depth`, then on smoothed views for the pairs it left unverified or with a kept object
    unranged (``config.noisy_retry_sigma_px``); per pair the second result where it is verified and ranges more
    objects, or as many where the first was not verified. Also returns ``(B,)`` bool: the pairs whose result is
    the smoothed pass's."""
    first = _dense_depth(batch, seg, sparse, fundamental_ok, points_left, inliers, rectified, H_left, H_right, config)
    from_smoothed = torch.zeros_like(rectified)
    kept = seg.left.kept_labels >= 0
    retry = ~first[2] | (kept & ~first[0].objects.valid[:, :kept.shape[1]]).any(1)
    if config.noisy_retry_sigma_px is None or not bool(retry.any()):
        return (*first, from_smoothed)
    # Only the retried pairs run again (a clean batch's verified pairs never pay for it).
    index, b = retry.nonzero().flatten(), batch.batch_size
    sub = (lambda tree: take_pairs(tree, index, b))
    smoothed = _smoothed(sub(batch), config.noisy_retry_sigma_px, config.dense)
    second = _dense_depth(smoothed, sub(seg), sub(sparse), sub(fundamental_ok), sub(points_left), sub(inliers),
                          sub(rectified), sub(H_left), sub(H_right), config)
    ranged_first, ranged_second = sub(first[0].objects.valid).sum(1), second[0].objects.valid.sum(1)
    # Only a verified second pass counts: views of different scenes are never verified, and smoothing must not
    # let their chance agreement reach the unverified share (experiments/verify_views.py).
    verified_first = sub(first[2])
    pick = second[2] & ((ranged_second > ranged_first) | (~verified_first & (ranged_second >= ranged_first)))
    if not bool(pick.any()):
        return (*first, from_smoothed)
    from_smoothed[index[pick]] = True
    depth, dense, verified, agreeing = put_pairs(first, index[pick], take_pairs(second, pick.nonzero().flatten(),
                                                                                 len(index)), b)
    # The batch's deepest search (an int, not per pair).
    dense = dataclasses.replace(dense, num_disparities=max(first[1].num_disparities, second[1].num_disparities))
    return depth, dense, verified, agreeing, from_smoothed


def segment_pair(batch: StereoBatch, config: SegmentationConfig, network: nn.Module | None = None,
                 left_logits: torch.Tensor | None = None) -> StereoSegmentation:
    """Both views of every pair segmented by ``config.segmenter``: Otsu (the paper, Sec. 3.2; or Canny by
    ``config.method``) or the learned segmenter (:mod:`svs_torch.learned_segmentation`; ``network``, or the
    weights ``config.segmenter`` names; ``left_logits``: the left views' logits, already computed); the same
    structure. Not differentiable. Each pair is segmented on its own ``image_hw`` pixels (pairs of different sizes
    as groups of one size, :mod:`svs_torch.size_groups`): padding never enters a threshold's histogram or a region;
    ``left_logits`` are for a batch whose pairs fill its tensors."""
    if left_logits is None:
        return run_by_size(batch, lambda group: _segment_group(group, config, network))
    if not bool((batch.image_hw == torch.tensor(batch.size_hw, device=batch.image_hw.device)).all()):
        raise InputError("left_logits: expected a batch whose pairs all fill its tensors (one size); pass none to "
                         "segment a padded batch pair by pair size")
    return _segment_group(batch, config, network, left_logits)


def _segment_group(batch: StereoBatch, config: SegmentationConfig, network: nn.Module | None = None,
                   left_logits: torch.Tensor | None = None) -> StereoSegmentation:
    if config.segmenter == "otsu":
        return segment_stereo(batch, config)
    return segment_stereo_learned(batch, config, _network(batch, config, network), left_logits)


def _network(batch: StereoBatch, config: SegmentationConfig, network: nn.Module | None) -> nn.Module:
    """The learned segmenter's network on the batch's device: ``network`` (which must be there already: moving
    a caller's module would move the parameters its optimiser holds) or the cached weights of
    ``config.segmenter``, moved and frozen."""
    if network is None:
        # Frozen: a differentiable run takes gradients to the images through it, never into the shared cache.
        return _cached_obstacle_net(config.segmenter).to(batch.left.device).requires_grad_(False)
    device = next(network.parameters()).device
    if device != batch.left.device:
        raise InputError(f"network: expected its parameters on the batch's device {batch.left.device}, got {device}")
    return network


def estimate_obstacle_depth(batch: StereoBatch, config: PipelineConfig = PipelineConfig(),
                            network: nn.Module | None = None) -> PipelineResult:
    """Range the obstacles of every pair of a stereo batch.

    Args:
        batch: :class:`~svs_torch.types.StereoBatch` (calibration: ``focal_px``, ``baseline_m``, ``doffs_px``).
        config: :class:`PipelineConfig`.
        network: the learned segmenter's network (an :class:`~svs_torch.learned_segmentation.ObstacleNet`, e.g.
            from :func:`~svs_torch.learned_segmentation.load_obstacle_net`) on the batch's device, used when
            ``config.segmentation.segmenter`` is learned; None: the weights that setting names.

    Returns:
        :class:`PipelineResult`. With ``config.differentiable`` (False by default) the hard pipeline runs
        detached: images or calibration that require gradients are detached, and nothing in the result carries
        a graph. With ``differentiable=True`` the hard pipeline still makes every discrete decision, and
        ``result.depth`` (each object's ``depth_median_m`` / ``depth_low_m`` / ``depth_high_m``, the nearest
        obstacle's ``depth_m`` and ``surface_m``, the range) is recomputed differentiably w.r.t. both images,
        the calibration and the parameters of ``network`` (:mod:`svs_torch.soft_pipeline`); ``.valid`` masks
        are the hard ones, and ``result.hard_depth`` holds the hard values.

    Each pair is ranged on its own ``image_hw`` pixels only: pairs of different sizes padded into one batch run as
    groups of one size, each cropped to its size (:mod:`svs_torch.size_groups`), so a pair's result is the same
    whatever else shares its batch; the result's maps are padded back to the batch's size.
    """
    check_instance(batch, "batch", StereoBatch)
    check_instance(config, "config", PipelineConfig)
    if network is not None:
        check_instance(network, "network", nn.Module)
        if config.segmentation.segmenter == "otsu":
            raise InputError("network: given, but config.segmentation.segmenter is 'otsu' (use a learned one)")
        from .nearness_segmentation import NearnessNet
        if config.segmentation.segmenter.startswith("nearness") != isinstance(network, NearnessNet):
            expected = "a NearnessNet" if config.segmentation.segmenter.startswith("nearness") else "an ObstacleNet"
            raise InputError(f"network: expected {expected} for segmenter {config.segmentation.segmenter!r}, got "
                             f"{type(network).__name__}")
    if not config.differentiable:
        batch = _detached(batch)
    return run_by_size(batch, lambda group: _estimate_group(group, config, network))


def _detached(batch: StereoBatch) -> StereoBatch:
    """The batch with every tensor detached (the hard path takes no gradients; a tensor that requires them would
    make the in-place stages raise)."""
    if not any(isinstance(v, torch.Tensor) and v.requires_grad for v in vars(batch).values()):
        return batch
    return dataclasses.replace(batch, **{k: v.detach() for k, v in vars(batch).items()
                                         if isinstance(v, torch.Tensor)})


def _estimate_group(batch: StereoBatch, config: PipelineConfig, network: nn.Module | None) -> PipelineResult:
    """:func:`estimate_obstacle_depth` on a batch whose pairs all fill its tensors: the hard pipeline without
    gradients, then, under ``config.differentiable``, the differentiable depths."""
    logits = None
    if config.differentiable and config.segmentation.segmenter != "otsu":
        # The left views' logits once, with gradients: the hard segmentation thresholds them (detached).
        logits = predict_obstacle_logits(_network(batch, config.segmentation, network), batch.left, batch.right)
    with torch.no_grad():
        result = _estimate_hard(_detached(batch), config, network, logits)
    if not config.differentiable:
        return result
    left, right = batch.left, batch.right
    if config.noisy_retry_sigma_px is not None and bool(result.smoothed.any()):
        # The pairs the hard stage measured on smoothed views are differentiated through the same (linear) blur.
        blurred = _smoothed(batch, config.noisy_retry_sigma_px, config.dense)
        pick = result.smoothed.view(-1, 1, 1, 1)
        left, right = torch.where(pick, blurred.left, left), torch.where(pick, blurred.right, right)
    H_left, H_right = _differentiable_homographies(batch, result, config)
    depth = differentiable_depth(
        left, right, result.segmentation.left.labels, logits, result.rectified, H_left, H_right,
        result.dense, result.depth, batch.focal_px, batch.baseline_m, batch.doffs_px, batch.image_hw,
        config.depth.object_percentiles, config.dense)
    return dataclasses.replace(result, depth=depth, hard_depth=result.depth, H_left=H_left, H_right=H_right)


def _differentiable_homographies(batch: StereoBatch, result: PipelineResult, config: PipelineConfig
                                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """The hard pass's homographies, with gradients to the images through the refined matches and F's refit and
    Hartley's rectification, or the row alignment's refit, where the pair was rectified by them
    (:mod:`svs_torch.soft_geometry`); the identity of unrectified pairs is a constant."""
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
                                     from_rows, result.H_left, result.H_right, batch.image_hw, config.rectification)


def _estimate_hard(batch: StereoBatch, config: PipelineConfig, network: nn.Module | None,
                   left_logits: torch.Tensor | None = None) -> PipelineResult:
    """The hard pipeline (no gradients) on a batch whose pairs all fill its tensors."""
    timings: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(stage: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        timings[stage] = now - clock
        clock = now

    seg = _segment_group(batch, config.segmentation, network, left_logits)
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
    rectified, H_left, H_right, row_aligned, row_inliers = _rectifying_homographies(
        points, fundamental, rectification, batch.image_hw, seeds, config)
    lap("rectification")
    depth = estimate_depth(
        points.left, points.right, fundamental.inliers, batch.focal_px, batch.baseline_m, batch.doffs_px,
        H_left=H_left, H_right=H_right,
        labels=seg.left.labels, region_labels=seg.left.kept_labels, image_hw=batch.image_hw, config=config.depth)
    dense = verified = agreeing = smoothed = None
    if config.depth.rule == "dense":
        fundamental_ok = ((fundamental.status == FundamentalStatus.OK)
                          & (fundamental.num_inliers >= config.verify_min_inliers)
                          & (fundamental.num_inliers >= config.verify_min_inlier_share * matches.valid.sum(1)))
        depth, dense, verified, agreeing, smoothed = _dense_depth_with_retry(
            batch, seg, depth, fundamental_ok, points.left, fundamental.inliers, rectified, H_left, H_right, config)
    lap("depth")
    num_keypoints = torch.stack([left.keypoints.valid.sum(1), right.keypoints.valid.sum(1)], dim=1)
    return PipelineResult(
        status=_status(seg, num_keypoints, fundamental, rectification, depth, config.rectify, dense is not None),
        segmentation=seg, features_left=left, features_right=right, matches=matches, points=points,
        fundamental=fundamental,
        rectification=rectification, rectified=rectified, depth=depth, dense=dense, range_rule=config.depth.rule,
        num_keypoints=num_keypoints,
        num_matches=matches.valid.sum(1), num_inliers=fundamental.num_inliers, timings_s=timings,
        verified=verified, num_agreeing_inliers=agreeing, H_left=H_left, H_right=H_right, smoothed=smoothed,
        row_aligned=row_aligned, row_alignment_inliers=row_inliers)
