"""The keystone model of :mod:`svs_torch.geometry.row_alignment` (its module docstring, "Keystone"): a right camera
turned about its y or x axis moves a right pixel ``(u, v)`` from the image centre to the left row
``a·v + b·u + t + p·u·v/f + q·v²/f``; its least-squares fit over given inliers, the homography that undoes the turn
and then the similarity, and the row residuals under a homography. Differentiable w.r.t. the points given the
inliers (the differentiable pass refits through :func:`keystone_refit`)."""

from __future__ import annotations

import torch

from ..core.numerics import safe_sqrt

__all__ = ["keystone_design", "keystone_homography", "keystone_refit", "mapped_row_residuals"]


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
