"""The pipeline's options (:class:`PipelineConfig`: one config per stage and the choices between them); its result
and per-pair status (:class:`PipelineStatus`: the stage that stopped) are in :mod:`.result`, re-exported.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Literal

from ..core.checks import InputError, check_count, check_flag, check_real, real_or_nan
from ..depth.dense_config import DenseConfig
from ..depth.depth_types import DepthConfig
from ..features.detector import SurfConfig
from ..features.limits import PIPELINE_METRIC_THRESHOLD
from ..geometry.kernels import MAX_HYPOTHESES
from ..geometry.lk_refinement import MatchRefinementConfig
from ..geometry.match_ratios import LOWE_MAX_RATIO, MATLAB_MAX_RATIO
from ..geometry.rectification import RectificationConfig
from ..geometry.row_alignment import RowAlignmentConfig
from ..segmentation.segment import SegmentationConfig
from .exposure import RETRY_MIN_CHANGE, ExposureConfig
from .result import PipelineResult, PipelineStatus  # noqa: F401  (re-exported: their home until it passed 400 lines)

__all__ = ["MIN_CORRESPONDENCES", "PipelineConfig", "PipelineResult", "PipelineStatus"]


#: A fundamental matrix needs 7 correspondences (Sec. 3.3 (3)).
MIN_CORRESPONDENCES = 7
#: The largest smoothing σ (pixels): its Gaussian is 6σ + 1 wide; σ 1e9 ran for hours, 1e4 took 8 s at 160×120.
MAX_SIGMA_PX = 1000


@dataclass(frozen=True)
class PipelineConfig:
    """Settings of every stage; the defaults are the best measured configuration, ``paper()`` the paper's MATLAB
    defaults. Each nested config documents its own fields.

    Attributes:
        segmentation: by default the nearness segmenter (:mod:`svs_torch.segmentation.nearness`: the near side
            of the pair's measured disparity; its shipped correction network adds nothing and is skipped; the
            nearest region first, then the largest). ``paper()``: Sec. 3.2 (Otsu, 5×5 opening, the two largest
            regions); ``method="canny"`` for the paper's comparison row; ``segmenter="learned"`` for the network
            of issue 13.
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
        laplacian_gate: match only keypoints with the same Laplacian sign (Bay et al. Sec. 4.3; not MATLAB's).
        epipolar_band_px: optional |y_left − y_right| limit on candidates, pixels (a nearly rectified rig).
        refine_matches: :class:`~svs_torch.geometry.lk_refinement.MatchRefinementConfig`: sub-pixel Lucas–Kanade
            refinement of each matched right point on the images the features were found on, with a correlation
            gate; None: the keypoints as detected (the paper).
        ransac_threshold_px: Sampson-distance inlier threshold, pixels, Sec. 3.3 (3); MATLAB's 0.1 in ``paper()``.
        ransac_confidence: stop when an all-inlier 7-point sample was drawn with this probability.
        ransac_max_iterations: 7-point samples per pair at most; 500 in ``paper()`` (MATLAB's NumTrials).
        ransac_scoring: ``"ransac"`` keeps the model with the most inliers (the paper's rule), ``"msac"`` the
            lowest truncated Sampson cost (more accurate on the same samples; the default), ``"lmeds"`` the least
            median (MATLAB's default method).
        rectify: ``"required"`` rectifies from F before measuring disparity and fails the pair when that is
            degenerate (the paper, Sec. 3.4); ``"auto"`` ranges the raw points when the inliers already lie on
            the same rows (median |y_left − y_right| ≤ ``row_tolerance_px``: a mechanically parallel rig like
            the SVS, where an F fitted to a few nearly planar obstacles would only add shear) or when F cannot
            rectify, and rectifies otherwise; ``"off"`` always measures x_left − x_right on the raw points.
        row_tolerance_px: see ``rectify="auto"``, pixels.
        row_alignment: :class:`~svs_torch.geometry.row_alignment.RowAlignmentConfig`: under ``rectify="auto"``, a right
            view whose matches fit a roll / vertical shift / scale of the right camera that moves some image
            corner's row by more than its ``min_correction_px``, or whose rows read a turn of the right camera
            about its y or x axis (a keystone), is aligned by that similarity (and unturned) instead (before the
            projective rule): a loosely mounted second board (``experiments/real_rig.py``). None: off.
        rectification: :class:`~svs_torch.geometry.rectification.RectificationConfig`.
        depth: :class:`~svs_torch.depth.DepthConfig`: the range rule (``"dense"``, the default, or the paper's
            ``"paper"``: min/max over the inliers, or robust percentiles).
        dense: :class:`~svs_torch.depth.dense.DenseConfig`, the dense SAD stage of the ``"dense"`` rule.
        verify_min_inliers, verify_min_inlier_share, verify_min_agreeing_inliers: under the dense rule, the
            sparse stage vouches that both views show one scene (``PipelineResult.verified``; the dense stage
            then accepts an object on ``depth.min_object_valid_fraction`` of its pixels instead of the stricter
            ``min_object_valid_fraction_unverified``) only when RANSAC found F with at least this many inliers,
            making at least this share of the matches, of which at least this many have the disparity the dense
            map measures at their pixel (within one working pixel,
            :func:`~svs_torch.depth.dense_objects.count_agreeing_inliers`). 7-point RANSAC fits some F to a dozen chance
            matches between unrelated views, but the dense map confirms at most 5 of them, against 7 or more on
            197 of 199 real and synthetic pairs (``experiments/verify_views.py``: 1966 pairs of unrelated
            Middlebury / KITTI views and 64 synthetic ones; the two others, Flowerpots and Reindeer squeezed to
            320×240, keep every object: each has 40 % of its region measured). With ``features_on="mask"``:
            at most 2 on the unrelated views, 9 or more on 198 of 199 (the one left has no F), 7 objects of the
            unrelated views ranged, as before. Measured again with today's stages (2026-11-25): the dense map
            confirms at most 4 inliers of unrelated views, up to 20 of a held-out 2005 scene against its
            near-duplicate (Baby1-3, Bowling1/2, Lampshade1/2, Midd1/2: the same objects moved), 6 such pairs
            verified; 196 of 199 real and synthetic pairs verified by it, 197 with ``verify_many_inliers``.
            Lowered from 6 to 5 on 2026-11-25 (camera frames, issue 33): noise leaves the dense map confirming
            few inliers of a real pair, and 5 stays above the 4 it confirms on unrelated views.
        verify_many_inliers, verify_many_inliers_min_agreeing: so many RANSAC inliers (with the share above)
            vouch with only this many of them confirmed by the dense map (None: never). A right camera that clips
            a white object, or noise, leaves a dense map that confirms few inliers of a real pair (held-out Baby2
            at 320×240 with the right view 30 % brighter: 121 inliers of 127 matches, 4 confirmed, the pair left
            unranged), while F fitted to views of different scenes kept at most 38 (``experiments/verify_views.py``);
            a pair with none confirmed is a dense map gone wrong (PianoL, lit by two lamps), not a clipped view.
        verify_unanimous_min_inliers, verify_unanimous_min_agreeing: so many RANSAC inliers (with the share above)
            vouch where the dense map confirms at least so many of them and every one of them it measured
            (``PipelineResult.num_measured_inliers``; None: never). Camera noise leaves the dense map measuring few
            windows, so it confirms few inliers of a real pair, yet none it measures disagrees; between unrelated
            views its chance agreements come with disagreements.
        verify_whole_view: a pair these rules leave unverified is checked again by them on a dense map of its whole
            left view: its inliers lie anywhere, the first map is only near the kept regions (noise can move them).
        seed: RANSAC seed; every pair uses it, so a pair's result does not depend on its batch.
        differentiable: after the hard pipeline (run without gradients: it makes every discrete decision), a
            differentiable pass recomputes each object's depth from the images and the segmenter's logits
            given those decisions (:mod:`svs_torch.pipeline.soft`): ``PipelineResult.depth`` then carries
            gradients to both images and to the network's weights, and ``hard_depth`` keeps the hard values.
            Needs the ``"dense"`` range rule.
        noisy_retry_sigma_px: under the dense rule, a pair the sparse stage did not verify (or with a kept object
            unranged) is measured again on both views smoothed by a Gaussian of this σ (working pixels), and that
            second measurement is kept where it is verified and ranges more objects (or as many, the first not
            verified): JPEG frames with sensor noise leave the x-Sobel SAD few unique windows and the SURF
            matches few inliers the map confirms, while a clean pair is verified and never retried. None: off.
        feature_smoothing_sigma_px: SURF detects, describes and the matches are refined on both views smoothed
            by a Gaussian of this σ (input pixels); None: on the views as they are. Set by the retry below.
        noisy_features_retry_sigma_px: under the dense rule, a pair the first run left unverified is run again with
            ``feature_smoothing_sigma_px`` this σ, and that second result is kept where it is verified and ranges
            as many objects or more (:func:`~svs_torch.pipeline.ranging.second_pass_is_better`;
            ``PipelineResult.features_smoothed``): in a JPEG digit 8 frame SURF's blobs are the noise's, and a
            rendered scene kept 6–16 matches of 250–400 keypoints a view, too few to verify it, where SURF on
            views smoothed by σ 1 px matched 18–39 and the pair was ranged at 98–99 %
            (:mod:`svs_torch.pipeline.features_retry`). A clean pair is verified and never retried. None: off (the
            paper's).
        coarse_retry_below_share: under the dense rule, a pair whose dense map measured less than this share of its
            kept regions' pixels (``ObjectDepths.num_valid_px`` over ``area_px``: the uniqueness and left–right
            checks reject a noisy frame's windows) is measured again at half the working width
            (``DenseConfig.working_width_px // 2``: each working pixel the mean of 4× as many input pixels, the
            window twice as wide), and that second measurement is kept where it is verified and ranges every
            object the first did, or is unverified as the first was and ranges as many (``PipelineResult.coarse``;
            :func:`~svs_torch.pipeline.ranging.coarse_is_better`). On the tuned scenes' camera frames it is the
            ranged pairs with wrong depths that it mends, which no retry of unfinished pairs reaches. None: off
            (the paper's).
        drop_unmeasured_below_share: under the dense rule, a kept left region whose dense map measured less than
            this share of its pixels (``ObjectDepths.num_valid_px`` over ``area_px``) is dropped from the kept
            regions where another kept region of the pair was ranged on at least that share, and the few pixels
            range the first no nearer than it, or not at all
            (:func:`~svs_torch.pipeline.ranging.drop_unmeasured_objects`; ``PipelineResult.dropped_objects``).
            Camera noise lets the segmenter keep a far region, or one straddling a depth edge, whose windows the
            dense checks mostly reject; the few kept are the wrong ones, and the pair would report a distance
            nothing has. A kept region the depth stage left unranged beside a ranged one is dropped too, whatever
            its share (one wholly in the left band the right camera may not see:
            ``DepthConfig.min_object_pixels_in_view``). The nearest obstacle does not change by this rule. None
            (the default, and the paper's): every kept region stays, and an evaluation scores a dropped one as an
            object without a distance anyway (``PipelineResult.dropped_labels``): dropping hides nothing from a score.
        drop_unmeasured_nearer_below_share: a kept left region measured on less than this share is dropped as
            above even where its few pixels range it nearer than the measured one (with
            ``drop_unmeasured_below_share`` set): nearly every window rejected, its range is mostly its row
            neighbours' disparities filled in, and noise ranges a far textureless region near. The only rule that
            can change the nearest obstacle. None (the default): a region ranged nearer than every measured one
            always stays.
        region_interior_working_px: under the dense rule, each kept left region of the nearness segmenter is
            measured over its interior, eroded by this radius in the dense stage's working pixels (at least one
            input pixel each; :mod:`svs_torch.segmentation.interior`, ``PipelineResult.object_labels``): a block
            matcher fattens near regions onto the background behind them. None: off (the paper's).
        measure_near_surface: under the dense rule, a kept object whose dense disparities split into two surfaces
            far apart (a near obstacle and the wall behind it, joined into one region by camera noise) is ranged
            over its near surface only (:mod:`svs_torch.pipeline.near_surface`; ``PipelineResult.near_surface``).
            False: over the whole region (the paper's).
        exposure: the two views' exposures matched before the first stage (:mod:`svs_torch.pipeline.exposure`:
            an affine map through both views' quartiles, where they differ by more than ``min_change``, applied to
            the darker view so that both clip the same highlights), e.g. ``ExposureConfig()``. None: off.
        exposure_right_clipped: where ``exposure`` is None, the same map first for the pairs whose right view clips
            at white more of its pixels than the left by its ``min_right_clipped_share`` (which must be set): a
            brighter right camera's one-sided highlights move the medians. None (the default): off.
        exposure_retry: under the dense rule, a pair left unverified, with a kept object unranged, or whose
            nearness split was taken again, whose views' exposures differ (by more than its ``min_change``,
            :data:`~svs_torch.pipeline.exposure.RETRY_MIN_CHANGE` by default) is run again with ``exposure`` set
            to this, and the second result is kept where it is verified and ranges more objects
            (:mod:`svs_torch.pipeline.exposure_retry` gives the whole rule): the gain difference of two boards is
            corrected where it costs a pair, and a pair lit by two lamps keeps its first result. None: off.
        exposure_retry_max_residual_ratio: a pair is run again only where the retry's map brings its views together
            where they see the same points: the median difference of its first run's RANSAC inliers (5×5 patch
            means) after the map at most this share of the one before (a gain difference, one map for every point:
            0.2–0.3; two lamps, PianoL: 0.99–1.65;
            :func:`~svs_torch.pipeline.exposure.matched_residual_ratio`). A pair with too few inliers to tell is
            run again. None: every pair the rule above names.

    ``PipelineConfig.paper()`` is the paper's pipeline with MATLAB's defaults and Eq. (5)–(8) as the range rule
    (Table 1's "proposed" row).
    """

    # The nearness segmenter, nearest region first then largest, of 0.3 % of the image at least (measured by both
    # cameras; 0.15 % if nearer than all those: experiments/thin_obstacles.md): select_nearness_rule.md. Under 12.5 %
    # of the view accepted by the block matcher, Otsu: views of two scenes (experiments/nearness_fallback.md). A
    # region half clipped at white is no candidate (real_rig.md, "Clipped regions": tuning sets, 0.5-0.7 alike).
    segmentation: SegmentationConfig = field(default_factory=lambda: SegmentationConfig(
        segmenter="nearness", keep="nearest_first", min_area_fraction=0.003, near_min_area_fraction=0.0015,
        min_measured_share=0.125, max_clipped_share=0.5))
    # MetricThreshold 100 rather than MATLAB's 1000, ratio 0.8 rather than 0.6, matches refined: the best measured
    # (experiments/surf_vs_sift.py and fundamental_vs_opencv.py --config; see the README's "Precise geometry").
    surf: SurfConfig = field(default_factory=lambda: SurfConfig(metric_threshold=PIPELINE_METRIC_THRESHOLD))
    # real_rig.py, tuned 320x240: a turned / shifted / brighter right view segments differently and the masked images'
    # region borders lose half the matches (roll 2 deg: 164 -> 72 on Aloe); the nearness regions of the right view are
    # the left ones moved by their disparity, which such a camera moves elsewhere: whole images kept or raised every
    # condition (roll 2 deg: 46 / 19 -> 81 / 84 %, shift 3 %: 26 / 39 -> 83 / 83 %, clean and JPEG unchanged).
    features_on: Literal["masked", "mask", "image"] = "image"  # the paper (Sec. 3.3 (1)): "masked"
    max_ratio: float = LOWE_MAX_RATIO  # Lowe's ratio; MATLAB matchFeatures MaxRatio is 0.6 (the paper preset)
    mutual: bool = False  # MATLAB matchFeatures Unique = false
    laplacian_gate: bool = True  # SURF's sign check, Bay et al. Sec. 4.3; off in paper() (MATLAB matchFeatures)
    epipolar_band_px: float | None = None  # pixels; None: no band
    refine_matches: MatchRefinementConfig | None = field(default_factory=MatchRefinementConfig)
    ransac_threshold_px: float = 1.0  # pixels, Sampson distance
    ransac_confidence: float = 0.99  # MATLAB / OpenCV default
    ransac_max_iterations: int = 1024  # 7-point samples per pair
    ransac_scoring: Literal["ransac", "msac", "lmeds"] = "msac"  # Sec. 3.3 (3) keeps the most inliers: "ransac"
    rectify: Literal["auto", "required", "off"] = "auto"  # Sec. 3.4, uncalibrated rectification
    row_tolerance_px: float = 1.0
    # experiments/real_rig.py: roll 2 deg / shift 3 % of the right view at 320x240 lost 27-50 points per object.
    row_alignment: RowAlignmentConfig | None = field(default_factory=RowAlignmentConfig)
    rectification: RectificationConfig = field(default_factory=RectificationConfig)
    depth: DepthConfig = field(default_factory=DepthConfig)
    dense: DenseConfig = field(default_factory=DenseConfig)
    # experiments/verify_views.py: the dense map's confirmation separates real pairs (>= 7 agreeing inliers, 197 of
    # 199) from unrelated views (<= 5 when first measured, <= 4 with the stages of 2026-11-25); 15 inliers left 7 real
    # pairs unverified and verified 15 unrelated ones.
    # 6 -> 5 (2026-11-25), chosen on the tuned split's half-contrast JPEG frames (experiments/real_rig.md, "sixth
    # time"); 5, not 4: the dense map confirms up to 4 inliers of unrelated views (Wood1 x Venus, verified at 4).
    verify_min_inliers: int = 0
    verify_min_inlier_share: float = 0.5
    verify_min_agreeing_inliers: int = 5
    # experiments/verify_views.py: F between views of different scenes kept at most 38 inliers (the held-out
    # 2005 near-duplicates Baby1-3, same objects moved; 12 on the tuning scenes' pairs, 9 synthetic). Tuned scenes
    # (experiments/real_rig.py --splits tuned --sizes 320x240,native --no-rival --set verify_many_inliers=N): with
    # none of them confirmed, 60 inliers ranged PianoL (two lightings, a wrong dense map) 14-53 % off in 11
    # conditions at 320x240 where it was unranged, 100 Shelves at digit 6 60 % off; with one confirmed, 60 ranges
    # Shelves at digit 6 (0 -> 91 %) and changes nothing else, while 30 or 40 range PianoL native at digit 1 15 % off.
    verify_many_inliers: int | None = 60
    verify_many_inliers_min_agreeing: int = 1
    # 2026-11-25, on the tuning set for camera frames (experiments/real_rig.md's opening: real_rig.py --splits tuned
    # --contrast 0.5 --no-rival, and --set verify_unanimous_min_inliers=none): digit 8 65.59 -> 85.47 % (Piano and
    # Shelves 0 -> 98.9 / 99.9, each 3 of 3 measured inliers confirmed), no other row changed, full contrast
    # unchanged at both sizes. Without the 20 inliers a synthetic negative (11 inliers, 3 of 3) was verified; a
    # share of 0.75 ranged PianoL at digit 2 57 % off; verify_views.py at these values: every negative set as
    # before.
    verify_unanimous_min_inliers: int | None = 20
    verify_unanimous_min_agreeing: int = 3
    verify_whole_view: bool = True  # see ranging._vouched_over_whole_view; experiments/real_rig.md (2026-11-28)
    seed: int = 0
    differentiable: bool = False  # issue 31: the hard pipeline's decisions, the depths recomputed with gradients
    # experiments/real_rig.py, tuned 320x240: JPEG digit 7 + sigma 6 68.8 -> 88.1 %, digit 8 + sigma 8 58.7 -> 78.4 %.
    noisy_retry_sigma_px: float | None = 1.0
    feature_smoothing_sigma_px: float | None = None
    # experiments/real_rig.py --splits tuned,synthetic --loose-rig-digit 8 --noise-seed 0|1|2 (tuning sets only):
    # rendered pairs 86.88 % (52 of 624 unranged) -> σ 0.7 / 1.0 / 1.5: 94.07 / 93.93 / 94.06 (1 / 1 / 0 unranged);
    # tuned pairs never retried; the tuning suite's one retried tuned pair (PianoL) 97.0 / 90.8 / 97.0.
    noisy_features_retry_sigma_px: float | None = 1.5
    # experiments/coarse_retry.md (tuned scenes only): camera frames at half contrast, 320x240, 87.83 -> 91.26 %, their
    # clean pairs 98.79 -> 98.85; native size within 0.05. Clean pairs measured 0.40-0.92 of their kept pixels.
    coarse_retry_below_share: float | None = 0.45
    # Off by default (experiments/real_rig.md, "Dropped regions scored"; tuning sets only). First chosen at 0.45 and
    # 0.15 under a score that left a dropped region out, so dropping a hard object could only raise it. Scored as
    # an object without a distance (0 %, as an unranged one), dropping lost on every tuning set: the camera-frame
    # suite (tuned scenes at 320x240 full and half contrast, 416 and 448 px half contrast, native, rendered; draws
    # 0-2; 1 584 pairs) per object 96.26 % with the rules, 98.53 without; R_max 98.40 / 98.53; R_min (the warning)
    # 98.77 either way. Misaligned and loose-rig frames likewise (loose rig digit 4, draw 0: 98.32 / 98.94).
    drop_unmeasured_below_share: float | None = None
    drop_unmeasured_nearer_below_share: float | None = None
    region_interior_working_px: float | None = 2.0  # experiments/select_region_interior.md (tuned split only)
    measure_near_surface: bool = True  # experiments/real_rig.md, "Two surfaces in one kept region" (tuning sets)
    # Off by default: it loses PianoL (two lightings, not two gains) where it ranges Piano (experiments/exposure.md).
    exposure: ExposureConfig | None = None
    # Off by default (experiments/real_rig.md, "One-sided clipping"): chosen on the tuning sets (bright tuned scenes,
    # right camera 30 % brighter: 98.78 -> 99.34 % at 320x240), it lost the held-out corners with a gain (up to 1.61).
    exposure_right_clipped: ExposureConfig | None = None
    # experiments/exposure.md: tuned "gain +30%" Piano 0 -> 99 % at both sizes, PianoL kept; RETRY_MIN_CHANGE's why.
    exposure_retry: ExposureConfig | None = field(default_factory=lambda: ExposureConfig(min_change=RETRY_MIN_CHANGE))
    # experiments/exposure.md, "The map at the matched points": the tuning sets per object within 0.01 (98.668 ->
    # 98.660 % over 3 480 camera-frame pair-conditions; 0.6: 98.652, 1.0: 98.658), 89 of 288 second runs left.
    exposure_retry_max_residual_ratio: float | None = 0.8

    def __post_init__(self) -> None:
        self._check_stage_settings()
        if self.features_on not in ("masked", "mask", "image"):
            raise InputError(f"features_on: expected 'masked', 'mask' or 'image', got {self.features_on!r}")
        if self.rectify not in ("auto", "required", "off"):
            raise InputError(f"rectify: expected 'auto', 'required' or 'off', got {self.rectify!r}")
        if self.ransac_scoring not in ("ransac", "msac", "lmeds"):
            raise InputError(f"ransac_scoring: expected 'ransac', 'msac' or 'lmeds', got {self.ransac_scoring!r}")
        ratio = self.max_ratio
        if isinstance(ratio, bool) or not isinstance(ratio, (int, float)) or not 0 < ratio <= 1:
            raise InputError(f"max_ratio: expected a ratio in (0, 1], got {ratio!r}")
        for name, least in (("verify_min_inliers", 0), ("verify_min_agreeing_inliers", 0),
                            ("verify_many_inliers_min_agreeing", 0), ("verify_unanimous_min_agreeing", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not (isinstance(value, int) and value >= least):
                raise InputError(f"{name}: expected an integer >= {least}, got {value!r}")
        for name in ("verify_many_inliers", "verify_unanimous_min_inliers"):
            many = getattr(self, name)
            if many is not None and (isinstance(many, bool) or not isinstance(many, int) or many < 1):
                raise InputError(f"{name}: expected an integer >= 1 or None, got {many!r}")
        if not (isinstance(self.seed, int) and -2**63 <= self.seed < 2**63):
            raise InputError(f"seed: expected a 64-bit integer, got {self.seed!r}")  # the RANSAC seeds are int64
        for name in ("verify_whole_view", "differentiable", "measure_near_surface"):
            if getattr(self, name) not in (True, False):
                raise InputError(f"{name}: expected a bool, got {getattr(self, name)!r}")
        if self.differentiable and self.depth.rule != "dense":
            raise InputError(f"differentiable: needs depth.rule 'dense' (the paper's rule ranges from extreme "
                             f"inliers, nothing to differentiate), got {self.depth.rule!r}")
        for name in ("noisy_retry_sigma_px", "feature_smoothing_sigma_px", "noisy_features_retry_sigma_px"):
            sigma = getattr(self, name)
            if sigma is not None and not (isinstance(sigma, (int, float)) and not isinstance(sigma, bool)
                                          and 0 < sigma <= MAX_SIGMA_PX):
                raise InputError(f"{name}: expected a σ in (0, {MAX_SIGMA_PX}] pixels or None, got {sigma!r}")
        for name in ("coarse_retry_below_share", "drop_unmeasured_below_share", "drop_unmeasured_nearer_below_share"):
            share = getattr(self, name)
            if share is not None and (isinstance(share, bool) or not isinstance(share, (int, float))
                                      or not 0 < share <= 1):
                raise InputError(f"{name}: expected a share in (0, 1] or None, got {share!r}")
        if (r := self.region_interior_working_px) is not None and not (type(r) in (int, float) and 0 <= r < 1000):
            raise InputError(f"region_interior_working_px: expected a radius in [0, 1000) or None, got {r!r}")
        for name in ("exposure", "exposure_retry", "exposure_right_clipped"):
            if getattr(self, name) is not None and not isinstance(getattr(self, name), ExposureConfig):
                raise InputError(f"{name}: expected an ExposureConfig or None, got {getattr(self, name)!r}")
        if self.exposure_right_clipped is not None and self.exposure_right_clipped.min_right_clipped_share is None:
            raise InputError("exposure_right_clipped: expected an ExposureConfig with min_right_clipped_share set")
        if (ratio := self.exposure_retry_max_residual_ratio) is not None and not (
                type(ratio) in (int, float) and 0 < ratio < math.inf):
            raise InputError(f"exposure_retry_max_residual_ratio: expected a ratio > 0 or None, got {ratio!r}")
        for name in ("mutual", "laplacian_gate"):
            check_flag(getattr(self, name), name)
        check_real(self.epipolar_band_px, "epipolar_band_px", 0.0, optional=True)
        check_real(self.ransac_threshold_px, "ransac_threshold_px", 0.0, low_open=True)
        check_real(self.ransac_confidence, "ransac_confidence", 0.0, 1.0, low_open=True)
        check_count(self.ransac_max_iterations, "ransac_max_iterations", 1, most=MAX_HYPOTHESES)  # 2^31 never ended
        check_real(self.row_tolerance_px, "row_tolerance_px", 0.0)
        if not 0 <= real_or_nan(self.verify_min_inlier_share) <= 1:
            raise InputError(f"verify_min_inlier_share: expected a share in [0, 1], got "
                             f"{self.verify_min_inlier_share!r}")

    def _check_stage_settings(self) -> None:
        """Each stage's settings are that stage's configuration (None only where a stage can be left out). Why:
        ``depth=None`` or ``surf={}`` was accepted and failed inside a stage, as ``'NoneType' object has no
        attribute 'rule'``."""
        for name, kind, optional in (
                ("segmentation", SegmentationConfig, False), ("surf", SurfConfig, False),
                ("refine_matches", MatchRefinementConfig, True), ("row_alignment", RowAlignmentConfig, True),
                ("rectification", RectificationConfig, False), ("depth", DepthConfig, False),
                ("dense", DenseConfig, False)):
            value = getattr(self, name)
            if not (isinstance(value, kind) or (optional and value is None)):
                raise InputError(f"{name}: expected a {kind.__name__}{' or None' if optional else ''}, got "
                                 f"{type(value).__name__}")

    def for_guide(self, floor_left_out: bool = True, second_passes: bool = True) -> PipelineConfig:
        """These settings as ``svs-depth guide`` runs them, which its benchmark times too: guide's segmentation
        (:meth:`SegmentationConfig.for_guide`: a camera's frames, the floor left out unless ``floor_left_out`` is
        False) and, with ``second_passes`` False (``guide --second-passes off``), neither pass that measures a
        pair again: the dense stage's coarse retry (``coarse_retry_below_share``) and the exposure retry
        (``exposure_retry``). Without them no frame waits for a second run (the shared real pairs as digit 4
        frames on a 2-core machine at 918d3e3: 90th percentile 24–26 → 17–19 ms, slowest 36–44 → 18–19; digit 8:
        slowest 98 → 35), but noisy frames lose accuracy (held-out digit 4 frames at 320×240: 97.95 → 95.34 % per
        object), so they stay on by default (``experiments/guide_second_passes.md``)."""
        passes = {} if second_passes else {"coarse_retry_below_share": None, "exposure_retry": None}
        return replace(self, segmentation=self.segmentation.for_guide(floor_left_out), **passes)

    @classmethod
    def paper(cls) -> PipelineConfig:
        """The paper's pipeline as published (Sec. 3.2–3.4): Otsu and the two largest regions, MATLAB's SURF,
        matching (SAD, MaxRatio 0.6, no Laplacian-sign gate) and RANSAC defaults (DistanceThreshold 0.01 bounds the
        squared Sampson distance in pixels²: 0.1 px; NumTrials 500), and R_min / R_max as the extremes over the
        RANSAC inliers (Eq. (5)–(8)). Measured by `svs-depth eval ../shared/data --size 320x240 --preset paper` (per
        object over the 12 pairs with a calibration). Not MATLAB's: U-SURF (``Upright`` false: 5 failed pairs, not
        1, 68.2 % against 80.3; the SVS is a roll-free rig), at most 512 keypoints an image (8192 changes nothing),
        no ``MatchThreshold`` (MATLAB's 1.0 is SAD ≤ 0.16 at D = 64: 14 of the 45 pairs would keep 7 matches, not 44).

        Two departures from the letter: RANSAC keeps the hypothesis of least truncated Sampson cost (``"msac"``)
        rather than the most inliers (``"ransac"``; R_min / R_max / per object 93.4 / 82.6 / 80.3 % against 92.9 /
        82.3 / 80.4), and a pair whose inliers already lie on the same rows is ranged on its raw points
        (``rectify="auto"``) rather than rectified from F whatever it is (``"required"``): an F fitted to a few
        nearly planar obstacles is degenerate for rectification on 33 of the 45 shared pairs at 320×240, each then a
        failed pair (27.8 %). ``replace(PipelineConfig.paper(), ransac_scoring="ransac", rectify="required")``
        (``--preset paper --set ransac_scoring=ransac --set rectify=required``) is the paper's letter: 30
        degenerate, 27.9 %."""
        return cls(segmentation=SegmentationConfig(), surf=SurfConfig(), features_on="masked", laplacian_gate=False,
                   max_ratio=MATLAB_MAX_RATIO, refine_matches=None, ransac_threshold_px=0.1, ransac_max_iterations=500,
                   row_alignment=None, depth=DepthConfig(rule="paper", min_in_front_share=0.0),
                   noisy_retry_sigma_px=None, noisy_features_retry_sigma_px=None, coarse_retry_below_share=None,
                   drop_unmeasured_below_share=None, drop_unmeasured_nearer_below_share=None, exposure_retry=None,
                   region_interior_working_px=None, measure_near_surface=False)
