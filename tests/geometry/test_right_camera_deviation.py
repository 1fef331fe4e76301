"""right_camera_deviation as a library caller meets it (PipelineResult's docstring and the README name the call):
a bad argument is an InputError naming it, not an IndexError from inside the maths."""

from __future__ import annotations

import pytest
import torch

from svs_torch import InputError
from svs_torch.geometry.row_alignment_keystone import right_camera_deviation


def test_one_pairs_homography_without_its_batch_dimension_is_named():
    """``result.H_right[0]`` (one pair's (3, 3)) raised "IndexError: too many indices for tensor of dimension 2"; an
    ``image_hw`` of another pair count was broadcast over the batch."""
    image_hw = torch.tensor([[240, 320]])
    with pytest.raises(InputError, match=r"H_right: expected \(B, 3, 3\), got \(3, 3\)"):
        right_camera_deviation(torch.eye(3), image_hw)
    with pytest.raises(InputError, match=r"image_hw: expected \(1, 2\), got \(2\)"):
        right_camera_deviation(torch.eye(3)[None], torch.tensor([240, 320]))
    with pytest.raises(InputError, match=r"image_hw: expected \(2, 2\), got \(1, 2\)"):
        right_camera_deviation(torch.eye(3).expand(2, 3, 3), image_hw)
    roll, shift, scale = right_camera_deviation(torch.eye(3)[None], image_hw)
    assert (roll.tolist(), shift.tolist(), scale.tolist()) == ([0.0], [0.0], [1.0])
