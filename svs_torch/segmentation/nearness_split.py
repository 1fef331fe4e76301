"""Where the nearness rule splits a measured disparity map into near and far (:mod:`.nearness`, step 2).

The split is the Otsu threshold of the filled disparity's 256-level histogram, the truth's rule applied to the
estimate. A block matcher's wrong matches lie far above the scene, so the histogram spans the map only up to its
99.5th percentile; where even that leaves less than ``min_near_share`` of the view near (more outliers than the
clip holds), the split is taken again up to the 90th percentile, the top of the spread
(``experiments/select_min_near_share.md``). A split taken again that lies inside one surface's disparities is not
taken, and the first split stands: the near side was no outliers but a small near object before a flat wall, whose
disparities hold the 90th percentile, so the second split falls below the whole wall (a clean pair: nearly the
whole view left near, ``max_retaken_near_share``) or cuts its noise in two (a camera frame: both sides' median
disparities within ``min_retaken_gap`` of each other, where the tuning suite's 598 second splits part their sides
by 17 % or more). Either way the wall was kept with the object and named the nearest obstacle (a 0.25 × 0.4 m box
1.25–2 m before a wall at 4.5 m, 3–6 % of the view; ``experiments/small_near_obstacles.md``). Not differentiable:
the split is a threshold (gradients of the rule's logits flow through the disparity, not the split).
"""

from __future__ import annotations

import math

import torch

from ..core.checks import check_dtype, check_real, check_shape
from ..core.mask_reductions import all_along, any_true
from ..depth.quantiles import labelled_quantile, row_quantile
from . import kernels
from .threshold import gray_histogram, gray_levels, otsu_threshold_level

__all__ = ["nearness_split"]


def nearness_split(disparity: torch.Tensor, min_near_share: float, exclude: torch.Tensor | None = None,
                   max_retaken_near_share: float = 1.0, min_retaken_gap: float = 0.0
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The split ``(B,)`` of filled disparity maps ``(B, 1, H, W)`` (module docstring), their 10–90 % spread
    ``(B,)`` (at least 1 px) and which pairs' split was taken again under the 90th percentile ``(B,)`` bool
    (``min_near_share`` 0: never; a second split leaving more than ``max_retaken_near_share`` of the pixels near,
    or whose sides' median disparities differ by less than ``min_retaken_gap`` of the near side's, is not taken;
    1 and 0: always). ``exclude`` ``(B, 1, H, W)`` bool: pixels left out of every statistic (the floor,
    :mod:`.ground_plane`: it spans every disparity from the feet to the horizon and would move the split by its
    extent rather than by the obstacles'); a pair that excludes every pixel keeps them all. Not differentiable
    (``disparity`` is detached: module docstring)."""
    # Called by hand, a float exclude failed in a bitwise and, one of another size in the quantiles naming their
    # labels, a map without its channel axis was taken (an audit). Shares past [0, 1] mean never or always.
    b = check_shape(disparity, "disparity", ["B", 1, "H", "W"])["B"]
    check_dtype(disparity, "disparity", "float")
    if exclude is not None:
        check_shape(exclude, "exclude", list(disparity.shape))
        check_dtype(exclude, "exclude", "bool")
    for name, value in (("min_near_share", min_near_share), ("max_retaken_near_share", max_retaken_near_share),
                        ("min_retaken_gap", min_retaken_gap)):
        check_real(value, name)
    disparity = disparity.detach()
    if exclude is not None:
        exclude = exclude & ~all_along(exclude.flatten(1), 1).view(b, 1, 1, 1)
        if not any_true(exclude):
            exclude = None
    if exclude is None:
        q = row_quantile(disparity.flatten(1), (0.1, 0.9, 0.995)).T
    else:  # the same quantiles of the pixels left in (label 1), the compiled selection where it runs
        kept = (~exclude).flatten(1).to(torch.int64)
        q = labelled_quantile(disparity.flatten(1), kept, torch.ones_like(kept[:, :1]), (0.1, 0.9, 0.995))
        q = q.values[:, 0].T
    spread = (q[1] - q[0]).clamp_min(1.0)
    split, retaken = _splits(disparity, exclude, q, min_near_share)
    if (max_retaken_near_share < 1 or min_retaken_gap > 0) and any_true(retaken):
        undo = retaken & ((_near_share(disparity, split, exclude) > max_retaken_near_share)
                          | (_sides_gap(disparity, split, exclude, retaken) < min_retaken_gap))
        if any_true(undo):
            first, _ = _splits(disparity, exclude, q, 0.0)
            split, retaken = torch.where(undo, first, split), retaken & ~undo
    return split, spread, retaken


def _sides_gap(disparity: torch.Tensor, split: torch.Tensor, exclude: torch.Tensor | None, pairs: torch.Tensor
               ) -> torch.Tensor:
    """``(B,)`` for the maps ``pairs`` ``(B,)`` bool: the difference of the median disparities above and at or below
    ``split`` over the one above (of the pixels not in ``exclude``; 1 where a side is empty); ``inf`` elsewhere."""
    b = disparity.shape[0]
    side = torch.where(disparity > split.view(b, 1, 1, 1), 1, 2)
    if exclude is not None:
        side = side.masked_fill(exclude, 0)
    side = side.masked_fill(~pairs.view(b, 1, 1, 1), 0).flatten(1)  # the other pairs take no median
    slots = torch.tensor([[1, 2]], device=disparity.device).expand(b, 2)
    medians = labelled_quantile(disparity.flatten(1), side, slots, (0.5,))
    near, far = medians.values[:, 0, 0], medians.values[:, 1, 0]
    gap = torch.where(medians.valid.all(1), (near - far) / near.clamp_min(1e-6), 1.0)
    return torch.where(pairs, gap, math.inf)


def _splits(disparity: torch.Tensor, exclude: torch.Tensor | None, q: torch.Tensor, min_near_share: float
            ) -> tuple[torch.Tensor, torch.Tensor]:
    """The Otsu split ``(B,)`` of each map under its 99.5th percentile ``q[2]``, taken again under its 90th
    ``q[1]`` where it leaves less than ``min_near_share`` near, and which pairs' was ``(B,)`` bool."""
    b = disparity.shape[0]
    # The compiled split: the steps below in one kernel, four reads of the map instead of a dozen passes (the same
    # values; at guide's B = 1 on a 320×240 camera frame 1.4–1.8 ms → 0.3, the percentiles above unchanged).
    fast = kernels.nearness_split(disparity.flatten(1), None if exclude is None else exclude.flatten(1), q[2], q[1],
                                  min_near_share)
    if fast is not None:
        return fast
    # The histogram spans the map's [min, 99.5 %]: a few wrong matches far above the rest (Tsukuba at 7×7: up to
    # 113 px where 99 % lie under 20) would otherwise squeeze the scene into a few levels and move the split
    # above nearly every pixel.
    split = _otsu_split(torch.minimum(disparity, q[2].view(b, 1, 1, 1)), exclude)
    return _split_leaving_near(disparity, split, q[1], min_near_share, exclude)


def _near_share(disparity: torch.Tensor, split: torch.Tensor, exclude: torch.Tensor | None) -> torch.Tensor:
    """``(B,)`` the share of each map's pixels (those not in ``exclude``) above its ``split``."""
    near = disparity > split.view(-1, 1, 1, 1)
    if exclude is None:
        return near.flatten(1).to(torch.float32).mean(1)
    return (near & ~exclude).flatten(1).sum(1) / (~exclude).flatten(1).sum(1).clamp_min(1)


def _otsu_split(disparity: torch.Tensor, exclude: torch.Tensor | None = None) -> torch.Tensor:
    """``(B,)`` the disparity at the Otsu split of each map's 256-level histogram over its [min, max] (of the
    pixels not in ``exclude``)."""
    flat = disparity.flatten(1)
    if exclude is None:
        low, high = flat.amin(1), flat.amax(1)
    else:
        left_out = exclude.flatten(1)
        low, high = flat.masked_fill(left_out, math.inf).amin(1), flat.masked_fill(left_out, -math.inf).amax(1)
    spread = (high - low).view(-1, 1, 1, 1)
    scaled = (disparity - low.view(-1, 1, 1, 1)) / torch.where(spread > 0, spread, 1.0)
    level = otsu_threshold_level(gray_histogram(gray_levels(scaled), exclude))
    return low + (level.to(flat.dtype) + 0.5) / 255 * (high - low)


def _split_leaving_near(disparity: torch.Tensor, split: torch.Tensor, upper_px: torch.Tensor,
                        min_near_share: float, exclude: torch.Tensor | None = None
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """``split`` ``(B,)``, or where it leaves less than ``min_near_share`` of the map ``(B, 1, H, W)`` above it,
    the Otsu split of the map clipped at ``upper_px`` ``(B,)`` (its 90th percentile, the spread's top) instead;
    and which pairs' split was taken again ``(B,)`` bool.

    Why: a few per cent of wrong matches far above the scene pass the 99.5 % clip and draw the split above
    nearly every pixel (the tuned PianoL at 320×240, clean: 2.6 % of the view matched above 25 working px where
    90 % lie under 18, the 99.5th percentile at 62; the split at 26 px left 2.5 % of the view near, the kept
    regions were specks and the pair went unranged, ``NO_DENSE_DEPTH``). Clipped at the 90th percentile, the
    split (11.5 px) stays inside the scene. Only such a split is taken again: one that leaves this share near
    is left as it was."""
    b = disparity.shape[0]
    never = torch.zeros(b, dtype=torch.bool, device=disparity.device)
    if min_near_share <= 0:
        return split, never
    redo = _near_share(disparity, split, exclude) < min_near_share
    if not bool(redo.any()):
        return split, never
    clipped = _otsu_split(torch.minimum(disparity, upper_px.view(b, 1, 1, 1)), exclude)
    return torch.where(redo, clipped, split), redo
