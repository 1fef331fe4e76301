"""Matched points: the coordinates of each match's two keypoints, gathered from the matches' indices
(:class:`MatchedPoints`), what the refinement, RANSAC and the depth rule take.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from ..core.checks import InputError, check_dtype, check_instance, check_shape
from ..core.types import Matches

__all__ = ["MatchedPoints", "gather_matched_points"]


class MatchedPoints(NamedTuple):
    """Matched point pairs aligned with the left keypoints, the input of RANSAC.

    Attributes:
        left: ``(B, K, 2)`` left keypoint positions (pixels), zero where not matched.
        right: ``(B, K, 2)`` the matched right keypoint positions, zero where not matched.
        valid: ``(B, K)`` bool, rows holding a match.
    """

    left: torch.Tensor
    right: torch.Tensor
    valid: torch.Tensor


def gather_matched_points(xy_left: torch.Tensor, xy_right: torch.Tensor, matches: Matches) -> MatchedPoints:
    """The matched point pairs as padded tensors aligned with the left keypoints, for RANSAC.

    Args:
        xy_left: ``(B, K, 2)`` left keypoint positions (pixels); xy_right: ``(B, K2, 2)``.
        matches: :class:`Matches` with ``idx (B, K)``.

    Returns:
        :class:`MatchedPoints` ``left (B, K, 2)``, ``right (B, K, 2)``, ``valid (B, K)``; row k is left keypoint
        k, so an inlier mask over these rows indexes the left keypoints directly. Differentiable w.r.t. the
        positions (gather), not the indices.
    """
    dims = check_shape(xy_left, "xy_left", ["B", "K", 2])
    check_shape(xy_right, "xy_right", [dims["B"], "K2", 2])
    check_instance(matches, "matches", Matches)  # an (idx,) tuple failed on .idx (an audit)
    check_shape(matches.idx, "matches.idx", [dims["B"], dims["K"]])
    check_dtype(matches.idx, "matches.idx", "int")
    # An index past the right keypoints failed inside torch's gather, and with no right keypoints at all it
    # matched the point (0, 0) in silence (an audit).
    low, high = (int(v) for v in torch.aminmax(matches.idx)) if matches.idx.numel() else (-1, -1)
    if not -1 <= low <= high < xy_right.shape[1]:
        raise InputError(f"matches.idx: expected right keypoint indices in [0, {xy_right.shape[1]}) or -1 (no "
                         f"match), got values in [{low}, {high}]")
    valid = matches.idx >= 0
    if xy_right.shape[1] == 0:
        right = torch.zeros_like(xy_left)
    else:
        right = xy_right.gather(1, matches.idx.clamp(min=0).unsqueeze(-1).expand(-1, -1, 2))
    zero = torch.zeros((), dtype=xy_left.dtype, device=xy_left.device)
    mask = valid.unsqueeze(-1)
    return MatchedPoints(left=torch.where(mask, xy_left, zero), right=torch.where(mask, right, zero), valid=valid)
