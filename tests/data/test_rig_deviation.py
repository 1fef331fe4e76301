"""svs_torch.data.rig_deviation: a loosely mounted right camera's view, against OpenCV's own transforms."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from svs_torch.core.errors import InputError
from svs_torch.data.rig_deviation import LOOSE_RIG, RigDeviation, deviate_view, deviation_homography


def test_each_deviation_is_the_transform_opencv_makes_of_it():
    """A roll is OpenCV's rotation about the view's centre (by minus the angle: y points down), a scale its scaling
    about the centre, a shift a move of the rows; no deviation is the identity."""
    height, width, focal = 240, 320, 300.0
    centre = ((width - 1) / 2, (height - 1) / 2)
    roll = deviation_homography(RigDeviation(roll_deg=10), height, width, focal)
    np.testing.assert_allclose(roll[:2], cv2.getRotationMatrix2D(centre, -10, 1.0), atol=1e-9)
    scale = deviation_homography(RigDeviation(scale=0.02), height, width, focal)
    np.testing.assert_allclose(scale[:2], cv2.getRotationMatrix2D(centre, 0, 1.02), atol=1e-9)
    shift = deviation_homography(RigDeviation(shift_y_fraction=0.03), height, width, focal)
    np.testing.assert_allclose(shift, [[1, 0, 0], [0, 1, 7.2], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(deviation_homography(RigDeviation(), height, width, focal), np.eye(3), atol=1e-12)
    # A tilt keeps the centre where it was (re-centred) and makes a keystone: the rows' spacing changes top to bottom.
    tilt = deviation_homography(RigDeviation(tilt_x_deg=3), height, width, focal)
    corners = cv2.perspectiveTransform(np.array([[[0, 0], [width - 1, 0], [centre[0], centre[1]]]], np.float64), tilt)
    np.testing.assert_allclose(corners[0, 2], centre, atol=1e-9)
    assert abs(float(corners[0, 1, 0] - corners[0, 0, 0]) - (width - 1)) > 1


def test_a_view_keeps_its_type_and_an_ideal_camera_changes_nothing():
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 256, (120, 160), dtype=np.uint8)
    assert np.array_equal(deviate_view(frame, RigDeviation(), 150.0), frame)
    seen = deviate_view(frame, LOOSE_RIG, 150.0)
    assert seen.dtype == np.uint8 and seen.shape == frame.shape and not np.array_equal(seen, frame)
    gray = frame.astype(np.float32) / 255
    darker = deviate_view(gray, RigDeviation(gain=-0.2), 150.0)
    assert darker.dtype == np.float32 and np.allclose(darker, gray * 0.8, atol=1e-6)
    shifted = deviate_view(frame, RigDeviation(shift_y_fraction=0.05), 150.0)  # 6 rows down, black above
    assert np.array_equal(shifted[6:], frame[:-6]) and not shifted[:6].any()


@pytest.mark.parametrize("fields, name", [({"roll_deg": 90.0}, "roll_deg"), ({"tilt_y_deg": float("nan")}, "tilt_y_deg"),
                                          ({"shift_y_fraction": 1.5}, "shift_y_fraction"), ({"scale": -1.0}, "scale"),
                                          ({"gain": "0.2"}, "gain")])
def test_a_deviation_out_of_range_names_its_field(fields, name):
    with pytest.raises(InputError, match=name):
        RigDeviation(**fields)


def test_a_bad_view_or_focal_length_is_named():
    with pytest.raises(InputError, match="image"):
        deviate_view(np.zeros((4, 4, 3), np.uint8), LOOSE_RIG, 100.0)
    with pytest.raises(InputError, match="image"):
        deviate_view(np.zeros((4, 4), np.float64), LOOSE_RIG, 100.0)
    with pytest.raises(InputError, match="focal_px"):
        deviation_homography(LOOSE_RIG, 4, 4, 0.0)
