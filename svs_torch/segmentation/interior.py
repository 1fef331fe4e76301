"""Kept regions cut to their interior: their border pixels given back to the background.

A block matcher fattens what is near: a window straddling a depth edge takes the disparity of its stronger
texture, most often the near surface's, so a near region cut from a block-matched map (the nearness segmenter,
:mod:`.nearness`: a 7-pixel window at 320 working pixels, then a median) reaches a few pixels past its obstacle
onto the background behind it. Those pixels pull the region's median depth back, and their dense disparities
straddle the same edge. Measured over its interior instead (the region eroded by a square of a few working
pixels), an object's distance is that of the obstacle, not of the band around it. A region too thin to keep half
of its pixels through the erosion (a pole, a branch) stays whole: it has no interior to measure.

Chosen on the tuned split only (``experiments/select_region_interior.md``).
"""

from __future__ import annotations

import torch

from ..core.checks import InputError, check_dtype, check_shape
from ..core.kernels.checks import canonical_bool
from ..core.mask_reductions import any_along, any_true
from . import kernels
from .morphology import erode, structuring_element

__all__ = ["region_interiors"]


def region_interiors(labels: torch.Tensor, kept_labels: torch.Tensor, radius_px: int, pairs: torch.Tensor,
                     min_share: float = 0.5) -> torch.Tensor:
    """``labels`` with the kept regions of ``pairs`` cut to their interior (module docstring).

    Args:
        labels: ``(B, 1, H, W)`` int64 region labels, 0 background.
        kept_labels: ``(B, N)`` int64 labels of the kept regions (≤ 0: an empty slot).
        radius_px: the erosion's radius, pixels: a square of side ``2 · radius_px + 1`` (OpenCV's ``cv2.erode``;
            the image border erodes nothing). 0 changes nothing.
        pairs: ``(B,)`` bool, the pairs to cut; the others keep their labels.
        min_share: a region is cut only where its interior holds at least this share of its pixels.

    Returns:
        The labels with the border pixels of the cut regions set to 0; every other pixel as it was. Not
        differentiable (which pixels belong to a region is a decision of the hard pass).
    """
    dims = check_shape(labels, "labels", ["B", 1, "H", "W"])
    check_dtype(labels, "labels", "int")
    b = dims["B"]
    check_shape(kept_labels, "kept_labels", [b, "N"])
    check_shape(pairs, "pairs", [b])
    # Their dtypes and the share were the kernel's contract alone: elsewhere a complex or float kept_labels, a
    # float or int pairs and a string share raised from deep inside torch or were taken in silence (an audit).
    check_dtype(kept_labels, "kept_labels", "int")
    check_dtype(pairs, "pairs", "bool")
    if isinstance(min_share, bool) or not isinstance(min_share, (int, float)):  # NaN or ±inf: none or every one
        raise InputError(f"min_share: expected a real number, got {min_share!r}")
    if isinstance(radius_px, bool) or not isinstance(radius_px, int) or radius_px < 0:
        raise InputError(f"radius_px: expected an int >= 0, got {radius_px!r}")
    pairs = canonical_bool(pairs)  # a mask viewed from other bytes: nonzero is True, on both paths
    if radius_px == 0 or kept_labels.shape[1] == 0 or not any_true(pairs):
        return labels
    fused = kernels.region_interiors(labels, kept_labels, radius_px, pairs, min_share)
    if fused is not None:  # the same labels, each pair read once (svs_torch/segmentation/kernels/region_interiors.c)
        return fused
    flat = labels.flatten(1)
    region = flat.unsqueeze(1) == torch.where(kept_labels > 0, kept_labels, -1).unsqueeze(-1)  # (B, N, H·W)
    kept = any_along(region, 1)
    # Kept regions are separate components of one mask, so eroding their union erodes each on its own.
    inside = erode(kept.view_as(labels), structuring_element("square", 2 * radius_px + 1, device=labels.device))
    inside = inside.flatten(1)
    total, interior = region.sum(-1), (region & inside.unsqueeze(1)).sum(-1)
    cut = (interior >= min_share * total) & (total > 0) & pairs.view(b, 1)
    border = kept & ~inside & any_along(region & cut.unsqueeze(-1), 1)
    return torch.where(border.view_as(labels), torch.zeros_like(labels), labels)
