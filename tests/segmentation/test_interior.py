"""Kept regions cut to their interior (svs_torch.segmentation.interior): OpenCV's erosion of each kept region, a
region too thin to keep half its pixels left whole, other regions and other pairs untouched."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from svs_torch import InputError
from svs_torch.segmentation.interior import region_interiors


def _scene() -> tuple[torch.Tensor, torch.Tensor]:
    """Two pairs of 40×60 labels: a 20×24 block (1), a 3-pixel-wide bar (2), a block on the image border (3) and a
    block not kept (4); slots keep 1, 2, 3."""
    labels = torch.zeros(2, 1, 40, 60, dtype=torch.int64)
    labels[:, 0, 5:25, 5:29] = 1
    labels[:, 0, 5:35, 35:38] = 2
    labels[:, 0, 28:40, 44:60] = 3
    labels[:, 0, 30:38, 5:20] = 4
    return labels, torch.tensor([[1, 2, 3], [1, 2, 3]])


def test_thick_regions_are_eroded_as_opencv_erodes_them_and_the_rest_is_kept():
    labels, kept = _scene()
    out = region_interiors(labels, kept, 2, torch.tensor([True, False]))
    element = np.ones((5, 5), np.uint8)
    for label in (1, 3):  # OpenCV's default border erodes nothing at the image's edges
        expected = cv2.erode((labels[0, 0] == label).numpy().astype(np.uint8), element) > 0
        assert np.array_equal((out[0, 0] == label).numpy(), expected)
    # the block on the border keeps its border rows and columns: only its inner sides move by 2
    assert int((out[0, 0] == 3).sum()) == (12 - 2) * (16 - 2)
    # a 3-pixel bar has no interior at radius 2 (nothing would be left): it stays whole
    assert torch.equal(out[0, 0] == 2, labels[0, 0] == 2)
    # a region not kept, and the pair not asked for, are as they were
    assert torch.equal(out[0, 0] == 4, labels[0, 0] == 4)
    assert torch.equal(out[1], labels[1])
    # removed pixels are background, never another label
    assert set(torch.unique(out).tolist()) == {0, 1, 2, 3, 4}


def test_a_region_keeping_under_half_its_pixels_stays_whole():
    labels = torch.zeros(1, 1, 30, 30, dtype=torch.int64)
    labels[0, 0, 5:12, 5:25] = 1  # 7 × 20: radius 2 keeps 3 × 16 = 48 of 140 pixels
    labels[0, 0, 15:28, 5:25] = 2  # 13 × 20: keeps 9 × 16 = 144 of 260
    out = region_interiors(labels, torch.tensor([[1, 2]]), 2, torch.tensor([True]))
    assert torch.equal(out == 1, labels == 1)
    assert int((out == 2).sum()) == 144
    assert int((region_interiors(labels, torch.tensor([[1, 2]]), 2, torch.tensor([True]), min_share=0.3) == 1).sum()
               ) == 48


def test_nothing_to_cut_returns_the_labels_themselves():
    labels, kept = _scene()
    pairs = torch.tensor([True, True])
    assert region_interiors(labels, kept, 0, pairs) is labels
    assert region_interiors(labels, kept, 2, torch.tensor([False, False])) is labels
    assert region_interiors(labels, kept[:, :0], 2, pairs) is labels
    assert torch.equal(region_interiors(labels, torch.full_like(kept, -1), 2, pairs), labels)


@pytest.mark.parametrize("radius", [-1, 1.5, True])
def test_a_bad_radius_is_refused_by_name(radius):
    labels, kept = _scene()
    with pytest.raises(InputError, match="radius_px"):
        region_interiors(labels, kept, radius, torch.tensor([True, True]))


def test_bad_labels_are_refused_by_name():
    labels, kept = _scene()
    with pytest.raises(InputError, match="labels"):
        region_interiors(labels.float(), kept, 2, torch.tensor([True, True]))
    with pytest.raises(InputError, match="pairs"):
        region_interiors(labels, kept, 2, torch.tensor([True]))


@pytest.mark.parametrize("kept_dtype, pairs_dtype, min_share, name", [
    (torch.complex64, torch.bool, 0.5, "kept_labels"),  # NotImplementedError from a comparison deep inside
    (torch.float32, torch.bool, 0.5, "kept_labels"),  # taken by the torch path, the kernel passed over
    (torch.int64, torch.float32, 0.5, "pairs"),  # NotImplementedError ("bitwise_and_cpu" for Float)
    (torch.int64, torch.int64, 0.5, "pairs"),  # taken as a mask of 0 / 1 in silence
    (torch.int64, torch.bool, "0.5", "min_share"),  # TypeError from the torch path's product
    (torch.int64, torch.bool, True, "min_share"),  # a flag in the wrong place, taken as 1
])
def test_kept_labels_pairs_and_share_of_another_kind_are_refused_by_name(kept_dtype, pairs_dtype, min_share, name):
    labels, kept = _scene()
    with pytest.raises(InputError, match=f"^{name}: expected"):
        region_interiors(labels, kept.to(kept_dtype), 2, torch.tensor([True, True], dtype=pairs_dtype), min_share)


@pytest.mark.parametrize("threads", [1, 3])
def test_the_kernel_gives_the_torch_paths_labels(generator, monkeypatch, threads):
    """The C kernel (each pair read once) against the torch path: random blocky labels with a thin band, slots
    empty, repeated, absent from the view or beyond its labels, some pairs not cut, radii past the view, shares on
    either side of the threshold and not numbers at all."""
    from svs_torch.segmentation import kernels

    if not kernels.available("region_interiors"):
        pytest.skip("no C compiler")
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for trial in range(6):
            coarse = torch.randint(0, 7, (3, 1, 6, 8), generator=generator)
            labels = torch.nn.functional.interpolate(coarse.float(), size=(30, 40), mode="nearest").long()
            labels[:, :, trial: trial + 3, :] = 9  # a band too thin to keep half of itself
            kept = torch.randint(-1, 11, (3, 4), generator=generator)
            kept[0, 1] = kept[0, 0]
            pairs = torch.rand(3, generator=generator) > 0.3
            for radius, share in ((1, 0.5), (2, 0.5), (2, 0.2), (60, 0.0), (1, float("nan")), (1, -float("inf"))):
                fused = region_interiors(labels, kept, radius, pairs, share)
                monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
                eager = region_interiors(labels, kept, radius, pairs, share)
                monkeypatch.delenv("SVS_TORCH_KERNELS")
                assert torch.equal(fused, eager), (trial, radius, share)
    finally:
        torch.set_num_threads(before)
