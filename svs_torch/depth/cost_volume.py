"""The SAD cost volume of the dense stage: the pre-filter (x-Sobel or raw levels, in whole 1/255 steps), the
crops around the kept regions (:func:`region_crop_boxes`, :func:`wanted_pixels`) and the window sums over
them, in cache-sized blocks; and the checks of the views, sizes and disparity range that every hard and soft
matcher of the stage shares (``_check_pair``, ``_check_sizes``, ``_check_range``).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..core.checks import InputError, check_dtype, check_instance, check_shape, check_stereo_views
from ..core.kernels.checks import as_integer_tensor, check_image_hw, check_nonempty
from ..core.mask_reductions import any_along
from . import kernels
from .dense_config import DenseConfig

__all__ = [
    "CACHE_BLOCK_BYTES", "crop_box", "crop_index", "prefilter_xsobel", "quantize_levels", "region_crop_boxes",
    "wanted_pixels"
]


# A cost volume past 2^31 float32 values (8 GB) for one pair, or one image row of it, is refused by name, not left
# to an allocator: 65 534 disparities over a 64-px-wide pair asked torch for 68 GB and the fused kernel (whose
# scratch is a row's volume, D x (W + 2 (D - 1))) for 34. No real pair comes near: 256 disparities over a
# 1390x1110 Middlebury view are 5e8 values. A batch's memory is its size times that: the caller's choice.
MAX_VOLUME_VALUES = 2**31


def check_volume_size(num_disparities: int, height: int, width: int, per: str = "pair") -> None:
    """InputError naming ``num_disparities`` when a cost volume of ``num_disparities`` by ``height`` by ``width``
    values (with the left–right check's extra columns; ``per`` says of what: a pair, or an image row with
    ``height`` 1) passes :data:`MAX_VOLUME_VALUES`."""
    values = num_disparities * height * width
    if values > MAX_VOLUME_VALUES:
        shape = f"{num_disparities} x {width}" if per != "pair" else f"{num_disparities} x {height} x {width}"
        raise InputError(f"num_disparities: {num_disparities} disparities ask for a {values * 4 / 2**30:.0f} GB cost "
                         f"volume per {per} ({shape} values, the left-right check's columns included; at most "
                         f"{MAX_VOLUME_VALUES * 4 // 2**30} GB): a pair's disparities that can match a pixel are "
                         "fewer than twice its width")


def prefilter_xsobel(image: torch.Tensor, cap: float) -> torch.Tensor:
    """``StereoBM``'s x-Sobel pre-filter: ``clip(Sobel_x(image), −cap, cap)`` on ``(B, 1, H, W)``, replicate
    border. Differentiable w.r.t. the image (zero gradient where clipped).

    The six taps are added as shifted slices in the row-major order of the 3×3 kernel, which gives
    ``F.conv2d``'s values bit for bit (checked in ``tests/depth/test_dense.py``) at a tenth of its time on this
    CPU (single-channel ``conv2d`` is not vectorised: 105 ms against 9 for 32 images of 320×240). ``image``
    float32 or float64 (an integer one failed in torch's in-place sums, a bool one in its padding)."""
    check_shape(image, "image", ["B", 1, "H", "W"])
    check_dtype(image, "image", "float")
    padded = F.pad(image, (1, 1, 1, 1), mode="replicate")
    h, w = image.shape[-2:]

    def tap(row: int, col: int) -> torch.Tensor:
        return padded[..., row:row + h, col:col + w]

    response = tap(0, 2) - tap(0, 0)
    if response.requires_grad:
        response = response - 2 * tap(1, 0) + 2 * tap(1, 2) - tap(2, 0) + tap(2, 2)
        return response.clamp(-cap, cap)
    response.sub_(tap(1, 0), alpha=2).add_(tap(1, 2), alpha=2).sub_(tap(2, 0)).add_(tap(2, 2))
    return response.clamp_(-cap, cap)


def quantize_levels(image: torch.Tensor) -> torch.Tensor:
    """``round(255 · image)``: values in whole 1/255 steps, as the 8-bit pre-filtered images ``StereoBM``
    matches (the hard path; not differentiable: its gradient is round's, zero everywhere, with no error; the soft
    path takes :func:`~svs_torch.pipeline.soft.quantize_straight_through`). ``image`` float32 or float64: a uint8
    one's ``255 · image`` wrapped around modulo 256."""
    check_dtype(image, "image", "float")
    return torch.round(image * 255)


def _prefilter(image: torch.Tensor, config: DenseConfig) -> torch.Tensor:
    return prefilter_xsobel(image, config.prefilter_cap) if config.prefilter == "xsobel" else image


#: Largest slab of a block of pairs in the cost-volume loop (:func:`_cost_volume`), bytes, so that the slab and
#: its running sums are reused from cache. Measured on the 45 shared pairs at 320×240 (depth stage, ms per pair
#: at B = 8 / 32 / 96): 512 KB 53 / 55 / 63, 2 MB 50 / 49 / 58, unblocked 53 / 55 / 65.
CACHE_BLOCK_BYTES = 2 * 1024 * 1024


def _box_sum(volume: torch.Tensor, size: int) -> torch.Tensor:
    """Sums over ``size × size`` windows of the last two dims, no padding (valid part only), separably, as
    running sums of shifted slices: on this CPU 2.7× faster than ``avg_pool2d`` with (k, 1) and (1, k)
    kernels, whose vertical pass is not vectorised, and as fast as cumulative sums without their round-off. Its
    adjoint is the box sum of the gradient zero-padded by ``size − 1`` (the soft-argmin's backward,
    :mod:`svs_torch.depth.soft_dense`). Not differentiable itself (in-place sums: call it on tensors without
    gradients)."""
    height, width = volume.shape[-2] - size + 1, volume.shape[-1] - size + 1
    rows = volume[..., 0:height, :].clone()
    for offset in range(1, size):
        rows.add_(volume[..., offset:offset + height, :])
    summed = rows[..., 0:width].clone()
    for offset in range(1, size):
        summed.add_(rows[..., offset:offset + width])
    return summed


def crop_index(x0: torch.Tensor, y0: torch.Tensor, height: int, width: int, image_hw: tuple[int, int]
               ) -> torch.Tensor:
    """``(B, height, width)`` flat pixel indices of the crops at per-pair corners ``x0``, ``y0`` ``(B,)`` of an
    ``image_hw`` frame, clamped to it (replicate border): :func:`crop_box` gathers at them. Not differentiable
    (integer indices)."""
    h, w = image_hw
    rows = (y0.view(-1, 1) + torch.arange(height, device=y0.device)).clamp(0, h - 1)  # (B, h')
    cols = (x0.view(-1, 1) + torch.arange(width, device=x0.device)).clamp(0, w - 1)  # (B, w')
    return rows.unsqueeze(-1) * w + cols.unsqueeze(1)


def _gather_crop(image: torch.Tensor, y0: torch.Tensor, x0: torch.Tensor, height: int,
                 width: int) -> torch.Tensor:
    """``(B, C, height, width)`` crops of ``image`` at per-pair offsets (B,), indices clamped to the image
    (replicate border)."""
    b, c, h, w = image.shape
    index = crop_index(x0, y0, height, width, (h, w)).unsqueeze(1).expand(b, c, height, width)
    # height · width, not -1: an empty batch (B = 0) has no size to infer it from.
    return image.reshape(b, c, h * w).gather(2, index.reshape(b, c, height * width)).reshape(b, c, height, width)


def crop_box(image: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """``(B, C, height, width)`` crops of ``image`` ``(B, C, H, W)`` (any dtype) with top-left corners ``x0``,
    ``y0`` ``(B,)`` int64; indices outside the image are clamped (replicate border). Differentiable w.r.t. the
    image."""
    return _gather_crop(image, y0, x0, height, width)


def _crops(left: torch.Tensor, right: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor, height: int, width: int,
           min_disparity: torch.Tensor, num_disparities: int, radius: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The left crop ``(B, 1, height + 2r, width + 2r)`` around the box at (x0, y0) and the right crop, which
    reaches ``num_disparities − 1`` columns further left: its columns ``[k, k + width + 2r)`` are disparity
    ``min + D − 1 − k``."""
    hl, wl = height + 2 * radius, width + 2 * radius
    left_crop = _gather_crop(left, y0 - radius, x0 - radius, hl, wl)
    right_x0 = x0 - radius - min_disparity - (num_disparities - 1)
    return left_crop, _gather_crop(right, y0 - radius, right_x0, hl, wl + num_disparities - 1)


def _cost_volume(left: torch.Tensor, right: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor, height: int,
                 width: int, min_disparity: torch.Tensor, num_disparities: int, image_w: torch.Tensor,
                 config: DenseConfig, counts: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor, tuple[torch.Tensor, torch.Tensor] | None]:
    """SAD costs ``(B, D, height, width)`` of the left pixels of the box at (x0, y0), disparity ``min + d``;
    ``(B, D, 1, width)`` bool: the right pixel ``x − min − d`` lies inside the pair's own width; and, when the
    pairs' own disparity ``counts`` ``(B,)`` are given (the hard path), the costs outside the image or past a
    pair's count set to +inf and the winner-takes-all ``(min cost, index)`` over D, both ``(B, height, width)``,
    found while each slab is in cache (the first index on ties, as ``min(dim=1)``); else None."""
    check_volume_size(num_disparities, height, width)
    radius = config.window_size // 2
    disparities = min_disparity.view(-1, 1) + torch.arange(num_disparities, device=left.device)  # (B, D)
    right_x = x0.view(-1, 1, 1) + torch.arange(width, device=left.device) - disparities.unsqueeze(-1)
    inside = ((right_x >= 0) & (right_x < image_w.view(-1, 1, 1))).unsqueeze(2)  # (B, D, 1, width)
    left_crop, right_crop = _crops(left, right, x0, y0, height, width, min_disparity, num_disparities, radius)
    # The hard path's +inf: outside the image or past the pair's own count of disparities.
    outside = None if counts is None else ~(inside & _own(counts, num_disparities))  # (B, D, 1, width)
    costs, winner = _costs_in_cache(left_crop, right_crop, height, width, num_disparities, config.window_size,
                                    outside, compiled=config.kernel != "torch")
    return costs, inside, winner


def _costs_in_cache(left_crop: torch.Tensor, right_crop: torch.Tensor, height: int, width: int, num_disparities: int,
                    size: int, outside: torch.Tensor | None, compiled: bool = True
                    ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor] | None]:
    """The costs of :func:`_cost_volume` and of the soft-argmin's forward (:mod:`.soft_dense`): disparity by
    disparity, a block of pairs at a time, so that each slab's differences and box sums stay in cache; with
    ``outside``, the +inf costs and the running winner.
    ``compiled``: the C kernel :func:`svs_torch.depth.kernels.sad_volume` where it runs (the same values bit for
    bit, about a tenth of the time), else this loop."""
    found = kernels.sad_volume(left_crop[:, 0], right_crop[:, 0], height, width, size, outside) if compiled else None
    if found is not None:
        return found
    hl, wl = height + size - 1, width + size - 1
    b = left_crop.shape[0]
    costs = left_crop.new_empty(b, num_disparities, height, width)
    # The 2 (size − 1) in-place adds of a slab run from cache only while the slab fits it: a block of pairs
    # whose slab is at most CACHE_BLOCK_BYTES (a loop over blocks, not pairs: each block is batched).
    block = max(1, min(b, CACHE_BLOCK_BYTES // (hl * wl * left_crop.element_size())))
    slab = left_crop.new_empty(block, hl, wl)
    rows = left_crop.new_empty(block, height, wl)
    if outside is not None:
        best_cost = left_crop.new_empty(b, height, width)
        best = torch.zeros(b, height, width, dtype=torch.int64, device=left_crop.device)
    for b0 in range(0, b, block):
        n = min(block, b - b0)
        left_block, right_block = left_crop[b0:b0 + n, 0], right_crop[b0:b0 + n, 0]
        slab_n, rows_n = slab[:n], rows[:n]
        for d in range(num_disparities):
            start = num_disparities - 1 - d
            torch.sub(left_block, right_block[:, :, start:start + wl], out=slab_n).abs_()
            rows_n.copy_(slab_n[:, 0:height])
            for offset in range(1, size):
                rows_n += slab_n[:, offset:offset + height]
            target = costs[b0:b0 + n, d]
            target.copy_(rows_n[..., 0:width])
            for offset in range(1, size):
                target += rows_n[..., offset:offset + width]
            if outside is None:
                continue
            target.masked_fill_(outside[b0:b0 + n, d], torch.inf)
            if d == 0:
                best_cost[b0:b0 + n] = target
            else:
                running = best_cost[b0:b0 + n]
                best[b0:b0 + n].masked_fill_(target < running, d)
                torch.minimum(running, target, out=running)
    return costs, (best_cost, best) if outside is not None else None


def _own(counts: torch.Tensor, num_disparities: int) -> torch.Tensor:
    """``(B, D, 1, 1)`` bool: disparity index d is within the pair's own count."""
    return torch.arange(num_disparities, device=counts.device).view(1, -1, 1, 1) < counts.view(-1, 1, 1, 1)


def region_crop_boxes(mask: torch.Tensor, margin_px: int, image_hw: torch.Tensor | None = None
                      ) -> tuple[torch.Tensor, torch.Tensor, int, int, torch.Tensor]:
    """One shared box size for the batch that holds each pair's ``mask`` ``(B, 1, H, W)`` bounding box plus
    ``margin_px``: per-pair offsets ``x0, y0`` ``(B,)`` and the size ``height, width``; and each pair's own box
    ``(B, 4)`` as x0, y0, width, height (results outside it are discarded, so that a pair's result does not
    depend on its batch). A pair with an empty mask gets a 1-pixel box at the origin (the caller marks it
    invalid). Not differentiable (integer boxes of a bool mask)."""
    b, _, h, w = mask.shape
    if image_hw is None:
        image_hw = torch.tensor([[h, w]], device=mask.device).expand(b, 2)
    rows, cols = any_along(mask, dim=-1).squeeze(1), any_along(mask, dim=-2).squeeze(1)  # (B, H), (B, W)

    def span(present: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor]:
        index = torch.arange(size, device=mask.device)
        first = torch.where(present, index, size).min(dim=1).values
        last = torch.where(present, index, -1).max(dim=1).values
        return first, last

    y_first, y_last = span(rows, h)
    x_first, x_last = span(cols, w)
    some = y_last >= 0
    y0 = torch.where(some, (y_first - margin_px).clamp_min(0), 0)
    x0 = torch.where(some, (x_first - margin_px).clamp_min(0), 0)
    y1 = torch.where(some, torch.minimum(y_last + margin_px + 1, image_hw[:, 0]), 1)
    x1 = torch.where(some, torch.minimum(x_last + margin_px + 1, image_hw[:, 1]), 1)
    own = torch.stack([x0, y0, x1 - x0, y1 - y0], dim=1)
    # One host sync: the crop size (1 x 1 for an empty batch, which has no box).
    height, width = (int((y1 - y0).max()), int((x1 - x0).max())) if b else (1, 1)
    # Keep every box inside the padded frame: shift it back where the shared size would overhang.
    y0 = torch.minimum(y0, torch.full_like(y0, h - height)).clamp_min(0)
    x0 = torch.minimum(x0, torch.full_like(x0, w - width)).clamp_min(0)
    return x0, y0, height, width, own


def wanted_pixels(mask: torch.Tensor, margin_px: int) -> torch.Tensor:
    """Where :func:`dense_disparity_over_regions` computes a disparity: in each row of ``mask`` ``(..., H, W)``
    bool, the columns from ``margin_px`` before its first mask pixel to ``margin_px`` past its last (nothing in a
    row without one). Depth is read only on the mask, and the row fill of its invalid pixels
    (:func:`fill_invalid_rows`) reaches along rows, so a margin along the row keeps the neighbours it fills
    from; computing the whole bounding box of two objects far apart would add the frame between them (the mask
    is about a third of a 320×240 frame on the shared scenes, its bounding box more than nine tenths). Not
    differentiable (a bool mask)."""
    w = mask.shape[-1]
    index = torch.arange(w, device=mask.device)
    rows = any_along(mask, dim=-1, keepdim=True)
    first = torch.where(mask, index, w).amin(dim=-1, keepdim=True)
    last = torch.where(mask, index, -1).amax(dim=-1, keepdim=True)
    return rows & (index >= first - margin_px) & (index <= last + margin_px)


def _check_pair(left: torch.Tensor, right: torch.Tensor, config: DenseConfig) -> int:
    # Values in [0, 1]: then the levels are whole numbers within ±255 and every SAD sum is exact, in the C
    # kernel's running window sums as in the torch path's box sums; an inf, a NaN or a huge value would make
    # inf − inf or round-off of the running sums where the box sums give another value. One aminmax per image.
    dims = check_stereo_views(left, right)
    check_nonempty(left, "left")
    check_instance(config, "config", DenseConfig)
    return dims["B"]


def _check_sizes(image_hw: torch.Tensor | None, left: torch.Tensor) -> torch.Tensor:
    """``image_hw`` ``(B, 2)``, each pair's size within the tensors (default: all of them)."""
    b, _, h, w = left.shape
    if image_hw is None:
        return torch.tensor([[h, w]], device=left.device).expand(b, 2)
    return check_image_hw(image_hw, b, h, w)


def _check_range(min_disparity_px: torch.Tensor | int, num_disparities: int, left: torch.Tensor,
                 left_right: bool) -> torch.Tensor:
    if type(num_disparities) is not int or not 1 <= num_disparities <= kernels.MAX_DISPARITIES:  # not a bool
        raise InputError(f"num_disparities: expected an int in [1, {kernels.MAX_DISPARITIES}], got {num_disparities!r}")
    check_volume_size(num_disparities, 1, left.shape[-1] + 2 * (num_disparities - 1) * left_right, "image row")
    minimum = as_integer_tensor(min_disparity_px, "min_disparity_px", left.device)
    minimum = minimum.expand(left.shape[0]) if minimum.dim() == 0 else minimum
    check_shape(minimum, "min_disparity_px", [left.shape[0]])
    check_dtype(minimum, "min_disparity_px", "int")
    # Column arithmetic in int64 (the kernel's and the torch path's index maths) must not overflow.
    if minimum.numel() and bool(((minimum.long() >= 2**31) | (minimum.long() <= -2**31)).any()):  # (abs(-2^63) < 0)
        raise InputError(f"min_disparity_px: expected values in (-2^31, 2^31), got {minimum.tolist()}")
    return minimum.long()
