"""Resampling stereo batches to another size, and collating pairs of different sizes into one batch.

Scaling rules (pixel-centre coordinates, ``x_new = (x_old + 0.5)·sx − 0.5`` with ``sx = W_new / W_old``):
a left pixel x_L that sees the right pixel x_L − d maps to x_L·sx and sees (x_L − d)·sx, so disparities, the
x focal length and ``doffs`` (a difference of principal-point x coordinates) all scale by sx. ``focal_px`` is the
x focal length; if the aspect ratio changes, the y focal length scales by sy = H_new / H_old, which the
batch does not store because only x matters for disparity and depth ``Z = f·B / (d + doffs)`` (and Z is
unchanged by the resize). Differentiable w.r.t. the images (bilinear); the GT resampling is not.
"""

from __future__ import annotations

import dataclasses
import functools
import operator
from collections.abc import Sequence

import torch
import torch.nn.functional as F

from ..core.camera import MAX_SIZE_PX
from ..core.checks import InputError, check_instance, checked_images
from ..core.types import StereoBatch

__all__ = ["resize_stereo_batch", "collate_stereo_batches"]


def _check_size_wh(size_wh: Sequence[int], name: str = "size_wh") -> tuple[int, int]:
    try:
        width, height = (operator.index(v) for v in size_wh)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected (width, height) as two ints, got {size_wh!r}") from None
    if width <= 0 or height <= 0:
        raise InputError(f"{name}: expected a positive width and height, got ({width}, {height})")
    if max(width, height) > MAX_SIZE_PX:  # as --size: (100000, 100000) failed in torch's allocator (40 GB)
        raise InputError(f"{name}: expected a width and height of at most {MAX_SIZE_PX} px, got ({width}, {height})")
    return width, height


def _crop(batch: StereoBatch, height: int, width: int) -> StereoBatch:
    """The top-left ``height × width`` part of every tensor image of ``batch`` (drops bottom/right padding)."""
    fields = {}
    for name in ("left", "right", "disparity_px", "disparity_valid", "disparity_nonoccluded"):
        value = getattr(batch, name)
        fields[name] = None if value is None else value[..., :height, :width]
    return dataclasses.replace(batch, **fields)


def _resize_filled(batch: StereoBatch, width: int, height: int) -> StereoBatch:
    """Resize a batch whose pairs all fill its tensors (no padding) to ``width × height``."""
    b = batch.batch_size
    sx = width / batch.size_hw[1]  # x scale: disparity, focal and doffs are x quantities

    def bilinear(image: torch.Tensor) -> torch.Tensor:
        # antialias: a box-like prefilter when shrinking 2–4×, so the small image is not aliased; the clamp only
        # removes float rounding above 1 (the filter weights are positive, so there is no real overshoot).
        out = F.interpolate(image, size=(height, width), mode="bilinear", align_corners=False, antialias=True)
        return out.clamp(0.0, 1.0)

    disparity = valid = nonoccluded = None
    if batch.disparity_px is not None:
        # Nearest at pixel centres: each new pixel takes one GT sample, so a depth edge never blends foreground
        # and background disparities into a value that belongs to neither surface.
        disparity = F.interpolate(batch.disparity_px, size=(height, width), mode="nearest-exact") * sx
        valid_float = batch.disparity_valid.to(batch.left.dtype)
        valid = F.interpolate(valid_float, size=(height, width), mode="nearest-exact") > 0.5
        disparity = torch.where(valid, disparity, torch.zeros_like(disparity))
        if batch.disparity_nonoccluded is not None:  # the same GT samples as the disparity's
            nonoccluded_float = batch.disparity_nonoccluded.to(batch.left.dtype)
            nonoccluded = (F.interpolate(nonoccluded_float, size=(height, width), mode="nearest-exact") > 0.5) & valid
    image_hw = torch.tensor([[height, width]], dtype=torch.int64, device=batch.left.device).expand(b, 2).clone()
    return dataclasses.replace(
        batch,
        left=bilinear(batch.left),
        right=bilinear(batch.right),
        focal_px=batch.focal_px * sx,
        doffs_px=batch.doffs_px * sx,
        image_hw=image_hw,
        disparity_px=disparity,
        disparity_valid=valid,
        disparity_nonoccluded=nonoccluded,
    )


def resize_stereo_batch(batch: StereoBatch, size_wh: Sequence[int]) -> StereoBatch:
    """Resample every pair of ``batch`` to ``size_wh = (width, height)``, e.g. ``(320, 240)`` for the SVS.

    Images ``(B, 1, H, W)`` → ``(B, 1, height, width)``: bilinear with antialiasing. Ground truth: nearest at
    pixel centres (``"nearest-exact"``), disparity multiplied by ``sx = width / W``, validity resampled the
    same way. ``focal_px`` and ``doffs_px`` are multiplied by sx; ``baseline_m`` is unchanged (see the module
    docstring for why only the x scale matters). A padded batch (``image_hw`` smaller than the tensors) is
    resized pair by pair from each pair's own ``image_hw`` region, so every pair fills the new size and has its
    own sx; ``image_hw`` becomes ``(height, width)`` for all.

    Differentiable w.r.t. ``left`` and ``right``; w.r.t. the ground truth only as nearest sampling copies it (each
    output pixel's gradient goes to the one input pixel it copies, times ``sx``).
    """
    check_instance(batch, "batch", StereoBatch)
    width, height = _check_size_wh(size_wh)
    full = torch.tensor(batch.size_hw, dtype=torch.int64, device=batch.image_hw.device)
    if bool((batch.image_hw == full).all()):
        return _resize_filled(batch, width, height)
    # Pairs of different true sizes need different scale factors, hence one interpolate call per pair.
    pieces = []
    for i, (h, w) in enumerate(batch.image_hw.tolist()):
        pieces.append(_resize_filled(_crop(batch.select([i]), h, w), width, height))
    return _concatenate(pieces)


def _pad_to(batch: StereoBatch, height: int, width: int) -> StereoBatch:
    """Zero-pad the tensors of ``batch`` at the bottom and right to ``height × width``; padding has no GT. A batch
    of that size already is returned as it is."""
    h, w = batch.size_hw
    if (h, w) == (height, width):
        return batch
    pad = (0, width - w, 0, height - h)  # F.pad order: left, right, top, bottom of the last two dims
    disparity = valid = nonoccluded = None
    if batch.disparity_px is not None:
        disparity = F.pad(batch.disparity_px, pad, value=0.0)
        valid = F.pad(batch.disparity_valid, pad, value=False)
    if batch.disparity_nonoccluded is not None:
        nonoccluded = F.pad(batch.disparity_nonoccluded, pad, value=False)
    return dataclasses.replace(batch, left=F.pad(batch.left, pad, value=0.0), right=F.pad(batch.right, pad, value=0.0),
                               disparity_px=disparity, disparity_valid=valid, disparity_nonoccluded=nonoccluded)


def _concatenate(batches: Sequence[StereoBatch]) -> StereoBatch:
    """Stack batches whose tensors share (H, W), in the widest of their dtypes and the first batch's device.

    A batch without ground truth gets disparity 0 and validity False when another batch has ground truth.
    Names are kept; a batch without names contributes empty strings when another batch has names.
    """
    first = batches[0]
    # The widest dtype of them all, whatever the order: in the first's, a float32 pair listed after a float64 one
    # ran in float64 and listed before it in float32 (an audit: R_min 1.4008746147 against 1.400874714446969 m).
    dtype = functools.reduce(torch.promote_types, (b.left.dtype for b in batches))
    batches = [b.to(device=first.left.device, dtype=dtype) for b in batches]

    def cat(name: str) -> torch.Tensor:
        return torch.cat([getattr(b, name) for b in batches], dim=0)

    disparity = valid = None
    if any(b.disparity_px is not None for b in batches):
        disparity = torch.cat([b.disparity_px if b.disparity_px is not None else torch.zeros_like(b.left)
                               for b in batches], dim=0)
        valid = torch.cat([b.disparity_valid if b.disparity_valid is not None
                           else torch.zeros_like(b.left, dtype=torch.bool) for b in batches], dim=0)
    nonoccluded = None
    if any(b.disparity_nonoccluded is not None for b in batches):
        # A pair whose data has no non-occlusion mask: no pixel of it is known to be non-occluded.
        nonoccluded = torch.cat([b.disparity_nonoccluded if b.disparity_nonoccluded is not None
                                 else torch.zeros_like(b.left, dtype=torch.bool) for b in batches], dim=0)
    names: tuple[str, ...] = ()
    if any(b.names for b in batches):
        names = tuple(name for b in batches for name in (b.names or ("",) * b.batch_size))
    left, right = cat("left"), cat("right")
    # Their parts were ranged when those batches were made: not scanned again here (the pipeline ranges the views
    # it is given once more, which refuses a batch written into after it was made).
    with checked_images(left, right):
        return StereoBatch(left=left, right=right, focal_px=cat("focal_px"), baseline_m=cat("baseline_m"),
                           doffs_px=cat("doffs_px"), calibrated=cat("calibrated"), image_hw=cat("image_hw"),
                           disparity_px=disparity, disparity_valid=valid, names=names,
                           disparity_nonoccluded=nonoccluded)


def collate_stereo_batches(
    batches: Sequence[StereoBatch],
    mode: str = "resize",
    size_wh: Sequence[int] | None = None,
) -> StereoBatch:
    """Concatenate batches whose pairs may have different sizes into one batch, in the widest of their dtypes
    (float64 if any is), whatever their order.

    Modes:
        ``"resize"``: resample every pair to ``size_wh`` (default: the first batch's tensor size) with
            :func:`resize_stereo_batch` (disparity, focal and doffs scaled by each pair's sx); ``image_hw`` is
            ``(height, width)`` for all.
        ``"pad"``: no resampling. Pad every pair with zeros at the bottom and right to the largest H and W
            (or to ``size_wh`` if given, which must be at least that large); ``disparity_valid`` is False in
            the padding, and ``image_hw`` keeps each pair's true size, so pixel coordinates are unchanged.

    Pairs without ground truth get disparity 0 and ``disparity_valid`` False when others have it (and
    ``disparity_nonoccluded`` False when others have a non-occlusion mask); ``names`` are
    concatenated (empty strings for batches that have none).

    Returns:
        A :class:`StereoBatch` with B = the total number of pairs.
    """
    if isinstance(batches, StereoBatch) or not batches:
        raise InputError("batches: expected a sequence of at least one StereoBatch, got "
                         + ("one StereoBatch" if isinstance(batches, StereoBatch) else "none"))
    for index, batch in enumerate(batches):
        check_instance(batch, f"batches[{index}]", StereoBatch)
    if mode not in ("resize", "pad"):
        raise InputError(f"mode: expected 'resize' or 'pad', got {mode!r}")
    if mode == "resize":
        width, height = _check_size_wh(size_wh) if size_wh is not None else batches[0].size_hw[::-1]
        return _concatenate([resize_stereo_batch(b, (width, height)) for b in batches])
    height = max(b.size_hw[0] for b in batches)
    width = max(b.size_hw[1] for b in batches)
    if size_wh is not None:
        want_w, want_h = _check_size_wh(size_wh)
        if want_w < width or want_h < height:
            raise InputError(f"size_wh: expected at least the largest pair ({width}, {height}) in pad mode, "
                             f"got ({want_w}, {want_h})")
        width, height = want_w, want_h
    return _concatenate([_pad_to(b, height, width) for b in batches])
