"""The keystone model of :mod:`svs_torch.geometry.row_alignment` (its module docstring, "Keystone"): a right camera
turned about its y or x axis moves a right pixel ``(u, v)`` from the image centre to the left row
``a·v + b·u + t + p·u·v/f + q·v²/f``; its least-squares fit over given inliers, the homography that undoes the turn
and then the similarity, the row residuals under a homography, and what an alignment says of the right camera
(:func:`right_camera_deviation`). Differentiable w.r.t. the points given the inliers (the differentiable pass
refits through :func:`keystone_refit`)."""

from __future__ import annotations

import torch

from ..core.checks import check_dtype, check_shape
from ..core.numerics import safe_sqrt

__all__ = ["keystone_design", "keystone_homography", "keystone_refit", "mapped_row_residuals", "right_camera_deviation"]


def keystone_design(right: torch.Tensor, image_hw: torch.Tensor, focal_px: torch.Tensor,
                    terms: torch.Tensor) -> torch.Tensor:
    """The keystone model's design ``(B, K, 5)``: ``(v, u, 1, u·v/f, v²/f)`` of the right points in pixels from the
    image centre, the last two zeroed where ``terms`` ``(B, 2)`` bool is False. Differentiable w.r.t. ``right``
    and ``focal_px``."""
    cy, cx = ((image_hw.to(right.dtype) - 1) / 2).unbind(-1)
    u, v = right[..., 0] - cx[:, None], right[..., 1] - cy[:, None]
    f, keep = focal_px.to(right.dtype)[:, None], terms.to(right.dtype)
    return torch.stack([v, u, torch.ones_like(u), keep[:, :1] * u * v / f, keep[:, 1:] * v * v / f], -1)


def keystone_refit(left: torch.Tensor, right: torch.Tensor, inliers: torch.Tensor, image_hw: torch.Tensor,
                   focal_px: torch.Tensor, terms: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Least-squares ``(a, b, t, p, q)`` ``(B, 5)`` of ``y_l = a·v + b·u + t + p·u·v/f + q·v²/f`` (rows from the
    centre) over each pair's inliers, and their standard errors ``(B, 5)`` (unused terms: p or q held at 0).
    Both differentiable w.r.t. ``left``, ``right`` and ``focal_px`` given the inliers."""
    design = keystone_design(right, image_hw, focal_px, terms)
    target = left[..., 1] - (image_hw[:, :1].to(left.dtype) - 1) / 2
    weight = inliers.to(design.dtype)
    weighted = design * weight[..., None]
    normal = weighted.transpose(1, 2) @ design + 1e-9 * torch.eye(5, dtype=design.dtype, device=design.device)
    params = torch.linalg.solve(normal, weighted.transpose(1, 2) @ target[..., None]).squeeze(-1)
    residual = (design @ params[..., None]).squeeze(-1) - target
    variance = (weight * residual ** 2).sum(1) / (weight.sum(1) - 5).clamp(min=1)
    error_square = torch.linalg.inv(normal).diagonal(dim1=-2, dim2=-1) * variance[:, None]
    # A pair without inliers (or an exact fit) has 0 here, where sqrt's infinite derivative made a NaN gradient.
    return params, safe_sqrt(error_square)


def keystone_homography(params: torch.Tensor, image_hw: torch.Tensor, focal_px: torch.Tensor) -> torch.Tensor:
    """``(B, 3, 3)``: undo the turn's keystone about the image centre, then the similarity ``(a, b, t)`` (module
    docstring, "Keystone"). Differentiable w.r.t. ``params`` and ``focal_px``."""
    a, b, t, p, q = params.unbind(-1)
    cy, cx = ((image_hw.to(params.dtype) - 1) / 2).unbind(-1)
    zero, one = torch.zeros_like(a), torch.ones_like(a)

    def matrix(*rows: tuple[torch.Tensor, ...]) -> torch.Tensor:
        return torch.stack([torch.stack(row, -1) for row in rows], -2)

    to_centre = matrix((one, zero, -cx), (zero, one, -cy), (zero, zero, one))
    from_centre = matrix((one, zero, cx), (zero, one, cy), (zero, zero, one))
    similarity = matrix((a, -b, zero), (b, a, t), (zero, zero, one))
    unturn = matrix((one, zero, zero), (zero, one, zero), (-p / (a * focal_px), -q / (a * focal_px), one))
    return from_centre @ similarity @ unturn @ to_centre


def mapped_row_residuals(homography: torch.Tensor, left: torch.Tensor, right: torch.Tensor) -> torch.Tensor:
    """|row of ``homography`` applied to the right points − left row| ``(B, K)``. Differentiable w.r.t.
    ``homography`` and both points (not at a zero residual, a kink)."""
    mapped = torch.cat([right, torch.ones_like(right[..., :1])], -1) @ homography.transpose(1, 2)
    return (mapped[..., 1] / mapped[..., 2] - left[..., 1]).abs()


def right_camera_deviation(H_right: torch.Tensor, image_hw: torch.Tensor
                           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """What a row alignment ``H_right`` ``(B, 3, 3)`` (right pixels to aligned ones) says of the right camera, in the
    terms ``experiments/real_rig.py`` misaligns it with: its roll about the optical axis (degrees; positive turns
    the view as ``cv2.getRotationMatrix2D`` with a negative angle does: clockwise on the screen), the vertical shift of
    its image centre (pixels; positive: the view lower) and its scale (1: none), each ``(B,)`` float64. Read from the
    inverse map (the ideal view's pixels to the camera's) at the image centre ``(image_hw − 1) / 2``, where the
    keystone's unturn is the identity to first order (a rig's roll, height and zoom difference read back; a wide
    lens's distortion and a near scene's vertical disparities, which the alignment absorbs too, add their own).
    The identity reads 0, 0 and 1. ``image_hw`` ``(B, 2)``: each pair's (height, width), as
    ``StereoBatch.image_hw``. Differentiable w.r.t. ``H_right``."""
    b = check_shape(H_right, "H_right", ["B", 3, 3])["B"]
    check_dtype(H_right, "H_right", "float")
    check_shape(image_hw, "image_hw", [b, 2])
    camera = torch.linalg.inv(H_right.to(torch.float64))
    cy, cx = ((image_hw.to(torch.float64) - 1) / 2).unbind(-1)
    mapped = (camera @ torch.stack([cx, cy, torch.ones_like(cx)], -1)[..., None]).squeeze(-1)
    w = mapped[:, 2, None, None]
    # The projective map's Jacobian at the centre, (A·w − q·hᵀ) / w² (A its upper-left 2×2, h its last row's first
    # two, q and w the centre mapped): the similarity's rotation and scale.
    jacobian = (camera[:, :2, :2] * w - mapped[:, :2, None] * camera[:, None, 2, :2]) / w ** 2
    roll_deg = torch.rad2deg(torch.atan2(jacobian[:, 1, 0], jacobian[:, 0, 0]))
    return roll_deg, mapped[:, 1] / mapped[:, 2] - cy, torch.hypot(jacobian[:, 1, 0], jacobian[:, 0, 0])
