"""Canny edges (MATLAB-style automatic thresholds) and the Canny pre-processing variant of the paper."""

from __future__ import annotations

import pytest
import torch

from svs_torch import InputError
from svs_torch.segmentation.canny import canny_edges
from svs_torch.segmentation.segment import SegmentationConfig, segment_images


def square_image(batch: int = 1) -> torch.Tensor:
    image = torch.full((batch, 1, 40, 50), 0.2)
    image[..., 10:30, 15:35] = 0.8
    return image


def test_edges_trace_the_outline_of_a_square():
    edges = canny_edges(square_image())[0, 0]
    ring = torch.zeros_like(edges)
    ring[8:32, 13:37] = True
    ring[12:28, 17:33] = False
    assert edges.any() and not (edges & ~ring).any()  # nothing far from the outline
    for row in (15, 20, 25):  # both vertical sides found on every row
        assert edges[row, 13:17].any() and edges[row, 33:37].any()


def test_hysteresis_keeps_weak_edges_only_when_connected_to_strong_ones():
    image = square_image()
    image[..., 10:30, 40:45] = 0.25  # a faint second square: weak edges only, not touching the strong ones
    strong_only = canny_edges(image, high_threshold=torch.tensor([0.1]))[0, 0]
    assert not strong_only[:, 39:47].any()
    low_enough = canny_edges(image, high_threshold=torch.tensor([0.01]))[0, 0]
    assert low_enough[:, 39:47].any()


def test_uniform_images_have_no_edges_and_batches_are_independent():
    blobs = torch.nn.functional.avg_pool2d(torch.rand(1, 1, 40, 50, generator=torch.Generator().manual_seed(0)),
                                           5, 1, 2)  # no exact ties between neighbours, unlike the square
    image = torch.cat([blobs, torch.full((1, 1, 40, 50), 0.5)])
    edges = canny_edges(image)
    assert edges[0].any() and not edges[1].any()
    torch.testing.assert_close(canny_edges(image[:1]), edges[:1])


def test_canny_segmentation_keeps_the_closed_outline():
    seg = segment_images(square_image(2), SegmentationConfig(method="canny", kernel_size=3))
    x0, y0, x1, y1 = seg.regions.bbox_xyxy[0, seg.kept_labels[0, 0] - 1].tolist()
    assert abs(x0 - 14) <= 2 and abs(y0 - 9) <= 2 and abs(x1 - 36) <= 2 and abs(y1 - 31) <= 2
    assert seg.status.tolist() == [0, 0]


@pytest.mark.parametrize("sigma", [float("nan"), -1.0, 0.0, 1e6])
def test_a_sigma_that_blurs_nothing_or_everything_is_refused(sigma):
    """Was: ValueError (NaN), RuntimeError (negative), no edges from a NaN kernel in silence (0), a terabyte
    allocation (1e6)."""
    with pytest.raises(InputError, match=r"sigma: expected a finite number in \(0, 100\]"):
        canny_edges(square_image(), sigma=sigma)


def test_a_high_threshold_of_the_wrong_shape_or_value_is_refused():
    with pytest.raises(InputError, match=r"high_threshold: expected \(2\), got \(3\)"):
        canny_edges(square_image(2), high_threshold=torch.full((3,), 0.1))
    with pytest.raises(InputError, match="high_threshold: expected finite values, got nan"):
        canny_edges(square_image(), high_threshold=torch.tensor([float("nan")]))
