"""Integral images and box sums, batched (the basis of SURF, Bay et al. 2008, Sec. 2).

``integral_image(x)[..., r, c]`` is the sum of ``x[..., :r, :c]``: one extra zero row and column, so a box
``[r0, r1) × [c0, c1)`` sums to ``I[r1, c1] − I[r0, c1] − I[r1, c0] + I[r0, c0]`` in four reads, whatever its size.

Ways of reading boxes:
- :func:`grid_box_sums`: one box shape at every point of a regular grid, by four slices of the integral's
  sub-lattices (no gather);
- :func:`sample_box_means` and :func:`sample_cell_means`: boxes at real-valued centres and sizes, by
  bilinear reads of a :class:`PaddedIntegral` (exact area integrals of the pixel-constant image, smooth in
  position and size, and differentiable with respect to the image).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..core.checks import InputError, check_image, check_shape
from .kernels import check_border

__all__ = [
    "PaddedIntegral", "grid_box_corners", "grid_box_sums", "image_means", "integral_image", "integral_phases",
    "pad_integral", "padded_integral_image", "sample_box_means", "sample_cell_means",
]


def integral_image(image: torch.Tensor, subtract_mean: bool = False) -> torch.Tensor:
    """Integral image ``(B, 1, H + 1, W + 1)`` of ``(B, 1, H, W)`` images, in the image's dtype; linear, so
    differentiable.

    With ``subtract_mean``, each image's mean is removed first. Zero-sum filters (the Hessian's) read the
    same responses, while the sums stay near zero instead of growing to 10⁵ over a 640×480 image, so float32
    keeps about five more significant digits in the small boxes.
    """
    check_image(image, "image", check_range=False)
    if subtract_mean:
        image = image - image_means(image).view(-1, 1, 1, 1)
    return F.pad(image.cumsum(-2).cumsum(-1), (1, 0, 1, 0))


def image_means(image: torch.Tensor) -> torch.Tensor:
    """Each image's mean ``(B,)`` of ``(B, 1, H, W)`` images, summed in one fixed order whatever the batch: a
    sequential scan of its pixels (a cumulative sum), not ``mean``, whose reduction torch splits across threads by
    the tensor's shape (1 or 16 images of 320×240 gave 5 of 16 means one ulp apart, so SURF's responses differed
    with the batch size; issue 29). Differentiable (every pixel's weight is ``1 / (H·W)``)."""
    flat = image.reshape(image.shape[0], math.prod(image.shape[1:]))  # (-1 cannot be inferred for no image)
    if flat.shape[1] == 0:
        return flat.sum(dim=1)
    return flat.cumsum(dim=1)[:, -1] / flat.shape[1]


def pad_integral(integral: torch.Tensor, pad: int) -> torch.Tensor:
    """Extend an integral image by ``pad`` on every side, constant in the outward direction.

    Reads beyond the image then add nothing (a box partly outside sums only its inside part), so box
    corners never need clamping. Differentiable with respect to ``integral`` (a replicate pad).
    """
    return F.pad(integral, (pad, pad, pad, pad), mode="replicate")


def integral_phases(padded: torch.Tensor, step: int) -> list[torch.Tensor]:
    """Split a padded integral into its ``step²`` sub-lattices ``padded[..., a::step, b::step]``, contiguous.

    Reading a box at every point of a grid with spacing ``step`` then takes unit-stride slices of one phase per
    corner: on CPU an order of magnitude faster than strided reads, for one extra pass over the table.
    Differentiable with respect to ``padded`` (copies of its slices).
    """
    if step == 1:
        return [padded]
    return [padded[..., a::step, b::step].contiguous() for a in range(step) for b in range(step)]


def grid_box_corners(
    phases: list[torch.Tensor], step: int, pad: int, rows: tuple[int, int], cols: tuple[int, int],
    size_hw: tuple[int, int],
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The four corner views of :func:`grid_box_sums` (bottom-right, top-right, bottom-left, top-left); the
    box sum is ``a − b − c + d``. Views only: nothing is read yet; gradients flow to the phases they view."""
    ny, nx = size_hw

    def corner(r: int, c: int) -> torch.Tensor:
        phase = phases[(pad + r) % step * step + (pad + c) % step]
        top, left = (pad + r) // step, (pad + c) // step
        return phase[..., top:top + ny, left:left + nx]

    (r0, r1), (c0, c1) = rows, cols
    return corner(r1, c1), corner(r0, c1), corner(r1, c0), corner(r0, c0)


def grid_box_sums(
    phases: list[torch.Tensor], step: int, pad: int, rows: tuple[int, int], cols: tuple[int, int],
    size_hw: tuple[int, int],
) -> torch.Tensor:
    """Sum of the box ``[y + rows[0], y + rows[1]) × [x + cols[0], x + cols[1])`` at every grid point.

    Args:
        phases: :func:`integral_phases` of a :func:`pad_integral` output ``(B, C, H + 1 + 2·pad, W + 1 + 2·pad)``.
        step: grid spacing in pixels; the grid is ``y = 0, step, 2·step, …`` (likewise x).
        pad: the padding of the integral; box offsets must stay within it.
        rows, cols: box extent relative to the grid point, in pixels, end exclusive.
        size_hw: (ny, nx) grid points.

    Returns:
        ``(B, C, ny, nx)``. Four unit-stride slices, no gather; linear, so differentiable with respect to
        ``phases``.
    """
    a, b, c, d = grid_box_corners(phases, step, pad, rows, cols, size_hw)
    return a - b - c + d


@dataclass(frozen=True)
class PaddedIntegral:
    """Integral image of an image extended by ``pad`` pixels of replicate border on every side.

    Attributes:
        table: ``(B, 1, H + 2·pad + 1, W + 2·pad + 1)``.
        pad: the border width, pixels. The continuous image coordinate u (pixel j spans [j − 0.5, j + 0.5])
            sits at table index u + 0.5 + pad.
    """

    table: torch.Tensor
    pad: int


def padded_integral_image(image: torch.Tensor, pad: int, subtract_mean: bool = True) -> PaddedIntegral:
    """:class:`PaddedIntegral` of ``(B, 1, H, W)`` images: boxes reaching past the border read the edge pixels
    (replicate border, as OpenCV's ``getRectSubPix``). Linear in the image, so differentiable.

    The table is anchored at the image's top-left corner (table index ``pad, pad`` holds 0): each value is the
    signed sum between that corner and its own, summed outward from the corner, so the values over the image and
    within any border do not depend on ``pad``. Why: a batch's border is as wide as its largest keypoint needs, and
    a table summed from its own corner gave an image other float roundings, so other descriptors, in another batch
    (issue 29). Box sums, differences of four values, are those of the plain integral image; with
    ``subtract_mean`` (the default, as for the zero-sum Haar filters of the descriptor) those of the image less
    its mean (:func:`image_means`), so :func:`sample_box_means` then reads each box's mean less the image's."""
    check_image(image, "image", check_range=False)
    check_border(pad, image.shape[-2], image.shape[-1])
    if subtract_mean:
        image = image - image_means(image).view(-1, 1, 1, 1)
    if pad > 0:
        image = F.pad(image, (pad, pad, pad, pad), mode="replicate")
    return PaddedIntegral(_anchored_cumsum(_anchored_cumsum(image, -1, pad), -2, pad), pad)


def _anchored_cumsum(values: torch.Tensor, dim: int, origin: int) -> torch.Tensor:
    """Signed cumulative sums along ``dim`` at the ``n + 1`` boundaries of ``n`` values, 0 at boundary ``origin``:
    ``Σ values[origin:t]`` after it, ``−Σ values[t:origin]`` before it, each summed outward from ``origin``."""
    n = values.shape[dim]
    after = values.narrow(dim, origin, n - origin).cumsum(dim)
    before = values.narrow(dim, 0, origin).flip(dim).cumsum(dim).flip(dim).neg()
    return torch.cat([before, torch.zeros_like(values.narrow(dim, 0, 1)), after], dim)


def _table_axis(coordinate: torch.Tensor, pad: int, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Where continuous image coordinates fall on a table axis of ``size`` >= 2 (index = coordinate + 0.5 + pad):
    the index before (at most ``size − 2``) and the weight of the one after, the coordinate clamped to the table
    (``grid_sample``'s bilinear, ``align_corners=True``). The weight comes from ``coordinate + 0.5`` before ``pad``
    is added, so it does not depend on the border (the C kernel's reads, in double, are exact too).
    Differentiable in the coordinate."""
    shifted = coordinate + 0.5
    whole = torch.floor(shifted.detach())
    fraction = shifted - whole
    first = whole.to(torch.int64).add_(pad)
    low, high = torch.aminmax(first) if first.numel() else (0, 0)
    if not 0 <= int(low) <= int(high) <= size - 2:  # rare: reads off the table
        fraction = torch.where(first < 0, 0.0, torch.where(first > size - 2, 1.0, fraction))
        first = first.clamp_(0, size - 2)
    return first, fraction


def _bilinear_read(integral: PaddedIntegral, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Integral read at continuous image coordinates ``x, y`` (same shape ``(B, …)``), clamped to the table.

    Bilinear interpolation of an integral image is the exact area integral of the pixel-constant image."""
    table = integral.table
    b, _, h1, w1 = table.shape
    x0, fx = _table_axis(x.reshape(b, -1), integral.pad, w1)
    y0, fy = _table_axis(y.reshape(b, -1), integral.pad, h1)
    flat = table.reshape(b, h1 * w1)
    index = y0.mul_(w1).add_(x0)
    # The other three corners through views of the table shifted by 1, w1 and w1 + 1 (no index tensor is added to).
    top = torch.lerp(flat.gather(1, index), flat[:, 1:].gather(1, index), fx)
    bottom = torch.lerp(flat[:, w1:].gather(1, index), flat[:, w1 + 1:].gather(1, index), fx)
    return torch.lerp(top, bottom, fy).view(x.shape)


def _check_reads(integral: PaddedIntegral, **coordinates: torch.Tensor | None) -> None:
    """Coordinates read from ``integral`` are tensors of its table's dtype (float64 centres on a float32 table
    failed in ``torch.lerp`` with "expected dtype float for `weight` but got dtype double")."""
    for name, value in coordinates.items():
        if value is not None and (not isinstance(value, torch.Tensor) or value.dtype != integral.table.dtype):
            got = value.dtype if isinstance(value, torch.Tensor) else type(value).__name__
            raise InputError(f"{name}: expected a tensor of the integral's dtype {integral.table.dtype}, got {got}")


def sample_box_means(
    integral: PaddedIntegral, center_xy: torch.Tensor, half_width: torch.Tensor, half_height: torch.Tensor | None = None
) -> torch.Tensor:
    """Mean intensity of axis-aligned boxes at real-valued centres (less the image's mean where ``integral`` was
    made with ``subtract_mean``, :func:`padded_integral_image`'s default).

    Args:
        integral: :class:`PaddedIntegral`; boxes should stay within its border.
        center_xy: ``(B, P, 2)`` box centres, pixel-centre coordinates.
        half_width: ``(B, P)`` half the box width, pixels (> 0).
        half_height: ``(B, P)`` half the box height; default ``half_width`` (a square box).

    Returns:
        ``(B, P)``. Differentiable with respect to the image (and the centres).
    """
    check_shape(center_xy, "center_xy", [integral.table.shape[0], "P", 2])
    _check_reads(integral, center_xy=center_xy, half_width=half_width, half_height=half_height)
    half_height = half_width if half_height is None else half_height
    x0, x1 = center_xy[..., 0] - half_width, center_xy[..., 0] + half_width
    y0, y1 = center_xy[..., 1] - half_height, center_xy[..., 1] + half_height
    corners = _bilinear_read(integral, torch.stack([x1, x1, x0, x0], -1), torch.stack([y1, y0, y1, y0], -1))
    a, b, c, d = corners.unbind(-1)
    return (a - b - c + d) / ((x1 - x0) * (y1 - y0))


def sample_cell_means(integral: PaddedIntegral, image_index: torch.Tensor, x_edges: torch.Tensor,
                             y_edges: torch.Tensor) -> torch.Tensor:
    """Means of the cells of a ragged set of P axis-aligned lattices, each on its own image of the batch: cell
    (m, n) of lattice p spans [x_n, x_{n+1}] × [y_m, y_{m+1}] of image ``image_index[p]``.

    Args:
        integral: :class:`PaddedIntegral` of B images.
        image_index: ``(P,)`` int64, the image of each lattice.
        x_edges: ``(P, N + 1)``; y_edges: ``(P, M + 1)``, pixel-centre coordinates of that image.

    Returns:
        ``(P, M, N)``. Neighbouring cells share corners (a 21 × 21 lattice costs 22² reads, not 4 · 21²); each
        lattice reads its own image's table only, so no padding keypoint is ever sampled. Differentiable with
        respect to the image.
    """
    _check_reads(integral, x_edges=x_edges, y_edges=y_edges)
    table = integral.table
    b, _, height, width = table.shape
    x0, fx = _table_axis(x_edges, integral.pad, width)  # (P, N + 1)
    y0, fy = _table_axis(y_edges, integral.pad, height)  # (P, M + 1)
    flat = table.reshape(b * height * width)
    index = (image_index * (height * width)).view(-1, 1, 1) + (y0 * width).unsqueeze(-1) + x0.unsqueeze(-2)
    fx, fy = fx.unsqueeze(-2), fy.unsqueeze(-1)
    shape, index = index.shape, index.view(-1)

    def read(shift: int) -> torch.Tensor:  # the corner ``shift`` table places on, through a view (no index added to)
        return flat[shift:].gather(0, index).view(shape)

    corners = torch.lerp(torch.lerp(read(0), read(1), fx), torch.lerp(read(width), read(width + 1), fx), fy)
    sums = corners[..., 1:, 1:] - corners[..., :-1, 1:] - corners[..., 1:, :-1] + corners[..., :-1, :-1]
    inverse_area = 1 / ((x_edges[..., 1:] - x_edges[..., :-1]).unsqueeze(-2) *
                        (y_edges[..., 1:] - y_edges[..., :-1]).unsqueeze(-1))
    return sums * inverse_area
