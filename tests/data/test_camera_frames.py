"""Camera frames as an SVS board sends them: noise, then the board's JPEG."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from svs_torch import InputError
from svs_torch.data import JPEG_QUALITY_FOR_DIGIT, camera_frame_pairs, camera_frames, random_obstacle_scenes


def _scene() -> torch.Tensor:
    return random_obstacle_scenes(2, 2, generator=torch.Generator().manual_seed(3)).batch.left


def test_a_frame_is_the_noisy_view_through_opencvs_jpeg():
    """Against OpenCV directly: the view plus σ-level noise from the generator, rounded to 8-bit levels, encoded
    at the digit's quality and decoded; the same seed gives the same frames, and the batch keeps its shape and
    dtype."""
    views = _scene()
    frames = camera_frames(views, 4, 4.0, torch.Generator().manual_seed(7))
    noise = torch.randn(views.shape, generator=torch.Generator().manual_seed(7), dtype=torch.float64) * 4.0
    levels = (views.double() * 255 + noise).round().clamp(0, 255).to(torch.uint8).numpy()
    for i in range(views.shape[0]):
        encoded = cv2.imencode(".jpg", levels[i, 0], [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY_FOR_DIGIT[4]])[1]
        expected = cv2.imdecode(encoded, cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255
        np.testing.assert_array_equal(frames[i, 0].numpy(), expected)
    assert frames.shape == views.shape and frames.dtype == views.dtype
    assert torch.equal(frames, camera_frames(views, 4, 4.0, torch.Generator().manual_seed(7)))


def test_a_higher_digit_loses_more_of_the_view():
    """Without noise, the JPEG alone: the board's digits 1, 4 and 8 depart from the view more and more."""
    views = _scene()
    errors = [float((camera_frames(views, digit, 0.0, torch.Generator()) - views).abs().mean()) for digit in (1, 4, 8)]
    assert errors[0] < errors[1] < errors[2]


@pytest.mark.parametrize("images, digit, sigma, pattern", [
    (torch.zeros(1, 3, 8, 8), 4, 4.0, r"^images: expected"),
    (torch.zeros(1, 1, 8, 8, dtype=torch.uint8), 4, 4.0, r"^images: expected a float tensor, got torch.uint8"),
    (torch.zeros(1, 1, 8, 8), 9, 4.0, r"^digit: expected the board's JPEG quality digit"),
    (torch.zeros(1, 1, 8, 8), "4", 4.0, r"^digit: expected"),
    (torch.zeros(1, 1, 8, 8), 4, -1.0, r"^sigma_levels: expected a noise level"),
])
def test_bad_arguments_are_refused_by_name(images, digit, sigma, pattern):
    with pytest.raises(InputError, match=pattern):
        camera_frames(images, digit, sigma, torch.Generator())


@pytest.mark.parametrize("generator", [None, 7])
def test_the_noise_needs_a_generator(generator):
    """Was: None drew from torch's global generator (another frame each run), 7 a TypeError from torch.randn."""
    with pytest.raises(InputError, match=r"^generator: expected a torch.Generator .*, got (NoneType|int)"):
        camera_frames(torch.zeros(1, 1, 8, 8), 4, 4.0, generator)
    with pytest.raises(InputError, match=r"^batch: expected a StereoBatch, got Tensor"):
        camera_frame_pairs(torch.zeros(1, 1, 8, 8), 4, 4.0, torch.Generator())


def test_pairs_draw_the_left_views_noise_then_the_rights():
    batch = random_obstacle_scenes(2, 2, generator=torch.Generator().manual_seed(2)).batch
    pair = camera_frame_pairs(batch, 4, 4.0, torch.Generator().manual_seed(5))
    generator = torch.Generator().manual_seed(5)
    assert torch.equal(pair.left, camera_frames(batch.left, 4, 4.0, generator))
    assert torch.equal(pair.right, camera_frames(batch.right, 4, 4.0, generator))
    assert torch.equal(pair.disparity_px, batch.disparity_px)
