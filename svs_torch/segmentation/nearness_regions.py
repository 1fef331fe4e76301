"""The candidate regions as the nearness rules weigh them: each region's median measured disparity, its area
the right camera sees and the block matcher measured, and the kept regions shifted into the right view.
"""

from __future__ import annotations

import torch

from ..core.checks import check_dtype
from ..core.levels import CLIPPED_LEVEL
from ..depth.quantiles import region_lower_median
from . import kernels
from .components import RegionProperties

__all__ = ["shift_regions_to_right"]


def _region_median_disparity(disparity: torch.Tensor, labels: torch.Tensor, num_regions: torch.Tensor
                             ) -> torch.Tensor:
    """``(B, L)`` lower median disparity of every region of ``labels`` (0 for an empty slot): the values of
    :func:`~svs_torch.depth.kept_region_lower_median` over every label, by
    :func:`~svs_torch.depth.quantiles.region_lower_median` (one selection per region, not a sort per region)."""
    slots = int(num_regions.max()) if num_regions.numel() else 0
    return region_lower_median(disparity.detach().flatten(1), labels.flatten(1), slots)[0]


def _area_measured_in_view(labels: torch.Tensor, regions: RegionProperties, region_disparity: torch.Tensor,
                           measured: torch.Tensor, min_area_px: float) -> torch.Tensor:
    """``(B, L)`` pixels of each region that the block matcher measured (``measured`` ``(B, 1, H, W)``, not
    filled) at columns the right camera sees at the nearest region's disparity (x ≥ the largest median disparity
    of the regions of at least ``min_area_px``): the pixels the dense stage can range (its objects need valid
    pixels where the pair's whole search lands in the right image,
    :func:`~svs_torch.depth.dense_objects.dense_object_depths`). A region of filled rows only, or in the band only the
    left camera sees, would be kept and never ranged (its slot scores 0 % in ``eval``: Midd1, Lampshade1, Rocks1 of the
    shared 2005–2006 scenes did so)."""
    b, slots = regions.area_px.shape
    big = regions.valid & (regions.area_px >= min_area_px)
    if not slots:
        return regions.area_px
    nearest = torch.where(big, region_disparity, torch.zeros_like(region_disparity)).amax(1)  # (B,)
    column = torch.arange(labels.shape[-1], device=labels.device, dtype=nearest.dtype)
    seen = (column.view(1, 1, 1, -1) >= nearest.view(-1, 1, 1, 1)) & measured
    return _label_counts(labels, seen, slots).to(regions.area_px.dtype)


def _label_counts(labels: torch.Tensor, flags: torch.Tensor, slots: int) -> torch.Tensor:
    """``(B, slots)`` int64: how many pixels of each region of ``labels`` ``(B, 1, H, W)`` (1 … ``slots``; 0, the
    background, not counted) ``flags`` ``(B, 1, H, W)`` bool marks. The C kernel of
    :func:`svs_torch.segmentation.kernels.label_counts` where it runs (one pass, no int64 copy of the flags: 12 ms a
    call for 8 pairs at 640x480 before), the same counts."""
    counted = kernels.label_counts(labels.flatten(1), flags.flatten(1), slots)
    if counted is not None:
        return counted
    counts = torch.zeros(labels.shape[0], slots + 1, dtype=torch.int64, device=labels.device)
    counts.scatter_add_(1, labels.flatten(1), flags.flatten(1).to(torch.int64))
    return counts[:, 1:]


def _without_clipped(candidate_area_px: torch.Tensor, labels: torch.Tensor, regions: RegionProperties,
                     left: torch.Tensor, max_share: float | None) -> torch.Tensor:
    """``candidate_area_px`` ``(B, L)`` with 0 for every region of ``labels`` ``(B, 1, H, W)`` holding at least
    ``max_share`` of its pixels clipped at white (:data:`~svs_torch.core.levels.CLIPPED_LEVEL`) in ``left``
    ``(B, 1, H, W)``; unchanged for None. Why: a saturated patch has no texture, so no matcher measures it; its
    nearness is its row fill's, and kept it was left unranged beside a real obstacle (the tuned Piano made bright,
    ``experiments/real_rig.py --brightness 1.4``, at 416×312: a white wall 96 % clipped, measured on 9 % of its
    pixels, the pair at 50 % in 11 of its 22 conditions; experiments/real_rig.md, "Clipped regions")."""
    if max_share is None or candidate_area_px.shape[1] == 0:
        return candidate_area_px
    clipped = _label_counts(labels, left.detach() >= CLIPPED_LEVEL, candidate_area_px.shape[1])
    share = clipped.to(torch.float64) / regions.area_px.clamp_min(1).to(torch.float64)
    return torch.where(share >= max_share, torch.zeros_like(candidate_area_px), candidate_area_px)


def shift_regions_to_right(labels: torch.Tensor, kept_labels: torch.Tensor, shift_px: torch.Tensor
                           ) -> torch.Tensor:
    """The right view's label image ``(B, 1, H, W)``: kept region ``kept_labels[:, n]`` of the left ``labels``
    moved ``shift_px[:, n]`` pixels left (its median disparity, rounded); 0 elsewhere. Where two shifted regions
    overlap the nearer (larger shift) wins, as it occludes the other. Without gradients (it has none to give) the
    C kernel of :func:`svs_torch.segmentation.kernels.shift_regions` computes the same labels row by row."""
    # Float labels were taken in silence (float labels out, the kernel skipped); the kernel checks the shapes.
    check_dtype(labels, "labels", "int")
    check_dtype(kept_labels, "kept_labels", "int")
    check_dtype(shift_px, "shift_px", "float")
    compiled = kernels.shift_regions(labels, kept_labels, shift_px)
    if compiled is not None:
        return compiled
    b, n = kept_labels.shape
    w = labels.shape[-1]
    out = torch.zeros_like(labels)
    best = torch.full_like(labels, -1, dtype=shift_px.dtype)
    column = torch.arange(w, device=labels.device)
    for slot in range(n):  # N slots (the kept regions, 2 by default), not pairs
        shift = shift_px[:, slot].round().long().view(b, 1, 1, 1)
        source = column.view(1, 1, 1, w) + shift
        inside = (source >= 0) & (source < w)
        hit = torch.gather(labels, 3, source.clamp(0, w - 1).expand_as(labels)) == kept_labels[:, slot].view(b, 1, 1, 1)
        hit = hit & inside & (kept_labels[:, slot] > 0).view(b, 1, 1, 1)
        take = hit & (shift_px[:, slot].view(b, 1, 1, 1) > best)
        out = torch.where(take, kept_labels[:, slot].view(b, 1, 1, 1), out)
        best = torch.where(take, shift_px[:, slot].view(b, 1, 1, 1), best)
    return out
