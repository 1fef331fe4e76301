"""Row alignment of a loosely mounted right camera: a similarity of the right view that puts every match on its
left row (roll, vertical shift and scale of a real rig's second board), fitted robustly to the putative matches.

Why not only the fundamental matrix: the SVS's obstacles are a few nearly planar regions, so F fitted to a few
dozen of their matches is loose, and the projective rectification derived from it is often refused (epipole
"in the image") or adds shear; a right camera turned by 2° about its optical axis or moved by 3 % of the image
height then leaves the dense stage matching along the wrong rows (``experiments/real_rig.py``). A similarity has
three free parameters that depth does not touch: with ``p' = A p`` for a right pixel ``p = (x, y)`` and

    A = [[a, −b, t_x], [b, a, t_y], [0, 0, 1]],

a match ``(p_left, p_right)`` of an ideal rig satisfies ``b·x_r + a·y_r + t_y = y_l`` whatever its disparity,
one linear equation per match: three matches fix ``(a, b, t_y)``. ``t_x`` cannot be told from disparity, so the
image centre keeps its column (the two principal points stay where they were). A keystone (a camera turned about
its x or y axis by ~1°) is not modelled: measured, it costs under a point at 320×240.

Batched over pairs: RANSAC over 3-match samples (the seeded counter-based draws of :mod:`svs_torch.geometry.ransac`, so
a pair's result does not depend on its batch), then a least-squares refit on the inliers. Not differentiable (the
inlier sets are discrete); the refit is differentiable w.r.t. the points given the inliers. The hypotheses' MSAC
costs are summed by a compiled kernel beside this stage (``kernels/row_alignment_cost.c``), whose torch reference
is :func:`_msac_cost`'s own expression.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..core.checks import InputError, check_dtype, check_shape
from . import kernels
from .ransac_sampling import draw_minimal_samples

__all__ = ["RowAlignment", "RowAlignmentConfig", "fit_row_alignment", "row_alignment_homography"]

_SAMPLE = 3  # matches per minimal sample: one row equation each, three unknowns (a, b, t_y)


@dataclass(frozen=True)
class RowAlignmentConfig:
    """Options of :func:`fit_row_alignment`.

    Attributes:
        threshold_px: a match is an inlier when the aligned right row is within this of the left row, pixels.
        num_hypotheses: 3-match samples per pair.
        min_inliers: fewest inliers to accept an alignment.
        min_inlier_share: least share of the matches that must be inliers.
        min_gain: the alignment must put at least ``max(min_gain, min_gain_share · n₀)`` more matches on their
            rows than the raw rows do (n₀ of them): with a dozen matches, three free parameters also fit a couple
            of wrong matches (Middlebury PianoL at 320×240: 10 of 11 aligned against 8 raw, a spurious 1° roll
            that cost 6 points).
        min_gain_share: see ``min_gain``.
        max_roll_deg, max_scale_change, max_shift_fraction: the largest roll, relative scale change and vertical
            shift (share of the height) accepted; beyond them the views are not a side-by-side rig.
        min_correction_px: the pipeline applies the alignment only where it moves some image corner's row by
            more than this (pixels); a straighter rig keeps its raw rows (``PipelineConfig.rectify="auto"``).
    """

    threshold_px: float = 1.0
    num_hypotheses: int = 256
    min_inliers: int = 7
    min_inlier_share: float = 0.25
    min_gain: int = 3
    min_gain_share: float = 0.25
    max_roll_deg: float = 5.0
    max_scale_change: float = 0.1
    max_shift_fraction: float = 0.1
    min_correction_px: float = 1.0

    def __post_init__(self) -> None:
        if not (self.threshold_px > 0 and self.max_roll_deg > 0 and self.max_scale_change > 0
                and self.max_shift_fraction > 0 and self.min_correction_px >= 0):
            raise InputError("RowAlignmentConfig: expected threshold_px, max_roll_deg, max_scale_change and "
                             "max_shift_fraction > 0 and min_correction_px >= 0")
        if not (isinstance(self.num_hypotheses, int) and self.num_hypotheses >= 1):
            raise InputError(f"num_hypotheses: expected an int >= 1, got {self.num_hypotheses!r}")
        if not (isinstance(self.min_inliers, int) and self.min_inliers >= _SAMPLE):
            raise InputError(f"min_inliers: expected an int >= {_SAMPLE}, got {self.min_inliers!r}")
        if not 0 <= self.min_inlier_share <= 1:
            raise InputError(f"min_inlier_share: expected a share in [0, 1], got {self.min_inlier_share!r}")


@dataclass(frozen=True)
class RowAlignment:
    """Per-pair row alignment (B pairs).

    Attributes:
        H_right: ``(B, 3, 3)`` right pixels to aligned pixels (the identity where not ``valid``).
        inliers: ``(B, K)`` bool, matches on their left row after the alignment.
        num_inliers: ``(B,)`` int64.
        correction_px: ``(B,)`` the largest row displacement of an image corner, pixels (0 where not ``valid``).
        valid: ``(B,)`` bool, an alignment within the config's limits was found.
    """

    H_right: torch.Tensor
    inliers: torch.Tensor
    num_inliers: torch.Tensor
    correction_px: torch.Tensor
    valid: torch.Tensor


def _row_residuals(params: torch.Tensor, left: torch.Tensor, right: torch.Tensor) -> torch.Tensor:
    """|b·x_r + a·y_r + t_y − y_l| ``(B, M, K)`` for parameters ``(B, M, 3)`` = (a, b, t_y) and points
    ``(B, K, 2)``."""
    a, b, t = params.unbind(-1)
    aligned = b[..., None] * right[:, None, :, 0] + a[..., None] * right[:, None, :, 1] + t[..., None]
    return (aligned - left[:, None, :, 1]).abs()


def _msac_cost(params: torch.Tensor, left: torch.Tensor, right: torch.Tensor, valid: torch.Tensor,
               threshold_px: float) -> torch.Tensor:
    """MSAC cost ``(B, M)`` of each hypothesis: its truncated squared row errors summed over the valid matches,
    +inf for a degenerate sample. The compiled kernel (:func:`svs_torch.geometry.kernels.row_alignment_cost`) sums
    each hypothesis in one pass; this torch expression is its reference, which writes ``(B, M, K)`` arrays."""
    fast = kernels.row_alignment_cost(params, left[..., 1], right[..., 0], right[..., 1], valid, threshold_px)
    if fast is not None:
        return fast
    residuals = _row_residuals(params, left, right)  # (B, M, K)
    cost = torch.where(valid[:, None], residuals.clamp(max=threshold_px) ** 2, 0.0).sum(-1)
    return torch.where(params.isnan().any(-1), float("inf"), cost)


def _sample_params(left: torch.Tensor, right: torch.Tensor, valid: torch.Tensor, seeds: torch.Tensor,
                   num_hypotheses: int) -> torch.Tensor:
    """(a, b, t_y) of each pair's 3-match samples ``(B, M, 3)``, NaN where a sample is degenerate."""
    if valid.shape[1] == 0:  # no match rows at all: nothing to sample (every hypothesis degenerate)
        return torch.full((valid.shape[0], num_hypotheses, 3), float("nan"), dtype=left.dtype, device=left.device)
    order = torch.argsort((~valid).to(torch.int8), dim=1, stable=True)  # valid rows first
    ranks = draw_minimal_samples(seeds, 0, num_hypotheses, valid.sum(1), _SAMPLE)  # (B, M, 3)
    # A pair with fewer than three matches has ranks past its rows: kept in range, and its samples dropped below.
    rows = torch.gather(order, 1, ranks.clamp(max=valid.shape[1] - 1).flatten(1)).view_as(ranks)

    def pick(points: torch.Tensor, coordinate: int) -> torch.Tensor:
        return torch.gather(points[..., coordinate], 1, rows.flatten(1)).view_as(rows)

    system = torch.stack([pick(right, 1), pick(right, 0), torch.ones_like(pick(right, 0))], -1)  # (B, M, 3, 3)
    target = pick(left, 1).unsqueeze(-1)
    # Collinear or repeated samples make the system singular: their hypotheses are dropped, not perturbed.
    scale = system[..., :2].abs().amax((-1, -2)).clamp(min=1.0)
    ok = (torch.linalg.det(system / scale[..., None, None]).abs() > 1e-6) & (valid.sum(1, keepdim=True) >= _SAMPLE)
    identity = torch.eye(3, dtype=system.dtype, device=system.device).expand_as(system)
    safe = torch.where(ok[..., None, None], system, identity)
    params = torch.linalg.solve(safe, target).squeeze(-1)
    return torch.where(ok[..., None], params, torch.full_like(params, float("nan")))


def _refit(left: torch.Tensor, right: torch.Tensor, inliers: torch.Tensor) -> torch.Tensor:
    """Least-squares (a, b, t_y) ``(B, 3)`` over each pair's inliers (normal equations, masked)."""
    design = torch.stack([right[..., 1], right[..., 0], torch.ones_like(right[..., 0])], -1)  # (B, K, 3)
    weight = inliers.to(design.dtype).unsqueeze(-1)
    normal = (design * weight).transpose(1, 2) @ design + 1e-9 * torch.eye(3, dtype=design.dtype, device=design.device)
    rhs = (design * weight).transpose(1, 2) @ left[..., 1:2]
    return torch.linalg.solve(normal, rhs).squeeze(-1)


def _homography(params: torch.Tensor, image_hw: torch.Tensor) -> torch.Tensor:
    """``A`` ``(B, 3, 3)`` with t_x keeping the image centre's column (module docstring)."""
    a, b, t_y = params.unbind(-1)
    cy, cx = ((image_hw.to(params.dtype) - 1) / 2).unbind(-1)
    t_x = cx - (a * cx - b * cy)
    zero, one = torch.zeros_like(a), torch.ones_like(a)
    return torch.stack([torch.stack([a, -b, t_x], -1), torch.stack([b, a, t_y], -1),
                        torch.stack([zero, zero, one], -1)], -2)


def fit_row_alignment(points_left: torch.Tensor, points_right: torch.Tensor, valid: torch.Tensor,
                      image_hw: torch.Tensor, config: RowAlignmentConfig = RowAlignmentConfig(),
                      pair_seeds: torch.Tensor | None = None) -> RowAlignment:
    """Fit each pair's right-view similarity that puts its matches on their left rows (module docstring).

    Args:
        points_left, points_right: ``(B, K, 2)`` matched pixels (x = column).
        valid: ``(B, K)`` bool, rows holding a match.
        image_hw: ``(B, 2)`` int64, each pair's (height, width).
        config: :class:`RowAlignmentConfig`.
        pair_seeds: ``(B,)`` int64 seeds of the samples (default 0 for every pair).
    """
    dims = check_shape(points_left, "points_left", ["B", "K", 2])
    check_shape(points_right, "points_right", [dims["B"], dims["K"], 2])
    check_shape(valid, "valid", [dims["B"], dims["K"]])
    check_shape(image_hw, "image_hw", [dims["B"], 2])
    check_dtype(points_left, "points_left", "float")
    if valid.dtype != torch.bool:
        raise InputError(f"valid: expected a bool tensor, got {valid.dtype}")
    left, right = points_left.to(torch.float64), points_right.to(torch.float64)
    seeds = torch.zeros(dims["B"], dtype=torch.int64, device=left.device) if pair_seeds is None else pair_seeds
    params = _sample_params(left, right, valid, seeds, config.num_hypotheses)
    cost = _msac_cost(params, left, right, valid, config.threshold_px)
    best = torch.gather(params, 1, cost.argmin(1).view(-1, 1, 1).expand(-1, 1, 3)).squeeze(1)
    inliers = valid & (_row_residuals(best.nan_to_num().unsqueeze(1), left, right)[:, 0] < config.threshold_px)
    refit = _refit(left, right, inliers)
    inliers = valid & (_row_residuals(refit.unsqueeze(1), left, right)[:, 0] < config.threshold_px)
    raw = (valid & ((left[..., 1] - right[..., 1]).abs() < config.threshold_px)).sum(1)
    return _accept(refit, inliers, valid, raw, image_hw, config)


def _accept(params: torch.Tensor, inliers: torch.Tensor, valid: torch.Tensor, raw: torch.Tensor,
            image_hw: torch.Tensor, config: RowAlignmentConfig) -> RowAlignment:
    """The alignment where it has enough inliers, ``min_gain`` more than the ``raw`` rows' ``(B,)``, and stays
    within the config's limits; the identity elsewhere."""
    a, b, t_y = params.unbind(-1)
    count = inliers.sum(1)
    scale = 1 / torch.hypot(a, b).clamp(min=1e-12)  # the right camera's magnification
    homography = _homography(params, image_hw)
    height, width = image_hw.to(params.dtype).unbind(-1)
    corners = torch.stack([torch.stack([x, y, torch.ones_like(x)], -1) for x, y in
                           ((0 * width, 0 * height), (width - 1, 0 * height), (0 * width, height - 1),
                            (width - 1, height - 1))], 1)  # (B, 4, 3)
    moved = (corners @ homography.transpose(1, 2))[..., 1] - corners[..., 1]
    centre_shift = t_y + b * (width - 1) / 2 + (a - 1) * (height - 1) / 2
    gain = torch.maximum(torch.full_like(raw, config.min_gain), (config.min_gain_share * raw).ceil().long())
    ok = (count >= config.min_inliers) & (count >= config.min_inlier_share * valid.sum(1)) & (count >= raw + gain) \
        & (torch.atan2(b, a).abs() <= math.radians(config.max_roll_deg)) \
        & ((scale - 1).abs() <= config.max_scale_change) \
        & (centre_shift.abs() <= config.max_shift_fraction * height) & params.isfinite().all(-1)
    identity = torch.eye(3, dtype=params.dtype, device=params.device).expand_as(homography)
    return RowAlignment(H_right=torch.where(ok[:, None, None], homography, identity), inliers=inliers & ok[:, None],
                        num_inliers=torch.where(ok, count, 0),
                        correction_px=torch.where(ok, moved.abs().amax(1), torch.zeros_like(a)), valid=ok)


def row_alignment_homography(points_left: torch.Tensor, points_right: torch.Tensor, inliers: torch.Tensor,
                             image_hw: torch.Tensor) -> torch.Tensor:
    """The right view's similarity ``(B, 3, 3)`` refitted by least squares to the matches ``inliers`` ``(B, K)``
    bool (:attr:`RowAlignment.inliers`) of points ``(B, K, 2)`` pixels, for pairs of ``image_hw`` ``(B, 2)``: the
    last step of :func:`fit_row_alignment` given its inliers, in float64. Differentiable w.r.t. the points (the
    differentiable pass of the pipeline takes its gradient, issue 31)."""
    left, right = points_left.to(torch.float64), points_right.to(torch.float64)
    return _homography(_refit(left, right, inliers), image_hw)
