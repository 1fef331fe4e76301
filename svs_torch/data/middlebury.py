"""Loaders of the Middlebury stereo data sets (MiddEval3, 2005/2006, 2003, 2001; formats and scales: ``MANIFEST.md``
§1–2), each a B = 1 :class:`~svs_torch.core.types.StereoBatch` (see :mod:`svs_torch.data.datasets`).

Convention for all: a left pixel x sees the right pixel x − d (verified photometrically, MANIFEST §3). Nothing here
is differentiable: these are file readers. ``truth=False`` reads the views and the calibration alone, no ground
truth (``estimate`` ranges a scene whose truth file is damaged so, and says why).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..core.camera import SVS_CAMERA, calibration_value_expected
from ..core.checks import InputError
from ..core.files import display_path
from ..core.image_files import declared_size
from ..core.types import StereoBatch
from .formats import read_middlebury_calib, read_pfm, read_scaled_disparity
from .scene_batch import check_scene_dir, make_scene_batch, read_mask_image, read_view_pair, warnings_once_loaded

__all__ = ["MIDDLEBURY_2005_BASELINE_M", "MIDDLEBURY_2005_DMIN_FULL_PX", "MIDDLEBURY_2005_FOCAL_FULL_PX",
           "eval3_calibration_source", "load_middlebury_2001", "load_middlebury_2003", "load_middlebury_2005_2006",
           "load_middlebury_eval3", "teddy_2003_calibration_source"]

# Middlebury 2005/2006 (Scharstein & Pal 2007): nominal full-size focal length 3740 px and baseline 160 mm
# (MANIFEST §1–2); half- and third-size images divide focal and dmin by 2 and 3.
MIDDLEBURY_2005_FOCAL_FULL_PX = 3740.0
MIDDLEBURY_2005_BASELINE_M = 0.160
# The full-size views' widths (Baby1 1240 px to Midd1 1396; the third-size copies are 413–465, MANIFEST §1).
_MIDDLEBURY_2005_FULL_WIDTHS_PX = (1240, 1396)
# Full-size dmin (= doffs) of the 2005/2006 scenes where it is known: Art's 200 px is implied by MiddEval3
# ArtL's calib.txt (quarter size: doffs 50, f 935 = 3740 / 4). The other dmin.txt files are not shipped (§4).
MIDDLEBURY_2005_DMIN_FULL_PX = {"Art": 200.0}
#: The left view's ground truth of a calib.txt scene: MiddEval3's GT archive, else a Middlebury 2014 data set's own.
#: (No export of ours is named ``disp0.pfm``: ``--method-name`` takes at least one character.)
_EVAL3_TRUTH_FILES = ("disp0GT.pfm", "disp0.pfm")
# MiddEval3 trainingQ/Teddy/calib.txt: f 1500 px, baseline 80 mm, doffs 52 px at 450×375, the same scene, view and
# scale as the 2003 quarter-size Teddy (not the same files: 2 % of the pixels differ by over 5 levels; the GT agrees
# with disp0GT.pfm to a median difference of 0 px, 0.5 % over 1 px).
_TEDDY_2003_QUARTER = {"focal_px": 1500.0, "baseline_m": 0.080, "doffs_px": 52.0}
#: The width those values are for (that calib.txt's ``width``).
_TEDDY_2003_QUARTER_WIDTH_PX = 450


@warnings_once_loaded()
def load_middlebury_eval3(scene_dir: str | Path, dtype: torch.dtype = torch.float32, truth: bool = True
                          ) -> StereoBatch:
    """MiddEval3 scene folder (``im0.png``, ``im1.png``, ``calib.txt``, ``disp0GT.pfm`` where the scene has a
    ground truth), e.g. trainingQ/Teddy.

    focal = ``cam0[0, 0]`` px, baseline mm → m, doffs px; calibrated. A ``calib.txt`` written for another image
    width (the views resized, MANIFEST §1, the file kept) has its focal and doffs scaled by the views' width over
    its ``width``, as the disparities are. GT valid where the PFM is finite; ``disparity_nonoccluded`` where
    ``mask0nocc.png`` (if the folder has it) is 255 (128 = occluded, 0 = no GT). A Middlebury 2014 scene (the
    same ``calib.txt`` and views) names its ground truth ``disp0.pfm``, the same format: read when there is no
    ``disp0GT.pfm`` (it loaded without truth, and ``eval`` said none of its pairs had any: an audit). A scene with
    neither (a test scene, or the data unpacked without the GT archive) loads without ground truth.
    """
    scene_dir = check_scene_dir(scene_dir, "scene_dir")
    calib = read_middlebury_calib(scene_dir / "calib.txt", "calib")
    left, right = read_view_pair(scene_dir / "im0.png", scene_dir / "im1.png", dtype)
    scale = _calib_width_scale(calib, left.shape[-1])
    read_truth, truth = truth, {}  # (the views' truth, as read: none where not asked for)
    truth_file = next((scene_dir / name for name in _EVAL3_TRUTH_FILES if (scene_dir / name).exists()), None)
    if truth_file is not None and read_truth:
        gt = read_pfm(truth_file, "disparity")
        if gt.ndim != 2:
            raise InputError(f"disparity: expected a 1-channel PFM ('Pf'), got {gt.shape[2]} channels ('PF'): "
                             f"{display_path(truth_file)}")
        valid = np.isfinite(gt)
        truth = {"disparity": np.where(valid, gt, 0.0), "valid": valid}
        if (scene_dir / "mask0nocc.png").is_file():
            truth["nonoccluded"] = _nonoccluded(scene_dir / "mask0nocc.png")
    focal_px, doffs_px = float(calib["cam0"][0, 0]) * scale, float(calib["doffs"]) * scale
    for key, value in (("focal_px", focal_px), ("doffs_px", doffs_px)):  # each in range, but scaled out of it
        if (expected := calibration_value_expected(key, value)) is not None:
            raise InputError(f"calib: {key} {value:g} once scaled from its width {calib['width']:g} px to the views' "
                             f"{left.shape[-1]}: expected {expected}: {display_path(scene_dir / 'calib.txt')}")
    return make_scene_batch(left, right, f"eval3/{scene_dir.name}", focal_px=focal_px,
                            baseline_m=float(calib["baseline"]) / 1000.0, doffs_px=doffs_px, calibrated=True, **truth)


def _nonoccluded(path: Path) -> np.ndarray:
    """MiddEval3's ``mask0nocc.png`` as a bool mask of the non-occluded pixels (255; 128 occluded, 0 unknown). Another
    mask (0 and 1) read as no pixel non-occluded, and its metrics were left out in silence (an audit)."""
    mask = read_mask_image(path, "mask0nocc")
    levels = np.unique(mask)
    if not np.isin(levels, (0, 128, 255)).all():
        shown = ", ".join(str(int(level)) for level in levels[:6]) + (", ..." if len(levels) > 6 else "")
        raise InputError(f"mask0nocc: expected MiddEval3's levels 255 (non-occluded), 128 (occluded) and 0 (unknown), "
                         f"got {shown}: {display_path(path)}")
    return mask == 255


def _calib_width_scale(calib: dict, width_px: int) -> float:
    """The views' width over the width ``calib.txt`` was written for (1 where it does not say): its focal and doffs
    are in that width's pixels, and a resize scales them by the width alone, as
    :func:`~svs_torch.data.resize_stereo_batch` does (disparities run along x)."""
    return width_px / float(calib["width"]) if "width" in calib else 1.0


@warnings_once_loaded()
def load_middlebury_2005_2006(scene_dir: str | Path, dtype: torch.dtype = torch.float32, truth: bool = True
                              ) -> StereoBatch:
    """Middlebury 2005/2006 scene (``view1.png`` left, ``view5.png`` right, ``disp1.png``) at any of the data set's
    three sizes: full (1240–1396 px wide), half or third (the shared copies, 413–465 px).

    ``disp1.png`` holds full-size disparities at every size (MANIFEST §2: the third-size values are 3·d), so the
    size divides them by 1, 2 or 3, read from the views' width; a width of none of the three sizes is refused
    (its disparity scale is unknown). Nominal focal 3740 px and baseline 0.160 m at full size, the focal divided
    alike. ``doffs`` = dmin over the same divisor is known only for Art (dmin 200: 66.667 px at third size), so
    only Art is calibrated; the others get doffs 0 and calibrated False.
    """
    scene_dir = check_scene_dir(scene_dir, "scene_dir")
    left, right = read_view_pair(scene_dir / "view1.png", scene_dir / "view5.png", dtype)
    divisor = _middlebury_2005_divisor(left.shape[-1], scene_dir / "view1.png")
    disparity, valid = read_scaled_disparity(scene_dir / "disp1.png", divisor, "disparity") if truth else (None, None)
    dmin_full = MIDDLEBURY_2005_DMIN_FULL_PX.get(scene_dir.name)
    return make_scene_batch(left, right, f"2005_2006/{scene_dir.name}",
                            focal_px=MIDDLEBURY_2005_FOCAL_FULL_PX / divisor, baseline_m=MIDDLEBURY_2005_BASELINE_M,
                            doffs_px=0.0 if dmin_full is None else dmin_full / divisor,
                            calibrated=dmin_full is not None, disparity=disparity, valid=valid)


def _middlebury_2005_divisor(width_px: int, path: Path) -> float:
    """1, 2 or 3: the full, half or third size of a 2005/2006 view ``width_px`` wide (two pixels of rounding
    allowed)."""
    low, high = _MIDDLEBURY_2005_FULL_WIDTHS_PX
    for divisor in (1.0, 2.0, 3.0):
        if low / divisor - 2 <= width_px <= high / divisor + 2:
            return divisor
    raise InputError(f"left: expected a Middlebury 2005/2006 view of full ({low}–{high} px wide), half or third size "
                     f"(its disp1.png's scale follows the size), got {width_px} px: {display_path(path)}")


@warnings_once_loaded()
def load_middlebury_2003(scene_dir: str | Path, dtype: torch.dtype = torch.float32, truth: bool = True
                         ) -> StereoBatch:
    """Middlebury 2003 quarter-size scene (``imL.png``, ``imR.png``, ``disp2.png`` = 4·d), Teddy or Cones.

    No calibration is shipped. Teddy takes MiddEval3 trainingQ/Teddy's ``calib.txt`` values (f 1500 px,
    baseline 0.080 m, doffs 52 px; calibrated True): that file describes the same scene and view at the same
    450×375 scale (the GT maps agree, median difference 0 px; the image files differ a little), so the values
    hold here; note they are Middlebury's own round, nominal numbers, as trusted as eval3/Teddy's and no more. Views
    of another width scale focal and doffs by their width over 450, as :func:`load_middlebury_eval3` scales a
    ``calib.txt`` (``disp2.png`` is still read as 4·d).
    Other scenes (Cones) get the SVS nominal focal and baseline and calibrated False.
    """
    scene_dir = check_scene_dir(scene_dir, "scene_dir")
    left, right = read_view_pair(scene_dir / "imL.png", scene_dir / "imR.png", dtype)
    disparity, valid = read_scaled_disparity(scene_dir / "disp2.png", 4.0, "disparity") if truth else (None, None)
    if scene_dir.name == "Teddy":
        # In the pixels of its 450 px width: views of another width scale focal and doffs as eval3's calib.txt does
        # (a 225 px copy read f 1500 px, and its median true depth 1.78 m for 1.45 m: an audit).
        scale = left.shape[-1] / _TEDDY_2003_QUARTER_WIDTH_PX
        camera = dict(_TEDDY_2003_QUARTER, calibrated=True, focal_px=_TEDDY_2003_QUARTER["focal_px"] * scale,
                      doffs_px=_TEDDY_2003_QUARTER["doffs_px"] * scale)
    else:
        camera = {"focal_px": SVS_CAMERA.focal_px(left.shape[-1]), "baseline_m": SVS_CAMERA.baseline_m}
    return make_scene_batch(left, right, f"2003/{scene_dir.name}", disparity=disparity, valid=valid, **camera)


@warnings_once_loaded()
def load_middlebury_2001(scene_dir: str | Path, dtype: torch.dtype = torch.float32, truth: bool = True
                         ) -> StereoBatch:
    """Middlebury 2001 scene: Tsukuba (``imL/imR.png``, ``truedisp.pgm`` = 16·d) or Venus (``im2/im6.ppm``,
    ``disp2.pgm`` = 8·d); 0 = unknown. No calibration: SVS nominal focal and baseline, calibrated False."""
    scene_dir = check_scene_dir(scene_dir, "scene_dir")
    if (scene_dir / "truedisp.pgm").is_file():
        left, right = read_view_pair(scene_dir / "imL.png", scene_dir / "imR.png", dtype)
        truth_file, scale = scene_dir / "truedisp.pgm", 16.0
    else:
        left, right = read_view_pair(scene_dir / "im2.ppm", scene_dir / "im6.ppm", dtype)
        truth_file, scale = scene_dir / "disp2.pgm", 8.0
    disparity, valid = read_scaled_disparity(truth_file, scale, "disparity") if truth else (None, None)
    return make_scene_batch(left, right, f"2001/{scene_dir.name}", focal_px=SVS_CAMERA.focal_px(left.shape[-1]),
                            baseline_m=SVS_CAMERA.baseline_m, disparity=disparity, valid=valid)


def teddy_2003_calibration_source(scene_dir: Path) -> str:
    """Where :func:`load_middlebury_2003` takes Teddy's calibration from, and how it was scaled where the views are
    not 450 px wide; read from the PNG's header alone."""
    return _scaled_source("MiddEval3 trainingQ/Teddy/calib.txt, the same scene and view", scene_dir / "imL.png",
                          _TEDDY_2003_QUARTER_WIDTH_PX)


def eval3_calibration_source(scene_dir: Path) -> str:
    """``Teddy/calib.txt``, and how its focal and doffs were scaled where the views are of another width
    (:func:`load_middlebury_eval3`); read from the file and the PNG's header alone."""
    source = f"{scene_dir.name}/calib.txt"
    try:
        calib_width = read_middlebury_calib(scene_dir / "calib.txt", "calib").get("width")
    except (InputError, OSError):  # the loader says what is wrong with it
        return source
    return _scaled_source(source, scene_dir / "im0.png", calib_width)


def _scaled_source(source: str, view: Path, calib_width: float | None) -> str:
    """``source``, and that its focal and doffs were scaled where the left view ``view`` is not ``calib_width`` px
    wide (None: the calibration does not say); read from the PNG's header alone."""
    try:
        with view.open("rb") as handle:
            size = declared_size(handle.read(64))
    except (InputError, OSError):  # the loader says what is wrong with it
        return source
    if calib_width is None or size is None or size[0] == calib_width:
        return source
    return f"{source}, scaled from its {calib_width:g} px wide to the views' {size[0]}"
