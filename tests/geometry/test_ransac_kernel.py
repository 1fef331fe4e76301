"""The C kernel of RANSAC (``svs_torch/geometry/kernels/ransac_fundamental.c``) against the torch path it mirrors:
the same inlier sets and F on drawn scenes with outliers, under every setting the kernel takes; what it refuses.
``tests/geometry/test_ransac.py`` runs the estimator's own tests on both paths."""

from __future__ import annotations

import math

import pytest
import torch
from test_ransac import noisy_matches

from svs_torch import InputError
from svs_torch.geometry import kernels as geometry_kernels
from svs_torch.geometry.kernels import RANSAC_SETTINGS
from svs_torch.geometry.ransac import estimate_fundamental_ransac

pytestmark = pytest.mark.skipif(not geometry_kernels.available("ransac_fundamental"), reason="no C compiler")


def _both(monkeypatch, *args, **kwargs):
    fused = estimate_fundamental_ransac(*args, **kwargs)
    with monkeypatch.context() as patch:
        patch.setenv("SVS_TORCH_KERNELS", "torch")
        eager = estimate_fundamental_ransac(*args, **kwargs)
    return fused, eager


@pytest.mark.parametrize("scoring", ["msac", "ransac"])
@pytest.mark.parametrize("local_optimization, preverification, polish",
                         [(True, True, True), (False, True, False), (True, False, True), (False, False, False)])
def test_the_kernel_finds_the_torch_paths_inliers_and_f(monkeypatch, generator, scoring, local_optimization,
                                                        preverification, polish):
    # Scenes from 9 to 300 matches, 0-60 % outliers, a tenth of the rows padding: the kernel's sums run in their own
    # order, so a tie between two hypotheses' float32 scores may go the other way (1 pair in 960 when this was
    # measured); everywhere else the same inliers, and F to round-off.
    same = total = 0
    for k, outlier_ratio in ((9, 0.0), (16, 0.2), (60, 0.5), (300, 0.6), (300, 0.3)):
        left, right, _, _, _ = noisy_matches(6, k, outlier_ratio, generator, noise_px=0.5)
        valid = torch.rand(6, k, generator=generator) < 0.9
        seeds = torch.randint(0, 1 << 62, (6,), generator=generator)
        fused, eager = _both(monkeypatch, left, right, valid, scoring=scoring, local_optimization=local_optimization,
                             preverification=preverification, polish=polish, pair_seeds=seeds)
        agree = (fused.inliers == eager.inliers).all(-1) & (fused.status == eager.status)
        same, total = same + int(agree.sum()), total + 6
        torch.testing.assert_close(fused.F[agree], eager.F[agree], rtol=0, atol=1e-9)
        assert torch.equal(fused.iterations[agree], eager.iterations[agree])
    assert same >= total - 1, f"{total - same} of {total} pairs differ"


def test_the_kernel_serves_pipeline_batches_and_lmeds_stays_in_torch(monkeypatch, generator):
    calls = []
    real = geometry_kernels.ransac_fundamental
    monkeypatch.setattr(geometry_kernels, "ransac_fundamental", lambda *a, **k: calls.append(1) or real(*a, **k))
    left, right, _, _, _ = noisy_matches(2, 40, 0.3, generator)
    valid = torch.ones(2, 40, dtype=torch.bool)
    estimate_fundamental_ransac(left.float(), right.float(), valid, pair_seeds=torch.tensor([1, 2]))
    assert calls == [1]
    estimate_fundamental_ransac(left, right, valid, scoring="lmeds", pair_seeds=torch.tensor([1, 2]))
    assert calls == [1]


def test_degenerate_and_short_pairs_get_the_torch_paths_status(monkeypatch, generator):
    left, right, _, _, _ = noisy_matches(4, 30, 0.2, generator)
    left[1] = left[1, :1]  # every point the same: every sample degenerate
    right[1] = right[1, :1]
    valid = torch.ones(4, 30, dtype=torch.bool)
    valid[2, 6:] = False  # six matches
    valid[3] = False
    fused, eager = _both(monkeypatch, left, right, valid, pair_seeds=torch.arange(4))
    assert torch.equal(fused.status, eager.status) and torch.equal(fused.iterations, eager.iterations)
    assert torch.equal(fused.inliers, eager.inliers) and torch.equal(fused.F[1:], torch.zeros(3, 3, 3,
                                                                                              dtype=fused.F.dtype))


def _settings(**changed) -> dict:
    values = {name: 1.0 for name in RANSAC_SETTINGS}
    values.update(changed)
    return values


@pytest.mark.parametrize("settings, message", [
    (_settings(chunk_size=0.0), r"^settings\['chunk_size'\]: expected a whole number >= 1"),
    (_settings(max_iterations=2.5), r"^settings\['max_iterations'\]: expected a whole number >= 1"),
    (_settings(confidence=math.nan), r"^settings\['confidence'\]: expected a finite number"),
    ({"threshold_px": 1.0}, r"^settings: expected exactly threshold_px, confidence"),
])
def test_the_wrapper_refuses_settings_its_kernel_cannot_take(settings, message):
    points = torch.zeros(1, 8, 2, dtype=torch.float64)
    with pytest.raises(InputError, match=message):
        geometry_kernels.ransac_fundamental(points, points, torch.ones(1, 8, dtype=torch.bool),
                                            torch.zeros(1, dtype=torch.int64), settings)


def test_the_wrapper_leaves_other_dtypes_to_torch():
    points = torch.zeros(1, 8, 2, dtype=torch.float32)
    assert geometry_kernels.ransac_fundamental(points, points, torch.ones(1, 8, dtype=torch.bool),
                                               torch.zeros(1, dtype=torch.int64), _settings()) is None


def test_a_chunk_past_every_iteration_is_asked_of_the_kernel_as_one_chunk(monkeypatch, generator):
    """chunk_size=10**9 made the kernel ask for 27 doubles a sample per thread up front (216 GB) and fall back to
    the torch path (an audit); the samples are drawn by index, so one chunk of max_iterations is the same search."""
    left, right, _, _, _ = noisy_matches(3, 80, 0.3, generator, noise_px=0.5)
    valid, seeds = torch.ones(3, 80, dtype=torch.bool), torch.randint(0, 1 << 62, (3,), generator=generator)
    asked, real = [], geometry_kernels.ransac_fundamental

    def spy(*args):
        asked.append(args[-1]["chunk_size"])
        return real(*args)

    monkeypatch.setattr(geometry_kernels, "ransac_fundamental", spy)
    huge = estimate_fundamental_ransac(left, right, valid, max_iterations=300, chunk_size=10**9, pair_seeds=seeds)
    whole = estimate_fundamental_ransac(left, right, valid, max_iterations=300, chunk_size=300, pair_seeds=seeds)
    assert asked == [300, 300]
    assert torch.equal(huge.inliers, whole.inliers) and torch.equal(huge.F, whole.F)
