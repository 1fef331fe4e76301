"""What every loader of :mod:`svs_torch.data.datasets` and :mod:`svs_torch.data.middlebury` shares: a scene folder
checked, both views read, a B = 1 :class:`~svs_torch.core.types.StereoBatch` made from them and the scene's truth,
and the warnings of a load given only once it has succeeded. Nothing here is differentiable: these are file readers.
"""

from __future__ import annotations

import contextlib
import os
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from ..core.checks import InputError
from ..core.files import display_path, path_kind
from ..core.image_files import read_image_array
from ..core.types import StereoBatch
from .formats import HELD_WARNINGS, read_gray_image

__all__ = ["check_scene_dir", "make_scene_batch", "named_folder", "read_mask_image", "read_view_pair",
           "warnings_once_loaded"]


def named_folder(path: str | Path) -> Path:
    """``path`` as a :class:`Path` whose last part is the folder's name: ``.`` and ``..`` (and ``a/..``) resolved,
    whose :attr:`Path.name` is empty or ``..``. Why: ``cd Teddy && svs-depth estimate .`` named the scene "eval3/",
    its calibration "/calib.txt", and wrote its map to maps/eval3/ instead of maps/Teddy/ (an audit)."""
    return Path(os.path.realpath(path)) if Path(path).name in ("", "..") else Path(path)


def check_scene_dir(path: str | Path, name: str) -> Path:
    """``path`` as a :class:`Path` (:func:`named_folder`); :class:`InputError` naming ``name`` unless it is a
    folder."""
    kind = path_kind(path, name)
    if kind != "folder":
        raise InputError(f"{name}: expected a folder, got {'no such path' if kind == 'missing' else 'a file'}: "
                         f"{display_path(path)}")
    return named_folder(path)


def make_scene_batch(
    left: torch.Tensor,
    right: torch.Tensor,
    name: str,
    focal_px: float,
    baseline_m: float,
    doffs_px: float = 0.0,
    calibrated: bool = False,
    disparity: np.ndarray | None = None,
    valid: np.ndarray | None = None,
    nonoccluded: np.ndarray | None = None,
) -> StereoBatch:
    """One-pair batch from ``(1, 1, H, W)`` images and an optional ``(H, W)`` disparity, its mask and its
    non-occluded mask (kept only where the disparity is valid)."""
    h, w = left.shape[-2:]
    if right.shape != left.shape:
        rh, rw = right.shape[-2:]
        raise InputError(f"right: expected the size of left {w}x{h} (WxH), got {rw}x{rh} [{name}]")
    disparity_t = valid_t = None
    if disparity is not None:
        if disparity.shape != (h, w):
            raise InputError(f"disparity: expected the size of left {w}x{h} (WxH), got "
                             f"{disparity.shape[1]}x{disparity.shape[0]} [{name}]")
        _check_truth_range(disparity, valid, w, name)
        disparity_t = torch.from_numpy(np.ascontiguousarray(disparity)).to(left.dtype)[None, None]
        valid_t = torch.from_numpy(np.ascontiguousarray(valid))[None, None]
    nonoccluded_t = None
    if nonoccluded is not None:
        if nonoccluded.shape != (h, w):
            raise InputError(f"nonoccluded: expected the size of left {w}x{h} (WxH), got "
                             f"{nonoccluded.shape[1]}x{nonoccluded.shape[0]} [{name}]")
        nonoccluded_t = torch.from_numpy(np.ascontiguousarray(nonoccluded & valid))[None, None]
    return StereoBatch.from_images(left, right, focal_px, baseline_m, doffs_px, calibrated,
                                   disparity_px=disparity_t, disparity_valid=valid_t, names=(name,),
                                   disparity_nonoccluded=nonoccluded_t)


def _check_truth_range(disparity: np.ndarray, valid: np.ndarray, width: int, name: str) -> None:
    """Refuse a ground truth whose known disparities are not in ``[0, width)`` px: no match lies outside the
    image. Why: a Middlebury 2003 ``disp2.png`` saved as 16 bits was read as disparities up to 16 000 px and
    scored (0 % accuracy, a median error of 9 933 px), and a PFM of −5 everywhere likewise (an audit of hostile
    data)."""
    known = disparity[valid]
    if known.size and (float(known.min()) < 0 or float(known.max()) >= width):
        raise InputError(f"disparity: expected ground-truth disparities in [0, {width}) px (the image's width), "
                         f"got {float(known.min()):g} to {float(known.max()):g} px (a file of another bit depth or "
                         f"scale?) [{name}]")


@contextlib.contextmanager
def warnings_once_loaded() -> Iterator[None]:
    """The loaders' own warnings given inside (:func:`~.formats.warn_when_loaded`: a 16-bit file read as nearly
    black), given only when the block completes: a pair that then fails (its right view missing, of another size,
    its ground truth unreadable) gets its one error, not a warning about a view first. Each loader of
    :mod:`.datasets` and :mod:`.middlebury` is wrapped in it whole (a context manager made by ``contextmanager`` is
    also a decorator)."""
    # Held per thread (formats.HELD_WARNINGS), not by warnings.catch_warnings: that swaps the process's filters, which
    # eval's loader thread did while the caller's thread ran (an audit: a caller's filter left in force for good).
    stack = HELD_WARNINGS.__dict__.setdefault("stack", [])
    held: list = []
    stack.append(held)
    try:
        yield
    finally:
        stack.pop()
    for message, category, filename, lineno in held:  # to the enclosing loader's block, if any, else given now
        if stack:
            stack[-1].append((message, category, filename, lineno))
        else:
            warnings.warn_explicit(message, category, filename, lineno)


def read_view_pair(left_path: Path, right_path: Path, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Both views as gray ``(1, 1, H, W)`` tensors, each file's errors naming ``left`` or ``right``."""
    return read_gray_image(left_path, "left", dtype), read_gray_image(right_path, "right", dtype)


def read_mask_image(path: Path, name: str) -> np.ndarray:
    """A one-channel 8-bit mask image as ``(H, W)`` uint8."""
    array = read_image_array(path, name)
    if array.ndim != 2 or array.dtype != np.uint8:
        raise InputError(f"{name}: expected a 1-channel uint8 mask image, got {array.dtype} with shape "
                         f"{array.shape}: {display_path(path)}")
    return array
