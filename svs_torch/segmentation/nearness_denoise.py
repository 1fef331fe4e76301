"""The nearness segmenter's disparity map made usable on a camera frame (issues 32 and 33): a noisy pair matched
with a wider window, the block matcher's rejected pixels filled along their rows, a median over the map, and,
for a pair whose matcher accepted too little of the view (JPEG frames with sensor noise, a dim scene), its
accepted matches checked against the same pair measured at a coarser scale.

Why the wider window (:func:`match_by_noise`): a SAD over K² pixels sums the sensor noise of both views with the
scene's texture; the gap between a wrong disparity's cost and the right one's grows as K², the noise's spread as
K (independent pixels), so the noise's share falls as 1/K. At the working width's 7×7 window a camera frame's map
is specks and streaks, whose Otsu split then cuts a near object's region into the wall behind it. A pair is noisy
by its matching residual (the median winning SAD per window pixel, as the dense stage's aggregation gate reads
it): the tuned scenes' clean pairs stay under the gate, and their camera frames at 320×240 reach it, most from the
board's digit 1 and all from digit 3. Only such pairs are matched again, so a clean pair's map and its thin near
objects keep the narrow window's detail. Chosen on the tuning sets (experiments/select_nearness_setting.md, third
selection; experiments/real_rig.md, "A wider window for noisy pairs").

Why the edge rows: the block matcher crops each pair with a replicated border, so a window centred within
``K // 2`` rows of the top or bottom edge repeats the edge row, and only its rows inside the view are independent.
On a noisy pair those few rows' noise decides the match, and a strip along the edge is ranged as if near (the
tuned Shelves at 448×336 as a JPEG digit 7 frame: a strip along the top kept as an object and ranged at 2.42 m,
truly 3.52; 83.4 → 99.7 % per object). A noisy pair's edge rows therefore take the nearest row whose window lies
inside the view (OpenCV's StereoBM leaves its border unmeasured; leaving them unmeasured here lost other tuned
frames, 320×240 digit 5 99.20 → 98.09 %: experiments/real_rig.md, "Edge rows of a noisy pair's map"). A clean
pair's map is left as the matcher made it: without its edge rows the tuned clean pairs at 448×336 fell 99.40 →
99.17.

Why the coarse check: on such a frame the uniqueness and left–right rules reject most windows at the working
width, and many of the windows that pass are noise matches, so the filled map is specks and streaks whose Otsu
split can keep a speck (tuned Piano at half contrast as JPEG digit 6 frames: 17 % of the view accepted, the kept
regions' IoU with the clean pair's 0.15). Averaging 2×2 pixels halves the noise and the window spans twice as much
of the scene: the same pair at half the working width accepts about three times as much and its map looks like
the clean pair's (IoU 0.72). A fine match is kept where it agrees with that coarse map (its detail at depth
edges), the coarse map stands in where it does not or where the fine matcher rejected the pixel, and the rows are
filled and the median taken as before. Clean pairs accept 41 % or more (experiments/nearness_fallback.md) and
never take this path.

Off by default (``NearnessNetConfig.sparse_reduction=1``): on the tuned split it raises the camera frames' per
object accuracy (experiments/select_nearness_setting.md), but on the held-out split it moves single pairs by
10–35 points both ways and leaves the board's default JPEG digit below OpenCV SGBM at both sizes (that file's
"Shipped" paragraph).

Why long runs stay unfilled (``NearnessNetConfig.max_fill_px``, off by default): on a noisy pair a plain wall (a
painted wall's texture is about one 8-bit level, under a camera's noise) is rejected almost everywhere, and the row
fill carries the nearest measured pixels across it: a box's edge along the rows to the view's border, or a speck of
wrong match. The map then joins the boxes and the wall into one near region, the kept region is mostly wall and
its distance the box's (rendered boxes 1–2 m before a plain wall at 5 m, ``experiments/real_rig.py --splits
synthetic-wall``: 99.97 % per object clean, 50.7–88.8 % as JPEG frames). With the setting a noisy pair's run of
rejected pixels is filled only where it is short, lies between two measured pixels that agree within 1 px (one
surface with a featureless patch), or runs from the left edge to a surface within its own disparity of it (the
band the right view cannot show it in); a longer run stays far. It ranges those frames at 97.7–99.9 % (digits
3–7), but the tuned scenes' camera frames, whose kept regions change shape with it, lose 0.3–1.0 points
at 320×240 (``experiments/real_rig.md``, "A plain wall behind the obstacles"), so it stays off.
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F

from ..core.checks import InputError, check_count, check_device, check_dtype, check_instance, check_shape
from ..depth.block_matching import (block_match_sad, block_match_sad_noisy_pairs, fill_invalid_rows,
                                    valid_row_neighbours)
from ..depth.dense_config import DenseConfig, DenseDisparity
from ..depth.soft_dense import soft_block_match
from . import kernels

if TYPE_CHECKING:
    from .nearness import NearnessNetConfig

__all__ = ["check_denoise_settings", "denoised_map", "fillable_runs", "match_by_noise", "reduced_to_width",
           "soft_match_by_noise"]


def reduced_to_width(image: torch.Tensor, width: int) -> torch.Tensor:
    """``image`` ``(B, 1, H, W)`` area-averaged to ``width`` columns (the height in proportion) when wider: the
    nearness map is matched at a working width (``NearnessNetConfig.working_width_px``)."""
    check_shape(image, "image", ["B", 1, "H", "W"])
    check_dtype(image, "image", "float")  # (0 or 2.5 columns failed deep in torch, or made an empty map: an audit)
    check_count(width, "width", least=1)
    h, w = image.shape[-2:]
    if w <= width:
        return image
    return F.interpolate(image, size=(max(1, round(h * width / w)), width), mode="area")


def check_denoise_settings(config: NearnessNetConfig) -> None:
    """The checks of the settings this module reads (``NearnessNetConfig.__post_init__`` calls it)."""
    fill = config.max_fill_px
    if fill is not None and (isinstance(fill, bool) or not isinstance(fill, int) or fill < 0):
        raise InputError(f"max_fill_px: expected None or an int >= 0, got {fill!r}")
    if not isinstance(config.sparse_reduction, int) or config.sparse_reduction < 1:
        raise InputError(f"sparse_reduction: expected an int >= 1, got {config.sparse_reduction!r}")
    if not config.noisy_min_residual_levels >= 0:
        raise InputError(f"noisy_min_residual_levels: expected a level >= 0, got {config.noisy_min_residual_levels!r}")
    if not config.sparse_agreement_px >= 0:
        raise InputError(f"sparse_agreement_px: expected a distance >= 0, got {config.sparse_agreement_px!r}")
    if not 0 <= config.sparse_share <= 1:
        raise InputError(f"sparse_share: expected a share in [0, 1], got {config.sparse_share!r}")


def _check_arguments(left: torch.Tensor, dense: DenseConfig, config: NearnessNetConfig,
                     **flags: torch.Tensor | None) -> None:
    """The settings, and each of ``flags`` (None or ``(B,)`` bool on the device of ``left`` ``(B, 1, h, w)``), named:
    flags of another length were taken in silence (``(1,)`` for two pairs flagged both, or cut the map to one pair)
    or failed deep in torch, int ones were inverted bit by bit, another config failed on its first field (an audit
    of the functions called by hand)."""
    from .nearness import NearnessNetConfig  # (nearness imports this module)
    b = check_shape(left, "left", ["B", 1, "h", "w"])["B"]
    check_instance(dense, "dense", DenseConfig)
    check_instance(config, "config", NearnessNetConfig)
    for name, value in flags.items():
        if value is not None:
            check_shape(value, name, [b])
            check_dtype(value, name, "bool")
            check_device(value, name, left, "the views'")


def match_by_noise(left: torch.Tensor, right: torch.Tensor, num_disparities: int, dense: DenseConfig,
                   config: NearnessNetConfig) -> tuple[DenseDisparity, torch.Tensor]:
    """The block matcher's map of the working-width views ``left`` / ``right`` ``(B, 1, h, w)`` over
    ``[0, num_disparities)`` with ``dense``'s window, the pairs whose matching residual reaches
    ``config.noisy_min_residual_levels`` matched again with ``config.noisy_window_size``, their edge rows taken
    from the nearest row whose window lies inside the view (module docstring); and
    those pairs ``(B,)`` bool. Each pair's map depends on that pair alone. Not differentiable (see
    :func:`soft_match_by_noise`).

    ``config.noisy_min_residual_levels == 0`` widens every pair (any residual reaches 0), so their map is matched
    with the wider window at once: the first pass, which only its residual would have served, is skipped (about a
    ninth of a 320×240 camera frame's time at B = 1; ``SegmentationConfig.camera_frames``)."""
    _check_arguments(left, dense, config)
    if config.noisy_min_residual_levels == 0 and config.noisy_window_size != dense.window_size:
        found = _edge_rows_from_interior(block_match_sad(
            left, right, 0, num_disparities, dataclasses.replace(dense, window_size=config.noisy_window_size)),
            config.noisy_window_size)
        return found, torch.ones(left.shape[0], dtype=torch.bool, device=left.device)
    found, noisy = block_match_sad_noisy_pairs(left, right, 0, num_disparities, config.noisy_min_residual_levels, dense)
    widened = noisy & (config.noisy_window_size != dense.window_size)
    if not bool(widened.any()):
        return found, widened
    index = widened.nonzero().flatten()
    wide = _edge_rows_from_interior(block_match_sad(
        left.index_select(0, index), right.index_select(0, index), 0, num_disparities,
        dataclasses.replace(dense, window_size=config.noisy_window_size)), config.noisy_window_size)
    return dataclasses.replace(found, disparity_px=found.disparity_px.index_copy(0, index, wide.disparity_px),
                               valid=found.valid.index_copy(0, index, wide.valid)), widened


def _edge_rows_from_interior(found: DenseDisparity, window_size: int) -> DenseDisparity:
    """``found`` with its rows within ``window_size // 2`` of the top and bottom edges replaced by the nearest row
    whose window lies wholly inside the view (module docstring, "Why the edge rows")."""
    rows = _interior_rows(found.disparity_px.shape[-2], window_size, found.valid.device)
    return dataclasses.replace(found, disparity_px=found.disparity_px.index_select(-2, rows),
                               valid=found.valid.index_select(-2, rows))


def _interior_rows(h: int, window_size: int, device: torch.device) -> torch.Tensor:
    """``(h,)``: for each row of a map ``h`` rows high, the nearest row whose ``window_size`` window lies inside it
    (every row itself where no row's does)."""
    reach = window_size // 2
    rows = torch.arange(h, device=device)
    return rows if h <= 2 * reach else rows.clamp(reach, h - 1 - reach)


def soft_match_by_noise(left: torch.Tensor, right: torch.Tensor, num_disparities: int, dense: DenseConfig,
                        config: NearnessNetConfig, widened: torch.Tensor) -> torch.Tensor:
    """The soft-argmin disparity ``(B, 1, h, w)`` (:func:`~svs_torch.depth.soft_dense.soft_block_match` at
    ``config.disparity_temperature``) over the same windows as :func:`match_by_noise`: ``widened`` ``(B,)`` pairs'
    with ``config.noisy_window_size`` and their edge rows taken from the same rows. Each pair's volume is built
    once, at its own window. Differentiable w.r.t. both images."""
    _check_arguments(left, dense, config, widened=widened)
    if not bool(widened.any()):
        return soft_block_match(left, right, 0, num_disparities, config.disparity_temperature, dense)
    wider = dataclasses.replace(dense, window_size=config.noisy_window_size)
    out = None
    for pick, window in ((~widened, dense), (widened, wider)):
        index = pick.nonzero().flatten()
        if len(index) == 0:
            continue
        part = soft_block_match(left.index_select(0, index), right.index_select(0, index), 0, num_disparities,
                                config.disparity_temperature, window)
        if window is wider:
            part = part.index_select(-2, _interior_rows(part.shape[-2], window.window_size, part.device))
        out = (part.new_zeros(len(pick), *part.shape[1:]) if out is None else out).index_copy(0, index, part)
    return out


def denoised_map(left: torch.Tensor, right: torch.Tensor, found: DenseDisparity, num_disparities: int,
                 dense: DenseConfig, config: NearnessNetConfig, noisy: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """The filled, median-filtered disparity ``(B, 1, h, w)`` (working pixels) of the block matcher's ``found``
    on the working-width views ``left`` / ``right`` ``(B, 1, h, w)``, and the pixels it rests on: those the
    matcher accepted, or for a sparse pair (module docstring) its agreeing fine matches and the coarse map's
    accepted pixels. ``noisy`` ``(B,)`` bool: the pairs :func:`match_by_noise` matched with the wider window, whose
    long runs ``config.max_fill_px`` limits (None: none). Each pair's result depends on that pair alone. Not
    differentiable (measured without gradients; the segmenter's gradient path is the soft-argmin's)."""
    _check_arguments(left, dense, config, noisy=noisy)
    check_instance(found, "found", DenseDisparity)
    disparity, valid = found.disparity_px, found.valid
    sparse = valid.flatten(1).to(torch.float32).mean(1) < config.sparse_share
    if config.sparse_reduction > 1 and bool(sparse.any()):
        index = sparse.nonzero().flatten()
        merged, merged_valid = _checked_against_coarse(
            left.index_select(0, index), right.index_select(0, index), disparity.index_select(0, index),
            valid.index_select(0, index), num_disparities, dense, config)
        disparity, valid = disparity.index_copy(0, index, merged), valid.index_copy(0, index, merged_valid)
    filled, reachable = fill_invalid_rows(disparity, valid)
    if config.max_fill_px is not None and noisy is not None and bool(noisy.any()):
        limited = fillable_runs(disparity, valid, config.max_fill_px) | ~noisy.view(-1, 1, 1, 1)
        reachable = reachable & limited
    return _median_by_share(torch.where(reachable, filled, 0.0), sparse, config), valid


def fillable_runs(disparity: torch.Tensor, valid: torch.Tensor, max_px: int) -> torch.Tensor:
    """``(..., W)`` bool: the ``valid`` pixels, and the rejected ones whose run of rejected pixels along the row
    may be filled (module docstring, "Why long runs stay unfilled"): a run at most ``max_px`` long, one between two
    measured pixels whose disparities agree within 1 px (one surface), or one from the left edge to a measured
    pixel at x whose disparity d reaches within ``max_px`` of it (x ≤ d + max_px: the band the right view cannot
    show that surface in). Not differentiable (a bool mask)."""
    width = valid.shape[-1]
    before, after, left_value, right_value = valid_row_neighbours(disparity, valid)
    short = after - before - 1 <= max_px
    one_surface = (before >= 0) & (after < width) & ((left_value - right_value).abs() <= 1)
    band = (before < 0) & (after < width) & (after <= right_value + max_px)
    return valid | short | one_surface | band


def _checked_against_coarse(left: torch.Tensor, right: torch.Tensor, disparity: torch.Tensor, valid: torch.Tensor,
                            num_disparities: int, dense: DenseConfig, config: NearnessNetConfig
                            ) -> tuple[torch.Tensor, torch.Tensor]:
    """The fine map ``disparity`` / ``valid`` ``(n, 1, h, w)`` of sparse pairs merged with the same views
    measured at ``1 / config.sparse_reduction`` of their width (filled and median-filtered there, then repeated
    back to ``(h, w)`` in working pixels): a fine match within ``config.sparse_agreement_px`` of the coarse map
    is kept, the coarse value taken elsewhere; valid where either the kept fine match or the coarse matcher
    accepted the pixel."""
    r = config.sparse_reduction
    h, w = disparity.shape[-2:]
    coarse_found = block_match_sad(F.avg_pool2d(left, r, ceil_mode=True), F.avg_pool2d(right, r, ceil_mode=True),
                                   0, max(2, math.ceil(num_disparities / r)), dense)
    coarse, reachable = fill_invalid_rows(coarse_found.disparity_px, coarse_found.valid)
    coarse = _median_halved(torch.where(reachable, coarse, 0.0), config.median_window)

    def repeat(t: torch.Tensor) -> torch.Tensor:
        return t.repeat_interleave(r, -2).repeat_interleave(r, -1)[..., :h, :w]

    coarse, coarse_valid = repeat(coarse) * r, repeat(coarse_found.valid)
    agrees = valid & ((disparity - coarse).abs() <= config.sparse_agreement_px)
    return torch.where(agrees, disparity, coarse), agrees | coarse_valid


def _median_halved(disparity: torch.Tensor, window: int) -> torch.Tensor:
    """``disparity`` ``(B, 1, h, w)`` replaced by the ``window``-sided median of its 2×2 box averages (edges
    replicated), back at ``(h, w)`` by nearest neighbour. JPEG frames with sensor noise leave the block matcher's
    map full of specks and, once filled along the rows, one-row streaks; a wide median removes them
    (experiments/select_nearness_denoise.md). On the halved map a 7×7 median spans 14×14 pixels at a quarter of
    the cost of one over the whole map."""
    if window == 1:
        return disparity
    h, w = disparity.shape[-2:]
    filtered = _median_filter(F.avg_pool2d(disparity, 2, ceil_mode=True), window)
    return F.interpolate(filtered, scale_factor=2, mode="nearest")[..., :h, :w]


def _median_by_share(disparity: torch.Tensor, sparse: torch.Tensor, config: NearnessNetConfig) -> torch.Tensor:
    """:func:`_median_halved` of each map ``(B, 1, h, w)`` with ``config.median_window``, or
    ``config.sparse_median_window`` for the ``sparse`` ``(B,)`` pairs: those whose block matcher accepted less
    than ``config.sparse_share`` of the view."""
    if config.sparse_median_window == config.median_window or not bool(sparse.any()):
        return _median_halved(disparity, config.median_window)
    if bool(sparse.all()):
        return _median_halved(disparity, config.sparse_median_window)
    out = torch.empty_like(disparity)
    for pick, window in ((~sparse, config.median_window), (sparse, config.sparse_median_window)):
        index = pick.nonzero().flatten()
        out[index] = _median_halved(disparity.index_select(0, index), window)
    return out


def _median_filter(image: torch.Tensor, window: int) -> torch.Tensor:
    """The ``window``-sided median (``torch.median``'s, the lower one) of each pixel of ``image`` ``(B, 1, h, w)``,
    edges replicated. The compiled kernel (:func:`svs_torch.segmentation.kernels.median_filter`: a selection network
    over 16 pixels at a time up to 7×7, the median tracked from pixel to pixel above; the halved map of a 320×240
    pair in 0.9 ms where the torch path takes 16) gives the values of the torch path below, which sorts every
    window, bit for bit. Not differentiable (the map it filters is measured without gradients)."""
    fast = kernels.median_filter(image, window)
    if fast is not None:
        return fast
    if image.numel() == 0:
        return image.clone()
    pad = window // 2
    windows = F.pad(image, (pad, pad, pad, pad), mode="replicate").unfold(2, window, 1).unfold(3, window, 1)
    return windows.reshape(*image.shape, window * window).median(-1).values

