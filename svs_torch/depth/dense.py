"""Dense SAD block matching over the obstacles, batched over B pairs (the depth stage's measurement, Sec. 3.4).

The paper ranges a pair from the extreme disparities of its sparse RANSAC inliers (Eq. (5)–(8)); one wrong
inlier then decides R_min or R_max, and a few dozen keypoints estimate an object's median poorly
(``../shared/REFERENCE.md``, "Pitfalls"). This stage measures a disparity at every pixel of the kept regions
instead, the way OpenCV's ``StereoBM`` does (Konolige 1997):

1. **Pre-filter** both images: the x-Sobel response clipped to ``±prefilter_cap`` (``StereoBM``'s default
   ``PREFILTER_XSOBEL``), which removes the exposure offset between the two cameras; or raw intensities. The
   hard path matches them in whole 1/255 steps, as ``StereoBM``'s 8-bit pre-filter does
   (:func:`quantize_levels`): its costs are then exact integers, which lets the fused C kernel
   (:mod:`svs_torch.core.kernels`) use running sums and still equal the torch path bit for bit.
2. **Cost**: for each disparity d of a per-pair range ``[d_lo, d_lo + D)``, the sum of absolute differences
   over a square window, ``C(x, y, d) = Σ_window |L(x, y) − R(x − d, y)|`` — box sums by separable pooling.
3. **Winner takes all**, then rejections (each marks the pixel invalid, never guesses): the window's mean
   |pre-filtered left| below ``texture_threshold`` (flat), the best cost not ``uniqueness_ratio`` below every
   cost farther than 1 px from it (ambiguous), a winner on the inner edge of the range (the true minimum may lie
   outside), and a left–right check: the right view's own winner at ``x − d`` must agree within
   ``lr_max_diff_px`` (occlusions, mismatches).
4. **Sub-pixel** by the equiangular (V) fit through the costs at d − 1, d, d + 1 — SAD costs are V-shaped near
   their minimum, where a parabola biases towards integers (Shimizu & Okutomi 2001).

Work is done only where it is needed: each pair's crop is the bounding box of its kept regions plus
``margin_px`` (one shared crop size for the batch, each pair at its own offset), and the disparity range comes
from the sparse inliers' disparities with a margin (:func:`disparity_search_range`), so the cost volume is
``B × D × crop`` rather than ``B × D_max × H × W``.

The hard path (WTA, rejections) is not differentiable. :func:`soft_block_match` is: a soft-argmin over the same
cost volume with a temperature, whose gradients reach both images.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal, NamedTuple

import torch
import torch.nn.functional as F

from . import kernels
from ..core.checks import InputError, check_dtype, check_image, check_shape
from ..core.kernels.checks import check_counts, check_image_hw, check_nonempty
from ..core.mask_reductions import any_along
from ..core.ordering import sort_last

__all__ = [
    "DenseConfig", "DenseDisparity", "DisparityRange", "block_match_sad", "coarse_search_range", "crop_box",
    "crop_index", "dense_disparity_over_regions", "disparity_search_range", "equiangular_offset",
    "estimate_dense_disparity", "mean_pool",
    "prefilter_xsobel", "quantize_levels", "region_crop_boxes", "soft_block_match", "wanted_pixels",
]


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
        margin_px: context around the kept regions' bounding box, working pixels.
        range_source: ``"coarse"``: the range comes from a coarse dense pass over the whole fallback range
            (:func:`coarse_search_range`); ``"inliers"``: from the sparse RANSAC inliers' disparities.
        coarse_width_px: the coarse pass reduces the working images to about this width.
        range_margin_px, range_margin_fraction: the search range is the samples' disparities widened by
            ``max(range_margin_px, range_margin_fraction · span)`` on each side.
        range_percentiles: the sample percentiles that bound the range before the margin (robust to a few
            wrong samples; (0, 100) is their min and max).
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
        kernel: how the hard path is computed: ``"auto"`` the fused C kernel of :mod:`svs_torch.core.kernels`
            where it can be built (costs, winner, rejections and sub-pixel fit, each pair at its own box and
            range: bit-identical to the torch path, several times faster), else torch; ``"c"`` the kernel or an
            error; ``"torch"`` the eager torch cost volume.
    """

    window_size: int = 9  # paper_table1.py, tuned split: 9 beat 5, 7, 11, 13, 15, 21 at 320 px wide
    prefilter: Literal["xsobel", "none"] = "xsobel"  # StereoBM PREFILTER_XSOBEL
    prefilter_cap: float = 31 / 255  # StereoBM preFilterCap 31
    texture_threshold: float = 2 / 255
    uniqueness_ratio: float = 0.10
    lr_max_diff_px: float | None = 1.0
    working_width_px: int = 320
    margin_px: int = 8
    range_source: Literal["coarse", "inliers"] = "coarse"
    coarse_width_px: int = 160
    range_margin_px: float = 2.0
    range_margin_fraction: float = 0.25
    range_percentiles: tuple[float, float] = (1.0, 99.0)
    max_num_disparities: int = 128
    fallback_max_disparity_fraction: float = 0.25
    min_range_inliers: int = 7
    min_range_pixels: int = 20
    fill_invalid: bool = True
    kernel: Literal["auto", "c", "torch"] = "auto"
    whole_range_in_view: bool = False  # paper_table1.py: on, tuned 320 R_min 98.9 -> 89.1 % (PianoL lost)

    def __post_init__(self) -> None:
        if not isinstance(self.window_size, int) or self.window_size < 1 or self.window_size % 2 == 0:
            raise InputError(f"window_size: expected an odd positive int, got {self.window_size!r}")
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
        if not 0 <= self.uniqueness_ratio < 10:
            raise InputError(f"uniqueness_ratio: expected a value in [0, 10), got {self.uniqueness_ratio!r}")
        if self.lr_max_diff_px is not None and not self.lr_max_diff_px >= 0:
            raise InputError(f"lr_max_diff_px: expected None or a value >= 0, got {self.lr_max_diff_px!r}")
        if not isinstance(self.max_num_disparities, int) or self.max_num_disparities < 2:
            raise InputError(f"max_num_disparities: expected an int >= 2, got {self.max_num_disparities!r}")
        low, high = self.range_percentiles
        if not 0 <= low <= high <= 100:
            raise InputError(f"range_percentiles: expected 0 <= low <= high <= 100, got {self.range_percentiles}")
        for name in ("prefilter_cap", "texture_threshold", "range_margin_px", "range_margin_fraction"):
            if not getattr(self, name) >= 0:
                raise InputError(f"{name}: expected a value >= 0, got {getattr(self, name)!r}")
        if not isinstance(self.margin_px, int) or self.margin_px < 0:
            raise InputError(f"margin_px: expected an int >= 0, got {self.margin_px!r}")


#: Pairs whose disparity counts differ by less than this factor share one cost volume (:func:`_match_in_groups`).
GROUP_RATIO = 1.5


class DisparityRange(NamedTuple):
    """Per-pair search range ``[min_disparity_px, min_disparity_px + pair_num_disparities)``: ``(B,)`` int64
    each; ``num_disparities`` is the batch's largest count, the depth of the shared cost volume (a pair's
    disparities past its own count get no cost, so its result does not depend on its batch). Without
    ``pair_num_disparities`` every pair searches ``num_disparities``."""

    min_disparity_px: torch.Tensor
    num_disparities: int
    pair_num_disparities: torch.Tensor | None = None


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
    """

    disparity_px: torch.Tensor
    valid: torch.Tensor
    min_disparity_px: torch.Tensor
    num_disparities: int
    crop_xywh: torch.Tensor
    pair_num_disparities: torch.Tensor


def prefilter_xsobel(image: torch.Tensor, cap: float) -> torch.Tensor:
    """``StereoBM``'s x-Sobel pre-filter: ``clip(Sobel_x(image), −cap, cap)`` on ``(B, 1, H, W)``, replicate
    border. Differentiable w.r.t. the image (zero gradient where clipped).

    The six taps are added as shifted slices in the row-major order of the 3×3 kernel, which gives
    ``F.conv2d``'s values bit for bit (checked in ``tests/test_dense.py``) at a tenth of its time on this
    CPU (single-channel ``conv2d`` is not vectorised: 105 ms against 9 for 32 images of 320×240)."""
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
    matches (the hard path; not differentiable)."""
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
    kernels, whose vertical pass is not vectorised, and as fast as cumulative sums without their round-off.
    Differentiable (:class:`_BoxSum`: the same values bit for bit)."""
    if torch.is_grad_enabled() and volume.requires_grad:
        return _BoxSum.apply(volume, size)
    height, width = volume.shape[-2] - size + 1, volume.shape[-1] - size + 1
    rows = volume[..., 0:height, :].clone()
    for offset in range(1, size):
        rows.add_(volume[..., offset:offset + height, :])
    summed = rows[..., 0:width].clone()
    for offset in range(1, size):
        summed.add_(rows[..., offset:offset + width])
    return summed


class _BoxSum(torch.autograd.Function):
    """:func:`_box_sum` with its adjoint as the backward: each input pixel receives the sum of the gradients of
    the windows that hold it, the box sum of the gradient zero-padded by ``size − 1``. Recorded slices would
    each allocate, zero and fill a volume-sized gradient in the backward (2 (size − 1) of them: most of the
    learned segmenter's backward, issue 31)."""

    @staticmethod
    def forward(ctx, volume: torch.Tensor, size: int) -> torch.Tensor:
        ctx.size = size
        with torch.no_grad():
            return _box_sum(volume, size)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, None]:
        pad = ctx.size - 1
        with torch.no_grad():
            return _box_sum(torch.nn.functional.pad(grad, (pad, pad, pad, pad)), ctx.size), None


def crop_index(x0: torch.Tensor, y0: torch.Tensor, height: int, width: int, image_hw: tuple[int, int]
               ) -> torch.Tensor:
    """``(B, height, width)`` flat pixel indices of the crops at per-pair corners ``x0``, ``y0`` ``(B,)`` of an
    ``image_hw`` frame, clamped to it (replicate border): :func:`crop_box` gathers at them."""
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
    radius = config.window_size // 2
    disparities = min_disparity.view(-1, 1) + torch.arange(num_disparities, device=left.device)  # (B, D)
    right_x = x0.view(-1, 1, 1) + torch.arange(width, device=left.device) - disparities.unsqueeze(-1)
    inside = ((right_x >= 0) & (right_x < image_w.view(-1, 1, 1))).unsqueeze(2)  # (B, D, 1, width)
    hl, wl = height + 2 * radius, width + 2 * radius
    left_crop, right_crop = _crops(left, right, x0, y0, height, width, min_disparity, num_disparities, radius)
    # The hard path's +inf: outside the image or past the pair's own count of disparities.
    outside = None if counts is None else ~(inside & _own(counts, num_disparities))  # (B, D, 1, width)
    if torch.is_grad_enabled() and (left.requires_grad or right.requires_grad):  # the soft path: no in-place ops
        windows = right_crop.squeeze(1).unfold(-1, wl, 1).flip(-2)  # (B, hl, D, wl) view, d ascending
        volume = (left_crop.squeeze(1).unsqueeze(-2) - windows).abs().transpose(1, 2).contiguous()
        costs = _box_sum(volume, config.window_size)
        winner = None
        if outside is not None:
            costs = costs.masked_fill(outside, torch.inf)
            winner = costs.min(dim=1)
    else:  # disparity by disparity, a block of pairs at a time: each slab's differences and box sums stay in cache
        size = config.window_size
        b = left_crop.shape[0]
        costs = left_crop.new_empty(b, num_disparities, height, width)
        # The 2 (size − 1) in-place adds of a slab run from cache only while the slab fits it: a block of pairs
        # whose slab is at most CACHE_BLOCK_BYTES (a loop over blocks, not pairs: each block is batched).
        block = max(1, min(b, CACHE_BLOCK_BYTES // (hl * wl * left_crop.element_size())))
        slab = left_crop.new_empty(block, hl, wl)
        rows = left_crop.new_empty(block, height, wl)
        if outside is not None:
            best_cost = left_crop.new_empty(b, height, width)
            best = torch.zeros(b, height, width, dtype=torch.int64, device=left.device)
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
        winner = (best_cost, best) if outside is not None else None
    return costs, inside, winner


def _own(counts: torch.Tensor, num_disparities: int) -> torch.Tensor:
    """``(B, D, 1, 1)`` bool: disparity index d is within the pair's own count."""
    return torch.arange(num_disparities, device=counts.device).view(1, -1, 1, 1) < counts.view(-1, 1, 1, 1)


def equiangular_offset(before: torch.Tensor, best: torch.Tensor, after: torch.Tensor) -> torch.Tensor:
    """Sub-pixel offset in [−0.5, 0.5] of a V-shaped minimum through three costs (Shimizu & Okutomi 2001)."""
    rise = 2 * (torch.maximum(before, after) - best)
    safe = torch.where(rise > 0, rise, torch.ones_like(rise))
    return torch.where(rise > 0, (before - after) / safe, torch.zeros_like(rise)).clamp(-0.5, 0.5)


class _WinnerStats(NamedTuple):
    """Per left pixel of the matched box, ``(B, h, w)`` each: the winner-takes-all ``best`` index over D (the
    first on ties) and its cost, the costs at ``best ∓ 1`` (clamped to the range), the least cost farther than
    1 px from ``best`` (``rival``, +inf if none; None when not needed) and the right view's winner
    (``right_best``, see :func:`_right_winner`; None when not needed)."""

    best_cost: torch.Tensor
    best: torch.Tensor
    before: torch.Tensor
    after: torch.Tensor
    rival: torch.Tensor | None
    right_best: torch.Tensor | None


def _winner_stats_torch(costs: torch.Tensor, minimum: tuple[torch.Tensor, torch.Tensor], uniqueness: bool,
                        right: bool) -> _WinnerStats:
    """:class:`_WinnerStats` from the cost volume ``(B, D, h, w)`` (+inf where not searched) and its WTA
    ``minimum`` (found by :func:`_cost_volume`). ``costs`` is read, and restored after the uniqueness rival
    writes into it."""
    num_disparities = costs.shape[1]
    best_cost, best = minimum  # (B, h, w)
    neighbours = (best.unsqueeze(1) + torch.tensor([-1, 0, 1], device=costs.device).view(1, 3, 1, 1))
    neighbours = neighbours.clamp(0, num_disparities - 1)  # (B, 3, h, w)
    near = costs.gather(1, neighbours)
    rival = None
    if uniqueness:  # the best cost farther than 1 px from the winner, without copying the volume
        costs.scatter_(1, neighbours, torch.inf)
        rival = costs.min(dim=1).values
        costs.scatter_(1, neighbours, near)
    return _WinnerStats(best_cost, best, near[:, 0], near[:, 2], rival, _right_winner(costs) if right else None)


def _winner(stats: _WinnerStats, num_disparities: int, config: DenseConfig, lower_is_limit: torch.Tensor,
            counts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The sub-pixel offset of each winner and the uniqueness / range-edge verdict, ``(B, h, w)`` each."""
    best_cost, best, before, after = stats.best_cost, stats.best, stats.before, stats.after
    interior = (best > 0) & (best < num_disparities - 1) & torch.isfinite(before) & torch.isfinite(after)
    offset = torch.where(interior, equiangular_offset(before, best_cost, after), torch.zeros_like(best_cost))
    ok = torch.isfinite(best_cost) & (best < counts.view(-1, 1, 1) - 1)
    ok &= (best > 0) | lower_is_limit.view(-1, 1, 1)  # a winner on the range's inner edge is unreliable
    if config.uniqueness_ratio > 0:
        ok &= stats.rival > (1 + config.uniqueness_ratio) * best_cost
    return offset, ok


def _right_winner(costs: torch.Tensor) -> torch.Tensor:
    """The right view's WTA index from the left volume, ``C_R(x_r, d) = C_L(x_r + d, d)`` (a shear), as a
    running minimum over d: ``(B, h, w)`` int64 indexed by the left-crop column ``j = x_r + d_lo − x0``; −1
    where every candidate is +inf. Ties keep the smaller d, as ``argmin`` does."""
    width = costs.shape[-1]
    best_cost = costs[:, 0].clone()
    best = torch.zeros(best_cost.shape, dtype=torch.int64, device=costs.device)
    for k in range(1, costs.shape[1]):
        candidate = costs[:, k, :, k:]  # column j + k of disparity k
        current = best_cost[..., :width - k]
        better = candidate < current
        torch.minimum(current, candidate, out=current)
        best[..., :width - k].masked_fill_(better, k)
    return best.masked_fill_(~torch.isfinite(best_cost), -1)


def _left_right_consistent(best: torch.Tensor, right_best: torch.Tensor, max_diff: float,
                           first_column: int = 0) -> torch.Tensor:
    """Left pixel j with index k is consistent when the right winner at left-crop column j − k is within
    ``max_diff`` of k (``StereoBM`` disp12MaxDiff on integer disparities). ``best`` ``(B, h, w)`` holds the
    crop's columns from ``first_column`` on; ``right_best`` every column of the crop."""
    w = best.shape[-1]
    column = torch.arange(first_column, first_column + w, device=best.device) - best  # (B, h, w)
    inside = column >= 0
    seen = right_best.gather(-1, column.clamp_min(0))
    return inside & (seen >= 0) & ((seen - best).abs() <= max_diff)


def _winner_stats(left: torch.Tensor, right: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor, height: int,
                  width: int, min_disparity: torch.Tensor, num_disparities: int, image_w: torch.Tensor,
                  config: DenseConfig, counts: torch.Tensor, extra: int = 0) -> _WinnerStats:
    """:class:`_WinnerStats` of the box at (x0, y0) from the torch cost volume. The box's first and last
    ``extra`` columns serve only the right view's winner: the left statistics are of the columns between
    (``right_best`` is of them all)."""
    uniqueness, right_check = config.uniqueness_ratio > 0, config.lr_max_diff_px is not None
    costs, _, minimum = _cost_volume(left, right, x0, y0, height, width, min_disparity, num_disparities, image_w,
                                     config, counts)
    stats = _winner_stats_torch(costs, minimum, uniqueness, right_check)
    core = slice(extra, width - extra)
    return _WinnerStats(*(None if t is None else t[..., core] for t in stats[:5]), stats.right_best)


def _compiled(left: torch.Tensor, right: torch.Tensor, config: DenseConfig) -> bool:
    """Whether the hard path may run the fused C kernel (:func:`_match_compiled`): float32 CPU images without
    gradients, and ``config.kernel`` allows it."""
    return (config.kernel != "torch" and left.dtype == torch.float32 and left.device.type == "cpu"
            and not (torch.is_grad_enabled() and (left.requires_grad or right.requires_grad)))


def _match_compiled(left: torch.Tensor, right: torch.Tensor, boxes: torch.Tensor, search: DisparityRange,
                    image_hw: torch.Tensor, config: DenseConfig, lower_is_limit: torch.Tensor,
                    mask: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor] | None:
    """:func:`_match_box` of each pair at its own box ``(B, 4)`` (x0, y0, width, height) and its own range, by
    the fused C kernel of :mod:`svs_torch.core.kernels`, straight to the full-frame disparity and validity
    ``(B, 1, H, W)``: the same values bit for bit (a pair's result never depends on its batch), without the
    batch's shared box, the groups of ranges or the scatter back; with ``mask`` ``(B, 1, H, W)`` only at its
    :func:`wanted_pixels`. None when the kernel cannot run here (then the torch path does; ``kernel="c"`` makes
    that an error)."""
    if not _compiled(left, right, config):
        return None
    counts = search.pair_num_disparities
    if counts is None:
        counts = torch.full_like(search.min_disparity_px, search.num_disparities)
    size = config.window_size
    # The kernel pre-filters (x-Sobel, clip, quantize_levels) and takes the texture a crop row at a time, the
    # torch path's values: whole pre-filtered frames cost passes over every pair, most of it outside the kept
    # regions (the dense stage on the shared Middlebury scenes at B = 32, 2 threads, interleaved: 3.0-3.2 ->
    # 2.9 ms a pair).
    found = kernels.block_match(
        left[:, 0], right[:, 0], config.texture_threshold > 0, size, boxes, search.min_disparity_px, counts,
        image_hw, lower_is_limit, config.uniqueness_ratio, config.lr_max_diff_px,
        config.texture_threshold * size ** 2, config.whole_range_in_view,
        source="xsobel" if config.prefilter == "xsobel" else "raw", prefilter_cap=config.prefilter_cap,
        mask=None if mask is None else mask[:, 0], mask_margin_px=config.margin_px)
    if found is None:
        if config.kernel == "c":
            raise InputError("kernel: 'c' asks for the compiled dense kernel, which is not available here "
                             "(no C compiler, or SVS_TORCH_KERNELS=torch); use 'auto' or 'torch'")
        return None
    return found[0].unsqueeze(1), found[1].unsqueeze(1)


def _match_box(left: torch.Tensor, right: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor, height: int,
               width: int, search: DisparityRange, image_hw: torch.Tensor, config: DenseConfig,
               lower_is_limit: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Disparity ``(B, height, width)`` and validity of the box at (x0, y0) of the images. The volume spans
    D − 1 extra columns on each side so the right view's winner (left–right check) sees every candidate."""
    sobel = prefilter_xsobel(left, config.prefilter_cap)
    if config.prefilter == "xsobel":
        left, right = sobel, prefilter_xsobel(right, config.prefilter_cap)
    # StereoBM's levels: the matched values in whole 1/255 intensity steps (its pre-filter is uint8). The SAD
    # costs are then whole numbers, exact in float32 (at most K² · 255 < 2²⁴) whatever the order of the sums,
    # so the C kernel's running sums give the torch path's costs bit for bit.
    left, right = quantize_levels(left), quantize_levels(right)
    num_disparities = search.num_disparities
    extra = num_disparities - 1 if config.lr_max_diff_px is not None else 0
    counts = search.pair_num_disparities
    if counts is None:
        counts = torch.full_like(search.min_disparity_px, num_disparities)
    # The extra columns serve only the right view's winner: every per-pixel verdict is made on the box itself.
    stats = _winner_stats(left, right, x0 - extra, y0, height, width + 2 * extra, search.min_disparity_px,
                          num_disparities, image_hw[:, 1], config, counts, extra)
    best = stats.best
    offset, ok = _winner(stats, num_disparities, config, lower_is_limit, counts)
    if config.lr_max_diff_px is not None:
        ok &= _left_right_consistent(best, stats.right_best, config.lr_max_diff_px, extra)
    if config.texture_threshold > 0:
        radius = config.window_size // 2
        texture = _gather_crop(sobel.abs(), y0 - radius, x0 - radius, height + 2 * radius, width + 2 * radius)
        ok &= _box_sum(texture, config.window_size).squeeze(1) >= config.texture_threshold * config.window_size ** 2
    disparity = search.min_disparity_px.view(-1, 1, 1).to(offset.dtype) + best.to(offset.dtype) + offset
    rows = y0.view(-1, 1, 1) + torch.arange(height, device=left.device).view(1, -1, 1)
    cols = x0.view(-1, 1, 1) + torch.arange(width, device=left.device).view(1, 1, -1)
    ok &= (rows >= 0) & (rows < image_hw[:, :1, None]) & (cols >= 0) & (cols < image_hw[:, 1:, None])
    if config.whole_range_in_view:  # the pair's largest disparity must still land inside the right image
        ok &= cols >= (search.min_disparity_px + counts - 1).view(-1, 1, 1)
    return torch.where(ok, disparity, torch.zeros_like(disparity)), ok


def fill_invalid_rows(disparity: torch.Tensor, valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Fill each invalid pixel of ``(..., W)`` rows from the nearest valid pixels to its left and right: their
    mean where they agree within 1 px (a textureless patch inside one surface), otherwise the smaller
    disparity (an occlusion is background: Hirschmüller 2008, Sec. 3.5); one side only where the other has
    none. Returns the filled disparity and where a fill was possible (``valid`` or a valid pixel in the row).
    Differentiable w.r.t. ``disparity``; without gradients a compiled kernel gives the same values in two
    passes per row (:mod:`svs_torch.core.kernels`)."""
    if not (disparity.requires_grad and torch.is_grad_enabled()):
        done = kernels.fill_invalid_rows(disparity, valid)
        if done is not None:
            return done
    width = disparity.shape[-1]
    index = torch.arange(width, device=disparity.device).expand_as(disparity)
    left_index = torch.where(valid, index, -1).cummax(dim=-1).values
    right_index = torch.where(valid, index, width).flip(-1).cummin(dim=-1).values.flip(-1)
    has_left, has_right = left_index >= 0, right_index < width
    from_left = disparity.gather(-1, left_index.clamp(0, width - 1))
    from_right = disparity.gather(-1, right_index.clamp(0, width - 1))
    agree = (from_left - from_right).abs() <= 1
    both = torch.where(agree, (from_left + from_right) / 2, torch.minimum(from_left, from_right))
    filled = torch.where(has_left & has_right, both, torch.where(has_left, from_left, from_right))
    reachable = valid | has_left | has_right
    return torch.where(valid, disparity, torch.where(reachable, filled, torch.zeros_like(filled))), reachable


def _check_pair(left: torch.Tensor, right: torch.Tensor) -> int:
    # Values in [0, 1]: then the levels are whole numbers within ±255 and every SAD sum is exact, in the C
    # kernel's running window sums as in the torch path's box sums; an inf, a NaN or a huge value would make
    # inf − inf or round-off of the running sums where the box sums give another value. One aminmax per image.
    dims = check_image(left, "left")
    check_image(right, "right")
    if left.shape != right.shape:
        raise InputError(f"right: expected the shape of left {tuple(left.shape)}, got {tuple(right.shape)}")
    check_nonempty(left, "left")
    return dims["B"]


def _check_sizes(image_hw: torch.Tensor | None, left: torch.Tensor) -> torch.Tensor:
    """``image_hw`` ``(B, 2)``, each pair's size within the tensors (default: all of them)."""
    b, _, h, w = left.shape
    if image_hw is None:
        return torch.tensor([[h, w]], device=left.device).expand(b, 2)
    return check_image_hw(image_hw, b, h, w)


def _check_range(min_disparity_px: torch.Tensor | int, num_disparities: int, b: int,
                 device: torch.device) -> torch.Tensor:
    if not isinstance(num_disparities, int) or not 1 <= num_disparities <= kernels.MAX_DISPARITIES:
        raise InputError(f"num_disparities: expected an int in [1, {kernels.MAX_DISPARITIES}], got {num_disparities!r}")
    minimum = torch.as_tensor(min_disparity_px, device=device)
    if minimum.dim() == 0:
        minimum = minimum.expand(b)
    check_shape(minimum, "min_disparity_px", [b])
    check_dtype(minimum, "min_disparity_px", "int")
    # Column arithmetic in int64 (the kernel's and the torch path's index maths) must not overflow.
    if minimum.numel() and bool((minimum.abs() >= 2**31).any()):
        raise InputError(f"min_disparity_px: expected values in (-2^31, 2^31), got {minimum.tolist()}")
    return minimum.long()


def block_match_sad(left: torch.Tensor, right: torch.Tensor, min_disparity_px: torch.Tensor | int,
                    num_disparities: int, config: DenseConfig = DenseConfig(),
                    image_hw: torch.Tensor | None = None) -> DenseDisparity:
    """Dense SAD block matching of whole images ``(B, 1, H, W)`` over the disparities
    ``[min_disparity_px, min_disparity_px + num_disparities)`` (an int or ``(B,)`` int64 per pair).

    Pixels whose right match ``x − d`` leaves the image for every candidate, and the rejections of the module
    docstring, are invalid. ``image_hw`` ``(B, 2)`` gives each pair's size before padding (default: all of it).
    Not differentiable (winner takes all); see :func:`soft_block_match`.
    """
    b = _check_pair(left, right)
    minimum = _check_range(min_disparity_px, num_disparities, b, left.device)
    h, w = left.shape[-2:]
    image_hw = _check_sizes(image_hw, left)
    zeros = torch.zeros(b, dtype=torch.int64, device=left.device)
    search = DisparityRange(minimum, num_disparities)
    box = torch.tensor([[0, 0, w, h]], device=left.device).expand(b, 4)
    found = _match_compiled(left, right, box, search, image_hw, config, minimum <= 0)
    if found is not None:
        return DenseDisparity(found[0], found[1], minimum, num_disparities, box.clone(),
                              torch.full_like(minimum, num_disparities))
    disparity, ok = _match_box(left, right, zeros, zeros, h, w, search,
                               image_hw, config, lower_is_limit=minimum <= 0)
    return DenseDisparity(disparity.unsqueeze(1), ok.unsqueeze(1), minimum, num_disparities, box.clone(),
                          torch.full_like(minimum, num_disparities))


def soft_block_match(left: torch.Tensor, right: torch.Tensor, min_disparity_px: torch.Tensor | int,
                     num_disparities: int, temperature: float, config: DenseConfig = DenseConfig()) -> torch.Tensor:
    """Differentiable dense disparity ``(B, 1, H, W)``: the soft-argmin ``Σ_d d · softmax(−C(d) / T)`` over the
    SAD cost volume of :func:`block_match_sad` (costs as window means, so ``temperature`` is in intensity units
    of the pre-filtered images). As ``temperature → 0`` it tends to the winner-takes-all disparity (without the
    rejections and sub-pixel fit). Candidates whose right pixel leaves the image get no weight; a pixel with none
    at all gets ``min_disparity_px``.

    Gradients flow to both images (through the pre-filter, the absolute differences and the softmax) and are
    defined wherever no difference is exactly zero.
    """
    b = _check_pair(left, right)
    minimum = _check_range(min_disparity_px, num_disparities, b, left.device)
    if not temperature > 0:
        raise InputError(f"temperature: expected a positive number, got {temperature!r}")
    h, w = left.shape[-2:]
    zeros = torch.zeros(b, dtype=torch.int64, device=left.device)
    costs, inside, _ = _cost_volume(_prefilter(left, config), _prefilter(right, config), zeros, zeros, h, w,
                                    minimum, num_disparities, torch.full((b,), w, device=left.device), config)
    costs = costs / config.window_size ** 2
    logits = torch.where(inside, -costs / temperature, torch.full_like(costs, -torch.inf))
    any_inside = inside.any(dim=1)  # (B, 1, w)
    logits = torch.where(any_inside.unsqueeze(1), logits, torch.zeros_like(logits))
    weights = torch.softmax(logits, dim=1)
    values = (minimum.view(-1, 1) + torch.arange(num_disparities, device=left.device)).to(costs.dtype)
    expected = (weights * values.view(b, -1, 1, 1)).sum(dim=1, keepdim=True)
    return torch.where(any_inside.unsqueeze(1), expected, values[:, :1].view(b, 1, 1, 1).expand_as(expected))


def region_crop_boxes(mask: torch.Tensor, margin_px: int, image_hw: torch.Tensor | None = None
                      ) -> tuple[torch.Tensor, torch.Tensor, int, int, torch.Tensor]:
    """One shared box size for the batch that holds each pair's ``mask`` ``(B, 1, H, W)`` bounding box plus
    ``margin_px``: per-pair offsets ``x0, y0`` ``(B,)`` and the size ``height, width``; and each pair's own box
    ``(B, 4)`` as x0, y0, width, height (results outside it are discarded, so that a pair's result does not
    depend on its batch). A pair with an empty mask gets a 1-pixel box at the origin (the caller marks it
    invalid)."""
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
    is about a third of a 320×240 frame on the shared scenes, its bounding box more than nine tenths)."""
    w = mask.shape[-1]
    index = torch.arange(w, device=mask.device)
    rows = any_along(mask, dim=-1, keepdim=True)
    first = torch.where(mask, index, w).amin(dim=-1, keepdim=True)
    last = torch.where(mask, index, -1).amax(dim=-1, keepdim=True)
    return rows & (index >= first - margin_px) & (index <= last + margin_px)


def _nearest_rank(ordered: torch.Tensor, count: torch.Tensor, q: float) -> torch.Tensor:
    """Nearest-rank quantile ``q`` of the first ``count`` entries of each sorted row of ``ordered`` ``(B, P)``."""
    if ordered.shape[1] == 0:
        return torch.zeros(ordered.shape[0], dtype=ordered.dtype, device=ordered.device)
    rank = ((count - 1).clamp_min(0).to(ordered.dtype) * q).round().long()
    return ordered.gather(1, rank.unsqueeze(1)).squeeze(1)


def _select_nearest_ranks(values: torch.Tensor, labels: torch.Tensor, slots: torch.Tensor,
                          q: tuple[float, ...]) -> tuple[torch.Tensor, list[torch.Tensor]] | None:
    """:func:`_nearest_rank` of each slot's members (``labels == slots[:, n]``, labels ``(B, P)``, slots
    ``(B, N)`` int64) by the compiled selection of :func:`svs_torch.core.kernels.labelled_select` instead of a sort
    of every sample: the member counts ``(B, N)`` and one ``(B, N)`` float64 tensor per quantile (not defined
    where a count is 0). The kernel finds the members of rank ⌊p⌋ and ⌈p⌉ around ``p = q · (count − 1)``;
    the nearest rank (rounded in float64, as :func:`_nearest_rank` does) is one of the two. The same values
    as the sort, exactly; None without the kernel, or for values other than float32 without NaN."""
    if values.dtype != torch.float32 or values.requires_grad or not kernels.available("labelled_select"):
        return None  # (values with NaN: labelled_select gives None)
    fractions = torch.tensor(q, dtype=torch.float32, device=values.device)
    selected = kernels.labelled_select(values.contiguous(), labels, slots, fractions)
    if selected is None:
        return None
    count, below, above = selected
    position = fractions * (count - 1).clamp_min(0).unsqueeze(-1).to(torch.float32)  # the kernel's ⌊p⌋
    rank = ((count - 1).clamp_min(0).unsqueeze(-1).to(torch.float64)
            * torch.tensor(q, dtype=torch.float64)).round()
    chosen = torch.where(rank == position.floor().to(torch.float64), below, above).to(torch.float64)
    return count, list(chosen.unbind(-1))


def disparity_search_range(disparity_px: torch.Tensor, valid: torch.Tensor, image_w: torch.Tensor,
                           config: DenseConfig = DenseConfig(), extra_margin_px: float = 0.0,
                           min_count: int | None = None, groups: torch.Tensor | None = None) -> DisparityRange:
    """Per-pair search range from sample disparities ``(B, P)`` (``valid`` ``(B, P)``: coarse dense pixels of
    the kept regions, or sparse inliers): their ``range_percentiles`` widened by
    ``max(range_margin_px, range_margin_fraction · span) + extra_margin_px`` on each side, clipped at 0 and to
    ``max_num_disparities`` around the centre. Pairs with fewer than ``min_count`` (default
    ``min_range_inliers``) samples search ``[0, fallback_max_disparity_fraction · width)``. D is the batch's
    widest range: every pair searches D disparities from its own minimum.

    ``groups`` ``(B, G, P)`` bool (optional): subsets of the samples, e.g. one per kept object. The percentiles
    are then taken within each group that has at least ``min_count`` samples and the pair's range is their
    union, so a small object at a different distance is not cut away as the outer percent of the pixels of a
    big one (measured: a 97-pixel far object of Middlebury Baby2 at 320 px was ranged at 7.5 m instead of
    11.5 m when the percentiles pooled both objects)."""
    check_shape(disparity_px, "disparity_px", ["B", "P"])
    check_shape(valid, "valid", list(disparity_px.shape))
    check_dtype(valid, "valid", "bool")
    values = disparity_px.detach().to(torch.float64)
    enough_count = config.min_range_inliers if min_count is None else min_count
    percentiles = (config.range_percentiles[0] / 100, config.range_percentiles[1] / 100)
    if groups is None:
        selected = _select_nearest_ranks(disparity_px.detach(), valid.long(),
                                         torch.ones(valid.shape[0], 1, dtype=torch.int64, device=valid.device),
                                         percentiles)
        if selected is not None:
            count, (low, high) = selected[0][:, 0], (v[:, 0] for v in selected[1])
        else:
            count = valid.sum(dim=1)
            ordered = sort_last(torch.where(valid, values, torch.full_like(values, torch.inf)))
            low = _nearest_rank(ordered, count, percentiles[0])
            high = _nearest_rank(ordered, count, percentiles[1])
    else:
        check_shape(groups, "groups", [disparity_px.shape[0], "G", disparity_px.shape[1]])
        check_dtype(groups, "groups", "bool")
        inside = groups & valid.unsqueeze(1)  # (B, G, P)
        selected = None
        if groups.shape[1] and bool((inside.sum(dim=1) <= 1).all()):  # disjoint groups (objects): one label each
            number = torch.arange(1, groups.shape[1] + 1, device=groups.device)
            member = (inside * number.view(1, -1, 1)).sum(dim=1)  # (B, P): the sample's group + 1, or 0
            selected = _select_nearest_ranks(disparity_px.detach(), member,
                                             number.expand(groups.shape[0], -1), percentiles)
        if selected is not None:
            group_count, (group_low, group_high) = selected
        else:
            group_count = inside.sum(dim=2)
            ordered = sort_last(torch.where(inside, values.unsqueeze(1), torch.inf))
            group_low = _nearest_rank(ordered.flatten(0, 1), group_count.flatten(),
                                      percentiles[0]).view_as(group_count)
            group_high = _nearest_rank(ordered.flatten(0, 1), group_count.flatten(),
                                       percentiles[1]).view_as(group_count)
        used = group_count >= enough_count
        low = torch.where(used, group_low, torch.full_like(group_low, torch.inf)).amin(dim=1)
        high = torch.where(used, group_high, torch.full_like(group_high, -torch.inf)).amax(dim=1)
        count = torch.where(used.any(dim=1), group_count.sum(dim=1), torch.zeros_like(group_count[:, 0]))
        low, high = torch.where(used.any(dim=1), low, 0.0), torch.where(used.any(dim=1), high, 0.0)
    margin = torch.clamp_min((high - low) * config.range_margin_fraction, config.range_margin_px) + extra_margin_px
    enough = count >= enough_count
    fallback_high = (image_w.to(torch.float64) * config.fallback_max_disparity_fraction).clamp_min(2)
    low = torch.where(enough, (low - margin).floor().clamp_min(0), torch.zeros_like(low))
    high = torch.where(enough, (high + margin).ceil(), fallback_high.floor())
    high = torch.maximum(high, low + 1)
    span = (high - low + 1).clamp_max(config.max_num_disparities)
    centre = (low + high) / 2
    low = torch.where(high - low + 1 > span, (centre - span / 2).floor().clamp_min(0), low)
    span = span.clamp_min(2).long()
    num_disparities = int(span.max()) if span.numel() else 2
    return DisparityRange(low.long(), num_disparities, span)


def coarse_search_range(left: torch.Tensor, right: torch.Tensor, mask: torch.Tensor, image_hw: torch.Tensor,
                        config: DenseConfig = DenseConfig(), objects: torch.Tensor | None = None
                        ) -> DisparityRange:
    """The search range of each pair from a coarse pass: the images reduced ``f`` times (``f ≈ W /
    coarse_width_px``, box average), matched over the whole fallback range ``[0, fraction · W / f)`` inside
    the reduced kept regions, and the range of what survives the rejections, scaled back by ``f`` with an
    ``f``-pixel allowance for the coarse grid. This needs no sparse inlier (a pair whose features failed still
    gets a range) and is not fooled by a wrong same-row inlier. It costs about ``1 / f³`` of a full search.
    ``objects`` ``(B, N, H, W)`` bool (optional): one mask per kept object; the range is then the union of the
    objects' ranges (see ``groups`` of :func:`disparity_search_range`)."""
    b = _check_pair(left, right)
    _, _, h, w = left.shape
    check_shape(mask, "mask", [b, 1, h, w])
    check_dtype(mask, "mask", "bool")
    image_hw = _check_sizes(image_hw, left)
    factor = max(1, round(w / config.coarse_width_px))
    small_hw = torch.div(image_hw, factor, rounding_mode="floor").clamp_min(1)
    if objects is not None:
        check_shape(objects, "objects", [b, "N", h, w])
        check_dtype(objects, "objects", "bool")
    if factor > 1:
        left, right = mean_pool(left, factor), mean_pool(right, factor)
        mask = _any_pool(mask, factor)
        if objects is not None:
            objects = _any_pool(objects, factor)
    full = disparity_search_range(left.new_zeros(b, 0), mask.new_zeros(b, 0), small_hw[:, 1], config)
    coarse = dense_disparity_over_regions(left, right, mask, full, replace(config, whole_range_in_view=False),
                                          small_hw)
    samples = (coarse.disparity_px * factor).flatten(1)
    inside = (coarse.valid & mask).flatten(1)
    groups = None if objects is None else objects.flatten(2)
    return disparity_search_range(samples, inside, image_hw[:, 1], config, extra_margin_px=factor,
                                  min_count=config.min_range_pixels, groups=groups)


def dense_disparity_over_regions(left: torch.Tensor, right: torch.Tensor, mask: torch.Tensor,
                                 search: DisparityRange, config: DenseConfig = DenseConfig(),
                                 image_hw: torch.Tensor | None = None) -> DenseDisparity:
    """Dense SAD disparity of the left view, computed only near each pair's ``mask`` ``(B, 1, H, W)`` bool (the
    kept regions: :func:`wanted_pixels`, each row's mask span and ``config.margin_px`` either side) and only over
    ``search``; elsewhere invalid. A pixel's value is the one a whole-frame match gives it.

    Args:
        left, right: ``(B, 1, H, W)`` images (rectified, or a rig whose rows already agree).
        mask: where depth is wanted (``Segmentation.kept_mask`` of the left view).
        search: :class:`DisparityRange`, e.g. from :func:`disparity_search_range`.
        image_hw: ``(B, 2)`` each pair's size before padding.

    Returns:
        :class:`DenseDisparity`. Not differentiable (see :func:`soft_block_match`).
    """
    b = _check_pair(left, right)
    check_shape(mask, "mask", [b, 1, *left.shape[-2:]])
    check_dtype(mask, "mask", "bool")
    minimum = _check_range(search.min_disparity_px, search.num_disparities, b, left.device)
    if search.pair_num_disparities is not None:
        check_counts(search.pair_num_disparities, "search.pair_num_disparities", b, search.num_disparities)
    h, w = left.shape[-2:]
    image_hw = _check_sizes(image_hw, left)
    x0, y0, height, width, own = region_crop_boxes(mask, config.margin_px, image_hw)
    search = DisparityRange(minimum, search.num_disparities, search.pair_num_disparities)
    counts = search.pair_num_disparities
    counts = torch.full_like(minimum, search.num_disparities) if counts is None else counts
    some = any_along(mask.flatten(1), dim=1)
    found = _match_compiled(left, right, torch.where(some.view(-1, 1), own, torch.zeros_like(own)), search,
                            image_hw, config, minimum <= 0, mask)
    if found is not None:
        return DenseDisparity(found[0], found[1], minimum, search.num_disparities, own, counts)
    disparity, ok = _match_box(left, right, x0, y0, height, width, search,
                               image_hw, config, lower_is_limit=minimum <= 0)
    ok &= some.view(-1, 1, 1) & crop_box(wanted_pixels(mask, config.margin_px), x0, y0, height, width)[:, 0]
    rows = y0.view(-1, 1, 1) + torch.arange(height, device=left.device).view(1, -1, 1)
    cols = x0.view(-1, 1, 1) + torch.arange(width, device=left.device).view(1, 1, -1)
    own_x0, own_y0, own_w, own_h = (v.view(-1, 1, 1) for v in own.unbind(1))
    ok &= (rows >= own_y0) & (rows < own_y0 + own_h) & (cols >= own_x0) & (cols < own_x0 + own_w)
    disparity = torch.where(ok, disparity, torch.zeros_like(disparity))
    full = torch.zeros(b, h * w, dtype=disparity.dtype, device=left.device)
    full_ok = torch.zeros(b, h * w, dtype=torch.bool, device=left.device)
    index = ((y0.view(-1, 1, 1) + torch.arange(height, device=left.device).view(1, -1, 1)) * w
             + x0.view(-1, 1, 1) + torch.arange(width, device=left.device).view(1, 1, -1)).reshape(b, -1)
    full.scatter_(1, index, disparity.reshape(b, -1))
    full_ok.scatter_(1, index, ok.reshape(b, -1))
    return DenseDisparity(full.view(b, 1, h, w), full_ok.view(b, 1, h, w), minimum, search.num_disparities, own,
                          counts)


def _block_slices(images: torch.Tensor, factor: int) -> list[torch.Tensor]:
    """The ``factor²`` strided slices of ``images`` ``(..., H, W)`` (cut to whole blocks), one per offset of a
    ``factor × factor`` block, in row-major order: a block's pixels are the same place of every slice."""
    height, width = images.shape[-2] // factor * factor, images.shape[-1] // factor * factor
    images = images[..., :height, :width]
    return [images[..., i::factor, j::factor] for i in range(factor) for j in range(factor)]


def mean_pool(images: torch.Tensor, factor: int) -> torch.Tensor:
    """``F.avg_pool2d(images, factor)`` bit for bit (the same float sums in the same row-major order, then one
    division), from the block slices: on this CPU 4–5× faster than ``avg_pool2d`` at factor 2."""
    first, *rest = _block_slices(images, factor)
    total = first
    for part in rest:
        total = total + part
    return total / (factor * factor)


def _any_pool(mask: torch.Tensor, factor: int) -> torch.Tensor:
    """``F.max_pool2d(mask.float(), factor) > 0`` for a bool mask: whether any pixel of each block is set, by
    OR-ing the block slices as bytes (on this CPU 20× faster than max-pooling a float copy). The OR of 0/1
    bytes is 0 or 1, a bool's own bytes: viewed as bool, not converted (as :func:`any_along` does)."""
    first, *rest = _block_slices(mask.view(torch.uint8), factor)
    found = first
    for part in rest:
        found = found | part
    return found.view(torch.bool)


def _reduce(left: torch.Tensor, right: torch.Tensor, mask: torch.Tensor, image_hw: torch.Tensor,
            factor: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Images box-averaged ``factor`` times, the mask by any-pooling, each pair's size floored."""
    if factor == 1:
        return left, right, mask, image_hw
    return (mean_pool(left, factor), mean_pool(right, factor), _any_pool(mask, factor),
            torch.div(image_hw, factor, rounding_mode="floor").clamp_min(1))


def _enlarge(dense: DenseDisparity, factor: int, height: int, width: int) -> DenseDisparity:
    """A reduced-resolution result on the full ``height × width`` grid: each working pixel covers a
    ``factor × factor`` block, disparities scaled by ``factor``; rows and columns past the reduced grid are
    invalid."""
    if factor == 1:
        return dense

    def grow(value: torch.Tensor) -> torch.Tensor:
        grown = value.repeat_interleave(factor, dim=-2).repeat_interleave(factor, dim=-1)
        grown = grown[..., :height, :width]
        return F.pad(grown, (0, width - grown.shape[-1], 0, height - grown.shape[-2]))

    return DenseDisparity(grow(dense.disparity_px * factor), grow(dense.valid), dense.min_disparity_px * factor,
                          dense.num_disparities * factor, dense.crop_xywh * factor,
                          dense.pair_num_disparities * factor)


def working_factor(width_px: int, config: DenseConfig = DenseConfig()) -> int:
    """The integer factor :func:`estimate_dense_disparity` reduces images ``width_px`` wide by (about
    ``width_px / config.working_width_px``, at least 1): one working pixel is this many input pixels."""
    return max(1, round(width_px / config.working_width_px))


def estimate_dense_disparity(left: torch.Tensor, right: torch.Tensor, mask: torch.Tensor,
                             config: DenseConfig = DenseConfig(), image_hw: torch.Tensor | None = None,
                             inlier_disparity_px: torch.Tensor | None = None,
                             inlier_valid: torch.Tensor | None = None,
                             objects: torch.Tensor | None = None) -> DenseDisparity:
    """The dense stage of the pipeline: reduce to ``working_width_px``, find each pair's search range (a coarse
    pass, or the sparse inliers' disparities ``(B, K)`` with ``inlier_valid``), match over the kept regions
    ``mask`` ``(B, 1, H, W)``, and return the disparity on the input grid (in input pixels).

    ``min_disparity_px``, ``num_disparities`` and ``crop_xywh`` of the result are in input pixels too (the
    working range times the factor). ``objects`` ``(B, N, H, W)`` bool (optional): one mask per kept object,
    so the coarse range covers every object (see :func:`coarse_search_range`). Not differentiable (see
    :func:`soft_block_match`).
    """
    b = _check_pair(left, right)
    check_shape(mask, "mask", [b, 1, *left.shape[-2:]])
    check_dtype(mask, "mask", "bool")
    if objects is not None:
        check_shape(objects, "objects", [b, "N", *left.shape[-2:]])
        check_dtype(objects, "objects", "bool")
    height, width = left.shape[-2:]
    image_hw = _check_sizes(image_hw, left)
    factor = working_factor(width, config)
    small_left, small_right, small_mask, small_hw = _reduce(left, right, mask, image_hw, factor)
    if config.range_source == "coarse" or inlier_disparity_px is None or inlier_valid is None:
        small_objects = None
        if objects is not None:
            small_objects = objects if factor == 1 else _any_pool(objects, factor)
        search = coarse_search_range(small_left, small_right, small_mask, small_hw, config, small_objects)
    else:
        search = disparity_search_range(inlier_disparity_px / factor, inlier_valid, small_hw[:, 1], config)
    dense = _match_in_groups(small_left, small_right, small_mask, search, config, small_hw)
    return _enlarge(dense, factor, height, width)


def _match_in_groups(left: torch.Tensor, right: torch.Tensor, mask: torch.Tensor, search: DisparityRange,
                     config: DenseConfig, image_hw: torch.Tensor) -> DenseDisparity:
    """:func:`dense_disparity_over_regions` on groups of pairs whose disparity counts are within a factor
    ``GROUP_RATIO`` of each other: the torch path's shared cost volume is as deep as its widest range, so a
    single pair with a wide range would otherwise make every pair of the batch pay for it (measured: 2.5–10×
    per pair at B = 8 on mixed Middlebury scenes). A loop over a few groups, never over pairs; results are the
    same as one call, since a pair's result never depends on its batch. The compiled path needs no groups: it
    matches each pair over its own range."""
    counts = search.pair_num_disparities
    if counts is None or left.shape[0] == 1 or (_compiled(left, right, config) and kernels.available()):
        # The compiled path matches each pair over its own range already.
        return dense_disparity_over_regions(left, right, mask, search, config, image_hw)
    group = (counts.clamp_min(1).to(torch.float64).log() / math.log(GROUP_RATIO)).floor().long()
    keys = group.unique()
    if keys.numel() == 1:
        return dense_disparity_over_regions(left, right, mask, search, config, image_hw)
    b, _, h, w = left.shape
    disparity = left.new_zeros(b, 1, h, w)
    valid = torch.zeros(b, 1, h, w, dtype=torch.bool, device=left.device)
    boxes = torch.zeros(b, 4, dtype=torch.int64, device=left.device)
    for key in keys:
        index = (group == key).nonzero().flatten()
        own = counts[index]
        part = dense_disparity_over_regions(
            left[index], right[index], mask[index],
            DisparityRange(search.min_disparity_px[index], int(own.max()), own), config, image_hw[index])
        disparity[index], valid[index], boxes[index] = part.disparity_px, part.valid, part.crop_xywh
    return DenseDisparity(disparity, valid, search.min_disparity_px, search.num_disparities, boxes, counts)
