"""Otsu's threshold, batched (paper Sec. 3.2, step 2: ``im2bw(I, graythresh(I))``).

MATLAB's ``graythresh`` and OpenCV's ``THRESH_OTSU`` both histogram the image over the 256 levels of the
uint8 range (not the image's own min..max, as kornia's ``otsu_threshold`` does) and pick the level that
maximises the between-class variance. Images in [0, 1] are quantised as ``round(255·x)``, which recovers
uint8 data exactly.
"""

from __future__ import annotations

import torch

from ..core.checks import check_dtype, check_image, check_shape
from ..core.errors import InputError
from . import kernels

__all__ = ["gray_levels", "gray_histogram", "gray_levels_and_histogram", "otsu_threshold_level", "otsu_threshold",
           "threshold_binary"]

NUM_LEVELS = 256


def gray_levels(image: torch.Tensor) -> torch.Tensor:
    """Quantise ``(B, 1, H, W)`` images in [0, 1] to uint8 gray levels 0..255 (``round(255·x)``).

    uint8 keeps the full-resolution passes that follow at one byte per pixel. Not differentiable (rounding).
    ``image`` float32 or float64 (InputError otherwise: a uint8 image's ``255·x`` wrapped around modulo 256).
    """
    check_dtype(image, "image", "float")
    return (image.detach() * (NUM_LEVELS - 1)).round_().clamp_(0, NUM_LEVELS - 1).to(torch.uint8)


def gray_histogram(levels: torch.Tensor, ignore: torch.Tensor | None = None) -> torch.Tensor:
    """Per-image histogram of gray levels ``(B, 1, H, W)`` uint8 → counts ``(B, 256)`` int64; ``ignore``
    ``(B, 1, H, W)`` bool: pixels not counted, whatever their level (invalid disparities, a floor).

    One ``bincount`` over the whole batch, with each image's levels offset into its own 256 bins (int32
    offsets: a quarter of the memory traffic of int64 for the same result). Not differentiable (counts).
    """
    # Other dtypes were taken in silence (an audit): an int level past 255 counted in the next image's bins, a float
    # one truncated, and an int ignore inverted bit by bit (~0 = -1) into indices.
    if not isinstance(levels, torch.Tensor) or levels.dtype != torch.uint8:
        raise InputError(f"levels: expected a uint8 tensor of gray levels, got {getattr(levels, 'dtype', levels)!r}")
    b = levels.shape[0]
    if ignore is not None:  # a mask of another size failed in an index deep inside
        check_shape(ignore, "ignore", list(levels.shape))
        check_dtype(ignore, "ignore", "bool")
    offsets = torch.arange(b, device=levels.device, dtype=torch.int32).view(b, 1) * NUM_LEVELS
    flat = (levels.reshape(b, -1).to(torch.int32) + offsets).flatten()
    if ignore is not None:
        flat = flat[~ignore.reshape(-1)]
    return torch.bincount(flat, minlength=b * NUM_LEVELS).view(b, NUM_LEVELS)


def gray_levels_and_histogram(image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`gray_levels` and :func:`gray_histogram` of ``(B, 1, H, W)`` images in [0, 1]: without a C compiler
    the two torch functions; with one, a kernel that reads each image once
    (:func:`svs_torch.segmentation.kernels.gray_levels`, the same values: 16 real 320×240 images, one thread, about 2.4
    → 0.4 ms). Not differentiable."""
    found = kernels.gray_levels(image)
    if found is not None:
        return found
    levels = gray_levels(image)
    return levels, gray_histogram(levels)


def otsu_threshold_level(histogram: torch.Tensor) -> torch.Tensor:
    """Otsu's level from histograms ``(B, 256)`` → ``(B,)`` int64 in 0..255 (or ``(B, L)`` of any L bins → 0..L−1:
    a histogram of other values, e.g. an object's disparities, :mod:`svs_torch.pipeline.near_surface`).

    Maximises the between-class variance σ²_B(t) = (s₁·w₂ − s₂·w₁)² / (w₁·w₂·n²) over t, where w and s are the
    count and the level sum of the classes ``≤ t`` and ``> t``. The numerator is computed exactly in float64
    (integer sums below 2⁵³), so plateaus over empty bins tie exactly and the first level of a plateau wins,
    as in OpenCV. A level whose class probability is below FLT_EPSILON is skipped (OpenCV's rule); an image
    with one gray level has no admissible split and gets level 0, OpenCV's answer. Not differentiable (an
    argmax).
    """
    counts = histogram.to(torch.float64)
    levels = torch.arange(histogram.shape[-1], dtype=torch.float64, device=histogram.device)
    total = counts.sum(dim=1, keepdim=True)  # (B, 1)
    level_sum = (counts * levels).sum(dim=1, keepdim=True)  # (B, 1)
    w1 = counts.cumsum(dim=1)  # (B, L)
    s1 = (counts * levels).cumsum(dim=1)
    w2 = total - w1
    s2 = level_sum - s1
    q1 = w1 / total.clamp(min=1)
    eps = torch.finfo(torch.float32).eps
    admissible = (torch.minimum(q1, 1 - q1) >= eps) & (torch.maximum(q1, 1 - q1) <= 1 - eps)
    numerator = (s1 * w2 - s2 * w1) ** 2
    sigma = numerator / torch.where(admissible, w1 * w2, torch.ones_like(w1))
    sigma = torch.where(admissible, sigma, torch.full_like(sigma, -1.0))
    best = sigma.argmax(dim=1)  # first maximum
    has_split = admissible.any(dim=1)
    return torch.where(has_split, best, torch.zeros_like(best))


def otsu_threshold(image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Otsu's threshold of each image of a batch.

    Args:
        image: ``(B, 1, H, W)`` float in [0, 1].

    Returns:
        ``threshold`` ``(B,)`` on the [0, 1] scale (level / 255, the image's dtype) and ``level`` ``(B,)`` int64
        on the 0–255 scale, equal to ``cv2.threshold(u8, 0, 255, THRESH_BINARY | THRESH_OTSU)[0]``.
        Foreground is ``round(255·image) > level`` (:func:`threshold_binary`), which is ``image > threshold`` only
        for images on the 1/255 grid: a resampled image's pixel at 106.2/255 is above threshold 106/255 but
        background. Not differentiable: the threshold is a histogram argmax; see
        :func:`svs_torch.segmentation.soft.soft_threshold` for a differentiable binarisation.
    """
    check_image(image, "image")
    level = otsu_threshold_level(gray_levels_and_histogram(image)[1])
    return level.to(image.dtype) / (NUM_LEVELS - 1), level


def threshold_binary(image: torch.Tensor, level: torch.Tensor) -> torch.Tensor:
    """Binary image ``(B, 1, H, W)`` bool: gray level ``> level`` (OpenCV ``THRESH_BINARY``; MATLAB ``im2bw``).

    ``image`` is a float image in [0, 1] or its uint8 :func:`gray_levels`; ``level`` ``(B,)`` int in 0..255.
    Compares integer gray levels, so ``image`` and OpenCV's uint8 input give identical masks. Not
    differentiable (rounding and a comparison).
    """
    levels = image if image.dtype == torch.uint8 else gray_levels(image)
    _check_level(level, levels.shape[0])
    # min(levels, level) differs from levels exactly where levels > level. The same mask, but torch compares
    # a tensor with a per-image scalar elementwise without its vector loop: for 16 images of 320×240, 1.5 ms
    # for ``levels > level`` against 0.15 for this minimum and same-shape comparison.
    return torch.minimum(levels, level.to(torch.uint8).view(-1, 1, 1, 1)) != levels


def _check_level(level: torch.Tensor, batch_size: int) -> None:
    """``level`` ``(B,)`` int in 0..255. Unchecked, the float threshold :func:`otsu_threshold` returns first (0.42)
    became level 0 and every pixel foreground, and a level of 300 wrapped to 44 in uint8, each in silence."""
    check_shape(level, "level", [batch_size])
    check_dtype(level, "level", "int")
    if level.numel() and not (0 <= int(level.min()) and int(level.max()) < NUM_LEVELS):
        raise InputError(f"level: expected gray levels from 0 to {NUM_LEVELS - 1}, got {level.tolist()[:8]}")
