"""Connected components and region properties vs OpenCV (regions, stats) and scikit-image (exact labels)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from real_images import PAIRS, opencv_segmentation, read_gray
from skimage.measure import label as skimage_label

from svs_torch import InputError
from svs_torch.segmentation.components import (connected_components_with_stats, label_connected_components,
                                               region_properties)


def assert_matches_opencv(mask: np.ndarray, labels, num, props, index: int, connectivity: int) -> None:
    """Same regions (up to numbering), areas, boxes and centroids as cv2.connectedComponentsWithStats."""
    count, cv_labels, stats, centroids = cv2.connectedComponentsWithStats(
        mask.astype(np.uint8), connectivity=connectivity)
    ours = labels[index, 0].numpy()
    assert int(num[index]) == count - 1
    assert np.array_equal(ours > 0, cv_labels > 0)
    for k in range(1, count):
        pixels = ours[cv_labels == k]
        assert (pixels == pixels[0]).all()  # one OpenCV region is one of ours
        slot = pixels[0] - 1
        x, y, w, h, area = stats[k]
        assert int(props.area_px[index, slot]) == area
        assert props.bbox_xyxy[index, slot].tolist() == [x, y, x + w, y + h]
        np.testing.assert_allclose(props.centroid_xy[index, slot].numpy(), centroids[k], atol=1e-6)


@pytest.mark.parametrize("connectivity", [4, 8])
@settings(max_examples=120, deadline=None)
@given(height=st.integers(1, 28), width=st.integers(1, 28), density=st.floats(0.05, 0.95),
       batch=st.integers(1, 3), seed=st.integers(0, 2**31 - 1))
def test_random_masks_equal_skimage_and_opencv(connectivity, height, width, density, batch, seed):
    mask = np.random.default_rng(seed).random((batch, height, width)) < density
    labels, num, props = connected_components_with_stats(torch.from_numpy(mask).unsqueeze(1), connectivity)
    for i in range(batch):
        # scikit-image numbers regions in raster order of their first pixel, as we do: exact equality.
        expected = skimage_label(mask[i], connectivity=1 if connectivity == 4 else 2)
        assert np.array_equal(labels[i, 0].numpy(), expected)
        assert_matches_opencv(mask[i], labels, num, props, i, connectivity)


@pytest.mark.parametrize("connectivity", [4, 8])
def test_real_segmentation_masks_equal_opencv(data_dir, connectivity):
    kernel = np.ones((5, 5), np.uint8)
    masks = []
    for left, right in PAIRS:
        for path in (left, right):
            _, _, opened, *_ = opencv_segmentation(read_gray(data_dir, path, (320, 240)), kernel, connectivity)
            masks.append(opened)
    batch = torch.from_numpy(np.stack(masks)).unsqueeze(1)
    labels, num, props = connected_components_with_stats(batch, connectivity)
    for i, mask in enumerate(masks):
        assert_matches_opencv(mask, labels, num, props, i, connectivity)
    # Batched equals one image at a time.
    for i in (0, len(masks) - 1):
        single, single_num = label_connected_components(batch[i:i + 1], connectivity)
        assert torch.equal(single, labels[i:i + 1]) and int(single_num) == int(num[i])


def test_long_thin_serpentine_is_one_region():
    # One region whose diameter is the whole image: max-pool propagation needs ~W·H/2 steps here.
    mask = torch.zeros(1, 1, 121, 160, dtype=torch.bool)
    mask[0, 0, ::2, :] = True
    for row in range(1, 121, 2):
        mask[0, 0, row, -1 if (row // 2) % 2 == 0 else 0] = True
    labels, num = label_connected_components(mask)
    assert int(num) == 1 and int(labels.max()) == 1 and torch.equal(labels > 0, mask)


def test_regions_never_cross_images():
    mask = torch.zeros(2, 1, 3, 3, dtype=torch.bool)
    mask[0, 0, 2, :] = True  # last row of the first image
    mask[1, 0, 0, :] = True  # first row of the second
    labels, num = label_connected_components(mask)
    assert num.tolist() == [1, 1]


def test_empty_and_full_masks():
    mask = torch.zeros(3, 1, 4, 5, dtype=torch.bool)
    mask[1] = True
    labels, num, props = connected_components_with_stats(mask)
    assert num.tolist() == [0, 1, 0]
    assert props.area_px.shape == (3, 1) and props.valid.tolist() == [[False], [True], [False]]
    assert props.bbox_xyxy[1, 0].tolist() == [0, 0, 5, 4]
    labels, num, props = connected_components_with_stats(torch.zeros(2, 1, 4, 4, dtype=torch.bool))
    assert props.area_px.shape == (2, 0) and labels.dtype == torch.int64


def test_region_properties_of_any_label_image():
    labels = torch.tensor([[[[1, 1, 0, 2], [0, 3, 3, 2], [1, 0, 0, 0]]]])
    props = region_properties(labels)
    assert props.area_px.tolist() == [[3, 2, 2]]
    assert props.bbox_xyxy[0, 0].tolist() == [0, 0, 2, 3]  # label 1 has two pieces
    np.testing.assert_allclose(props.centroid_xy[0, 1].numpy(), [3.0, 0.5])
    # A label beyond num_labels is left out, never counted in another image's slots.
    assert region_properties(labels, torch.tensor([2])).area_px.tolist() == [[3, 2]]


def test_errors_name_the_argument():
    with pytest.raises(InputError, match="connectivity: expected 4 or 8, got 6"):
        label_connected_components(torch.zeros(1, 1, 3, 3, dtype=torch.bool), 6)
    with pytest.raises(InputError, match="mask: expected a bool tensor, got torch.float32"):
        label_connected_components(torch.zeros(1, 1, 3, 3))
    with pytest.raises(InputError, match=r"labels: expected \(B, 1, H, W\)"):
        region_properties(torch.zeros(3, 3, dtype=torch.int64))
