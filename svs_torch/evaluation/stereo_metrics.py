"""The metrics stereo papers cite, batched over dense disparity maps: the Middlebury SDK set and KITTI's D1.

Definitions (``../shared/REFERENCE.md``, "Standard stereo metrics and formats"; MiddEval3 SDK ``evaldisp.cpp``;
KITTI stereo devkit). The *evaluated* pixels of a pair are those with a known GT disparity inside a mask: every
such pixel (Middlebury's "all", KITTI's "occ") or only the non-occluded ones (``mask0nocc.png`` = 255, KITTI's
"noc"). The *covered* pixels are the evaluated ones where the estimate is valid. Then, with the error
``e = |d − d_GT|`` in the data's native pixels:

* ``density``: covered / evaluated, in [0, 1]: every other number is measured at this density;
* ``bad-t``: percent of the covered pixels with ``e > t``, t = 0.5, 1, 2, 4 px;
* ``avgerr``, ``rms``: mean of ``e`` and root of the mean of ``e²`` over the covered pixels, px;
* ``A50 / A90 / A95 / A99``: error quantiles: the smallest ``e`` such that at least q % of the covered pixels
  have an error no larger (the inverse of the empirical distribution; ``numpy.quantile(method="inverted_cdf")``);
* ``D1``: percent of the covered pixels with ``e > 3`` px and ``e > 5 %`` of the true disparity (KITTI 2015).

Unknown estimates are not filled: the metrics hold at the submitted density, which is always reported with
them (the SDK's evaldisp reports that way too; its columns follow from ours: its ``bad`` is our bad-t × density,
its ``totbad`` adds ``100 · (1 − density)``, its ``avgErr`` is our avgerr). Middlebury's online table and the
KITTI server instead fill a sparse map (background interpolation along rows) and score every pixel; this
pipeline measures only the kept regions, so a filled whole-frame score would grade the fill, not the matcher.
Valid estimates are not clipped to a disparity range (the SDK clips to ``[0, maxdisp]``; the maps here are
already inside their searched range).

Resolution: thresholds hold at the data's own resolution (2 px at full size is 0.5 px at quarter size). When
the map is at another size than the data (the pipeline ran on a resized pair), ``px_scale`` ``(B,)`` turns an
error in the map's pixels into native pixels (``W_native / W_map``): the errors are converted, the thresholds
stay as published. The pixels themselves are then those of the resized grid (each with its nearest GT sample).

Nothing here is differentiable (thresholds, counts, a sort): these are reports.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from ..checks import InputError, check_dtype, check_shape

if TYPE_CHECKING:
    from ..pipeline import PipelineResult
    from ..types import StereoBatch

__all__ = ["BAD_THRESHOLDS_PX", "D1_ABSOLUTE_PX", "D1_RELATIVE", "METRIC_NAMES", "QUANTILES_PCT", "STEREO_FIELDS",
           "STEREO_SCOPES", "StereoMetrics", "dense_map_metrics", "measure_stereo_metrics", "metric_values",
           "object_map_metrics"]

#: Middlebury's bad-pixel thresholds, native pixels.
BAD_THRESHOLDS_PX = (0.5, 1.0, 2.0, 4.0)
#: Middlebury's error quantiles A50 / A90 / A95 / A99, percent.
QUANTILES_PCT = (50, 90, 95, 99)
#: KITTI 2015's D1 outlier: error above 3 px and above 5 % of the true disparity.
D1_ABSOLUTE_PX, D1_RELATIVE = 3.0, 0.05

#: The names of one scope's values (:func:`metric_values`), units in the names (``_pct`` percent, ``_px``
#: native pixels, ``density`` a share, ``num_px`` the evaluated GT pixels).
METRIC_NAMES = ("density", "bad0_5_pct", "bad1_pct", "bad2_pct", "bad4_pct", "avgerr_px", "rms_px", "a50_px",
                "a90_px", "a95_px", "a99_px", "d1_pct", "num_px")
#: Where a pair's dense map is scored: over every GT pixel of the frame (``map``) or only over the kept regions
#: (``kept``, the pixels the pipeline ranges), each with all GT pixels or the non-occluded ones (``nocc``,
#: where the data has a non-occlusion mask).
STEREO_SCOPES = ("map_all", "map_nocc", "kept_all", "kept_nocc")
#: The per-pair result fields of the stereo metrics whose mean over pairs an evaluation's summary reports.
STEREO_FIELDS = tuple(f"{scope}_{name}" for scope in STEREO_SCOPES for name in METRIC_NAMES if name != "num_px")


@dataclass(frozen=True)
class StereoMetrics:
    """Stereo metrics of B maps (module docstring). All ``(B,)`` unless noted; 0 where not ``valid``.

    Attributes:
        density: covered / evaluated pixels (0 where nothing is evaluated).
        num_evaluated, num_covered: int64 pixel counts.
        bad_pct: ``(B, 4)`` bad-0.5 / 1 / 2 / 4, percent of the covered pixels.
        avgerr_px, rms_px: mean and RMS error, native pixels.
        quantile_px: ``(B, 4)`` A50 / A90 / A95 / A99, native pixels.
        d1_pct: KITTI D1, percent of the covered pixels.
        valid: bool, at least one covered pixel.
    """

    density: torch.Tensor
    num_evaluated: torch.Tensor
    num_covered: torch.Tensor
    bad_pct: torch.Tensor
    avgerr_px: torch.Tensor
    rms_px: torch.Tensor
    quantile_px: torch.Tensor
    d1_pct: torch.Tensor
    valid: torch.Tensor


def _check_inputs(disparity_px: torch.Tensor, valid: torch.Tensor, truth_px: torch.Tensor, truth_valid: torch.Tensor,
                  mask: torch.Tensor | None, px_scale: torch.Tensor | None) -> int:
    check_shape(disparity_px, "disparity_px", ["B", 1, "H", "W"])
    check_dtype(disparity_px, "disparity_px", "float")
    shape = list(disparity_px.shape)
    check_shape(truth_px, "truth_px", shape)
    check_dtype(truth_px, "truth_px", "float")
    for name, value in (("valid", valid), ("truth_valid", truth_valid), ("mask", mask)):
        if value is not None:
            check_shape(value, name, shape)
            check_dtype(value, name, "bool")
    b = shape[0]
    if px_scale is not None:
        check_shape(px_scale, "px_scale", [b])
        if not bool(torch.isfinite(px_scale).all() and (px_scale > 0).all()):
            raise InputError(f"px_scale: expected finite positive factors, got {px_scale.tolist()}")
    # A NaN or inf where a value is declared known would poison every sum: name it instead.
    for name, value, known, known_name in (("disparity_px", disparity_px, valid, "valid"),
                                           ("truth_px", truth_px, truth_valid, "truth_valid")):
        if not bool(torch.isfinite(value[known]).all()):
            raise InputError(f"{name}: expected finite values where {known_name} holds, got NaN or inf")
    return b


def measure_stereo_metrics(disparity_px: torch.Tensor, valid: torch.Tensor, truth_px: torch.Tensor,
                   truth_valid: torch.Tensor, mask: torch.Tensor | None = None,
                   px_scale: torch.Tensor | None = None) -> StereoMetrics:
    """Middlebury's and KITTI's metrics of ``B`` disparity maps against their GT (module docstring).

    Args:
        disparity_px: ``(B, 1, H, W)`` estimated disparity of the left view, in the map's pixels.
        valid: ``(B, 1, H, W)`` bool, where the estimate exists (unknown pixels lower the density).
        truth_px, truth_valid: GT disparity ``(B, 1, H, W)`` in the same pixels, and where it is known.
        mask: ``(B, 1, H, W)`` bool, the pixels to evaluate (e.g. non-occluded, or a region); None: all.
            Padding outside a pair's own size must be False in ``truth_valid`` or ``mask``.
        px_scale: ``(B,)`` factor from the map's pixels to the data's native pixels; None: 1.

    Raises:
        InputError: shapes or dtypes other than documented, a non-finite value where it is declared known, a
            scale that is not finite and positive.
    """
    b = _check_inputs(disparity_px, valid, truth_px, truth_valid, mask, px_scale)
    dtype = disparity_px.dtype
    evaluated = truth_valid if mask is None else truth_valid & mask
    covered = (evaluated & valid).reshape(b, -1)
    scale = (torch.ones(b, dtype=dtype, device=disparity_px.device) if px_scale is None
             else px_scale.to(dtype)).view(b, 1)
    truth = truth_px.to(dtype).reshape(b, -1)
    error = torch.where(covered, (disparity_px.reshape(b, -1) - truth).abs() * scale, torch.zeros_like(truth))
    num_evaluated = evaluated.reshape(b, -1).sum(1)
    num_covered = covered.sum(1)
    # Sums in float64: a quarter-million float32 errors lose digits a published table shows.
    denominator = num_covered.clamp(min=1).to(torch.float64)

    def percent(hit: torch.Tensor) -> torch.Tensor:
        return ((hit & covered).sum(1).to(torch.float64) * 100.0 / denominator).to(dtype)

    bad = torch.stack([percent(error > t) for t in BAD_THRESHOLDS_PX], dim=1)
    d1 = percent((error > D1_ABSOLUTE_PX) & (error > D1_RELATIVE * truth.abs() * scale))
    error64 = error.to(torch.float64)
    avgerr = (error64.sum(1) / denominator).to(dtype)
    rms = (error64.square().sum(1) / denominator).sqrt().to(dtype)
    # Inverse empirical CDF: the k-th smallest covered error, k = ceil(q · n) (1-based), in integer arithmetic.
    ordered = torch.where(covered, error, torch.full_like(error, float("inf"))).sort(dim=1).values
    ranks = torch.stack([(q * num_covered + 99) // 100 for q in QUANTILES_PCT], dim=1)  # (B, 4)
    quantiles = ordered.gather(1, (ranks - 1).clamp(min=0, max=max(ordered.shape[1] - 1, 0)))
    ok = num_covered > 0
    quantiles = torch.where(ok.view(b, 1), quantiles, torch.zeros_like(quantiles))
    density = (num_covered.to(torch.float64) / num_evaluated.clamp(min=1).to(torch.float64)).to(dtype)
    return StereoMetrics(density=density, num_evaluated=num_evaluated, num_covered=num_covered, bad_pct=bad,
                         avgerr_px=avgerr, rms_px=rms, quantile_px=quantiles, d1_pct=d1, valid=ok)


def metric_values(metrics: StereoMetrics, index: int) -> dict[str, float | int | None]:
    """Pair ``index``'s values under :data:`METRIC_NAMES`: all None where nothing was evaluated (no GT in the
    mask), only ``density`` (0) and ``num_px`` where nothing evaluated was covered."""
    evaluated = int(metrics.num_evaluated[index])
    values: dict[str, float | int | None] = dict.fromkeys(METRIC_NAMES)
    if evaluated == 0:
        return values
    values["num_px"] = evaluated
    values["density"] = float(metrics.density[index])
    if bool(metrics.valid[index]):
        bad, quantiles = metrics.bad_pct[index].tolist(), metrics.quantile_px[index].tolist()
        values.update(zip(("bad0_5_pct", "bad1_pct", "bad2_pct", "bad4_pct"), bad))
        values.update(zip(("a50_px", "a90_px", "a95_px", "a99_px"), quantiles))
        values.update(avgerr_px=float(metrics.avgerr_px[index]), rms_px=float(metrics.rms_px[index]),
                      d1_pct=float(metrics.d1_pct[index]))
    return values


def _raw_pixels(batch: StereoBatch, result: PipelineResult) -> torch.Tensor | None:
    """``(B, 1, H, W)`` bool: the pixels where the dense map and the GT share a grid (pairs ranged on their raw
    rows: a rectified pair's map is in rectified pixels), or None when there is nothing to score."""
    dense = result.dense
    if dense is None or batch.disparity_px is None or dense.disparity_px.shape != batch.disparity_px.shape:
        return None
    return (~result.rectified).view(-1, 1, 1, 1).expand_as(batch.disparity_valid)


def dense_map_metrics(batch: StereoBatch, result: PipelineResult,
                      px_scale: torch.Tensor | None = None) -> dict[str, StereoMetrics]:
    """:func:`measure_stereo_metrics` of the pipeline's dense map in each of :data:`STEREO_SCOPES` the data
    has (``*_nocc`` only with ``batch.disparity_nonoccluded``); {} under the paper rule or without GT. A
    rectified pair evaluates no pixel (its metrics are null): its map is not in the GT's pixels."""
    raw = _raw_pixels(batch, result)
    if raw is None:
        return {}
    kept = result.segmentation.left.kept_mask
    masks = {"map_all": raw, "kept_all": raw & kept}
    if batch.disparity_nonoccluded is not None:
        nonoccluded = raw & batch.disparity_nonoccluded
        masks.update(map_nocc=nonoccluded, kept_nocc=nonoccluded & kept)
    dense = result.dense
    return {scope: measure_stereo_metrics(dense.disparity_px, dense.valid, batch.disparity_px,
                                          batch.disparity_valid, masks[scope], px_scale)
            for scope in STEREO_SCOPES if scope in masks}


def object_map_metrics(batch: StereoBatch, result: PipelineResult,
                       px_scale: torch.Tensor | None = None) -> list[StereoMetrics]:
    """:func:`measure_stereo_metrics` of the dense map over each kept object's region (all GT pixels), one
    per kept slot (slot n is ``kept_labels[:, n]``); [] where :func:`dense_map_metrics` is {}. A loop over
    the few slots, each batched over the pairs."""
    raw = _raw_pixels(batch, result)
    if raw is None:
        return []
    segmentation, dense = result.segmentation.left, result.dense
    out = []
    for slot in range(segmentation.kept_labels.shape[1]):
        label = segmentation.kept_labels[:, slot].view(-1, 1, 1, 1)
        region = raw & (segmentation.labels == label) & (label > 0)
        out.append(measure_stereo_metrics(dense.disparity_px, dense.valid, batch.disparity_px,
                                          batch.disparity_valid, region, px_scale))
    return out
