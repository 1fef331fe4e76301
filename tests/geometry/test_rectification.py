"""Uncalibrated rectification vs exact two-camera geometry and OpenCV's ``stereoRectifyUncalibrated``."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
import torch

from svs_torch import InputError
from svs_torch.geometry.epipolar import fundamental_8point
from svs_torch.geometry.rectification import (RectificationConfig, RectificationStatus, apply_homography,
                                              rectify_uncalibrated, warp_rectified, warp_views)

F64 = torch.float64
SIZE_HW = (480, 640)
FOCAL_PX = 500.0
BASELINE_M = 0.12
PARALLEL = RectificationConfig()
HARTLEY = RectificationConfig(x_alignment="hartley")


def _skew(t: torch.Tensor) -> torch.Tensor:
    zero = torch.zeros_like(t[..., 0])
    rows = [[zero, -t[..., 2], t[..., 1]], [t[..., 2], zero, -t[..., 0]], [-t[..., 1], t[..., 0], zero]]
    return torch.stack([torch.stack(row, -1) for row in rows], -2)


def make_rigs(n: int, k: int, generator: torch.Generator, max_angle_rad: float = 0.02,
              baseline_jitter: float = 0.05) -> tuple[torch.Tensor, ...]:
    """n stereo rigs (f = 500 px, 640×480, principal point at the centre) with a roughly horizontal baseline
    of 0.12 m (right camera at +X) and a random rotation up to ``max_angle_rad`` about each axis; k points
    1.5–6 m in front of the left camera, inside its image. ``X_right = R X_left + t``.

    Returns F ``(n, 3, 3)`` (unit norm, ``x_rᵀ F x_l = 0``), left and right points ``(n, k, 2)`` (float64), and
    the points' depths ``(n, k)`` in the left camera.
    """
    intrinsics = torch.tensor([[FOCAL_PX, 0, 319.5], [0, FOCAL_PX, 239.5], [0, 0, 1]], dtype=F64)
    angles = (torch.rand(n, 3, generator=generator, dtype=F64) * 2 - 1) * max_angle_rad
    rotation = torch.linalg.matrix_exp(_skew(angles))
    direction = torch.cat([-torch.ones(n, 1, dtype=F64),
                           (torch.rand(n, 2, generator=generator, dtype=F64) * 2 - 1) * baseline_jitter], 1)
    centre_right = -direction * BASELINE_M / direction.norm(dim=1, keepdim=True)  # ≈ (+0.12, 0, 0)
    translation = -(rotation @ centre_right.unsqueeze(-1)).squeeze(-1)
    pixels = torch.rand(n, k, 2, generator=generator, dtype=F64) * torch.tensor([639.0, 479.0], dtype=F64)
    depth = 1.5 + 4.5 * torch.rand(n, k, generator=generator, dtype=F64)
    homogeneous = torch.cat([pixels, torch.ones(n, k, 1, dtype=F64)], -1)
    scene = (homogeneous @ torch.linalg.inv(intrinsics).T) * depth.unsqueeze(-1)
    projected = (scene @ rotation.transpose(1, 2) + translation.unsqueeze(1)) @ intrinsics.T
    right = projected[..., :2] / projected[..., 2:]
    inverse = torch.linalg.inv(intrinsics)
    fundamental = inverse.T @ _skew(translation) @ rotation @ inverse
    return fundamental / fundamental.flatten(1).norm(dim=1).view(-1, 1, 1), pixels, right, depth


def rectified(result, left: torch.Tensor, right: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    return apply_homography(result.H_left, left).xy, apply_homography(result.H_right, right).xy


def all_inliers(points: torch.Tensor) -> torch.Tensor:
    return torch.ones(points.shape[:2], dtype=torch.bool)


@pytest.mark.parametrize("config", [PARALLEL, HARTLEY], ids=["parallel", "hartley"])
def test_rows_align_noise_free(config, dtype, generator):
    F, left, right, _ = make_rigs(8, 40, generator)
    result = rectify_uncalibrated(F.to(dtype), left.to(dtype), right.to(dtype), all_inliers(left), SIZE_HW, config)
    assert result.H_left.shape == (8, 3, 3) and result.H_left.dtype == dtype and result.status.dtype == torch.int64
    assert (result.status == RectificationStatus.OK).all()
    assert result.num_inliers.tolist() == [40] * 8
    rect_left, rect_right = rectified(result, left.to(dtype), right.to(dtype))
    row_error = (rect_left[..., 1] - rect_right[..., 1]).abs().max()
    assert row_error < (1e-6 if dtype == F64 else 2e-3)
    assert result.rms_row_error_px.max() < (1e-6 if dtype == F64 else 2e-3)
    # No flip, no wild scaling: the homographies keep the image's orientation and about its size.
    for H in (result.H_left.double(), result.H_right.double()):
        corners = torch.tensor([[0.0, 0.0], [639.0, 0.0], [0.0, 479.0], [639.0, 479.0]], dtype=F64).expand(8, 4, 2)
        mapped = apply_homography(H, corners).xy
        width, height = mapped[:, 1, 0] - mapped[:, 0, 0], mapped[:, 2, 1] - mapped[:, 0, 1]
        assert ((width - 639).abs() < 64).all() and ((height - 479).abs() < 48).all()


def test_parallel_disparity_is_positive_and_near_the_truth(generator):
    """For a near-parallel rig (≤ 0.5° per axis) the "parallel" alignment keeps d = f·B/Z up to the unobservable
    toe-in offset f·ψ (≤ 4.4 px here): positive for every point in front."""
    F, left, right, depth = make_rigs(16, 50, generator, max_angle_rad=0.0087)
    result = rectify_uncalibrated(F, left, right, all_inliers(left), SIZE_HW)
    rect_left, rect_right = rectified(result, left, right)
    disparity = rect_left[..., 0] - rect_right[..., 0]
    truth = FOCAL_PX * BASELINE_M / depth
    assert (disparity > 0).all()
    assert (disparity - truth).abs().max() < 8.0
    # The error is (nearly) one offset per pair, so depth order is kept.
    error = disparity - truth
    assert (error.amax(1) - error.amin(1)).max() < 2.0


def test_pure_translation_gives_identity(generator):
    F, left, right, depth = make_rigs(4, 30, generator, max_angle_rad=0.0, baseline_jitter=0.0)
    parallel = rectify_uncalibrated(F, left, right, all_inliers(left), SIZE_HW)
    eye = torch.eye(3, dtype=F64).expand(4, 3, 3)
    for epipole in (parallel.epipole_left, parallel.epipole_right):  # at infinity along x
        assert torch.allclose(epipole.abs(), torch.tensor([1.0, 0.0, 0.0], dtype=F64).expand(4, 3), atol=1e-12)
    assert torch.allclose(parallel.H_left, eye, atol=1e-9) and torch.allclose(parallel.H_right, eye, atol=1e-9)
    rect_left, rect_right = rectified(parallel, left, right)
    assert torch.allclose(rect_left[..., 0] - rect_right[..., 0], FOCAL_PX * BASELINE_M / depth, atol=1e-6)
    # Hartley's alignment: identity up to the x row, which absorbs the mean disparity (MATLAB/OpenCV behaviour).
    hartley = rectify_uncalibrated(F, left, right, all_inliers(left), SIZE_HW, HARTLEY)
    assert torch.allclose(hartley.H_right, eye, atol=1e-9)
    assert torch.allclose(hartley.H_left[:, 1:], eye[:, 1:], atol=1e-9)
    shift = hartley.H_left[:, 0, 2]
    assert ((shift + FOCAL_PX * BASELINE_M / depth.mean(1)).abs() < 15).all() and (shift < 0).all()


def test_noisy_near_rectified_pair(generator):
    """F estimated from matches with 0.2 px noise on a parallel rig: near-identity homographies, rows within
    0.5 px, disparities within 1 px of the truth."""
    _, left, right, depth = make_rigs(6, 120, generator, max_angle_rad=0.0, baseline_jitter=0.0)
    noisy_left = left + 0.2 * torch.randn(left.shape, generator=generator, dtype=F64)
    noisy_right = right + 0.2 * torch.randn(right.shape, generator=generator, dtype=F64)
    F = fundamental_8point(noisy_left, noisy_right)
    result = rectify_uncalibrated(F, noisy_left, noisy_right, all_inliers(left), SIZE_HW)
    assert (result.status == RectificationStatus.OK).all()
    assert result.rms_row_error_px.max() < 0.5
    rect_left, rect_right = rectified(result, left, right)
    assert (rect_left[..., 1] - rect_right[..., 1]).abs().max() < 0.5
    assert (rect_left[..., 0] - rect_right[..., 0] - FOCAL_PX * BASELINE_M / depth).abs().max() < 1.0
    grid = torch.stack(torch.meshgrid(torch.linspace(0, 639, 5, dtype=F64), torch.linspace(0, 479, 5, dtype=F64),
                                      indexing="xy"), -1).reshape(1, -1, 2).expand(6, -1, -1)
    for H in (result.H_left, result.H_right):
        assert (apply_homography(H, grid).xy - grid).abs().max() < 3.0  # a common tilt of both images


def test_noisy_general_rig_rows_align(generator):
    _, left, right, _ = make_rigs(6, 150, generator)
    noisy_left = left + 0.2 * torch.randn(left.shape, generator=generator, dtype=F64)
    noisy_right = right + 0.2 * torch.randn(right.shape, generator=generator, dtype=F64)
    F = fundamental_8point(noisy_left, noisy_right)
    for config in (PARALLEL, HARTLEY):
        result = rectify_uncalibrated(F, noisy_left, noisy_right, all_inliers(left), SIZE_HW, config)
        assert (result.status == RectificationStatus.OK).all()
        assert result.rms_row_error_px.max() < 0.5
        rect_left, rect_right = rectified(result, left, right)
        assert (rect_left[..., 1] - rect_right[..., 1]).abs().max() < 0.5


def _opencv_homographies(F: torch.Tensor, left: torch.Tensor, right: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """OpenCV's H1, H2 per pair, scaled so that w > 0 (OpenCV returns them with an arbitrary sign)."""
    result = []
    for i in range(F.shape[0]):
        ok, h1, h2 = cv2.stereoRectifyUncalibrated(left[i].numpy(), right[i].numpy(), F[i].numpy(),
                                                   (SIZE_HW[1], SIZE_HW[0]), threshold=0)
        assert ok
        result.append([torch.from_numpy(h / h[2, 2]) for h in (h1, h2)])
    return tuple(torch.stack(list(column)) for column in zip(*result))


def test_matches_opencv(generator):
    """Hartley's alignment is OpenCV's algorithm: both rectify, and the two maps agree to a fraction of a pixel
    (OpenCV puts the image centre at the rounded ((W−1)/2, (H−1)/2), we at the exact one)."""
    F, left, right, _ = make_rigs(10, 60, generator)
    h1, h2 = _opencv_homographies(F, left, right)
    cv_left, cv_right = apply_homography(h1, left).xy, apply_homography(h2, right).xy
    assert (cv_left[..., 1] - cv_right[..., 1]).abs().max() < 1e-6
    ours = rectify_uncalibrated(F, left, right, all_inliers(left), SIZE_HW, HARTLEY)
    our_left, our_right = rectified(ours, left, right)
    assert (our_left - cv_left).abs().max() < 0.5 and (our_right - cv_right).abs().max() < 0.5
    # The "parallel" alignment shares the rows with Hartley's (only the left x row differs).
    parallel = rectify_uncalibrated(F, left, right, all_inliers(left), SIZE_HW)
    par_left, par_right = rectified(parallel, left, right)
    assert torch.allclose(par_left[..., 1], our_left[..., 1], atol=1e-6)
    assert torch.allclose(par_right, our_right, atol=1e-9)


def _bad_cases(generator: torch.Generator) -> tuple[torch.Tensor, ...]:
    """Six pairs: OK, zero F, rank-1 F, forward motion (epipole in the image), 5 inliers, NaN F."""
    F, left, right, _ = make_rigs(6, 20, generator)
    inliers = all_inliers(left).clone()
    F[1] = 0
    F[2] = torch.outer(torch.tensor([1.0, 2.0, 3.0], dtype=F64), torch.tensor([0.5, -1.0, 2.0], dtype=F64))
    F[3] = _skew(torch.tensor([330.0, 250.0, 1.0], dtype=F64))  # forward motion: epipole near the centre
    inliers[4, 5:] = False
    F[5, 0, 0] = float("nan")
    return F, left, right, inliers


def test_failures_are_per_pair_statuses(generator):
    F, left, right, inliers = _bad_cases(generator)
    result = rectify_uncalibrated(F, left, right, inliers, SIZE_HW)
    S = RectificationStatus
    assert result.status.tolist() == [S.OK, S.DEGENERATE, S.DEGENERATE, S.EPIPOLE_IN_IMAGE, S.NOT_ENOUGH_INLIERS,
                                      S.DEGENERATE]
    eye = torch.eye(3, dtype=F64)
    assert (result.H_left[1:] == eye).all() and (result.H_right[1:] == eye).all()
    assert torch.isfinite(result.rms_row_error_px).all()
    forward = result.epipole_right[3]
    assert torch.allclose(forward[:2] / forward[2], torch.tensor([330.0, 250.0], dtype=F64))
    assert (result.epipole_left[1:3] == 0).all() and torch.isfinite(result.epipole_left).all()
    # Collinear inliers leave Hartley's x row undetermined.
    collinear_left = left.clone()
    collinear_left[:, :, 1] = 100 + 0.5 * collinear_left[:, :, 0]
    hartley = rectify_uncalibrated(F[:1], collinear_left[:1], right[:1], inliers[:1], SIZE_HW, HARTLEY)
    assert hartley.status.tolist() == [S.DEGENERATE]


def test_distortion_and_flip_are_reported(generator):
    """An epipole 1.5 image widths from the centre: allowed by default, DISTORTED under a tight area bound."""
    F, left, right, _ = make_rigs(1, 30, generator, max_angle_rad=0.0, baseline_jitter=0.0)
    epipole = torch.tensor([319.5 + 960.0, 239.5, 1.0], dtype=F64)
    F_near = _skew(epipole).unsqueeze(0)  # a pure-translation F whose epipole is at x = 1280 px
    points = left
    right_points = right.clone()
    assert rectify_uncalibrated(F_near, points, right_points, all_inliers(left), SIZE_HW).status.tolist() == [0]
    tight = RectificationConfig(max_area_scale=1.2)
    status = rectify_uncalibrated(F_near, points, right_points, all_inliers(left), SIZE_HW, tight).status
    assert status.tolist() == [RectificationStatus.DISTORTED]
    # A vertical rig would be rotated by 90°: reported; a 20° tilt passes by default, not under a 10° bound.
    vertical = _skew(torch.tensor([0.0, 1.0, 0.0], dtype=F64)).unsqueeze(0)
    status = rectify_uncalibrated(vertical, points, right_points, all_inliers(left), SIZE_HW).status
    assert status.tolist() == [RectificationStatus.DISTORTED]
    tilted = _skew(torch.tensor([np.cos(0.35), np.sin(0.35), 0.0], dtype=F64)).unsqueeze(0)
    assert rectify_uncalibrated(tilted, points, right_points, all_inliers(left), SIZE_HW).status.tolist() == [0]
    level = RectificationConfig(max_rotation_deg=10.0)
    status = rectify_uncalibrated(tilted, points, right_points, all_inliers(left), SIZE_HW, level).status
    assert status.tolist() == [RectificationStatus.DISTORTED]
    # Hartley's fit to mirrored matches would flip the left image: reported, not returned.
    mirrored = left.clone()
    mirrored[..., 0] = 639 - mirrored[..., 0]
    flipped = rectify_uncalibrated(F, mirrored, right, all_inliers(left), SIZE_HW, HARTLEY)
    assert flipped.status.tolist() == [RectificationStatus.DISTORTED]


@pytest.mark.parametrize("config", [PARALLEL, HARTLEY], ids=["parallel", "hartley"])
def test_batched_equals_per_pair_and_padding_is_ignored(config, generator):
    F, left, right, inliers = _bad_cases(generator)
    batched = rectify_uncalibrated(F, left, right, inliers, SIZE_HW, config)
    for i in range(6):
        single = rectify_uncalibrated(F[i:i + 1], left[i:i + 1], right[i:i + 1], inliers[i:i + 1], SIZE_HW, config)
        assert single.status.item() == batched.status[i].item()
        assert torch.allclose(single.H_left[0], batched.H_left[i], atol=1e-12)
        assert torch.allclose(single.H_right[0], batched.H_right[i], atol=1e-12)
    garbage = torch.rand(6, 7, 2, generator=generator, dtype=F64) * 1e4
    garbage[:, 0] = float("inf")
    padded = rectify_uncalibrated(F, torch.cat([left, garbage], 1), torch.cat([right, -garbage], 1),
                                  torch.cat([inliers, torch.zeros(6, 7, dtype=torch.bool)], 1),
                                  torch.tensor([SIZE_HW] * 6), config)
    assert torch.equal(padded.status, batched.status)
    assert torch.allclose(padded.H_left, batched.H_left, atol=1e-12)
    assert torch.allclose(padded.rms_row_error_px, batched.rms_row_error_px, atol=1e-12)


def test_per_pair_image_sizes(generator):
    """A smaller pair padded into a bigger batch uses its own size (its own centre)."""
    F, left, right, _ = make_rigs(1, 30, generator)
    sizes = torch.tensor([[480, 640], [240, 320]])
    result = rectify_uncalibrated(F.expand(2, 3, 3), left.expand(2, -1, -1), right.expand(2, -1, -1),
                                  all_inliers(left).expand(2, -1), sizes)
    alone = rectify_uncalibrated(F, left, right, all_inliers(left), (240, 320))
    assert torch.allclose(result.H_left[1], alone.H_left[0], atol=1e-12)
    assert not torch.allclose(result.H_left[0], result.H_left[1], atol=1e-3)
    # Sizes in int32 run the same path (an int32 size once skipped the C kernel: its row error 1 ulp off).
    narrow = rectify_uncalibrated(F.expand(2, 3, 3), left.expand(2, -1, -1), right.expand(2, -1, -1),
                                  all_inliers(left).expand(2, -1), sizes.int())
    assert all(torch.equal(getattr(result, f.name), getattr(narrow, f.name)) for f in dataclasses.fields(result))


def test_empty_and_input_errors(generator):
    F, left, right, _ = make_rigs(2, 10, generator)
    empty = rectify_uncalibrated(F, left[:, :0], right[:, :0], torch.zeros(2, 0, dtype=torch.bool), SIZE_HW)
    assert empty.status.tolist() == [RectificationStatus.NOT_ENOUGH_INLIERS] * 2
    assert empty.rms_row_error_px.tolist() == [0.0, 0.0]
    with pytest.raises(InputError, match=r"F: expected \(B, 3, 3\), got \(2, 3, 4\)"):
        rectify_uncalibrated(F[..., :2].repeat(1, 1, 2), left, right, all_inliers(left), SIZE_HW)
    with pytest.raises(InputError, match=r"points_right: expected \(2, K, 2\)"):
        rectify_uncalibrated(F, left, right[..., :1], all_inliers(left), SIZE_HW)
    with pytest.raises(InputError, match="inliers: expected a bool tensor"):
        rectify_uncalibrated(F, left, right, all_inliers(left).double(), SIZE_HW)
    with pytest.raises(InputError, match="x_alignment"):
        rectify_uncalibrated(F, left, right, all_inliers(left), SIZE_HW, RectificationConfig(x_alignment="x"))
    with pytest.raises(InputError, match="image_hw"):
        rectify_uncalibrated(F, left, right, all_inliers(left), (0, 640))
    for size in (480, None):  # was: TypeError from len(), naming no argument
        with pytest.raises(InputError, match=rf"image_hw: expected \(height, width\) as two ints .*, got {size}$"):
            rectify_uncalibrated(F, left, right, all_inliers(left), size)
    # Found by an audit of the library called by hand: another kind of config raised AttributeError (x_alignment).
    with pytest.raises(InputError, match="^config: expected a RectificationConfig, got dict$"):
        rectify_uncalibrated(F, left, right, all_inliers(left), SIZE_HW, {"x_alignment": "parallel"})


def test_gradcheck(generator):
    F, left, right, _ = make_rigs(1, 9, generator)
    inliers = all_inliers(left)
    F = F.clone().requires_grad_()

    def parallel(F: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        result = rectify_uncalibrated(F, left, right, inliers, SIZE_HW)
        return result.H_left, result.H_right

    assert torch.autograd.gradcheck(parallel, (F,), eps=1e-7, atol=1e-5)
    points = left.clone().requires_grad_()

    def hartley(F: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        return rectify_uncalibrated(F, points, right, inliers, SIZE_HW, HARTLEY).H_left

    assert torch.autograd.gradcheck(hartley, (F, points), eps=1e-7, atol=1e-5)


def test_apply_homography_matches_opencv_and_masks_behind(generator):
    H = torch.tensor([[[1.02, 0.03, -5.0], [-0.01, 0.98, 3.0], [2e-5, -1e-5, 1.0]]], dtype=F64)
    points = torch.rand(1, 20, 2, generator=generator, dtype=F64) * 600
    mapped = apply_homography(H, points)
    theirs = cv2.perspectiveTransform(points.numpy(), H[0].numpy())
    assert np.allclose(mapped.xy.numpy(), theirs, atol=1e-9) and mapped.valid.all()
    behind = apply_homography(torch.tensor([[[1.0, 0, 0], [0, 1, 0], [-0.01, 0, 1]]], dtype=F64),
                              torch.tensor([[[50.0, 0.0], [100.0, 0.0], [150.0, 5.0]]], dtype=F64))
    assert behind.valid.tolist() == [[True, False, False]] and (behind.xy[0, 1:] == 0).all()


def test_warp_matches_opencv(generator):
    image = torch.rand(2, 1, 48, 64, generator=generator, dtype=torch.float32)
    H = torch.tensor([[1.02, 0.03, -2.0], [-0.01, 0.98, 1.5], [2e-4, -1e-4, 1.0]]).expand(2, 3, 3)
    warped = warp_rectified(image, H)
    assert warped.shape == image.shape and warped.dtype == image.dtype
    theirs = cv2.warpPerspective(image[0, 0].numpy(), H[0].numpy(), (64, 48), flags=cv2.INTER_LINEAR)
    interior = (slice(4, -4), slice(4, -4))
    assert np.abs(warped[0, 0].numpy()[interior] - theirs[interior]).max() < 1e-2
    identity = warp_rectified(image, torch.eye(3).expand(2, 3, 3))
    assert torch.allclose(identity, image, atol=1e-5)


def test_warped_views_stay_in_the_unit_range():
    """A white view warped bilinearly: kornia's blend of 1.0 pixels rounds one ulp above 1 at a few pixels (which
    every stage taking a view refuses: a brighter, clipped right camera once stopped the whole batch), and
    ``warp_views`` holds them at 1 while every other value is ``warp_rectified``'s."""
    white = torch.ones(3, 1, 48, 64)
    angles = torch.tensor([0.5, 1.0, 2.0]).deg2rad()
    H = torch.zeros(3, 3, 3)
    H[:, 0, 0], H[:, 0, 1], H[:, 1, 0], H[:, 1, 1] = 1.013 * angles.cos(), -1.013 * angles.sin(), \
        1.013 * angles.sin(), 1.013 * angles.cos()
    H[:, 0, 2], H[:, 1, 2], H[:, 2, 0], H[:, 2, 2] = 0.3, -0.7, 1e-5, 1.0
    blended = warp_rectified(white, H)
    assert bool((blended > 1).any())  # the rounding this guards against happens
    views = warp_views(white, H)
    assert float(views.max()) == 1.0 and torch.equal(views, blended.clamp(max=1.0))
    image = torch.rand(3, 1, 48, 64, generator=torch.Generator().manual_seed(0))
    assert torch.equal(warp_views(image, H), warp_rectified(image, H).clamp(0, 1))


def test_a_pairs_homography_gradient_is_the_same_alone_and_batched():
    """The gradient of a warp w.r.t. a pair's homography, a sum over every pixel, is that pair's whatever else is in
    its batch: batched, the sum was split among the threads by the batch's size, and pair 0's moved (0.75 in 2.5e6
    at 240x320 alone and among three, 2 threads; an audit). Values and image gradients were already the same."""
    generator = torch.Generator().manual_seed(0)
    images, weights = torch.rand(3, 1, 240, 320, generator=generator), torch.rand(1, 1, 240, 320, generator=generator)
    H = torch.eye(3).repeat(3, 1, 1)
    H[:, 0, 1], H[:, 1, 2], H[:, 2, 0] = 0.01, 0.7, 1e-5
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        found = []
        for count in (1, 3):
            homographies = H[:count].clone().requires_grad_()
            for warp in (warp_rectified, warp_views):
                warped = warp(images[:count], homographies)
                (gradient,) = torch.autograd.grad((warped[:1] * weights).sum(), homographies)
                found.append((warped[0].detach(), gradient[0]))
    finally:
        torch.set_num_threads(before)
    for (alone, batched) in ((found[0], found[2]), (found[1], found[3])):
        assert torch.equal(alone[0], batched[0]) and torch.equal(alone[1], batched[1])
    with torch.no_grad():  # without a gradient, the batch in one call: the same values
        assert torch.equal(warp_rectified(images, H)[:1], warp_rectified(images[:1], H[:1]))


@pytest.mark.parametrize("threads", [1, 3])
def test_the_compiled_parallel_mode_gives_the_torch_paths_rectification(generator, monkeypatch, dtype, threads):
    """The C kernel (a pair in one pass) against the torch path: every status (OK, zero, rank-1 and NaN F, an
    epipole in the image, too few inliers; a distorted pair under tight limits), homographies and epipoles to their
    last bits, the RMS row error to its dtype's round-off, per-pair image sizes and some inliers left out."""
    from svs_torch.geometry import kernels

    if not kernels.available("rectify_parallel"):
        pytest.skip("no C compiler")
    F, left, right, inliers = _bad_cases(generator)
    rigs = make_rigs(6, 20, generator, max_angle_rad=0.05, baseline_jitter=0.3)
    F, left, right = torch.cat([F, rigs[0]]), torch.cat([left, rigs[1]]), torch.cat([right, rigs[2]])
    inliers = torch.cat([inliers, torch.rand(6, 20, generator=generator) > 0.2])
    image_hw = torch.tensor([[480, 640]] * 6 + [[480, 640], [240, 320]] * 3)
    F, left, right = F.to(dtype), left.to(dtype), right.to(dtype)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for config in (PARALLEL, RectificationConfig(max_area_scale=1.05, max_rotation_deg=2.0)):
            fused = rectify_uncalibrated(F, left, right, inliers, image_hw, config)
            monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
            eager = rectify_uncalibrated(F, left, right, inliers, image_hw, config)
            monkeypatch.delenv("SVS_TORCH_KERNELS")
            assert torch.equal(fused.status, eager.status) and torch.equal(fused.num_inliers, eager.num_inliers)
            assert set(fused.status.tolist()) >= ({0, 1, 2, 3} if config is PARALLEL else {1, 2, 3, 4})
            exact = 1e-12 if dtype == F64 else 1e-5  # float32: a float64 ulp may round the other way
            for name in ("H_left", "H_right", "epipole_left", "epipole_right"):
                a, b = getattr(fused, name), getattr(eager, name)
                assert a.dtype == b.dtype == dtype, name
                torch.testing.assert_close(a, b, rtol=exact, atol=exact)
            # float32 rows of 640 px round to 3e-5 px in torch's sums; the kernel's are in double.
            torch.testing.assert_close(fused.rms_row_error_px, eager.rms_row_error_px, rtol=1e-6,
                                       atol=1e-9 if dtype == F64 else 1e-4)
    finally:
        torch.set_num_threads(before)


def test_a_huge_inlier_minimum_and_bad_limits(generator):
    """A minimum past int64 refuses every pair on both paths (the kernel's argument is clamped, not wrapped); limits
    that would refuse every pair, or are not numbers, are refused when the config is made."""
    F, left, right, _ = make_rigs(2, 20, generator)
    strict = RectificationConfig(min_inliers=2**70)
    assert rectify_uncalibrated(F, left, right, all_inliers(left), SIZE_HW, strict).status.tolist() == [1, 1]
    for bad in (dict(max_area_scale=0.5), dict(max_rotation_deg=0.0), dict(min_inliers=-1), dict(x_alignment="x")):
        with pytest.raises(InputError, match=next(iter(bad))):
            RectificationConfig(**bad)


@pytest.mark.parametrize("path", ["compiled", "torch"])
def test_a_turn_either_way_and_the_fewest_inliers_on_both_paths(generator, monkeypatch, path):
    """Found by a mutation audit: the torch path's rotation bound held one way only without its ``abs()``, and
    ``min_inliers`` read as "more than" went unnoticed. A rig tilted 20° either way is DISTORTED under a 10° bound;
    exactly ``min_inliers`` (the 7-point minimum) inliers rectify, one fewer do not."""
    if path == "torch":
        monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
    F, left, right, _ = make_rigs(1, 30, generator, max_angle_rad=0.0, baseline_jitter=0.0)
    level = RectificationConfig(max_rotation_deg=10.0)
    for turn in (0.35, -0.35):
        tilted = _skew(torch.tensor([np.cos(turn), np.sin(turn), 0.0], dtype=F64)).unsqueeze(0)
        assert rectify_uncalibrated(tilted, left, right, all_inliers(left), SIZE_HW).status.tolist() == [0]
        status = rectify_uncalibrated(tilted, left, right, all_inliers(left), SIZE_HW, level).status
        assert status.tolist() == [RectificationStatus.DISTORTED], turn
    fewest = PARALLEL.min_inliers
    for count, expected in ((fewest, RectificationStatus.OK), (fewest - 1, RectificationStatus.NOT_ENOUGH_INLIERS)):
        inliers = torch.arange(30).unsqueeze(0) < count
        assert rectify_uncalibrated(F, left, right, inliers, SIZE_HW).status.tolist() == [expected], count


@pytest.mark.parametrize("path", ["compiled", "torch"])
def test_an_inlier_at_a_nan_point_is_neither_used_nor_counted(generator, monkeypatch, path):
    """Found by an audit: an inlier whose point is NaN (or inf) in either view was skipped by both paths yet counted
    in ``num_inliers``, so that ``min_inliers`` − 1 usable inliers and one NaN passed as enough. It counts as the
    inlier it is not: the pair's rectification is that of its finite inliers alone."""
    if path == "torch":
        monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
    F, left, right, _ = make_rigs(1, 30, generator)
    fewest = PARALLEL.min_inliers
    inliers = torch.arange(30).unsqueeze(0) < fewest
    finite = rectify_uncalibrated(F, left, right, inliers, SIZE_HW)
    for view, bad in (("left", float("nan")), ("right", float("inf"))):
        points = {"left": left.clone(), "right": right.clone()}
        points[view][0, 0, 1] = bad
        spoilt = rectify_uncalibrated(F, points["left"], points["right"], inliers, SIZE_HW)
        assert spoilt.num_inliers.tolist() == [fewest - 1], view
        assert spoilt.status.tolist() == [RectificationStatus.NOT_ENOUGH_INLIERS], view
        wide = torch.arange(30).unsqueeze(0) < fewest + 1
        with_one_more = rectify_uncalibrated(F, points["left"], points["right"], wide, SIZE_HW)
        assert with_one_more.num_inliers.tolist() == [fewest] and with_one_more.status.tolist() == [0], view
    assert finite.num_inliers.tolist() == [fewest] and finite.status.tolist() == [0]
