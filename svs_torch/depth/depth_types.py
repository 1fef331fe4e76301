"""The depth stage's options (:class:`DepthConfig`) and results: disparities and depths of points, the
range over a pair, each object's depths, the nearest obstacle.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Literal, NamedTuple

import torch

from ..core.checks import InputError, check_count, check_flag, check_percentiles, check_real

__all__ = [
    "Accuracy", "DepthConfig", "DepthResult", "Disparities", "NearestObstacle", "ObjectDepths", "ObstacleSide",
    "PointDepths", "RangeEstimate"
]


class ObstacleSide(enum.IntEnum):
    """Which third of the image width an obstacle's centroid falls in, or the centre for one that reaches across the
    middle column (in the walker's path); stored as int64 in tensors.

    Values:
        NONE (−1): no obstacle (padding slot, or no valid object for the nearest).
        LEFT (0), CENTRE (1), RIGHT (2): the left, middle or right third of the left view.
    """

    NONE = -1
    LEFT = 0
    CENTRE = 1
    RIGHT = 2


@dataclass(frozen=True)
class DepthConfig:
    """Options of :func:`estimate_depth`.

    Attributes:
        rule: how the pipeline ranges a pair. ``"dense"`` (the default): each kept object's depth is the
            median over its region's valid dense disparities (:mod:`svs_torch.depth.dense_objects`), R_min / R_max the
            nearest / farthest object. ``"paper"``: Eq. (5)–(8) over the sparse RANSAC inliers, objects from
            the inliers on each region. :func:`estimate_depth` itself is the sparse rule; the pipeline adds the
            dense one.
        percentiles: ``None`` for the paper's d_min/d_max (Eq. (5)–(6), min and max over the inliers), or
            ``(low, high)`` percentiles in [0, 100] (e.g. ``(10, 90)``) as robust stand-ins (``"paper"`` rule).
        object_percentiles: the ``(low, high)`` percentiles of each object's depth, besides its median; the low
            one of the nearest object is its nearest visible surface (``NearestObstacle.surface_m``).
        surface_within_in_view_top: take the low percentile over the dense pixels at or below the pair's in-view
            top only (:func:`~svs_torch.depth.dense_objects.surface_pixels`: leaving out noise's wrong matches far
            above every object's range, which pull the nearest surface near while the median stays right); the
            median and the high percentile stay over every pixel (``"dense"`` rule).
        min_object_inliers: fewest valid inliers for an object's depth to count (``"paper"`` rule).
        min_in_front_share: a pair is ranged by the ``"paper"`` rule only where more than this share of its
            inliers lie in front of the rig (``d + doffs > 0``); else its views are swapped (or its ``doffs``
            wrong) and the few in front are stray matches: swapped views were ranged at 0.20 m from one stray
            inlier of 274, a false warning. 0 is the paper's letter (any inlier in front), which the paper preset
            keeps; at 0.5 the shared pairs lose only Flowerpots at 320×240 under the paper preset, whose 8 inliers
            are all wrong (4 of them in front: not more than half).
        min_object_pixels: fewest valid dense pixels for an object's depth to count (``"dense"`` rule).
        min_object_valid_fraction: least share of an object's region with valid dense disparities (``"dense"``
            rule) where the pair's geometry is verified (``PipelineResult.verified``: RANSAC found F and the
            dense map confirms enough of its inliers): both views show the same scene.
        min_object_valid_fraction_unverified: the same where it is not. Views of different scenes leave up to
            32 % of a region consistent by chance (``experiments/verify_views.py``, synthetic scenes; related
            Middlebury scenes up to 42 %), real pairs 47–98 % (a lighting-change scene 18 %, an occluding plant
            17 % at native size, both verified): with no geometry to vouch for the pair, an object with less is
            not ranged rather than ranged wrong.
        min_object_pixels_in_view: fewest valid dense pixels an object needs at columns where every disparity
            of the pair's search range still lands inside the right image (``x ≥ d_max``; ``"dense"`` rule).
            Nearer the left border a near surface's match can lie outside the right view, and the best visible
            candidate is then wrong: an object that lies wholly in that band has no pixel the right camera is
            sure to see, and is not ranged rather than ranged wrong (Middlebury Laundry at 320 px: a 38 px
            strip 3.6 m away on the left border was ranged at 11.3 m). ``d_max`` leaves out a detached near tail
            of noise's wrong coarse matches (``DenseConfig.in_view_detached_tail_share``). 0 turns the check off. Unlike
            ``DenseConfig.whole_range_in_view`` it drops no pixel: an object with enough pixels in view keeps
            its median over all of them.
        coarse_retry_max_period_peak: a pair one of whose kept regions repeats itself along the rows (its row
            autocorrelation rises again to a peak of at least this; each region tested on its own,
            :func:`svs_torch.depth.periodicity.object_periods`) is not measured again on the coarse grid
            (``PipelineConfig.coarse_retry_below_share``), where the pattern's period halves and aliases; None:
            every pair may be (``"dense"`` rule).
        alias_check_min_period_peak: a kept object that repeats itself along the rows (a peak of at least this,
            as above) is measured again over one period about the alias its whole region matches best where its
            windows' median lies there, and loses its pixels where the two disagree
            (:func:`svs_torch.depth.alias_choice.settle_aliases`); None: every object as measured (``"dense"``
            rule).
        coarse_retry_max_period_px, alias_check_max_period_px: the longest period each test above looks for,
            pixels at the dense stage's working width (the row autocorrelation's longest lag, 4 to 1024; a period
            up to one less is found); the coarse pass looks over the same stretch of the image, half as many of its
            pixels. A railing near the walker (bars 12 cm apart are 41 px apart at 0.8 m) is kept off the coarse
            grid; the alias check does not look past 31 px, where the shared chessboard at 0.38 m (a 33 px period,
            running off the view) had its whole-object shift on the wrong alias and was dropped.
    """

    rule: Literal["dense", "paper"] = "dense"  # paper_table1.py: dense 98-99 % vs sparse extremes 74-84 %
    percentiles: tuple[float, float] | None = None  # Sec. 3.4, Eq. (5)–(6) when None
    object_percentiles: tuple[float, float] = (10.0, 90.0)
    surface_within_in_view_top: bool = True  # guide_confirm.md, "The nearest surface within the in-view top"
    min_object_inliers: int = 1
    min_in_front_share: float = 0.5
    min_object_pixels: int = 20
    min_object_valid_fraction: float = 0.1
    min_object_valid_fraction_unverified: float = 0.4  # verify_views.py: 0.3 ranged 10 of 64 synthetic mismatches
    min_object_pixels_in_view: int = 20  # paper_table1.py: changes only held-out Laundry at 320 px (R_max 0 -> 99 %)
    coarse_retry_max_period_peak: float | None = 0.5  # experiments/repeated_patterns.md
    alias_check_min_period_peak: float | None = 0.5  # experiments/repeated_patterns.md, "The whole object's alias"
    coarse_retry_max_period_px: int = 64  # experiments/repeated_patterns.md, "A railing near the walker"
    alias_check_max_period_px: int = 32  # the same section: the shared chessboard

    def __post_init__(self) -> None:
        if self.rule not in ("dense", "paper"):
            raise InputError(f"rule: expected 'dense' or 'paper', got {self.rule!r}")
        for name in ("min_object_inliers", "min_object_pixels", "min_object_pixels_in_view"):
            check_count(getattr(self, name), name)
        for name in ("coarse_retry_max_period_px", "alias_check_max_period_px"):
            check_count(getattr(self, name), name, 4, most=1024)  # a lag past the working width finds nothing
        check_flag(self.surface_within_in_view_top, "surface_within_in_view_top")
        for name in ("coarse_retry_max_period_peak", "alias_check_min_period_peak"):
            if getattr(self, name) is not None:
                check_real(getattr(self, name), name, 0.0, 1.0)
        for name in ("min_object_valid_fraction", "min_object_valid_fraction_unverified", "min_in_front_share"):
            check_real(getattr(self, name), name, 0.0, 1.0)
        check_percentiles(self.percentiles, "percentiles", optional=True)
        check_percentiles(self.object_percentiles, "object_percentiles")


@dataclass(frozen=True)
class Disparities:
    """Rectified disparities ``disparity_px`` ``(B, K)`` (``x_left − x_right``), ``row_error_px`` ``(B, K)``
    (``y_left − y_right``, ≈ 0 when rectified) and ``valid`` ``(B, K)`` bool (input mask and both points mapped
    in front of the homographies' line at infinity); zeros where not valid. The sign of d is not checked here."""

    disparity_px: torch.Tensor
    row_error_px: torch.Tensor
    valid: torch.Tensor


@dataclass(frozen=True)
class PointDepths:
    """Per-correspondence depth ``depth_m`` ``(B, K)`` = ``f·B / (d + doffs)`` and ``valid`` ``(B, K)``
    (valid disparity with ``d + doffs > 0``); zeros where not valid."""

    depth_m: torch.Tensor
    valid: torch.Tensor


@dataclass(frozen=True)
class RangeEstimate:
    """The pair's disparity and depth range (Sec. 3.4). All ``(B,)``; zeros where not ``valid``.

    Under the paper's rule (``DepthConfig.rule="paper"``) it is Eq. (5)–(8) over the RANSAC inliers; under the
    default dense rule R_min / R_max are the nearest / farthest ranged object's median depth and d_max / d_min
    their disparities (:func:`svs_torch.depth.dense_objects.range_from_objects`).

    Attributes:
        d_min_px, d_max_px: Eq. (6), (5) over the inliers with ``d + doffs > 0`` (or the chosen percentiles);
            dense rule: ``f·B / R − doffs`` of R_max and R_min.
        r_min_m: Eq. (7), ``f·B / (d_max + doffs)``; dense rule: the nearest ranged object's median depth.
        r_max_m: Eq. (8), ``f·B / (d_min + doffs)``; dense rule: the farthest ranged object's median depth.
        num_disparities: int64, inliers that entered; dense rule: the ranged objects' valid dense pixels.
        valid: bool, at least one did.
    """

    d_min_px: torch.Tensor
    d_max_px: torch.Tensor
    r_min_m: torch.Tensor
    r_max_m: torch.Tensor
    num_disparities: torch.Tensor
    valid: torch.Tensor


class Accuracy(NamedTuple):
    """Eq. (9) ``percent`` (same shape as the inputs) and ``valid`` bool (``real > 0``, both finite)."""

    percent: torch.Tensor
    valid: torch.Tensor


@dataclass(frozen=True)
class ObjectDepths:
    """Depth of each kept region (N slots; slot n is ``region_labels[:, n]``). All ``(B, N)``.

    Attributes:
        label: int64 label of the slot, −1 for padding (or a slot the pipeline dropped as unmeasured,
            ``PipelineResult.dropped_objects``).
        area_px: int64 pixel count of the region in the label image.
        centroid_x_px: mean column of the region (pixel centres); 0 where the area is 0.
        side: :class:`ObstacleSide` of the centroid (thirds of the pair's width), NONE where the area is 0; under the
            dense rule, of the part its distances were measured on where that is not the whole region
            (:mod:`svs_torch.pipeline.near_side`).
        num_inliers: int64, valid depths whose left point lies on the region.
        depth_median_m, depth_low_m, depth_high_m: median and ``object_percentiles`` of those depths (under the
            default dense rule: of the region's dense-map depths, its invalid pixels filled from their rows,
            :func:`svs_torch.depth.dense_objects.dense_object_depths`); 0 where not ``valid``.
        valid: bool, the slot holds a region with at least ``min_inliers`` valid depths (dense rule: enough valid
            dense pixels by ``DepthConfig.min_object_pixels``, its valid-fraction and in-view rules).
        point_slot: ``(B, K)`` int64, the slot of each correspondence (−1: none or invalid depth).
        num_valid_px: ``(B, N)`` int64, valid dense-disparity pixels of the region when the depths come from the
            dense stage (:func:`svs_torch.depth.dense_objects.dense_object_depths`); None for the sparse rule.
        num_in_view_px: ``(B, N)`` int64, those of them at columns where the pair's whole disparity range lands
            inside the right image (``DepthConfig.min_object_pixels_in_view``); None for the sparse rule.
    """

    label: torch.Tensor
    area_px: torch.Tensor
    centroid_x_px: torch.Tensor
    side: torch.Tensor
    num_inliers: torch.Tensor
    depth_median_m: torch.Tensor
    depth_low_m: torch.Tensor
    depth_high_m: torch.Tensor
    valid: torch.Tensor
    point_slot: torch.Tensor
    num_valid_px: torch.Tensor | None = None
    num_in_view_px: torch.Tensor | None = None


@dataclass(frozen=True)
class NearestObstacle:
    """The valid object with the smallest median depth: ``slot`` ``(B,)`` int64 (−1 none), ``depth_m`` ``(B,)``
    (its median, 0 none), ``side`` ``(B,)`` int64 :class:`ObstacleSide`, ``valid`` ``(B,)`` bool, and
    ``surface_m`` ``(B,)``: its low depth percentile (``DepthConfig.object_percentiles[0]``), the nearest visible
    surface of that obstacle — what a walker would bump into first (0 none)."""

    slot: torch.Tensor
    depth_m: torch.Tensor
    side: torch.Tensor
    valid: torch.Tensor
    surface_m: torch.Tensor | None = None


@dataclass(frozen=True)
class DepthResult:
    """Everything :func:`estimate_depth` computes; ``objects`` and ``nearest`` are None without labels."""

    disparities: Disparities
    points: PointDepths
    range: RangeEstimate
    objects: ObjectDepths | None
    nearest: NearestObstacle | None
