"""The differentiable pass's geometry (issue 31, svs_torch.geometry.soft): the LK-refined right points, F's refit
on RANSAC's inliers and Hartley's homographies, each with the hard values and gradients to the images."""

from __future__ import annotations

import pytest
import torch
from test_rectification import make_rigs

from svs_torch import InputError
from svs_torch.geometry.epipolar import fundamental_8point
from svs_torch.geometry.lk_refinement import _refine_lk_torch
from svs_torch.geometry.matched_points import MatchedPoints
from svs_torch.geometry.rectification import RectificationConfig, rectify_uncalibrated
from svs_torch.geometry.soft import (geometry_straight_through, lk_points_straight_through, lk_step,
                                     refit_fundamental_straight_through)

F64 = torch.float64


def _blobs(shift_xy: tuple[float, float], seed: int, size: int = 32) -> torch.Tensor:
    """A smooth image ``(1, 1, size, size)``: twelve Gaussian blobs, sampled at pixels shifted by ``shift_xy``
    (so a shift of (0.4, 0.25) moves its content by −(0.4, 0.25) px)."""
    gen = torch.Generator().manual_seed(seed)
    centres = torch.rand(12, 2, generator=gen, dtype=F64) * (size - 1)
    amplitude = torch.randn(12, generator=gen, dtype=F64)
    sigma = 1.5 + 2 * torch.rand(12, generator=gen, dtype=F64)
    y, x = torch.meshgrid(torch.arange(size, dtype=F64), torch.arange(size, dtype=F64), indexing="ij")
    x, y = x + shift_xy[0], y + shift_xy[1]
    squared = (x - centres[:, 0].view(-1, 1, 1)) ** 2 + (y - centres[:, 1].view(-1, 1, 1)) ** 2
    return (amplitude.view(-1, 1, 1) * torch.exp(-squared / (2 * sigma.view(-1, 1, 1) ** 2))).sum(0).view(1, 1, size,
                                                                                                           size)


def _lk_setup():
    left, right = _blobs((0.0, 0.0), 1), _blobs((0.4, 0.25), 1)
    xy_left = torch.tensor([[[15.0, 16.0], [12.0, 10.0]]], dtype=F64)
    start = xy_left - torch.tensor([0.3, 0.15], dtype=F64)
    radius = torch.full((1, 2), 5.0, dtype=F64)
    valid = torch.ones(1, 2, dtype=torch.bool)
    return left, right, xy_left, start, radius, valid


def _hard_lk(left, right, xy_left, start, radius, valid):
    """The torch reference refinement, run to convergence."""
    return _refine_lk_torch(left, right, MatchedPoints(xy_left, start, valid), radius, 50, 2.0, -1.0).right


def test_lk_points_keep_the_hard_values_and_follow_the_refinement_under_a_perturbation():
    left, right, xy_left, start, radius, valid = _lk_setup()
    hard = _hard_lk(left, right, xy_left, start, radius, valid)
    assert torch.allclose(hard, xy_left - torch.tensor([0.4, 0.25], dtype=F64), atol=0.06)
    soft = lk_points_straight_through(left, right.requires_grad_(), xy_left, hard, radius, valid)
    assert torch.equal(soft.detach(), hard) and soft.grad_fn is not None
    # Independent check: the hard refinement's response to a perturbation of each image (central differences)
    # against the straight-through point's directional derivative (implicit function theorem, GN Hessian).
    for which in (0, 1):
        direction = 0.05 * _blobs((0.0, 0.0), 7)
        eps = 1e-4

        def moved(sign: float) -> torch.Tensor:
            images = [left, right.detach()]
            images[which] = images[which] + sign * eps * direction
            return _hard_lk(*images, xy_left, start, radius, valid)

        finite = (moved(1) - moved(-1)) / (2 * eps)
        images = [left, right.detach()]

        def point(image: torch.Tensor) -> torch.Tensor:
            images[which] = image
            return lk_points_straight_through(*images, xy_left, hard, radius, valid)

        derivative = torch.autograd.functional.jvp(point, images[which].clone(), direction)[1]
        assert finite.abs().max() > 1e-3
        assert (derivative - finite).norm() < 0.25 * finite.norm()


def test_lk_step_gradcheck_and_rows_not_moved_carry_no_gradient():
    left, right, xy_left, start, radius, valid = _lk_setup()
    left, right = left[..., 4:24, 4:24].clone(), right[..., 4:24, 4:24].clone()  # a small gradcheck
    xy_left, start = xy_left - 4, start - 4
    radius = torch.full((1, 2), 3.0, dtype=F64)
    moved = torch.tensor([[True, False]])
    assert torch.autograd.gradcheck(lambda a, b: lk_step(a, b, xy_left, start, radius, moved),
                                     (left.requires_grad_(), right.requires_grad_()), eps=1e-6, atol=1e-6,
                                     fast_mode=True)
    soft = lk_points_straight_through(left, right, xy_left, start, radius, moved)
    grads = torch.autograd.grad(soft[0, 1].sum(), (left, right), allow_unused=True)
    assert all(g is None or not bool(g.any()) for g in grads)


@pytest.mark.parametrize("change", ["float16", "bfloat16", "moved_float"])
def test_lk_step_refuses_what_its_solve_cannot_take(change):
    """float16 images and a float ``moved`` raised NotImplementedError from inside torch ('"lu_cpu" not
    implemented for 'Half'', '"bitwise_and_cpu" not implemented for 'Float''; an audit): refused by name."""
    left, right, xy_left, start, radius, _ = _lk_setup()
    moved = torch.ones(xy_left.shape[:2], dtype=torch.bool)
    if change == "moved_float":
        moved, name = moved.float(), "moved"
    else:
        left, right, name = left.to(getattr(torch, change)), right.to(getattr(torch, change)), "left"
    with pytest.raises(InputError, match=f"{name}: expected a"):
        lk_step(left, right, xy_left, start, radius, moved)


def test_refit_fundamental_keeps_ransacs_values_with_the_8point_gradient(generator):
    F_true, left, right, _ = make_rigs(3, 20, generator)
    noise = 0.3 * torch.randn(right.shape, generator=generator, dtype=F64)
    right = right + noise
    inliers = torch.ones(3, 20, dtype=torch.bool)
    inliers[1, 12:] = False  # 12 inliers: refitted
    inliers[2, 8:] = False  # 8 inliers: too few, F stays a constant
    F_hard = F_true.to(torch.float32)
    right_grad = right.clone().requires_grad_()
    F, refit = refit_fundamental_straight_through(F_hard, left, right_grad, inliers)
    assert refit.tolist() == [True, True, False]
    assert torch.equal(F.detach(), F_hard.to(F64))
    # The gradient is the weighted 8-point's on the inliers (an independent call).
    weights = torch.rand(3, 3, 3, generator=generator, dtype=F64)
    (grad,) = torch.autograd.grad((F * weights).sum(), right_grad)
    reference = fundamental_8point(left[1:2, :12], right[1:2, :12])
    sign = torch.sign((reference * F_hard[1].to(F64)).sum())
    right_one = right[1:2, :12].clone().requires_grad_()
    (expected,) = torch.autograd.grad((sign * fundamental_8point(left[1:2, :12], right_one) * weights[1]).sum(),
                                      right_one)
    assert torch.allclose(grad[1, :12], expected[0], atol=1e-10)
    assert not bool(grad[1, 12:].any()) and not bool(grad[2].any()) and bool(grad[0].any())


@pytest.mark.parametrize("x_alignment", ["parallel", "hartley"])
def test_rectification_gradcheck_in_F(generator, x_alignment):
    F, left, right, _ = make_rigs(2, 16, generator)
    inliers = torch.ones(2, 16, dtype=torch.bool)
    config = RectificationConfig(x_alignment=x_alignment)
    assert (rectify_uncalibrated(F, left, right, inliers, (480, 640), config).status == 0).all()

    def homographies(F_in: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        result = rectify_uncalibrated(F_in, left, right, inliers, (480, 640), config)
        return result.H_left, result.H_right

    assert torch.autograd.gradcheck(homographies, (F.clone().requires_grad_(),), eps=1e-7, atol=1e-5)


def test_geometry_gives_the_hard_homographies_and_gradients_only_where_rectified_from_F():
    left, right, xy_left, start, radius, valid = _lk_setup()
    b, k = 2, 12
    gen = torch.Generator().manual_seed(3)
    xy_left = 8 + 16 * torch.rand(b, k, 2, generator=gen, dtype=F64)
    disparity = torch.stack([0.5 + 2.5 * torch.rand(b, k, generator=gen, dtype=F64),
                             0.05 * torch.randn(b, k, generator=gen, dtype=F64)], -1)
    xy_right = xy_left - disparity  # a near-parallel rig: F rectifies with an epipole far off the image
    images = [torch.cat([image] * b).requires_grad_() for image in (left, right)]
    inliers = torch.ones(b, k, dtype=torch.bool)
    F_hard = fundamental_8point(xy_left, xy_right, inliers.to(F64))
    config = RectificationConfig(x_alignment="hartley")
    hard = rectify_uncalibrated(F_hard, xy_left, xy_right, inliers, (32, 32), config)
    assert bool((hard.status == 0).all())
    from_F = torch.tensor([True, False])
    H_left, H_right = geometry_straight_through(*images, xy_left, xy_right, torch.full((b, k), 4.0, dtype=F64),
                                                inliers, inliers, F_hard, from_F, inliers, torch.zeros_like(from_F),
                                                hard.H_left, hard.H_right, torch.tensor([[32, 32]] * b), config)
    assert torch.equal(H_left.detach(), hard.H_left) and torch.equal(H_right.detach(), hard.H_right)
    grads = torch.autograd.grad((H_left * torch.randn(b, 3, 3, generator=gen, dtype=F64)).sum()
                                + (H_right * torch.randn(b, 3, 3, generator=gen, dtype=F64)).sum(), images)
    for grad in grads:
        assert bool(grad[0].any()) and not bool(grad[1].any()) and bool(torch.isfinite(grad).all())


def test_degenerate_rows_and_pairs_give_finite_gradients():
    """Found by an audit of the gradient claims: each gave finite values but NaN gradients (sqrt's or a quotient's
    infinite derivative at 0, times the zero a mask passes back): a flat patch in lk_step (both images' gradients,
    over the patch); a pair without inliers in keystone_refit's standard errors; and a pair without inliers in
    row_alignment_homography with a focal length, even where no pair is turned."""
    from svs_torch.geometry.row_alignment import row_alignment_homography
    from svs_torch.geometry.row_alignment_keystone import keystone_refit

    d, generator = torch.float64, torch.Generator().manual_seed(0)
    left = torch.rand(1, 1, 40, 40, dtype=d, generator=generator)
    left[..., 10:30, 10:30] = 0.5  # a flat square around the point
    left.requires_grad_(True)
    right = left.detach().clone().requires_grad_(True)
    xy = torch.tensor([[[20.0, 20.0]]], dtype=d)
    step = lk_step(left, right, xy, xy + 0.3, torch.tensor([[4.0]], dtype=d), torch.tensor([[True]]))
    assert torch.equal(step, torch.zeros_like(step))
    assert all(g.isfinite().all() for g in torch.autograd.grad(step.sum(), [left, right]))

    points_left = (torch.rand(2, 12, 2, dtype=d, generator=generator) * 60).requires_grad_(True)
    shift = 0.3 * torch.rand(2, 12, 2, dtype=d, generator=generator)
    points_right = (points_left.detach() + shift).requires_grad_(True)
    inliers = torch.ones(2, 12, dtype=torch.bool)
    inliers[1] = False
    image_hw, focal = torch.tensor([[72, 96], [72, 96]]), torch.tensor([80.0, 80.0], dtype=d)
    _, errors = keystone_refit(points_left, points_right, inliers, image_hw, focal, torch.ones(2, 2, dtype=torch.bool))
    assert torch.equal(errors[1], torch.zeros(5, dtype=d))
    assert torch.autograd.grad(errors.sum(), points_left)[0].isfinite().all()
    for turn in ([[0.5, 0.0], [0.0, 0.0]], [[0.0, 0.0], [0.0, 0.0]]):
        homography = row_alignment_homography(points_left, points_right, inliers, image_hw, focal,
                                              torch.tensor(turn, dtype=d))
        assert homography[0].isfinite().all()
        assert all(g.isfinite().all() for g in torch.autograd.grad(homography.sum(), [points_left, points_right]))
