"""The differentiable variant of the block matching: a soft-argmin over the same cost volume.

The soft-argmin is one autograd node (:class:`_SoftArgminSAD`): its forward builds the volume disparity by disparity
in cache (:func:`~svs_torch.depth.cost_volume._costs_in_cache`, the hard path's loop, the same values bit for bit as
the op-by-op version) and keeps only the softmax weights, and its backward is written out one disparity at a time:
d E / d C(d) = w(d) (E − d) / (K² T), the box sum's adjoint, the absolute differences' signs recomputed. Recorded op by
op, the call kept volume-sized tensors for every step of the backward: through the default pipeline, 8 pairs at
320×240 took 2.40 s and a 1393 MB peak for a forward and backward, 0.89 s and 683 MB this way
(``experiments/bench_differentiable.py``).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..core.checks import InputError, check_positive_scalar
from ..core.numerics import per_pair
from .cost_volume import _box_sum, _check_pair, _check_range, _costs_in_cache, _crops, _prefilter, check_volume_size
from .dense_config import DenseConfig

__all__ = ["soft_block_match"]


def soft_block_match(left: torch.Tensor, right: torch.Tensor, min_disparity_px: torch.Tensor | int,
                     num_disparities: int, temperature: float, config: DenseConfig = DenseConfig()) -> torch.Tensor:
    """Differentiable dense disparity ``(B, 1, H, W)``: the soft-argmin ``Σ_d d · softmax(−C(d) / T)`` over the
    SAD cost volume of :func:`block_match_sad`'s pre-filter and window (costs as window means, so ``temperature``
    is in intensity units of the pre-filtered images), but on the pre-filtered values themselves: the hard path
    rounds them to whole 8-bit levels first (``quantize_levels``), whose steps have no gradient. As ``temperature →
    0`` it tends to the winner-takes-all disparity of those unrounded costs (without the rejections and sub-pixel
    fit), which is :func:`block_match_sad`'s at all but a few pixels (0.2–0.6 % of the valid ones on three real
    scenes at 160×120, where the rounding turns a near tie; an audit). Candidates whose right pixel leaves the image
    get no weight; a pixel with none at all gets ``min_disparity_px``.

    Gradients flow to both images (through the pre-filter, the absolute differences and the softmax) and are
    defined wherever no difference is exactly zero (there the absolute value's gradient is taken as 0, as
    autograd's); not to ``temperature``, a constant (a tensor that requires grad is refused). The backward is
    written by hand (no volume-sized temporaries); with ``create_graph=True`` it is taken again op by op by
    autograd, so second derivatives are the true ones (the hand-written one gave zeros, in silence).
    """
    b = _check_pair(left, right, config)
    minimum = _check_range(min_disparity_px, num_disparities, left, left_right=False)
    if isinstance(temperature, torch.Tensor) and temperature.requires_grad:
        raise InputError("temperature: expected a number; no gradient flows to it (got a tensor that requires grad)")
    check_positive_scalar(temperature, "temperature")
    h, w = left.shape[-2:]
    check_volume_size(num_disparities, h, w)
    radius = config.window_size // 2
    zeros = torch.zeros(b, dtype=torch.int64, device=left.device)
    left_crop, right_crop = _crops(_prefilter(left, config), _prefilter(right, config), zeros, zeros, h, w, minimum,
                                   num_disparities, radius)
    disparities = minimum.view(-1, 1) + torch.arange(num_disparities, device=left.device)  # (B, D)
    right_x = torch.arange(w, device=left.device) - disparities.unsqueeze(-1)
    inside = ((right_x >= 0) & (right_x < w)).unsqueeze(2)  # (B, D, 1, W): the right pixel is in the image
    values = disparities.to(left.dtype)
    expected = _SoftArgminSAD.apply(left_crop, right_crop, inside, values, config.window_size, temperature)
    any_inside = inside.any(dim=1, keepdim=True)  # (B, 1, 1, W)
    return torch.where(any_inside, expected, values[:, :1].view(b, 1, 1, 1).expand_as(expected))


def _softmax_over_disparities(logits: torch.Tensor) -> torch.Tensor:
    """``softmax(logits, dim=1)`` of ``(B, D, H, W)``; taken :func:`per_pair`: one call over the batch rounded a pair's
    weights by an ulp differently with the other pairs of its batch (9 × 14, 157 × 117: an audit)."""
    return torch.softmax(logits, dim=1)


class _SoftArgminSAD(torch.autograd.Function):
    """``Σ_d v(d) · softmax_d(−(C(d) / K²) / T)`` ``(B, 1, H, W)`` of the crops' SAD costs ``C`` over K × K windows
    (window means), candidates outside the image (``inside`` False) without weight and a column with none uniform
    (its value is replaced by the caller). Gradients to both crops; ``inside``, ``values``, K and T are constants."""

    @staticmethod
    def forward(ctx, left_crop: torch.Tensor, right_crop: torch.Tensor, inside: torch.Tensor, values: torch.Tensor,
                size: int, temperature: float) -> torch.Tensor:
        b, d = values.shape
        h, w = left_crop.shape[-2] - size + 1, left_crop.shape[-1] - size + 1
        with torch.no_grad():
            costs, _ = _costs_in_cache(left_crop, right_crop, h, w, d, size, None, compiled=False)
            # −(C / K²) / T in the order the op-by-op version computed it, so the values are the same bit for bit.
            logits = costs.div_(size * size).div_(temperature).neg_().masked_fill_(~inside, -torch.inf)
            logits.masked_fill_(~inside.any(dim=1, keepdim=True), 0.0)  # no candidate: uniform, replaced later
            weights = per_pair(_softmax_over_disparities, logits)
            expected = (weights * values.view(b, d, 1, 1)).sum(dim=1, keepdim=True)
        ctx.save_for_backward(left_crop, right_crop, weights, values, expected, inside)
        ctx.size, ctx.temperature = size, temperature
        return expected

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        left_crop, right_crop, weights, values, expected, inside = ctx.saved_tensors
        if torch.is_grad_enabled():
            # create_graph=True: the hand-written backward below runs without a graph, so a second derivative
            # through it was silently zero; here the forward is taken again op by op and differentiated by autograd.
            return (*_differentiable_backward(ctx, grad, left_crop, right_crop, inside, values), None, None, None, None)
        size, (b, d) = ctx.size, values.shape
        pad, width = size - 1, left_crop.shape[-1]
        scaled = grad[:, 0] / (size * size * ctx.temperature)  # (B, H, W)
        grad_left = torch.zeros_like(left_crop[:, 0])
        grad_right = torch.zeros_like(right_crop[:, 0])
        with torch.no_grad():
            for index in range(d):  # one disparity at a time: no volume-sized temporary
                # d E / d C(d) = w(d) (E − v(d)) / (K² T) per pixel, times the incoming gradient; then the box
                # sum's adjoint (the box sum of the zero-padded gradient) gives each absolute difference's.
                grad_cost = weights[:, index] * (expected[:, 0] - values[:, index].view(b, 1, 1)) * scaled
                grad_difference = _box_sum(F.pad(grad_cost, (pad, pad, pad, pad)), size)  # (B, hl, wl)
                start = d - 1 - index  # the right crop's columns [D − 1 − d, … + wl) are disparity index d
                grad_difference.mul_(torch.sign(left_crop[:, 0] - right_crop[:, 0, :, start:start + width]))
                grad_left += grad_difference
                grad_right[..., start:start + width] -= grad_difference
        return grad_left.unsqueeze(1), grad_right.unsqueeze(1), None, None, None, None


def _differentiable_backward(ctx, grad: torch.Tensor, left_crop: torch.Tensor, right_crop: torch.Tensor,
                             inside: torch.Tensor, values: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
    """The crops' gradients of :class:`_SoftArgminSAD` with their own graph (``create_graph=True``): its forward op
    by op (window means by ``avg_pool2d``: equal to the forward's up to round-off), differentiated by autograd."""
    size, temperature, (b, d) = ctx.size, ctx.temperature, values.shape
    width = left_crop.shape[-1]
    wanted = [t for t, needed in zip((left_crop, right_crop), ctx.needs_input_grad[:2]) if needed]
    with torch.enable_grad():
        means = torch.cat([F.avg_pool2d((left_crop - right_crop[..., d - 1 - i:d - 1 - i + width]).abs(), size,
                                        stride=1) for i in range(d)], dim=1)
        logits = (-means / temperature).masked_fill(~inside, -torch.inf)
        logits = logits.masked_fill(~inside.any(dim=1, keepdim=True), 0.0)
        weights = per_pair(_softmax_over_disparities, logits)
        expected = (weights * values.view(b, d, 1, 1)).sum(dim=1, keepdim=True)
        found = iter(torch.autograd.grad(expected, wanted, grad, create_graph=True))
    return tuple(next(found) if needed else None for needed in ctx.needs_input_grad[:2])
