"""Binary morphology on batches (paper Sec. 3.2, step 3: erosion then dilation).

Conventions follow OpenCV's ``cv2.erode``/``cv2.dilate`` so results are identical:
- a structuring element is a 2-D bool tensor ``(kh, kw)`` with anchor at its centre ``(kh // 2, kw // 2)``;
- both operations take the min / max over ``x(p + q − anchor)`` for the element's offsets q (OpenCV does not
  reflect the element for dilation; for symmetric elements this is the textbook definition);
- outside the image nothing erodes and nothing dilates (OpenCV's default border value).

Both run as logical OR / AND over shifted bool slices, one per element offset (the "shift" engine that
REFERENCE.md measured fastest on CPU), separably for a full rectangle. Hard morphology on bool
masks is not differentiable; see :mod:`svs_torch.segmentation.soft` for a smooth variant.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..core.checks import InputError, check_dtype, check_shape

__all__ = ["MAX_ELEMENT_SIZE", "structuring_element", "erode", "dilate", "open_binary"]


#: The largest element side :func:`structuring_element` builds (a 16 MB table; an opening wider than a few hundred
#: pixels removes every obstacle anyway): 2^31 failed in an allocation.
MAX_ELEMENT_SIZE = 4095


def structuring_element(shape: str, size: int, device: torch.device | None = None) -> torch.Tensor:
    """A ``(size, size)`` bool structuring element: ``"square"``, ``"cross"`` or ``"ellipse"`` (disk).

    ``"ellipse"`` equals ``cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))``; ``"square"`` is
    MATLAB's ``strel('square', size)``. Not differentiable (a constant bool table).
    """
    if not isinstance(size, int) or isinstance(size, bool) or not 1 <= size <= MAX_ELEMENT_SIZE:
        raise InputError(f"size: expected an integer from 1 to {MAX_ELEMENT_SIZE}, got {size!r}")
    if shape == "square":
        return torch.ones(size, size, dtype=torch.bool, device=device)
    if shape == "cross":
        element = torch.zeros(size, size, dtype=torch.bool, device=device)
        element[size // 2, :] = True
        element[:, size // 2] = True
        return element
    if shape == "ellipse":
        import cv2  # the reference definition; a tiny host-side table

        table = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
        return torch.from_numpy(table.astype(bool)).to(device)
    raise InputError(f"shape: expected 'square', 'cross' or 'ellipse', got {shape!r}")


def _check(mask: torch.Tensor, element: torch.Tensor) -> None:
    check_shape(mask, "mask", ["B", 1, "H", "W"])
    check_dtype(mask, "mask", "bool")
    check_shape(element, "element", ["kh", "kw"])
    check_dtype(element, "element", "bool")


def anchor_padding(element: torch.Tensor) -> tuple[int, int, int, int]:
    """(left, right, top, bottom) padding that puts the anchor at the element's centre."""
    kh, kw = element.shape
    ay, ax = kh // 2, kw // 2
    return ax, kw - 1 - ax, ay, kh - 1 - ay


def _shift_reduce(mask: torch.Tensor, element: torch.Tensor, erosion: bool) -> torch.Tensor:
    """OR (dilation) or AND (erosion) of ``mask (B, 1, H, W)`` bool over the element's offsets.

    Bool slices and logical ops touch one byte per pixel: several times faster on CPU than a float max-pool.
    The padding value makes the outside neutral: False for OR, True for AND.
    """
    h, w = mask.shape[-2:]
    reduce = torch.logical_and if erosion else torch.logical_or
    left, right, top, bottom = anchor_padding(element)
    padded = F.pad(mask, (left, right, top, bottom), value=erosion)
    kh, kw = element.shape
    if bool(element.all()):
        # Separable rectangle: reduce along rows, then along columns.
        rows = padded[..., :, 0:w]
        for dx in range(1, kw):
            rows = reduce(rows, padded[..., :, dx:dx + w])
        out = rows[..., 0:h, :]
        for dy in range(1, kh):
            out = reduce(out, rows[..., dy:dy + h, :])
        return out
    offsets = element.nonzero().tolist()
    dy, dx = offsets[0]
    out = padded[..., dy:dy + h, dx:dx + w]
    for dy, dx in offsets[1:]:
        out = reduce(out, padded[..., dy:dy + h, dx:dx + w])
    return out.clone() if len(offsets) == 1 else out


def dilate(mask: torch.Tensor, element: torch.Tensor) -> torch.Tensor:
    """Binary dilation of ``mask (B, 1, H, W)`` bool by ``element (kh, kw)`` bool; equals ``cv2.dilate``. Not
    differentiable (bool in, bool out)."""
    _check(mask, element)
    if not bool(element.any()):
        return torch.zeros_like(mask)
    return _shift_reduce(mask, element, erosion=False)


def erode(mask: torch.Tensor, element: torch.Tensor) -> torch.Tensor:
    """Binary erosion of ``mask (B, 1, H, W)`` bool by ``element (kh, kw)`` bool; equals ``cv2.erode``. Not
    differentiable (bool in, bool out)."""
    _check(mask, element)
    if not bool(element.any()):
        return torch.ones_like(mask)
    return _shift_reduce(mask, element, erosion=True)


def open_binary(mask: torch.Tensor, element: torch.Tensor) -> torch.Tensor:
    """Erosion then dilation (morphological opening): removes specks smaller than the element. Not
    differentiable (bool in, bool out)."""
    return dilate(erode(mask, element), element)
