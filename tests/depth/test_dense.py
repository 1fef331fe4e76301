"""Dense SAD block matching: a float64 per-pixel loop reference, OpenCV's StereoBM, real ground truth, the
region crop, batching, the soft-argmin variant (gradcheck) and bad input."""

from __future__ import annotations

import shutil
from dataclasses import replace

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from svs_torch import InputError
from svs_torch.core import kernels
from svs_torch.data import load_middlebury_eval3, resize_stereo_batch
from svs_torch.depth.block_matching import block_match_sad, dense_disparity_over_regions, fill_invalid_rows
from svs_torch.depth.cost_volume import prefilter_xsobel, quantize_levels, wanted_pixels
from svs_torch.depth.dense import estimate_dense_disparity, working_window
from svs_torch.depth.dense_config import DenseConfig, DisparityRange
from svs_torch.depth.search_range import coarse_search_range, disparity_search_range
from svs_torch.depth.soft_dense import soft_block_match
from svs_torch.segmentation.segment import segment_stereo

F64 = torch.float64


def reference_block_match(left: np.ndarray, right: np.ndarray, min_d: int, num_d: int,
                          config: DenseConfig) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel loops over one (H, W) float64 pair, written from the module docstring."""
    h, w = left.shape
    cap, r = config.prefilter_cap, config.window_size // 2

    def sobel(image):
        p = np.pad(image, 1, mode="edge")
        out = np.zeros_like(image)
        for y in range(h):
            for x in range(w):
                win = p[y:y + 3, x:x + 3]
                out[y, x] = (win[:, 2] - win[:, 0]) @ np.array([1.0, 2.0, 1.0])
        return np.clip(out, -cap, cap)

    sob_l, sob_r = sobel(left), sobel(right)
    fl, fr = (sob_l, sob_r) if config.prefilter == "xsobel" else (left, right)
    fl, fr = np.round(fl * 255), np.round(fr * 255)  # matched in whole 1/255 steps, as StereoBM's uint8

    def pixel(image, y, x):
        return image[min(max(y, 0), h - 1), min(max(x, 0), w - 1)]

    def cost(y, x, d):
        if not 0 <= x - d < w:
            return np.inf
        return sum(abs(pixel(fl, y + dy, x + dx) - pixel(fr, y + dy, x + dx - d))
                   for dy in range(-r, r + 1) for dx in range(-r, r + 1))

    costs = np.array([[[cost(y, x, min_d + k) for k in range(num_d)] for x in range(w)] for y in range(h)])
    best = costs.argmin(-1)
    disparity, valid = np.zeros((h, w)), np.zeros((h, w), bool)
    for y in range(h):
        for x in range(w):
            c, k = costs[y, x], best[y, x]
            ok = np.isfinite(c[k]) and k < num_d - 1 and (k > 0 or min_d <= 0)
            if config.uniqueness_ratio > 0:
                rivals = [c[j] for j in range(num_d) if abs(j - k) > 1]
                ok &= all(v > (1 + config.uniqueness_ratio) * c[k] for v in rivals)
            if config.lr_max_diff_px is not None:  # the right view's winner at x_r = x − d
                xr = x - (min_d + k)
                right_costs = [costs[y, xr + min_d + j, j] if 0 <= xr + min_d + j < w else np.inf
                               for j in range(num_d)]
                ok &= 0 <= xr and abs(int(np.argmin(right_costs)) - k) <= config.lr_max_diff_px
            if config.texture_threshold > 0:
                texture = sum(abs(pixel(sob_l, y + dy, x + dx)) for dy in range(-r, r + 1) for dx in range(-r, r + 1))
                ok &= texture >= config.texture_threshold * config.window_size ** 2
            offset = 0.0
            if 0 < k < num_d - 1 and np.isfinite(c[k - 1]) and np.isfinite(c[k + 1]):
                rise = 2 * (max(c[k - 1], c[k + 1]) - c[k])
                offset = float(np.clip((c[k - 1] - c[k + 1]) / rise, -0.5, 0.5)) if rise > 0 else 0.0
            if config.whole_range_in_view:  # the largest disparity searched lands inside the right image
                ok &= x >= min_d + num_d - 1
            valid[y, x] = ok
            disparity[y, x] = min_d + k + offset if ok else 0.0
    return disparity, valid


@pytest.mark.parametrize("config", [
    DenseConfig(window_size=3),
    DenseConfig(window_size=5, prefilter="none", uniqueness_ratio=0.0, lr_max_diff_px=None, texture_threshold=0.0),
    DenseConfig(window_size=3, uniqueness_ratio=0.3, lr_max_diff_px=0.0, texture_threshold=0.05),
    DenseConfig(window_size=3, whole_range_in_view=True),
], ids=["default-rules", "raw-no-rules", "strict", "whole-range-in-view"])
def test_batched_equals_float64_loop_reference(config, generator):
    base = torch.rand(2, 1, 9, 18, generator=generator, dtype=F64)
    shifted = torch.roll(base, shifts=-3, dims=-1)  # the right view: x_r = x − 3
    right = (0.9 * shifted + 0.1 * torch.rand(2, 1, 9, 18, generator=generator, dtype=F64)).clamp(0, 1)
    minimum = torch.tensor([1, 0])
    result = block_match_sad(base, right, minimum, 6, config)
    for i in range(2):
        disparity, valid = reference_block_match(base[i, 0].numpy(), right[i, 0].numpy(), int(minimum[i]), 6, config)
        assert result.valid[i, 0].numpy().tolist() == valid.tolist()
        np.testing.assert_allclose(result.disparity_px[i, 0].numpy(), disparity, atol=1e-9)
    assert result.valid.any()


@pytest.fixture(scope="module")
def teddy(data_dir):
    return resize_stereo_batch(load_middlebury_eval3(data_dir / "middlebury_eval3_Q" / "Teddy"), (320, 267))


def test_agrees_with_opencv_stereobm(teddy):
    """Same inputs, window 9, 32 disparities, every rejection off on both sides: OpenCV's integer SAD and
    fixed-point sub-pixel (1/16 px) differ from ours only in rounding."""
    left = (teddy.left[0, 0] * 255).round().to(torch.uint8).numpy()
    right = (teddy.right[0, 0] * 255).round().to(torch.uint8).numpy()
    matcher = cv2.StereoBM_create(numDisparities=32, blockSize=9)
    for setter, value in (("setUniquenessRatio", 0), ("setTextureThreshold", 0), ("setSpeckleWindowSize", 0),
                          ("setDisp12MaxDiff", -1)):
        getattr(matcher, setter)(value)
    theirs = matcher.compute(left, right).astype(np.float32) / 16
    config = DenseConfig(window_size=9, uniqueness_ratio=0.0, texture_threshold=0.0, lr_max_diff_px=None)
    as_float = [torch.from_numpy(image).float()[None, None] / 255 for image in (left, right)]
    ours = block_match_sad(*as_float, 0, 32, config)
    both = ours.valid[0, 0].numpy() & (theirs >= 0)
    assert both.mean() > 0.8
    within = np.abs(ours.disparity_px[0, 0].numpy() - theirs)[both] <= 1
    assert within.mean() >= 0.95  # measured 0.997


def test_default_rules_against_ground_truth(teddy):
    """With the default rejections most surviving pixels are right, and more are right than without them."""
    seg = segment_stereo(teddy)
    search = DisparityRange(torch.tensor([0]), 64)
    gt, known = teddy.disparity_px, teddy.disparity_valid & seg.left.kept_mask

    def bad1(config):
        dense = dense_disparity_over_regions(teddy.left, teddy.right, seg.left.kept_mask, search, config)
        used = dense.valid & known
        return float(((dense.disparity_px - gt).abs()[used] > 1).float().mean()), float(used.sum() / known.sum())

    strict, kept = bad1(DenseConfig())
    loose, _ = bad1(DenseConfig(uniqueness_ratio=0.0, lr_max_diff_px=None, texture_threshold=0.0))
    assert strict < 0.12 and strict < loose and kept > 0.6  # measured 0.07 / 0.17, 77 % kept


@pytest.mark.parametrize("kernel", ["auto", "torch"])
def test_region_crop_equals_the_whole_frame_where_wanted(teddy, kernel):
    """Only the pixels near the mask along their row are computed (wanted_pixels), each with the value a
    whole-frame match gives it; the rest of the frame and of the box stays invalid."""
    seg = segment_stereo(teddy)
    mask = seg.left.kept_mask.clone()
    mask[..., :, :100] = False  # a box that does not start at the image border
    mask[..., 60:80, 200:] = False  # rows whose span is narrower than the box
    search = DisparityRange(torch.tensor([5]), 30)
    config = DenseConfig(kernel=kernel)
    cropped = dense_disparity_over_regions(teddy.left, teddy.right, mask, search, config)
    whole = block_match_sad(teddy.left, teddy.right, search.min_disparity_px, 30, config)
    x0, y0, width, height = cropped.crop_xywh[0].tolist()
    assert x0 >= 100 - config.margin_px and width < 320 - 90
    wanted = wanted_pixels(mask, config.margin_px)
    in_box = torch.zeros_like(wanted)
    in_box[..., y0:y0 + height, x0:x0 + width] = True
    assert (in_box & ~wanted).sum() > 1000  # the rule leaves out part of the box
    assert torch.equal(cropped.valid, whole.valid & wanted & in_box) and cropped.valid.sum() > 5000
    torch.testing.assert_close(cropped.disparity_px[cropped.valid], whole.disparity_px[cropped.valid])
    assert not cropped.disparity_px[~cropped.valid].any()


def test_wanted_pixels_are_each_rows_mask_span_and_margin():
    mask = torch.zeros(1, 1, 3, 12, dtype=torch.bool)
    mask[0, 0, 0, [4, 6]] = True
    mask[0, 0, 2, 0] = True
    expected = torch.tensor([[0, 0, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0], [0] * 12, [1, 1, 1] + [0] * 9], dtype=torch.bool)
    assert torch.equal(wanted_pixels(mask, 2)[0, 0], expected)


def test_batched_equals_per_pair_with_padding_and_own_ranges(teddy, generator):
    """A pair's result does not depend on its batch: not on the shared crop size, nor on the batch's widest
    disparity range, nor on the padding of a smaller pair."""
    other = torch.rand(1, 1, 267, 320, generator=generator)
    left, right = torch.cat([teddy.left, other]), torch.cat([teddy.right, other.roll(-4, -1)])
    mask = torch.zeros_like(left, dtype=torch.bool)
    mask[0, :, 100:200, 40:300] = True
    mask[1, :, 20:120, 10:90] = True
    hw = torch.tensor([[267, 320], [200, 300]])
    search = DisparityRange(torch.tensor([3, 0]), 40, torch.tensor([40, 12]))
    both = dense_disparity_over_regions(left, right, mask, search, DenseConfig(), hw)
    for i in range(2):
        own = DisparityRange(search.min_disparity_px[i:i + 1], int(search.pair_num_disparities[i]),
                             search.pair_num_disparities[i:i + 1])
        single = dense_disparity_over_regions(left[i:i + 1], right[i:i + 1], mask[i:i + 1], own, DenseConfig(),
                                              hw[i:i + 1])
        assert torch.equal(single.valid[0], both.valid[i]) and single.valid.any()
        torch.testing.assert_close(single.disparity_px[0], both.disparity_px[i])
        assert torch.equal(single.crop_xywh[0], both.crop_xywh[i])
    assert not both.valid[1, :, 200:].any() and not both.valid[1, :, :, 300:].any()
    assert float(both.disparity_px[1][both.valid[1]].max()) <= 11  # its own 12 disparities, not the batch's 40


def test_coarse_range_covers_the_truth(teddy):
    seg = segment_stereo(teddy)
    search = coarse_search_range(teddy.left, teddy.right, seg.left.kept_mask, teddy.image_hw)
    known = teddy.disparity_px[teddy.disparity_valid & seg.left.kept_mask]
    low, high = torch.quantile(known, torch.tensor([0.02, 0.98])).tolist()
    first = int(search.min_disparity_px[0])
    assert first <= low and first + search.num_disparities - 1 >= high
    assert search.num_disparities <= 48  # far narrower than the 80-disparity fallback at 320 px


def test_search_range_from_samples():
    values = torch.tensor([[10.0, 12.0, 20.0, 0.0], [0.0, 0.0, 0.0, 0.0]])
    valid = torch.tensor([[True, True, True, False], [False] * 4])
    config = DenseConfig(range_percentiles=(0.0, 100.0), range_margin_px=2.0, range_margin_fraction=0.1,
                         min_range_inliers=3)
    search = disparity_search_range(values, valid, torch.tensor([320, 320]), config)
    assert search.min_disparity_px.tolist() == [8, 0]  # 10 − 2; the second pair falls back to [0, 80)
    assert search.num_disparities == 81


@pytest.mark.parametrize("disparity, image_w, expected", [
    # A (B, 1) width broadcast the pair's range to (B, B) in silence.
    (torch.full((2, 5), 4.0), torch.tensor([[320], [320]]), r"^image_w: expected \(2\), got \(2, 1\)"),
    (torch.full((2, 5), 4.0), torch.full((2,), 320 + 0j), "^image_w: expected an? int"),  # deep RuntimeError
    (torch.full((2, 5), 4.0 + 0j), torch.tensor([320, 320]), "^disparity_px: expected"),  # imaginary part dropped
])
def test_the_search_range_names_a_width_or_samples_of_another_kind(disparity, image_w, expected):
    with pytest.raises(InputError, match=expected):
        disparity_search_range(disparity, torch.ones(disparity.shape, dtype=torch.bool), image_w)


def test_fill_invalid_rows():
    disparity = torch.tensor([[5.0, 0.0, 5.5, 0.0, 0.0, 9.0, 0.0]])
    valid = torch.tensor([[True, False, True, False, False, True, False]])
    filled, reachable = fill_invalid_rows(disparity, valid)
    # 5 and 5.5 agree (mean); 5.5 and 9 disagree (the background, the smaller); the end has one side only.
    assert filled.tolist() == [[5.0, 5.25, 5.5, 5.5, 5.5, 9.0, 9.0]] and reachable.all()
    empty, none = fill_invalid_rows(torch.zeros(1, 3), torch.zeros(1, 3, dtype=torch.bool))
    assert not none.any() and not empty.any()


@pytest.mark.parametrize("grad", [False, True], ids=["kernel", "torch"])
@pytest.mark.parametrize("disparity, valid, expected", [
    (torch.ones(1, 3), torch.ones(1, 3), "^valid: expected a bool tensor"),  # where(): "expected ... boolean"
    (torch.ones(1, 3), torch.ones(1, 1, dtype=torch.bool), r"^valid: expected \(1, 3\)"),  # broadcast in silence
    (torch.ones(1, 3, dtype=torch.complex64), torch.ones(1, 3, dtype=torch.bool), "^disparity: expected"),
    (torch.ones(1, 3, dtype=torch.bool), torch.ones(1, 3, dtype=torch.bool), "^disparity: expected"),
])
def test_fill_invalid_rows_names_a_bad_argument_on_both_paths(disparity, valid, expected, grad):
    """Its checks were the C kernel's alone: the torch path (a disparity that requires grad, or a dtype the kernel
    does not take) raised from deep inside torch or broadcast a valid of another shape."""
    if grad and disparity.is_floating_point():
        disparity = disparity.clone().requires_grad_()
    with pytest.raises(InputError, match=expected):
        fill_invalid_rows(disparity, valid)


def test_soft_block_match_gradcheck_and_low_temperature_limit(generator):
    left = torch.rand(1, 1, 6, 10, generator=generator, dtype=F64, requires_grad=True)
    right = torch.rand(1, 1, 6, 10, generator=generator, dtype=F64, requires_grad=True)
    config = DenseConfig(window_size=3, prefilter="none")
    assert torch.autograd.gradcheck(lambda a, b: soft_block_match(a, b, 0, 4, 0.05, config), (left, right))
    sobel = DenseConfig(window_size=3)
    assert torch.autograd.gradcheck(lambda a, b: soft_block_match(a, b, 1, 3, 0.1, sobel), (left, right))
    cold = soft_block_match(left.detach(), right.detach(), 0, 4, 1e-6, replace(config, lr_max_diff_px=None))
    hard = block_match_sad(left.detach(), right.detach(), 0, 4, replace(
        config, uniqueness_ratio=0.0, lr_max_diff_px=None, texture_threshold=0.0))
    integer = (hard.disparity_px - hard.disparity_px.round()).abs() < 1e-12  # no sub-pixel shift applied
    assert integer.any()
    torch.testing.assert_close(cold[hard.valid & integer], hard.disparity_px[hard.valid & integer])


def test_soft_block_match_gives_a_pair_alone_its_value_in_a_batch(generator):
    """torch.softmax over the disparities (dim 1) splits B·H·W into vectorised runs and a scalar tail whose
    exp rounds differently, so at some sizes (here 9 × 14) a pair's disparity and gradient moved by an ulp with
    the other pairs of its batch (an audit): now each pair's softmax is its own call."""
    left = torch.rand(4, 1, 9, 14, generator=generator, requires_grad=True)
    right = torch.rand(4, 1, 9, 14, generator=generator, requires_grad=True)
    config = DenseConfig(window_size=3)
    batched = soft_block_match(left, right, 0, 4, 0.5, config)
    grads = torch.autograd.grad(batched.sum(), (left, right), create_graph=True)
    for index in range(4):
        one = (left[index:index + 1], right[index:index + 1])
        alone = soft_block_match(*one, 0, 4, 0.5, config)
        assert torch.equal(alone, batched[index:index + 1])
        for got, want in zip(torch.autograd.grad(alone.sum(), one, create_graph=True), grads):
            assert torch.equal(got, want[index:index + 1])


def test_soft_block_match_second_derivatives_are_the_true_ones(generator):
    """Found by an audit: the hand-written backward ran without a graph, so create_graph=True gave a second
    derivative of zero in silence (a gradient penalty through the soft-argmin trained on nothing). With
    create_graph the backward is taken op by op: gradgradcheck, and the op-by-op reference's Hessian-vector
    product; a temperature that asks for a gradient is refused (none flows to it). 4 x 8 views (a gradgradcheck's
    cost grows with the inputs: 6 x 10 took twice as long): rows at both borders and inside, columns where some of
    the 4 disparities fall outside the right view and where none does."""
    left = torch.rand(1, 1, 4, 8, generator=generator, dtype=F64, requires_grad=True)
    right = torch.rand(1, 1, 4, 8, generator=generator, dtype=F64, requires_grad=True)
    for config in (DenseConfig(window_size=3, prefilter="none"), DenseConfig(window_size=3)):
        assert torch.autograd.gradgradcheck(lambda a, b: soft_block_match(a, b, 0, 4, 0.1, config), (left, right))
        squared = []
        for run in (lambda a, b: soft_block_match(a, b, torch.tensor([0]), 4, 0.1, config),
                    lambda a, b: _soft_block_match_op_by_op(a, b, torch.tensor([0]), 4, 0.1, config)):
            first, = torch.autograd.grad(run(left, right).sum(), left, create_graph=True)
            squared.append(torch.autograd.grad((first ** 2).sum(), right)[0])
        assert squared[0].abs().sum() > 0
        torch.testing.assert_close(squared[0], squared[1])
    with pytest.raises(InputError, match="temperature: expected a number; no gradient flows to it"):
        soft_block_match(left, right, 0, 4, torch.tensor(0.1, requires_grad=True))


def _soft_block_match_op_by_op(left, right, minimum, count, temperature, config):
    """The soft-argmin written the plain way, every op recorded by autograd: a reference for the hand-written
    backward of :func:`soft_block_match` (replicate borders, costs as window means, no weight outside the image)."""
    size, (h, w) = config.window_size, left.shape[-2:]
    images = [prefilter_xsobel(image, config.prefilter_cap) if config.prefilter == "xsobel" else image
              for image in (left, right)]
    r = size // 2
    left_p, right_p = (F.pad(image, (r, r, r, r), mode="replicate") for image in images)
    weights_by_pair = []
    for pair, low in enumerate(minimum.tolist()):
        costs, inside = [], []
        for index in range(count):
            shift = low + index
            columns = (torch.arange(w + 2 * r) - shift).clamp(0, w - 1 + 2 * r)
            difference = (left_p[pair, 0] - right_p[pair, 0][:, columns]).abs()
            costs.append(F.avg_pool2d(difference[None, None], size, stride=1)[0, 0])
            inside.append((torch.arange(w) - shift >= 0).expand(h, w))
        logits = torch.where(torch.stack(inside), -torch.stack(costs) / temperature, -torch.inf)
        weights = torch.softmax(logits, dim=0)
        weights_by_pair.append((weights * (low + torch.arange(count, dtype=left.dtype)).view(-1, 1, 1)).sum(0))
    return torch.stack(weights_by_pair)[:, None]


def test_soft_block_match_backward_equals_the_op_by_op_one(teddy):
    # The hand-written backward (one disparity at a time) against autograd's own, on a real crop in float64.
    left = teddy.left[:1, :, 100:130, 200:260].double().requires_grad_()
    right = teddy.right[:1, :, 100:130, 180:240].double().requires_grad_()
    left2, right2 = (t.detach().clone().requires_grad_() for t in (left, right))
    config, minimum = DenseConfig(window_size=7), torch.tensor([3])
    ours = soft_block_match(left, right, minimum, 12, 0.003, config)
    reference = _soft_block_match_op_by_op(left2, right2, minimum, 12, 0.003, config)
    torch.testing.assert_close(ours[..., 20:], reference[..., 20:], rtol=0, atol=1e-9)  # every candidate inside
    weight = torch.linspace(0.5, 1.5, 40, dtype=F64)
    (ours[..., 20:] * weight).sum().backward()
    (reference[..., 20:] * weight).sum().backward()
    torch.testing.assert_close(left.grad, left2.grad, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(right.grad, right2.grad, rtol=1e-9, atol=1e-9)


def test_soft_block_match_gradients_reach_both_images(generator):
    left = torch.rand(2, 1, 8, 12, generator=generator, requires_grad=True)
    right = torch.rand(2, 1, 8, 12, generator=generator, requires_grad=True)
    soft_block_match(left, right, torch.tensor([0, 2]), 5, 0.1).sum().backward()
    assert left.grad.abs().sum() > 0 and right.grad.abs().sum() > 0


def test_prefilter_matches_opencv_sobel(teddy):
    image = teddy.left[:, :, :40, :60].double()
    ours = prefilter_xsobel(image, 1e9)[0, 0].numpy()
    theirs = cv2.Sobel(image[0, 0].numpy(), cv2.CV_64F, 1, 0, ksize=3, borderType=cv2.BORDER_REPLICATE)
    np.testing.assert_allclose(ours, theirs, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.int32, torch.int16, torch.uint8])
def test_block_matching_takes_a_narrower_integer_minimum(generator, dtype):
    # An int32 min_disparity_px of zeros was refused with "expected values in (-2^31, 2^31), got [0, 0]": the
    # bound 2^31 wrapped around in the tensor's own dtype.
    left = torch.rand(2, 1, 12, 30, generator=generator)
    right = torch.roll(left, -2, dims=-1)
    expected = block_match_sad(left, right, torch.tensor([0, 1]), 6)
    found = block_match_sad(left, right, torch.tensor([0, 1], dtype=dtype), 6)
    assert torch.equal(found.disparity_px, expected.disparity_px) and torch.equal(found.valid, expected.valid)
    assert torch.equal(soft_block_match(left, right, torch.tensor([0, 1], dtype=dtype), 6, 0.05),
                       soft_block_match(left, right, torch.tensor([0, 1]), 6, 0.05))


@pytest.mark.parametrize("dtype", [torch.uint8, torch.int64, torch.bool, torch.float16])
def test_prefilter_names_an_image_that_is_not_float(dtype):
    # uint8 / int64 raised torch's "result type Float can't be cast to the desired output type", bool a
    # NotImplementedError of replication_pad2d.
    with pytest.raises(InputError, match=f"image: expected a float.* tensor, got {dtype}"):
        prefilter_xsobel(torch.ones(1, 1, 6, 8, dtype=dtype), 0.12)
    with pytest.raises(InputError, match=r"image: expected \(B, 1, H, W\), got \(6, 8\)"):
        prefilter_xsobel(torch.ones(6, 8), 0.12)


def test_quantize_levels_refuses_an_integer_image():
    # quantize_levels(uint8 200) gave 56 (255 * 200 wrapped modulo 256) in silence.
    assert quantize_levels(torch.tensor([0.0, 0.5, 1.0])).tolist() == [0.0, 128.0, 255.0]
    for dtype in (torch.uint8, torch.int64, torch.float16):
        with pytest.raises(InputError, match=f"image: expected a float.* tensor, got {dtype}"):
            quantize_levels(torch.full((1, 1, 2, 2), 200).to(dtype))


@pytest.mark.parametrize("kwargs, message", [
    ({"window_size": 4}, "window_size: expected an odd int from 1 to 511"),
    ({"prefilter": "census"}, "prefilter: expected 'xsobel' or 'none'"),
    ({"range_source": "gt"}, "range_source: expected 'coarse' or 'inliers'"),
    ({"lr_max_diff_px": -1.0}, "lr_max_diff_px: expected None or a value >= 0"),
    ({"range_percentiles": (50.0, 10.0)}, r"range_percentiles: expected \(low, high\) with 0 <= low <= high <= 100"),
    ({"kernel": "gpu"}, "kernel: expected 'auto', 'c' or 'torch'"),
    ({"scale_window": 1}, "scale_window: expected a bool"),
])
def test_config_errors(kwargs, message):
    with pytest.raises(InputError, match=message):
        DenseConfig(**kwargs)


def test_a_bool_number_of_disparities_is_refused():
    """True is an int to isinstance: block_match_sad and soft_block_match searched one disparity in silence."""
    image = torch.rand(1, 1, 8, 8)
    for match in (lambda n: block_match_sad(image, image, 0, n), lambda n: soft_block_match(image, image, 0, n, 1.0),
                  lambda n: dense_disparity_over_regions(image, image, torch.ones(1, 1, 8, 8, dtype=torch.bool),
                                                         DisparityRange(torch.tensor([0]), n))):
        with pytest.raises(InputError, match=r"^num_disparities: expected an int in \[1, 65534\], got True$"):
            match(True)


def test_argument_errors():
    image = torch.rand(1, 1, 8, 8)
    with pytest.raises(InputError, match=r"right: expected the shape of left"):
        block_match_sad(image, torch.rand(1, 1, 8, 9), 0, 4)
    with pytest.raises(InputError, match=r"num_disparities: expected an int in \[1, 65534\]"):
        block_match_sad(image, image, 0, 0)
    with pytest.raises(InputError, match=r"min_disparity_px: expected \(1\)"):
        block_match_sad(image, image, torch.tensor([0, 1]), 4)
    # Found by an audit of the differentiable API: these failed inside torch.as_tensor or a meta tensor's copy.
    for bad, shown in (("a", "'a'"), (None, "None"), (torch.tensor([0], device="meta"), "a meta-device tensor")):
        for match in (lambda m: block_match_sad(image, image, m, 4), lambda m: soft_block_match(image, image, m, 4, 1.0),
                      lambda m: dense_disparity_over_regions(image, image, torch.ones(1, 1, 8, 8, dtype=torch.bool),
                                                             DisparityRange(m, 4))):
            with pytest.raises(InputError, match=f"^min_disparity_px: expected an int or an int tensor \\(one per "
                                                 f"pair\\), got {shown}$"):
                match(bad)
    assert block_match_sad(image, image, [0], 4).min_disparity_px.tolist() == [0]  # a list of ints, as before
    with pytest.raises(InputError, match="temperature: expected a positive number"):
        soft_block_match(image, image, 0, 4, 0.0)
    with pytest.raises(InputError, match=r"mask: expected \(1, 1, 8, 8\)"):
        dense_disparity_over_regions(image, image, torch.ones(1, 1, 8, 9, dtype=torch.bool),
                                     DisparityRange(torch.tensor([0]), 4))
    # Found by an audit: a plain (min, count) tuple failed with "'tuple' object has no attribute ...".
    with pytest.raises(InputError, match=r"^search: expected a DisparityRange, got tuple$"):
        dense_disparity_over_regions(image, image, torch.ones(1, 1, 8, 8, dtype=torch.bool), (0, 4))


def test_views_of_two_dtypes_are_refused_by_every_dense_entry():
    """A library user's audit: estimate_dense_disparity took a float64 left view with a float32 right one, its map
    in the left view's dtype and its values 1e-6 apart with the views' order swapped; a StereoBatch already refused
    such a pair, every dense entry now does too."""
    image = torch.rand(1, 1, 16, 16)
    mask = torch.ones(1, 1, 16, 16, dtype=torch.bool)
    calls = (lambda l, r: estimate_dense_disparity(l, r, mask), lambda l, r: block_match_sad(l, r, 0, 4),
             lambda l, r: soft_block_match(l, r, 0, 4, 1.0),
             lambda l, r: dense_disparity_over_regions(l, r, mask, DisparityRange(torch.tensor([0]), 4)))
    for call in calls:
        for left, right in ((image.double(), image), (image, image.double())):
            with pytest.raises(InputError, match=f"^right: expected the left view's dtype {left.dtype}, got "
                                                 f"{right.dtype}$"):
                call(left, right)


def test_search_range_per_object_keeps_a_small_far_object():
    """Pooled percentiles cut a small object's disparities as outliers of a big one; per-object groups do not."""
    from svs_torch.depth.search_range import disparity_search_range

    big = torch.full((1, 1000), 30.0) + torch.linspace(-2, 2, 1000)
    small = torch.full((1, 8), 8.0)
    samples = torch.cat([big, small], dim=1)
    valid = torch.ones_like(samples, dtype=torch.bool)
    groups = torch.zeros(1, 2, 1008, dtype=torch.bool)
    groups[0, 0, :1000], groups[0, 1, 1000:] = True, True
    config = DenseConfig(range_percentiles=(1.0, 99.0))
    pooled = disparity_search_range(samples, valid, torch.tensor([320]), config, min_count=5)
    grouped = disparity_search_range(samples, valid, torch.tensor([320]), config, min_count=5, groups=groups)
    assert int(pooled.min_disparity_px[0]) > 8
    low = int(grouped.min_disparity_px[0])
    assert low <= 8 and low + int(grouped.pair_num_disparities[0]) - 1 >= 32
    # A group below min_count is ignored (here: the small one), as is a pair whose groups are all too small.
    too_small = disparity_search_range(samples, valid, torch.tensor([320]), config, min_count=10, groups=groups)
    assert int(too_small.min_disparity_px[0]) > 8
    with pytest.raises(InputError, match="groups"):
        disparity_search_range(samples, valid, torch.tensor([320]), config, groups=groups[:, :, :5])


def _reference_tail_ceiling(values: np.ndarray, bin_px: float, share: float) -> float:
    """Written from the docstring of ``_detached_tail_ceiling``: a loop over the bins of one group."""
    bins = np.floor(values / bin_px).astype(int)
    hist = np.bincount(bins, minlength=bins.max() + 2)
    total, median = len(values), 0
    while hist[:median + 1].sum() < total / 2:
        median += 1
    for k in range(median + 1, len(hist)):
        if hist[k] == 0 and hist[k + 1:].sum() <= share * total:
            return k * bin_px
    return np.inf


def test_in_view_top_leaves_out_a_detached_near_tail_of_wrong_matches():
    """A cluster of wrong coarse matches far above an object's disparities (noisy frames) lifts the 99th
    percentile; with ``in_view_detached_tail_share`` the top the in-view rule allows for leaves out a near tail
    cut off by an empty coarse pixel and holding at most that share, while the range searched keeps it, and a
    tail holding more is kept. The ceilings equal a loop over the bins."""
    from svs_torch.depth.search_range import _detached_tail_ceiling

    generator = torch.Generator().manual_seed(3)
    main = 15 + 2 * torch.randn(2, 950, generator=generator, dtype=F64).clamp(-3, 3)
    tail = torch.tensor([[68.0] * 30 + [84.0] * 20, [68.0] * 25 + [2.0] * 25], dtype=F64)
    samples = torch.cat([main, tail], dim=1)
    valid = torch.ones_like(samples, dtype=torch.bool)
    width = torch.tensor([700, 700])
    plain = disparity_search_range(samples, valid, width, DenseConfig(in_view_detached_tail_share=None), min_count=20,
                                   tail_bin_px=2)
    top = plain.min_disparity_px + plain.pair_num_disparities - 1
    assert plain.in_view_top_px is None and (top >= 68).all()
    config = DenseConfig()  # the default: 0.1
    trimmed = disparity_search_range(samples, valid, width, config, min_count=20, tail_bin_px=2)
    assert torch.equal(trimmed.min_disparity_px, plain.min_disparity_px)  # the same range searched
    assert torch.equal(trimmed.pair_num_disparities, plain.pair_num_disparities)
    assert (trimmed.in_view_top_px < 40).all() and (trimmed.in_view_top_px >= 21).all()  # its own 9-21 px + margin
    kept = disparity_search_range(samples, valid, width, replace(config, in_view_detached_tail_share=0.01),
                                  min_count=20, tail_bin_px=2)
    assert torch.equal(kept.in_view_top_px, top)  # tails of 2–3 % > 1 %: kept
    # Without the coarse grid (sparse inliers) nothing is trimmed; one group is the pair.
    assert disparity_search_range(samples, valid, width, config, min_count=20).in_view_top_px is None
    grouped = disparity_search_range(samples, valid, width, config, min_count=20, groups=valid.unsqueeze(1),
                                     tail_bin_px=2)
    assert torch.equal(grouped.in_view_top_px, trimmed.in_view_top_px)
    values = torch.cat([torch.randint(0, 60, (3, 40), generator=generator),
                        torch.randint(20, 30, (3, 400), generator=generator)], dim=1).to(F64) + 0.5
    inside = torch.rand(3, 2, 440, generator=generator) < 0.5
    ceiling = _detached_tail_ceiling(values, inside, 2.0, 0.06)
    for b in range(3):
        for g in range(2):
            assert float(ceiling[b, g]) == _reference_tail_ceiling(values[b][inside[b, g]].numpy(), 2.0, 0.06)
    with pytest.raises(InputError, match="in_view_detached_tail_share"):
        DenseConfig(in_view_detached_tail_share=0.5)


def _reference_in_view_top(groups: list[np.ndarray], config: DenseConfig, extra_px: float, per_object: bool) -> float:
    """Written from the docstrings of ``DenseConfig.in_view_margin`` and ``_in_view_top`` for groups without a
    detached near tail: each group's nearest-rank percentiles, the margin rule from its own span ("object") or
    from the lowest group's low ("pair"), the highest top."""
    def rank(values, q):
        ordered = np.sort(values)
        return ordered[int(round((len(ordered) - 1) * q))]

    low_q, high_q = (p / 100 for p in config.range_percentiles)
    lows, highs = [rank(g, low_q) for g in groups], [rank(g, high_q) for g in groups]
    bases = lows if per_object else [min(lows)] * len(lows)
    tops = [high + max(config.range_margin_px, config.range_margin_fraction * (high - base)) + extra_px
            for base, high in zip(bases, highs)]
    return float(np.ceil(max(tops)))


def test_in_view_top_takes_each_objects_margin_from_its_own_span():
    """Two kept objects: a near one at 44–52 px and a far one at 20–26 px whose coarse matches hold a 3 % tail of
    wrong far matches at 2–4 px (not detached above its median, so kept). The range searched spans both with the
    margin of that whole span; the in-view top widens each object's top by its own span's margin, so the far
    object's tail no longer lifts it (the near object's 99th percentile 52 px, plus 2 px for the coarse grid and
    the margin: of the whole 3–52 px span, 12 px, "pair": 67; of its own 44–52 px, 2 px, "object": 56), while the
    range searched is 0–67 px either way. Both equal a reference
    written from the docstrings; one group gives the same top either way."""
    generator = torch.Generator().manual_seed(5)
    near = 44 + 8 * torch.rand(600, generator=generator, dtype=F64)
    far = torch.cat([20 + 6 * torch.rand(388, generator=generator, dtype=F64),
                     2 + 2 * torch.rand(12, generator=generator, dtype=F64)])
    samples = torch.cat([near, far]).unsqueeze(0)
    valid = torch.ones_like(samples, dtype=torch.bool)
    groups = torch.zeros(1, 2, 1000, dtype=torch.bool)
    groups[0, 0, :600], groups[0, 1, 600:] = True, True
    width = torch.tensor([320])
    tops = {}
    for margin in ("object", "pair"):
        config = DenseConfig(in_view_margin=margin)
        found = disparity_search_range(samples, valid, width, config, extra_margin_px=2, min_count=20, groups=groups,
                                       tail_bin_px=2)
        expected = _reference_in_view_top([near.numpy(), far.numpy()], config, 2, margin == "object")
        searched_top = int(found.min_disparity_px[0] + found.pair_num_disparities[0] - 1)
        assert int(found.in_view_top_px[0]) == min(expected, searched_top)
        tops[margin] = (int(found.in_view_top_px[0]), found.min_disparity_px, found.pair_num_disparities)
    assert (tops["object"][0], tops["pair"][0]) == (56, 67)
    assert torch.equal(tops["object"][1], tops["pair"][1]) and torch.equal(tops["object"][2], tops["pair"][2])
    one = [disparity_search_range(samples, valid, width, DenseConfig(in_view_margin=m), extra_margin_px=2,
                                  min_count=20, tail_bin_px=2).in_view_top_px for m in ("object", "pair")]
    assert torch.equal(one[0], one[1])
    with pytest.raises(InputError, match="in_view_margin: expected 'object' or 'pair'"):
        DenseConfig(in_view_margin="pairs")


def test_in_view_top_of_each_object():
    """``DenseConfig.in_view_per_object``: each group's own in-view top beside the pair's, equal to the reference
    written from the docstrings for that group alone (near 44–52 px: 56; far 20–26 px with its far tail: its own
    span's margin), capped at the range searched; a group with too few samples gets the pair's top; without groups,
    or with the setting off, none. The range searched and the pair's top are the same either way."""
    generator = torch.Generator().manual_seed(5)
    near = 44 + 8 * torch.rand(600, generator=generator, dtype=F64)
    far = torch.cat([20 + 6 * torch.rand(388, generator=generator, dtype=F64),
                     2 + 2 * torch.rand(12, generator=generator, dtype=F64)])
    samples = torch.cat([near, far, torch.full((5,), 30.0, dtype=F64)]).unsqueeze(0)
    valid = torch.ones_like(samples, dtype=torch.bool)
    groups = torch.zeros(1, 3, 1005, dtype=torch.bool)
    groups[0, 0, :600], groups[0, 1, 600:1000], groups[0, 2, 1000:] = True, True, True  # the third: 5 < 20 samples
    width, config = torch.tensor([320]), DenseConfig()
    assert config.in_view_per_object
    found = disparity_search_range(samples, valid, width, config, extra_margin_px=2, min_count=20, groups=groups,
                                   tail_bin_px=2)
    searched_top = int(found.min_disparity_px[0] + found.pair_num_disparities[0] - 1)
    own = [min(_reference_in_view_top([g.numpy()], config, 2, True), searched_top) for g in (near, far)]
    assert found.object_in_view_top_px.tolist() == [[*own, int(found.in_view_top_px[0])]]
    assert own[0] == 56 == int(found.in_view_top_px[0]) and own[1] < 40
    plain = disparity_search_range(samples, valid, width, DenseConfig(in_view_per_object=False), extra_margin_px=2,
                                   min_count=20, groups=groups, tail_bin_px=2)
    assert plain.object_in_view_top_px is None
    assert all(torch.equal(getattr(plain, f), getattr(found, f))
               for f in ("min_disparity_px", "pair_num_disparities", "in_view_top_px"))
    alone = disparity_search_range(samples, valid, width, config, extra_margin_px=2, min_count=20, tail_bin_px=2)
    assert alone.object_in_view_top_px is None and alone.in_view_top_px is not None
    with pytest.raises(InputError, match="in_view_per_object: expected a bool"):
        DenseConfig(in_view_per_object=1)
    for share in (-0.1, 1.5, True, float("nan")):
        with pytest.raises(InputError, match=r"in_view_own_min_valid_share: expected a share in \[0, 1\]"):
            DenseConfig(in_view_own_min_valid_share=share)


def _one_object_of_disparity_2(valid: torch.Tensor) -> tuple:
    """Stand-ins for :func:`dense_object_depths`: label 1 over columns 0–15 of ``valid`` ``(B, 1, H, W)``, a dense
    map of 2 px where valid (searched 0–20, in view from row 20, its own top at 8), and one kept object."""
    from svs_torch.depth.dense_config import DenseDisparity
    from svs_torch.depth.depth_types import ObjectDepths

    b, _, h, w = valid.shape
    labels = torch.zeros(b, 1, h, w, dtype=torch.int64)
    labels[..., :16] = 1
    dense = DenseDisparity(torch.where(valid, 2.0, 0.0), valid, torch.zeros(b, dtype=torch.int64), 21,
                           torch.tensor([[0, 0, w, h]] * b), torch.full((b,), 21), torch.full((b,), 20),
                           torch.full((b, 1), 8))
    zeros = torch.zeros(b, 1)
    objects = ObjectDepths(torch.ones(b, 1, dtype=torch.int64), torch.full((b, 1), 160), zeros,
                           torch.zeros(b, 1, dtype=torch.int64), torch.zeros(b, 1, dtype=torch.int64), zeros, zeros,
                           zeros, torch.zeros(b, 1, dtype=torch.bool), torch.zeros(b, 0, dtype=torch.int64))
    return labels, dense, objects


@pytest.mark.parametrize("path", ["auto", "torch"])
def test_own_in_view_top_needs_most_of_its_band_measured(monkeypatch, path):
    """An object in view from its own top (8 px, below its pair's 20) keeps it where at least
    ``min_own_view_valid_share`` of its pixels from column 8 on are valid (pair 0: all of them), and is in view from
    its pair's top where fewer are (pair 1: 3 of 8 columns, 0.375 < 0.5): counted by hand, on both paths."""
    from svs_torch.depth.dense_objects import dense_object_depths

    if path == "torch":
        monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
    b, h, w = 2, 10, 40
    valid = torch.zeros(b, 1, h, w, dtype=torch.bool)
    valid[0, ..., :16] = True
    valid[1, ..., :5], valid[1, ..., 13:16] = True, True
    labels, dense, objects = _one_object_of_disparity_2(valid)
    counted = {share: dense_object_depths(dense, labels, objects, 100.0, 0.1, min_valid_px=1, fill_invalid=False,
                                          min_own_view_valid_share=share).num_in_view_px[:, 0].tolist()
               for share in (0.0, 0.375, 0.5)}
    assert counted == {0.0: [8 * h, 3 * h], 0.375: [8 * h, 3 * h], 0.5: [8 * h, 0]}


@pytest.mark.parametrize("grouped", [False, True])
def test_search_range_by_selection_equals_the_sort(grouped, monkeypatch):
    """The compiled selection of the range's nearest-rank percentiles gives the sort's range exactly, with
    ties, many counts (ranks that round up and down, an empty group, a pair without samples) and groups."""
    if not kernels.available("labelled_select"):
        pytest.skip("no C compiler")
    import svs_torch.depth.search_range as dense_module

    generator = torch.Generator().manual_seed(7)
    samples = (torch.rand(6, 700, generator=generator) * 40).round() / 4  # quarter steps: many ties
    valid = torch.rand(6, 700, generator=generator) < torch.tensor([0.9, 0.5, 0.2, 0.05, 0.01, 0.0]).view(-1, 1)
    groups = None
    if grouped:
        which = torch.randint(0, 3, (6, 700), generator=generator)
        groups = torch.stack([which == 0, which == 1, torch.zeros_like(valid)], dim=1)  # the third empty
    config = DenseConfig(range_percentiles=(1.0, 99.0))
    width = torch.full((6,), 320)
    selected = disparity_search_range(samples, valid, width, config, min_count=3, groups=groups)
    calls = []
    monkeypatch.setattr(dense_module, "_select_nearest_ranks",
                        lambda *args, real=dense_module._select_nearest_ranks: calls.append(real(*args)) or calls[-1])
    assert torch.equal(disparity_search_range(samples, valid, width, config, min_count=3, groups=groups)
                       .min_disparity_px, selected.min_disparity_px)
    assert calls and calls[0] is not None  # the selection did run
    monkeypatch.setattr(dense_module, "_select_nearest_ranks", lambda *args: None)
    sorted_ = disparity_search_range(samples, valid, width, config, min_count=3, groups=groups)
    assert torch.equal(selected.min_disparity_px, sorted_.min_disparity_px)
    assert torch.equal(selected.pair_num_disparities, sorted_.pair_num_disparities)
    assert selected.num_disparities == sorted_.num_disparities


def test_pooling_helpers_equal_torch_pooling():
    """The strided-slice block mean and block "any" of the coarse pass give ``avg_pool2d`` / ``max_pool2d``'s
    values bit for bit, at odd sizes and several factors."""
    import torch.nn.functional as F

    from svs_torch.depth.pooling import _any_pool, mean_pool

    generator = torch.Generator().manual_seed(3)
    for factor in (2, 3, 4):
        images = torch.rand(3, 1, 61, 83, generator=generator)
        masks = torch.rand(3, 2, 61, 83, generator=generator) > 0.9
        assert torch.equal(mean_pool(images, factor), F.avg_pool2d(images, factor))
        assert torch.equal(_any_pool(masks, factor), F.max_pool2d(masks.float(), factor) > 0)


def test_cost_volume_winner_found_in_cache_blocks_equals_the_volume_minimum(monkeypatch):
    """The running winner of the blocked cost-volume loop is the volume's min over D (first index on ties),
    whatever the block size, with costs outside the image or past a pair's own count at +inf."""
    import svs_torch.depth.cost_volume as dense_module

    generator = torch.Generator().manual_seed(4)
    left = dense_module.prefilter_xsobel(torch.rand(5, 1, 30, 40, generator=generator), 31 / 255)
    right = dense_module.prefilter_xsobel(torch.rand(5, 1, 30, 40, generator=generator), 31 / 255)
    left[2], right[2] = 0.0, 0.0  # a flat pair: every disparity ties
    x0, y0 = torch.tensor([-6, 0, 3, 10, 0]), torch.tensor([0, 2, 0, 5, 1])
    minimum, counts = torch.tensor([0, 2, 0, 1, 0]), torch.tensor([12, 7, 12, 3, 12])
    config = DenseConfig(window_size=5)
    reference = None
    for block_bytes in (1, 3 * 34 * 34 * 4, 1 << 30):  # one pair per block, blocks of 3, the whole batch
        monkeypatch.setattr(dense_module, "CACHE_BLOCK_BYTES", block_bytes)
        costs, inside, (best_cost, best) = dense_module._cost_volume(
            left, right, x0, y0, 20, 30, minimum, 12, torch.full((5,), 40), config, counts)
        own = torch.arange(12).view(1, -1, 1, 1) < counts.view(-1, 1, 1, 1)
        assert torch.isinf(costs[~(inside & own).expand_as(costs)]).all()
        volume_cost, volume_best = costs.min(dim=1)
        assert torch.equal(best_cost, volume_cost) and torch.equal(best, volume_best)
        if reference is None:
            reference = costs
        assert torch.equal(costs, reference)


needs_kernel = pytest.mark.skipif(not kernels.available(), reason="no C compiler: the torch path is tested alone")


@needs_kernel
@pytest.mark.parametrize("config", [
    DenseConfig(),
    DenseConfig(window_size=3, uniqueness_ratio=0.3, lr_max_diff_px=0.0, texture_threshold=0.05),
    DenseConfig(window_size=5, prefilter="none", uniqueness_ratio=0.0, lr_max_diff_px=None, texture_threshold=0.0),
    # 17² · 255 > 65535: the kernel's float costs instead of its 16-bit ones
    DenseConfig(window_size=17, prefilter="none"),
], ids=["default", "strict", "raw-no-rules", "raw-float-costs"])
def test_compiled_kernel_is_bit_identical_to_the_torch_path(config, generator):
    """The fused C kernel (svs_torch.depth.kernels) makes the torch path's float32 arithmetic in the same order:
    same disparities, same validity, bit for bit — on whole images with per-pair ranges, a flat pair (every
    disparity ties), padding (image_hw) and a range wider than the image."""
    base = torch.rand(4, 1, 37, 61, generator=generator)
    right = (0.9 * torch.roll(base, shifts=-5, dims=-1) + 0.1 * torch.rand(4, 1, 37, 61, generator=generator))
    base[2], right[2] = 0.5, 0.5
    minimum, image_hw = torch.tensor([0, 3, 0, 1]), torch.tensor([[37, 61], [30, 50], [37, 61], [37, 61]])
    config = replace(config, whole_range_in_view=False)  # keep the pixels a range wider than the image cuts
    for num_disparities in (12, 70):
        kernel = block_match_sad(base, right, minimum, num_disparities, replace(config, kernel="c"), image_hw)
        eager = block_match_sad(base, right, minimum, num_disparities, replace(config, kernel="torch"), image_hw)
        assert torch.equal(kernel.disparity_px, eager.disparity_px) and torch.equal(kernel.valid, eager.valid)
        assert kernel.valid.any()


@needs_kernel
@pytest.mark.parametrize("window_size", [7, 9, 11, 13, 19, 21])
def test_compiled_kernel_window_sums_over_rows_longer_than_a_chunk(window_size, generator):
    """The kernel sums a wide window (9 and more) through sums of three, 256 columns at a time: on rows longer
    than two such chunks, with the 16-bit costs (pre-filtered levels) and the float ones (raw levels past 16
    bits at 13 and more), the torch path's disparities and validity bit for bit."""
    base = torch.rand(2, 1, 30, 600, generator=generator)
    right = 0.9 * torch.roll(base, shifts=-6, dims=-1) + 0.1 * torch.rand(2, 1, 30, 600, generator=generator)
    for prefilter in ("xsobel", "none"):
        config = DenseConfig(window_size=window_size, prefilter=prefilter, whole_range_in_view=False)
        kernel = block_match_sad(base, right, 0, 20, replace(config, kernel="c"))
        eager = block_match_sad(base, right, 0, 20, replace(config, kernel="torch"))
        assert torch.equal(kernel.disparity_px, eager.disparity_px) and torch.equal(kernel.valid, eager.valid)
        assert kernel.valid.float().mean() > 0.5


@needs_kernel
def test_compiled_kernel_gives_the_pipeline_the_same_depths(teddy):
    """Region crops, per-pair ranges, groups and the coarse pass through both paths: the same dense maps."""
    left = teddy.left.repeat(3, 1, 1, 1)
    right = torch.cat([teddy.right, torch.roll(teddy.right, 4, -1), teddy.right])
    mask = segment_stereo(teddy).left.kept_mask.repeat(3, 1, 1, 1)
    mask[1, :, :100] = False  # pairs with different regions
    results = [estimate_dense_disparity(left, right, mask, DenseConfig(kernel=kernel))
               for kernel in ("c", "torch")]
    assert torch.equal(results[0].disparity_px, results[1].disparity_px)
    assert torch.equal(results[0].valid, results[1].valid) and results[0].valid.sum() > 1000


def test_kernel_off_or_unbuildable_falls_back_to_torch(monkeypatch, tmp_path, capsys, generator):
    """SVS_TORCH_KERNELS=torch, or a compiler that fails: the dense stage runs its torch path (same result),
    says why on stderr, and kernel="c" is then a clear error."""
    left, right = torch.rand(1, 1, 20, 30, generator=generator), torch.rand(1, 1, 20, 30, generator=generator)
    expected = block_match_sad(left, right, 0, 8, DenseConfig(kernel="torch"))
    monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
    assert kernels.load() is None
    monkeypatch.delenv("SVS_TORCH_KERNELS")
    monkeypatch.setattr(kernels, "_LIBRARIES", {})
    monkeypatch.setenv("SVS_TORCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("CC", "false")  # a compiler that always fails
    result = block_match_sad(left, right, 0, 8, DenseConfig())
    assert "did not compile" in capsys.readouterr().err
    assert torch.equal(result.disparity_px, expected.disparity_px) and torch.equal(result.valid, expected.valid)
    with pytest.raises(InputError, match="kernel: 'c' asks for the compiled dense kernel"):
        block_match_sad(left, right, 0, 8, DenseConfig(kernel="c"))
    assert not any((tmp_path / "cache").glob("*.so"))  # nothing half-written left behind


def test_compiled_kernel_cache_is_reused(monkeypatch, tmp_path, capsys):
    """The first load compiles (said on stderr) into the cache directory; a later process loads it silently. The
    smallest of the stage's kernels (the block matcher took 5 s to compile; tests/core/test_kernel_cache.py tests
    the cache itself)."""
    if shutil.which("cc") is None and shutil.which("gcc") is None:
        pytest.skip("no C compiler")
    monkeypatch.setenv("SVS_TORCH_CACHE", str(tmp_path))
    monkeypatch.setattr(kernels, "_LIBRARIES", {})
    assert kernels.load("fill_invalid_rows") is not None
    assert "compiling the C kernels" in capsys.readouterr().err
    assert len(list(tmp_path.glob("fill_invalid_rows-*.so"))) == 1 and not list(tmp_path.glob("block_match-*"))
    monkeypatch.setattr(kernels, "_LIBRARIES", {})
    assert kernels.load("fill_invalid_rows") is not None and capsys.readouterr().err == ""


def test_prefilter_slices_equal_conv2d_bit_for_bit(teddy):
    """The slice-and-add Sobel gives conv2d's float32 values exactly (same summation order)."""
    image = teddy.left
    kernel = torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]]).view(1, 1, 3, 3)
    expected = torch.nn.functional.conv2d(torch.nn.functional.pad(image, (1, 1, 1, 1), mode="replicate"), kernel)
    assert torch.equal(prefilter_xsobel(image, 31 / 255), expected.clamp(-31 / 255, 31 / 255))


def test_count_agreeing_inliers_by_hand():
    """An inlier agrees where the dense map is valid at its (rounded, rectified) left point and within the
    tolerance of its sparse disparity; outliers, points off the map, invalid pixels and points behind the
    homography's line at infinity do not count."""
    from svs_torch.depth.dense_config import DenseDisparity
    from svs_torch.depth.dense_objects import count_agreeing_inliers
    from svs_torch.depth.depth_types import Disparities

    b, h, w = 2, 6, 8
    disparity = torch.arange(w, dtype=torch.float32).expand(b, 1, h, w).clone()  # d = column
    valid = torch.ones(b, 1, h, w, dtype=torch.bool)
    valid[:, :, 0, :] = False  # row 0 unmeasured
    dense = DenseDisparity(disparity, valid, torch.zeros(b, dtype=torch.int64), 8,
                           torch.tensor([[0, 0, w, h]] * b), torch.full((b,), 8))
    points = torch.tensor([[[3.2, 2.0], [5.0, 3.4], [2.0, 0.0], [9.0, 1.0], [4.0, 4.0], [6.0, 5.0]]] * b)
    sparse = torch.tensor([[3.0, 6.4, 2.0, 9.0, 4.0, 0.0]] * b)  # agree, 1.4 off, row 0, off the map, ok, far off
    inliers = torch.tensor([[True, True, True, True, False, True]] * b)
    disparities = Disparities(sparse, torch.zeros_like(sparse), torch.ones(b, 6, dtype=torch.bool))
    count = count_agreeing_inliers(dense, points, disparities, inliers)
    assert count.tolist() == [1, 1]
    assert count_agreeing_inliers(dense, points, disparities, inliers, tolerance_px=1.5).tolist() == [2, 2]
    assert count_agreeing_inliers(dense, points, disparities, torch.ones_like(inliers)).tolist() == [2, 2]
    # Measured: the inliers at a valid pixel, agreeing or not (the first, the 1.4 px one and the far-off one).
    agreeing, measured = count_agreeing_inliers(dense, points, disparities, inliers, return_measured=True)
    assert agreeing.tolist() == [1, 1] and measured.tolist() == [3, 3]
    # Pair 1's dense map was measured after a shift of one column right: its points move with it.
    shift = torch.eye(3).expand(b, 3, 3).clone()
    shift[1, 0, 2] = 1.0
    first = torch.zeros_like(inliers)
    first[:, 0] = True
    shifted = count_agreeing_inliers(dense, points, disparities, first, shift, tolerance_px=0.5)
    assert shifted.tolist() == [1, 0]  # pair 1's (3.2, 2) → (4.2, 2) reads d = 4, 1 px from its sparse 3
    behind = torch.eye(3).expand(b, 3, 3).clone()
    behind[:, 2, 2] = -1.0  # every point maps behind the line at infinity
    assert count_agreeing_inliers(dense, points, disparities, inliers, behind).tolist() == [0, 0]
    with pytest.raises(InputError, match="inliers"):
        count_agreeing_inliers(dense, points, disparities, inliers[:, :3])


def test_box_sum_with_gradients_keeps_the_values_and_its_adjoint_passes_gradcheck(generator):
    """The recorded box sum (issue 31: an autograd Function, its backward the adjoint box sum) gives the untracked
    one's values bit for bit, and a pooling-based sum's gradient."""
    from svs_torch.depth.cost_volume import _box_sum

    volume = torch.randn(2, 3, 11, 13, generator=generator, dtype=torch.float64)
    tracked = volume.clone().requires_grad_()
    assert torch.equal(_box_sum(tracked, 5).detach(), _box_sum(volume, 5))
    assert torch.autograd.gradcheck(lambda v: _box_sum(v, 3), (tracked,))
    weights = torch.randn(2, 3, 7, 9, generator=generator, dtype=torch.float64)
    (ours,) = torch.autograd.grad((_box_sum(tracked, 5) * weights).sum(), tracked)
    (pooled,) = torch.autograd.grad((torch.nn.functional.avg_pool2d(tracked, 5, stride=1) * 25 * weights).sum(),
                                    tracked)
    assert torch.allclose(ours, pooled, atol=1e-12)


def test_the_window_spans_the_same_share_of_the_view_at_every_working_width(teddy):
    """``working_window``: 9 at the 320-px working width and wherever the factor reduces the images; the odd side
    nearest 9 · W / 320 where the images are matched unreduced and wider (the held-out scenes at native size,
    413–465 px wide); off, 9 everywhere. The stage matches with it."""
    widths = (160, 320, 352, 413, 448, 465, 480, 640, 741)
    assert [working_window(w) for w in widths] == [9, 9, 9, 11, 13, 13, 9, 9, 9]
    assert {working_window(w, DenseConfig(scale_window=False)) for w in widths} == {9}
    assert working_window(448, DenseConfig(window_size=7)) == 9 and working_window(465, DenseConfig(window_size=7)) == 11
    for size_wh, changed in (((448, 336), True), ((320, 267), False)):
        pair = resize_stereo_batch(teddy, size_wh)
        mask = torch.zeros_like(pair.left, dtype=torch.bool)
        mask[..., size_wh[1] // 4:size_wh[1] * 3 // 4, size_wh[0] // 8:size_wh[0] * 7 // 8] = True
        scaled = estimate_dense_disparity(pair.left, pair.right, mask, DenseConfig())
        fixed = estimate_dense_disparity(pair.left, pair.right, mask, DenseConfig(scale_window=False))
        assert torch.equal(scaled.disparity_px, fixed.disparity_px) != changed


# Boundaries the float64 loop reference never meets on random images (a mutation audit: each comparison below
# could be turned to its neighbour in both the torch path and the C kernel, and no test failed).
def _stripes(period: int, shift: int, h: int = 12, w: int = 48) -> tuple[torch.Tensor, torch.Tensor]:
    row = torch.tensor([0.1, 0.3, 0.8, 0.5, 0.2, 0.9, 0.4, 0.6][:period]).repeat(w // period + 6)
    left = row[2 * period: 2 * period + w].expand(h, w)
    right = row[2 * period + shift: 2 * period + shift + w].expand(h, w)  # x_right = x - shift
    return left[None, None].contiguous(), right[None, None].contiguous()


@pytest.mark.parametrize("kernel", ["torch", "auto"])
def test_uniqueness_rejects_a_rival_that_ties_the_best(kernel):
    """A texture of period 4 shifted by 2 px: SAD is exactly 0 at d = 2, 6, 10, 14, so the rival equals the best;
    StereoBM rejects every such pixel (a rival must be strictly above (1 + r) times the best)."""
    left, right = _stripes(4, 2)
    config = DenseConfig(window_size=5, uniqueness_ratio=0.1, lr_max_diff_px=None, texture_threshold=0.0,
                         kernel=kernel)
    assert not block_match_sad(left, right, 0, 16, config).valid[..., 3:-3, 20:-3].any()


@pytest.mark.parametrize("kernel", ["torch", "auto"])
def test_texture_exactly_at_the_threshold_is_kept(kernel):
    """One step of 0.5 (over the prefilter cap 0.125): |x-Sobel| is the cap on the two columns beside it, so a 3x3
    window over both sums 6 x 0.125 = 0.75 exactly; at texture_threshold 0.75 / 9 (per pixel) it is kept, as
    StereoBM rejects only a sum below the threshold."""
    image = torch.zeros(1, 1, 8, 24)
    image[..., 12:] = 0.5
    assert 0.75 / 9 * 9 == 0.75
    config = DenseConfig(window_size=3, prefilter_cap=0.125, texture_threshold=0.75 / 9, uniqueness_ratio=0.0,
                         lr_max_diff_px=None, kernel=kernel)
    valid = block_match_sad(image, image, 0, 4, config).valid[0, 0, 2:-2]
    assert valid[:, 11].all() and valid[:, 12].all()


def test_the_row_fill_averages_neighbours_exactly_one_px_apart():
    """Neighbours 1 px apart agree (the mean fills the gap); test_fill_invalid_rows met only 0.5 and 3.5."""
    filled, _ = fill_invalid_rows(torch.tensor([[5.0, 0.0, 6.0]]), torch.tensor([[True, False, True]]))
    assert filled[0, 1].item() == 5.5


def test_the_search_range_holds_fractional_extremes():
    """Without margins the range must still hold 10.5 and 20.25 px: its low end floored (10), its top ceiled
    (21); a ceiled low end (11) dropped the nearest samples and the default 2 px margin hid it."""
    disparity = torch.tensor([[10.5] * 10 + [20.25] * 10], dtype=torch.float64)
    config = replace(DenseConfig(), range_margin_px=0.0, range_margin_fraction=0.0, range_percentiles=(0.0, 100.0))
    found = disparity_search_range(disparity, torch.ones_like(disparity, dtype=torch.bool), torch.tensor([320]),
                                   config, min_count=1)
    assert found.min_disparity_px.tolist() == [10]
    assert (found.min_disparity_px + found.pair_num_disparities - 1).tolist() == [21]


@pytest.mark.parametrize("kernels", ["auto", "torch"])
def test_dense_object_depth_adds_doffs(monkeypatch, kernels):
    """Z = f·B / (d + doffs) over an object's dense disparities, in the C kernel and the torch path: a mutation
    audit turned the sign of doffs in both and tests/depth passed (only a pipeline test noticed; the sparse
    point_depths had their own check)."""
    from svs_torch.depth.dense_objects import dense_object_depths

    monkeypatch.setenv("SVS_TORCH_KERNELS", kernels)
    valid = torch.zeros(1, 1, 10, 40, dtype=torch.bool)
    valid[..., :16] = True
    labels, dense, objects = _one_object_of_disparity_2(valid)
    out = dense_object_depths(dense, labels, objects, 100.0, 0.1, doffs_px=3.0, min_valid_px=1, fill_invalid=False)
    assert torch.allclose(out.depth_median_m[0, 0], torch.tensor(2.0))  # 100 · 0.1 / (2 + 3)


@pytest.mark.parametrize("kernels", ["auto", "torch"])
@pytest.mark.parametrize("fill", [True, False])
def test_the_nearest_surface_leaves_out_matches_above_the_in_view_top(monkeypatch, kernels, fill):
    """Noise's wrong matches far above every object's range pull an object's low depth percentile, the nearest
    surface ``guide`` says, near while its median stays right (experiments/guide_confirm.md). Over
    :func:`surface_pixels` (at or below the pair's in-view top) the low percentile is the true surface's; the median,
    the high percentile and the counts stay over every pixel, and an object with no measured pixel there keeps its
    own. The same numbers in the C kernel, the torch path and the torch path with gradients."""
    from svs_torch.depth.dense_config import DenseDisparity
    from svs_torch.depth.dense_objects import dense_object_depths, surface_pixels
    from svs_torch.depth.depth_types import DepthConfig, ObjectDepths

    monkeypatch.setenv("SVS_TORCH_KERNELS", kernels)
    disparity = torch.full((1, 1, 10, 40), 10.0)
    disparity[..., :3] = 40.0  # 15 % of object 1's pixels: wrong matches far above the top (20 px)
    disparity[..., 24:] = 44.0  # object 2 is wholly above it
    labels = torch.zeros(1, 1, 10, 40, dtype=torch.int64)
    labels[..., :20], labels[..., 24:] = 1, 2
    valid = labels > 0
    dense = DenseDisparity(disparity, valid, torch.zeros(1, dtype=torch.int64), 48, torch.tensor([[0, 0, 40, 10]]),
                           torch.tensor([48]), torch.tensor([20]))
    zeros, none = torch.zeros(1, 2), torch.zeros(1, 2, dtype=torch.int64)
    objects = ObjectDepths(torch.tensor([[1, 2]]), torch.tensor([[200, 160]]), zeros, none, none, zeros, zeros, zeros,
                           torch.zeros(1, 2, dtype=torch.bool), torch.zeros(1, 0, dtype=torch.int64))
    surface = surface_pixels(dense)
    assert int((valid & ~surface).sum()) == 30 + 160
    plain = dense_object_depths(dense, labels, objects, 100.0, 0.1, min_valid_px=1, fill_invalid=fill)
    out = dense_object_depths(dense, labels, objects, 100.0, 0.1, min_valid_px=1, fill_invalid=fill,
                              surface_valid=surface)
    assert float(plain.depth_low_m[0, 0]) == pytest.approx(0.25)  # 10 / 40: the wrong matches
    assert out.depth_low_m[0].tolist() == pytest.approx([1.0, 10 / 44])  # 10 / 10; object 2 keeps its own
    for name in ("depth_median_m", "depth_high_m", "valid", "num_valid_px", "num_in_view_px"):
        assert torch.equal(getattr(out, name), getattr(plain, name)), name
    trained = disparity.clone().requires_grad_()
    graded = dense_object_depths(replace(dense, disparity_px=trained), labels, objects, 100.0, 0.1,
                                 min_valid_px=1, fill_invalid=fill, surface_valid=surface)
    assert torch.allclose(graded.depth_low_m, out.depth_low_m)
    graded.depth_low_m[0, 0].backward()
    assert float(trained.grad[..., :3].abs().sum()) == 0 and float(trained.grad[..., 3:20].abs().sum()) > 0
    # without a top, or with nothing above it, every valid pixel counts
    assert surface_pixels(replace(dense, in_view_top_px=None)) is None
    assert surface_pixels(replace(dense, in_view_top_px=torch.tensor([44]))) is None
    # half a pixel above the top is allowed for the sub-pixel fit, not more
    for above, left_out in ((0.25, 0), (0.5, 0), (0.501, 160)):
        lifted = replace(dense, disparity_px=torch.where(labels == 2, 44.0 + above, disparity),
                         in_view_top_px=torch.tensor([44]))
        surface = surface_pixels(lifted)
        assert (surface is None) if not left_out else int((valid & ~surface).sum()) == left_out, above
    with pytest.raises(InputError, match=r"dense.in_view_top_px: expected \(1\), got \(1, 2\)"):
        surface_pixels(replace(dense, in_view_top_px=torch.tensor([[20, 20]])))
    with pytest.raises(InputError, match="surface_within_in_view_top: expected a bool"):
        DepthConfig(surface_within_in_view_top="yes")


@pytest.mark.parametrize("kernels", ["auto", "torch"])
def test_an_object_with_exactly_the_fewest_pixels_is_ranged(monkeypatch, kernels):
    """``min_valid_px`` and ``min_in_view_px`` are the fewest pixels an object is ranged with: exactly that many
    range it, one fewer do not, in the C kernel and the torch path (a mutation audit read both '>=' as '>' and no
    test failed)."""
    from svs_torch.depth.dense_objects import dense_object_depths

    monkeypatch.setenv("SVS_TORCH_KERNELS", kernels)
    valid = torch.zeros(1, 1, 10, 40, dtype=torch.bool)
    valid[..., :16] = True
    labels, dense, objects = _one_object_of_disparity_2(valid)

    def ranged(**fewest) -> bool:
        out = dense_object_depths(dense, labels, objects, 100.0, 0.1, fill_invalid=False, **fewest)
        return bool(out.valid[0, 0])

    assert ranged(min_valid_px=160) and not ranged(min_valid_px=161)
    in_view = int(dense_object_depths(dense, labels, objects, 100.0, 0.1, min_valid_px=1, fill_invalid=False,
                                      min_own_view_valid_share=0.5).num_in_view_px[0, 0])
    assert 0 < in_view < 160
    assert ranged(min_valid_px=1, min_own_view_valid_share=0.5, min_in_view_px=in_view)
    assert not ranged(min_valid_px=1, min_own_view_valid_share=0.5, min_in_view_px=in_view + 1)
