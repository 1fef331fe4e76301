"""The segmentation stage (paper Sec. 3.2) against an OpenCV implementation of the same steps, on real pairs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from real_images import PAIRS, opencv_segmentation, read_gray

from svs_torch import InputError, SegmentationStatus, StereoBatch
from svs_torch.segmentation.segment import SegmentationConfig, segment_images, segment_stereo


def stereo_batch(data_dir, size_wh=(320, 240)) -> tuple[StereoBatch, list[np.ndarray], list[np.ndarray]]:
    lefts = [read_gray(data_dir, left, size_wh) for left, _ in PAIRS]
    rights = [read_gray(data_dir, right, size_wh) for _, right in PAIRS]

    def stack(images):
        return torch.from_numpy(np.stack(images)).float().div(255).unsqueeze(1)

    return StereoBatch.from_images(stack(lefts), stack(rights), 276.0, 0.1075), lefts, rights


def check_against_opencv(seg, index: int, gray: np.ndarray, config: SegmentationConfig) -> None:
    kernel = np.ones((config.kernel_size, config.kernel_size), np.uint8)
    level, binary, opened, count, labels, stats, centroids = opencv_segmentation(gray, kernel, config.connectivity)
    assert int(seg.threshold_level[index]) == int(level)
    assert np.array_equal(seg.binary[index, 0].numpy(), binary)
    assert np.array_equal(seg.opened[index, 0].numpy(), opened)
    assert int(seg.num_regions[index]) == count
    # The kept regions are OpenCV's N largest (stable on ties: lowest OpenCV label first is not guaranteed,
    # so compare the areas, boxes and centroids as multisets).
    n = min(config.num_keep, count)
    order = np.argsort(-stats[:, 4], kind="stable")[:n]
    kept = [label for label in seg.kept_labels[index].tolist() if label > 0]
    ours = sorted((int(seg.regions.area_px[index, k - 1]), *seg.regions.bbox_xyxy[index, k - 1].tolist())
                  for k in kept)
    theirs = sorted((int(stats[j, 4]), int(stats[j, 0]), int(stats[j, 1]), int(stats[j, 0] + stats[j, 2]),
                     int(stats[j, 1] + stats[j, 3])) for j in order)
    assert ours == theirs
    kept_mask = np.isin(labels, order + 1)
    if len(set(stats[:, 4])) == count:  # no area ties: the kept pixels are exactly OpenCV's
        assert np.array_equal(seg.kept_mask[index, 0].numpy(), kept_mask)


@pytest.mark.parametrize("config", [
    SegmentationConfig(),
    SegmentationConfig(kernel_size=3, num_keep=3, connectivity=4),
    SegmentationConfig(kernel_size=8, num_keep=1),
], ids=["paper", "k3-keep3-c4", "k8-keep1"])
def test_equals_opencv_on_real_pairs(data_dir, config):
    batch, lefts, rights = stereo_batch(data_dir)
    seg = segment_stereo(batch, config)
    for i in range(batch.batch_size):
        check_against_opencv(seg.left, i, lefts[i], config)
        check_against_opencv(seg.right, i, rights[i], config)
    assert seg.status.tolist() == [SegmentationStatus.OK] * batch.batch_size


def test_native_resolution_equals_opencv(data_dir):
    for left, _ in PAIRS[:4]:
        gray = read_gray(data_dir, left)
        image = torch.from_numpy(gray).float().div(255).view(1, 1, *gray.shape)
        check_against_opencv(segment_images(image), 0, gray, SegmentationConfig())


def test_kept_regions_are_largest_first_and_mask_the_image(data_dir):
    batch, _, _ = stereo_batch(data_dir)
    seg = segment_stereo(batch).left
    for i in range(batch.batch_size):
        kept = seg.kept_labels[i]
        areas = seg.regions.area_px[i, kept[kept > 0] - 1]
        assert torch.all(areas[:-1] >= areas[1:])
        assert int(areas[0]) == int(seg.regions.area_px[i][seg.regions.valid[i]].max())
        union = torch.isin(seg.labels[i], kept[kept > 0])
        assert torch.equal(union, seg.kept_mask[i])
    assert torch.equal(seg.masked, batch.left * seg.kept_mask)


def test_batched_equals_per_pair(data_dir):
    batch, _, _ = stereo_batch(data_dir)
    whole = segment_stereo(batch)
    for i in (0, 3, batch.batch_size - 1):
        single = segment_stereo(batch.select([i]))
        for field in ("threshold_level", "opened", "labels", "kept_labels", "kept_mask", "status"):
            assert torch.equal(getattr(single.left, field)[0], getattr(whole.left, field)[i]), field
            assert torch.equal(getattr(single.right, field)[0], getattr(whole.right, field)[i]), field


def test_a_padded_pair_is_segmented_on_its_own_pixels(data_dir):
    """Pairs of two sizes padded into one batch: each pair's Otsu level, opening and kept regions are the pair's
    alone (the padding's black never enters a histogram or a region), as the pipeline's segmentation."""
    from svs_torch.data import collate_stereo_batches, resize_stereo_batch

    batch, _, _ = stereo_batch(data_dir)
    small = resize_stereo_batch(batch.select([1]), (200, 150))
    padded = collate_stereo_batches([batch.select([0]), small], mode="pad")
    whole = segment_stereo(padded)
    for index, pair in enumerate((batch.select([0]), small)):
        alone = segment_stereo(pair)
        h, w = pair.size_hw
        for view in ("left", "right"):
            got, want = getattr(whole, view), getattr(alone, view)
            assert torch.equal(got.threshold_level[index], want.threshold_level[0]), (index, view)
            for field in ("opened", "labels", "kept_mask"):
                assert torch.equal(getattr(got, field)[index, :, :h, :w], getattr(want, field)[0]), (index, view, field)
    assert torch.equal(whole.status, torch.cat([segment_stereo(batch.select([0])).status,
                                                segment_stereo(small).status]))


def test_blank_saturated_and_textureless_pairs_get_a_status_not_an_exception():
    left = torch.rand(4, 1, 40, 50, generator=torch.Generator().manual_seed(0))
    left = torch.nn.functional.avg_pool2d(left, 5, 1, 2)  # smooth blobs: a normal image
    right = left.clone()
    left[1] = 0.0  # all black
    left[2] = 1.0  # all white
    right[3] = 0.5  # textureless gray
    seg = segment_stereo(StereoBatch.from_images(left, right, 276.0, 0.1075))
    assert seg.left.status.tolist() == [SegmentationStatus.OK, SegmentationStatus.UNIFORM_IMAGE,
                                        SegmentationStatus.UNIFORM_IMAGE, SegmentationStatus.OK]
    assert seg.status.tolist()[1:] == [SegmentationStatus.UNIFORM_IMAGE] * 3
    assert not seg.left.kept_mask[1].any()  # black: empty mask (OpenCV: nothing above level 0)
    # White: one full region (OpenCV: everything above level 0), but a one-level view holds no obstacle to keep.
    assert seg.left.opened[2].all() and seg.right.opened[3].all()
    assert not seg.left.kept_mask[2].any() and not seg.right.kept_mask[3].any()
    assert seg.left.kept_labels[2].tolist() == seg.right.kept_labels[3].tolist() == [-1, -1]
    assert int(seg.left.num_regions[1]) == 0 and seg.left.kept_labels[1].tolist() == [-1, -1]


def test_specks_only_give_no_foreground():
    image = torch.zeros(2, 1, 30, 30)
    image[0, 0, 10:12, 10:12] = 1.0  # a 2x2 speck: removed by the 5x5 opening
    image[1, 0, 5:20, 5:20] = 1.0  # a 15x15 obstacle survives
    seg = segment_images(image)
    assert seg.status.tolist() == [SegmentationStatus.NO_FOREGROUND, SegmentationStatus.OK]
    assert not seg.kept_mask[0].any() and seg.kept_labels[0].tolist() == [-1, -1]


def test_dark_foreground_keeps_the_dark_side():
    image = torch.full((1, 1, 30, 30), 0.8)
    image[0, 0, 5:15, 5:20] = 0.1
    seg = segment_images(image, SegmentationConfig(foreground="dark"))
    assert seg.regions.bbox_xyxy[0, seg.kept_labels[0, 0] - 1].tolist() == [5, 5, 20, 15]


def test_config_sweep_with_replace_and_errors():
    config = dataclasses.replace(SegmentationConfig(), kernel_size=7)
    assert config.kernel_size == 7 and config.num_keep == 2
    with pytest.raises(InputError, match="kernel_size: expected a positive integer up to 255, got 0"):
        SegmentationConfig(kernel_size=0)
    with pytest.raises(InputError, match="num_keep: expected a positive integer"):
        SegmentationConfig(num_keep=0)
    # A mistyped size would ask for gigabytes; labels beyond 255 would not fit a uint8 label image.
    with pytest.raises(InputError, match="kernel_size: expected a positive integer up to 255, got 99999"):
        SegmentationConfig(kernel_size=99999)
    with pytest.raises(InputError, match="num_keep: expected a positive integer up to 255, got 256"):
        SegmentationConfig(num_keep=256)
    with pytest.raises(InputError, match="connectivity: expected 4 or 8"):
        SegmentationConfig(connectivity=6)
    with pytest.raises(InputError, match="kernel_shape|shape: expected"):
        SegmentationConfig(kernel_shape="hexagon")
    with pytest.raises(InputError, match=r"image: expected \(B, 1, H, W\), got \(1, 40, 50\)"):
        segment_images(torch.rand(1, 40, 50))


@pytest.mark.parametrize("segmenter", ["nearness", "learned"])
def test_segment_stereo_runs_the_segmenter_its_config_names(data_dir, segmenter):
    """Was: segment_stereo ran Otsu whatever ``config.segmenter`` said, in silence. Now it segments as the pipeline
    does; segment_images, which has one view, refuses a stereo segmenter by name."""
    from svs_torch.pipeline import segment_pair

    batch, _, _ = stereo_batch(data_dir)
    config = SegmentationConfig(segmenter=segmenter)
    ours = segment_stereo(batch, config)
    assert torch.equal(ours.left.kept_mask, segment_pair(batch, config).left.kept_mask)
    assert not torch.equal(ours.left.kept_mask, segment_stereo(batch, SegmentationConfig()).left.kept_mask)
    with pytest.raises(InputError, match=f"config: segment_images runs the Otsu segmenter .* {segmenter!r}"):
        segment_images(batch.left, config)


@pytest.mark.parametrize("segmenter", ["otsu", "nearness", "learned"])
def test_region_centroids_follow_the_image_dtype(data_dir, segmenter):
    # The centroids were in torch's default dtype whatever the image's: float32 for a float64 batch (and float64
    # for a float32 one under torch.set_default_dtype(torch.float64)), unlike every other float output.
    batch, _, _ = stereo_batch(data_dir, (160, 120))
    config = SegmentationConfig(segmenter=segmenter)
    batch64 = dataclasses.replace(batch, left=batch.left.double(), right=batch.right.double())
    found = []  # each batch segmented once (the learned segmenter in float64: a second each)
    for source, dtype in ((batch, torch.float32), (batch64, torch.float64)):
        found.append(segment_stereo(source, config))
        assert found[-1].left.regions.centroid_xy.dtype == found[-1].right.regions.centroid_xy.dtype == dtype
    reference, centroids = found[0].left.regions, found[1].left.regions.centroid_xy
    if segmenter == "otsu":
        torch.testing.assert_close(centroids, reference.centroid_xy.double())
    default = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    try:
        assert segment_images(batch.left).regions.centroid_xy.dtype == torch.float32
    finally:
        torch.set_default_dtype(default)
