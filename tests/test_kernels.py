"""The fused C kernels (svs_torch.kernels) against the torch paths they replace: the same values bit for bit,
the fallback without a compiler, the on-disk cache. The dense-stage kernel's own tests are in test_dense.py."""

from __future__ import annotations

import torch
import pytest

from svs_torch import kernels
from svs_torch.data import load_middlebury_eval3, resize_stereo_batch
from svs_torch.features import SurfConfig, extract_surf_features
from svs_torch.hessian import hessian_octaves

needs_kernel = pytest.mark.skipif(not kernels.available("hessian_level"), reason="no C compiler")


@pytest.fixture(scope="module")
def images(data_dir):
    pair = resize_stereo_batch(load_middlebury_eval3(data_dir / "middlebury_eval3_Q" / "Teddy"), (320, 267))
    return torch.cat([pair.left, pair.right, torch.flip(pair.left, (-1,))])


@needs_kernel
def test_hessian_kernel_is_bit_identical_to_torch(images, monkeypatch):
    """Every octave's det(H) and trace from the C kernel equal the torch path's (same float32 operations in
    the same order, no FMA contraction), on real images with an odd size."""
    images = images[..., :263, :317]
    fused = hessian_octaves(images, num_octaves=4)
    monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
    eager = hessian_octaves(images, num_octaves=4)
    for a, b in zip(fused, eager):
        assert torch.equal(a.det, b.det) and torch.equal(a.trace, b.trace)
    assert any(bool((a.det > 1e-4).any()) for a in fused)


@needs_kernel
def test_surf_features_unchanged_by_the_kernel(images, monkeypatch):
    fused = extract_surf_features(images, config=SurfConfig())
    monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
    eager = extract_surf_features(images, config=SurfConfig())
    assert torch.equal(fused.keypoints.xy, eager.keypoints.xy)
    assert torch.equal(fused.descriptors, eager.descriptors)


def test_hessian_gradients_and_float64_take_the_torch_path(images):
    """The kernel is the no-gradient float32 path: a float64 image, or one that needs gradients, still gets
    the differentiable torch responses."""
    image = images[:1, :, :60, :80].double().requires_grad_()
    octaves = hessian_octaves(image, num_octaves=1)
    octaves[0].det.sum().backward()
    assert image.grad is not None and image.grad.abs().sum() > 0


def test_hessian_kernel_refuses_views_it_cannot_read():
    """A view with a column stride other than 1 is left to torch (returns False, writes nothing)."""
    if not kernels.available("hessian_level"):
        pytest.skip("no C compiler")
    base = torch.rand(2, 1, 10, 24)
    corners = [base[..., ::2]] * 32
    det, trace = torch.zeros(2, 1, 10, 12), torch.zeros(2, 1, 10, 12)
    assert not kernels.hessian_level(corners, 1.0, 1.0, 0.9, det, trace)
    assert not det.any() and not trace.any()
