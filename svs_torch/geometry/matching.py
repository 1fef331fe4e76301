"""Descriptor matching by the sum of absolute differences (paper Sec. 3.3 (2)).

The paper matches SURF descriptors with the SAD measure through MATLAB's ``matchFeatures``, whose defaults are
kept here: nearest neighbour, ratio test with MaxRatio 0.6, an optional MatchThreshold, and an optional unique
(forward–backward, i.e. mutual) check. Two gates the paper's pipeline benefits from are added as options:
SURF's Laplacian sign (a dark blob never matches a bright one) and an epipolar band ``|y_left − y_right| ≤ b``
for a nearly rectified rig such as the SVS.

Shapes: B pairs, K left and K2 right keypoints (padded), D descriptor length.
"""

from __future__ import annotations

import math
import numbers

import torch

from ..core.checks import InputError, all_finite, check_dtype, check_flag, check_shape
from ..core.types import Matches
from . import kernels
from .lk_refinement import MatchRefinementConfig, refine_matched_points, refine_matches_lk
from .match_ratios import MATLAB_MAX_RATIO
from .matched_points import MatchedPoints, gather_matched_points

__all__ = [
    "MatchRefinementConfig", "MatchedPoints", "gather_matched_points", "match_sad", "max_sad_distance",
    "refine_matched_points", "refine_matches_lk"
]


#: Distance matrices are built for groups of pairs holding at most this many entries (float32: 64 MB), so
#: memory stays bounded for large batches; pairs never interact, so grouping changes no result.
_MAX_ENTRIES_PER_GROUP = 1 << 24


def max_sad_distance(descriptor_length: int) -> float:
    """The largest SAD between two unit-L2-norm descriptors of length D: ``2·√D``.

    ``‖u − v‖₁ ≤ √D·‖u − v‖₂ ≤ 2√D`` (Cauchy–Schwarz, then the triangle inequality). MATLAB's
    ``matchFeatures`` normalises non-binary descriptors to unit L2 norm and expresses MatchThreshold as a percent
    of this largest distance, so ``MatchThreshold = T`` means ``SAD ≤ T/100 · 2√D`` (1.6 for T = 10, D = 64).
    """
    if isinstance(descriptor_length, bool) or not isinstance(descriptor_length, int) or descriptor_length < 1:
        raise InputError(f"descriptor_length: expected a positive int, got {descriptor_length!r}")  # -5: math domain
    return 2.0 * math.sqrt(descriptor_length)


def _check_match_args(desc_left: torch.Tensor, desc_right: torch.Tensor, valid_left: torch.Tensor,
                      valid_right: torch.Tensor) -> dict[str, int]:
    dims = check_shape(desc_left, "desc_left", ["B", "K", "D"])
    dims.update(check_shape(desc_right, "desc_right", [dims["B"], "K2", dims["D"]]))
    check_dtype(desc_left, "desc_left", "float")
    check_dtype(desc_right, "desc_right", "float")
    if desc_right.dtype != desc_left.dtype:  # cdist would refuse the mix from deep inside torch
        raise InputError(f"desc_right: expected the dtype of desc_left, {desc_left.dtype}, got {desc_right.dtype}")
    check_shape(valid_left, "valid_left", [dims["B"], dims["K"]])
    check_dtype(valid_left, "valid_left", "bool")
    check_shape(valid_right, "valid_right", [dims["B"], dims["K2"]])
    check_dtype(valid_right, "valid_right", "bool")
    # A NaN distance is the least to argmin (the torch path's mutual check) and no distance to the kernel: the two
    # paths matched differently. Padding may hold anything; only valid rows are read.
    for name, desc, valid in (("desc_left", desc_left, valid_left), ("desc_right", desc_right, valid_right)):
        if not all_finite(desc) and not bool(
                torch.where(valid.unsqueeze(-1), desc.detach(), 0.0).isfinite().all()):
            raise InputError(f"{name}: expected finite descriptors in valid rows (NaN or inf found)")
    return dims


def _real(value: object) -> float:
    """``value`` as a float where it is a real number (numpy's too; not a bool, a string or a tensor), else NaN,
    which every range check refuses."""
    return float(value) if isinstance(value, numbers.Real) and not isinstance(value, bool) else math.nan


def _check_gates(dims: dict[str, int], laplacian_left: torch.Tensor | None, laplacian_right: torch.Tensor | None,
                 xy_left: torch.Tensor | None, xy_right: torch.Tensor | None,
                 epipolar_band_px: float | None) -> None:
    if (laplacian_left is None) != (laplacian_right is None):
        raise InputError("laplacian_right: expected it together with laplacian_left (both or neither)")
    if laplacian_left is not None:
        check_shape(laplacian_left, "laplacian_left", [dims["B"], dims["K"]])
        check_shape(laplacian_right, "laplacian_right", [dims["B"], dims["K2"]])
        check_dtype(laplacian_left, "laplacian_left", "int")
        check_dtype(laplacian_right, "laplacian_right", "int")
    if epipolar_band_px is None:
        return
    # A string or a tensor raised from the comparison or a slice, and inf was refused as the kernel's "band_px".
    if not 0 <= _real(epipolar_band_px) < math.inf:
        raise InputError(f"epipolar_band_px: expected a finite non-negative number of pixels, got {epipolar_band_px!r}")
    if xy_left is None or xy_right is None:
        raise InputError("xy_left: expected xy_left and xy_right with epipolar_band_px")
    check_shape(xy_left, "xy_left", [dims["B"], dims["K"], 2])
    check_shape(xy_right, "xy_right", [dims["B"], dims["K2"], 2])
    check_dtype(xy_left, "xy_left", "float")  # the kernel's own check named its y_left, no argument of this call
    check_dtype(xy_right, "xy_right", "float")


def _allowed(valid_left: torch.Tensor, valid_right: torch.Tensor, laplacian_left: torch.Tensor | None,
             laplacian_right: torch.Tensor | None, xy_left: torch.Tensor | None, xy_right: torch.Tensor | None,
             epipolar_band_px: float | None) -> torch.Tensor:
    """Candidate mask ``(b, K, K2)``: both valid, same Laplacian sign, inside the epipolar band."""
    allowed = valid_left.unsqueeze(-1) & valid_right.unsqueeze(-2)
    if laplacian_left is not None:
        allowed &= laplacian_left.unsqueeze(-1) == laplacian_right.unsqueeze(-2)
    if epipolar_band_px is not None:
        allowed &= (xy_left[..., 1].unsqueeze(-1) - xy_right[..., 1].unsqueeze(-2)).abs() <= epipolar_band_px
    return allowed


def _match_group(desc_left: torch.Tensor, desc_right: torch.Tensor, gates: tuple, max_ratio: float,
                 max_cost: float | None, mutual: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest neighbour, ratio test, threshold and mutual check for a group of pairs: idx, cost ``(b, K)``.
    ``gates``: :func:`_allowed`'s arguments. Without gradients, float32 descriptors on CPU take the C kernel of
    :mod:`svs_torch.geometry.kernels`: the same search without the mask or the distance matrix, each left row against
    the right descriptors of its Laplacian sign only, each distance summed over d in order (on real descriptors
    the same matches and costs as ``cdist``; another summation order could differ in the last bits)."""
    found = None
    if not (torch.is_grad_enabled() and (desc_left.requires_grad or desc_right.requires_grad)):
        valid_left, valid_right, sign_left, sign_right, xy_left, xy_right, band_px = gates
        found = kernels.sad_nearest(desc_left, desc_right, valid_left, valid_right, sign_left, sign_right,
                                    None if band_px is None else xy_left[..., 1],
                                    None if band_px is None else xy_right[..., 1], band_px)
    if found is not None:
        best, second, idx, back = found
    else:
        allowed = _allowed(*gates)
        distance = torch.cdist(desc_left, desc_right, p=1)  # (b, K, K2) SAD
        distance = torch.where(allowed, distance, math.inf)
        nearest = torch.topk(distance, k=min(2, distance.shape[-1]), dim=-1, largest=False)  # sorted ascending
        best, idx = nearest.values[..., 0], nearest.indices[..., 0]
        second = nearest.values[..., 1] if distance.shape[-1] > 1 else torch.full_like(best, math.inf)
        back = distance.argmin(dim=-2) if mutual else None  # (b, K2) best left index for each right keypoint
    # MATLAB's ratio test d1/d2 ≤ MaxRatio; d1 = d2 = 0 (two identical candidates) is ambiguous and rejected.
    keep = best.isfinite() & (best <= max_ratio * second) & (second > 0)
    if max_cost is not None:
        keep &= best <= max_cost
    if mutual:
        # MATLAB's Unique: match back from the right and keep the pairs that agree (first index on ties).
        rows = torch.arange(desc_left.shape[-2], device=idx.device)
        keep &= back.gather(-1, idx) == rows
    return torch.where(keep, idx, -1), torch.where(keep, best, math.inf)


def _used_rows(valid: torch.Tensor) -> int:
    """1 + the last valid row index over the batch (0 when nothing is valid)."""
    if valid.numel() == 0:  # no keypoint rows, or no pairs (B = 0)
        return 0
    rows = torch.arange(1, valid.shape[1] + 1, device=valid.device)
    return int((valid * rows).amax())


def match_sad(
    desc_left: torch.Tensor,
    desc_right: torch.Tensor,
    valid_left: torch.Tensor,
    valid_right: torch.Tensor,
    *,
    max_ratio: float = MATLAB_MAX_RATIO,
    match_threshold: float | None = None,
    mutual: bool = False,
    laplacian_left: torch.Tensor | None = None,
    laplacian_right: torch.Tensor | None = None,
    xy_left: torch.Tensor | None = None,
    xy_right: torch.Tensor | None = None,
    epipolar_band_px: float | None = None,
) -> Matches:
    """Match each left descriptor to its nearest right descriptor by SAD (paper Sec. 3.3 (2)).

    Args:
        desc_left: ``(B, K, D)`` left descriptors; desc_right: ``(B, K2, D)``.
        valid_left: ``(B, K)`` bool; valid_right: ``(B, K2)`` bool. Padding never matches and is never a
            nearest or second-nearest neighbour.
        max_ratio: ratio test ``d1 ≤ max_ratio · d2`` between the nearest and second-nearest allowed right
            descriptor (MATLAB MaxRatio, default 0.6). A left keypoint with a single allowed candidate passes;
            1.0 disables the test (except for exact ties at distance 0, which are always ambiguous).
        match_threshold: MATLAB MatchThreshold, a percent (0, 100] of the largest possible distance: keep
            ``d1 ≤ match_threshold/100 · 2√D``, exact for unit-L2-norm descriptors (:func:`max_sad_distance`).
            None (default) keeps every distance; MATLAB's own default 1.0 is very strict for SAD (0.16 at D=64).
        mutual: keep only mutual nearest neighbours (MATLAB ``Unique``: forward–backward matching).
        laplacian_left, laplacian_right: optional ``(B, K)``, ``(B, K2)`` int Laplacian signs
            (:attr:`Keypoints.laplacian_sign`); only equal signs are candidates (SURF, Bay et al. Sec. 4.3).
        xy_left, xy_right: ``(B, K, 2)``, ``(B, K2, 2)`` pixels; needed with ``epipolar_band_px``.
        epipolar_band_px: optional; only right keypoints with ``|y_left − y_right| ≤ band`` are candidates.

    The gates act before the neighbour search, so the ratio test compares allowed candidates only.

    Returns:
        :class:`Matches`: ``idx (B, K)`` int64 into the right keypoints, −1 unmatched; ``cost (B, K)`` the SAD of
        the match (input dtype), inf where unmatched. ``cost`` is differentiable w.r.t. the descriptors
        (subgradient of |·|); ``idx`` is not (argmin).
    """
    dims = _check_match_args(desc_left, desc_right, valid_left, valid_right)
    check_flag(mutual, "mutual")  # 'no' was truthy: a mutual check in silence
    _check_gates(dims, laplacian_left, laplacian_right, xy_left, xy_right, epipolar_band_px)
    max_cost = _max_cost(max_ratio, match_threshold, dims["D"])
    b, k, k2 = dims["B"], dims["K"], dims["K2"]
    idx = torch.full((b, k), -1, dtype=torch.int64, device=desc_left.device)
    cost = torch.full((b, k), math.inf, dtype=desc_left.dtype, device=desc_left.device)
    # Padding never matches and is never a candidate: search only up to the last valid row of any pair (a
    # detector pads at the end, often by more than half), then pad the result back to K.
    used, used2 = _used_rows(valid_left), _used_rows(valid_right)
    if used == 0 or used2 == 0:
        return Matches(idx=idx, cost=cost)
    if (used, used2) != (k, k2):
        d_l, v_l, s_l, xy_l = (None if v is None else v[:, :used]
                               for v in (desc_left, valid_left, laplacian_left, xy_left))
        d_r, v_r, s_r, xy_r = (None if v is None else v[:, :used2]
                               for v in (desc_right, valid_right, laplacian_right, xy_right))
        matches = match_sad(d_l, d_r, v_l, v_r, max_ratio=max_ratio, match_threshold=match_threshold, mutual=mutual,
                            laplacian_left=s_l, laplacian_right=s_r, xy_left=xy_l, xy_right=xy_r,
                            epipolar_band_px=epipolar_band_px)
        idx[:, :used], cost[:, :used] = matches.idx, matches.cost
        return Matches(idx=idx, cost=cost)
    gates = (valid_left, valid_right, laplacian_left, laplacian_right, xy_left, xy_right, epipolar_band_px)
    idx, cost = _match_in_groups(desc_left, desc_right, gates, max_ratio, max_cost, mutual)
    return Matches(idx=idx, cost=cost)


def _max_cost(max_ratio: float, match_threshold: float | None, descriptor_length: int) -> float | None:
    """The largest SAD a match may have (None: any), after checking the ratio test's and the threshold's values."""
    # _real: a string ('0.8', as read from a file) raised TypeError from the comparison, naming nothing.
    if not 0 < _real(max_ratio) <= 1:
        raise InputError(f"max_ratio: expected a value in (0, 1], got {max_ratio!r}")
    if match_threshold is not None and not 0 < _real(match_threshold) <= 100:
        raise InputError(f"match_threshold: expected a percent in (0, 100], got {match_threshold!r}")
    return None if match_threshold is None else match_threshold / 100.0 * max_sad_distance(descriptor_length)


def _match_in_groups(desc_left: torch.Tensor, desc_right: torch.Tensor, gates: tuple, max_ratio: float,
                     max_cost: float | None, mutual: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`_match_group` over groups of pairs whose distance matrices hold about ``_MAX_ENTRIES_PER_GROUP``
    entries together (the gates' tensors taken per group, the band as it is)."""
    b, k, k2 = desc_left.shape[0], desc_left.shape[1], desc_right.shape[1]
    group = max(1, _MAX_ENTRIES_PER_GROUP // (k * k2))
    idx_parts, cost_parts = [], []
    for start in range(0, b, group):
        part = slice(start, start + group)
        picked = tuple(value[part] if isinstance(value, torch.Tensor) else value for value in gates)
        group_idx, group_cost = _match_group(desc_left[part], desc_right[part], picked, max_ratio, max_cost, mutual)
        idx_parts.append(group_idx)
        cost_parts.append(group_cost)
    return torch.cat(idx_parts), torch.cat(cost_parts)
