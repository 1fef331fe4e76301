"""Tests of svs_torch.data: file readers, the real-data loaders and resampling.

Values come from ``../shared/data/MANIFEST.md`` §3 (an independent check by the data's curator) and from OpenCV.
Every shared pair is loaded once per module (``shared_pairs``) to keep the file fast.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from svs_torch import SVS_CAMERA, InputError, StereoBatch
from svs_torch.data import (collate_stereo_batches, list_shared_pairs, load_image_pair, load_kitti,
                            load_middlebury_2001, load_middlebury_2003, load_middlebury_eval3, load_stereo_pair,
                            read_gray_image, read_middlebury_calib, read_pfm, resize_stereo_batch)

# MANIFEST.md §3 table: name → (width, height, valid fraction, min d, max d) in pixels. Our names replace the
# MANIFEST's folder prefixes: eval3_Q/ → eval3/, 2005_2006_third/ → 2005_2006/, 2003_quarter/ → 2003/,
# kitti/stereo2012_training/disp_occ/<frame>.png → kitti2012/<frame>, opencv_samples/aloe → opencv/aloe.
MANIFEST_TABLE = {
    "eval3/ArtL": (347, 277, 0.998, 19.25, 55.50),
    "eval3/Jadeplant": (659, 497, 0.986, 9.73, 143.71),
    "eval3/Motorcycle": (741, 497, 0.979, 9.18, 62.88),
    "eval3/MotorcycleE": (741, 497, 0.979, 9.18, 62.88),
    "eval3/Piano": (707, 481, 0.946, 10.13, 51.44),
    "eval3/PianoL": (707, 481, 0.946, 10.13, 51.44),
    "eval3/Pipes": (735, 485, 0.965, 8.05, 67.28),
    "eval3/Playroom": (699, 476, 0.946, 9.76, 73.58),
    "eval3/Shelves": (738, 497, 0.897, 14.01, 50.45),
    "eval3/Teddy": (450, 375, 0.977, 15.00, 52.75),
    "2005_2006/Aloe": (427, 370, 0.971, 14.33, 70.33),
    "2005_2006/Art": (463, 370, 0.999, 24.33, 74.67),
    "2005_2006/Baby1": (413, 370, 0.998, 8.33, 45.33),
    "2005_2006/Baby2": (413, 370, 0.979, 13.33, 51.67),
    "2005_2006/Baby3": (437, 370, 0.938, 15.67, 51.00),
    "2005_2006/Books": (463, 370, 0.997, 21.67, 73.67),
    "2005_2006/Bowling1": (417, 370, 0.979, 3.33, 76.67),
    "2005_2006/Bowling2": (443, 370, 0.950, 13.33, 66.00),
    "2005_2006/Cloth1": (417, 370, 1.000, 13.00, 57.33),
    "2005_2006/Cloth2": (433, 370, 0.994, 14.00, 76.00),
    "2005_2006/Cloth3": (417, 370, 0.993, 15.00, 55.33),
    "2005_2006/Cloth4": (433, 370, 0.994, 15.67, 67.00),
    "2005_2006/Dolls": (463, 370, 0.996, 3.00, 73.67),
    "2005_2006/Flowerpots": (437, 370, 0.856, 1.00, 60.33),
    "2005_2006/Lampshade1": (433, 370, 0.970, 14.00, 64.67),
    "2005_2006/Lampshade2": (433, 370, 0.979, 8.67, 65.33),
    "2005_2006/Laundry": (447, 370, 0.998, 11.67, 77.33),
    "2005_2006/Midd1": (465, 370, 0.931, 5.00, 69.00),
    "2005_2006/Midd2": (455, 370, 0.920, 3.67, 61.67),
    "2005_2006/Moebius": (463, 370, 0.995, 21.33, 72.67),
    "2005_2006/Monopoly": (443, 370, 0.993, 0.67, 53.33),
    "2005_2006/Reindeer": (447, 370, 0.995, 3.67, 67.00),
    "2005_2006/Rocks1": (425, 370, 0.956, 19.33, 56.67),
    "2005_2006/Rocks2": (425, 370, 0.956, 23.33, 56.00),
    "2005_2006/Wood1": (457, 370, 0.992, 21.67, 71.67),
    "2005_2006/Wood2": (435, 370, 0.982, 14.33, 72.33),
    "2003/Cones": (450, 375, 0.968, 5.50, 55.00),
    "2003/Teddy": (450, 375, 0.980, 12.50, 52.75),
    "2001/Tsukuba": (384, 288, 0.793, 5.00, 14.00),
    "2001/Venus": (434, 383, 1.000, 3.00, 19.75),
    "kitti2012/000000_10": (1226, 370, 0.358, 4.40, 69.82),
    "kitti2012/000001_10": (1226, 370, 0.242, 4.24, 124.07),
    "kitti2015/000000_10": (1242, 375, 0.191, 4.62, 64.09),
    "kitti2015/000001_10": (1242, 375, 0.230, 4.70, 78.48),
    "opencv/aloe": (1282, 1110, 0.965, 43.00, 211.00),
}

# MANIFEST.md §3, Z_mm column: depth range of the MiddEval3 GT, Z = baseline·f / (d + doffs), in millimetres.
EVAL3_DEPTH_MM = {
    "ArtL": (1418, 2160), "Jadeplant": (2010, 3288), "Motorcycle": (2017, 4597), "MotorcycleE": (2017, 4597),
    "Piano": (1534, 3063), "PianoL": (1534, 3063), "Pipes": (2708, 8566), "Playroom": (2402, 4330),
    "Shelves": (2430, 3869), "Teddy": (1146, 1791),
}

# Bound on photoerr(d) / photoerr(0). The right images of ArtL, MotorcycleE and PianoL have changed lighting
# or exposure (MANIFEST §3); Monopoly's right image is about 8 gray levels darker overall (MANIFEST photoerr
# 8 vs 15). For those the warp must still beat d = 0, but by less.
PHOTO_RATIO_DEFAULT = 0.5
PHOTO_RATIO = {"eval3/ArtL": 0.9, "eval3/MotorcycleE": 0.9, "eval3/PianoL": 0.9, "2005_2006/Monopoly": 0.6}
NAMES = sorted(MANIFEST_TABLE)


@pytest.fixture(scope="module")
def shared_pairs(data_dir: Path) -> dict[str, StereoBatch]:
    """Every shared pair, loaded once, keyed by its name."""
    batches = [load_stereo_pair(path) for path in list_shared_pairs(data_dir)]
    return {batch.names[0]: batch for batch in batches}


@pytest.fixture(scope="module")
def resized_pairs(shared_pairs: dict[str, StereoBatch]) -> dict[str, StereoBatch]:
    """Every shared pair at the SVS default size 320×240."""
    return {name: resize_stereo_batch(batch, (320, 240)) for name, batch in shared_pairs.items()}


def photometric_error(batch: StereoBatch, disparity_scale: float = 1.0) -> float:
    """Median |L(x) − R(x − s·d)| in gray levels over valid GT whose match lies inside the right image."""
    left, right = batch.left, batch.right
    _, _, h, w = left.shape
    ys, xs = torch.meshgrid(torch.arange(h, dtype=left.dtype), torch.arange(w, dtype=left.dtype), indexing="ij")
    x_right = xs - disparity_scale * batch.disparity_px[:, 0]  # (1, H, W)
    inside = batch.disparity_valid[:, 0] & (x_right >= 0) & (x_right <= w - 1)
    # align_corners=True: normalized −1 / +1 are the centres of the first / last pixels.
    grid = torch.stack([2 * x_right / (w - 1) - 1, (2 * ys / (h - 1) - 1).expand_as(x_right)], dim=-1)
    warped = F.grid_sample(right, grid, mode="bilinear", align_corners=True)
    return float((left - warped).abs()[:, 0][inside].median()) * 255


def test_list_shared_pairs_finds_the_45_manifest_pairs(shared_pairs: dict[str, StereoBatch]) -> None:
    assert sorted(shared_pairs) == NAMES


@pytest.mark.parametrize("name", NAMES)
def test_pair_matches_manifest(shared_pairs: dict[str, StereoBatch], name: str) -> None:
    width, height, valid_fraction, d_min, d_max = MANIFEST_TABLE[name]
    batch = shared_pairs[name]
    assert batch.left.shape == batch.right.shape == batch.disparity_px.shape == (1, 1, height, width)
    assert batch.left.dtype == batch.disparity_px.dtype == torch.float32
    assert batch.image_hw.tolist() == [[height, width]]
    assert batch.names == (name,)
    valid = batch.disparity_valid
    assert float(valid.float().mean()) == pytest.approx(valid_fraction, abs=0.01)
    known = batch.disparity_px[valid]
    assert float(known.min()) == pytest.approx(d_min, abs=0.5)
    assert float(known.max()) == pytest.approx(d_max, abs=0.5)
    assert bool((batch.disparity_px[~valid] == 0).all())


@pytest.mark.parametrize("name", NAMES)
def test_photometric_consistency(shared_pairs: dict, resized_pairs: dict, name: str) -> None:
    """The GT warp explains the right image far better than no shift, before and after resizing to 320×240
    (the latter proves that resizing scales the disparities)."""
    bound = PHOTO_RATIO.get(name, PHOTO_RATIO_DEFAULT)
    for batch in (shared_pairs[name], resized_pairs[name]):
        error = photometric_error(batch)
        assert error / photometric_error(batch, disparity_scale=0.0) <= bound
    # The decoded scale (/3, /4, /8, /16, /256, 1) beats 20 % smaller or larger disparities (MANIFEST §3).
    batch = shared_pairs[name]
    error = photometric_error(batch)
    margin = 1.0 if name in PHOTO_RATIO else 1.1
    assert error * margin < min(photometric_error(batch, 0.8), photometric_error(batch, 1.25))


@pytest.mark.parametrize("scene", sorted(EVAL3_DEPTH_MM))
def test_eval3_depth_matches_manifest(shared_pairs: dict, resized_pairs: dict, scene: str) -> None:
    z_min_mm, z_max_mm = EVAL3_DEPTH_MM[scene]
    full = shared_pairs[f"eval3/{scene}"]
    assert bool(full.calibrated.all())
    depth, valid = full.ground_truth_depth_m()
    assert torch.equal(valid, full.disparity_valid)
    assert float(depth[valid].min()) * 1000 == pytest.approx(z_min_mm, rel=2e-3)
    assert float(depth[valid].max()) * 1000 == pytest.approx(z_max_mm, rel=2e-3)
    # Resizing scales d, f and doffs together, so the depth of every kept GT sample is unchanged.
    small_depth, small_valid = resized_pairs[f"eval3/{scene}"].ground_truth_depth_m()
    assert z_min_mm * 0.998 <= float(small_depth[small_valid].min()) * 1000
    assert float(small_depth[small_valid].max()) * 1000 <= z_max_mm * 1.002


def test_calibration_per_dataset(shared_pairs: dict[str, StereoBatch]) -> None:
    art = shared_pairs["2005_2006/Art"]  # dmin 200 → doffs 66.67 px; MANIFEST §1: Art 1.41–2.19 m
    assert float(art.focal_px) == pytest.approx(3740 / 3) and float(art.doffs_px) == pytest.approx(200 / 3)
    depth, valid = art.ground_truth_depth_m()
    assert (float(depth[valid].min()), float(depth[valid].max())) == pytest.approx((1.41, 2.19), abs=0.01)
    teddy = shared_pairs["2003/Teddy"]  # MiddEval3 Teddy's calib, same images and scale
    assert bool(teddy.calibrated) and float(teddy.focal_px) == 1500 and float(teddy.doffs_px) == 52
    for name in ("2005_2006/Aloe", "2003/Cones", "2001/Tsukuba", "kitti2012/000000_10", "opencv/aloe"):
        assert not bool(shared_pairs[name].calibrated)
        assert not bool(shared_pairs[name].ground_truth_depth_m()[1].any())
    assert float(shared_pairs["kitti2015/000000_10"].focal_px) == pytest.approx(721.5377)
    assert float(shared_pairs["2001/Venus"].focal_px) == pytest.approx(SVS_CAMERA.focal_px(434))


def test_resize_scales_focal_doffs_and_disparity(shared_pairs: dict[str, StereoBatch]) -> None:
    batch = shared_pairs["eval3/Motorcycle"]  # 741×497 → 320×240: the aspect ratio changes
    small = resize_stereo_batch(batch, (320, 240))
    sx = 320 / 741
    assert small.left.shape == small.disparity_px.shape == (1, 1, 240, 320)
    assert small.image_hw.tolist() == [[240, 320]]
    assert float(small.focal_px) == pytest.approx(float(batch.focal_px) * sx)
    assert float(small.doffs_px) == pytest.approx(float(batch.doffs_px) * sx)
    assert torch.equal(small.baseline_m, batch.baseline_m) and small.names == batch.names
    assert 0.0 <= float(small.left.min()) and float(small.left.max()) <= 1.0
    # Nearest sampling: every resized GT value is an original GT value times sx, never a blend of two.
    original = torch.unique(batch.disparity_px[batch.disparity_valid] * sx)
    resized = small.disparity_px[small.disparity_valid]
    index = torch.searchsorted(original, resized).clamp(max=original.numel() - 1)
    nearest = torch.minimum((original[index] - resized).abs(), (original[(index - 1).clamp(min=0)] - resized).abs())
    assert float(nearest.max()) < 1e-4


def test_collate_pad_keeps_sizes_and_masks_padding(shared_pairs: dict, data_dir: Path) -> None:
    no_gt = load_image_pair(data_dir / "middlebury_2001/Tsukuba/imL.png", data_dir / "middlebury_2001/Tsukuba/imR.png")
    parts = [shared_pairs["2001/Tsukuba"], shared_pairs["2001/Venus"], no_gt, shared_pairs["2003/Teddy"]]
    batch = collate_stereo_batches(parts, mode="pad")
    assert batch.left.shape == batch.disparity_px.shape == (4, 1, 383, 450)
    assert batch.image_hw.tolist() == [[288, 384], [383, 434], [288, 384], [375, 450]]
    assert batch.names == ("2001/Tsukuba", "2001/Venus", "Tsukuba", "2003/Teddy")
    for i, part in enumerate(parts):
        h, w = part.size_hw
        assert torch.equal(batch.left[i, :, :h, :w], part.left[0])
        assert float(batch.left[i, :, h:].abs().sum() + batch.left[i, :, :, w:].abs().sum()) == 0
        assert not bool(batch.disparity_valid[i, :, h:].any() or batch.disparity_valid[i, :, :, w:].any())
    assert not bool(batch.disparity_valid[2].any())  # the pair without GT
    assert torch.equal(batch.disparity_px[0, :, :288, :384], parts[0].disparity_px[0])
    # In the widest dtype, whatever the order (an audit: the first's, so a float32 pair listed after a float64 one
    # ran in float64 and before it in float32).
    wide = parts[1].to(dtype=torch.float64)
    for order in ([parts[0], wide], [wide, parts[0]]):
        for mode in ("pad", "resize"):
            mixed = collate_stereo_batches(order, mode=mode)
            assert mixed.left.dtype == mixed.focal_px.dtype == mixed.disparity_px.dtype == torch.float64, mode


def test_collate_resize_and_resize_of_padded_batch(shared_pairs: dict[str, StereoBatch]) -> None:
    parts = [shared_pairs["2001/Tsukuba"], shared_pairs["2001/Venus"]]
    batch = collate_stereo_batches(parts)  # default size: the first pair's 384×288
    assert batch.left.shape == (2, 1, 288, 384) and batch.image_hw.tolist() == [[288, 384]] * 2
    assert float(batch.focal_px[1]) == pytest.approx(float(parts[1].focal_px) * 384 / 434)
    assert batch.names == ("2001/Tsukuba", "2001/Venus")
    small = collate_stereo_batches(parts, mode="resize", size_wh=(160, 120))
    assert small.left.shape == (2, 1, 120, 160)
    # Resizing a padded batch resizes each pair from its own region: batched equals per pair.
    padded = collate_stereo_batches(parts, mode="pad")
    from_padded = resize_stereo_batch(padded, (160, 120))
    for name in ("left", "right", "focal_px", "doffs_px", "disparity_px", "disparity_valid"):
        assert torch.equal(getattr(from_padded, name), getattr(small, name)), name
    with pytest.raises(InputError, match="mode: expected 'resize' or 'pad'"):
        collate_stereo_batches(parts, mode="crop")
    with pytest.raises(InputError, match="size_wh: expected at least the largest pair"):
        collate_stereo_batches(parts, mode="pad", size_wh=(400, 400))


def test_loaders_follow_dtype_and_detect_layouts(data_dir: Path) -> None:
    teddy = load_middlebury_eval3(data_dir / "middlebury_eval3_Q/Teddy", dtype=torch.float64)
    assert teddy.left.dtype == teddy.disparity_px.dtype == teddy.focal_px.dtype == torch.float64
    kitti = load_stereo_pair(data_dir / "kitti/stereo2015_training")  # a root folder: the default frame
    assert kitti.names == ("kitti2015/000000_10",)
    assert load_kitti(data_dir / "kitti/stereo2012_training", "000001_10").names == ("kitti2012/000001_10",)
    assert load_middlebury_2003(data_dir / "middlebury_2003_quarter/Cones").names == ("2003/Cones",)
    with pytest.raises(InputError, match="path: no known stereo layout"):
        load_stereo_pair(data_dir / "kitti")
    with pytest.raises(InputError, match="scene_dir: expected a folder"):
        load_middlebury_2001(data_dir / "no_such_scene")


def test_load_image_pair_calibration(data_dir: Path) -> None:
    left, right = data_dir / "middlebury_2001/Venus/im2.ppm", data_dir / "middlebury_2001/Venus/im6.ppm"
    nominal = load_image_pair(left, right)
    assert nominal.disparity_px is None and not bool(nominal.calibrated)
    assert float(nominal.focal_px) == pytest.approx(SVS_CAMERA.focal_px(434))
    assert float(nominal.baseline_m) == pytest.approx(SVS_CAMERA.baseline_m)
    given = load_image_pair(left, right, focal_px=500.0, baseline_m=0.1, doffs_px=3.0)
    assert bool(given.calibrated) and float(given.doffs_px) == 3.0


def test_a_focal_in_millimetres_is_warned_of_and_a_baseline_in_millimetres_refused(data_dir: Path) -> None:
    """An audit: --focal-px 3.6 (the SVS lens's 3.6 mm) ranged Teddy at 0.009 m, and --baseline-m 80 (80 mm) at
    3593 m, each with the status OK and no word."""
    import warnings

    left, right = data_dir / "middlebury_2001/Venus/im2.ppm", data_dir / "middlebury_2001/Venus/im6.ppm"
    with pytest.warns(UserWarning, match=r"^focal_px: 3.6 px across an image 434 px wide is a 178-degree view: "
                                         r"millimetres\? .* \(the SVS's 3.6 mm lens: 375 px at this width\)$"):
        load_image_pair(left, right, focal_px=3.6, baseline_m=0.08)
    with pytest.raises(InputError, match=r"baseline_m: expected a baseline in metres from 0.001 to 2 \(millimetres"):
        load_image_pair(left, right, focal_px=500.0, baseline_m=80.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a real rig's numbers, and the SVS model's, say nothing
        load_image_pair(left, right, focal_px=40.0, baseline_m=0.54)
        load_image_pair(left, right)


FOCAL_RANGE = "a focal length in pixels from 1 to 1,000,000"


@pytest.mark.parametrize("calibration, message", [
    ({"focal_px": "500", "baseline_m": 0.1}, f"focal_px: expected {FOCAL_RANGE}, got '500'"),
    ({"focal_px": True, "baseline_m": 0.1}, f"focal_px: expected {FOCAL_RANGE}, got True"),
    ({"doffs_px": "3"}, "doffs_px: expected pixels from -1,000,000 to 1,000,000, got '3'"),
    # The options' ranges (CALIBRATION_RANGES): a focal of 1e30 from a script ranged Teddy at 3e27 m, status OK.
    ({"focal_px": 1e30, "baseline_m": 0.1}, rf"focal_px: expected {FOCAL_RANGE}, got 1e\+30"),
    ({"baseline_m": 1e-30},
     r"baseline_m: expected a baseline in metres from 0.001 to 2 \(millimetres / 1000\), got 1e-30"),
])
def test_load_image_pair_takes_numbers_only(tmp_path: Path, data_dir: Path, calibration, message) -> None:
    """Was: TypeError 'must be real number, not str' from math.isfinite, and True taken as a focal of 1 px. The
    calibration is checked before a file is read (a missing file does not hide it); a numpy number is a number."""
    with pytest.raises(InputError, match=f"^{message}$"):
        load_image_pair(tmp_path / "missing_left.png", tmp_path / "missing_right.png", **calibration)
    left, right = data_dir / "middlebury_2001/Venus/im2.ppm", data_dir / "middlebury_2001/Venus/im6.ppm"
    assert float(load_image_pair(left, right, focal_px=np.float32(500.0), baseline_m=0.1).focal_px) == 500.0


def test_a_dash_for_standard_input_is_said_not_to_be_read(tmp_path: Path, monkeypatch) -> None:
    """An audit: 'estimate - right.png' (the Unix habit for standard input) said "file not found: -"."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputError, match="^right: '-' \\(standard input\\) is not read: expected an image file name$"):
        read_gray_image("-", "right")


def test_a_phones_heif_photo_is_named_with_what_to_do(tmp_path: Path) -> None:
    """An audit: an iPhone's HEIC photo (OpenCV decodes no HEIF) was "not a readable image file", as if damaged."""
    photo = tmp_path / "IMG_0001.HEIC"
    photo.write_bytes(b"\x00\x00\x00\x18ftypheic\x00\x00\x00\x00mif1heic" + bytes(64))
    with pytest.raises(InputError, match="^left: a HEIF/HEIC photo, which OpenCV does not decode: save it as JPEG or "
                                         "PNG: .*IMG_0001.HEIC$"):
        read_gray_image(photo, "left")


def test_bad_inputs_raise_one_clear_error(tmp_path: Path, data_dir: Path) -> None:
    with pytest.raises(InputError, match="left: file not found"):
        read_gray_image(tmp_path / "missing.png", "left")
    text = tmp_path / "notes.png"
    text.write_text("not an image\n")
    with pytest.raises(InputError, match="right: not a readable image file"):
        read_gray_image(text, "right")
    rgba = tmp_path / "rgba.png"  # colour + alpha is read like colour: the alpha channel is dropped
    bgra = np.random.default_rng(0).integers(0, 256, (4, 5, 4), dtype=np.uint8)
    cv2.imwrite(str(rgba), bgra)
    expected = cv2.cvtColor(bgra[..., :3], cv2.COLOR_BGR2GRAY)
    assert torch.equal((read_gray_image(rgba, "left")[0, 0] * 255).round().to(torch.uint8),
                       torch.from_numpy(expected))
    tiff = tmp_path / "float.tiff"
    cv2.imwrite(str(tiff), np.zeros((4, 5), np.float32))
    with pytest.raises(InputError, match=r"image: expected a uint8 or uint16 image, got float32 \(save it as an 8- "
                                         r"or 16-bit image"):
        read_gray_image(tiff, "image")
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((10, 12), np.uint8))
    # With the two files (an audit: the pair's name stood in, a folder's for a generic left name such as L.png).
    left = data_dir / "middlebury_2001/Tsukuba/imL.png"
    with pytest.raises(InputError, match=rf"right: expected the size of left 384x288 \(WxH, {left}\), got 12x10 "
                                         rf"\({small}\)"):
        load_image_pair(left, small)
    with pytest.raises(InputError, match="right: file not found"):
        load_image_pair(data_dir / "middlebury_2001/Tsukuba/imL.png", tmp_path / "missing.png")
    with pytest.raises(InputError, match="size_wh: expected a positive width and height"):
        resize_stereo_batch(load_image_pair(small, small), (0, 10))


def test_an_image_pair_is_not_ranged_again_after_it_is_read(tmp_path: Path, monkeypatch) -> None:
    """load_image_pair's views are k / 255 as read, in [0, 1]: making the batch does not scan them again (the
    pipeline ranges the batch it is given), and the batch holds the levels read."""
    levels = np.arange(240, dtype=np.uint8).reshape(12, 20)
    cv2.imwrite(str(tmp_path / "L.png"), levels)
    cv2.imwrite(str(tmp_path / "R.png"), levels[:, ::-1])
    scanned = []
    aminmax = torch.aminmax
    monkeypatch.setattr(torch, "aminmax", lambda tensor, *args, **kwargs: scanned.append(tuple(tensor.shape))
                        or aminmax(tensor, *args, **kwargs))
    batch = load_image_pair(tmp_path / "L.png", tmp_path / "R.png")
    assert (1, 1, 12, 20) not in scanned
    assert torch.equal(batch.left[0, 0], torch.from_numpy(levels / 255).float())
    assert torch.equal(batch.right[0, 0], torch.from_numpy(levels[:, ::-1] / 255).float())


def test_gray_images_round_trip_and_equal_opencv(tmp_path: Path, data_dir: Path) -> None:
    levels = np.arange(256, dtype=np.uint8).reshape(16, 16)
    cv2.imwrite(str(tmp_path / "levels.png"), levels)
    for dtype in (torch.float32, torch.float64):
        gray = read_gray_image(tmp_path / "levels.png", dtype=dtype)
        assert gray.shape == (1, 1, 16, 16) and gray.dtype == dtype
        # Each level's value is k / 255 in float64 rounded once to the dtype, whichever way it is divided.
        assert torch.equal(gray[0, 0], torch.from_numpy(levels.astype(np.float64) / 255).to(dtype))
        assert np.array_equal((gray[0, 0] * 255).round().to(torch.uint8).numpy(), levels)
    deep = (np.arange(64, dtype=np.uint16) * 1000).reshape(8, 8)
    cv2.imwrite(str(tmp_path / "deep.png"), deep)
    gray16 = read_gray_image(tmp_path / "deep.png")
    assert np.array_equal((gray16[0, 0].double() * 65535).round().numpy().astype(np.uint16), deep)
    # 10-bit levels in a 16-bit file read as nearly black: said, and read as they are.
    cv2.imwrite(str(tmp_path / "ten_bits.png"), (np.arange(64, dtype=np.uint16) * 16).reshape(8, 8))
    with pytest.warns(RuntimeWarning, match="left: a 16-bit image whose brightest level is 1008 of 65535"):
        assert float(read_gray_image(tmp_path / "ten_bits.png", "left").max()) == pytest.approx(1008 / 65535)
    # A color file: the gray levels are OpenCV's own BGR→gray conversion, exactly.
    path = data_dir / "middlebury_eval3_Q/Teddy/im0.png"
    expected = cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGR2GRAY)
    gray = read_gray_image(path)
    assert np.array_equal((gray[0, 0] * 255).round().to(torch.uint8).numpy(), expected)


def test_a_colour_jpeg_is_read_as_its_luma_as_guide_decodes_it(tmp_path: Path, data_dir: Path) -> None:
    """The SVS sends colour 4:2:2 JPEGs. A file of one (what ``capture`` and ``guide --record`` save) is read to
    the gray levels OpenCV's ``imread(..., IMREAD_GRAYSCALE)`` gives and ``guide`` decodes live, exactly: not
    decoded to colour and weighted back, which moves a street frame's pixels by up to 18 levels."""
    from svs_torch.capture.link_types import RawFrame
    from svs_torch.capture.protocol import FrameHeader
    from svs_torch.capture.stereo import decode_frame

    colour = cv2.imread(str(data_dir / "kitti/stereo2015_training/image_2/000000_10.png"))[:240, :320]
    ok, encoded = cv2.imencode(".jpg", colour, [cv2.IMWRITE_JPEG_QUALITY, 75, cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
                                                cv2.IMWRITE_JPEG_SAMPLING_FACTOR_422])
    path = tmp_path / "pair000000_left.jpg"
    path.write_bytes(encoded.tobytes())
    read = (read_gray_image(path)[0, 0] * 255).round().to(torch.uint8).numpy()
    assert np.array_equal(read, cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))
    weighted = cv2.cvtColor(cv2.imdecode(encoded, cv2.IMREAD_UNCHANGED), cv2.COLOR_BGR2GRAY)
    assert not np.array_equal(read, weighted)  # what it was read as before: the two differ on this frame
    raw = RawFrame(FrameHeader("5", 320, 240, encoded.size), encoded.tobytes(), 0.0, 0.0, 0.0, 1, 0)
    assert np.array_equal(decode_frame(raw, "left", "test").image, read)


def _with_exif_orientation(jpeg: bytes, tag: int) -> bytes:
    """``jpeg`` with an EXIF APP1 segment holding one Orientation (0x0112) entry, as a phone writes it."""
    entry = b"\x01\x12\x00\x03\x00\x00\x00\x01" + tag.to_bytes(2, "big") + b"\x00\x00"
    exif = b"Exif\x00\x00MM\x00\x2a\x00\x00\x00\x08\x00\x01" + entry + b"\x00\x00\x00\x00"
    return jpeg[:2] + b"\xff\xe1" + (len(exif) + 2).to_bytes(2, "big") + exif + jpeg[2:]


@pytest.mark.parametrize("tag, stored_as", [(6, cv2.ROTATE_90_COUNTERCLOCKWISE), (8, cv2.ROTATE_90_CLOCKWISE),
                                            (3, cv2.ROTATE_180)])
def test_a_jpeg_is_read_turned_by_its_exif_orientation(tmp_path: Path, data_dir: Path, tag, stored_as) -> None:
    """An audit: a phone's portrait JPEG (pixels on their side, an Orientation tag) was read as stored, so a pair's
    baseline ran along its columns and estimate ranged Teddy at 0.87 or 11.6 m instead of 1.25 m, status OK. It
    is read as cv2.imread and every viewer show it, and as the same view stored upright."""
    upright = cv2.imread(str(data_dir / "middlebury_eval3_Q/Teddy/im0.png"))
    plain = tmp_path / "plain.jpg"
    plain.write_bytes(cv2.imencode(".jpg", upright, [cv2.IMWRITE_JPEG_QUALITY, 100])[1].tobytes())
    turned = tmp_path / "phone.jpg"
    stored = cv2.imencode(".jpg", cv2.rotate(upright, stored_as), [cv2.IMWRITE_JPEG_QUALITY, 100])[1].tobytes()
    turned.write_bytes(_with_exif_orientation(stored, tag))
    read, expected = read_gray_image(turned), read_gray_image(plain)
    assert read.shape == expected.shape == (1, 1, *upright.shape[:2])
    assert float((read - expected).abs().mean()) < 1 / 255  # the same view, up to the two encodings' loss
    assert np.array_equal((read[0, 0] * 255).round().to(torch.uint8).numpy(),
                          cv2.imread(str(turned), cv2.IMREAD_GRAYSCALE))


def test_a_pair_of_sizes_an_exif_orientation_made_differ_names_the_turn(tmp_path: Path, data_dir: Path) -> None:
    """An audit: a left photo with an Orientation tag beside a right one without was refused as "expected the size
    of left 375x450", a size neither file's header nor an image tool's listing shows (both store 450x375)."""
    upright = cv2.imread(str(data_dir / "middlebury_eval3_Q/Teddy/im0.png"))
    encoded = cv2.imencode(".jpg", upright)[1].tobytes()
    tagged, plain = tmp_path / "left.jpg", tmp_path / "right.jpg"
    tagged.write_bytes(_with_exif_orientation(encoded, 6))
    plain.write_bytes(encoded)
    turned = ", turned upright by its EXIF orientation from the 450x375 it stores"
    with pytest.raises(InputError, match=f"expected the size of left 375x450 \\(WxH, .*left.jpg{turned}\\), got "
                                         f"450x375 \\(.*right.jpg\\)$"):
        load_image_pair(tagged, plain)
    with pytest.raises(InputError, match=f"left 450x375 \\(WxH, .*right.jpg\\), got 375x450 \\(.*left.jpg{turned}\\)$"):
        load_image_pair(plain, tagged)


@pytest.mark.parametrize("suffix", [".png", ".webp"])
@pytest.mark.parametrize("tag, stored_as", [(6, cv2.ROTATE_90_COUNTERCLOCKWISE), (8, cv2.ROTATE_90_CLOCKWISE),
                                            (3, cv2.ROTATE_180), (2, None), (5, None), (7, None)])
def test_a_png_or_webp_is_read_turned_by_its_exif_orientation(tmp_path: Path, data_dir: Path, suffix, tag,
                                                              stored_as) -> None:
    """An audit: a PNG or WebP with an EXIF Orientation tag (a phone's portrait photo converted, its pixels on their
    side) was read as stored, where a JPEG is turned: estimate ranged such a Teddy pair at 0.93 m instead of
    1.24 m, status OK. It is read as cv2.imread and viewers show it, the same view as stored upright."""
    from PIL import Image

    upright = cv2.imread(str(data_dir / "middlebury_eval3_Q/Teddy/im0.png"))[100:160, 50:130]
    stored = {2: upright[:, ::-1], 5: upright.swapaxes(0, 1), 7: upright[::-1, ::-1].swapaxes(0, 1)}.get(tag)
    stored = cv2.rotate(upright, stored_as) if stored is None else np.ascontiguousarray(stored)
    image = Image.fromarray(stored[:, :, ::-1])
    exif = image.getexif()
    exif[0x0112] = tag
    turned = tmp_path / f"phone{suffix}"
    image.save(turned, exif=exif, lossless=True)
    plain = tmp_path / "plain.png"
    cv2.imwrite(str(plain), upright)
    read, expected = read_gray_image(turned), read_gray_image(plain)
    assert read.shape == expected.shape == (1, 1, *upright.shape[:2])
    assert torch.equal(read, expected)


@pytest.mark.parametrize("little_endian", [True, False])
def test_read_pfm_flips_rows_and_keeps_inf(tmp_path: Path, little_endian: bool) -> None:
    image = np.array([[1.5, np.inf, 3.0], [4.0, 5.0, -6.25]], dtype=np.float32)  # (H, W) top row first
    order = "<" if little_endian else ">"
    header = f"Pf\n3 2\n{-1.0 if little_endian else 1.0}\n".encode()
    path = tmp_path / "disp.pfm"
    path.write_bytes(header + np.flipud(image).astype(order + "f4").tobytes())  # stored bottom row first
    decoded = read_pfm(path)
    assert decoded.dtype == np.float32 and np.array_equal(decoded, image)
    path.write_bytes(b"P6\n3 2\n255\n")
    with pytest.raises(InputError, match="disparity: not a PFM file"):
        read_pfm(path, "disparity")
    # Found by an audit: more data than the header's size was read as its first values, the scene scored OK.
    data = np.flipud(image).astype(order + "f4").tobytes()
    path.write_bytes(header + data + b"\n")  # a stray line end after the data is still the file
    assert np.array_equal(read_pfm(path), image)
    for extra in (data[:4], b"\n\n\n\n", np.zeros(12, "f4").tobytes()):  # another size; 3 channels under 'Pf'
        path.write_bytes(header + data + extra)
        with pytest.raises(InputError, match=r"^disparity: expected 24 bytes of data for 3 x 2 x 1 \(Pf\), got "
                                             r"\d+: its header's size does not match its data"):
            read_pfm(path, "disparity")


@pytest.mark.parametrize("scale", [0.0, -4.0, float("nan"), "3"])
def test_read_scaled_disparity_needs_a_positive_scale(data_dir: Path, scale) -> None:
    """Was: scale 0 gave inf disparities, a negative one negative disparities, NaN NaN ones, all as known."""
    from svs_torch.data import read_scaled_disparity

    with pytest.raises(InputError, match=r"^scale: expected a finite number in \(0, inf\)"):
        read_scaled_disparity(data_dir / "opencv_samples" / "aloeGT.png", scale)


def test_read_middlebury_calib_tolerates_odd_whitespace(tmp_path: Path, data_dir: Path) -> None:
    path = tmp_path / "calib.txt"
    path.write_text("  cam0=[ 10 0 4 ;0 10 3; 0 0 1 ] \n cam1 =[10 0 57.271; 0 10 3; 0 0 1]\n"
                    " doffs= 53.271 \nbaseline= 80\n")
    calib = read_middlebury_calib(path)
    assert calib["cam1"][0, 2] == 57.271 and calib["doffs"] == 53.271 and calib["baseline"] == 80
    motorcycle = read_middlebury_calib(data_dir / "middlebury_eval3_Q/Motorcycle/calib.txt")
    assert motorcycle["cam0"][0, 0] == 999.421 and motorcycle["doffs"] == 32.778 and motorcycle["width"] == 741
    path.write_text("cam0=[1 0 0; 0 1 0; 0 0 1]\n")
    with pytest.raises(InputError, match="calib file lacks 'cam1'"):
        read_middlebury_calib(path)


def test_preloaded_arrays_are_not_read_again(tmp_path):
    """An array another process decoded (``svs-depth estimate --pairs`` decodes in its parent while the workers
    start) is returned for its file instead of reading it; without it the file is read (and a missing one
    refused) as before."""
    from svs_torch.core.image_files import PRELOADED, preload_key, read_image_array

    path = tmp_path / "a.png"
    cv2.imwrite(str(path), np.arange(12, dtype=np.uint8).reshape(3, 4))
    array = read_image_array(path, "left")
    assert np.array_equal(array, cv2.imread(str(path), cv2.IMREAD_UNCHANGED))
    elsewhere = tmp_path / "decoded-elsewhere.png"  # no such file
    PRELOADED[preload_key(str(elsewhere))] = array
    try:
        assert read_image_array(elsewhere, "left") is array
        assert torch.equal(read_gray_image(elsewhere), read_gray_image(path))
    finally:
        PRELOADED.clear()
    with pytest.raises(InputError, match="left: file not found"):
        read_image_array(elsewhere, "left")


def test_a_preloaded_array_is_never_taken_for_another_file(tmp_path):
    """Two spellings that name two files: ``lnk/../L.png`` (``lnk`` a link into another folder: the file beside its
    target) and ``L.png``. Keyed by their lexical absolute path, both were one key, and ``estimate --pairs
    --workers 2 --batch-size 2`` ranged the first pair on the second's images (r_min 1.247 m, Teddy's, for a Pipes
    pair ranged at 1.536 m by one worker): an audit of results against the number of workers."""
    from svs_torch.core.image_files import PRELOADED, preload_key, read_image_array

    (tmp_path / "here").mkdir()
    (tmp_path / "there" / "deep").mkdir(parents=True)
    for folder, value in (("here", 1), ("there", 2)):
        cv2.imwrite(str(tmp_path / folder / "L.png"), np.full((3, 4), value, np.uint8))
    (tmp_path / "here" / "lnk").symlink_to(tmp_path / "there" / "deep")
    plain, through = str(tmp_path / "here" / "L.png"), str(tmp_path / "here" / "lnk" / ".." / "L.png")
    assert preload_key(plain) != preload_key(through)
    PRELOADED[preload_key(plain)] = read_image_array(plain, "left")
    try:
        assert read_image_array(through, "left")[0, 0] == 2  # the file the system opens, not the preloaded one
        assert read_image_array(plain, "left")[0, 0] == 1
    finally:
        PRELOADED.clear()


def test_a_loader_in_another_thread_leaves_the_callers_warning_filters_alone(tmp_path, recwarn):
    """Found by an audit of the API's effect on its caller: eval's loader thread held a pair's warnings with
    ``warnings.catch_warnings``, which swaps the process's filters; a caller whose own ``catch_warnings`` block
    (an ``ignore``) ended while a load ran had that ``ignore`` put back for good when the load ended. The warnings
    are now held per thread, and still given once the pair is read whole, in the loading thread."""
    import threading
    import warnings

    from svs_torch.data.scene_batch import warnings_once_loaded

    dim = tmp_path / "dim.png"
    cv2.imwrite(str(dim), np.full((4, 4), 1000, np.uint16))
    before = list(warnings.filters)
    inside, release, caught = threading.Event(), threading.Event(), []

    def load():
        with warnings_once_loaded():
            inside.set()
            release.wait(10)
            read_gray_image(dim, "left", torch.float32)
            caught.append("read")

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        loader = threading.Thread(target=load)
        loader.start()
        inside.wait(10)
    release.set()
    loader.join(10)
    assert caught == ["read"] and warnings.filters == before
    assert [str(w.message).split(",")[0] for w in recwarn] == [
        "left: a 16-bit image whose brightest level is 1000 of 65535"]  # given once the pair was read
    # the loader's warning is still given, from its thread, once the pair is read
    caught.clear(), inside.clear(), release.set()
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        loader = threading.Thread(target=load)
        loader.start()
        loader.join(10)
    assert caught == ["read"] and [str(w.message).split(",")[0] for w in shown] == [
        "left: a 16-bit image whose brightest level is 1000 of 65535"]


def test_a_doffs_of_none_is_refused_by_name(data_dir):
    """Found by an audit of the Python API: load_pair_source(source, doffs_px=None), as EvalSetup(doffs_px=None)
    passed it, was a TypeError from float(None) deep in load_image_pair, naming neither the argument nor the pair."""
    from svs_torch.data.pair_list import PairSource, load_pair_source

    folder = data_dir / "opencv_samples"
    source = PairSource(str(folder / "left01.jpg"), str(folder / "right01.jpg"))
    with pytest.raises(InputError, match=r"doffs_px: expected .*, got None"):
        load_pair_source(source, doffs_px=None)
    with pytest.raises(InputError, match=r"doffs_px: expected .*, got None"):
        load_image_pair(source.left, source.right, doffs_px=None)
