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
           "object_map_metrics", "pair_map_metrics"]

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
    return _measure(disparity_px, valid, truth_px, truth_valid, [mask], px_scale)[0]


def _measure(disparity_px: torch.Tensor, valid: torch.Tensor, truth_px: torch.Tensor, truth_valid: torch.Tensor,
             masks: list[torch.Tensor | None], px_scale: torch.Tensor | None) -> list[StereoMetrics]:
    """:func:`measure_stereo_metrics` for several masks of the same maps. The pixels with both an estimate and
    a GT value (a third of a frame at most, for the pipeline's maps) are gathered once into a flat list grouped
    by pair, and sorted by error once within each pair; a mask's k-th smallest error is where its running count
    of covered pixels along that order reaches k. Full-frame passes over ``(B, H·W)`` cost 30-60 ms each at
    native MiddEval3 Q size on this project's CPU, so each mask makes only the one that counts its pixels."""
    b = _check_inputs(disparity_px, valid, truth_px, truth_valid, None, px_scale)
    for mask in masks:
        if mask is not None:
            check_shape(mask, "mask", list(disparity_px.shape))
            check_dtype(mask, "mask", "bool")
    dtype, device = disparity_px.dtype, disparity_px.device
    pixels = disparity_px[0, 0].numel()
    rows, columns = (truth_valid & valid).reshape(b, -1).nonzero(as_tuple=True)  # grouped by pair, in order
    flat = rows * pixels + columns  # (M,)
    scale = (torch.ones(b, dtype=dtype, device=device) if px_scale is None else px_scale.to(dtype))[rows]
    truth = truth_px.to(dtype).reshape(-1)[flat]
    error = (disparity_px.reshape(-1)[flat] - truth).abs() * scale  # (M,) native pixels
    # Per pixel, the columns every mask sums: one, a hit of each bad-t threshold, a D1 outlier, e, e² (float64:
    # a quarter-million float32 errors lose digits a published table shows).
    error64 = error.to(torch.float64)
    d1_hit = (error > D1_ABSOLUTE_PX) & (error > D1_RELATIVE * truth.abs() * scale)
    features = torch.stack([torch.ones_like(error64), *[(error > t).to(torch.float64) for t in BAD_THRESHOLDS_PX],
                            d1_hit.to(torch.float64), error64, error64.square()], dim=1)  # (M, 8)
    # Within each pair by error: a stable sort by pair of the order by error (rows are already grouped).
    by_error = error.sort(stable=True).indices
    order = by_error[rows[by_error].sort(stable=True).indices]
    measured = _Measured(rows, flat, features, order, error[order], b)
    return [_one_mask(truth_valid.reshape(b, -1) if mask is None else (truth_valid & mask).reshape(b, -1),
                      measured, dtype) for mask in masks]


@dataclass(frozen=True)
class _Measured:
    """The pixels with an estimate and a GT value, flat ``(M,)``: their pair, index in ``(B·H·W)``, the
    ``(M, 8)`` columns a mask sums (see :func:`_measure`), the order by error within each pair, and the errors
    so ordered."""

    rows: torch.Tensor
    flat: torch.Tensor
    features: torch.Tensor
    order: torch.Tensor
    ordered: torch.Tensor
    batch_size: int


def _one_mask(evaluated: torch.Tensor, m: _Measured, dtype: torch.dtype) -> StereoMetrics:
    """The metrics over the ``evaluated`` pixels ``(B, P)`` (see :func:`_measure`)."""
    b = m.batch_size
    covered = evaluated.reshape(-1)[m.flat]  # (M,)
    num_evaluated = evaluated.sum(1)
    sums = torch.zeros(b, m.features.shape[1], dtype=torch.float64, device=evaluated.device)
    sums.index_add_(0, m.rows, m.features * covered.unsqueeze(1))  # (B, 8)
    num_covered = sums[:, 0].round().long()
    denominator = num_covered.clamp(min=1).to(torch.float64)
    shares = (sums[:, 1:6] * 100.0 / denominator.view(b, 1)).to(dtype)
    avgerr = (sums[:, 6] / denominator).to(dtype)
    rms = (sums[:, 7] / denominator).sqrt().to(dtype)
    # Inverse empirical CDF: the k-th smallest covered error, k = ceil(q · n) (1-based, integer arithmetic),
    # found where the running count of covered pixels along the order first reaches (pairs before) + k.
    ranks = torch.stack([(q * num_covered + 99) // 100 for q in QUANTILES_PCT], dim=1).clamp(min=1)  # (B, 4)
    before = (num_covered.cumsum(0) - num_covered).view(b, 1)
    running = covered[m.order].cumsum(0)
    last = max(m.ordered.numel() - 1, 0)
    position = torch.searchsorted(running, before + ranks).clamp(max=last)
    ok = num_covered > 0
    picked = m.ordered[position] if m.ordered.numel() else torch.zeros(b, 4, dtype=dtype, device=evaluated.device)
    quantiles = torch.where(ok.view(b, 1), picked, torch.zeros_like(picked))
    density = (num_covered.to(torch.float64) / num_evaluated.clamp(min=1).to(torch.float64)).to(dtype)
    return StereoMetrics(density=density, num_evaluated=num_evaluated, num_covered=num_covered,
                         bad_pct=shares[:, :4], avgerr_px=avgerr, rms_px=rms, quantile_px=quantiles,
                         d1_pct=shares[:, 4], valid=ok)


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


def _scope_masks(batch: StereoBatch, result: PipelineResult, raw: torch.Tensor) -> dict[str, torch.Tensor]:
    kept = result.segmentation.left.kept_mask
    masks = {"map_all": raw, "kept_all": raw & kept}
    if batch.disparity_nonoccluded is not None:
        nonoccluded = raw & batch.disparity_nonoccluded
        masks.update(map_nocc=nonoccluded, kept_nocc=nonoccluded & kept)
    return {scope: masks[scope] for scope in STEREO_SCOPES if scope in masks}


def _object_masks(result: PipelineResult, raw: torch.Tensor) -> list[torch.Tensor]:
    segmentation = result.segmentation.left
    labels = segmentation.kept_labels.view(*segmentation.kept_labels.shape, 1, 1)  # (B, N, 1, 1)
    return [raw & (segmentation.labels == labels[:, n:n + 1]) & (labels[:, n:n + 1] > 0)
            for n in range(segmentation.kept_labels.shape[1])]


def pair_map_metrics(batch: StereoBatch, result: PipelineResult, px_scale: torch.Tensor | None = None
                     ) -> tuple[dict[str, StereoMetrics], list[StereoMetrics]]:
    """:func:`dense_map_metrics` and :func:`object_map_metrics` together, with one sort of the errors."""
    raw = _raw_pixels(batch, result)
    if raw is None:
        return {}, []
    scopes, objects = _scope_masks(batch, result, raw), _object_masks(result, raw)
    dense = result.dense
    measured = _measure(dense.disparity_px, dense.valid, batch.disparity_px, batch.disparity_valid,
                        [*scopes.values(), *objects], px_scale)
    return dict(zip(scopes, measured)), measured[len(scopes):]


def dense_map_metrics(batch: StereoBatch, result: PipelineResult,
                      px_scale: torch.Tensor | None = None) -> dict[str, StereoMetrics]:
    """:func:`measure_stereo_metrics` of the pipeline's dense map in each of :data:`STEREO_SCOPES` the data
    has (``*_nocc`` only with ``batch.disparity_nonoccluded``); {} under the paper rule or without GT. A
    rectified pair evaluates no pixel (its metrics are null): its map is not in the GT's pixels."""
    raw = _raw_pixels(batch, result)
    if raw is None:
        return {}
    scopes = _scope_masks(batch, result, raw)
    dense = result.dense
    return dict(zip(scopes, _measure(dense.disparity_px, dense.valid, batch.disparity_px, batch.disparity_valid,
                                     list(scopes.values()), px_scale)))


def object_map_metrics(batch: StereoBatch, result: PipelineResult,
                       px_scale: torch.Tensor | None = None) -> list[StereoMetrics]:
    """:func:`measure_stereo_metrics` of the dense map over each kept object's region (all GT pixels), one
    per kept slot (slot n is ``kept_labels[:, n]``); [] where :func:`dense_map_metrics` is {}."""
    raw = _raw_pixels(batch, result)
    if raw is None:
        return []
    dense = result.dense
    return _measure(dense.disparity_px, dense.valid, batch.disparity_px, batch.disparity_valid,
                    _object_masks(result, raw), px_scale)
