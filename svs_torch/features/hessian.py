"""SURF's fast-Hessian detector, batched (paper Sec. 3.3 (1); Bay et al., CVIU 2008, Sec. 3).

Second derivatives of Gaussians are approximated by box filters read from an integral image: Dyy is three
stacked lobes (+1, −2, +1) of (2l − 1) × l pixels, Dxx its transpose, Dxy four l × l boxes (+ − / − +) with a
one-pixel gap, for filter size L = 3l. As in MATLAB's ``detectSURFFeatures`` (built on OpenCV's SURF), each box
is normalised by its own area, so a response is a difference of mean intensities whatever the filter size and
the metric threshold means the same at every scale; the blob response is det(H) = Dxx·Dyy − (0.9·Dxy)² (Bay
Eq. (4)) and the sign of the Laplacian Dxx + Dyy is kept.

Scale space (Bay Sec. 3.3, Fig. 6): octave o uses filter sizes 3 + 6·2^o·(1 + i), i = 0 … levels − 1 (9, 15,
21, 27; 15, 27, 39, 51; 27, 51, 75, 99; …), sampled every 2^o pixels. Maxima over 3 × 3 × 3 (scale, y, x)
neighbourhoods of the inner levels, above the threshold, are refined by a quadratic fit (Brown & Lowe 2002).

Response maps are differentiable with respect to the image; the choice of keypoints (threshold, maxima,
top-k) is not.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch

from ..core.checks import check_image
from ..core.compiling import maybe_compiled
from ..core.inference import outside_inference_mode
from . import kernels
from .integral import grid_box_corners, integral_image, integral_phases, pad_integral

__all__ = ["HessianOctave", "filter_sizes", "hessian_octaves"]

#: Bay's relative weight of Dxy (Eq. (4)): keeps det(H) close to the Gaussian one across filter sizes.
DXY_WEIGHT = 0.9


def filter_sizes(octave: int, num_scale_levels: int) -> list[int]:
    """Box-filter sizes L of one octave: 9, 15, 21, 27 for octave 0; 15, 27, 39, 51 for octave 1; …"""
    step = 6 << octave
    return [3 + step * (1 + i) for i in range(num_scale_levels)]


@dataclass(frozen=True)
class HessianOctave:
    """Responses of one octave on its sampling grid (grid point (i, j) is pixel (y, x) = step · (i, j)).

    Attributes:
        det: ``(B, S, ny, nx)`` det(H) per level, on the [0, 1] intensity scale (× 255² for MATLAB's units).
        trace: ``(B, S, ny, nx)`` Dxx + Dyy, the Laplacian whose sign classifies the blob.
        inside: ``(S, ny, nx)`` bool, where the level's whole filter lies inside the image.
        sizes: the S filter sizes L, pixels.
        step: grid spacing, pixels.
    """

    det: torch.Tensor
    trace: torch.Tensor
    inside: torch.Tensor
    sizes: tuple[int, ...]
    step: int


def _level_corners(phases: list[torch.Tensor], step: int, pad: int, size: int,
                   grid_hw: tuple[int, int]) -> list[torch.Tensor]:
    """The 32 integral-image views (4 corners × 8 boxes) of one filter size at every grid point.

    Boxes are relative to the centre pixel: Dxx is the whole (2l − 1) × 3l band and its middle lobe (weights
    +1 and −3 give the +1, −2, +1 lobes), Dyy the same transposed, Dxy four l × l boxes around a one-pixel gap.
    """
    lobe = size // 3
    half = size // 2  # the filter spans centre − half … centre + half
    long_rows = (-(lobe - 1), lobe)  # 2l − 1 pixels, centred
    outer = (-half, half + 1)  # all three lobes
    centre = (-(lobe // 2), lobe // 2 + 1)  # the middle lobe
    before, after = (-lobe, 0), (1, lobe + 1)  # l pixels on each side of a one-pixel gap
    boxes = [(long_rows, outer), (long_rows, centre), (outer, long_rows), (centre, long_rows),
             (before, before), (before, after), (after, before), (after, after)]
    return [view for rows, cols in boxes for view in grid_box_corners(phases, step, pad, rows, cols, grid_hw)]


def _det_trace(corners: list[torch.Tensor], inverse_lobe_area: float, inverse_dxy_area: float):
    """det(H) = Dxx·Dyy − (0.9·Dxy)² (Bay Eq. (4)) and the trace Dxx + Dyy from the 32 corner views; each box
    normalised by its own area."""
    box = [corners[4 * i] - corners[4 * i + 1] - corners[4 * i + 2] + corners[4 * i + 3] for i in range(8)]
    dxx = (box[0] - 3 * box[1]) * inverse_lobe_area
    dyy = (box[2] - 3 * box[3]) * inverse_lobe_area
    dxy = (box[4] - box[5] - box[6] + box[7]) * inverse_dxy_area
    return dxx * dyy - (DXY_WEIGHT * dxy) ** 2, dxx + dyy


def _level_into(corners: list[torch.Tensor], inverse_lobe_area: float, inverse_dxy_area: float,
                det_out: torch.Tensor, trace_out: torch.Tensor) -> None:
    """:func:`_det_trace` written into slices of the octave's stacked maps: when compiled, one fused pass over
    the corner views that writes the level in place (no separate stacking copy)."""
    det, trace = _det_trace(corners, inverse_lobe_area, inverse_dxy_area)
    det_out.copy_(det)
    trace_out.copy_(trace)


@functools.lru_cache(maxsize=64)
@outside_inference_mode  # cached across calls: never an inference tensor
def _inside_levels(sizes: tuple[int, ...], step: int, grid_hw: tuple[int, int], image_hw: tuple[int, int],
                   device: torch.device) -> torch.Tensor:
    """``(S, ny, nx)`` bool: the whole filter of each size fits in the image at the grid point. Cached (a
    batch of one size asks for the same few tables every time); the callers only read it."""
    ys = torch.arange(grid_hw[0], device=device) * step
    xs = torch.arange(grid_hw[1], device=device) * step
    levels = []
    for size in sizes:
        half = size // 2
        fit_y = (ys >= half) & (ys <= image_hw[0] - 1 - half)
        fit_x = (xs >= half) & (xs <= image_hw[1] - 1 - half)
        levels.append(fit_y[:, None] & fit_x[None, :])
    return torch.stack(levels)


def _padded_table(image: torch.Tensor, pad: int, use_kernel: bool) -> torch.Tensor:
    """The integral image of ``image`` minus its mean, padded by ``pad``: with ``use_kernel`` in one pass per
    image by the C kernel (the same values), else by :func:`pad_integral` of :func:`integral_image`."""
    padded = None
    if use_kernel:
        check_image(image, "image", check_range=False)
        padded = kernels.padded_integral(image, None, pad)  # the kernel takes image_means' means itself
    if padded is None:
        padded = pad_integral(integral_image(image, subtract_mean=True), pad)
    return padded


def hessian_octaves(
    image: torch.Tensor, num_octaves: int = 3, num_scale_levels: int = 4, compiled: bool = False
) -> list[HessianOctave]:
    """Box-filter Hessian responses of a batch over SURF's scale space.

    Args:
        image: ``(B, 1, H, W)`` float in [0, 1].
        num_octaves: octaves (MATLAB ``NumOctaves``, default 3).
        num_scale_levels: filter sizes per octave (MATLAB ``NumScaleLevels``, default 4; at least 3).
        compiled: run the per-level kernel through ``torch.compile`` (identical output, about 10× faster on
            CPU once compiled; the first call compiles for about 20 s, later processes reuse inductor's
            on-disk cache). Without it, float32 images that need no gradient go through the fused C kernel of
            :mod:`svs_torch.features.kernels` where it can be built (identical output too, no compile wait).

    Returns:
        One :class:`HessianOctave` per octave, in the image's dtype. Differentiable with respect to ``image``.
        A constant added to the image changes nothing (every filter's weights sum to zero).

    On the torch path coarser octaves read the integral's sub-lattices
    (:func:`~svs_torch.features.integral.integral_phases`), so every read is unit-stride: in eager torch strided reads
    cost an order of magnitude more. The C kernel reads the padded table at the octave's step directly.
    """
    h, w = image.shape[-2:]
    largest = filter_sizes(num_octaves - 1, num_scale_levels)[-1]
    pad = largest // 2 + 2
    kernel_ok = image.dtype == torch.float32 and not (torch.is_grad_enabled() and image.requires_grad)
    padded = _padded_table(image, pad, kernel_ok and not compiled)
    # One dynamic-shape graph serves every level and octave: the slicing happens outside, so filter sizes and
    # offsets never reach the graph.
    level = maybe_compiled(_level_into, compiled)
    octaves = []
    for octave in range(num_octaves):
        step = 1 << octave
        grid_hw = ((h + step - 1) // step, (w + step - 1) // step)
        sizes = filter_sizes(octave, num_scale_levels)
        lobes = [size // 3 for size in sizes]
        inverse_lobe_area = [1.0 / ((2 * lobe - 1) * lobe) for lobe in lobes]
        inverse_dxy_area = [1.0 / lobe**2 for lobe in lobes]
        det = image.new_empty(image.shape[0], len(sizes), *grid_hw)
        trace = torch.empty_like(det)
        # Without compile, float32 images that need no gradient go to the C kernel: the same values, the whole
        # octave in one call straight from the padded table (no sub-lattice copies, no views).
        if not (kernel_ok and not compiled and kernels.hessian_octave(
                padded, pad, step, sizes, inverse_lobe_area, inverse_dxy_area, DXY_WEIGHT, det, trace)):
            phases = integral_phases(padded, step)
            for i, size in enumerate(sizes):
                level(_level_corners(phases, step, pad, size, grid_hw), inverse_lobe_area[i], inverse_dxy_area[i],
                      det[:, i:i + 1], trace[:, i:i + 1])
        octaves.append(HessianOctave(
            det=det,
            trace=trace,
            inside=_inside_levels(tuple(sizes), step, grid_hw, (h, w), image.device),
            sizes=tuple(sizes),
            step=step,
        ))
    return octaves


def _max3(x: torch.Tensor, dim: int) -> torch.Tensor:
    """Maximum of each run of 3 along ``dim`` (the result is 2 shorter): slices only, no padding or pooling."""
    n = x.shape[dim]
    return torch.maximum(torch.maximum(x.narrow(dim, 0, n - 2), x.narrow(dim, 1, n - 2)), x.narrow(dim, 2, n - 2))


def _interior_maxima(det: torch.Tensor, support: torch.Tensor, threshold: float) -> torch.Tensor:
    """det where it is a 3 × 3 × 3 maximum above ``threshold`` with ``support``, −inf elsewhere; interior
    only ``(B, S − 2, ny − 2, nx − 2)``."""
    peak = _max3(_max3(_max3(det, 3), 2), 1)
    centre = det[:, 1:-1, 1:-1, 1:-1]
    keep = (centre == peak) & (centre > threshold) & support
    return torch.where(keep, centre, torch.full_like(centre, float("-inf")))


def maxima_support(octave: HessianOctave, mask: torch.Tensor | None = None) -> torch.Tensor | None:
    """Where a maximum of ``octave`` may stand: ``(1 or B, S − 2, ny − 2, nx − 2)`` bool over its interior points,
    those whose whole neighbourhood is in the image (the next larger level must fit one grid step around it) and,
    given ``mask (B, 1, H, W)``, inside it. None for a grid under 3 points (an image under 5 px at octave 2's step
    of 4), which has no interior point."""
    ny, nx = octave.det.shape[-2:]
    if min(ny, nx) < 3:
        return None
    inside = octave.inside
    larger_fits = inside[2:, :-2, 1:-1] & inside[2:, 2:, 1:-1] & inside[2:, 1:-1, :-2] & inside[2:, 1:-1, 2:]
    support = (larger_fits & inside[2:, 1:-1, 1:-1]).unsqueeze(0)  # (1, S − 2, ny − 2, nx − 2)
    if mask is not None:
        support = support & mask[:, :, ::octave.step, ::octave.step][:, :, 1:ny - 1, 1:nx - 1]
    return support


def local_maxima_scores(
    octave: HessianOctave, threshold: float, mask: torch.Tensor | None = None, compiled: bool = False
) -> torch.Tensor:
    """Scale-space maxima of one octave: ``(B, S − 2, ny − 2, nx − 2)`` det at 3 × 3 × 3 maxima of the inner
    levels above ``threshold`` (and inside ``mask (B, 1, H, W)`` if given), −inf elsewhere.

    Interior grid point (l, i, j) is level l + 1, grid row i + 1, column j + 1. A maximum needs its whole
    neighbourhood in the image: the next larger level must fit one grid step around it. Ties with a
    neighbour count as maxima (OpenCV requires strictly larger; float responses rarely tie).
    """
    b, levels, ny, nx = octave.det.shape
    support = maxima_support(octave, mask)
    if support is None:
        return octave.det.new_full((b, levels - 2, max(ny - 2, 0), max(nx - 2, 0)), float("-inf"))
    # Without compile and without gradients, the C kernel: the same comparisons in one pass.
    if not compiled and not (torch.is_grad_enabled() and octave.det.requires_grad):
        scores = kernels.local_maxima(octave.det, support, threshold)
        if scores is not None:
            return scores
    return maybe_compiled(_interior_maxima, compiled)(octave.det, support, threshold)
