"""Low-level readers for the file formats of the stereo data sets (``../shared/data/MANIFEST.md`` §2).

Every reader raises :class:`~svs_torch.core.checks.InputError` with one line that names the argument and the problem
(missing file, unreadable file, wrong channel count, unsupported dtype). Images are read with OpenCV so that the
gray levels equal OpenCV's own (the segmentation stage compares its Otsu threshold with ``cv2.threshold``).
Nothing here is differentiable: these are file readers.
"""

from __future__ import annotations

import math
import re
import sys
import threading
import warnings
from pathlib import Path

import cv2
import numpy as np
import torch

from ..core.camera import MAX_SIZE_PX, calibration_value_expected
from ..core.checks import InputError, check_float_dtype, check_real
from ..core.files import display_path, write_bytes_atomic
from ..core.image_files import check_file as _check_file
from ..core.image_files import read_image_array as _imread

__all__ = [
    "read_pfm",
    "read_middlebury_calib",
    "read_gray_image",
    "read_kitti_disparity",
    "read_scaled_disparity",
    "write_kitti_disparity",
    "write_pfm",
]

# Full-scale value of each supported integer image dtype: a pixel becomes value / full scale in [0, 1].
_FULL_SCALE = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}
#: A 16-bit image whose brightest level is under this (12 bits) likely holds a 10- or 12-bit sensor's levels.
_FEW_BITS_LEVEL = 4096


def read_pfm(path: str | Path, name: str = "path") -> np.ndarray:
    """Read a PFM file (Middlebury ``disp0GT.pfm``) as float32.

    Header ``Pf`` (1 channel) or ``PF`` (3 channels), then ``W H``, then a scale whose sign gives the byte order
    (negative = little endian). Rows are stored bottom-to-top, so the result is flipped to top-to-bottom.
    Unknown disparities are ``+inf`` in Middlebury files and are kept as such (test with ``np.isfinite``).

    Returns:
        ``(H, W)`` float32 for ``Pf``, ``(H, W, 3)`` for ``PF``.
    """
    path = _check_file(path, name)
    with path.open("rb") as handle:
        # The header is three text lines; read it line by line so the binary payload after it stays intact.
        header = handle.readline().strip()
        if header not in (b"Pf", b"PF"):
            raise InputError(f"{name}: not a PFM file (expected header 'Pf' or 'PF', got {header[:8]!r}): {path}")
        dims = handle.readline().split()
        scale_line = handle.readline().strip()
        try:
            width, height = int(dims[0]), int(dims[1])
            scale = float(scale_line)
        except (IndexError, ValueError):
            raise InputError(f"{name}: malformed PFM header (size {dims!r}, scale {scale_line!r}): {path}") from None
        if width < 1 or height < 1 or not math.isfinite(scale) or scale == 0:
            # The scale's sign is the byte order: zero or NaN says nothing.
            raise InputError(f"{name}: malformed PFM header (expected a positive width and height and a nonzero "
                             f"scale, got {width} x {height}, scale {scale_line.decode(errors='replace')!r}): "
                             f"{display_path(path)}")
        payload = handle.read()
    channels = 1 if header == b"Pf" else 3
    count = width * height * channels
    if len(payload) < 4 * count:
        raise InputError(f"{name}: truncated PFM: expected {4 * count} bytes of data, got {len(payload)}: {path}")
    # More data than the header's size (another size, or 3 channels under 'Pf') was read as its first W x H values
    # and the scene scored as OK (an audit); a stray line end after the data is no such file.
    if len(payload) - 4 * count >= 4 or payload[4 * count:].strip():
        raise InputError(f"{name}: expected {4 * count} bytes of data for {width} x {height} x {channels} "
                         f"({header.decode()}), got {len(payload)}: its header's size does not match its data: {path}")
    dtype = np.dtype("<f4") if scale < 0 else np.dtype(">f4")
    data = np.frombuffer(payload, dtype=dtype, count=count)
    shape = (height, width) if channels == 1 else (height, width, 3)
    return np.ascontiguousarray(np.flipud(data.reshape(shape))).astype(np.float32, copy=False)


# "key = value" with spaces or tabs around either side, on one line; a value is a bracketed matrix or one token.
_CALIB_ENTRY = re.compile(r"(\w+)[ \t]*=[ \t]*(\[[^\]]*\]|[^\s\[\]]*)")
#: calib.txt's values that must be finite and positive (focal lengths and sizes), or only finite.
_CALIB_POSITIVE = ("baseline", "width", "height")
#: How far a calib.txt's doffs may lie from cam1's cx − cam0's cx, pixels: the files print 3 decimals (the shared
#: copies agree within 0.001 px); a tenth of a pixel leaves room for a file rounded otherwise (a scene refused is
#: lost to a whole evaluation) and still catches a contradiction (doffs 500 for cams 52 px apart).
_DOFFS_AGREE_PX = 0.1


def read_middlebury_calib(path: str | Path, name: str = "path") -> dict[str, float | np.ndarray]:
    """Read a Middlebury 2014 / MiddEval3 ``calib.txt``.

    Tolerant of the odd whitespace of the shared copies (``" doffs= 53.271 "``, leading spaces). Matrices
    ``cam0=[f 0 cx0; 0 f cy; 0 0 1]`` become ``(3, 3)`` float64 arrays; other values become floats.

    Returns:
        A dict with at least ``cam0``, ``cam1`` (pixels), ``doffs`` (pixels, ``cx1 − cx0``) and ``baseline``
        (millimetres), plus whatever else the file holds (``width``, ``height``, ``ndisp``, ``vmin``, ...).

    Raises:
        InputError: naming ``name``, the key and the file, for a key given twice or without a value, a value that
            is not a number (or a 3×3 matrix for ``cam0`` / ``cam1``), a baseline, width, height or focal length
            that is not finite and positive, or a doffs that is not finite; a focal, doffs or baseline out of the
            range of any rig (the options' bounds, :data:`~svs_torch.core.camera.CALIBRATION_RANGES`), or a width
            or height that is not a whole number of pixels up to :data:`~svs_torch.core.camera.MAX_SIZE_PX`.
    """
    path = _check_file(path, name)
    text = path.read_text(encoding="ascii", errors="replace")
    calib: dict[str, float | np.ndarray] = {}
    for key, raw in _CALIB_ENTRY.findall(text):
        if key in calib:
            raise InputError(f"{name}: '{key}' given twice: {display_path(path)}")
        try:
            if raw.startswith("["):
                rows = [row.split() for row in raw.strip("[]").split(";")]
                calib[key] = np.array(rows, dtype=np.float64)
            else:
                calib[key] = float(raw)
        except ValueError:
            raise InputError(f"{name}: expected a number for '{key}', got {raw!r}: {display_path(path)}") from None
    for key in ("cam0", "cam1", "doffs", "baseline"):
        if key not in calib:
            raise InputError(f"{name}: calib file lacks '{key}': {display_path(path)}")
    _check_calib_values(calib, name, path)
    return calib


def _check_calib_values(calib: dict, name: str, path: Path) -> None:
    """The values depth is computed from, checked (see :func:`read_middlebury_calib`)."""
    for key in ("cam0", "cam1"):
        if np.shape(calib[key]) != (3, 3):
            raise InputError(f"{name}: expected {key} as a 3x3 matrix, got shape {np.shape(calib[key])}: "
                             f"{display_path(path)}")
        focal = calib[key][0, 0]
        if not (np.isfinite(calib[key]).all() and focal > 0):
            raise InputError(f"{name}: expected {key} finite with a positive focal length, got f {focal:g}: "
                             f"{display_path(path)}")
    for key in ("doffs", *_CALIB_POSITIVE):
        value = calib.get(key)
        if isinstance(value, np.ndarray):  # "doffs=[1 2]": an internal TypeError stopped the whole eval run (an audit)
            raise InputError(f"{name}: expected a number for '{key}', got a matrix: {display_path(path)}")
        if isinstance(value, float) and not (math.isfinite(value) and (key == "doffs" or value > 0)):
            need = "a finite number" if key == "doffs" else "a finite positive number"
            raise InputError(f"{name}: expected {need} for '{key}', got {value:g}: {display_path(path)}")
    _check_calib_ranges(calib, name, path)
    _check_calib_agrees(calib, name, path)


def _check_calib_agrees(calib: dict, name: str, path: Path) -> None:
    """cam0 and cam1 of rectified views (one focal length) and doffs their principal points' x apart, as the format
    defines it (``doffs = cx1 − cx0``; within :data:`_DOFFS_AGREE_PX`). Why: Teddy's file edited to 'doffs= 500' (its
    cams say 52) ranged it at 0.225 m for 1.405 m, and eval scored it 99.9 % (the truth's depth read the same doffs);
    a cam1 of another focal was never read (an audit of numbers read from files)."""
    cam0, cam1 = calib["cam0"], calib["cam1"]
    if not math.isclose(cam0[0, 0], cam1[0, 0], rel_tol=1e-4):  # (room for rounding, as the doffs')
        raise InputError(f"{name}: expected cam0 and cam1 with one focal length (rectified views), got {cam0[0, 0]:g} "
                         f"and {cam1[0, 0]:g} px: {display_path(path)}")
    apart_px = cam1[0, 2] - cam0[0, 2]
    if not abs(calib["doffs"] - apart_px) <= _DOFFS_AGREE_PX:
        raise InputError(f"{name}: expected 'doffs' = cam1's cx - cam0's cx ({apart_px:g} px, the format's definition),"
                         f" got {calib['doffs']:g}: {display_path(path)}")


def _check_calib_ranges(calib: dict, name: str, path: Path) -> None:
    """The values in the ranges any rig's take (:data:`svs_torch.core.camera.CALIBRATION_RANGES`, as the options
    ``--focal-px``, ``--baseline-m``, ``--doffs-px``), and whole pixel counts for the size. Why: a baseline of 1e9 mm,
    a focal or doffs of 1e30 px and a width of 0.0001 px (Teddy's focal scaled to 6.75e9 px) were each ranged and
    scored, status OK (an audit of numbers read from files)."""
    values = [(f"{key}'s focal", "focal_px", calib[key][0, 0], 1.0, "px") for key in ("cam0", "cam1")]
    values += [("doffs", "doffs_px", calib["doffs"], 1.0, "px"),
               ("baseline", "baseline_m", calib["baseline"], 1e-3, "mm")]
    for label, kind, value, to_range_unit, unit in values:  # (the file's baseline in mm, the range's in metres)
        if (expected := calibration_value_expected(kind, float(value) * to_range_unit)) is not None:
            raise InputError(f"{name}: '{label}' {value:g} {unit}: expected {expected}: {display_path(path)}")
    for key in ("width", "height"):
        value = calib.get(key)
        if isinstance(value, float) and not (value.is_integer() and value <= MAX_SIZE_PX):
            raise InputError(f"{name}: expected a whole number of pixels from 1 to {MAX_SIZE_PX} for '{key}', got "
                             f"{value:g}: {display_path(path)}")


#: The warnings held in this thread by :func:`~svs_torch.data.scene_batch.warnings_once_loaded`: a stack, one list
#: of (message, category, filename, lineno) per loader running. Thread-local, not ``warnings.catch_warnings``: that
#: swaps the process's filters, and ``eval``'s loader thread, inside it while the caller's thread entered and left
#: its own, left the caller's filter (an ``ignore``) in force for good (an audit of the API's effect on its caller).
HELD_WARNINGS = threading.local()


def warn_when_loaded(message: str, category: type[Warning] = RuntimeWarning, stacklevel: int = 2) -> None:
    """``warnings.warn(message, category)`` from the caller of the function that calls this (``stacklevel`` counts
    as warnings.warn's does, from that function), or held until the loader running in this thread has read its whole
    pair (:func:`~svs_torch.data.scene_batch.warnings_once_loaded`)."""
    stack = getattr(HELD_WARNINGS, "stack", None)
    if not stack:
        warnings.warn(message, category, stacklevel=stacklevel + 1)
        return
    frame = sys._getframe(stacklevel)  # where warnings.warn would say it came from
    stack[-1].append((message, category, frame.f_code.co_filename, frame.f_lineno))


def read_gray_image(path: str | Path, name: str = "path", dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Read an 8- or 16-bit gray or colour image (alpha ignored) as a gray tensor ``(1, 1, H, W)`` in [0, 1].

    Color images are converted with ``cv2.cvtColor(BGR2GRAY)``, so the gray levels equal OpenCV's own
    conversion (0.299 R + 0.587 G + 0.114 B, rounded to the input's integer type); a JPEG is decoded to its
    luma at once, as ``cv2.imread(path, cv2.IMREAD_GRAYSCALE)`` and ``guide``'s live frames are
    (:func:`~svs_torch.core.image_files.read_image_array`'s ``gray``). uint8 values are divided by 255 and uint16
    by 65535; a uint8 image round-trips exactly: ``round(tensor * 255)`` gives it back. Not differentiable (a
    tensor read from a file, with no ``grad_fn``).

    Raises:
        InputError: naming ``name``, for a missing file, a file OpenCV cannot decode, a channel count other
            than 1 to 4, or a dtype other than uint8 / uint16.
    """
    # Gray levels in [0, 1] need a float type the pipeline computes in; int64 would floor them to 0 or 1.
    check_float_dtype(dtype)
    array = _imread(path, name, gray=True)
    channels = 1 if array.ndim == 2 else array.shape[2]
    if channels not in (1, 2, 3, 4):
        raise InputError(f"{name}: expected 1 (gray), 2 (gray + alpha), 3 (BGR) or 4 (BGRA) channels, "
                         f"got {channels}: {path}")
    if array.dtype not in _FULL_SCALE:
        # Said how to mend it (an audit): a float image's scale, [0, 1] or [0, 255], is not in the file.
        raise InputError(f"{name}: expected a uint8 or uint16 image, got {array.dtype} (save it as an 8- or 16-bit "
                         f"image; a float image's scale is not known): {path}")
    if array.shape[0] < 1 or array.shape[1] < 1:
        raise InputError(f"{name}: expected an image of at least 1x1 pixels, got {array.shape[1]}x{array.shape[0]}")
    # The alpha channel of a gray + alpha or BGRA file is dropped: the camera sees the colour, not the mask.
    if channels in (3, 4):
        array = cv2.cvtColor(array, cv2.COLOR_BGR2GRAY if channels == 3 else cv2.COLOR_BGRA2GRAY)
    elif array.ndim == 3:
        array = array[:, :, 0]
    full_scale = _FULL_SCALE[array.dtype]
    if array.dtype == np.uint16 and 0 < (brightest := int(array.max())) < _FEW_BITS_LEVEL:
        warn_when_loaded(f"{name}: a 16-bit image whose brightest level is {brightest} of 65535, read as nearly "
                         f"black; if it holds 10- or 12-bit data, scale it to the full 16-bit range: {path}")
    if array.dtype == np.uint8:  # (float32 or float64: check_float_dtype)
        # k / 255 divided in the dtype itself: for each of the 256 levels the value the float64 division gives
        # rounded to float32 (tests/data/test_data.py tries them all), in two passes instead of four (0.26 ->
        # 0.12 ms a 320x240 view).
        return torch.from_numpy(array).to(dtype).div_(full_scale)[None, None]
    # Divide in float64 then cast: k / 255 rounded once to float32 lies within half an ulp of the exact value,
    # so multiplying by 255 and rounding recovers k exactly.
    gray = torch.from_numpy(array.astype(np.float64) / full_scale).to(dtype)
    return gray[None, None]  # (1, 1, H, W)


def read_scaled_disparity(path: str | Path, scale: float, name: str = "path") -> tuple[np.ndarray, np.ndarray]:
    """Read an integer disparity map stored as ``value = disparity · scale`` with 0 = unknown.

    Middlebury 2005/2006 third size (scale 3), 2003 quarter (4), 2001 Venus (8) and Tsukuba (16), KITTI
    (uint16, 256), OpenCV ``aloeGT.png`` (1).

    Returns:
        disparity ``(H, W)`` float32 in pixels (0 where unknown) and validity ``(H, W)`` bool.
    """
    check_real(scale, "scale", 0.0, low_open=True)  # 0 gave inf disparities, a negative one negative ones
    array = _imread(path, name)
    if array.ndim != 2:
        raise InputError(f"{name}: expected a 1-channel disparity image, got {array.shape[2]} channels: {path}")
    if array.dtype not in _FULL_SCALE:
        raise InputError(f"{name}: expected a uint8 or uint16 disparity image, got {array.dtype}: {path}")
    return _scaled_disparity(array, scale)


def _scaled_disparity(array: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Disparity ``value / scale`` (0 where the value is 0, unknown) in float32, and its validity."""
    valid = array > 0
    disparity = np.where(valid, array.astype(np.float32) / np.float32(scale), np.float32(0.0))
    return disparity.astype(np.float32), valid


def write_pfm(path: str | Path, array: np.ndarray) -> None:
    """Write an ``(H, W)`` map as a one-channel PFM (``Pf``, little-endian float32: scale −1, rows bottom to
    top), the Middlebury SDK's disparity format; ``+inf`` marks unknown disparities. :func:`read_pfm` reads it
    back bit for bit. Written whole through :func:`~svs_torch.core.files.write_bytes_atomic`."""
    array = np.asarray(array)
    if array.ndim != 2 or array.shape[0] < 1 or array.shape[1] < 1 or not np.issubdtype(array.dtype, np.floating):
        raise InputError(f"array: expected a non-empty (H, W) float map, got {array.dtype} {array.shape}")
    height, width = array.shape
    header = f"Pf\n{width} {height}\n-1\n".encode("ascii")
    write_bytes_atomic(path, header + np.ascontiguousarray(np.flipud(array), dtype="<f4").tobytes())


#: KITTI's disparity PNG: uint16, value = disparity · 256, 0 = unknown.
KITTI_DISPARITY_SCALE = 256.0


def write_kitti_disparity(path: str | Path, disparity_px: np.ndarray, valid: np.ndarray) -> None:
    """Write an ``(H, W)`` disparity map as KITTI's uint16 PNG: ``round(d · 256)`` where ``valid``, 0 elsewhere.

    A valid disparity is clipped to [1/256, 65535/256] px, the values the format can hold as known (0 means
    unknown, so a known disparity below 1/512 px is written as 1/256 rather than lost); a negative or non-finite
    one is written unknown. :func:`read_kitti_disparity` reads back exactly the multiples of 1/256 in that range.
    Written whole through :func:`~svs_torch.core.files.write_bytes_atomic`."""
    disparity_px, valid = np.asarray(disparity_px), np.asarray(valid)
    if disparity_px.ndim != 2 or disparity_px.size == 0 or valid.shape != disparity_px.shape or valid.dtype != bool:
        raise InputError(f"disparity_px, valid: expected a non-empty (H, W) map and an (H, W) bool mask, got "
                         f"{disparity_px.shape} and {valid.dtype} {valid.shape}")
    known = valid & np.isfinite(disparity_px) & (disparity_px >= 0)
    scaled = np.rint(np.where(known, disparity_px, 0).astype(np.float64) * KITTI_DISPARITY_SCALE)
    values = np.where(known, np.clip(scaled, 1, 65535), 0).astype(np.uint16)
    ok, encoded = cv2.imencode(".png", values)
    if not ok:  # pragma: no cover - OpenCV encodes any uint16 gray image as PNG
        raise InputError(f"path: OpenCV could not encode a {values.shape} uint16 PNG for {display_path(path)}")
    write_bytes_atomic(path, encoded.tobytes())


def read_kitti_disparity(path: str | Path, name: str = "path") -> tuple[np.ndarray, np.ndarray]:
    """Read a KITTI disparity PNG (uint16, value / 256, 0 = unknown): disparity ``(H, W)`` float32 pixels (0
    where unknown) and validity ``(H, W)`` bool."""
    array = _imread(path, name)
    if array.dtype != np.uint16:
        raise InputError(f"{name}: expected a uint16 KITTI disparity PNG, got {array.dtype}"
                         f"{'' if array.ndim == 2 else f' with {array.shape[2]} channels'}: {display_path(path)}")
    if array.ndim != 2:
        raise InputError(f"{name}: expected a 1-channel KITTI disparity PNG, got {array.shape[2]} channels: "
                         f"{display_path(path)}")
    return _scaled_disparity(array, KITTI_DISPARITY_SCALE)
