"""The right view's exposure matched to the left's (svs_torch.pipeline.exposure, issue 33): the affine map against
numpy's quantiles, the dead band, gradients, refusals, and a brighter right camera ranged as the pair was."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from svs_torch import InputError
from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth
from svs_torch.pipeline.exposure import ExposureConfig, match_exposure


def _views(generator: torch.Generator, b: int = 3, h: int = 24, w: int = 32) -> torch.Tensor:
    return 0.1 + 0.7 * torch.rand(b, 1, h, w, generator=generator, dtype=torch.float64)


def test_map_sends_the_right_quartiles_onto_the_left_ones(generator):
    """Against numpy: the map is the affine one through both views' quartiles (np.quantile's linear rule)."""
    left = _views(generator).float()
    right = (left * torch.tensor([1.3, 0.7, 1.0]).view(-1, 1, 1, 1) + torch.tensor([0.0, 0.06, 0.0]).view(-1, 1, 1, 1)
             ).clamp(0, 1)
    hw = torch.tensor([[24, 32]] * 3)
    mapped, changed = match_exposure(left, right, hw)
    assert changed.tolist() == [True, True, False]
    for i in range(2):
        ql, qr = (np.quantile(v[i].flatten().numpy().astype(np.float64), [0.25, 0.75]) for v in (left, right))
        scale = (ql[1] - ql[0]) / (qr[1] - qr[0])
        expected = np.clip(scale * right[i].numpy() + (ql[0] - scale * qr[0]), 0, 1)
        np.testing.assert_allclose(mapped[i].numpy(), expected, atol=2e-6)
        unsaturated = right[i] < 1
        np.testing.assert_allclose(mapped[i][unsaturated].numpy(), left[i][unsaturated].numpy(), atol=2e-3)
    assert torch.equal(mapped[2], right[2])  # the same exposure: untouched, bit for bit


def test_views_that_agree_or_a_flat_right_view_are_left_alone(generator):
    left = _views(generator).float()
    hw = torch.tensor([[24, 32]] * 3)
    right = left * 1.02  # within the dead band
    mapped, changed = match_exposure(left, right, hw)
    assert mapped is right and not bool(changed.any())
    flat = torch.full_like(left, 0.5)
    mapped, changed = match_exposure(left, flat, hw)
    assert mapped is flat and not bool(changed.any())
    mapped, changed = match_exposure(left, left * 1.02, hw, ExposureConfig(min_change=0.0))
    assert bool(changed.all())


def test_gradients_flow_to_both_views(generator):
    left = _views(generator, b=2, h=5, w=6).requires_grad_(True)
    right = (left.detach() * 0.6 + 0.05).requires_grad_(True)
    hw = torch.tensor([[5, 6]] * 2)
    assert torch.autograd.gradcheck(lambda a, b: match_exposure(a, b, hw)[0], (left, right))


def test_bad_input_is_refused_by_name():
    images = torch.rand(2, 1, 8, 8)
    with pytest.raises(InputError, match=r"^image_hw: expected every pair to fill"):
        match_exposure(images, images, torch.tensor([[8, 8], [6, 8]]))
    with pytest.raises(InputError, match=r"^right: expected"):
        match_exposure(images, torch.rand(2, 1, 8, 7), torch.tensor([[8, 8]] * 2))
    with pytest.raises(InputError, match=r"^quantiles"):
        ExposureConfig(quantiles=(0.75, 0.25))
    with pytest.raises(InputError, match=r"^min_change"):
        ExposureConfig(min_change=float("nan"))


@pytest.mark.parametrize("exposure, ranged", [(None, False), (ExposureConfig(), True)])
def test_a_brighter_right_camera_is_ranged_with_the_option(data_dir, exposure, ranged):
    """Middlebury Piano (a tuned scene) at 320×240 with its right view 30 % brighter (experiments/real_rig.py's
    "gain +30%"): unranged by the default, ranged to its clean accuracy with the exposure matched
    (experiments/exposure.md)."""
    import sys

    from conftest import REPO_ROOT
    from svs_torch.evaluation import evaluate_result

    sys.path.insert(0, str(REPO_ROOT / "experiments"))
    import real_rig

    batch = real_rig.resample(real_rig.load_scene(data_dir / "middlebury_eval3_Q" / "Piano"), "320x240")
    bright = real_rig.stack_conditions(batch, [("gain +30%", batch.left, real_rig.misalign_right(
        batch.right, real_rig.Misalignment(gain=0.3), float(batch.focal_px[0])))])
    result = estimate_obstacle_depth(bright, PipelineConfig(exposure=exposure))
    evaluation = evaluate_result(bright, result)[0]
    assert (evaluation.status == "OK") == ranged
    if ranged:
        assert evaluation.acc_objects_pct > 97
