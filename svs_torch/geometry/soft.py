"""The geometry of the differentiable pass (issue 31): the rectifying homographies the hard pipeline used, with
gradients to both images through the matched points, F and Hartley's rectification.

The hard pipeline decides everything discrete (the keypoints, the matches, RANSAC's inliers, which pairs are
rectified from F); this module recomputes the continuous chain from the images given those decisions:

1. **Matched right points** (:func:`lk_points_straight_through`): the hard Lucas–Kanade refinement
   (:func:`~svs_torch.geometry.lk_refinement.refine_matches_lk`) leaves each right point where its patch best aligns
   with the left keypoint's patch. One Gauss–Newton step from that point, computed from the images with gradients,
   is (almost) zero there, and its derivative w.r.t. the images is the derivative of the optimum (the implicit
   function theorem, with the Gauss–Newton Hessian). The point is ``hard + (step − step.detach())``: the hard value, the
   step's gradient. The left points (SURF keypoints) carry none.
2. **F** (:func:`refit_fundamental_straight_through`): the weighted normalised 8-point
   (:func:`~svs_torch.geometry.epipolar.fundamental_8point`) on RANSAC's inliers, straight-through onto RANSAC's F (the
   values are RANSAC's, the gradients the refit's).
3. **Homographies**: :func:`~svs_torch.geometry.rectification.rectify_uncalibrated` of that F (its maths is smooth in F)
   for pairs rectified from F; for row-aligned pairs the right view's similarity refitted by least squares on the
   alignment's inliers (:func:`~svs_torch.geometry.row_alignment.row_alignment_homography`); both straight-through onto
   the hard homographies (:func:`geometry_straight_through`). Unrectified pairs keep the identity, a constant.
"""

from __future__ import annotations

import torch

from ..core.checks import check_dtypes
from .epipolar import fundamental_8point
from .lk_refinement import LK_GRID_HALF_WIDTH, _centre, _sample_patches
from .rectification import RectificationConfig, rectify_uncalibrated
from .row_alignment import row_alignment_homography

__all__ = ["MIN_REFIT_INLIERS", "geometry_straight_through", "lk_points_straight_through", "lk_step",
           "refit_fundamental_straight_through", "straight_through"]

#: Fewest inliers for a pair's F to be refitted: the 8-point's normal matrix needs 8 in general position, and one
#: more keeps its smallest eigenvalue apart from the next (whose gap the eigenvector's gradient divides by).
MIN_REFIT_INLIERS = 9


def straight_through(hard: torch.Tensor, soft: torch.Tensor) -> torch.Tensor:
    """``hard``'s values with ``soft``'s gradient: ``hard + (soft − soft.detach())``, in ``soft``'s dtype."""
    return hard.detach().to(soft.dtype) + (soft - soft.detach())


def _lk_grid(radius: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The refinement's sample offsets ``(B, K, P, 2)`` and Gaussian weights ``(B, K, P)`` for patch radii
    ``(B, K)`` (the same grid as :func:`~svs_torch.geometry.lk_refinement._refine_lk_torch`)."""
    half = LK_GRID_HALF_WIDTH
    grid = torch.arange(-half, half + 1, dtype=radius.dtype, device=radius.device)
    v, u = torch.meshgrid(grid, grid, indexing="ij")
    unit = torch.stack([u.reshape(-1), v.reshape(-1)], -1)  # (P, 2)
    offsets = unit * (radius / half).clamp_min(1.0)[..., None, None]
    distance_sq = (offsets ** 2).sum(-1)
    radius = radius.unsqueeze(-1)
    weight = torch.exp(-distance_sq / (2 * (radius / 2) ** 2)) * (distance_sq <= (radius + 0.5) ** 2)
    return offsets, weight / weight.sum(-1, keepdim=True)


def lk_points_straight_through(left: torch.Tensor, right: torch.Tensor, xy_left: torch.Tensor,
                               xy_right: torch.Tensor, radius: torch.Tensor, moved: torch.Tensor) -> torch.Tensor:
    """The hard refined right points ``xy_right`` ``(B, K, 2)`` with the gradient of :func:`lk_step` from them
    (module docstring, 1). Differentiable w.r.t. both images; the values are ``xy_right``'s. The step's
    Gauss–Newton Hessian stands in for the full one: against finite differences of the refinement (Art at 160×120,
    float64, converged) its gradient was off by 16–18 % (median relative error; an audit)."""
    return straight_through(xy_right, lk_step(left, right, xy_left, xy_right, radius, moved))


def lk_step(left: torch.Tensor, right: torch.Tensor, xy_left: torch.Tensor, xy_right: torch.Tensor,
            radius: torch.Tensor, moved: torch.Tensor) -> torch.Tensor:
    """One inverse-compositional Gauss–Newton step ``(B, K, 2)`` of the hard refinement from the right points
    ``xy_right`` ``(B, K, 2)``: images ``(B, 1, H, W)``, left keypoints ``xy_left`` ``(B, K, 2)`` (constants), patch
    radii ``radius`` ``(B, K)`` pixels, and ``moved`` ``(B, K)`` bool, the rows the hard refinement moved (elsewhere
    the point is a keypoint's position: step 0, no gradient). Differentiable w.r.t. both images.

    Raises:
        InputError: images not float32 / float64 (float16's Hessian solve raised NotImplementedError from inside
            torch), or ``moved`` not bool."""
    check_dtypes(left=(left, "float"), right=(right, "float"), moved=(moved, "bool"))
    dtype = left.dtype
    offsets, weight = _lk_grid(radius.detach().to(dtype))
    xy_left, xy_right = xy_left.detach().to(dtype), xy_right.detach().to(dtype)
    template, rms = _centre(_sample_patches(left, xy_left, offsets), weight)
    template = template / rms
    step_xy = torch.eye(2, dtype=dtype, device=left.device) * 0.5
    gradient = torch.stack([(_sample_patches(left, xy_left, offsets + step_xy[i])
                             - _sample_patches(left, xy_left, offsets - step_xy[i])) / rms for i in range(2)], -1)
    # As the hard refinement: the Jacobian of the standardised patch (mean and template components removed).
    gradient = gradient - (gradient * weight.unsqueeze(-1)).sum(-2, keepdim=True)
    gradient = gradient - template.unsqueeze(-1) * (gradient * (weight * template).unsqueeze(-1)).sum(-2, keepdim=True)
    weighted_gradient = gradient * weight.unsqueeze(-1)  # (B, K, P, 2)
    hessian = weighted_gradient.transpose(-1, -2) @ gradient  # (B, K, 2, 2)
    # Unusable rows (flat patches, not moved) get the identity: finite, and their step is masked out below.
    usable = moved & (torch.linalg.det(hessian.detach()).abs() > 1e-12)
    hessian = torch.where(usable[..., None, None], hessian, torch.eye(2, dtype=dtype, device=left.device))
    warped, warped_rms = _centre(_sample_patches(right, xy_right, offsets), weight)
    residual = warped / warped_rms - template  # (B, K, P)
    rhs = (residual.unsqueeze(-2) @ weighted_gradient).squeeze(-2)  # (B, K, 2)
    step = -torch.linalg.solve(hessian, rhs.unsqueeze(-1)).squeeze(-1)
    return torch.where(usable.unsqueeze(-1), step, torch.zeros_like(step))


def refit_fundamental_straight_through(F_hard: torch.Tensor, points_left: torch.Tensor, points_right: torch.Tensor,
                                       inliers: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """RANSAC's ``F_hard`` ``(B, 3, 3)`` with the gradient of the weighted normalised 8-point on its ``inliers``
    ``(B, K)`` bool, and ``(B,)`` bool the pairs refitted (at least :data:`MIN_REFIT_INLIERS` inliers; the others
    keep ``F_hard`` as a constant). Points ``(B, K, 2)`` pixels. Differentiable w.r.t. the points."""
    refit = inliers.sum(dim=1) >= MIN_REFIT_INLIERS
    index = refit.nonzero().squeeze(1)
    F = F_hard.detach().to(points_right.dtype)
    if index.numel() == 0:
        return F, refit
    # Only the refitted pairs enter the 8-point: an ill-posed pair's eigenvector gradient would be NaN, and a
    # NaN times a zero upstream gradient is still NaN.
    soft = fundamental_8point(points_left[index], points_right[index], inliers[index].to(points_right.dtype))
    # Both are unit norm with a positive largest entry; a refit whose sign convention flips (a near-tie of the
    # largest entries) is turned to RANSAC's so the gradient points the same way as the value.
    sign = torch.where((soft.detach() * F[index]).sum(dim=(1, 2), keepdim=True) < 0, -1.0, 1.0).to(soft.dtype)
    return F.index_put((index,), straight_through(F[index], sign * soft)), refit


def geometry_straight_through(left: torch.Tensor, right: torch.Tensor, xy_left: torch.Tensor,
                              xy_right: torch.Tensor, radius: torch.Tensor, moved: torch.Tensor,
                              inliers: torch.Tensor, F_hard: torch.Tensor, from_F: torch.Tensor,
                              row_inliers: torch.Tensor, from_rows: torch.Tensor, H_left: torch.Tensor,
                              H_right: torch.Tensor, image_hw: torch.Tensor, config: RectificationConfig,
                              focal_px: torch.Tensor | None = None, row_turn_deg: torch.Tensor | None = None
                              ) -> tuple[torch.Tensor, torch.Tensor]:
    """The hard homographies ``H_left``, ``H_right`` ``(B, 3, 3)``, with gradients to the images ``(B, 1, H, W)``
    (those the matches were refined on) through the matched points ``xy_left``, ``xy_right`` ``(B, K, 2)``
    (refinement ``radius`` and ``moved`` as :func:`lk_points_straight_through` takes them) where the pair was
    rectified from RANSAC's ``F_hard`` with its ``inliers`` ``(B, K)`` (``from_F`` ``(B,)``: F refitted, then
    Hartley's method), or row-aligned (``from_rows`` ``(B,)``: the similarity refitted on ``row_inliers``
    ``(B, K)``, with the keystone's turn terms of ``row_turn_deg`` ``(B, 2)`` and ``focal_px`` ``(B,)`` where given:
    :func:`~svs_torch.geometry.row_alignment.row_alignment_homography`). Elsewhere, and for pairs with too
    few inliers to refit, the homographies are constants. Differentiable w.r.t. both images."""
    dtype = left.dtype
    use_F = from_F & (inliers.sum(dim=1) >= MIN_REFIT_INLIERS)
    use_rows = from_rows & ~from_F & (row_inliers.sum(dim=1) >= MIN_REFIT_INLIERS)
    H_left_out, H_right_out = H_left.detach().to(dtype), H_right.detach().to(dtype)
    index = (use_F | use_rows).nonzero().squeeze(1)
    if index.numel() == 0:
        return H_left_out, H_right_out
    points = xy_right.detach().to(dtype).index_put((index,), lk_points_straight_through(
        left[index], right[index], xy_left[index], xy_right[index], radius[index], moved[index]))
    xy_left = xy_left.detach().to(dtype)
    fitted = use_F.nonzero().squeeze(1)
    if fitted.numel():
        F, _ = refit_fundamental_straight_through(F_hard[fitted], xy_left[fitted], points[fitted], inliers[fitted])
        soft = rectify_uncalibrated(F, xy_left[fitted], points[fitted], inliers[fitted], image_hw[fitted], config)
        H_left_out = H_left_out.index_put((fitted,), straight_through(H_left_out[fitted], soft.H_left))
        H_right_out = H_right_out.index_put((fitted,), straight_through(H_right_out[fitted], soft.H_right))
    aligned = use_rows.nonzero().squeeze(1)
    if aligned.numel():
        turn = None if row_turn_deg is None else row_turn_deg[aligned]
        focal = None if focal_px is None else focal_px[aligned]
        soft = row_alignment_homography(xy_left[aligned], points[aligned], row_inliers[aligned], image_hw[aligned],
                                        focal, turn)
        H_right_out = H_right_out.index_put((aligned,), straight_through(H_right_out[aligned], soft.to(dtype)))
    return H_left_out, H_right_out
