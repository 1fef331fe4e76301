"""Epipolar solvers and distances vs exact synthetic geometry, OpenCV and naive formulas; gradchecks."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from svs_torch import InputError, estimate_fundamental_ransac
from svs_torch.geometry.epipolar import fundamental_7point, fundamental_8point
from svs_torch.geometry.epipolar_distance import sampson_distance, symmetric_epipolar_distance
from svs_torch.geometry.minimal_solvers import enforce_rank2, real_cubic_roots
from svs_torch.geometry.point_pairs import normalize_points_hartley

MOTIONS = ["general", "rectified", "vertical", "forward"]


def _skew(t: torch.Tensor) -> torch.Tensor:
    zero = torch.zeros_like(t[..., 0])
    rows = [[zero, -t[..., 2], t[..., 1]], [t[..., 2], zero, -t[..., 0]], [-t[..., 1], t[..., 0], zero]]
    return torch.stack([torch.stack(row, -1) for row in rows], -2)


def _motion(n: int, motion: str, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Rotation ``(n, 3, 3)`` and unit translation ``(n, 3)`` of the right camera (X_right = R X_left + t)."""
    f64 = torch.float64
    if motion == "general":
        axis = torch.randn(n, 3, generator=generator, dtype=f64)
        angle = (torch.rand(n, 1, 1, generator=generator, dtype=f64) * 2 - 1) * 0.3
        rotation = torch.linalg.matrix_exp(_skew(axis / axis.norm(dim=-1, keepdim=True)) * angle)
        translation = torch.randn(n, 3, generator=generator, dtype=f64)
        return rotation, translation / translation.norm(dim=-1, keepdim=True)
    direction = {"rectified": [-1.0, 0.0, 0.0], "vertical": [0.0, -1.0, 0.0], "forward": [0.1, 0.05, -1.0]}[motion]
    translation = torch.tensor(direction, dtype=f64).expand(n, 3)
    return torch.eye(3, dtype=f64).expand(n, 3, 3), translation / translation.norm(dim=-1, keepdim=True)


def random_camera_pairs(n: int, k: int, generator: torch.Generator, motion: str = "general",
                        size_wh: tuple[int, int] = (640, 480)) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Exact correspondences of k random 3-D points seen by n random camera pairs (float64).

    Returns left, right ``(n, k, 2)`` pixels and the true F ``(n, 3, 3)`` (unit norm,
    ``F = K⁻ᵀ [t]ₓ R K⁻¹``), so that ``x_rightᵀ F x_left = 0``.
    """
    f64 = torch.float64
    focal = 400 + 300 * torch.rand(n, generator=generator, dtype=f64)
    intrinsics = torch.zeros(n, 3, 3, dtype=f64)
    intrinsics[:, 0, 0] = intrinsics[:, 1, 1] = focal
    intrinsics[:, 0, 2], intrinsics[:, 1, 2], intrinsics[:, 2, 2] = size_wh[0] / 2, size_wh[1] / 2, 1.0
    rotation, translation = _motion(n, motion, generator)
    scene = torch.rand(n, k, 3, generator=generator, dtype=f64) * torch.tensor([4.0, 3.0, 4.0], dtype=f64)
    scene = scene + torch.tensor([-2.0, -1.5, 4.0], dtype=f64)  # 4–8 m in front of both cameras

    def project(points: torch.Tensor) -> torch.Tensor:
        pixels = points @ intrinsics.transpose(1, 2)
        return pixels[..., :2] / pixels[..., 2:]

    left = project(scene)
    right = project(scene @ rotation.transpose(1, 2) + translation.unsqueeze(1))
    inverse = torch.linalg.inv(intrinsics)
    fundamental = inverse.transpose(1, 2) @ _skew(translation) @ rotation @ inverse
    return left, right, fundamental / fundamental.flatten(1).norm(dim=1).view(-1, 1, 1)


def distance_up_to_sign(estimate: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Frobenius distance between unit-norm F's, up to sign: ``(...)``."""
    estimate = estimate / estimate.flatten(-2).norm(dim=-1)[..., None, None]
    plus = (estimate - truth).flatten(-2).norm(dim=-1)
    minus = (estimate + truth).flatten(-2).norm(dim=-1)
    return torch.minimum(plus, minus)


@pytest.mark.parametrize("motion", MOTIONS)
def test_8point_recovers_exact_f(motion, dtype, generator):
    left, right, truth = random_camera_pairs(16, 30, generator, motion)
    estimate = fundamental_8point(left.to(dtype), right.to(dtype))
    assert estimate.shape == (16, 3, 3) and estimate.dtype == dtype
    tolerance = 1e-8 if dtype == torch.float64 else 2e-3
    assert distance_up_to_sign(estimate.double(), truth).max() < tolerance
    assert sampson_distance(left, right, estimate.double()).max() < (1e-6 if dtype == torch.float64 else 0.05)
    singular = torch.linalg.svdvals(estimate.double())
    assert (singular[:, 2] / singular[:, 0]).max() < (1e-12 if dtype == torch.float64 else 1e-6)  # rank 2
    assert torch.allclose(estimate.double().flatten(1).norm(dim=1), torch.ones(16, dtype=torch.float64))


def test_sign_of_a_translation_f_does_not_depend_on_the_order_of_the_points(generator):
    # A rig that only translates (the SVS's parallel rig, a rectified pair) has a skew-symmetric F: its largest
    # entries are tied in magnitude with opposite signs, and the "largest entry positive" rule used to pick one of
    # them by rounding, so the same correspondences in another order (or RANSAC with another seed) gave -F.
    left, right, _ = random_camera_pairs(1, 40, generator, "rectified")
    first = fundamental_8point(left, right)
    for seed in range(12):
        order = torch.randperm(40, generator=torch.Generator().manual_seed(seed))
        again = fundamental_8point(left[:, order], right[:, order])
        assert (first - again).abs().max() < 1e-9, seed
        found = estimate_fundamental_ransac(left, right, torch.ones(1, 40, dtype=torch.bool),
                                            generator=torch.Generator().manual_seed(seed))
        assert (first - found.F).abs().max() < 1e-6, seed
    solutions, valid = fundamental_7point(left[:, :7], right[:, :7])
    assert valid.any() and ((solutions[valid] - first).flatten(1).norm(dim=1).min() < 1e-6)


def test_8point_weights_exclude_outliers_and_leading_dims_broadcast(generator):
    left, right, truth = random_camera_pairs(6, 20, generator)
    corrupted = right.clone()
    corrupted[:, :5] += 40.0
    weights = torch.ones(6, 20, dtype=torch.float64)
    weights[:, :5] = 0
    assert distance_up_to_sign(fundamental_8point(left, corrupted, weights), truth).max() < 1e-8
    assert distance_up_to_sign(fundamental_8point(left, corrupted), truth).min() > 1e-3
    stacked = fundamental_8point(left.view(2, 3, 20, 2), right.view(2, 3, 20, 2))
    assert stacked.shape == (2, 3, 3, 3)
    assert torch.allclose(stacked.view(6, 3, 3), fundamental_8point(left, right), atol=1e-12)


def test_8point_gradcheck(generator):
    left, right, _ = random_camera_pairs(1, 12, generator)
    left = (left + 0.3 * torch.randn(left.shape, generator=generator, dtype=torch.float64)).requires_grad_()
    right = right.requires_grad_()
    weights = (0.5 + torch.rand(1, 12, generator=generator, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(fundamental_8point, (left, right, weights), eps=1e-6, atol=1e-5)


@pytest.mark.parametrize("motion", MOTIONS)
def test_7point_true_f_is_among_solutions(motion, generator):
    left, right, truth = random_camera_pairs(200, 7, generator, motion)
    solutions, valid = fundamental_7point(left, right)
    assert solutions.shape == (200, 3, 3, 3) and valid.shape == (200, 3)
    error = torch.where(valid, distance_up_to_sign(solutions, truth.unsqueeze(1)), math.inf).amin(1)
    assert error.max() < 1e-7
    # Every valid solution is singular and fits the 7 points exactly.
    algebraic = sampson_distance(left.unsqueeze(1).expand(-1, 3, -1, -1), right.unsqueeze(1).expand(-1, 3, -1, -1),
                                 solutions)
    assert algebraic[valid].max() < 1e-6
    assert torch.linalg.det(solutions[valid]).abs().max() < 1e-8
    assert (solutions[~valid] == 0).all()


def test_7point_matches_opencv(generator):
    """Solution sets equal OpenCV's FM_7POINT (up to sign and order), noisy points, float32 input."""
    left, right, _ = random_camera_pairs(20, 7, generator)
    right = right + 0.5 * torch.randn(right.shape, generator=generator, dtype=torch.float64)
    solutions, valid = fundamental_7point(left.float(), right.float())
    assert solutions.dtype == torch.float32
    for i in range(20):
        theirs, _ = cv2.findFundamentalMat(left[i].float().numpy(), right[i].float().numpy(), cv2.FM_7POINT)
        theirs = torch.from_numpy(theirs).view(-1, 3, 3).double()
        theirs = theirs / theirs.flatten(1).norm(dim=1).view(-1, 1, 1)
        ours = solutions[i][valid[i]].double()
        assert len(ours) == len(theirs)
        pairwise = distance_up_to_sign(ours.unsqueeze(1), theirs.unsqueeze(0))  # (n, n)
        assert pairwise.amin(1).max() < 1e-3


@pytest.mark.parametrize("case", ["repeated", "collinear_left", "collinear_right", "identical"])
def test_7point_degenerate_samples_are_flagged(case, generator):
    left, right, _ = random_camera_pairs(10, 7, generator)
    if case == "repeated":
        left[:, 1], right[:, 1] = left[:, 0], right[:, 0]
    elif case == "collinear_left":
        left[..., 1] = 0.5 * left[..., 0] + 3.0
    elif case == "collinear_right":
        right[..., 1] = -0.2 * right[..., 0] + 100.0
    else:
        left[:], right[:] = left[:, :1], right[:, :1]
    solutions, valid = fundamental_7point(left, right)
    assert not valid.any()
    assert (solutions == 0).all()


def test_real_cubic_roots_match_numpy(generator):
    coefficients = torch.randn(2000, 4, generator=generator, dtype=torch.float64)
    coefficients[:5] = torch.tensor([[1.0, -6.0, 11.0, -6.0]] * 5, dtype=torch.float64)  # roots 1, 2, 3
    roots, valid = real_cubic_roots(coefficients)
    for i in range(2000):
        expected = np.roots(coefficients[i].numpy())
        expected = np.sort(expected[np.abs(expected.imag) < 1e-7].real)
        ours = np.sort(roots[i][valid[i]].numpy())
        assert len(ours) == len(expected), i
        np.testing.assert_allclose(ours, expected, rtol=1e-6, atol=1e-6)
    assert not real_cubic_roots(torch.tensor([[0.0, 1.0, 2.0, 3.0]], dtype=torch.float64))[1].any()


def test_enforce_rank2_is_the_nearest_rank2_matrix(generator):
    matrices = torch.randn(50, 3, 3, generator=generator, dtype=torch.float64)
    projected = enforce_rank2(matrices)
    singular = torch.linalg.svdvals(matrices)
    assert torch.linalg.matrix_rank(projected).eq(2).all()
    torch.testing.assert_close((matrices - projected).flatten(1).norm(dim=1), singular[:, 2])


def test_normalize_points_hartley(generator):
    points = 100 * torch.rand(4, 30, 2, generator=generator, dtype=torch.float64)
    weights = (torch.rand(4, 30, generator=generator) < 0.7).double()
    normalised, transform = normalize_points_hartley(points, weights)
    mask = weights.bool()
    for i in range(4):
        kept = normalised[i][mask[i]]
        torch.testing.assert_close(kept.mean(0), torch.zeros(2, dtype=torch.float64), atol=1e-12, rtol=0)
        torch.testing.assert_close(kept.norm(dim=1).mean(), torch.tensor(math.sqrt(2), dtype=torch.float64))
    homogeneous = torch.cat([points, torch.ones_like(points[..., :1])], -1) @ transform.transpose(1, 2)
    torch.testing.assert_close(homogeneous[..., :2], normalised)
    same, same_transform = normalize_points_hartley(torch.full((1, 5, 2), 7.0))
    assert same.abs().max() == 0 and same_transform[0, 0, 0] == 1.0


def test_sampson_distance_matches_opencv(generator):
    left, right, truth = random_camera_pairs(3, 40, generator)
    right = right + torch.randn(right.shape, generator=generator, dtype=torch.float64)
    ours = sampson_distance(left, right, truth, squared=True)
    for i in range(3):
        for k in range(40):
            theirs = cv2.sampsonDistance(np.append(left[i, k].numpy(), 1.0), np.append(right[i, k].numpy(), 1.0),
                                         truth[i].numpy())
            assert ours[i, k].item() == pytest.approx(theirs, rel=1e-9)
    torch.testing.assert_close(sampson_distance(left, right, truth), ours.sqrt())


def test_symmetric_distance_matches_point_line_distances(generator):
    left, right, truth = random_camera_pairs(2, 25, generator)
    right = right + torch.randn(right.shape, generator=generator, dtype=torch.float64)
    ones = torch.ones_like(left[..., :1])
    left_h, right_h = torch.cat([left, ones], -1), torch.cat([right, ones], -1)
    line_right = left_h @ truth.transpose(1, 2)  # lines a x + b y + c = 0
    line_left = right_h @ truth
    to_right = (right_h * line_right).sum(-1).abs() / line_right[..., :2].norm(dim=-1)
    to_left = (left_h * line_left).sum(-1).abs() / line_left[..., :2].norm(dim=-1)
    expected = to_right.square() + to_left.square()
    torch.testing.assert_close(symmetric_epipolar_distance(left, right, truth, squared=True), expected)
    # e²/a + e²/b vs e²/(a + b): about 4× the squared Sampson distance when a ≈ b (never less).
    ratio = expected / sampson_distance(left, right, truth, squared=True)
    assert ratio.min() >= 4.0 - 1e-9 and ratio.median().item() == pytest.approx(4.0, rel=0.1)


def test_distances_gradcheck_and_epipole(generator):
    # Unit-scale points and F keep the finite differences well conditioned (pixel F entries are ~1e-6).
    left, right = torch.randn(2, 2, 6, 2, generator=generator, dtype=torch.float64)
    fundamental = torch.randn(2, 3, 3, generator=generator, dtype=torch.float64)
    inputs = (left.requires_grad_(), right.requires_grad_(), fundamental.requires_grad_())
    assert torch.autograd.gradcheck(sampson_distance, inputs)
    assert torch.autograd.gradcheck(symmetric_epipolar_distance, inputs)
    # A point pair at both epipoles has undefined lines: 0 when it satisfies F, never NaN, finite gradients.
    at_epipole = torch.tensor([[[0.0, 0.0]]], dtype=torch.float64, requires_grad=True)
    singular = torch.tensor([[[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    assert sampson_distance(at_epipole, at_epipole, singular).item() == math.inf
    singular[0, 2, 2] = 0.0
    singular[0, 0, 1] = 1.0
    value = sampson_distance(at_epipole, at_epipole, singular)
    value.sum().backward()
    assert value.item() == 0.0 and torch.isfinite(at_epipole.grad).all()


def test_errors_name_the_argument():
    points = torch.zeros(2, 10, 2)
    with pytest.raises(InputError, match=r"points_left: expected \(N0, K, 2\), got \(2, 10, 3\)"):
        fundamental_8point(torch.zeros(2, 10, 3), points)
    with pytest.raises(InputError, match=r"points_right: expected the shape of points_left"):
        fundamental_8point(points, torch.zeros(2, 9, 2))
    with pytest.raises(InputError, match="at least 8 points, got 5"):
        fundamental_8point(torch.zeros(5, 2), torch.zeros(5, 2))
    with pytest.raises(InputError, match=r"points_left: expected \(N0, 7, 2\), got \(2, 10, 2\)"):
        fundamental_7point(points, points)
    with pytest.raises(InputError, match=r"fundamental: expected \(N0, 3, 3\), got \(2, 4, 4\)"):
        sampson_distance(points, points, torch.zeros(2, 4, 4))
    with pytest.raises(InputError, match="points_left: expected a float tensor, got torch.int64"):
        sampson_distance(points.long(), points, torch.zeros(2, 3, 3))
    # Integer pixels gave a silently truncated integer T (scale 0.02 -> 0) and float32 points.
    with pytest.raises(InputError, match="points: expected a float tensor, got torch.int64"):
        normalize_points_hartley(torch.arange(20).view(10, 2) * 7)
    with pytest.raises(InputError, match=r"points: expected \(K, 2\), got \(10, 3\)"):
        normalize_points_hartley(torch.zeros(10, 3))
    with pytest.raises(InputError, match="weights: expected a float or bool tensor, got torch.int64"):
        normalize_points_hartley(points, torch.ones(2, 10, dtype=torch.long))
    # torch's SVD raised "linalg.svd: Expected a floating point or complex tensor as input. Got Long".
    with pytest.raises(InputError, match="fundamental: expected a float tensor, got torch.int64"):
        enforce_rank2(torch.ones(2, 3, 3, dtype=torch.long))
    with pytest.raises(InputError, match=r"fundamental: expected \(N0, 3, 3\), got \(2, 4, 4\)"):
        enforce_rank2(torch.zeros(2, 4, 4))
