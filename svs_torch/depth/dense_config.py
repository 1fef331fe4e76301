"""The dense stage's options (:class:`DenseConfig`), a search range (:class:`DisparityRange`) and its
result (:class:`DenseDisparity`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, NamedTuple

import torch

from ..core.checks import InputError, check_count, check_flag, check_percentiles, check_real, real_or_nan
from .kernels import MAX_WINDOW

__all__ = ["DenseConfig", "DenseDisparity", "DisparityRange", "RepeatedObjects"]


@dataclass(frozen=True)
class DenseConfig:
    """Options of the dense stage; defaults measured in ``experiments/paper_table1.py`` on the shared
    Middlebury scenes (the tuned-vs-held-out split is in that script's docstring).

    Attributes:
        window_size: side of the square SAD window, pixels, odd (``StereoBM`` blockSize).
        prefilter: ``"xsobel"`` (``StereoBM``'s default) or ``"none"`` (raw intensities).
        prefilter_cap: clip of the x-Sobel response, [0, 1] intensity units (``StereoBM`` preFilterCap 31 on
            0–255 images).
        texture_threshold: least mean |clipped x-Sobel of the left image| over the window, [0, 1] units;
            flatter windows are invalid (``StereoBM`` textureThreshold, there a sum over the window).
        uniqueness_ratio: every cost more than 1 px from the best must exceed ``(1 + ratio)`` times the best
            (``StereoBM`` uniquenessRatio, there in percent); 0 turns the check off.
        lr_max_diff_px: largest left–right disagreement, pixels (``StereoBM`` disp12MaxDiff); None: no check.
        working_width_px: the stage matches images reduced by an integer factor ``f ≈ W / working_width_px``
            (box average) and scales the disparities back by ``f``: the cost volume shrinks ``f³`` times, and
            on the shared scenes a 9-pixel window at this width ranged objects better than at native size.
        scale_window: where the integer factor leaves the images unreduced and wider than ``working_width_px``
            (353–479 px), the window is the odd side nearest ``window_size`` × their width / ``working_width_px``,
            spanning as much of the scene as at that width (:func:`~svs_torch.depth.dense.working_window`). False:
            ``window_size`` at every width.
        margin_px: context around the kept regions' bounding box, working pixels.
        range_source: ``"coarse"``: the range comes from a coarse dense pass over the whole fallback range
            (:func:`coarse_search_range`); ``"inliers"``: from the sparse RANSAC inliers' disparities.
        coarse_width_px: the coarse pass reduces the working images to about this width.
        range_margin_px, range_margin_fraction: the search range is the samples' disparities widened by
            ``max(range_margin_px, range_margin_fraction · span)`` on each side.
        range_percentiles: the sample percentiles that bound the range before the margin (robust to a few
            wrong samples; (0, 100) is their min and max).
        in_view_detached_tail_share: the top of the disparities the in-view rule allows for
            (``DepthConfig.min_object_pixels_in_view``) leaves out a near tail of an object's coarse disparities cut
            off from its median by an empty coarse pixel and holding at most this share of them (clustered wrong
            matches of noisy frames; :func:`~svs_torch.depth.search_range._detached_tail_ceiling`); the range
            searched keeps them. None: the top of the range searched.
        in_view_margin: the margin the in-view top is widened by (with ``in_view_detached_tail_share`` set):
            ``"object"``, the range's margin rule applied to each kept object's own coarse disparities, the top
            being the highest object's; ``"pair"``, the rule applied to the span of all of them, so that a far
            object (or its own far tail of wrong matches) lifts the top above the nearest object's and widens the
            band the in-view rule leaves unranged on the left border. The range searched is the same either way.
        in_view_per_object: each kept object is in view from its own in-view top (its coarse disparities'
            top, the rules above), not the highest object's: a far object on the left border beside a near one is
            ranged where the right camera sees it at its own distance (False: every object from the pair's top,
            the rule before; the rendered border set's far boxes then go unranged in up to 4 of its 16 pairs).
        in_view_own_min_valid_share: an object's own top counts only where at least this share of its pixels from
            there on is valid (:func:`~svs_torch.depth.dense_objects.dense_object_depths`): an object the right
            camera cannot see gets wrong small coarse disparities, and so a low top of its own, but few valid pixels.
        max_num_disparities: most disparities searched per pair (the range is clipped around its centre).
        fallback_max_disparity_fraction: the widest disparity searched, as a fraction of the width: the
            coarse pass's range, and the range of a pair with too few samples.
        min_range_inliers: fewest sparse inliers to bound the range from them.
        min_range_pixels: fewest valid coarse pixels to bound the range from them.
        fill_invalid: per-object statistics fill invalid pixels from their row neighbours first
            (:func:`fill_invalid_rows`), so an object's median is over its whole region.
        whole_range_in_view: a pixel counts only where its pair's whole disparity range lands inside the right
            image, ``x ≥ d_max`` (``StereoBM`` leaves that left band unmatched): nearer the left border the true
            match may be out of the right view and the best visible candidate is then wrong (a 15 px strip of a
            near object on the left border of Middlebury Laundry is ranged at 11 m instead of 3.6 m). Off by
            default: in ``experiments/paper_table1.py`` it fixed Laundry but dropped correctly ranged objects
            near the left border elsewhere (tuned 320 px: R_min 98.9 → 89.1 %, a pair lost; held-out native:
            98.0 / 92.4 → 97.3 / 90.1 %). The default guards per object instead, keeping every pixel:
            ``DepthConfig.min_object_pixels_in_view`` leaves unranged only an object with too few pixels in view. The
            coarse range pass never applies it (it only bounds the search).
        kernel: how the hard path is computed: ``"auto"`` the fused C kernel of :mod:`svs_torch.depth.kernels`
            where it can be built (costs, winner, rejections and sub-pixel fit, each pair at its own box and
            range: bit-identical to the torch path, several times faster), else torch; ``"c"`` the kernel or an
            error; ``"torch"`` the eager torch cost volume, with its window sums and its winner's statistics in
            torch too (the semi-global aggregation below runs its C kernels under every setting: the same values
            as its torch path).
        smoothing_penalties: ``(P1, P2)``: aggregate the SAD volume semi-globally before the winner
            (:mod:`svs_torch.depth.semi_global`), with penalties in multiples of the pair's matching residual
            (the median best SAD per window pixel over the wanted pixels, 8-bit levels of the clipped x-Sobel);
            the aggregated volume picks the winner and makes the verdicts, the sub-pixel fit stays on the plain
            costs. None: plain block matching. Pairs with a residual under ``smoothing_min_residual_levels``
            (clean frames) are not aggregated, nor pairs the stage reduces by more than
            ``smoothing_max_reduction`` (``working_width_px``: the box average has already averaged the noise).
            The fused kernel matches every pair and reports its residual; only the noisy pairs are matched again
            on their whole cost volume (its window sums, aggregation, winner and the winner's statistics by C
            kernels).
        retry_smoothing_penalties: ``smoothing_penalties`` of the pipeline's second pass at half the working
            width (``PipelineConfig.coarse_retry_below_share``: the pairs the first pass measured too little of),
            where the default aggregates; the first pass stays plain block matching (``experiments/real_rig.md``,
            "Semi-global aggregation": on the tuning sets, aggregating the second pass raised the camera frames
            at 320×240 by 1.3 points and cost the clean pairs nothing; aggregating the first pass too cost them).
        smoothing_min_residual_levels, smoothing_max_reduction: see ``smoothing_penalties``.
        smoothing_intensity_weight: on the pairs aggregated semi-globally, the SAD of the intensities themselves
            (8-bit levels) times this is added to the x-Sobel SAD before the aggregation, and the penalties are
            taken in units of that sum's residual, as OpenCV's ``StereoSGBM`` adds a quarter of the intensities'
            cost to the x-derivative's. A featureless surface's x-Sobel holds only noise away from its left and
            right edges, and the columns' paths carry the disparity of what lies above and below into it; its
            intensity step against the background holds it a window wide (``experiments/real_rig.md``,
            "Featureless obstacles"). 0: the x-Sobel costs alone.
    """

    # With uniqueness_ratio, experiments/sweep_defaults.md: 7 and 0.2 lead on the clean tuned pairs by 0.1 point,
    # 9 and 0.10 kept for the tuned split's camera frames (320x240 JPEG mean 98.83 against 98.63 %).
    window_size: int = 9
    prefilter: Literal["xsobel", "none"] = "xsobel"  # StereoBM PREFILTER_XSOBEL
    prefilter_cap: float = 31 / 255  # StereoBM preFilterCap 31
    texture_threshold: float = 2 / 255
    uniqueness_ratio: float = 0.10  # with window_size: experiments/sweep_defaults.md
    lr_max_diff_px: float | None = 1.0
    working_width_px: int = 320
    scale_window: bool = True  # experiments/real_rig.md, "The window at the working width" (tuning sets only)
    margin_px: int = 8
    range_source: Literal["coarse", "inliers"] = "coarse"
    coarse_width_px: int = 160
    range_margin_px: float = 2.0
    range_margin_fraction: float = 0.25
    range_percentiles: tuple[float, float] = (1.0, 99.0)
    in_view_detached_tail_share: float | None = 0.1  # real_rig.md, "The in-view top": 0.05-0.2 alike (tuning sets)
    in_view_margin: Literal["object", "pair"] = "object"  # real_rig.md, "Each object's own margin"
    in_view_per_object: bool = True  # real_rig.md, "Each object's own in-view top" (tuning and rendered sets)
    in_view_own_min_valid_share: float = 0.5  # the same section: a wrong near strip 0.33, seen far boxes >= 0.93
    max_num_disparities: int = 128
    fallback_max_disparity_fraction: float = 0.25
    min_range_inliers: int = 7
    min_range_pixels: int = 20
    fill_invalid: bool = True
    kernel: Literal["auto", "c", "torch"] = "auto"
    whole_range_in_view: bool = False  # paper_table1.py: on, tuned 320 R_min 98.9 -> 89.1 % (PianoL lost)
    smoothing_penalties: tuple[float, float] | None = None
    retry_smoothing_penalties: tuple[float, float] | None = (4.0, 16.0)
    smoothing_min_residual_levels: float = 9.0
    smoothing_max_reduction: int = 2
    smoothing_intensity_weight: float = 0.25  # experiments/real_rig.md, "Featureless obstacles" (tuning sets)

    def __post_init__(self) -> None:
        window = self.window_size
        if not isinstance(window, int) or not 1 <= window <= MAX_WINDOW or window % 2 == 0:
            # the kernel's bound (dense.working_window widens no further); 10001 took 1.8 GB on a 64x48 view
            raise InputError(f"window_size: expected an odd int from 1 to {MAX_WINDOW}, got {self.window_size!r}")
        for name in ("scale_window", "in_view_per_object", "fill_invalid", "whole_range_in_view"):
            check_flag(getattr(self, name), name)  # None reached a kernel's int() before
        if self.range_source not in ("coarse", "inliers"):
            raise InputError(f"range_source: expected 'coarse' or 'inliers', got {self.range_source!r}")
        if not isinstance(self.working_width_px, int) or self.working_width_px < 8:
            raise InputError(f"working_width_px: expected an int >= 8, got {self.working_width_px!r}")
        if not isinstance(self.coarse_width_px, int) or self.coarse_width_px < 8:
            raise InputError(f"coarse_width_px: expected an int >= 8, got {self.coarse_width_px!r}")
        if self.kernel not in ("auto", "c", "torch"):
            raise InputError(f"kernel: expected 'auto', 'c' or 'torch', got {self.kernel!r}")
        if self.prefilter not in ("xsobel", "none"):
            raise InputError(f"prefilter: expected 'xsobel' or 'none', got {self.prefilter!r}")
        if not 0 <= real_or_nan(self.uniqueness_ratio) < 10:
            raise InputError(f"uniqueness_ratio: expected a value in [0, 10), got {self.uniqueness_ratio!r}")
        if self.lr_max_diff_px is not None and not real_or_nan(self.lr_max_diff_px) >= 0:
            raise InputError(f"lr_max_diff_px: expected None or a value >= 0, got {self.lr_max_diff_px!r}")
        if not isinstance(self.max_num_disparities, int) or self.max_num_disparities < 2:
            raise InputError(f"max_num_disparities: expected an int >= 2, got {self.max_num_disparities!r}")
        share = self.in_view_detached_tail_share
        if share is not None and (isinstance(share, bool) or not isinstance(share, (int, float))
                                  or not 0 <= share < 0.5):
            raise InputError(f"in_view_detached_tail_share: expected None or a share in [0, 0.5), got {share!r}")
        share = self.in_view_own_min_valid_share
        if isinstance(share, bool) or not isinstance(share, (int, float)) or not 0 <= share <= 1:
            raise InputError(f"in_view_own_min_valid_share: expected a share in [0, 1], got {share!r}")
        if self.in_view_margin not in ("object", "pair"):
            raise InputError(f"in_view_margin: expected 'object' or 'pair', got {self.in_view_margin!r}")
        check_percentiles(self.range_percentiles, "range_percentiles")
        for name in ("prefilter_cap", "texture_threshold", "range_margin_px", "range_margin_fraction"):
            # 1e308 failed late, an overflow of the kernel's texture_min
            if not 0 <= real_or_nan(getattr(self, name)) <= 1e6:
                raise InputError(f"{name}: expected a value from 0 to 1e6, got {getattr(self, name)!r}")
        for name in ("smoothing_penalties", "retry_smoothing_penalties"):
            penalties = getattr(self, name)
            pair = isinstance(penalties, (tuple, list)) and len(penalties) == 2 and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) for v in penalties)
            if penalties is not None and not (pair and 0 <= penalties[0] <= penalties[1] < float("inf")):
                raise InputError(f"{name}: expected None or (P1, P2) with 0 <= P1 <= P2, got {penalties!r}")
        if not isinstance(self.smoothing_max_reduction, int) or self.smoothing_max_reduction < 1:
            raise InputError(f"smoothing_max_reduction: expected an int >= 1, got {self.smoothing_max_reduction!r}")
        weight = self.smoothing_intensity_weight
        if isinstance(weight, bool) or not isinstance(weight, (int, float)) or not 0 <= weight < float("inf"):
            raise InputError(f"smoothing_intensity_weight: expected a finite value >= 0, got {weight!r}")
        if not real_or_nan(self.smoothing_min_residual_levels) >= 0:
            raise InputError(f"smoothing_min_residual_levels: expected a value >= 0, got "
                             f"{self.smoothing_min_residual_levels!r}")
        if not isinstance(self.margin_px, int) or not 0 <= self.margin_px < 2**31:
            raise InputError(f"margin_px: expected an int from 0 to 2^31 - 1, got {self.margin_px!r}")
        check_real(self.fallback_max_disparity_fraction, "fallback_max_disparity_fraction", 0.0, 1.0, low_open=True)
        check_count(self.min_range_inliers, "min_range_inliers")  # 0 counts as 1: a range needs a sample
        check_count(self.min_range_pixels, "min_range_pixels")


class DisparityRange(NamedTuple):
    """Per-pair search range ``[min_disparity_px, min_disparity_px + pair_num_disparities)``: ``(B,)`` int64
    each; ``num_disparities`` is the batch's largest count, the depth of the shared cost volume (a pair's
    disparities past its own count get no cost, so its result does not depend on its batch). Without
    ``pair_num_disparities`` every pair searches ``num_disparities``. ``in_view_top_px`` ``(B,)`` int64
    (optional): the largest disparity the in-view rule allows for, at most the range's top
    (``DenseConfig.in_view_detached_tail_share``); ``object_in_view_top_px`` ``(B, N)`` int64 (optional): each
    kept object's own (``DenseConfig.in_view_per_object``)."""

    min_disparity_px: torch.Tensor
    num_disparities: int
    pair_num_disparities: torch.Tensor | None = None
    in_view_top_px: torch.Tensor | None = None
    object_in_view_top_px: torch.Tensor | None = None


@dataclass(frozen=True)
class RepeatedObjects:
    """The kept objects that repeat themselves along the rows (a fence, a railing, a grate) and whether each was
    settled on one alias (:mod:`svs_torch.depth.alias_choice`).

    Attributes:
        period_px: ``(B, N)`` int64, each object's period along the rows, input pixels; 0: it does not repeat (or
            its pair was not tested).
        disparity_px: ``(B, N)`` float, the shift its whole region fits best within the range searched, input
            pixels, where ``fitted`` (0 elsewhere). Its aliases lie whole periods from it.
        fitted: ``(B, N)`` bool, the objects whose whole region fits a shift (not: no pixel, or none in view).
        settled: ``(B, N)`` bool, the repeated objects measured again over the one period about that shift; a
            repeated object not settled lost its pixels (its alias was not told, or its windows lay on another).
    """

    period_px: torch.Tensor
    disparity_px: torch.Tensor
    fitted: torch.Tensor
    settled: torch.Tensor

    def unranged(self, ranged: torch.Tensor) -> torch.Tensor:
        """``(B, N)`` bool: the repeated objects not ``ranged`` ``(B, N)`` bool (an object's depth ``valid``)."""
        return (self.period_px > 0) & ~ranged

    @staticmethod
    def none(objects: torch.Tensor, dtype: torch.dtype) -> RepeatedObjects:
        """No object of ``objects`` ``(B, N, H, W)`` repeats; ``disparity_px`` in ``dtype`` (the views')."""
        shape, device = objects.shape[:2], objects.device
        none = torch.zeros(shape, dtype=torch.bool, device=device)
        return RepeatedObjects(torch.zeros(shape, dtype=torch.int64, device=device),
                               torch.zeros(shape, dtype=dtype, device=device), none, none)


@dataclass(frozen=True)
class DenseDisparity:
    """Dense disparity of the left view, ``x_right = x_left − d``.

    Attributes:
        disparity_px: ``(B, 1, H, W)`` sub-pixel disparity, 0 where not valid.
        valid: ``(B, 1, H, W)`` bool: inside the searched crop and every rejection passed.
        min_disparity_px: ``(B,)`` int64, the range searched: ``[min, min + pair_num_disparities)``.
        num_disparities: the batch's largest count D (the depth of the shared cost volume).
        crop_xywh: ``(B, 4)`` int64, the searched box of each pair (x0, y0, width, height), pixels; every
            valid pixel lies inside it.
        pair_num_disparities: ``(B,)`` int64, each pair's own count.
        in_view_top_px: ``(B,)`` int64 or None: the largest disparity the in-view rule allows for
            (``DisparityRange.in_view_top_px``); None: the top of the range searched.
        object_in_view_top_px: ``(B, N)`` int64 or None: each kept object's own, in the order of the objects the
            range was found for (``DenseConfig.in_view_per_object``); None: ``in_view_top_px`` for every object.
        repeated: :class:`RepeatedObjects` of the kept objects where the whole-object alias check ran
            (``DepthConfig.alias_check_min_period_peak``); None where it did not.
    """

    disparity_px: torch.Tensor
    valid: torch.Tensor
    min_disparity_px: torch.Tensor
    num_disparities: int
    crop_xywh: torch.Tensor
    pair_num_disparities: torch.Tensor
    in_view_top_px: torch.Tensor | None = None
    object_in_view_top_px: torch.Tensor | None = None
    repeated: RepeatedObjects | None = None
