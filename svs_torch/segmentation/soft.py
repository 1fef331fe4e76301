"""A differentiable relaxation of the segmentation stage, for learning thresholds or training upstream models.

The hard stage (:mod:`svs_torch.segmentation`) is piecewise constant: Otsu's argmax, ``>``, min/max filters
and component labels pass no gradient. Here:

- the binary image becomes ``sigmoid((image − threshold) / temperature)``: gradients reach the image and the
  threshold;
- erosion and dilation become smooth min / max filters, ``T·log(mean exp(x / T))`` over the structuring
  element (and its mirror for the minimum), which tend to the hard filters as ``T → 0`` and equal them on
  constant windows;
- region selection (which components are the N largest) stays a hard decision taken from the hard pipeline:
  the soft mask is gated by the kept-region mask, so gradients flow inside the kept obstacles.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..core.checks import (InputError, check_device, check_dtype, check_finite, check_image, check_positive_scalar,
                           check_shape)
from ..core.numerics import per_pair
from ..core.types import Segmentation
from .morphology import anchor_padding, structuring_element
from .segment import SegmentationConfig, segment_images

__all__ = ["soft_threshold", "soft_dilate", "soft_erode", "soft_open", "SoftSegmentation", "soft_segment_images"]


def _check_temperature(temperature: float, name: str = "temperature", dtype: torch.dtype | None = None) -> None:
    """One positive number (:func:`~svs_torch.core.checks.check_positive_scalar`), and with ``dtype`` (the smooth
    filters') finite in it: their ``T·log(mean exp(x / T))`` was inf · 0 = NaN at every pixel for an inf temperature
    or one past the dtype's largest number (1e39 with float32), where the threshold's sigmoid takes its limit, 0.5
    (an audit)."""
    check_positive_scalar(temperature, name, "temperature")
    value = float(temperature.detach()) if isinstance(temperature, torch.Tensor) else temperature
    if dtype is not None and not value <= torch.finfo(dtype).max:
        raise InputError(f"{name}: expected a finite positive temperature (at most {torch.finfo(dtype).max:.3g} in "
                         f"{dtype}), got {temperature!r}")


def soft_threshold(image: torch.Tensor, threshold: torch.Tensor, temperature: float = 0.02) -> torch.Tensor:
    """Soft binary image ``sigmoid((image − threshold) / temperature)``.

    Args:
        image: ``(B, 1, H, W)`` float in [0, 1].
        threshold: ``(B,)`` float on the [0, 1] scale (e.g. Otsu's, or a learnable parameter).
        temperature: width of the transition on the [0, 1] intensity scale; ``→ 0`` gives ``image > threshold``.

    Returns:
        ``(B, 1, H, W)`` float in (0, 1). Differentiable with respect to ``image`` and ``threshold``.
    """
    check_image(image, "image")
    check_shape(threshold, "threshold", [image.shape[0]])
    check_dtype(threshold, "threshold", "float")
    check_device(threshold, "threshold", image, "the image's")  # (a meta one failed in check_finite's bool())
    check_finite(threshold, "threshold")  # a NaN gave NaN masks in silence (any finite value is a threshold)
    _check_temperature(temperature)
    # In the image's dtype: a float64 threshold made a float32 image's mask float64 (an audit).
    return per_pair(torch.sigmoid, (image - threshold.to(image.dtype).view(-1, 1, 1, 1)) / temperature)


def _soft_max_filter(x: torch.Tensor, element: torch.Tensor, temperature: float, empty: float) -> torch.Tensor:
    """``T·log(mean over in-image offsets of exp(x / T))``, the same offsets and anchor as the hard filter; ``empty``
    where no offset lands in the image (an element off to one side of its anchor), as the hard filter gives there
    (dilation 0, erosion 1: the max and min of nothing), where log(0 / 0) was NaN (an audit)."""
    h, w = x.shape[-2:]
    padded = F.pad(x, anchor_padding(element), value=float("-inf"))
    offsets = element.nonzero().tolist()
    windows = [padded[..., dy:dy + h, dx:dx + w] for dy, dx in offsets]
    count = torch.zeros_like(x)
    for window in windows:
        count = count + torch.isfinite(window).to(x.dtype)
    some = count > 0
    # Shift by the hard maximum for stability; the result's gradient does not depend on the shift.
    peak = windows[0].detach()
    for window in windows[1:]:
        peak = torch.maximum(peak, window.detach())
    peak = torch.where(some, peak, torch.zeros_like(peak))
    total = torch.zeros_like(x)
    for window in windows:
        # 0 outside the image. Not as exp(−inf / T): its gradient w.r.t. a temperature given as a tensor was
        # 0 · inf = NaN at every pixel whose window reaches past the border (an audit).
        inside = torch.isfinite(window)
        shifted = torch.where(inside, window - peak, torch.zeros_like(window))
        total = total + torch.where(inside, torch.exp(shifted / temperature), torch.zeros_like(window))
    ratio = torch.where(some, total / torch.where(some, count, 1.0), torch.ones_like(total))
    return torch.where(some, peak + temperature * torch.log(ratio), torch.full_like(x, empty))


def _check_soft(x: torch.Tensor, element: torch.Tensor, temperature: float) -> None:
    check_shape(x, "x", ["B", 1, "H", "W"])
    check_dtype(x, "x", "float")
    check_shape(element, "element", ["kh", "kw"])
    check_dtype(element, "element", "bool")
    if element.is_meta:  # its offsets are read on the host (any device with values serves): a meta one failed deep
        raise InputError("element: expected a tensor with values, got one on the meta device")
    if not bool(element.any()):
        raise InputError("element: expected at least one True offset")
    _check_temperature(temperature, dtype=x.dtype)


def soft_dilate(x: torch.Tensor, element: torch.Tensor, temperature: float = 0.05) -> torch.Tensor:
    """Smooth dilation of ``x (B, 1, H, W)`` float by ``element (kh, kw)`` bool; ``→ cv2.dilate`` as ``T → 0``.

    Differentiable with respect to ``x`` (softmax weights over each window) and a ``temperature`` given as a tensor.
    """
    _check_soft(x, element, temperature)
    return _soft_max_filter(x, element, temperature, empty=0.0)


def soft_erode(x: torch.Tensor, element: torch.Tensor, temperature: float = 0.05) -> torch.Tensor:
    """Smooth erosion, ``−soft_dilate(−x)``; ``→ cv2.erode`` as ``T → 0``. Differentiable with respect to ``x``."""
    _check_soft(x, element, temperature)
    return -_soft_max_filter(-x, element, temperature, empty=-1.0)


def soft_open(x: torch.Tensor, element: torch.Tensor, temperature: float = 0.05) -> torch.Tensor:
    """Smooth opening (erosion then dilation). Differentiable with respect to ``x``."""
    _check_soft(x, element, temperature)
    return _soft_max_filter(-_soft_max_filter(-x, element, temperature, empty=-1.0), element, temperature, empty=0.0)


@dataclass(frozen=True)
class SoftSegmentation:
    """Soft segmentation of B images.

    Attributes:
        soft_binary: ``(B, 1, H, W)`` soft threshold of the image.
        soft_opened: ``(B, 1, H, W)`` its smooth opening.
        soft_mask: ``(B, 1, H, W)`` ``soft_opened`` gated by the hard kept-region mask.
        masked: ``(B, 1, H, W)`` ``image · soft_mask``.
        hard: the hard :class:`Segmentation` that chose the kept regions (and the default threshold).
    """

    soft_binary: torch.Tensor
    soft_opened: torch.Tensor
    soft_mask: torch.Tensor
    masked: torch.Tensor
    hard: Segmentation


def soft_segment_images(
    image: torch.Tensor,
    threshold: torch.Tensor | None = None,
    config: SegmentationConfig = SegmentationConfig(),
    threshold_temperature: float = 0.02,
    morphology_temperature: float = 0.05,
) -> SoftSegmentation:
    """Differentiable counterpart of :func:`svs_torch.segmentation.segment_images`.

    Args:
        image: ``(B, 1, H, W)`` float in [0, 1].
        threshold: ``(B,)`` threshold on the [0, 1] scale; default: Otsu's where the hard stage's rounding to gray
            levels puts it, ``(level + 0.5) / 255`` (then no gradient reaches it).
        config: the hard stage's :class:`SegmentationConfig` (element, connectivity, kept regions).
        threshold_temperature: sigmoid width of :func:`soft_threshold`.
        morphology_temperature: temperature of the smooth min / max filters.

    Returns:
        :class:`SoftSegmentation`. Gradients of ``soft_mask`` and ``masked`` reach ``image`` and ``threshold``;
        which regions are kept is decided by the hard pipeline and carries no gradient. Otsu's threshold only:
        Canny's edges (``method="canny"``) and the networks' segmenters have no soft counterpart here.
    """
    if isinstance(config, SegmentationConfig) and config.method != "otsu":
        # It returned a relaxation of Otsu gated by Canny's regions: 87.5 % agreement with the hard mask.
        raise InputError(f"config.method: the soft segmentation relaxes Otsu's threshold ('otsu'), got "
                         f"{config.method!r}")
    if isinstance(config, SegmentationConfig) and config.segmenter != "otsu":
        # segment_images' refusal pointed to segment_stereo, which has no soft counterpart (an audit).
        raise InputError(f"config.segmenter: the soft segmentation relaxes the Otsu segmenter ('otsu'), got "
                         f"{config.segmenter!r} (its soft path: estimate_obstacle_depth with differentiable=True)")
    hard = segment_images(image, config)
    # By the names passed here: soft_threshold and the filters call theirs "temperature" (an audit).
    _check_temperature(threshold_temperature, "threshold_temperature")
    _check_temperature(morphology_temperature, "morphology_temperature", image.dtype)
    if threshold is None:
        # Halfway to the next level: the hard stage keeps round(255 · x) > level, so a pixel at Otsu's level itself
        # (every 8-bit image has some) stayed at 0.5 at any temperature, and a dark foreground's kept mask held 0.5
        # there, not 1 (an audit: 714 pixels of Teddy's). Now both tend to the hard masks.
        threshold = (hard.threshold_level.to(image.dtype) + 0.5) / 255
    soft_binary = soft_threshold(image, threshold, threshold_temperature)
    if config.foreground == "dark":
        soft_binary = 1 - soft_binary
    element = structuring_element(config.kernel_shape, config.kernel_size, device=image.device)
    soft_opened = soft_open(soft_binary, element, morphology_temperature)
    soft_mask = soft_opened * hard.kept_mask.to(image.dtype)
    return SoftSegmentation(soft_binary, soft_opened, soft_mask, image * soft_mask, hard)
