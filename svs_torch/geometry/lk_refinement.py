"""Sub-pixel refinement of matched points: a Lucas–Kanade alignment of each right patch on its left patch
(Gauss–Newton on the weighted patch difference), and the correlation gate that drops matches whose patches
disagree; the fused C kernel (``geometry/kernels/lk_refine.c``) where it runs, else the torch path.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F

from ..core.checks import (FLOAT32_MAX, InputError, check_device, check_dtype, check_finite_where, check_image,
                           check_instance, check_shape, real_or_nan)
from ..core.kernels.checks import check_nonempty
from ..core.numerics import safe_sqrt
from ..core.types import Matches
from . import kernels
from .kernels import MAX_LK_ITERATIONS
from .matched_points import MatchedPoints

__all__ = ["LK_GRID_HALF_WIDTH", "MAX_LK_ITERATIONS", "MatchRefinementConfig", "refine_matched_points",
           "refine_matches_lk"]


#: Half-width, in samples, of the patch grid of :func:`refine_matches_lk` (a 13 × 13 grid).
LK_GRID_HALF_WIDTH = 6
#: The largest patch radius: the radii are a float32 tensor (:data:`~svs_torch.core.checks.FLOAT32_MAX`).
_MAX_RADIUS_PX = FLOAT32_MAX


@dataclass(frozen=True)
class MatchRefinementConfig:
    """Settings of :func:`refine_matches_lk` (see its arguments), as a pipeline stage.

    Not in the paper: MATLAB's SURF locates a keypoint only to its box-filter grid, and a fundamental matrix fitted
    to such points is loose. The defaults are the best measured (``experiments/surf_vs_sift.py``: on the 40
    shared Middlebury pairs at 320×240, with the pipeline's MetricThreshold 100 and ratio 0.8, 0.83 of the
    matches lie within 1 px of GT disparity (0.83 at native size), against 0.79 (0.77) for OpenCV SIFT under the
    same ratio rule; ``min_correlation`` 0.7 beats 0.5 and 0. ``fundamental_vs_opencv.py``, 10 seeds: on
    OpenCV's chessboards the median Sampson distance of the true corners to F is 1.4 px (share of runs within
    2 px 0.59), against 2.1 px (0.50) for SIFT + FM_RANSAC; patches capped at 6 px gave 2.4 px, so large
    keypoints get patches up to 12 px, sampled on a 13 × 13 grid.)
    """

    radius_scales: float = 1.5
    min_radius_px: float = 3.0
    max_radius_px: float = 12.0
    iterations: int = 8
    max_shift_px: float = 2.0
    min_correlation: float = 0.7

    def __post_init__(self) -> None:
        if not (isinstance(self.iterations, int) and 0 <= self.iterations <= MAX_LK_ITERATIONS):
            raise InputError(f"iterations: expected an integer from 0 to {MAX_LK_ITERATIONS}, got {self.iterations!r}")
        shift, scales, low, high = (real_or_nan(getattr(self, name)) for name in (
            "max_shift_px", "radius_scales", "min_radius_px", "max_radius_px"))
        if not (shift >= 0 and scales > 0 and 0 < low <= high <= _MAX_RADIUS_PX):
            raise InputError("MatchRefinementConfig: expected max_shift_px >= 0, radius_scales > 0 and "
                             f"0 < min_radius_px <= max_radius_px <= {_MAX_RADIUS_PX:.3g}, got {self.max_shift_px!r}, "
                             f"{self.radius_scales!r}, {self.min_radius_px!r}, {self.max_radius_px!r}")
        if not -1 <= real_or_nan(self.min_correlation) <= 1:
            raise InputError(f"min_correlation: expected a correlation in [-1, 1], got {self.min_correlation!r}")


def refine_matched_points(left: torch.Tensor, right: torch.Tensor, points: MatchedPoints, matches: Matches,
                          scale: torch.Tensor | None, config: MatchRefinementConfig | None
                          ) -> tuple[MatchedPoints, Matches]:
    """:func:`refine_matches_lk` as a pipeline stage: the refined points, and ``matches`` without the rows the
    correlation gate dropped (so match counts and the points agree). ``config`` None: both unchanged. Gradients
    flow to the kept left points and costs (passed through), not to the refined right points (detached)."""
    if config is None:
        return points, matches
    # Another config failed as unknown keywords, matches of another kind on .valid (an audit).
    check_instance(config, "config", MatchRefinementConfig)
    check_instance(matches, "matches", Matches)
    refined = refine_matches_lk(left, right, points, scale, **asdict(config))
    dropped = matches.valid & ~refined.valid
    return refined, Matches(idx=torch.where(dropped, -1, matches.idx),
                            cost=torch.where(dropped, torch.full_like(matches.cost, math.inf), matches.cost))


def _sample_patches(image: torch.Tensor, centres: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """Bilinear samples ``(B, K, P)`` of ``image (B, 1, H, W)`` at ``centres (B, K, 2) + offsets (B, K, P, 2)``
    (pixel-centre coordinates; the border pixel repeats outside), in the dtype of the points."""
    h, w = image.shape[-2:]
    points = centres.unsqueeze(2) + offsets
    scale = torch.tensor([2.0 / max(w - 1, 1), 2.0 / max(h - 1, 1)], dtype=points.dtype, device=points.device)
    grid = (points * scale - 1).to(image.dtype)
    return F.grid_sample(image, grid, mode="bilinear", padding_mode="border", align_corners=True)[:, 0].to(points.dtype)


def _centre(values: torch.Tensor, weight: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Weighted zero-mean patches and their weighted RMS ``(…, 1)`` (clamped away from 0)."""
    centred = values - (values * weight).sum(-1, keepdim=True)
    mean_square = ((centred**2) * weight).sum(-1, keepdim=True)
    # A flat patch's RMS is 0, where sqrt's derivative is infinite and 0 · inf = NaN reached both images' gradients
    # (geometry.soft.lk_step); the clamp gives it 1e-6.
    return centred, safe_sqrt(mean_square).clamp(min=1e-6)


def _check_scale(scale: torch.Tensor | None, valid: torch.Tensor) -> None:
    """``scale`` None or ``(B, K)`` like ``valid``: real, finite in the valid rows, on their device. Only its shape was
    checked (an audit): a NaN scale made a NaN patch radius and moved the points in silence, a bool one was taken
    as 1, a complex one lost its imaginary part with a warning, and a meta one failed deep inside."""
    if scale is None:
        return
    check_shape(scale, "scale", list(valid.shape))
    check_dtype(scale, "scale", "float|int")
    check_device(scale, "scale", valid, "the points'")
    check_finite_where(scale, "scale", valid, "points.valid")


def refine_matches_lk(
    left: torch.Tensor,
    right: torch.Tensor,
    points: MatchedPoints,
    scale: torch.Tensor | None = None,
    *,
    radius_scales: float = 1.5,
    min_radius_px: float = 3.0,
    max_radius_px: float = 12.0,
    iterations: int = 8,
    max_shift_px: float = 2.0,
    min_correlation: float = 0.0,
) -> MatchedPoints:
    """Sub-pixel refinement of matched points: each right point moves to where its patch best aligns with the
    left point's patch (translational Lucas–Kanade, inverse compositional, gain and offset normalised).

    A blob detector localises a keypoint only as well as its box-filter responses and sampling grid allow
    (SURF: 0.2–0.4 px median disparity error on Middlebury, against 0.14 for SIFT). The left point (the
    keypoint) is kept; the right point takes a fixed number of Gauss–Newton steps minimising the Gaussian-
    weighted squared difference of the zero-mean, unit-RMS patches, as KLT refines a track. Batched over pairs
    and matches, fixed step count: deterministic. Float32 images on CPU go through the C kernel of
    :mod:`svs_torch.geometry.kernels` (the same steps, one match at a time; points within about 1e-4 px of the torch
    path, which runs without a compiler or with ``SVS_TORCH_KERNELS=torch``).

    Args:
        left, right: ``(B, 1, H, W)`` float images the points were found on.
        points: :class:`MatchedPoints`: ``left``, ``right`` ``(B, K, 2)`` pixel-centre coordinates, ``valid (B, K)``;
            finite in the valid rows. A valid row with a point more than a pixel outside the image is made invalid.
        scale: optional ``(B, K)`` scale of the left keypoints (SURF s); the patch radius is ``radius_scales · s``
            clamped to [``min_radius_px``, ``max_radius_px``]. None: ``min_radius_px`` for every point.
        radius_scales, min_radius_px, max_radius_px: the patch radius rule. Patches are sampled on a 13 × 13
            grid, every pixel up to radius 6 and every radius / 6 pixels beyond, weighted by a Gaussian of
            σ = radius / 2.
        iterations: Gauss–Newton steps (each clamped to 1 px per axis).
        max_shift_px: a refined point farther than this from its matched position keeps the matched position.
        min_correlation: matches whose final weighted normalised cross-correlation is below this are
            invalidated; the default 0 drops only anti-correlated matches, −1 keeps every match.

    Returns:
        :class:`MatchedPoints`: the same left points, refined right points, ``valid`` a subset of the input's
        (rows that became invalid are zeroed). The left points pass their gradients through; the refined right
        points carry none (a fixed-step optimisation on detached inputs).
    """
    dims = check_image(left, "left", check_range=False)
    check_shape(right, "right", [dims["B"], 1, dims["H"], dims["W"]])
    check_instance(points, "points", MatchedPoints)  # a plain (left, right, valid) tuple failed on .left
    k = check_shape(points.left, "points.left", [dims["B"], "K", 2])["K"]
    check_shape(points.right, "points.right", [dims["B"], k, 2])
    check_shape(points.valid, "points.valid", [dims["B"], k])
    check_dtype(points.valid, "points.valid", "bool")
    check_nonempty(left, "left")
    _check_scale(scale, points.valid)
    if not (0 <= iterations <= MAX_LK_ITERATIONS and max_shift_px >= 0 and 0 < min_radius_px <= max_radius_px
            <= _MAX_RADIUS_PX and radius_scales > 0 and -1 <= min_correlation <= 1):  # NaN fails each
        raise InputError(f"refine_matches_lk: expected 0 <= iterations <= {MAX_LK_ITERATIONS}, max_shift_px >= 0, "
                         f"radius_scales > 0, 0 < min_radius_px <= max_radius_px <= {_MAX_RADIUS_PX:.3g} and "
                         f"min_correlation in [-1, 1], "
                         f"got {iterations}, {max_shift_px}, {radius_scales}, {min_radius_px}, {max_radius_px}, "
                         f"{min_correlation}")
    if k == 0 or not bool(points.valid.any()):
        return points
    points = _inside_only(points, dims["H"], dims["W"])
    # Work on the valid rows only: compacted to the front (a stable sort keeps their order) and cut at the
    # largest count over the batch, so padding costs nothing; scattered back at the end.
    order = torch.argsort((~points.valid).to(torch.int8), dim=1, stable=True)
    k_used = int(points.valid.sum(1).max())
    order = order[:, :k_used]
    compact = MatchedPoints(left=torch.gather(points.left, 1, order.unsqueeze(-1).expand(-1, -1, 2)),
                            right=torch.gather(points.right, 1, order.unsqueeze(-1).expand(-1, -1, 2)),
                            valid=torch.gather(points.valid, 1, order))
    compact_scale = None if scale is None else torch.gather(scale, 1, order)
    refined = _refine_lk(left, right, compact, compact_scale, radius_scales, min_radius_px, max_radius_px,
                         iterations, max_shift_px, min_correlation)
    valid = torch.zeros_like(points.valid).scatter(1, order, refined.valid)
    right_xy = torch.zeros_like(points.right).scatter(1, order.unsqueeze(-1).expand(-1, -1, 2), refined.right)
    zero = torch.zeros((), dtype=points.right.dtype, device=points.right.device)
    mask = valid.unsqueeze(-1)
    return MatchedPoints(left=torch.where(mask, points.left, zero), right=torch.where(mask, right_xy, zero),
                         valid=valid)


def _inside_only(points: MatchedPoints, height: int, width: int) -> MatchedPoints:
    """``points`` with the valid rows whose left or right point lies more than a pixel outside the image made
    invalid (their patches are all border: the C kernel and the torch path judged them apart); a non-finite
    coordinate in a valid row is an InputError (a NaN right point came back valid, and NaN)."""
    both = torch.cat([points.left, points.right], -1).detach()  # (B, K, 4): x, y, x, y
    valid = points.valid
    if not bool(torch.where(valid.unsqueeze(-1), both, 0.0).isfinite().all()):
        raise InputError("points: expected finite coordinates in valid rows (NaN or inf found)")
    limit = torch.tensor([width, height, width, height], dtype=both.dtype, device=both.device)
    inside = ((both >= -1) & (both <= limit)).all(-1)
    if bool((inside | ~valid).all()):
        return points
    keep = valid & inside
    zero = torch.zeros((), dtype=points.left.dtype, device=points.left.device)
    return MatchedPoints(left=torch.where(keep.unsqueeze(-1), points.left, zero),
                         right=torch.where(keep.unsqueeze(-1), points.right, zero), valid=keep)


def _refine_lk(left: torch.Tensor, right: torch.Tensor, points: MatchedPoints, scale: torch.Tensor | None,
               radius_scales: float, min_radius_px: float, max_radius_px: float, iterations: int,
               max_shift_px: float, min_correlation: float) -> MatchedPoints:
    """:func:`refine_matches_lk` on rows already compacted (see there): by the C kernel of
    :mod:`svs_torch.geometry.kernels` where it can be built (the same steps, one match at a time in cache: positions
    within about 1e-4 px of the torch path), else by :func:`_refine_lk_torch`."""
    # float32: positions stay within 1e-4 px of a float64 run, at half the memory traffic.
    dtype, device = torch.float32, left.device
    left, right = left.detach().to(dtype), right.detach().to(dtype)
    if scale is None:
        radius = torch.full(points.valid.shape, float(min_radius_px), dtype=dtype, device=device)
    else:
        radius = (radius_scales * scale.detach().to(dtype)).clamp(min_radius_px, max_radius_px)
    xy_left, xy_right = points.left.detach().to(dtype), points.right.detach().to(dtype)
    found = kernels.lk_refine(left, right, xy_left, xy_right, radius, points.valid, iterations, max_shift_px)
    if found is None:
        return _refine_lk_torch(left, right, points, radius, iterations, max_shift_px, min_correlation)
    refined, correlation = found
    return _refined_points(points, refined, correlation, min_correlation)


def _refined_points(points: MatchedPoints, refined: torch.Tensor, correlation: torch.Tensor,
                    min_correlation: float) -> MatchedPoints:
    """The refined right points in the input's dtype, and the rows whose correlation passes the gate."""
    refined = refined.to(points.right.dtype)
    valid = points.valid & (correlation >= min_correlation) if min_correlation > -1 else points.valid
    zero = torch.zeros((), dtype=points.right.dtype, device=points.right.device)
    mask = valid.unsqueeze(-1)
    return MatchedPoints(left=torch.where(mask, points.left, zero), right=torch.where(mask, refined, zero),
                         valid=valid)


def _refine_lk_torch(left: torch.Tensor, right: torch.Tensor, points: MatchedPoints, radius: torch.Tensor,
                     iterations: int, max_shift_px: float, min_correlation: float) -> MatchedPoints:
    """The refinement in torch, batched over every row at once (the reference of the C kernel)."""
    dtype, device = left.dtype, left.device
    # A (2n+1)² sample grid per point, every pixel up to radius n (the same samples as a dense grid, whose
    # weights beyond the radius are zero) and spaced radius / n beyond: a 12 px patch costs what a 6 px one
    # does (3.7× fewer samples than a dense 25 × 25 grid), sampled every 2 px under a Gaussian of σ = 6 px.
    half = LK_GRID_HALF_WIDTH
    grid = torch.arange(-half, half + 1, dtype=dtype, device=device)
    v, u = torch.meshgrid(grid, grid, indexing="ij")
    unit = torch.stack([u.reshape(-1), v.reshape(-1)], -1)  # (P, 2)
    spacing = (radius / half).clamp_min(1.0)  # (B, K) pixels between samples
    offsets = unit * spacing[..., None, None]  # (B, K, P, 2) pixel offsets
    distance_sq = (offsets**2).sum(-1)  # (B, K, P)
    radius = radius.unsqueeze(-1)
    weight = torch.exp(-distance_sq / (2 * (radius / 2) ** 2)) * (distance_sq <= (radius + 0.5) ** 2)
    weight = weight / weight.sum(-1, keepdim=True)  # (B, K, P)
    xy_left, xy_right = points.left.detach().to(dtype), points.right.detach().to(dtype)
    template, rms = _centre(_sample_patches(left, xy_left, offsets), weight)
    template = template / rms
    # Template gradient: central differences of the bilinear image half a pixel either side, standardised alike.
    step_xy = torch.eye(2, dtype=dtype, device=device) * 0.5
    gradient = torch.stack([(_sample_patches(left, xy_left, offsets + step_xy[i])
                             - _sample_patches(left, xy_left, offsets - step_xy[i])) / rms for i in range(2)], -1)
    # The Jacobian of the standardised patch: remove the gradient's weighted mean and its component along the
    # template (the normalisation absorbs both); without this the Gauss–Newton steps are too short.
    gradient = gradient - (gradient * weight.unsqueeze(-1)).sum(-2, keepdim=True)
    gradient = gradient - template.unsqueeze(-1) * (gradient * (weight * template).unsqueeze(-1)).sum(-2, keepdim=True)
    weighted_gradient = gradient * weight.unsqueeze(-1)  # (B, K, P, 2)
    hessian = weighted_gradient.transpose(-1, -2) @ gradient  # (B, K, 2, 2), batched matmuls
    inverse, info = torch.linalg.inv_ex(hessian)
    solvable = (info == 0) & torch.isfinite(inverse).flatten(-2).all(-1)
    inverse = torch.where(solvable[..., None, None], inverse, torch.zeros_like(inverse))
    # Gauss–Newton: step = −H⁻¹ Σ_p w_p ∇T_p r_p, i.e. (residual row) @ (weighted gradient) then H⁻¹.
    descent = weighted_gradient @ inverse.transpose(-1, -2)  # (B, K, P, 2): H⁻¹ applied once, not per step
    shift = torch.zeros_like(xy_right)
    for _ in range(iterations):
        warped, warped_rms = _centre(_sample_patches(right, xy_right + shift, offsets), weight)
        residual = warped / warped_rms - template
        step = -(residual.unsqueeze(-2) @ descent).squeeze(-2)
        shift = shift + step.clamp(-1.0, 1.0)
    moved = solvable & torch.isfinite(shift).all(-1) & (shift.norm(dim=-1) <= max_shift_px)
    refined = torch.where(moved.unsqueeze(-1), xy_right + shift, xy_right)
    warped, warped_rms = _centre(_sample_patches(right, refined, offsets), weight)
    correlation = (warped / warped_rms * template * weight).sum(-1)  # at the position returned
    return _refined_points(points, refined, correlation, min_correlation)
