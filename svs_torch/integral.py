"""Integral images and box sums, batched (the basis of SURF, Bay et al. 2008, Sec. 2).

``integral_image(x)[..., r, c]`` is the sum of ``x[..., :r, :c]``: one extra zero row and column, so a box
``[r0, r1) × [c0, c1)`` sums to ``I[r1, c1] − I[r0, c1] − I[r1, c0] + I[r0, c0]`` in four reads, whatever its size.

Two ways of reading boxes:
- :func:`grid_box_sums`: one box shape at every point of a regular grid, by four strided slices (no gather);
- :func:`sample_box_means`: boxes at arbitrary real-valued centres and sizes, by bilinear reads of the
  integral image (exact area integrals of the pixel-constant image along each axis, smooth in position and
  size, and differentiable with respect to the image).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .checks import check_image

__all__ = ["integral_image", "pad_integral", "grid_box_sums", "sample_box_means"]


def integral_image(image: torch.Tensor, subtract_mean: bool = False) -> torch.Tensor:
    """Integral image ``(B, 1, H + 1, W + 1)`` of ``(B, 1, H, W)`` images, in the image's dtype; linear, so
    differentiable.

    With ``subtract_mean``, each image's mean is removed first. Zero-sum filters (the Hessian's) read the
    same responses, while the sums stay near zero instead of growing to 10⁵ over a 640×480 image, so float32
    keeps about five more significant digits in the small boxes.
    """
    check_image(image, "image", check_range=False)
    if subtract_mean:
        image = image - image.mean(dim=(-2, -1), keepdim=True)
    return F.pad(image.cumsum(-2).cumsum(-1), (1, 0, 1, 0))


def pad_integral(integral: torch.Tensor, pad: int) -> torch.Tensor:
    """Extend an integral image by ``pad`` on every side, constant in the outward direction.

    Reads beyond the image then add nothing (a box partly outside sums only its inside part), so box
    corners never need clamping.
    """
    return F.pad(integral, (pad, pad, pad, pad), mode="replicate")


def grid_box_sums(
    padded: torch.Tensor, pad: int, rows: tuple[int, int], cols: tuple[int, int], step: int, size_hw: tuple[int, int]
) -> torch.Tensor:
    """Sum of the box ``[y + rows[0], y + rows[1]) × [x + cols[0], x + cols[1])`` at every grid point.

    Args:
        padded: :func:`pad_integral` output ``(B, C, H + 1 + 2·pad, W + 1 + 2·pad)``.
        pad: the padding used; offsets must stay within it.
        rows, cols: box extent relative to the grid point, in pixels, end exclusive.
        step: grid spacing in pixels; the grid is ``y = 0, step, 2·step, …`` (likewise x).
        size_hw: (ny, nx) grid points.

    Returns:
        ``(B, C, ny, nx)``. Four strided slices, no gather.
    """
    ny, nx = size_hw

    def corner(r: int, c: int) -> torch.Tensor:
        return padded[..., pad + r::step, pad + c::step][..., :ny, :nx]

    (r0, r1), (c0, c1) = rows, cols
    return corner(r1, c1) - corner(r0, c1) - corner(r1, c0) + corner(r0, c0)


def _bilinear_read(integral: torch.Tensor, y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Integral image ``(B, 1, H + 1, W + 1)`` read at real indices ``y, x`` ``(B, P)`` (clamped to the image)."""
    b, _, h1, w1 = integral.shape
    y = y.clamp(0, h1 - 1)
    x = x.clamp(0, w1 - 1)
    # grid_sample with align_corners=True maps −1 and 1 to the first and last index.
    grid = torch.stack([2 * x / max(w1 - 1, 1) - 1, 2 * y / max(h1 - 1, 1) - 1], dim=-1)  # (B, P, 2)
    out = F.grid_sample(integral, grid.view(b, -1, 1, 2).to(integral.dtype), mode="bilinear", align_corners=True)
    return out.view(b, -1)


def sample_box_means(
    integral: torch.Tensor, center_xy: torch.Tensor, half_size: torch.Tensor, half_height: torch.Tensor | None = None
) -> torch.Tensor:
    """Mean intensity of axis-aligned boxes at real-valued centres, from an integral image.

    Args:
        integral: ``(B, 1, H + 1, W + 1)`` from :func:`integral_image`.
        center_xy: ``(B, P, 2)`` box centres, pixel-centre coordinates (pixel j spans [j − 0.5, j + 0.5]).
        half_size: ``(B, P)`` half the box width, pixels (> 0).
        half_height: ``(B, P)`` half the box height; default ``half_size`` (a square box).

    Returns:
        ``(B, P)`` the mean over the part of each box inside the image; a box wholly beyond an edge reads the
        edge pixels (replicate border). Differentiable with respect to the image (and the centres).
    """
    h, w = integral.shape[-2] - 1, integral.shape[-1] - 1
    half_height = half_size if half_height is None else half_height
    # Integral index of the continuous coordinate u is u + 0.5. Clip the box to the image, but keep at least
    # the edge pixel: a box beyond the border reads the edge row / column (replicate border), and the mean of
    # a partly-outside box is the mean of its inside part.
    x0, x1 = _clip_span(center_xy[..., 0] - half_size + 0.5, center_xy[..., 0] + half_size + 0.5, w)
    y0, y1 = _clip_span(center_xy[..., 1] - half_height + 0.5, center_xy[..., 1] + half_height + 0.5, h)
    ys = torch.cat([y1, y0, y1, y0], dim=1)
    xs = torch.cat([x1, x1, x0, x0], dim=1)
    a, b_, c, d = _bilinear_read(integral, ys, xs).chunk(4, dim=1)
    return (a - b_ - c + d) / ((x1 - x0) * (y1 - y0))


def _clip_span(lo: torch.Tensor, hi: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Clip [lo, hi] (integral coordinates) to [0, size], keeping at least the edge pixel [size − 1, size] or
    [0, 1] when the span lies wholly outside."""
    return lo.clamp(0, size).clamp(max=size - 1), hi.clamp(0, size).clamp(min=1)
