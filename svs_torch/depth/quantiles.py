"""Medians and percentiles over masks and labels, batched: what the depth rules report for each region.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch

from ..core.checks import InputError, check_dtype, check_shape
from ..core.ordering import argsort_last, sort_last
from . import kernels

__all__ = ["Quantiles", "kept_region_lower_median", "labelled_quantile", "masked_lower_median", "masked_quantile",
           "region_lower_median", "row_quantile"]


class Quantiles(NamedTuple):
    """``values`` ``(..., Q)`` (0 where not valid) and ``valid`` ``(...)`` bool (at least one element)."""

    values: torch.Tensor
    valid: torch.Tensor


def _quantile_levels(q: Sequence[float] | torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """``q`` as a flat tensor of ``values``' dtype and device, each in [0, 1] (InputError naming ``q`` otherwise: a
    string failed in a torch constructor, NaN fails the bounds)."""
    try:
        levels = torch.as_tensor(q, dtype=values.dtype, device=values.device)
    except (TypeError, ValueError, RuntimeError):
        raise InputError(f"q: expected quantiles in [0, 1] (a number, a sequence or a tensor), got {q!r}") from None
    if levels.dim() > 1:  # flattened, a (2, 2) q gave 4 quantiles in a row, not the shape asked for (an audit)
        raise InputError(f"q: expected a number or one sequence of quantiles, got shape {tuple(levels.shape)}")
    levels = levels.flatten()
    if not bool(((levels >= 0) & (levels <= 1)).all()):  # written so that NaN fails too
        raise InputError(f"q: expected quantiles in [0, 1], got {levels.tolist()}")
    return levels


def masked_lower_median(values: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Lower median (``torch.median``'s) over the last dimension where ``mask`` holds: ``(...,)`` values
    (0 where empty) and ``(...,)`` int64 counts. Gradients flow to ``values`` at each median element (a gather
    after the sort); the counts have none. An empty last dimension (no keypoint at all) gives 0 and 0. ``values``
    float32, float64 or integer (as ``torch.median`` takes them); the medians have its dtype. A NaN where ``mask``
    holds counts as the largest value (``torch.median`` would return NaN): mask NaN out."""
    check_dtype(values, "values", "float|int")
    check_shape(mask, "mask", list(values.shape))
    check_dtype(mask, "mask", "bool")
    count = mask.sum(-1)
    if values.shape[-1] == 0:
        return values.sum(-1).to(values.dtype), count  # zeros, with a graph to values where there is one
    # Masked-out entries sort last: +inf, or an integer dtype's largest value (inf overflowed int64 in torch).
    last = torch.inf if values.is_floating_point() else torch.iinfo(values.dtype).max
    ordered = sort_last(torch.where(mask, values, torch.full_like(values, last)))
    median = ordered.gather(-1, ((count - 1).clamp(min=0) // 2).unsqueeze(-1)).squeeze(-1)
    return torch.where(count > 0, median, torch.zeros_like(median)), count


def kept_region_lower_median(values: torch.Tensor, known: torch.Tensor, labels: torch.Tensor,
                             kept_labels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`masked_lower_median` of ``values`` ``(B, 1, H, W)`` over each kept region's pixels where ``known``
    holds: ``(B, N)`` medians (0 where empty) and counts, slot n for region ``kept_labels[:, n]`` (−1: none) of
    ``labels`` ``(B, 1, H, W)``. The true distance of a region (GT depth), used for the truth of evaluations.
    Gradients flow to ``values`` at each region's median pixel (a gather after the sort); the counts have none."""
    b = check_shape(values, "values", ["B", 1, "H", "W"])["B"]
    for tensor, name in ((known, "known"), (labels, "labels")):
        check_shape(tensor, name, list(values.shape))
    check_dtype(known, "known", "bool")
    check_shape(kept_labels, "kept_labels", [b, "N"])
    # Int labels only (an audit): a bool kept_labels was read as label 1, a complex one failed deep inside, and a
    # float labels image was taken, a fractional label matching no slot.
    check_dtype(labels, "labels", "int")
    check_dtype(kept_labels, "kept_labels", "int")
    region = ((labels.flatten(1).unsqueeze(1) == kept_labels.unsqueeze(-1)) & (kept_labels > 0).unsqueeze(-1)
              & known.flatten(1).unsqueeze(1))  # (B, N, H·W); flatten, not reshape(b, ...): B may be 0
    return masked_lower_median(values.flatten(1).unsqueeze(1).expand_as(region), region)


def region_lower_median(values: torch.Tensor, labels: torch.Tensor, num_labels: int
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """Lower median (``torch.median``'s) of ``values`` ``(B, P)`` over each label ``1 .. num_labels`` of ``labels``
    ``(B, P)`` (0: no region): ``(B, num_labels)`` medians (0 for an empty label) and int64 counts. The compiled
    selection (:func:`svs_torch.depth.kernels.region_medians`, O(P)) gives the values of the torch path below,
    which sorts each pair's values and then stably its labels, so each region's values lie together in ascending
    order (two sorts of ``(B, P)`` rather than one of ``(B, num_labels, P)``). Not differentiable."""
    check_shape(values, "values", ["B", "P"])
    check_dtype(values, "values", "float|int")  # a complex one failed in the sort, a bool one was taken (an audit)
    check_shape(labels, "labels", list(values.shape))
    check_dtype(labels, "labels", "int")
    most = max(values.shape[1], 65536)  # one slot per label in the outputs: 2^40 asked for 8.8 TB
    if isinstance(num_labels, int) and num_labels > most:
        raise InputError(f"num_labels: expected at most {most} (the values per pair, or 65536), got {num_labels}")
    # The kernel's wrapper checks num_labels and the labels' range itself (the same messages): they are checked
    # here only where it leaves the values to the torch path.
    fast = kernels.region_medians(values, labels.to(torch.int64), num_labels)
    if fast is not None:
        count, median = fast
        return median, count
    if not (isinstance(num_labels, int) and num_labels >= 0):
        raise InputError(f"num_labels: expected a non-negative int, got {num_labels!r}")
    if labels.numel() and not (int(labels.min()) >= 0 and int(labels.max()) <= num_labels):
        raise InputError(f"labels: expected labels in [0, {num_labels}], got [{int(labels.min())}, "
                         f"{int(labels.max())}]")
    b, labels, values = labels.shape[0], labels.to(torch.int64), values.detach()
    by_value = torch.sort(values, dim=1, stable=True).indices
    grouped = by_value.gather(1, torch.sort(labels.gather(1, by_value), dim=1, stable=True).indices)
    ordered = values.gather(1, grouped)  # by label, then by value
    counts = torch.zeros(b, num_labels + 1, dtype=torch.int64, device=labels.device)
    counts.scatter_add_(1, labels, torch.ones_like(labels))  # label 0 (no region) .. num_labels
    start = counts.cumsum(1) - counts
    middle = (start + (counts - 1).clamp(min=0) // 2)[:, 1:].clamp(max=max(values.shape[1] - 1, 0))
    median = ordered.gather(1, middle) if values.shape[1] else values.new_zeros(b, num_labels)
    return torch.where(counts[:, 1:] > 0, median, torch.zeros_like(median)), counts[:, 1:]


def row_quantile(values: torch.Tensor, q: Sequence[float]) -> torch.Tensor:
    """``torch.quantile(values, q, dim=1).T`` of ``values`` ``(B, P)``, ``P ≥ 1``: ``(B, Q)``, the same numbers.
    Without gradients, for float32 CPU values without NaN, the compiled selection
    (:func:`svs_torch.depth.kernels.labelled_select`, O(P), where ``torch.quantile`` sorts each row) finds the two
    order statistics of each quantile, interpolated here as ``torch.quantile`` does (rank ``q · (P − 1)`` in the
    values' dtype, ``torch.lerp``). Differentiable w.r.t. ``values`` through ``torch.quantile`` otherwise."""
    if check_shape(values, "values", ["B", "P"])["P"] == 0:
        raise InputError("values: expected at least one value per row, got (B, 0)")
    check_dtype(values, "values", "float")
    q_tensor = _quantile_levels(q, values)
    if not (values.requires_grad and torch.is_grad_enabled()):
        b = values.shape[0]
        ones = torch.ones(1, 1, dtype=torch.int64).expand(b, values.shape[1])
        selected = kernels.labelled_select(values, ones, torch.ones(b, 1, dtype=torch.int64), q_tensor)
        if selected is not None:
            _, below, above = selected
            rank = q_tensor * (values.shape[1] - 1)
            weight = rank - rank.long().to(rank.dtype)
            return torch.lerp(below[:, 0], above[:, 0], weight.expand(b, -1))
    return torch.quantile(values, q_tensor, dim=1).T


def masked_quantile(values: torch.Tensor, valid: torch.Tensor, q: Sequence[float] | torch.Tensor) -> Quantiles:
    """Quantiles ``q`` (in [0, 1]) over the valid entries of the last dimension of ``values`` ``(..., K)``,
    linear interpolation between order statistics (numpy's default, ``torch.quantile``'s ``"linear"``). A NaN
    among the valid entries sorts above every number (``torch.sort``), so the quantiles below it stay finite where
    numpy and ``torch.quantile`` return NaN for all: mask NaN out with ``valid``. Differentiable w.r.t. ``values``
    (the two neighbouring order statistics get the gradient)."""
    check_dtype(values, "values", "float")
    if valid.shape != values.shape:
        raise InputError(f"valid: expected the shape of values {tuple(values.shape)}, got {tuple(valid.shape)}")
    check_dtype(valid, "valid", "bool")
    q = _quantile_levels(q, values)
    count = valid.sum(dim=-1, keepdim=True)  # (..., 1)
    shape = (*values.shape[:-1], q.numel())
    if values.shape[-1] == 0:
        return Quantiles(values.new_zeros(shape), count.squeeze(-1) > 0)
    ordered = sort_last(torch.where(valid, values, torch.full_like(values, torch.inf)))
    rank = torch.arange(values.shape[-1], device=values.device)
    ordered = torch.where(rank < count, ordered, torch.zeros_like(ordered))  # padding sorts last; zero it
    low, high = _ranks(count, q)  # (..., Q)
    return _interpolate_ranks(ordered.gather(-1, low), ordered.gather(-1, high), count, q)


def labelled_quantile(values: torch.Tensor, labels: torch.Tensor, slots: torch.Tensor,
                      q: Sequence[float] | torch.Tensor) -> Quantiles:
    """:func:`masked_quantile` of ``values`` ``(B, P)`` over each slot's entries, ``labels == slots[:, n]``, for
    the slots ``(B, N)`` (a slot ≤ 0 and a label ≤ 0 take no entry): ``values`` ``(B, N, Q)``, ``valid``
    ``(B, N)``. The same numbers as ``masked_quantile(values.unsqueeze(1).expand(B, N, P), labels == slots)``
    with one sort of ``(B, P)`` instead of one of ``(B, N, P)``: each slot's order statistics are read from
    the pair's sorted values at the places where its running count of members reaches the rank. Without
    gradients, for float32 CPU values without NaN, a compiled quickselect per slot finds the same order
    statistics (:mod:`svs_torch.depth.kernels`). Differentiable w.r.t. ``values`` (the two neighbouring order
    statistics get the gradient)."""
    check_shape(values, "values", ["B", "P"])  # 1-D or 3-D values failed unpacking their shape
    check_dtype(values, "values", "float")
    check_shape(labels, "labels", list(values.shape))
    check_dtype(labels, "labels", "int")
    check_shape(slots, "slots", [values.shape[0], "N"])
    check_dtype(slots, "slots", "int")
    q = _quantile_levels(q, values)  # the kernel casts each to a rank
    b, p = values.shape
    shape = (b, slots.shape[1], q.numel())
    if p == 0 or slots.shape[1] == 0:
        return Quantiles(values.new_zeros(shape), torch.zeros(shape[:2], dtype=torch.bool, device=values.device))
    if not (values.requires_grad and torch.is_grad_enabled()):
        # The compiled selection (svs_torch/depth/kernels/labelled_select.c): the same order statistics, O(P) per slot;
        # None for values with NaN (it orders by <), which the sort below puts last.
        selected = kernels.labelled_select(values, labels, slots, q)
        if selected is not None:
            count, below, above = selected
            return _interpolate_ranks(below, above, count.unsqueeze(-1), q)
    labelled = labels > 0
    keyed = torch.where(labelled, values, torch.full_like(values, torch.inf))
    order = argsort_last(keyed)
    ordered = keyed.gather(1, order)
    sorted_labels = torch.where(labelled, labels, torch.zeros_like(labels)).gather(1, order)
    member = (sorted_labels.unsqueeze(1) == slots.unsqueeze(-1)) & (slots > 0).unsqueeze(-1)  # (B, N, P)
    running = member.cumsum(dim=-1)  # members up to and including each sorted place
    count = running[..., -1:]  # (B, N, 1)
    low, high = _ranks(count, q)
    # The member of rank r sits where the running count first reaches r + 1.
    places = torch.searchsorted(running, torch.cat([low, high], dim=-1) + 1).clamp_max(p - 1)
    below, above = ordered.unsqueeze(1).expand(-1, shape[1], -1).gather(-1, places).chunk(2, dim=-1)
    return _interpolate_ranks(below, above, count, q)


def _ranks(count: torch.Tensor, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The ranks below and above quantile ``q`` among ``count`` sorted members."""
    position = q * (count - 1).clamp_min(0).to(q.dtype)
    return position.floor().long(), position.ceil().long()


def _interpolate_ranks(below: torch.Tensor, above: torch.Tensor, count: torch.Tensor,
                       q: torch.Tensor) -> Quantiles:
    """Linear interpolation between the order statistics ``below`` / ``above`` ``(..., Q)`` of quantile ``q``
    among ``count`` ``(..., 1)`` members (0 where there are none)."""
    position = q * (count - 1).clamp_min(0).to(q.dtype)
    fraction = position - position.floor()
    result = below + (above - below) * fraction
    present = count > 0
    return Quantiles(torch.where(present, result, torch.zeros_like(result)), present.squeeze(-1))
