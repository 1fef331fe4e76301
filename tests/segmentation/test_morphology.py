"""Binary erosion and dilation: equal to cv2.erode / cv2.dilate (default border) for any element."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from real_images import PAIRS, read_gray

from svs_torch import InputError
from svs_torch.segmentation.morphology import dilate, erode, open_binary, structuring_element


def to_u8(mask: np.ndarray) -> np.ndarray:
    return mask.astype(np.uint8) * 255


@settings(max_examples=150, deadline=None)
@given(
    height=st.integers(1, 24), width=st.integers(1, 24), density=st.floats(0.05, 0.95),
    element_h=st.integers(1, 6), element_w=st.integers(1, 6), seed=st.integers(0, 2**31 - 1),
)
def test_equals_opencv_on_random_masks_and_elements(height, width, density, element_h, element_w, seed):
    rng = np.random.default_rng(seed)
    mask = rng.random((2, height, width)) < density
    element = rng.random((element_h, element_w)) < 0.7
    element[element_h // 2, element_w // 2] = True
    kernel = element.astype(np.uint8)
    tensor = torch.from_numpy(mask).unsqueeze(1)
    eroded, dilated = erode(tensor, torch.from_numpy(element)), dilate(tensor, torch.from_numpy(element))
    for i in range(2):  # values generated with OpenCV
        assert np.array_equal(eroded[i, 0].numpy(), cv2.erode(to_u8(mask[i]), kernel) > 0)
        assert np.array_equal(dilated[i, 0].numpy(), cv2.dilate(to_u8(mask[i]), kernel) > 0)


@pytest.mark.parametrize("shape", ["square", "cross", "ellipse"])
@pytest.mark.parametrize("size", [1, 2, 3, 4, 5, 9])
def test_named_elements_equal_opencv_on_a_real_binary_image(data_dir, shape, size):
    gray = read_gray(data_dir, PAIRS[0][0], (320, 240))
    _, binary = cv2.threshold(gray, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
    element = structuring_element(shape, size)
    kernel = element.numpy().astype(np.uint8)
    opened = open_binary(torch.from_numpy(binary > 0).view(1, 1, 240, 320), element)
    assert np.array_equal(opened[0, 0].numpy(), cv2.dilate(cv2.erode(binary, kernel), kernel) > 0)


def test_ellipse_matches_opencv_definition():
    for size in (3, 5, 7, 11):
        expected = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size)).astype(bool)
        assert np.array_equal(structuring_element("ellipse", size).numpy(), expected)


def test_border_neither_erodes_nor_dilates():
    full = torch.ones(1, 1, 6, 6, dtype=torch.bool)
    assert torch.equal(erode(full, structuring_element("square", 3)), full)
    empty = torch.zeros(1, 1, 6, 6, dtype=torch.bool)
    assert torch.equal(dilate(empty, structuring_element("square", 3)), empty)


def test_empty_batch_and_shapes():
    element = structuring_element("square", 3)
    assert erode(torch.zeros(0, 1, 5, 5, dtype=torch.bool), element).shape == (0, 1, 5, 5)
    assert dilate(torch.zeros(3, 1, 1, 1, dtype=torch.bool), element).shape == (3, 1, 1, 1)


def test_errors_name_the_argument():
    element = structuring_element("square", 3)
    with pytest.raises(InputError, match="mask: expected a bool tensor"):
        erode(torch.zeros(1, 1, 4, 4), element)
    with pytest.raises(InputError, match=r"mask: expected \(B, 1, H, W\), got \(4, 4\)"):
        dilate(torch.zeros(4, 4, dtype=torch.bool), element)
    with pytest.raises(InputError, match="shape: expected 'square', 'cross' or 'ellipse'"):
        structuring_element("disk", 3)
    with pytest.raises(InputError, match="size: expected an integer from 1"):
        structuring_element("square", 0)
