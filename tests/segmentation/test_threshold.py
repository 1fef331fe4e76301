"""Otsu threshold: equal to OpenCV's THRESH_OTSU on real and random uint8 images."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from real_images import PAIRS, read_gray

from svs_torch import InputError
from svs_torch.segmentation.threshold import gray_histogram, gray_levels, otsu_threshold, threshold_binary


def as_tensor(images: list[np.ndarray], dtype=torch.float32) -> torch.Tensor:
    return torch.from_numpy(np.stack(images)).to(dtype).div(255).unsqueeze(1)


@pytest.mark.parametrize("size_wh", [None, (320, 240)], ids=["native", "320x240"])
def test_equals_opencv_on_real_images(data_dir, size_wh):
    images = [read_gray(data_dir, path, size_wh) for pair in PAIRS for path in pair]
    for image in images:  # native sizes differ: one image per call
        threshold, level = otsu_threshold(as_tensor([image]))
        expected, binary = cv2.threshold(image, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
        assert int(level) == int(expected)  # value generated with OpenCV
        assert torch.equal(threshold_binary(as_tensor([image]), level)[0, 0], torch.from_numpy(binary > 0))
        assert float(threshold) == pytest.approx(expected / 255)


def test_batched_equals_per_image(data_dir):
    images = [read_gray(data_dir, path, (320, 240)) for pair in PAIRS for path in pair]
    _, batched = otsu_threshold(as_tensor(images))
    single = torch.cat([otsu_threshold(as_tensor([image]))[1] for image in images])
    assert torch.equal(batched, single)
    assert batched.dtype == torch.int64


def test_equals_opencv_on_few_level_images():
    # Few gray levels make exact ties and empty-bin plateaus: the first maximum must win, as in OpenCV.
    rng = np.random.default_rng(0)
    for _ in range(500):
        h, w = rng.integers(1, 30, 2)
        palette = rng.integers(0, 256, size=rng.integers(1, 6))
        image = palette[rng.integers(0, len(palette), size=(h, w))].astype(np.uint8)
        expected, _ = cv2.threshold(image, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
        assert int(otsu_threshold(as_tensor([image]))[1]) == int(expected)


@pytest.mark.parametrize("value", [0, 128, 255])
def test_uniform_image_gets_level_zero_like_opencv(value):
    image = np.full((12, 9), value, np.uint8)
    expected, binary = cv2.threshold(image, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
    threshold, level = otsu_threshold(as_tensor([image]))
    assert int(level) == int(expected) == 0
    assert torch.equal(threshold_binary(as_tensor([image]), level)[0, 0], torch.from_numpy(binary > 0))


def test_dtype_follows_input(dtype):
    threshold, level = otsu_threshold(torch.rand(2, 1, 8, 8, dtype=dtype))
    assert threshold.dtype == dtype and level.dtype == torch.int64 and threshold.shape == (2,)


def test_histogram_counts_every_pixel():
    levels = gray_levels(torch.rand(3, 1, 5, 7))
    histogram = gray_histogram(levels)
    assert histogram.shape == (3, 256) and torch.equal(histogram.sum(1), torch.full((3,), 35))


@pytest.mark.parametrize("levels, ignore, expected", [
    # An int64 level past 255 was counted in the next image's bins (its 300 in image 1's level 44), in silence.
    (torch.tensor([300, 0, 0, 0, 0, 0, 0, 0]).view(2, 1, 2, 2), None, "^levels: expected a uint8 tensor"),
    (torch.full((1, 1, 2, 2), 0.9), None, "^levels: expected a uint8 tensor"),  # truncated to level 0
    # An int ignore was inverted bit by bit (~0 = -1) and taken as indices: image 0 counted nothing, image 1 twice.
    (torch.zeros(2, 1, 2, 2, dtype=torch.uint8), torch.zeros(2, 1, 2, 2, dtype=torch.int64),
     "^ignore: expected a bool tensor"),
    (torch.zeros(2, 1, 2, 2, dtype=torch.uint8), torch.zeros(2, 1, 2, 2), "^ignore: expected a bool tensor"),
])
def test_histogram_refuses_levels_and_ignore_of_another_dtype(levels, ignore, expected):
    with pytest.raises(InputError, match=expected):
        gray_histogram(levels, ignore)


def test_histogram_leaves_out_the_ignored_pixels_whatever_their_level():
    """``ignore``: each image's histogram is that of its other pixels alone (numpy's, per image)."""
    generator = torch.Generator().manual_seed(5)
    levels = torch.randint(0, 256, (3, 1, 20, 30), generator=generator, dtype=torch.uint8)
    ignore = torch.rand(3, 1, 20, 30, generator=generator) < 0.4
    histogram = gray_histogram(levels, ignore)
    for i in range(3):
        expected = np.bincount(levels[i][~ignore[i]].numpy(), minlength=256)
        assert np.array_equal(histogram[i].numpy(), expected)
    assert torch.equal(gray_histogram(levels, torch.zeros_like(ignore)), gray_histogram(levels))


def test_errors_name_the_argument():
    with pytest.raises(InputError, match=r"image: expected \(B, 1, H, W\), got \(2, 3, 4, 4\)"):
        otsu_threshold(torch.rand(2, 3, 4, 4))
    with pytest.raises(InputError, match=r"image: expected values in \[0, 1\]"):
        otsu_threshold(torch.full((1, 1, 4, 4), 2.0))
    with pytest.raises(InputError, match="image: expected a float tensor"):
        otsu_threshold(torch.zeros(1, 1, 4, 4, dtype=torch.uint8))


@pytest.mark.parametrize("dtype", [torch.uint8, torch.int64, torch.bool, torch.float16])
def test_gray_levels_refuses_an_image_that_is_not_float32_or_float64(dtype):
    # A uint8 image (0..255) came back wrapped modulo 256 (200 -> 56) and an int64 one clamped to 255, in silence;
    # threshold_binary passed an int64 image on to it the same way.
    image = torch.full((1, 1, 4, 4), 200).to(dtype)
    with pytest.raises(InputError, match=f"image: expected a float.* tensor, got {dtype}"):
        gray_levels(image)
    if dtype != torch.uint8:  # threshold_binary takes uint8 as gray levels already
        with pytest.raises(InputError, match=f"image: expected a float.* tensor, got {dtype}"):
            threshold_binary(image, torch.tensor([100]))


def test_threshold_binary_refuses_a_level_outside_the_gray_levels():
    """Was silent: otsu_threshold's first value, the threshold in [0, 1], became level 0 (every pixel foreground),
    and 300 wrapped to 44 in uint8."""
    image = torch.rand(1, 1, 8, 8, generator=torch.Generator().manual_seed(0))
    threshold, level = otsu_threshold(image)
    assert 0 < threshold_binary(image, level).sum() < 64
    with pytest.raises(InputError, match="level: expected an int tensor, got torch.float32"):
        threshold_binary(image, threshold)
    for bad in (300, -1):
        with pytest.raises(InputError, match=rf"level: expected gray levels from 0 to 255, got \[{bad}\]"):
            threshold_binary(image, torch.tensor([bad]))
    with pytest.raises(InputError, match=r"level: expected \(1\), got \(2\)"):
        threshold_binary(image, torch.tensor([100, 100]))
