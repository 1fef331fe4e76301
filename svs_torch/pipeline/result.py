"""The pipeline's per-pair result (:class:`PipelineResult`) and status (:class:`PipelineStatus`), apart from its
options (:mod:`.config`, which re-exports both)."""

from __future__ import annotations

import enum
from dataclasses import dataclass

import torch

from ..core.types import FundamentalResult, Matches, StereoSegmentation
from ..depth.dense_config import DenseDisparity
from ..depth.depth_types import DepthResult
from ..depth.floor_distance import FloorDistances
from ..features.surf import SurfFeatures
from ..geometry.matched_points import MatchedPoints
from ..geometry.rectification import Rectification

__all__ = ["PipelineResult", "PipelineStatus"]


class PipelineStatus(enum.IntEnum):
    """Per-pair outcome of the whole pipeline; the first stage that failed names it. ``result.status`` holds the
    values as int64 ``(B,)``: ``PipelineStatus(int(result.status[i])).name`` names pair i's.

    Values:
        OK (0): ranged.
        NO_OBJECTS (1): segmentation kept no region (blank, saturated or textureless image).
        TOO_FEW_KEYPOINTS (2): fewer than 7 keypoints in the left or right image.
        TOO_FEW_MATCHES (3): fewer than 7 matches.
        RANSAC_FAILED (4): every sample degenerate, or too few inliers.
        DEGENERATE_RECTIFICATION (5): epipole in the image, singular F, or a wildly distorting homography.
        NO_POSITIVE_DISPARITY (6): no inlier (``DepthConfig.min_in_front_share``: or too few) with d + doffs > 0.
        NO_DENSE_DEPTH (7): dense rule: no kept object has enough valid dense disparities (flat, occluded).
    """

    OK = 0
    NO_OBJECTS = 1
    TOO_FEW_KEYPOINTS = 2
    TOO_FEW_MATCHES = 3
    RANSAC_FAILED = 4
    DEGENERATE_RECTIFICATION = 5
    NO_POSITIVE_DISPARITY = 6
    NO_DENSE_DEPTH = 7


@dataclass(frozen=True)
class PipelineResult:
    """Per-pair results of :func:`estimate_obstacle_depth` (B pairs).

    Attributes:
        status: :class:`PipelineStatus` ``(B,)`` int64; a pair not OK is unranged (its ``depth`` not ``valid``).
        segmentation: the :class:`~svs_torch.core.types.StereoSegmentation`; a stereo segmenter's (nearness,
            learned) of the ``row_aligned`` pairs is made on their aligned views, its maps in input pixels.
        features_left, features_right: :class:`~svs_torch.features.SurfFeatures` of each side.
        matches: left-to-right :class:`~svs_torch.core.types.Matches`.
        points: :class:`~svs_torch.geometry.matched_points.MatchedPoints` ``(B, K, 2)``: the matched points F is
            fitted to (the right points refined to sub-pixel under ``refine_matches``), rows as in ``matches``.
        fundamental: :class:`~svs_torch.core.types.FundamentalResult` over the matched rows (row k = left keypoint k).
        rectification: :class:`~svs_torch.geometry.rectification.Rectification` computed from F (its homographies are
            the identity where its status is not OK).
        rectified: ``(B,)`` bool, pairs whose disparities were measured after rectification.
        depth: :class:`~svs_torch.depth.DepthResult`: the pair's R_min / R_max, per-object depths of the kept
            left regions and the nearest obstacle, by ``config.depth.rule`` (``range_rule``).
        dense: :class:`~svs_torch.depth.dense.DenseDisparity` of the left view (in rectified pixels where
            ``rectified``), None under the ``"paper"`` rule.
        range_rule: ``"dense"`` or ``"paper"``: the rule that produced ``depth``.
        num_keypoints: ``(B, 2)`` int64, valid keypoints left and right.
        num_matches, num_inliers: ``(B,)`` int64.
        timings_s: wall time of each stage for the whole batch, seconds.
        verified: ``(B,)`` bool, under the dense rule: the sparse stage vouches that both views show one scene
            (``PipelineConfig.verify_min_inliers`` …); None under the ``"paper"`` rule.
        num_agreeing_inliers: ``(B,)`` int64, the RANSAC inliers whose disparity the dense map confirms
            (:func:`~svs_torch.depth.dense_objects.count_agreeing_inliers`); None under the ``"paper"`` rule.
        num_measured_inliers: ``(B,)`` int64, the RANSAC inliers at a pixel the dense map measured (agreeing or
            not); None under the ``"paper"`` rule.
        hard_depth: under ``PipelineConfig.differentiable``, the hard pipeline's :class:`DepthResult` (``depth``
            is then the differentiable one); None otherwise.
        H_left, H_right: ``(B, 3, 3)``, the homographies the disparities were measured after: F's rectification
            or the right view's row alignment where ``rectified``, the identity elsewhere. Under
            ``differentiable``, F's rectifications carry gradients to both images (``svs_torch.geometry.soft``).
        smoothed: ``(B,)`` bool, under the dense rule: pairs whose dense depth comes from the second pass on
            smoothed views (``PipelineConfig.noisy_retry_sigma_px``); None under the ``"paper"`` rule.
        coarse: ``(B,)`` bool, under the dense rule: pairs whose dense depth was measured at half the working width
            (``PipelineConfig.coarse_retry_below_share``); None under the ``"paper"`` rule.
        row_aligned: ``(B,)`` bool, pairs rectified by the right view's row alignment rather than F's
            rectification; row_alignment_inliers ``(B, K)`` bool, the matches the row alignment's similarity fits
            (where ``row_aligned``; all False without a row alignment); row_alignment_turn_deg ``(B, 2)``, the right
            camera's turn about its y and x axes the alignment undid, degrees (its keystone,
            :class:`~svs_torch.geometry.row_alignment.RowAlignment`'s ``keystone_deg``; 0 where none). A
            ``row_aligned`` pair's roll, vertical shift and scale undone: ``right_camera_deviation(result.H_right,
            batch.image_hw)`` (:func:`~svs_torch.geometry.row_alignment_keystone.right_camera_deviation`), as
            ``estimate`` prints them.
        dropped_labels: ``(B, N)`` int64, under the dense rule: the left label each kept slot dropped as
            unmeasured held (``PipelineConfig.drop_unmeasured_below_share``; its ``kept_labels`` entry is now −1),
            −1 elsewhere, so that an evaluation scores a dropped region as an object left without a distance
            (:func:`~svs_torch.evaluation.measured_regions`); None under the ``"paper"`` rule.
            ``dropped_objects`` (a property) is the same as ``(B, N)`` bool.
        exposure_matched: ``(B,)`` bool, pairs whose two views' exposures were matched, the darker view mapped
            onto the brighter (``exposure``, ``exposure_right_clipped``, or the ``exposure_retry`` kept); the masked
            images are of the mapped views.
        features_smoothed: ``(B,)`` bool, pairs whose SURF features were found on views smoothed by a Gaussian
            (``PipelineConfig.feature_smoothing_sigma_px``: the ``noisy_features_retry_sigma_px`` retry kept).
        object_labels: ``(B, 1, H, W)`` int64, the left labels each object of ``depth`` was measured over, input
            pixels: the kept regions' interiors (``PipelineConfig.region_interior_working_px``), else the
            segmentation's labels, an object ranged over its near surface cut to it (``near_surface``). An object's
            true distance is the median ground truth over the same pixels
            (:func:`svs_torch.evaluation.measured_regions`); ``segmentation`` keeps the whole regions.
        near_surface: ``(B, N)`` bool, under the dense rule with ``PipelineConfig.measure_near_surface``: the objects
            whose region spanned two surfaces, ranged over the nearer; None otherwise.
        floor: :class:`~svs_torch.depth.floor_distance.FloorDistances`, under the dense rule: where the segmenter
            found the floor (``SegmentationConfig.ground``, ``guide``'s default), the camera's height and pitch over
            it and each object's distance ahead along it (what ``guide`` says); none found where it did not look;
            None under the ``"paper"`` rule.
        focal_px, baseline_m, doffs_px: ``(B,)``, the calibration the depths were computed with (the batch's), so
            that a disparity of the result can be read as a distance (``dense.repeated``'s aliases,
            :func:`~svs_torch.depth.alias_choice.alias_depths_m`).
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
    num_measured_inliers: torch.Tensor | None = None
    hard_depth: DepthResult | None = None
    H_left: torch.Tensor | None = None
    H_right: torch.Tensor | None = None
    smoothed: torch.Tensor | None = None
    row_aligned: torch.Tensor | None = None
    exposure_matched: torch.Tensor | None = None
    row_alignment_inliers: torch.Tensor | None = None
    row_alignment_turn_deg: torch.Tensor | None = None
    coarse: torch.Tensor | None = None
    dropped_labels: torch.Tensor | None = None
    object_labels: torch.Tensor | None = None
    near_surface: torch.Tensor | None = None
    features_smoothed: torch.Tensor | None = None
    floor: FloorDistances | None = None
    focal_px: torch.Tensor | None = None
    baseline_m: torch.Tensor | None = None
    doffs_px: torch.Tensor | None = None

    @property
    def dropped_objects(self) -> torch.Tensor | None:
        """``(B, N)`` bool: the kept left slots dropped as unmeasured (:attr:`dropped_labels` ≥ 0); None under the
        ``"paper"`` rule."""
        return None if self.dropped_labels is None else self.dropped_labels >= 0

    @property
    def unranged_repeated(self) -> torch.Tensor | None:
        """``(B, N)`` bool: the kept objects that repeat themselves along the rows (a fence, a grate) and were left
        without a distance, mostly as their alias was not told (``dense.repeated``; the distances their aliases
        would give: :func:`~svs_torch.depth.alias_choice.alias_depths_m`); None where the check did not run."""
        if self.dense is None or self.dense.repeated is None:
            return None
        return (self.segmentation.left.kept_labels >= 0) & self.dense.repeated.unranged(self.depth.objects.valid)

    @property
    def nearest_unranged_alias_m(self) -> torch.Tensor | None:
        """``(B,)``: how near each pair's :attr:`unranged_repeated` objects may be, by the nearest of their aliases'
        distances (0: one no alias bounds; NaN: the pair has none;
        :func:`~svs_torch.depth.alias_choice.nearest_alias_depth_m`); None where the check did not run. ``guide``
        says such a pattern aloud when it may lie within the warning band."""
        unranged = self.unranged_repeated
        if unranged is None:
            return None
        from ..depth.alias_choice import nearest_alias_depth_m

        return nearest_alias_depth_m(self.dense, unranged, self.focal_px, self.baseline_m, self.doffs_px)
