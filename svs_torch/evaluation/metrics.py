"""Scoring pipeline results against ground truth, per pair (the paper's Table 1 rules, Sec. 4, Eq. (9)).

Truth: the kept regions of the left segmentation are the objects; an object's true distance is the median GT
depth ``Z = f·B / (d + doffs)`` over its region's pixels with known disparity (the lower median, as
``torch.median``); true R_min / R_max are the nearest / farthest object with a truth. The estimate is the
pipeline's own (its range rule's R_min / R_max and per-object medians), taken only for a pair whose status is
OK. Accuracy is Eq. (9), ``(1 − |real − est| / real) · 100``, floored at 0; a missing estimate (failed pair,
object without depth) scores 0 %, so failures are counted, never hidden.

Pairs without a measured calibration (``StereoBatch.calibrated`` False: most Middlebury 2005/2006 scenes,
2003 Cones, 2001, KITTI, aloe) are scored with a nominal calibration (:func:`with_nominal_calibration`) for
truth and estimate alike: with doffs 0 both depths scale with f·B, so Eq. (9) measures the disparity-derived
depth consistently, whatever f·B is; their metres are nominal.

Disparity errors (pixels, in the pair's working image):

* dense: ``|d_dense − d_GT|`` over the kept regions where both are valid, for pairs ranged on their raw rows
  (the dense map of a pair rectified from F is in rectified pixels, which GT does not share: null there; a
  row-aligned pair's stays in the left view's);
* sparse: ``|(x_left − x_right) − d_GT(x_left)|`` over the RANSAC inliers with GT at the rounded left point;
  ``inlier_precision`` is the share of those inliers whose right point lies within 1 px of the true one in
  both x and y (a correct correspondence, not only a correct disparity).

The standard stereo metrics of the dense map (Middlebury's bad-t, avgerr, rms, A-quantiles and KITTI's D1, each
with its density, errors in the data's native pixels) are :mod:`.stereo_metrics`'; :class:`PairEvaluation`
carries them as ``<scope>_<metric>`` fields and each object's in its ``objects`` entry.

Medians are lower medians; shares are in [0, 1]. Nothing here is differentiable (medians of hard selections,
status-gated estimates): these are reports, not losses.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import torch

from ..core.checks import InputError, check_instance
from ..core.types import Segmentation, StereoBatch
from ..depth.quantiles import kept_region_lower_median
from ..pipeline import PipelineResult, PipelineStatus
from .disparity_errors import (DisparityErrors, _error_fields, check_result_of, dense_disparity_errors,
                               disparity_map_errors, sparse_disparity_errors)
from .stereo_metrics import StereoMetrics, measured_regions, metric_values, pair_map_metrics

__all__ = [
    "DisparityErrors", "NOMINAL_BASELINE_M", "NOMINAL_FOCAL_PX", "ObjectTruth", "PairEstimate", "PairEvaluation",
    "PairScore", "UNRUN_STATUSES", "accuracy_pct", "dense_disparity_errors", "disparity_map_errors",
    "estimates_from_result", "evaluate_result", "measured_regions", "object_truth", "score_pair",
    "sparse_disparity_errors", "with_nominal_calibration"
]


#: Nominal calibration for pairs without a measured one: Middlebury 2005/2006 third size, f = 3740 / 3 px and
#: B = 160 mm (MANIFEST §1), doffs 0. Any positive f·B gives the same Eq. (9) accuracy (module docstring).
NOMINAL_FOCAL_PX, NOMINAL_BASELINE_M = 3740 / 3, 0.160


def with_nominal_calibration(batch: StereoBatch) -> StereoBatch:
    """``batch`` with every pair that is not ``calibrated`` given a nominal calibration and marked calibrated, so
    its ground truth has a depth; calibrated pairs are unchanged. The nominal one is Middlebury's (f 3740 / 3 px,
    B 0.160 m), but a KITTI pair (its name starts with ``kitti``) keeps the focal and baseline its loader gave
    (KITTI's rig, MANIFEST §4): its metres are then a street's, and a rule that reads the baseline in metres (the
    ground plane's camera height, :mod:`svs_torch.segmentation.ground_plane`) sees a car's rig. So does OpenCV's
    full-size Aloe (``opencv/aloe``): its loader gives Middlebury's nominal rig at full size (f 3740 px), and the
    third size's focal put it 3 times nearer than ``estimate`` and the third-size Aloe do (1.8 against 5.4 m, an
    audit). doffs is 0 either way. Apply it at the input size, before any resampling (which scales focal and
    doffs)."""
    check_instance(batch, "batch", StereoBatch)
    keep = batch.calibrated
    # A batch may have no names (StereoBatch.from_images' default): none of its pairs is then KITTI's or Aloe's.
    names = batch.names or ("",) * batch.batch_size
    own_rig = keep | torch.tensor([name.startswith(("kitti", "opencv/")) for name in names], dtype=torch.bool,
                                  device=keep.device)
    return dataclasses.replace(
        batch,
        focal_px=torch.where(own_rig, batch.focal_px, torch.full_like(batch.focal_px, NOMINAL_FOCAL_PX)),
        baseline_m=torch.where(own_rig, batch.baseline_m, torch.full_like(batch.baseline_m, NOMINAL_BASELINE_M)),
        doffs_px=torch.where(keep, batch.doffs_px, torch.zeros_like(batch.doffs_px)),
        calibrated=torch.ones_like(keep))


@dataclass(frozen=True)
class ObjectTruth:
    """The true distance of each kept left region. All ``(B, N)``, slot n is ``kept_labels[:, n]``.

    Attributes:
        depth_m: median GT depth over the region's pixels with known depth, metres; 0 where not ``valid``.
        num_px: int64, those pixels.
        valid: bool, the slot holds a region with at least one such pixel.
    """

    depth_m: torch.Tensor
    num_px: torch.Tensor
    valid: torch.Tensor


def object_truth(batch: StereoBatch, segmentation: Segmentation) -> ObjectTruth:
    """True distances of the kept regions of ``segmentation`` (the left view of ``batch``), batched. No gradient:
    a target (the README's training loss differentiated through it too, and the focal length's gradient cancelled,
    0.015 → 5e-10; an audit).

    Raises:
        InputError: the batch has no ground truth.
    """
    check_instance(batch, "batch", StereoBatch)
    check_instance(segmentation, "segmentation", Segmentation, ("labels", "kept_labels"))
    depth, known = batch.ground_truth_depth_m()  # (B, 1, H, W) each
    median, count = kept_region_lower_median(depth.detach(), known, segmentation.labels, segmentation.kept_labels)
    return ObjectTruth(depth_m=median, num_px=count, valid=count > 0)


@dataclass(frozen=True)
class PairEstimate:
    """What the pipeline reports for one pair, in plain numbers: ``status`` name, and R_min / R_max and each
    kept slot's median depth where the pair is OK and the value valid (None elsewhere)."""

    status: str
    r_min_m: float | None
    r_max_m: float | None
    objects_m: list[float | None]


def estimates_from_result(result: PipelineResult) -> list[PairEstimate]:
    """The :class:`PairEstimate` of every pair of a :class:`~svs_torch.pipeline.PipelineResult`."""
    check_instance(result, "result", PipelineResult)
    rng, objects = result.depth.range, result.depth.objects
    rows = zip(result.status.tolist(), rng.valid.tolist(), rng.r_min_m.tolist(), rng.r_max_m.tolist(),
               objects.depth_median_m.tolist(), objects.valid.tolist())
    estimates = []
    for status, range_ok, r_min, r_max, medians, valid in rows:
        ok = status == PipelineStatus.OK
        estimates.append(PairEstimate(PipelineStatus(status).name, r_min if ok and range_ok else None,
                                      r_max if ok and range_ok else None,
                                      [m if ok and v else None for m, v in zip(medians, valid)]))
    return estimates


def accuracy_pct(real: float, estimated: float | None) -> float:
    """Eq. (9): ``(1 − |real − estimated| / real) · 100``; a missing estimate (or a worse than 0 %) counts 0, so a
    mean over pairs is not dragged below 0 by one wild estimate (:func:`svs_torch.depth.accuracy_percent`, the
    differentiable tensor form, is not floored).

    Raises:
        InputError: ``real`` is not a finite positive distance (0 divided by zero; a negative one scored above
            100 %), ``estimated`` neither None nor a real number.
    """
    try:
        number = math.nan if isinstance(real, bool) else float(real)
    except (TypeError, ValueError):
        number = math.nan
    if not 0 < number < math.inf:
        raise InputError(f"real: expected a finite positive distance, got {real!r}")
    if estimated is None:
        return 0.0
    # The numbers, not the arguments: a string float() reads ('2.0'), or a one-element tensor, failed in the
    # arithmetic below with a TypeError, and a bool estimate scored as 1 m.
    if isinstance(estimated, (bool, str)) or not hasattr(estimated, "__float__"):
        raise InputError(f"estimated: expected None or a distance, got {estimated!r}")
    return max(0.0, (1 - abs(number - float(estimated)) / number) * 100)


@dataclass(frozen=True)
class PairScore:
    """Eq. (9) scores of one pair; the accuracies are None when no kept object has a truth.

    Attributes:
        real_r_min_m, real_r_max_m: nearest / farthest object's true distance.
        acc_r_min_pct, acc_r_max_pct: Eq. (9) of the estimated R_min / R_max against them.
        acc_objects_pct: mean Eq. (9) over the objects with a truth, each against its own slot's estimate.
        objects: per slot with a truth: ``{"slot", "real_m", "estimated_m", "acc_pct"}``; :func:`evaluate_result`
            adds ``"dropped"`` under the dense rule: a kept region the depth stage dropped as unmeasured
            (``PipelineResult.dropped_objects``), which scores 0 % like any object left without a distance.
    """

    real_r_min_m: float | None
    real_r_max_m: float | None
    acc_r_min_pct: float | None
    acc_r_max_pct: float | None
    acc_objects_pct: float | None
    objects: list[dict] = field(default_factory=list)

    @property
    def num_objects(self) -> int:
        return len(self.objects)


def score_pair(truth: Sequence[tuple[int, float]], estimate: PairEstimate) -> PairScore:
    """Score one pair: ``truth`` is ``[(slot, true distance m), ...]`` for the kept slots with a truth."""
    check_instance(estimate, "estimate", PairEstimate, ("r_min_m", "r_max_m", "objects_m"))  # None: AttributeError
    if not truth:
        return PairScore(None, None, None, None, None)
    real = [depth for _, depth in truth]
    objects = []
    for slot, depth in truth:
        estimated = estimate.objects_m[slot] if slot < len(estimate.objects_m) else None
        objects.append({"slot": slot, "real_m": depth, "estimated_m": estimated,
                        "acc_pct": accuracy_pct(depth, estimated)})
    return PairScore(min(real), max(real), accuracy_pct(min(real), estimate.r_min_m),
                     accuracy_pct(max(real), estimate.r_max_m),
                     sum(o["acc_pct"] for o in objects) / len(objects), objects)


def truth_list(truth: ObjectTruth, index: int) -> list[tuple[int, float]]:
    """``[(slot, true distance m), ...]`` of pair ``index``, for :func:`score_pair`."""
    return [(slot, depth) for slot, (depth, ok) in
            enumerate(zip(truth.depth_m[index].tolist(), truth.valid[index].tolist())) if ok]


#: Statuses of pairs the pipeline did not run on (their ``time_s`` is 0; a results store runs them again on
#: resume: :data:`svs_torch.evaluation.store.RETRIED_STATUSES`): unreadable, too small, or a run that raised.
UNRUN_STATUSES = ("BAD_INPUT", "TOO_SMALL", "ERROR")


@dataclass(frozen=True)
class PairEvaluation:
    """Everything measured on one pair: identity, outcome, Eq. (9) scores, disparity errors, counts, time.

    ``status`` is the pipeline's (:class:`~svs_torch.pipeline.PipelineStatus` name) or, for a pair it did not
    run on, ``BAD_INPUT`` (unreadable entry), ``TOO_SMALL`` or ``ERROR`` (an exception, in ``reason``).
    Metric fields are None where they do not exist (no ground truth, paper rule without dense, failed pair).
    ``objects`` lists the per-object scores (:class:`PairScore`); a pair without ground truth lists its ranged
    objects, ``real_m`` and ``acc_pct`` None; ``num_objects`` counts the list. ``time_s`` is the pair's share of
    its batch's pipeline time (the batch's time over its pairs, as ``estimate --pairs`` rows give it).
    ``calibrated``: the data's own calibration (False: scored with the nominal one); ``calibration``: the values
    the metres use and their source (:func:`~svs_torch.data.calibration_record`).
    """

    name: str
    status: str
    reason: str | None = None
    calibrated: bool | None = None
    calibration: dict | None = None
    has_truth: bool = False
    r_min_m: float | None = None
    r_max_m: float | None = None
    real_r_min_m: float | None = None
    real_r_max_m: float | None = None
    acc_r_min_pct: float | None = None
    acc_r_max_pct: float | None = None
    acc_objects_pct: float | None = None
    num_objects: int = 0
    dense_error_median_px: float | None = None
    dense_within_1px: float | None = None
    dense_within_3px: float | None = None
    dense_num_px: int = 0
    sparse_error_median_px: float | None = None
    sparse_within_1px: float | None = None
    sparse_within_3px: float | None = None
    inlier_precision: float | None = None
    sparse_num_points: int = 0
    num_keypoints_left: int = 0
    num_keypoints_right: int = 0
    num_matches: int = 0
    num_inliers: int = 0
    rectified: bool = False
    time_s: float = 0.0
    # Stereo metrics of the dense map (stereo_metrics.py; STEREO_SCOPES): over every GT pixel of the frame
    # (map_*) or the kept regions (kept_*), all or non-occluded GT; errors in the data's native pixels
    # (metric_px_scale = native / working width).
    metric_px_scale: float | None = None
    map_all_density: float | None = None
    map_all_bad0_5_pct: float | None = None
    map_all_bad1_pct: float | None = None
    map_all_bad2_pct: float | None = None
    map_all_bad4_pct: float | None = None
    map_all_avgerr_px: float | None = None
    map_all_rms_px: float | None = None
    map_all_a50_px: float | None = None
    map_all_a90_px: float | None = None
    map_all_a95_px: float | None = None
    map_all_a99_px: float | None = None
    map_all_d1_pct: float | None = None
    map_all_num_px: int | None = None
    map_nocc_density: float | None = None
    map_nocc_bad0_5_pct: float | None = None
    map_nocc_bad1_pct: float | None = None
    map_nocc_bad2_pct: float | None = None
    map_nocc_bad4_pct: float | None = None
    map_nocc_avgerr_px: float | None = None
    map_nocc_rms_px: float | None = None
    map_nocc_a50_px: float | None = None
    map_nocc_a90_px: float | None = None
    map_nocc_a95_px: float | None = None
    map_nocc_a99_px: float | None = None
    map_nocc_d1_pct: float | None = None
    map_nocc_num_px: int | None = None
    kept_all_density: float | None = None
    kept_all_bad0_5_pct: float | None = None
    kept_all_bad1_pct: float | None = None
    kept_all_bad2_pct: float | None = None
    kept_all_bad4_pct: float | None = None
    kept_all_avgerr_px: float | None = None
    kept_all_rms_px: float | None = None
    kept_all_a50_px: float | None = None
    kept_all_a90_px: float | None = None
    kept_all_a95_px: float | None = None
    kept_all_a99_px: float | None = None
    kept_all_d1_pct: float | None = None
    kept_all_num_px: int | None = None
    kept_nocc_density: float | None = None
    kept_nocc_bad0_5_pct: float | None = None
    kept_nocc_bad1_pct: float | None = None
    kept_nocc_bad2_pct: float | None = None
    kept_nocc_bad4_pct: float | None = None
    kept_nocc_avgerr_px: float | None = None
    kept_nocc_rms_px: float | None = None
    kept_nocc_a50_px: float | None = None
    kept_nocc_a90_px: float | None = None
    kept_nocc_a95_px: float | None = None
    kept_nocc_a99_px: float | None = None
    kept_nocc_d1_pct: float | None = None
    kept_nocc_num_px: int | None = None
    objects: list[dict] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.status == "OK"


def _stereo_fields(scopes: dict[str, StereoMetrics], index: int) -> dict:
    return {f"{scope}_{key}": value for scope, metrics in scopes.items()
            for key, value in metric_values(metrics, index).items()}


def evaluate_result(batch: StereoBatch, result: PipelineResult, time_s: float = 0.0,
                    calibrated: Sequence[bool] | None = None,
                    px_scale: Sequence[float] | None = None) -> list[PairEvaluation]:
    """Score every pair of a pipeline run on ``batch`` (with or without ground truth).

    Args:
        batch: the batch the pipeline ran on (GT resampled with it); give it the nominal calibration first
            (:func:`with_nominal_calibration`) so pairs without a measured one have a depth truth.
        result: :func:`~svs_torch.pipeline.estimate_obstacle_depth`'s result on it.
        time_s: each pair's pipeline time, seconds.
        calibrated: per pair, whether the calibration was the data's own (before the nominal one).
        px_scale: per pair, the data's native width over the width the pipeline ran at (the stereo metrics'
            errors are in native pixels, :mod:`.stereo_metrics`); None: 1 (the pipeline ran at native size).
    """
    _check_evaluated(batch, result, calibrated, px_scale)
    estimates = estimates_from_result(result)
    has_gt = batch.disparity_px is not None
    truth = object_truth(batch, measured_regions(result)) if has_gt else None
    dense = dense_disparity_errors(batch, result)
    sparse = sparse_disparity_errors(batch, result)
    scale = None if px_scale is None else torch.tensor(list(px_scale), dtype=batch.left.dtype,
                                                       device=batch.left.device)
    scopes, per_object = pair_map_metrics(batch, result, scale)
    dropped = result.dropped_objects.tolist() if result.dropped_objects is not None else None
    keypoints = result.num_keypoints.tolist()
    counts = zip(result.num_matches.tolist(), result.num_inliers.tolist(), result.rectified.tolist())
    evaluations = []
    for i, (estimate, (matches, inliers, rectified)) in enumerate(zip(estimates, counts)):
        score = score_pair(truth_list(truth, i), estimate) if truth is not None else PairScore(None, None, None,
                                                                                                 None, None)
        has_truth = has_gt and bool(batch.disparity_valid[i].any())
        if has_truth:
            objects = [dict(o, **metric_values(per_object[o["slot"]], i)) if per_object else o
                       for o in score.objects]
        else:  # its ranged objects, unscored (a camera's pair read as having none: an audit)
            objects = [{"slot": slot, "real_m": None, "estimated_m": depth, "acc_pct": None}
                       for slot, depth in enumerate(estimate.objects_m) if depth is not None]
        if dropped is not None:  # scored as an object without a distance (stereo_metrics.measured_regions)
            objects = [dict(o, dropped=dropped[i][o["slot"]]) for o in objects]
        evaluations.append(PairEvaluation(
            name=batch.names[i] if batch.names else str(i), status=estimate.status,
            calibrated=None if calibrated is None else bool(calibrated[i]), has_truth=has_truth,
            r_min_m=estimate.r_min_m, r_max_m=estimate.r_max_m, real_r_min_m=score.real_r_min_m,
            real_r_max_m=score.real_r_max_m, acc_r_min_pct=score.acc_r_min_pct, acc_r_max_pct=score.acc_r_max_pct,
            acc_objects_pct=score.acc_objects_pct, num_objects=len(objects),
            dense_num_px=int(dense.count[i]) if dense is not None else 0,
            sparse_num_points=int(sparse.count[i]) if sparse is not None else 0,
            num_keypoints_left=keypoints[i][0], num_keypoints_right=keypoints[i][1], num_matches=matches,
            num_inliers=inliers, rectified=bool(rectified), time_s=time_s, objects=objects,
            # Per pair, not per batch: a pair without truth had a scale when batched with a scene (an audit)
            metric_px_scale=(1.0 if px_scale is None else float(px_scale[i])) if scopes and has_truth else None,
            **_error_fields(dense, i, "dense"), **_error_fields(sparse, i, "sparse"), **_stereo_fields(scopes, i)))
    return evaluations


def _check_evaluated(batch: StereoBatch, result: PipelineResult, calibrated: Sequence[bool] | None,
                     px_scale: Sequence[float] | None) -> None:
    """:func:`evaluate_result`'s arguments: a result of a run on this batch (its pairs, its size), one value per pair
    (a result of another batch failed deep inside torch, or scored pairs against another's truth)."""
    check_instance(batch, "batch", StereoBatch)
    check_instance(result, "result", PipelineResult)
    check_result_of(batch, result)
    b = batch.batch_size
    for name, values in (("calibrated", calibrated), ("px_scale", px_scale)):
        if values is not None and len(values) != b:
            raise InputError(f"{name}: expected {b} values, one per pair, got {len(values)}")
