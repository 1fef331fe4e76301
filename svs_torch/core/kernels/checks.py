"""The checks at the boundary of the C kernels: what their loops assume (shapes, batch lengths, boxes and sizes
inside the buffers, non-empty images, finite parameters in range), raised as :class:`~svs_torch.InputError`
naming the argument, as OpenCV's ``CV_Assert`` and PyTorch's ``TORCH_CHECK`` guard their kernels; the C code then
trusts its inputs. Each check is on shapes or on a ``(B,)`` / ``(B, 4)`` tensor: none is a pass over an image.
"""

from __future__ import annotations

import math

import torch

from ..checks import check_dtype, check_instance, check_shape
from ..errors import InputError

__all__ = ["as_integer_tensor", "canonical_bool", "check_boxes", "check_counts", "check_image_hw", "check_nonempty",
           "check_number", "check_positive_hw", "check_row_fill", "check_rows", "settings_table"]


def check_rows(tensor: torch.Tensor, name: str, rows: int | str, *tail: int | str, kinds: str = "int"
               ) -> torch.Tensor:
    """``tensor`` as ``(rows, *tail)`` of dtype family ``kinds`` (exactly one row per pair), e.g.
    ``image_hw: expected (4, 2), got (1, 2)``; ``rows`` a letter (``"B"``) takes the first size as the B."""
    check_shape(tensor, name, [rows, *tail])
    check_dtype(tensor, name, kinds)
    return tensor


def check_row_fill(disparity: torch.Tensor, valid: torch.Tensor) -> None:
    """The arguments of ``fill_invalid_rows`` (:mod:`svs_torch.depth.block_matching`), on its torch path as on its
    kernel's: ``disparity`` ``(..., W)`` float or int, ``valid`` of its shape, bool. They were the kernel's alone:
    on the torch path (a disparity that requires grad) a float valid raised from deep inside torch, one of another
    shape was broadcast in silence, and a bool or complex disparity failed in its sums (an audit)."""
    check_instance(disparity, "disparity", torch.Tensor)
    if disparity.dim() < 1:
        raise InputError(f"disparity: expected (..., W), got {tuple(disparity.shape)}")
    check_dtype(disparity, "disparity", "float|int")
    check_shape(valid, "valid", list(disparity.shape))
    check_dtype(valid, "valid", "bool")


def check_image_hw(image_hw: torch.Tensor, b: int, h: int, w: int) -> torch.Tensor:
    """Each pair's size before padding ``(B, 2)`` int: at least 1 and within the ``H × W`` tensors (a kernel
    reads and writes rows up to it). The rows are read as Python numbers: a handful of values, for which one copy
    costs less than the nine small torch operations of a comparison (a one-pair call checks a dozen such)."""
    check_rows(image_hw, "image_hw", b, 2)
    for row in image_hw.tolist():
        if not (1 <= row[0] <= h and 1 <= row[1] <= w):
            raise InputError(f"image_hw: expected (height, width) rows with 1 <= height <= {h} and 1 <= width <= {w} "
                             f"(the image tensors' size), got {row}")
    return image_hw


def check_positive_hw(image_hw: torch.Tensor, b: int) -> torch.Tensor:
    """Each pair's size ``(B, 2)`` int, at least 1, where no image tensor bounds it (a stage given points only:
    rectification, row alignment; :func:`check_image_hw` where one does)."""
    check_rows(image_hw, "image_hw", b, 2)
    if image_hw.numel() and int(image_hw.min()) < 1:
        raise InputError(f"image_hw: expected positive (height, width) per pair, got {image_hw.tolist()[:4]}")
    return image_hw


def check_boxes(boxes: torch.Tensor, b: int, h: int, w: int, name: str = "boxes") -> torch.Tensor:
    """Boxes ``(B, 4)`` int as x0, y0, width, height, each inside the ``H × W`` frame (a kernel writes them)."""
    check_rows(boxes, name, b, 4)
    for x0, y0, width, height in boxes.tolist():
        if min(x0, y0, width, height) < 0 or x0 + width > w or y0 + height > h:
            raise InputError(f"{name}: expected (x0, y0, width, height) rows inside the {h} x {w} frame, "
                             f"got {[x0, y0, width, height]}")
    return boxes


def check_counts(counts: torch.Tensor, name: str, b: int, upper: int) -> torch.Tensor:
    """Per-pair counts ``(B,)`` int in ``[1, upper]`` (e.g. each pair's disparities within the batch's D)."""
    check_rows(counts, name, b)
    for count in counts.tolist():
        if not 1 <= count <= upper:
            raise InputError(f"{name}: expected values in [1, {upper}], got {count}")
    return counts


def as_integer_tensor(value: object, name: str, device: torch.device) -> torch.Tensor:
    """``value``, an int, a list of ints or an int tensor, as a tensor on ``device`` (the dtype is checked by the
    caller, which names what it expects). Why: a string or None failed inside ``torch.as_tensor``, and a meta-device
    tensor in a copy ("Cannot copy out of meta tensor"), naming no argument (an audit of the differentiable API)."""
    if isinstance(value, torch.Tensor) and value.is_meta:
        raise InputError(f"{name}: expected an int or an int tensor (one per pair), got a meta-device tensor")
    try:
        return torch.as_tensor(value, device=device)
    except (TypeError, ValueError, RuntimeError):
        raise InputError(f"{name}: expected an int or an int tensor (one per pair), got {repr(value)[:60]}") from None


def check_nonempty(image: torch.Tensor, name: str) -> None:
    """An image batch ``(..., H, W)`` with H, W >= 1: the kernels (and the torch paths' sampling, padding and
    reductions) need a pixel to read; an empty batch (B = 0) is fine."""
    if image.shape[-1] < 1 or image.shape[-2] < 1:
        raise InputError(f"{name}: expected images of at least 1 x 1 pixels, got {tuple(image.shape)}")


def check_number(value: float, name: str, low: float | None = None, high: float | None = None) -> float:
    """A finite real parameter within ``[low, high]`` (NaN fails every comparison, so it is caught here rather
    than cast to an integer in C, which is undefined)."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a finite number, got {value!r}") from None
    if not math.isfinite(number) or (low is not None and number < low) or (high is not None and number > high):
        bounds = f" in [{low if low is not None else '-inf'}, {high if high is not None else 'inf'}]"
        raise InputError(f"{name}: expected a finite number{bounds}, got {value!r}")
    return number


def settings_table(settings: dict[str, float], names: tuple[str, ...], counts: dict[str, int],
                   low: float | None = None) -> torch.Tensor:
    """``settings`` as the float64 table ``(len(names),)`` a kernel reads, in the order of ``names`` (its C source's
    ``enum``): exactly those names, each a finite number (at least ``low``), those in ``counts`` whole numbers of at
    least their value there (a kernel casts them to integers)."""
    if set(settings) != set(names):
        raise InputError(f"settings: expected exactly {', '.join(names)}, got {', '.join(sorted(settings))}")
    values = [check_number(settings[name], f"settings[{name!r}]", low) for name in names]
    for name, least in counts.items():
        if not (float(settings[name]).is_integer() and least <= settings[name] < 2**53):
            raise InputError(f"settings[{name!r}]: expected a whole number >= {least}, got {settings[name]!r}")
    return torch.tensor(values, dtype=torch.float64)


def canonical_bool(mask: torch.Tensor) -> torch.Tensor:
    """``mask`` with bytes 0 / 1 only: a bool tensor viewed from other bytes (``uint8.view(torch.bool)``) is read
    as "nonzero is True", as NumPy does. One ``amax`` over the bytes (16 masks of 320×240, one thread: 0.02 ms,
    where ``(bytes > 1).any()`` took 20); a new tensor only when some byte is not 0 or 1."""
    if mask.dtype != torch.bool or mask.numel() == 0:
        return mask
    raw = mask.view(torch.uint8)  # the same bytes, any strides
    if int(raw.amax()) > 1:
        return raw != 0
    return mask
