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

These are reports: the shares, counts and densities are thresholds and sums of bools; only the mean, the RMS
and the quantiles carry gradients to the map, the GT and ``px_scale`` (:func:`measure_stereo_metrics`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from ..core.checks import InputError, check_dtype, check_instance, check_shape
from ..core.numerics import safe_sqrt

if TYPE_CHECKING:
    from ..pipeline import PipelineResult
    from ..core.types import Segmentation, StereoBatch

__all__ = ["BAD_THRESHOLDS_PX", "D1_ABSOLUTE_PX", "D1_RELATIVE", "METRIC_NAMES", "QUANTILES_PCT", "STEREO_FIELDS",
           "STEREO_SCOPES", "StereoMetrics", "dense_map_metrics", "measure_stereo_metrics", "measured_regions",
           "metric_values", "object_map_metrics", "pair_map_metrics"]

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
    if 0 in shape[-2:]:
        raise InputError(f"disparity_px: expected maps of at least 1x1 pixels, got {shape[-1]}x{shape[-2]} (WxH)")
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
    return b


def measure_stereo_metrics(disparity_px: torch.Tensor, valid: torch.Tensor, truth_px: torch.Tensor,
                   truth_valid: torch.Tensor, mask: torch.Tensor | None = None,
                   px_scale: torch.Tensor | None = None) -> StereoMetrics:
    """Middlebury's and KITTI's metrics of ``B`` disparity maps against their GT (module docstring).

    Reports, not losses: only ``avgerr_px``, ``rms_px`` and ``quantile_px`` carry gradients (to ``disparity_px``,
    ``truth_px`` and ``px_scale``; an RMS of 0 has the subgradient 0).

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
    a GT value (a third of a frame at most, for the pipeline's maps) are gathered once, grouped by pair, and
    their errors sorted once per pair (a ``(B, max count)`` table, +inf after each pair's own). For a mask,
    the running count of its covered pixels along that order gives everything by lookups: its k-th smallest
    error (where the count reaches k), its bad-t counts (the count where the errors pass t), its size. Each
    mask makes one pass over the whole frame, to count its GT pixels."""
    b = _check_inputs(disparity_px, valid, truth_px, truth_valid, None, px_scale)
    for mask in masks:
        if mask is not None:
            check_shape(mask, "mask", list(disparity_px.shape))
            check_dtype(mask, "mask", "bool")
    dtype, device = disparity_px.dtype, disparity_px.device
    pixels = disparity_px.shape[-2] * disparity_px.shape[-1]  # of one map (B may be 0)
    rows, columns = (truth_valid & valid).reshape(b, pixels).nonzero(as_tuple=True)  # grouped by pair, in order
    flat = rows * pixels + columns  # (M,)
    estimate = disparity_px.reshape(-1).index_select(0, flat)
    truth = truth_px.to(dtype).reshape(-1).index_select(0, flat)
    # A NaN or inf where a value is declared known would poison every sum: name it instead. (Values where the
    # other map is unknown are never read.)
    for name, value, known_name in (("disparity_px", estimate, "valid"), ("truth_px", truth, "truth_valid")):
        if not bool(torch.isfinite(value).all()):
            raise InputError(f"{name}: expected finite values where {known_name} holds, got NaN or inf")
    scale = (torch.ones(b, dtype=dtype, device=device) if px_scale is None else px_scale.to(dtype))[rows]
    error = (estimate - truth).abs() * scale  # (M,) native pixels
    d1_hit = (error > D1_ABSOLUTE_PX) & (error > D1_RELATIVE * truth.abs() * scale)
    counts = torch.bincount(rows, minlength=b)
    slot = torch.arange(rows.numel(), device=device) - (counts.cumsum(0) - counts)[rows]  # place within its pair
    width = max(int(counts.max()) if b else 0, 1)

    def table(values: torch.Tensor, fill: float | bool) -> torch.Tensor:
        out = torch.full((b, width), fill, dtype=values.dtype, device=device)
        out[rows, slot] = values
        return out

    ordered, order = table(error, float("inf")).sort(dim=1)  # (B, width): each pair's errors ascending
    present = table(torch.ones_like(d1_hit), False).gather(1, order)
    # Where each bad-t threshold falls in each pair's order: the entries before it have e <= t.
    thresholds = torch.tensor(BAD_THRESHOLDS_PX, dtype=dtype, device=device).expand(b, -1).contiguous()
    measured = _Measured(sorted_flat=table(flat, 0).gather(1, order), sorted_present=present,
                         sorted_d1=table(d1_hit, False).gather(1, order),
                         sorted_error64=torch.where(present, ordered, torch.zeros_like(ordered)).to(torch.float64),
                         ordered=ordered, below=torch.searchsorted(ordered, thresholds, right=True), batch_size=b)
    return [_one_mask(truth_valid.reshape(b, pixels) if mask is None else (truth_valid & mask).reshape(b, pixels),
                      measured, dtype) for mask in masks]


@dataclass(frozen=True)
class _Measured:
    """The pixels with an estimate and a GT value, per pair in order of error, ``(B, width)`` (see
    :func:`_measure`): each entry's index in ``(B·H·W)``, whether it is a pixel (not padding), whether it is a
    D1 outlier, its error in float64 (0 in padding) and as measured (+inf in padding); ``below`` ``(B, 4)``:
    how many entries have an error at most each bad-t threshold."""

    sorted_flat: torch.Tensor
    sorted_present: torch.Tensor
    sorted_d1: torch.Tensor
    sorted_error64: torch.Tensor
    ordered: torch.Tensor
    below: torch.Tensor
    batch_size: int


def _one_mask(evaluated: torch.Tensor, m: _Measured, dtype: torch.dtype) -> StereoMetrics:
    """The metrics over the ``evaluated`` pixels ``(B, P)`` (see :func:`_measure`). Every count is exact; the
    error sums are running sums along each pair's order (sequential, padding adds zeros at the end), so a
    pair's values are the same bit for bit whatever the other pairs of its batch."""
    b = m.batch_size
    num_evaluated = torch.count_nonzero(evaluated, dim=1)  # (a bool .sum() copies to int64 first: 6x slower)
    in_order = evaluated.reshape(-1).index_select(0, m.sorted_flat.reshape(-1)).view_as(m.sorted_flat)
    covered = in_order & m.sorted_present  # (B, width), in each pair's order of error
    running = covered.cumsum(1)  # (B, width) int64
    num_covered = running[:, -1]
    at_most = torch.where(m.below > 0, running.gather(1, (m.below - 1).clamp(min=0)), torch.zeros_like(m.below))
    counts = torch.cat([num_covered.view(b, 1) - at_most,
                        torch.count_nonzero(covered & m.sorted_d1, dim=1).view(b, 1)], dim=1)  # (B, 5)
    # Sums in float64: a quarter-million float32 errors lose digits a published table shows.
    denominator = num_covered.clamp(min=1).to(torch.float64)
    shares = (counts.to(torch.float64) * 100.0 / denominator.view(b, 1)).to(dtype)
    kept = m.sorted_error64 * covered
    avgerr = (kept.cumsum(1)[:, -1] / denominator).to(dtype)
    mean_square = kept.square().cumsum(1)[:, -1] / denominator
    # An RMS of 0 (no pixel covered, or no error) gets the subgradient 0: a NaN would reach every pair of the batch.
    rms = safe_sqrt(mean_square).to(dtype)
    # Inverse empirical CDF: the k-th smallest covered error, k = ceil(q · n) (1-based, integer arithmetic),
    # found where the pair's running count of covered pixels first reaches k.
    ranks = torch.stack([(q * num_covered + 99) // 100 for q in QUANTILES_PCT], dim=1).clamp(min=1)  # (B, 4)
    position = torch.searchsorted(running, ranks).clamp(max=m.ordered.shape[1] - 1)
    ok = num_covered > 0
    picked = m.ordered.gather(1, position)
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
    rows or row-aligned: the map of a pair rectified from F is in rectified pixels), or None when there is
    nothing to score."""
    from ..core.types import StereoBatch
    from ..pipeline import PipelineResult
    from .disparity_errors import check_result_of, map_in_left_pixels  # (these import the pipeline: loaded late)

    check_instance(batch, "batch", StereoBatch)
    check_instance(result, "result", PipelineResult)
    check_result_of(batch, result)
    dense = result.dense
    if dense is None or batch.disparity_px is None or dense.disparity_px.shape != batch.disparity_px.shape:
        return None
    return map_in_left_pixels(result).view(-1, 1, 1, 1).expand_as(batch.disparity_valid)


def _scope_masks(batch: StereoBatch, result: PipelineResult, raw: torch.Tensor) -> dict[str, torch.Tensor]:
    kept = result.segmentation.left.kept_mask
    masks = {"map_all": raw, "kept_all": raw & kept}
    if batch.disparity_nonoccluded is not None:
        nonoccluded = raw & batch.disparity_nonoccluded
        masks.update(map_nocc=nonoccluded, kept_nocc=nonoccluded & kept)
    return {scope: masks[scope] for scope in STEREO_SCOPES if scope in masks}


def measured_regions(result: PipelineResult) -> Segmentation:
    """The left segmentation of ``result`` with the labels its objects were measured over
    (``PipelineResult.object_labels``: the kept regions' interiors under
    ``PipelineConfig.region_interior_working_px``): an object's true distance is the median ground truth over the
    pixels its estimate is the median of, and its map metrics are over those pixels too.

    A region the segmentation kept and the depth stage dropped as unmeasured (``PipelineResult.dropped_labels``)
    stays an object, one without a distance: it scores 0 % and its truth counts towards the real R_max, as an
    unranged object's does. Otherwise dropping a region the pair cannot measure would hide it from the score, and
    a rule that drops the hard objects would look better than one that ranges them."""
    from ..pipeline import PipelineResult  # (loaded late, as in _raw_pixels)

    check_instance(result, "result", PipelineResult)
    left = result.segmentation.left
    if result.dropped_labels is not None:
        kept = torch.where(result.dropped_labels >= 0, result.dropped_labels, left.kept_labels)
        left = dataclasses.replace(left, kept_labels=kept)
    return left if result.object_labels is None else dataclasses.replace(left, labels=result.object_labels)


def _object_masks(result: PipelineResult, raw: torch.Tensor) -> list[torch.Tensor]:
    """Each kept object's pixels of ``raw``: those it was measured over (:func:`measured_regions`)."""
    segmentation = measured_regions(result)
    labels = segmentation.kept_labels.view(*segmentation.kept_labels.shape, 1, 1)  # (B, N, 1, 1)
    return [raw & (segmentation.labels == labels[:, n:n + 1]) & (labels[:, n:n + 1] > 0)
            for n in range(segmentation.kept_labels.shape[1])]


def pair_map_metrics(batch: StereoBatch, result: PipelineResult, px_scale: torch.Tensor | None = None
                     ) -> tuple[dict[str, StereoMetrics], list[StereoMetrics]]:
    """:func:`dense_map_metrics` and :func:`object_map_metrics` together, with one sort of the errors. Gradients as
    :func:`dense_map_metrics`' (the pipeline's dense map carries none)."""
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
    has (``*_nocc`` only with ``batch.disparity_nonoccluded``); {} under the paper rule or without GT. A pair
    rectified from F evaluates no pixel (its metrics are null): its map is not in the GT's pixels. Gradients as
    :func:`measure_stereo_metrics`' (to the dense map, the GT and ``px_scale``); the pipeline's ``result.dense`` is
    its hard map, which carries none even with ``differentiable=True`` (the depths are recomputed with gradients
    instead: :mod:`svs_torch.pipeline.soft`), so from a result only the GT and ``px_scale`` receive any."""
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
    per kept slot (slot n is ``kept_labels[:, n]``); [] where :func:`dense_map_metrics` is {}. Gradients as
    :func:`dense_map_metrics`' (the pipeline's dense map carries none)."""
    raw = _raw_pixels(batch, result)
    if raw is None:
        return []
    dense = result.dense
    return _measure(dense.disparity_px, dense.valid, batch.disparity_px, batch.disparity_valid,
                    _object_masks(result, raw), px_scale)
