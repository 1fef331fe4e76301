"""Loaders for the real stereo data sets of ``../shared/data`` (formats and scales: ``MANIFEST.md`` §2–4).

Each loader returns a :class:`~svs_torch.core.types.StereoBatch` with B = 1: gray left and right images
``(1, 1, H, W)`` in [0, 1], the ground-truth disparity of the LEFT view ``(1, 1, H, W)`` in pixels (0 where
unknown) with its mask ``disparity_valid``, the calibration where the data set gives one, and one name such as
``"eval3/Teddy"`` (the loader's prefix keeps names unique across data sets that share a scene).
Convention for all: a left pixel x sees the right pixel x − d (verified photometrically, MANIFEST §3).

``calibrated`` is True only where focal, baseline and doffs come from the data (MiddEval3 ``calib.txt``, and the
scenes whose values follow from it); elsewhere the values are nominal and depth is not meaningful.

The Middlebury loaders live in :mod:`.middlebury` (and are importable from here), KITTI, the OpenCV sample, plain
image pairs and the detection of a folder's layout here, what they share in :mod:`.scene_batch`.
"""

from __future__ import annotations

import math
import numbers
import os
import re
import warnings
from pathlib import Path

import numpy as np
import torch

from ..core.camera import CALIBRATION_RANGES, SVS_CAMERA, calibration_value_expected
from ..core.checks import InputError, checked_images
from ..core.dataset_files import KITTI_LAYOUTS, KITTI_LEFT_FOLDERS
from ..core.files import check_path_given, display_path, path_kind
from ..core.image_files import turned_note
from ..core.types import StereoBatch
from .formats import read_kitti_disparity, read_scaled_disparity
from .middlebury import (MIDDLEBURY_2005_BASELINE_M, MIDDLEBURY_2005_DMIN_FULL_PX, MIDDLEBURY_2005_FOCAL_FULL_PX,
                         eval3_calibration_source, load_middlebury_2001, load_middlebury_2003,
                         load_middlebury_2005_2006, load_middlebury_eval3, teddy_2003_calibration_source)
from .scene_batch import check_scene_dir, make_scene_batch, named_folder, read_view_pair, warnings_once_loaded

__all__ = [
    "load_middlebury_eval3",
    "load_middlebury_2005_2006",
    "load_middlebury_2003",
    "load_middlebury_2001",
    "load_kitti",
    "KITTI_LEFT_FOLDERS",
    "kitti_left_images",
    "load_opencv_aloe",
    "load_image_pair",
    "load_stereo_pair",
    "list_shared_pairs",
    "SHARED_DATA_FOLDERS",
    "detect_stereo_layout",
    "SCENE_LEFT_VIEWS",
    "partial_scene_reason",
    "pair_name",
    "scene_name",
    "scene_calibration_source",
]

# KITTI rectified-camera values inferred from the image width (MANIFEST §4; not verified per frame):
# width → (focal px, baseline m). 1242: P_rect_02 of 2011_09_26, B = (44.857 + 339.524) / 721.538.
_KITTI_NOMINAL = {1226: (707.09, 0.537), 1242: (721.5377, 0.5327)}


@warnings_once_loaded()
def load_kitti(root: str | Path, frame: str = "000000_10", dtype: torch.dtype = torch.float32,
               truth: bool = True) -> StereoBatch:
    """KITTI stereo 2012 (``colored_0/1``, ``disp_occ``) or 2015 (``image_2/3``, ``disp_occ_0``) training frame.

    GT is uint16 / 256, 0 = unknown (sparse LiDAR, 19–36 % valid); where the folder also has the non-occluded
    GT (``disp_noc`` / ``disp_noc_0``), its known pixels are ``disparity_nonoccluded`` (the shared copies have
    only the all-pixel ``disp_occ``). A frame without a GT file (a testing frame, an ``_11`` frame) loads without
    ground truth. No calib files are shipped: focal and baseline are the nominal values for the image width
    (MANIFEST §4; the nearest listed width otherwise, its focal scaled by the width over that one's for a resized
    copy), calibrated False — use KITTI for disparity-level evaluation only.
    """
    root = check_scene_dir(root, "root")
    layout = next((layout for layout in KITTI_LAYOUTS if (root / layout[0]).is_dir()), None)
    if layout is None:
        raise InputError(f"root: expected a KITTI training folder with colored_0/ (2012) or image_2/ (2015): {root}")
    *folders, noc, prefix = layout
    left, right = read_view_pair(root / folders[0] / f"{frame}.png", root / folders[1] / f"{frame}.png", dtype)
    read_truth, truth = truth, {}  # (truth=False: the views alone, as the Middlebury loaders read them)
    if read_truth and (root / folders[2] / f"{frame}.png").exists():  # a testing frame, or an _11 frame, has none
        truth["disparity"], truth["valid"] = read_kitti_disparity(root / folders[2] / f"{frame}.png", "disparity")
        if (root / noc / f"{frame}.png").is_file():
            truth["nonoccluded"] = read_kitti_disparity(root / noc / f"{frame}.png", "disparity_noc")[1]
    focal_px, baseline_m = _kitti_nominal_camera(left.shape[-1])
    return make_scene_batch(left, right, f"{prefix}/{frame}", focal_px=focal_px, baseline_m=baseline_m, **truth)


def _kitti_nominal_camera(width_px: int) -> tuple[float, float]:
    """Focal length (px) and baseline (m) for a KITTI frame ``width_px`` wide: the nearest listed width's values,
    the focal scaled by the width over that one's where it is not within 2 % of it (a copy resized by a user: a
    half-size frame kept the native focal and read every distance twice too far, an audit). The native widths of
    the KITTI sequences (1224–1242 px) take their listed values unscaled."""
    listed = min(_KITTI_NOMINAL, key=lambda w: abs(math.log(width_px / w)))
    focal_px, baseline_m = _KITTI_NOMINAL[listed]
    if abs(width_px / listed - 1.0) > 0.02:
        focal_px *= width_px / listed
    return focal_px, baseline_m


def kitti_left_images(root: str | Path) -> list[Path]:
    """The left images of a KITTI folder, sorted: in a training folder those with ground truth, frame ``_10`` (a
    download also holds ``_11``, the next frame of the flow benchmark, with no disparity, which :func:`load_kitti`
    cannot score); in a folder without any (a testing folder), every frame, loaded without truth."""
    root = Path(root)
    for left, _, truth, _, _ in KITTI_LAYOUTS:
        if (root / left).is_dir():
            frames = sorted((root / left).glob("*.png"))
            scored = [path for path in frames if (root / truth / path.name).is_file()]
            return scored or frames
    return []


@warnings_once_loaded()
def load_opencv_aloe(directory: str | Path, dtype: torch.dtype = torch.float32, truth: bool = True) -> StereoBatch:
    """OpenCV sample Aloe (``aloeL.jpg``, ``aloeR.jpg``, ``aloeGT.png`` = d, 0 = unknown), full size 1282×1110.

    Middlebury 2006 nominal full-size focal 3740 px and baseline 0.160 m; dmin unknown → calibrated False.
    """
    directory = check_scene_dir(directory, "directory")
    left, right = read_view_pair(directory / "aloeL.jpg", directory / "aloeR.jpg", dtype)
    disparity, valid = read_scaled_disparity(directory / "aloeGT.png", 1.0, "disparity") if truth else (None, None)
    return make_scene_batch(left, right, "opencv/aloe", focal_px=MIDDLEBURY_2005_FOCAL_FULL_PX,
                            baseline_m=MIDDLEBURY_2005_BASELINE_M, disparity=disparity, valid=valid)


@warnings_once_loaded()
def load_image_pair(
    left_path: str | Path,
    right_path: str | Path,
    focal_px: float | None = None,
    baseline_m: float | None = None,
    doffs_px: float = 0.0,
    dtype: torch.dtype = torch.float32,
) -> StereoBatch:
    """Two plain image files (8/16-bit, gray or BGR), no ground truth.

    Focal and baseline default to the SVS camera model (``SVS_CAMERA.focal_px(width)``,
    ``SVS_CAMERA.baseline_m``); calibrated is True only when both ``focal_px`` and ``baseline_m`` are given.

    Raises:
        InputError: for an unreadable file (naming ``left`` or ``right``), a focal, baseline or doffs out of
            the range any rig takes (:data:`~svs_torch.core.camera.CALIBRATION_RANGES`, as the options'), or
            left and right of different sizes (naming ``right`` and both sizes).
    """
    # Numbers only: a str from a script raised TypeError from math.isfinite, and True was taken as a focal of 1 px.
    def number(value: object) -> bool:
        return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)

    # The ranges the options and a pair list's line are held to (CALIBRATION_RANGES): focal_px=1e30 from a script
    # ranged Teddy at 3e27 m, status OK, where --focal-px 1e30 was refused.
    for name, value in (("focal_px", focal_px), ("baseline_m", baseline_m), ("doffs_px", doffs_px)):
        # (a doffs of None is not "not given": it was float(None)'s TypeError, from load_pair_source too)
        given = value is not None or name == "doffs_px"
        if given and not (number(value) and calibration_value_expected(name, value) is None):
            raise InputError(f"{name}: expected {CALIBRATION_RANGES[name][2]}, got {value!r}")
    for name, path in (("left", left_path), ("right", right_path)):
        if not isinstance(path, (str, os.PathLike)):  # None or bytes: a TypeError from pathlib named neither
            raise InputError(f"{name}: expected an image file name (str or os.PathLike), got "
                             f"{type(path).__name__} {path!r:.60}")
        check_path_given(path, name, "an image file name")  # before Path(), which makes "" the current folder
    left, right = read_view_pair(Path(left_path), Path(right_path), dtype)
    if right.shape != left.shape:  # with the files: the pair's name is a folder's for a generic name (L.png)
        (h, w), (rh, rw) = left.shape[-2:], right.shape[-2:]
        raise InputError(f"right: expected the size of left {w}x{h} (WxH, {display_path(left_path)}"
                         f"{turned_note(left_path, (w, h))}), got {rw}x{rh} ({display_path(right_path)}"
                         f"{turned_note(right_path, (rw, rh))})")
    calibrated = focal_px is not None and baseline_m is not None
    width = left.shape[-1]
    _warn_of_millimetres(focal_px, width)
    with checked_images(left, right):  # k / 255 or k / 65535 as read: in [0, 1], not scanned again (0.2 ms a pair)
        return make_scene_batch(left, right, pair_name(left_path),
                                focal_px=SVS_CAMERA.focal_px(width) if focal_px is None else float(focal_px),
                                baseline_m=SVS_CAMERA.baseline_m if baseline_m is None else float(baseline_m),
                                doffs_px=float(doffs_px), calibrated=calibrated)


def _warn_of_millimetres(focal_px: float | None, width: int) -> None:
    """Warn of a focal length that reads as millimetres. Why: '--focal-px 3.6' (the SVS lens's 3.6 mm) ranged Teddy
    at 0.009 m with the status OK (an audit). A baseline in millimetres is refused: over 2 m
    (:data:`~svs_torch.core.camera.MAX_BASELINE_M`)."""
    if focal_px is not None and focal_px < 0.09 * width:  # a field of view over 160 degrees: no rectified view
        field = math.degrees(2 * math.atan(width / 2 / focal_px))
        warnings.warn(f"focal_px: {focal_px:g} px across an image {width} px wide is a {field:.0f}-degree view: "
                      f"millimetres? In pixels it is mm x width / sensor width (the SVS's 3.6 mm lens: "
                      f"{SVS_CAMERA.focal_px(width):.0f} px at this width)", stacklevel=3)


# Left-image file names that say only "left" (im0.png, imL.png, view1.png, left.png, image_2.png, L.jpg): a pair
# with such a name is named after its folder, the scene.
GENERIC_LEFT_NAME = re.compile(r"(im[0-9lr]?|img[0-9lr]?|image_?[0-9]?|view[0-9]|left|right|[lr]|cam[0-9]?)",
                               re.IGNORECASE)


def pair_name(left_path: str | Path) -> str:
    """A pair's name from its left file: the file's stem (``left01``), or its folder's name when the stem only
    says which view it is (``Teddy/im0.png`` → ``Teddy``)."""
    path = Path(left_path)
    generic = GENERIC_LEFT_NAME.fullmatch(path.stem) is not None
    return path.resolve().parent.name or path.stem if generic else path.stem


@warnings_once_loaded()
def load_stereo_pair(path: str | Path, dtype: torch.dtype = torch.float32, truth: bool = True) -> StereoBatch:
    """Load one pair, detecting the format from a folder's contents.

    ``path`` is a scene folder (MiddEval3, 2005/2006, 2003, 2001), the OpenCV samples folder (Aloe), a KITTI
    training folder (frame 000000_10) or a KITTI left image ``colored_0/<frame>.png`` / ``image_2/<frame>.png``
    (the entries of :func:`list_shared_pairs`). ``truth`` False: the views and calibration alone, no ground truth.
    """
    path = Path(path)
    if path_kind(path, "path") == "file" and path.parent.name in KITTI_LEFT_FOLDERS:
        return load_kitti(path.parent.parent, frame=path.stem, dtype=dtype, truth=truth)
    path = check_scene_dir(path, "path")
    layout = detect_stereo_layout(path)
    if layout is None:
        partial = partial_scene_reason(path)
        raise InputError(f"path: no known stereo layout (MiddEval3, Middlebury 2001–2006, KITTI, OpenCV aloe) in "
                         f"{path}" + (f": {partial}" if partial else ""))
    if layout == "kitti":
        return load_kitti(path, dtype=dtype, truth=truth)
    return _LOADERS[layout](path, dtype, truth=truth)


def detect_stereo_layout(path: str | Path) -> str | None:
    """The data-set layout of a scene folder, from its file names alone (nothing is read): ``"eval3"``,
    ``"2005_2006"``, ``"2003"``, ``"2001"``, ``"aloe"``, ``"kitti"``, or None for a folder (or file) that
    :func:`load_stereo_pair` cannot load as one pair."""
    names = _folder_names(path)
    return None if names is None else _layout_of(names)


def _folder_names(path: str | Path) -> set[str] | None:
    """The names in the folder ``path``; None for a file, or a name no folder can have."""
    try:
        return {entry.name for entry in Path(path).iterdir()}
    except (OSError, ValueError):
        return None


def _layout_of(names: set[str]) -> str | None:
    """The layout whose marker files ``names`` holds (:data:`_LAYOUT_MARKERS`, in order), or None."""
    return next((layout for layout, marker in _LAYOUT_MARKERS if any(set(files) <= names for files in marker)), None)


#: The data sets' names, as messages give them.
LAYOUT_NAMES = {"eval3": "MiddEval3", "2005_2006": "Middlebury 2005/2006", "2003": "Middlebury 2003"}


def partial_scene_reason(path: str | Path) -> str | None:
    """Why a folder that holds part of a scene's files is no scene (``a MiddEval3 scene folder without calib.txt``),
    or None where it is one, or holds none of them. A folder of scene folders left such a folder out of ``eval``
    without a word (an audit: three of five scenes dropped, "2 pairs, 1 failed")."""
    names = _folder_names(path)  # (listed once: a scene's layout and its missing files read the same names)
    if names is None or _layout_of(names) is not None:
        return None
    by_lower = {name.lower(): name for name in names}
    for layout, marker in _LAYOUT_MARKERS:
        for files in (files for files in marker if len(files) > 1):  # (a one-file marker is whole or absent)
            missing = [name for name in files if name not in names]
            if len(missing) == len(files) and not any(name.lower() in by_lower for name in files):
                continue
            other_case = [f"{by_lower[name.lower()]} is there" for name in missing if name.lower() in by_lower]
            hint = f" ({', '.join(other_case)}: file names are case-sensitive)" if other_case else ""
            return f"a {LAYOUT_NAMES[layout]} scene folder without {' and '.join(missing)}{hint}"
    return None


def scene_name(path: str | Path) -> str:
    """The name :func:`load_stereo_pair` gives the scene at ``path`` (``eval3/Teddy``, ``kitti2015/000000_10``,
    ``opencv/aloe``), from its file names alone; the folder's own name for a folder of no known layout."""
    path = named_folder(path)  # ('.': its folder's name, not "")
    prefixes = {layout[0]: layout[-1] for layout in KITTI_LAYOUTS}
    if path.parent.name in prefixes and path.suffix:  # a KITTI left image
        return f"{prefixes[path.parent.name]}/{path.stem}"
    layout = detect_stereo_layout(path)
    if layout == "aloe":
        return "opencv/aloe"
    if layout == "kitti":
        folder = next(layout[0] for layout in KITTI_LAYOUTS if (path / layout[0]).is_dir())
        return f"{prefixes[folder]}/000000_10"
    return f"{layout}/{path.name}" if layout else path.name


def scene_calibration_source(path: str | Path) -> str:
    """Where the calibration :func:`load_stereo_pair` gives the scene at ``path`` comes from, in words: the file
    it was read from, or the nominal values assumed where the data set ships none (the loaders' own rules;
    ``calibrated`` is False exactly where this says "assumed")."""
    path = named_folder(path)  # ('.': its folder's name, which the rules below read)
    if path_kind(path, "path") == "file":  # a KITTI left image
        return "KITTI nominal values for the image width assumed: no calib file shipped"
    layout = detect_stereo_layout(path)
    if layout == "eval3":
        return eval3_calibration_source(path)
    if layout == "2005_2006" and path.name in MIDDLEBURY_2005_DMIN_FULL_PX:
        return "Middlebury nominal f and B, dmin from MiddEval3 ArtL's calib.txt"
    if layout in ("2005_2006", "aloe"):
        return "Middlebury 2005/2006 nominal f and B assumed: no calibration shipped, dmin unknown"
    if layout == "2003" and path.name == "Teddy":
        return teddy_2003_calibration_source(path)
    if layout == "kitti":
        return "KITTI nominal values for the image width assumed: no calib file shipped"
    return "the SVS model assumed: no calibration shipped"


# Each layout's file names (any one set present marks it), in the order they are tried.
_LAYOUT_MARKERS = (
    ("eval3", [("calib.txt", "im0.png")]),
    ("2005_2006", [("view1.png", "disp1.png")]),
    ("2003", [("imL.png", "disp2.png")]),
    ("2001", [("truedisp.pgm",), ("disp2.pgm",)]),
    ("aloe", [("aloeL.jpg",)]),
    ("kitti", [(folder,) for folder in KITTI_LEFT_FOLDERS]),
)
#: The left view file each layout's loader reads (both 2001 scenes' names): the images that a scene folder's own
#: calibration and ground truth describe.
SCENE_LEFT_VIEWS = {"eval3": ("im0.png",), "2005_2006": ("view1.png",), "2003": ("imL.png",),
                    "2001": ("imL.png", "im2.ppm"), "aloe": ("aloeL.jpg",)}
_LOADERS = {"eval3": load_middlebury_eval3, "2005_2006": load_middlebury_2005_2006, "2003": load_middlebury_2003,
            "2001": load_middlebury_2001, "aloe": load_opencv_aloe}


def list_shared_pairs(data_dir: str | Path) -> list[Path]:
    """Every pair with ground truth in the shared data folder, as paths for :func:`load_stereo_pair`.

    45 pairs when the folder is complete (MANIFEST §1): 10 eval3_Q, 26 2005/2006, 2 2003, 2 2001, 4 KITTI left
    images and the OpenCV samples folder (Aloe). Sorted within each data set; missing data sets are skipped. Only
    the data sets' own folders (:data:`SHARED_DATA_FOLDERS`) are looked in.
    """
    data_dir = check_scene_dir(data_dir, "data_dir")
    pairs: list[Path] = []
    for folder, marker in (("middlebury_eval3_Q", "calib.txt"), ("middlebury_2005_2006_third", "view1.png"),
                           ("middlebury_2003_quarter", "imL.png"), ("middlebury_2001", "*disp*.pgm")):
        scenes = warn_unreadable(sorted(d for d in (data_dir / folder).glob("*") if d.is_dir()))
        pairs += [scene for scene in scenes if any(scene.glob(marker))]
    for kitti in ("kitti/stereo2012_training", "kitti/stereo2015_training"):
        pairs += kitti_left_images(data_dir / kitti)
    if (data_dir / "opencv_samples" / "aloeL.jpg").is_file():
        pairs.append(data_dir / "opencv_samples")
    return pairs


def unreadable_reason(folder: Path) -> str | None:
    """Why ``folder`` cannot be listed (``Permission denied``), or None when it can."""
    try:
        os.scandir(folder).close()
    except OSError as error:
        return error.strerror or type(error).__name__
    return None


def warn_unreadable(folders: list[Path]) -> list[Path]:
    """``folders``, with one warning for each that cannot be listed: a scene folder others may not read was
    skipped without a word (``eval`` over a data set ran the rest and said "1 pairs, 0 failed", an audit)."""
    for folder in folders:
        reason = unreadable_reason(folder)
        if reason is not None:
            warnings.warn(f"{display_path(folder)}: a folder that cannot be read ({reason}): skipped", RuntimeWarning,
                          stacklevel=3)
    return folders


#: The shared data folder's sub-folders :func:`list_shared_pairs` reads (MANIFEST §1).
SHARED_DATA_FOLDERS = ("middlebury_eval3_Q", "middlebury_2005_2006_third", "middlebury_2003_quarter",
                       "middlebury_2001", "kitti", "opencv_samples")
