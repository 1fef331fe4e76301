"""Disparity errors against the ground truth, for the dense map and for the sparse inliers: mean and median
absolute error, the share of bad pixels, over the pixels both know. In the pixels the pipeline ran at (a resized
pair's, with its GT resampled): the stereo metrics (:mod:`.stereo_metrics`) are the ones in the data's native
pixels, at the published thresholds.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..core.checks import InputError, check_finite_where, check_instance
from ..core.types import StereoBatch
from ..depth.quantiles import masked_lower_median
from ..pipeline import PipelineResult
from .stereo_metrics import _check_inputs

__all__ = ["DisparityErrors", "check_result_of", "dense_disparity_errors", "disparity_map_errors", "map_in_left_pixels",
           "sparse_disparity_errors"]


@dataclass(frozen=True)
class DisparityErrors:
    """Absolute disparity errors against GT, per pair. All ``(B,)``.

    Attributes:
        median_px: lower median of the errors, pixels (0 where not ``valid``).
        within_1px, within_2px, within_3px: share of the errors at most 1 / 2 / 3 px (1 − Middlebury's bad-1
            / bad-2 / bad-3).
        count: int64, the pixels or points compared.
        precision: share of correct correspondences (sparse only: within 1 px in x and y), else None.
        valid: bool, at least one comparison.
    """

    median_px: torch.Tensor
    within_1px: torch.Tensor
    within_2px: torch.Tensor
    within_3px: torch.Tensor
    count: torch.Tensor
    valid: torch.Tensor
    precision: torch.Tensor | None = None


def _errors(error: torch.Tensor, mask: torch.Tensor, correct: torch.Tensor | None = None) -> DisparityErrors:
    """Statistics of ``error`` ``(B, P)`` where ``mask`` ``(B, P)`` holds."""
    median, count = masked_lower_median(error, mask)
    denominator = count.clamp(min=1).to(error.dtype)

    def share(hit: torch.Tensor) -> torch.Tensor:
        return (hit & mask).sum(-1).to(error.dtype) / denominator

    return DisparityErrors(median, share(error <= 1.0), share(error <= 2.0), share(error <= 3.0), count, count > 0,
                           None if correct is None else share(correct))


def disparity_map_errors(disparity_px: torch.Tensor, valid: torch.Tensor, truth_px: torch.Tensor,
                         truth_valid: torch.Tensor, mask: torch.Tensor | None = None) -> DisparityErrors:
    """Errors of any dense disparity map ``(B, 1, H, W)`` (the pipeline's, or a rival's such as ``StereoBM``'s)
    against the GT ``truth_px`` where ``mask`` (None: every pixel, as in
    :func:`~svs_torch.evaluation.measure_stereo_metrics`), the map's ``valid`` and ``truth_valid`` all hold (bool
    maps of the same shape). Only ``median_px`` carries gradients (to ``disparity_px`` and ``truth_px`` at the
    median pixel); the shares and counts are thresholds and sums of bools."""
    _check_inputs(disparity_px, valid, truth_px, truth_valid, mask, None)  # each argument by its own name
    compared = valid & truth_valid if mask is None else mask & valid & truth_valid
    # A NaN compared gave a NaN median and counted as wrong at every threshold, in silence (measure_stereo_metrics
    # names it): named as there.
    check_finite_where(disparity_px, "disparity_px", compared, "valid")
    check_finite_where(truth_px, "truth_px", compared, "truth_valid")
    error = (disparity_px - truth_px.to(disparity_px.dtype)).abs()
    return _errors(error.flatten(1), compared.flatten(1))


def map_in_left_pixels(result: PipelineResult) -> torch.Tensor:
    """``(B,)`` bool: pairs whose dense map lies on the left view's pixels, the GT's grid: ranged on their raw
    rows, or row-aligned (the row alignment warps the right view alone); F's rectification warps both views.
    Not differentiable (bool)."""
    check_instance(result, "result", PipelineResult, ("rectified",))
    aligned = getattr(result, "row_aligned", None)
    aligned = torch.zeros_like(result.rectified) if aligned is None else aligned
    return ~result.rectified | aligned


def check_result_of(batch: StereoBatch, result: PipelineResult) -> None:
    """``result`` is a run on ``batch``: as many pairs, and its maps of the batch's size. Why: another batch's
    result was scored against this batch's truth in silence (or failed deep inside torch). ``result`` may be a
    stand-in with ``segmentation`` or ``points`` only (as hand-made test cases are)."""
    segmentation = getattr(result, "segmentation", None)
    if segmentation is not None:
        mask = segmentation.left.kept_mask
        pairs, size = mask.shape[0], tuple(mask.shape[-2:])
    else:
        pairs, size = result.points.left.shape[0], batch.size_hw
    if pairs != batch.batch_size or size != batch.size_hw:
        raise InputError(f"result: expected the result of a run on batch ({batch.batch_size} pairs of "
                         f"{batch.size_hw[1]}x{batch.size_hw[0]}), got {pairs} pairs of {size[1]}x{size[0]}")


def dense_disparity_errors(batch: StereoBatch, result: PipelineResult) -> DisparityErrors | None:
    """Dense disparity error over the kept left regions (module docstring); None under the paper rule."""
    check_instance(batch, "batch", StereoBatch)
    check_instance(result, "result", PipelineResult, ("dense", "rectified", "segmentation"))
    check_result_of(batch, result)
    dense = result.dense
    if dense is None or batch.disparity_px is None or dense.disparity_px.shape != batch.disparity_px.shape:
        return None
    b = batch.batch_size
    mask = result.segmentation.left.kept_mask & map_in_left_pixels(result).view(b, 1, 1, 1)
    return disparity_map_errors(dense.disparity_px, dense.valid, batch.disparity_px, batch.disparity_valid, mask)


def sparse_disparity_errors(batch: StereoBatch, result: PipelineResult) -> DisparityErrors | None:
    """Disparity error and precision of the RANSAC inliers (module docstring)."""
    check_instance(batch, "batch", StereoBatch)
    check_instance(result, "result", PipelineResult, ("points", "fundamental"))
    check_result_of(batch, result)
    if batch.disparity_px is None:
        return None
    b, _, height, width = batch.disparity_px.shape
    left, right = result.points.left, result.points.right  # (B, K, 2) each
    column = left[..., 0].round().long().clamp(0, width - 1)
    row = left[..., 1].round().long().clamp(0, height - 1)
    flat = row * width + column  # (B, K)
    truth = batch.disparity_px.reshape(b, -1).gather(1, flat)
    known = batch.disparity_valid.reshape(b, -1).gather(1, flat)
    mask = result.fundamental.inliers & result.points.valid & known
    error = ((left[..., 0] - right[..., 0]) - truth).abs()
    correct = (error <= 1.0) & ((left[..., 1] - right[..., 1]).abs() <= 1.0)
    return _errors(error, mask, correct)


def _error_fields(errors: DisparityErrors | None, index: int, prefix: str) -> dict:
    if errors is None or not bool(errors.valid[index]):
        return {}
    values = {f"{prefix}_error_median_px": float(errors.median_px[index]),
              f"{prefix}_within_1px": float(errors.within_1px[index]),
              f"{prefix}_within_3px": float(errors.within_3px[index])}
    if errors.precision is not None:
        values["inlier_precision"] = float(errors.precision[index])
    return values
