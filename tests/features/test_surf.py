"""SURF detector and descriptor: a slow per-pixel / per-keypoint reference (loops, float64) written here,
invariance properties, padding, batching, gradients, and real images with ground truth."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from svs_torch import InputError, Keypoints
from svs_torch.features.descriptor import describe_surf, surf_orientation, with_orientation
from svs_torch.features.detector import SurfConfig, detect_surf_keypoints, metric_threshold_01
from svs_torch.features.hessian import filter_sizes, hessian_octaves
from svs_torch.features.integral import padded_integral_image, sample_box_means, sample_cell_means
from svs_torch.features.surf import extract_surf_features


def smooth_image(batch: int, height: int, width: int, seed: int, dtype=torch.float64) -> torch.Tensor:
    """Blobs of several sizes in [0.1, 0.9]: plenty of scale-space maxima."""
    g = torch.Generator().manual_seed(seed)
    image = torch.zeros(batch, 1, height, width, dtype=dtype)
    for k in (3, 7, 11):
        noise = torch.rand(batch, 1, height, width, generator=g, dtype=dtype)
        image += torch.nn.functional.avg_pool2d(noise, k, 1, k // 2, count_include_pad=False)
    image = (image - image.amin()) / (image.amax() - image.amin())
    return 0.1 + 0.8 * image


# ----------------------------------------------------------------------------------------------------------
# Slow reference: box sums straight from the pixels, keypoints by explicit loops.

def box(img: np.ndarray, y: int, x: int, rows: tuple[int, int], cols: tuple[int, int]) -> float:
    """Sum of pixels [y + r0, y + r1) × [x + c0, x + c1), clipped to the image."""
    h, w = img.shape
    return float(img[max(0, y + rows[0]):min(h, y + rows[1]), max(0, x + cols[0]):min(w, x + cols[1])].sum())


def reference_response(img: np.ndarray, size: int, y: int, x: int) -> tuple[float, float]:
    """det(H) and trace of one filter at one pixel, from the definitions (Bay Fig. 1, per-lobe means)."""
    l, half = size // 3, size // 2
    lobe_area = (2 * l - 1) * l
    dxx = (box(img, y, x, (-(l - 1), l), (-half, -half + l)) - 2 * box(img, y, x, (-(l - 1), l), (-(l // 2), l // 2 + 1))
           + box(img, y, x, (-(l - 1), l), (half - l + 1, half + 1))) / lobe_area
    dyy = (box(img, y, x, (-half, -half + l), (-(l - 1), l)) - 2 * box(img, y, x, (-(l // 2), l // 2 + 1), (-(l - 1), l))
           + box(img, y, x, (half - l + 1, half + 1), (-(l - 1), l))) / lobe_area
    dxy = (box(img, y, x, (-l, 0), (-l, 0)) - box(img, y, x, (-l, 0), (1, l + 1))
           - box(img, y, x, (1, l + 1), (-l, 0)) + box(img, y, x, (1, l + 1), (1, l + 1))) / (l * l)
    return dxx * dyy - (0.9 * dxy) ** 2, dxx + dyy


def test_responses_equal_the_definition():
    image = smooth_image(1, 41, 47, 0)
    img = image[0, 0].numpy()
    octaves = hessian_octaves(image, num_octaves=2, num_scale_levels=4)
    checked = 0
    for octave in octaves:
        for level, size in enumerate(octave.sizes):
            # Where the filter sticks out of the image the response is undefined (and never used).
            for i, j in octave.inside[level].nonzero().tolist():
                det, trace = reference_response(img, size, i * octave.step, j * octave.step)
                assert float(octave.det[0, level, i, j]) == pytest.approx(det, abs=1e-12)
                assert float(octave.trace[0, level, i, j]) == pytest.approx(trace, abs=1e-12)
                checked += 1
    assert checked > 1000
    assert [o.sizes for o in octaves] == [(9, 15, 21, 27), (15, 27, 39, 51)]
    assert filter_sizes(2, 4) == [27, 51, 75, 99]


def reference_keypoints(img: np.ndarray, config: SurfConfig) -> list[tuple[float, float, float, float, int]]:
    """(x, y, scale, score, sign) by loops over every octave grid point: 3×3×3 maxima, quadratic fit."""
    h, w = img.shape
    threshold = metric_threshold_01(config.metric_threshold)
    found = []
    for octave in range(config.num_octaves):
        step, sizes = 1 << octave, filter_sizes(octave, config.num_scale_levels)
        ny, nx = -(-h // step), -(-w // step)
        det = np.zeros((len(sizes), ny, nx))
        trace = np.zeros_like(det)
        for s, size in enumerate(sizes):
            for i in range(ny):
                for j in range(nx):
                    det[s, i, j], trace[s, i, j] = reference_response(img, size, i * step, j * step)

        def fits(size, i, j):
            half = size // 2
            return half <= i * step <= h - 1 - half and half <= j * step <= w - 1 - half

        for s in range(1, len(sizes) - 1):
            for i in range(1, ny - 1):
                for j in range(1, nx - 1):
                    v = det[s, i, j]
                    if v <= threshold or not all(fits(sizes[s + 1], i + a, j + b) for a in (-1, 0, 1) for b in (-1, 0, 1)):
                        continue
                    if v < det[s - 1:s + 2, i - 1:i + 2, j - 1:j + 2].max():
                        continue
                    n = det[s - 1:s + 2, i - 1:i + 2, j - 1:j + 2]  # n[ds, dy, dx]
                    g = np.array([n[1, 1, 2] - n[1, 1, 0], n[1, 2, 1] - n[1, 0, 1], n[2, 1, 1] - n[0, 1, 1]]) / 2
                    hxx = n[1, 1, 2] + n[1, 1, 0] - 2 * v
                    hyy = n[1, 2, 1] + n[1, 0, 1] - 2 * v
                    hss = n[2, 1, 1] + n[0, 1, 1] - 2 * v
                    hxy = (n[1, 2, 2] - n[1, 2, 0] - n[1, 0, 2] + n[1, 0, 0]) / 4
                    hxs = (n[2, 1, 2] - n[2, 1, 0] - n[0, 1, 2] + n[0, 1, 0]) / 4
                    hys = (n[2, 2, 1] - n[2, 0, 1] - n[0, 2, 1] + n[0, 0, 1]) / 4
                    offset = np.linalg.solve([[hxx, hxy, hxs], [hxy, hyy, hys], [hxs, hys, hss]], -g)
                    if np.abs(offset).max() > config.max_offset:
                        continue
                    size = sizes[0] + (s + offset[2]) * (sizes[1] - sizes[0])
                    found.append(((j + offset[0]) * step, (i + offset[1]) * step, 1.2 * size / 9,
                                  v + 0.5 * g @ offset, 1 if trace[s, i, j] >= 0 else -1))
    return sorted(found, key=lambda k: -k[3])


def test_keypoints_equal_the_loop_reference():
    image = smooth_image(1, 84, 96, 1)
    config = SurfConfig(metric_threshold=10.0, num_octaves=2, max_keypoints=400)
    expected = reference_keypoints(image[0, 0].numpy(), config)
    kp = detect_surf_keypoints(image, config)
    n = int(kp.valid.sum())
    assert len(expected) > 20 and n == len(expected)
    got = sorted(zip(kp.xy[0, :n, 0].tolist(), kp.xy[0, :n, 1].tolist(), kp.scale[0, :n].tolist(),
                     kp.score[0, :n].tolist(), kp.laplacian_sign[0, :n].tolist()), key=lambda k: -k[3])
    np.testing.assert_allclose(np.array(got), np.array(expected), atol=1e-9)
    assert torch.all(kp.score[0, :n - 1] >= kp.score[0, 1:n])  # strongest first


def reference_cell_mean(img: np.ndarray, cx: float, cy: float, half: float) -> float:
    """Mean of the pixel-constant image over [cx ± half] × [cy ± half], by exact pixel overlaps, the image
    extended by its edge pixels (replicate border)."""
    pad = 40
    img = np.pad(img, pad, mode="edge")
    cx, cy = cx + pad, cy + pad
    h, w = img.shape
    x0, x1 = cx - half, cx + half
    y0, y1 = cy - half, cy + half
    total = 0.0
    for r in range(max(0, math.floor(y0 + 0.5)), min(h, math.ceil(y1 + 0.5))):
        oy = min(y1, r + 0.5) - max(y0, r - 0.5)
        for c in range(max(0, math.floor(x0 + 0.5)), min(w, math.ceil(x1 + 0.5))):
            ox = min(x1, c + 0.5) - max(x0, c - 0.5)
            if ox > 0 and oy > 0:
                total += img[r, c] * ox * oy
    return total / ((x1 - x0) * (y1 - y0))


def reference_descriptor(img: np.ndarray, x: float, y: float, s: float, theta: float) -> np.ndarray:
    """SURF-64 from its definition: 21×21 cell means, 2×2-cell Haar, Gaussian σ = 3.3, 4×4 sub-regions."""
    patch = np.zeros((21, 21))
    c, si = math.cos(theta), math.sin(theta)
    for i in range(21):
        for j in range(21):
            u, v = j - 10, i - 10
            patch[i, j] = reference_cell_mean(img, x + s * (c * u - si * v), y + s * (si * u + c * v), s / 2)
    vector = []
    for bi in range(4):
        for bj in range(4):
            sums = np.zeros(4)
            for i in range(5 * bi, 5 * bi + 5):
                for j in range(5 * bj, 5 * bj + 5):
                    weight = math.exp(-((i - 9.5) ** 2 + (j - 9.5) ** 2) / (2 * 3.3**2))
                    dx = (patch[i, j + 1] - patch[i, j] + patch[i + 1, j + 1] - patch[i + 1, j]) / 2 * weight
                    dy = (patch[i + 1, j] - patch[i, j] + patch[i + 1, j + 1] - patch[i, j + 1]) / 2 * weight
                    sums += [dx, dy, abs(dx), abs(dy)]
            vector.extend(sums)
    vector = np.array(vector)
    return vector / np.linalg.norm(vector)


def make_keypoints(xy, scale, orientation=None, k_total=None) -> Keypoints:
    xy = torch.tensor(xy, dtype=torch.float64).view(1, -1, 2)
    k = xy.shape[1]
    kp = Keypoints(xy=xy, scale=torch.tensor(scale, dtype=torch.float64).view(1, k),
                   score=torch.ones(1, k, dtype=torch.float64), laplacian_sign=torch.ones(1, k, dtype=torch.int64),
                   orientation=torch.tensor(orientation or [0.0] * k, dtype=torch.float64).view(1, k),
                   valid=torch.ones(1, k, dtype=torch.bool))
    return kp


def test_descriptor_equals_the_loop_reference_upright_and_rotated():
    image = smooth_image(1, 60, 70, 2)
    img = image[0, 0].numpy()
    xy, scale, theta = [[30.3, 28.6], [12.0, 50.2], [65.5, 4.0]], [1.6, 2.3, 1.2], [0.0, 0.7, -2.0]
    kp = make_keypoints(xy, scale, theta)
    ours = describe_surf(image, kp)
    for n in range(3):
        np.testing.assert_allclose(ours[0, n].numpy(), reference_descriptor(img, *xy[n], scale[n], theta[n]),
                                   atol=1e-9)


def test_brightness_offset_leaves_responses_unchanged():
    image = smooth_image(2, 50, 60, 3)
    base = hessian_octaves(image * 0.8)
    shifted = hessian_octaves(image * 0.8 + 0.15)
    for a, b in zip(base, shifted):
        torch.testing.assert_close(a.det, b.det, atol=1e-12, rtol=0)
        torch.testing.assert_close(a.trace, b.trace, atol=1e-12, rtol=0)


def test_detections_follow_an_integer_shift():
    image = smooth_image(1, 96, 112, 4)
    config = SurfConfig(metric_threshold=60.0, max_keypoints=300)
    dy, dx = 8, 12  # multiples of the coarsest grid step (4), so every octave's grid shifts with the image
    shifted = torch.zeros_like(image)
    shifted[..., dy:, dx:] = image[..., :-dy, :-dx]
    a, b = detect_surf_keypoints(image, config), detect_surf_keypoints(shifted, config)

    def interior(kp, lo_x, lo_y, hi_x, hi_y):
        keep = kp.valid[0] & (kp.xy[0, :, 0] > lo_x) & (kp.xy[0, :, 1] > lo_y) & (kp.xy[0, :, 0] < hi_x) & \
            (kp.xy[0, :, 1] < hi_y)
        return {(round(x, 6), round(y, 6), round(s, 6)) for (x, y), s in zip(kp.xy[0][keep].tolist(),
                                                                             kp.scale[0][keep].tolist())}

    # Away from both images' borders by more than the largest filter reach (99 // 2 + 4).
    margin = 54
    before = interior(a, margin, margin, 112 - dx - margin, 96 - dy - margin)
    after = {(round(x - dx, 6), round(y - dy, 6), s) for x, y, s in
             interior(b, margin + dx, margin + dy, 112 - margin, 96 - margin)}
    assert before == after


def test_descriptor_is_unchanged_by_a_brightness_gain():
    image = smooth_image(1, 60, 70, 5)
    kp = make_keypoints([[30.0, 30.0], [20.5, 40.2]], [2.0, 1.5])
    torch.testing.assert_close(describe_surf(image * 0.7, kp), describe_surf(image, kp), atol=1e-9, rtol=0)
    torch.testing.assert_close(describe_surf(image * 0.7 + 0.2, kp), describe_surf(image, kp), atol=1e-9, rtol=0)


def test_orientation_turns_with_the_image_and_descriptors_follow():
    image = smooth_image(1, 64, 64, 6)
    kp = make_keypoints([[31.5, 31.5], [25.0, 36.0]], [1.8, 2.2])
    rotated = torch.rot90(image, 1, dims=(2, 3))  # a quarter turn counter-clockwise
    xy = kp.xy.clone()
    kp_rot = make_keypoints(torch.stack([xy[0, :, 1], 63 - xy[0, :, 0]], -1).tolist(), kp.scale[0].tolist())
    theta, theta_rot = surf_orientation(image, kp), surf_orientation(rotated, kp_rot)
    turn = (theta_rot - theta + math.pi) % (2 * math.pi) - math.pi
    torch.testing.assert_close(turn, torch.full_like(turn, -math.pi / 2), atol=1e-9, rtol=0)
    torch.testing.assert_close(describe_surf(image, with_orientation(kp, theta)),
                               describe_surf(rotated, with_orientation(kp_rot, theta_rot)), atol=1e-6, rtol=0)


def test_extended_descriptor_puts_responses_zero_by_definition_in_the_not_negative_half(monkeypatch):
    """In the replicate border every cell reads the edge pixel, so a Haar response across the border is 0 and the
    extended descriptor puts the other response's sums into its "not negative" half: above and below the image no
    Σdx where dy < 0, left of it no Σdy where dx < 0. Round-off gave those zeros a sign, and the C kernel (double)
    and the torch path split the sums differently: 0.024 apart on this keypoint, which the kernel fuzz drew at
    ``SVS_FUZZ_SCALE=3`` (an 8 x 18 image, a keypoint 0.001 px from its left edge)."""
    from svs_torch.core import kernels

    y, x = torch.meshgrid(torch.arange(8.0), torch.arange(18.0), indexing="ij")
    image = (0.5 + 0.4 * torch.sin(x / 3 + 4.2469) * torch.cos(y / 4 - 4.2469)).view(1, 1, 8, 18)
    kp = Keypoints(torch.tensor([[[9.7291e-04, 4.8310]]]), torch.tensor([[1.0626]]), torch.zeros(1, 1),
                   torch.zeros(1, 1, dtype=torch.int64), torch.zeros(1, 1), torch.ones(1, 1, dtype=torch.bool))
    paths = {"kernel": describe_surf(image, kp, extended=True)}
    monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
    paths.update(float32=describe_surf(image, kp, extended=True), float64=describe_surf(image.double(), kp, True))
    for name, descriptor in paths.items():
        blocks = descriptor.view(4, 4, 8)  # sub-region rows (top to bottom), columns, the 8 sums
        assert torch.all(blocks[[0, 3], :, :2] == 0) and torch.all(blocks[:, 0, 4:6] == 0), name
        assert blocks[[0, 3], :, 2:4].abs().amax() > 0.01 and blocks[:, 0, 6:].abs().amax() > 0.01, name
    torch.testing.assert_close(paths["float32"].double(), paths["float64"], atol=5e-4, rtol=0)
    if kernels.available("usurf_describe"):  # the kernel built from today's source (its cache key is the source)
        torch.testing.assert_close(paths["kernel"].double(), paths["float64"], atol=1e-5, rtol=0)


def test_padding_rows_are_zero_and_change_nothing():
    image = smooth_image(2, 70, 80, 7, torch.float32)
    config = SurfConfig(metric_threshold=100.0, max_keypoints=600)
    features = extract_surf_features(image, config)
    kp = features.keypoints
    assert kp.xy.shape == (2, 600, 2) and kp.valid.dtype == torch.bool
    invalid = ~kp.valid
    assert invalid.any() and torch.all(kp.xy[invalid] == 0) and torch.all(kp.scale[invalid] == 0)
    assert torch.all(features.descriptors[invalid] == 0) and torch.all(kp.laplacian_sign[invalid] == 0)
    torch.testing.assert_close(features.descriptors[kp.valid].norm(dim=-1),
                               torch.ones(int(kp.valid.sum())), atol=1e-5, rtol=0)
    # Describing without the padding rows gives the same descriptors for the real ones.
    n = int(kp.valid.sum(1).max())
    trimmed = Keypoints(kp.xy[:, :n], kp.scale[:, :n], kp.score[:, :n], kp.laplacian_sign[:, :n],
                        kp.orientation[:, :n], kp.valid[:, :n])
    torch.testing.assert_close(describe_surf(image, trimmed), features.descriptors[:, :n])


def test_batched_equals_per_image_and_dtype_follows():
    image = smooth_image(3, 60, 64, 8, torch.float32)
    config = SurfConfig(metric_threshold=100.0, max_keypoints=64)
    batched = extract_surf_features(image, config)
    for i in range(3):
        single = extract_surf_features(image[i:i + 1], config)
        k = single.keypoints.xy.shape[1]
        assert torch.equal(single.keypoints.xy, batched.keypoints.xy[i:i + 1, :k])
        # The replicate border follows the batch's largest scale, and changes nothing (an anchored table).
        assert torch.equal(single.descriptors, batched.descriptors[i:i + 1, :k])
    assert batched.keypoints.xy.dtype == torch.float32 and batched.descriptors.dtype == torch.float32
    assert batched.descriptors.shape == (3, 64, 64)
    assert extract_surf_features(image, SurfConfig(max_keypoints=8, extended=True)).descriptors.shape == (3, 8, 128)


def test_mask_restricts_keypoints_and_blank_images_give_none():
    image = smooth_image(2, 80, 80, 9, torch.float32)
    image[1] = 0.5  # textureless
    mask = torch.zeros(2, 1, 80, 80, dtype=torch.bool)
    mask[:, :, :, :40] = True
    kp = detect_surf_keypoints(image, SurfConfig(metric_threshold=50.0), mask)
    assert kp.valid[0].any() and torch.all(kp.xy[0][kp.valid[0]][:, 0] <= 40.0 + 1.0)
    assert not kp.valid[1].any()
    assert detect_surf_keypoints(image, SurfConfig(max_keypoints=0)).xy.shape == (2, 0, 2)
    blank = extract_surf_features(torch.full((2, 1, 80, 80), 0.3))  # no keypoint in the whole batch
    assert not blank.keypoints.valid.any() and blank.descriptors.shape == (2, 512, 64)
    assert extract_surf_features(torch.full((1, 1, 80, 80), 0.3), SurfConfig(extended=True)).descriptors.shape == \
        (1, 512, 128)


def test_gradients_reach_the_image():
    image = smooth_image(1, 23, 24, 10).requires_grad_()
    # Every input pixel's column of the Jacobian is checked, against 16 fixed random mixtures of the 1 656 outputs
    # instead of each output (one backward pass each): 3 s instead of 14, and a 1 % error in one border pixel's
    # gradient still fails it.
    mixtures = torch.randn(3 * 23 * 24, 16, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    torch.autograd.gradcheck(
        lambda x: hessian_octaves(x, num_octaves=1, num_scale_levels=3)[0].det.flatten(1) @ mixtures, (image,))
    kp = make_keypoints([[11.2, 11.7]], [0.8])
    torch.autograd.gradcheck(lambda x: describe_surf(x, kp), (image,))


def test_upsampled_detection_maps_back_to_input_pixels():
    # A bright square blob: detected at its centre and at a scale proportional to its size, either way.
    image = torch.full((1, 1, 64, 64), 0.2, dtype=torch.float64)
    image[..., 28:37, 20:29] = 0.9  # 9×9 blob centred at (24, 32)
    for upsample in (False, True):
        kp = detect_surf_keypoints(image, SurfConfig(metric_threshold=500.0, upsample=upsample, max_keypoints=1))
        assert bool(kp.valid[0, 0]) and int(kp.laplacian_sign[0, 0]) == -1  # bright blob: negative trace
        torch.testing.assert_close(kp.xy[0, 0], torch.tensor([24.0, 32.0], dtype=torch.float64), atol=0.3, rtol=0)
        assert 2.0 < float(kp.scale[0, 0]) < 4.5


def test_compiled_detector_gives_identical_keypoints():
    # Two octaves (the first and a strided one): each octave's shapes are one more compile, 15 s for three.
    image = smooth_image(2, 60, 80, 11, torch.float32)
    config = SurfConfig(metric_threshold=80.0, max_keypoints=100, num_octaves=2)
    eager = detect_surf_keypoints(image, config)
    compiled = detect_surf_keypoints(image, dataclasses.replace(config, compiled=True))
    assert torch.equal(eager.valid, compiled.valid)
    torch.testing.assert_close(eager.xy, compiled.xy, atol=1e-5, rtol=0)


def test_errors_name_the_argument():
    with pytest.raises(InputError, match="num_scale_levels: expected an integer from 3 to 8, got 2"):
        SurfConfig(num_scale_levels=2)
    # Limits against a mistyped setting asking for gigabytes (tests/test_hardening.py).
    with pytest.raises(InputError, match="num_octaves: expected an integer from 1 to 6, got 7"):
        SurfConfig(num_octaves=7)
    with pytest.raises(InputError, match="max_keypoints: expected an integer from 0 to 10000, got 99999999999999"):
        SurfConfig(max_keypoints=99999999999999)
    with pytest.raises(InputError, match="metric_threshold: expected a non-negative number"):
        SurfConfig(metric_threshold=-1.0)
    with pytest.raises(InputError, match=r"image: expected \(B, 1, H, W\)"):
        detect_surf_keypoints(torch.rand(1, 3, 40, 40))
    with pytest.raises(InputError, match=r"mask: expected \(1, 1, 40, 40\), got \(1, 1, 40, 41\)"):
        detect_surf_keypoints(torch.rand(1, 1, 40, 40), mask=torch.ones(1, 1, 40, 41, dtype=torch.bool))
    kp = make_keypoints([[1.0, 1.0]], [1.2])
    with pytest.raises(InputError, match=r"keypoints.xy: expected \(2, K, 2\)"):
        describe_surf(torch.rand(2, 1, 20, 20), kp)
    # Found by an audit of the library called by hand: None or a tuple of the fields raised AttributeError on .xy.
    for keypoints in (None, tuple(vars(kp).values())):
        with pytest.raises(InputError, match=f"^keypoints: expected a Keypoints, got {type(keypoints).__name__}$"):
            describe_surf(torch.rand(1, 1, 20, 20), keypoints)


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_orientation_and_descriptors_refuse_a_non_finite_image(bad):
    """Was: surf_orientation failed in scatter_add ("index -9223372036854775808 is out of bounds"), and
    describe_surf gave every valid keypoint an all-zero descriptor, in silence."""
    image = torch.rand(1, 1, 20, 20, generator=torch.Generator().manual_seed(0))
    image[0, 0, 3, 4] = bad
    kp = make_keypoints([[10.0, 10.0]], [1.2])
    for describe in (surf_orientation, describe_surf):
        with pytest.raises(InputError, match=r"image: expected finite values \(NaN or inf found\)"):
            describe(image, kp)


def test_box_and_cell_means_name_coordinates_of_another_dtype():
    # float64 centres on a float32 table raised torch.lerp's "expected dtype float for `weight` but got dtype
    # double"; a (B, P) centre tensor failed unpacking its last dimension.
    image = torch.rand(2, 1, 20, 20, generator=torch.Generator().manual_seed(0))
    integral = padded_integral_image(image, 4, subtract_mean=False)
    centres, half = torch.full((2, 3, 2), 9.5), torch.full((2, 3), 2.0)
    means = sample_box_means(integral, centres, half)
    torch.testing.assert_close(means[:, 0], image[:, 0, 8:12, 8:12].mean(dim=(1, 2)))
    with pytest.raises(InputError, match="center_xy: expected a tensor of the integral's dtype torch.float32, got "
                                         "torch.float64"):
        sample_box_means(integral, centres.double(), half.double())
    with pytest.raises(InputError, match="half_width: expected a tensor of the integral's dtype torch.float32"):
        sample_box_means(integral, centres, 2.0)
    with pytest.raises(InputError, match=r"center_xy: expected \(2, P, 2\), got \(2, 3\)"):
        sample_box_means(integral, half, half)
    edges = torch.tensor([[7.5, 9.5, 11.5]])
    with pytest.raises(InputError, match="x_edges: expected a tensor of the integral's dtype torch.float32"):
        sample_cell_means(integral, torch.tensor([0]), edges.double(), edges)
    assert sample_cell_means(integral, torch.tensor([0]), edges, edges).shape == (1, 2, 2)


def test_real_pair_matches_mostly_at_the_true_disparity(data_dir):
    from svs_torch.data import load_middlebury_eval3, resize_stereo_batch

    batch = resize_stereo_batch(load_middlebury_eval3(data_dir / "middlebury_eval3_Q" / "Teddy"), (320, 240))
    left, right = extract_surf_features(batch.left), extract_surf_features(batch.right)
    lv, rv = left.keypoints.valid[0], right.keypoints.valid[0]
    distance = torch.cdist(left.descriptors[0][lv][None], right.descriptors[0][rv][None], p=1)[0]
    best = torch.topk(distance, 2, dim=1, largest=False)
    keep = best.values[:, 0] < 0.6 * best.values[:, 1]  # MATLAB matchFeatures MaxRatio
    lxy, rxy = left.keypoints.xy[0][lv][keep], right.keypoints.xy[0][rv][best.indices[keep, 0]]
    cols, rows = lxy[:, 0].round().long(), lxy[:, 1].round().long()
    gt, known = batch.disparity_px[0, 0, rows, cols], batch.disparity_valid[0, 0, rows, cols]
    correct = ((lxy[:, 0] - rxy[:, 0]) - gt).abs() <= 1.0
    assert int(known.sum()) >= 40
    assert float(correct[known].float().mean()) >= 0.6  # measured 0.6–0.8 on this pair; SIFT gets ~0.75


@pytest.mark.parametrize("upright", [True, False])
def test_features_in_cache_blocks_equal_one_batch(monkeypatch, upright):
    """extract_surf_features over blocks of images: the keypoints of one batch, padded to one K (zero / False
    rows); orientations and descriptors equal bit for bit."""
    import svs_torch.features.surf as features_module
    from svs_torch.data.synthetic import random_obstacle_scenes

    scenes = random_obstacle_scenes(6, 2, size_wh=(160, 120), generator=torch.Generator().manual_seed(2)).batch
    images = torch.cat([scenes.left, scenes.right, torch.full_like(scenes.left[:1], 0.5)])  # 13, one blank
    config = SurfConfig(metric_threshold=100, upright=upright)
    monkeypatch.setattr(features_module, "BLOCK_IMAGES", 1000)
    whole = extract_surf_features(images, config, images > 0.2)
    monkeypatch.setattr(features_module, "BLOCK_IMAGES", 4)
    blocked = extract_surf_features(images, config, images > 0.2)
    for name in ("xy", "scale", "score", "laplacian_sign", "valid"):  # the detector does not see the batch
        assert torch.equal(getattr(blocked.keypoints, name), getattr(whole.keypoints, name)), name
    assert torch.equal(blocked.keypoints.orientation, whole.keypoints.orientation)
    assert not blocked.keypoints.valid[-1].any() and blocked.descriptors[-1].eq(0).all()
    assert torch.equal(blocked.descriptors, whole.descriptors)



def test_blocked_images_are_ranged_once_and_a_bad_one_is_named_in_the_whole_batch(monkeypatch):
    """More images than a block: one range scan of the whole batch (each block's detection and description had
    scanned its images twice), and an image out of range is named by its place in the batch, not in its block."""
    import svs_torch.features.surf as features_module

    monkeypatch.setattr(features_module, "BLOCK_IMAGES", 4)
    images = torch.rand(10, 1, 40, 50, generator=torch.Generator().manual_seed(3))
    scanned = []
    aminmax = torch.aminmax
    monkeypatch.setattr(torch, "aminmax", lambda tensor, *args, **kwargs: scanned.append(tuple(tensor.shape))
                        or aminmax(tensor, *args, **kwargs))
    extract_surf_features(images, SurfConfig(upright=False))
    assert scanned.count((10, 1, 40, 50)) == 1 and not [s for s in scanned if s[1:] == (1, 40, 50) and s[0] < 10]
    for value, said in ((float("nan"), "got NaN"), (1.5, "got min .*, max 1.5")):
        bad = images.clone()
        bad[9, 0, 3, 3] = value
        with pytest.raises(InputError, match=rf"^image: expected values in \[0, 1\], {said} \(image 9 of 10\)"):
            extract_surf_features(bad)

@pytest.mark.parametrize("path", ["kernel", "float64", "rotated"])
def test_real_views_features_do_not_depend_on_the_batch(data_dir, path):
    """Issue 29: six real views at 320×240, batched and one at a time, with two threads (torch splits a mean over
    a large image across threads by the tensor's shape, and a batch's border is as wide as its largest keypoint
    needs): the same keypoints and descriptors bit for bit, on the C kernel's path and the torch path."""
    from svs_torch.data import load_stereo_pair, resize_stereo_batch

    scenes = sorted((data_dir / "middlebury_eval3_Q").iterdir())[:6]
    images = torch.cat([resize_stereo_batch(load_stereo_pair(s), (320, 240)).left for s in scenes])
    images = images.double() if path == "float64" else images
    config = SurfConfig(metric_threshold=100.0, upright=path != "rotated")
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        whole = extract_surf_features(images, config)
        for i in range(len(scenes)):
            alone = extract_surf_features(images[i:i + 1], config)
            k = alone.keypoints.xy.shape[1]
            assert torch.equal(alone.keypoints.xy, whole.keypoints.xy[i:i + 1, :k]), f"{path}: view {i}"
            assert torch.equal(alone.descriptors, whole.descriptors[i:i + 1, :k]), f"{path}: view {i}"
    finally:
        torch.set_num_threads(threads)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_no_image_gives_no_features(dtype):
    """An empty batch (a block of a list with no pair of its size) gives empty features: the per-image means of no
    image are no values (a reshape to (0, -1) would fail)."""
    features = extract_surf_features(torch.zeros(0, 1, 40, 50, dtype=dtype))
    assert features.descriptors.shape[0] == 0 and features.keypoints.valid.shape[0] == 0
