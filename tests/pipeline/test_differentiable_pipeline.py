"""estimate_obstacle_depth(..., differentiable=True): the hard pipeline's decisions, depths with gradients to both
images and the segmenter's weights (issue 31); and images that require grad under the hard path."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from svs_torch import InputError
from svs_torch.data import collate_stereo_batches, load_middlebury_eval3, resize_stereo_batch
from svs_torch.depth.dense_config import DenseConfig
from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth
from svs_torch.pipeline.soft import (_bands, _fill_sources, _soft_disparity, _window_costs, band_mean,
                                     quantize_straight_through, subpixel_disparity)
from svs_torch.segmentation.network_files import load_obstacle_net
from svs_torch.segmentation.segment import SegmentationConfig

LEARNED = SegmentationConfig(segmenter="learned")
DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=DEVICES)
def device(request) -> str:
    return request.param


def _teddy(data_dir, size_wh=(320, 240), device="cpu"):
    batch = resize_stereo_batch(load_middlebury_eval3(data_dir / "middlebury_eval3_Q" / "Teddy"), size_wh)
    return batch.to(device) if device != "cpu" else batch


def _requiring_grad(batch):
    return replace(batch, left=batch.left.clone().requires_grad_(), right=batch.right.clone().requires_grad_())


# ------------------------------------------------------------------------------------------------- pieces
def test_quantize_straight_through_rounds_and_passes_the_gradient(generator):
    image = torch.rand(2, 1, 5, 7, generator=generator, dtype=torch.float64, requires_grad=True)
    levels = quantize_straight_through(image)
    assert torch.equal(levels, torch.round(image.detach() * 255))  # the hard stage's levels, exactly
    levels.sum().backward()
    assert torch.equal(image.grad, torch.full_like(image, 255.0))


def test_quantize_straight_through_refuses_what_the_hard_levels_refuse():
    """Found by an audit: a uint8 image's 255 · image wrapped around modulo 256 in silence (2 became 254) and a bool
    one became 0 / 255, where the hard stage's quantize_levels, whose values it claims bit for bit, refuses both."""
    from svs_torch.depth.cost_volume import quantize_levels

    for image in (torch.tensor([[0, 1, 2]], dtype=torch.uint8), torch.tensor([[False, True]]),
                  torch.tensor([[3]]), torch.tensor([[0.5]], dtype=torch.float16)):
        for quantize in (quantize_levels, quantize_straight_through):
            with pytest.raises(InputError, match=r"^image: expected a (float|float32 or float64) tensor, got "):
                quantize(image)


def test_window_costs_equal_a_naive_loop_with_clamped_reads(generator):
    left = torch.rand(2, 1, 7, 11, generator=generator, dtype=torch.float64)
    right = torch.rand(2, 1, 7, 11, generator=generator, dtype=torch.float64)
    pixels = torch.tensor([[0, 0, 0], [0, 3, 5], [1, 6, 10], [1, 2, 1]])
    disparities = torch.tensor([[0, 1, 2], [3, -1, 4], [9, 12, 0], [2, 1, 0]])
    costs = _window_costs(left, right, pixels, disparities, 5)
    L, R = left.numpy()[:, 0], right.numpy()[:, 0]
    for p, (b, y, x) in enumerate(pixels.tolist()):
        for c, d in enumerate(disparities[p].tolist()):
            total = 0.0
            for v in range(-2, 3):
                for u in range(-2, 3):
                    row = min(max(y + v, 0), 6)
                    total += abs(L[b, row, min(max(x + u, 0), 10)] - R[b, row, min(max(x + u - d, 0), 10)])
            assert costs[p, c].item() == pytest.approx(total, abs=1e-12)


def test_subpixel_disparity_gradcheck(generator):
    left = torch.rand(1, 1, 6, 12, generator=generator, dtype=torch.float64, requires_grad=True)
    right = torch.rand(1, 1, 6, 12, generator=generator, dtype=torch.float64, requires_grad=True)
    pixels = torch.tensor([[0, 2, 6], [0, 4, 9], [0, 1, 4]])
    winner = torch.tensor([2, 3, 1])
    minimum, width = torch.tensor([0]), torch.tensor([12])

    def fit(a, b):
        return subpixel_disparity(a, b, pixels, winner, minimum, width, 3)

    assert torch.autograd.gradcheck(fit, (left, right), fast_mode=True)
    offsets = fit(left, right).detach() - winner
    assert bool((offsets.abs() <= 0.5).all()) and bool((offsets != 0).any())


def test_band_mean_gradcheck_and_values(generator):
    values = torch.rand(2, 9, generator=generator, dtype=torch.float64, requires_grad=True)
    weights = torch.rand(2, 9, generator=generator, dtype=torch.float64, requires_grad=True)
    band = torch.rand(2, 3, 9, generator=generator) > 0.4
    band[1, 2] = False
    mean, some = band_mean(values, weights, band)
    v, w = values.detach(), weights.detach()
    expected = [[float((v[i][band[i, m]] * w[i][band[i, m]]).sum() / w[i][band[i, m]].sum())
                 if band[i, m].any() else 0.0 for m in range(3)] for i in range(2)]
    assert some.tolist() == band.any(-1).tolist()
    torch.testing.assert_close(torch.where(some, mean, 0.0).detach(), torch.tensor(expected, dtype=torch.float64))
    assert torch.autograd.gradcheck(lambda v, w: band_mean(v, w, band)[0], (values, weights))
    # A NaN outside every band is not read (an audit: 0 · NaN made the band's mean NaN).
    outside = torch.zeros(1, 3, dtype=torch.float64)
    outside[0, 2] = float("nan")
    mean, some = band_mean(outside, torch.ones(1, 3, dtype=torch.float64), torch.tensor([[[True, True, False]]]))
    assert mean.tolist() == [[0.0]] and some.tolist() == [[True]]


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.int64])
def test_band_mean_refuses_values_it_cannot_sum(dtype):
    """float16 values summed to inf (20 000 depths of 8 m, a mean of inf, in silence; an audit): refused by name."""
    values, band = torch.full((1, 20000), 8.0).to(dtype), torch.ones(1, 1, 20000, dtype=torch.bool)
    with pytest.raises(InputError, match="values: expected a float32 or float64 tensor|values: expected a float"):
        band_mean(values, torch.ones(1, 20000), band)
    assert band_mean(values.float(), torch.ones(1, 20000), band)[0].tolist() == [[8.0]]


@pytest.mark.parametrize("weights, band, message", [
    (torch.ones(2, 8), torch.ones(2, 3, 9, dtype=torch.bool), r"weights: expected \(2, 9\), got \(2, 8\)"),
    (torch.ones(2, 9), torch.ones(3, 3, 9, dtype=torch.bool), r"band: expected \(2, M, 9\), got \(3, 3, 9\)"),
    (torch.ones(2, 9), torch.ones(2, 9, dtype=torch.bool), r"band: expected \(2, M, 9\), got \(2, 9\)"),
    (torch.ones(2, 9), torch.ones(2, 3, 9), "band: expected a bool tensor, got torch.float32")])
def test_band_mean_names_a_mismatched_argument(weights, band, message):
    """Mismatched shapes failed in torch's broadcasting, a float band in torch.where, and a band without its M axis
    gave a (2, 2) mean in silence (an audit): each is refused by the argument's name."""
    with pytest.raises(InputError, match=message):
        band_mean(torch.ones(2, 9), weights, band)


@pytest.mark.parametrize("argument", ["half images", "float winner", "float pixels"])
def test_subpixel_disparity_refuses_what_it_cannot_index_or_fit(argument):
    """Was: float16 images were fitted in silence (float16 disparities), and a float winner or pixel index failed
    deep inside torch ('index_select(): Expected dtype int32 or int64'; an audit). Refused by name."""
    left, right = torch.rand(1, 1, 20, 30), torch.rand(1, 1, 20, 30)
    pixels, winner, bounds = torch.tensor([[0, 10, 20]]), torch.tensor([5]), (torch.tensor([0]), torch.tensor([30]))
    name, *call = {"half images": ("left", left.half(), right.half(), pixels, winner),
                   "float winner": ("winner", left, right, pixels, winner.float()),
                   "float pixels": ("pixels", left, right, pixels.float(), winner)}[argument]
    with pytest.raises(InputError, match=f"^{name}: expected"):
        subpixel_disparity(*call, *bounds, 5)
    assert subpixel_disparity(left, right, pixels, winner, *bounds, 5).dtype == torch.float32


@pytest.mark.parametrize("argument, message", [
    ("pixels without the pair", r"^pixels: expected \(P, 3\), got \(1, 2\)$"),
    ("a pixel past the rows", r"^pixels: expected \(pair, row, column\) rows inside the images' \(B, H, W\) = "
                              r"\(1, 20, 30\)$"),
    ("two winners", r"^winner: expected \(1\), got \(2\)$"),
    ("bounds of two pairs", r"^min_disparity_px: expected \(1\), got \(2\)$"),
    ("an even window", r"^window_size: expected an odd int >= 1, got 4$")])
def test_subpixel_disparity_names_an_argument_of_another_shape(argument, message):
    """Found by an audit of the differentiable pieces called by hand: pixels without their pair column, a pixel
    outside the images, a winner or bounds of another length failed in an index deep inside torch ('index out of
    range in self'), and an even window was fitted in silence."""
    left, right = torch.rand(1, 1, 20, 30), torch.rand(1, 1, 20, 30)
    call = {"pixels": torch.tensor([[0, 10, 20]]), "winner": torch.tensor([5]), "min_disparity_px": torch.tensor([0]),
            "image_w": torch.tensor([30]), "window_size": 5}
    call.update({"pixels without the pair": {"pixels": torch.tensor([[10, 20]])},
                 "a pixel past the rows": {"pixels": torch.tensor([[0, 20, 20]])},
                 "two winners": {"winner": torch.tensor([5, 6])},
                 "bounds of two pairs": {"min_disparity_px": torch.tensor([0, 0])},
                 "an even window": {"window_size": 4}}[argument])
    with pytest.raises(InputError, match=message):
        subpixel_disparity(left, right, **call)


def test_bands_hold_the_order_statistics_the_quantile_interpolates(generator):
    """A 30-member object: the median interpolates ranks 14 and 15, a 1 % band around it by value would be empty."""
    depth = torch.rand(1, 40, generator=generator, dtype=torch.float64)
    members = torch.zeros(1, 40, dtype=torch.int64)
    members[0, :30] = 3
    bands = _bands(depth, members, torch.tensor([[3, -1]]), torch.tensor([0.5, 0.1], dtype=torch.float64))
    ordered = depth[0, :30].sort().values
    assert bands.shape == (1, 2, 2, 40) and not bool(bands[:, 1].any()) and not bool(bands[0, 0, :, 30:].any())
    median_band = depth[0][bands[0, 0, 0]].sort().values
    assert torch.equal(median_band, ordered[14:16])  # ranks ⌊0.49 · 29⌋ = 14 to ⌈0.51 · 29⌉ = 15
    assert torch.equal(depth[0][bands[0, 0, 1]].sort().values, ordered[2:5])  # ranks ⌊0.09 · 29⌋ = 2 to ⌈0.11 · 29⌉ = 4


def test_fill_sources_are_the_valid_pixels_each_needed_fill_reads(generator):
    valid = torch.rand(3, 4, 30, generator=generator) > 0.6
    needed = torch.rand(3, 4, 30, generator=generator) > 0.7
    found = _fill_sources(valid, needed)
    expected = needed.clone()
    for i, j in (~valid & needed).nonzero()[:, :2].unique(dim=0).tolist():  # a naive walk along each row
        row_valid, row_needed = valid[i, j].tolist(), needed[i, j]
        for x in range(30):
            if row_needed[x] and not row_valid[x]:
                left = [k for k in range(x) if row_valid[k]]
                right = [k for k in range(x + 1, 30) if row_valid[k]]
                for k in left[-1:] + right[:1]:
                    expected[i, j, k] = True
    assert torch.equal(found, expected)


# ------------------------------------------------------------------------------------------------- real pair
@pytest.mark.parametrize("working_width_px", [320, 160, 224], ids=["factor1", "factor2", "factor1-window13"])
def test_soft_dense_map_is_the_hard_map_bit_for_bit(data_dir, working_width_px):
    batch = _teddy(data_dir)
    config = PipelineConfig(dense=DenseConfig(working_width_px=working_width_px))
    hard = estimate_obstacle_depth(batch, config)
    assert not bool(hard.rectified.any())
    dense = hard.dense
    soft = _soft_disparity(batch.left.clone().requires_grad_(), batch.right, dense,
                           torch.ones_like(dense.valid), batch.image_hw, config.dense)
    assert int(dense.valid.sum()) > 5000
    assert torch.equal(soft.detach()[dense.valid], dense.disparity_px[dense.valid])


@pytest.mark.parametrize("working_width_px", [320, 160], ids=["factor1", "factor2"])
def test_a_hard_value_the_plain_fit_misses_by_a_hair_is_kept_bit_for_bit(data_dir, working_width_px):
    """Found by an audit: where an aggregated volume's fit saturated at ±0.5, the plain costs' fit can miss the hard
    value by less than a thousandth (Pipes as a camera frame: 25.0009 for 25.0); the recomputed value was kept
    there, so the depths with gradients differed from those under no_grad, which read the hard map (4.8e-7 m).
    Now the hard value, straight-through, with the recomputation's gradient."""
    batch = _teddy(data_dir)
    config = PipelineConfig(dense=DenseConfig(working_width_px=working_width_px))
    dense = estimate_obstacle_depth(batch, config).dense
    factor = 320 // working_width_px
    picked = torch.rand(1, 1, 240 // factor, 320 // factor, generator=torch.Generator().manual_seed(0)) < 0.01
    moved = picked.repeat_interleave(factor, -2).repeat_interleave(factor, -1) & dense.valid  # whole working pixels
    dense = replace(dense, disparity_px=torch.where(moved, dense.disparity_px + 5e-4 * factor, dense.disparity_px))
    left = batch.left.clone().requires_grad_()
    soft = _soft_disparity(left, batch.right, dense, torch.ones_like(dense.valid), batch.image_hw, config.dense)
    assert int(moved.sum()) > 20
    assert torch.equal(soft.detach()[dense.valid], dense.disparity_px[dense.valid])
    (grad,) = torch.autograd.grad(soft[moved].sum(), left)
    assert int((grad != 0).sum()) > 20


def test_teddy_learned_gradients_reach_both_images_and_the_weights(data_dir):
    net = load_obstacle_net()
    batch = _requiring_grad(_teddy(data_dir, (240, 180)))
    config = PipelineConfig(differentiable=True, segmentation=LEARNED)
    result = estimate_obstacle_depth(batch, config, network=net)
    objects, hard = result.depth.objects, result.hard_depth.objects
    assert bool(objects.valid.any())
    assert torch.equal(objects.valid, hard.valid)
    # The same estimator: every object within 0.5 % of the hard pipeline's depth.
    relative = (objects.depth_median_m.detach() - hard.depth_median_m).abs() / hard.depth_median_m.clamp_min(1e-9)
    assert float(relative[objects.valid].max()) < 0.005
    assert result.depth.nearest.depth_m.requires_grad
    loss = objects.depth_median_m[objects.valid].sum() + result.depth.nearest.depth_m.sum()
    loss.backward()
    for image in (batch.left, batch.right):
        assert bool(torch.isfinite(image.grad).all())
        assert int((image.grad != 0).sum()) > 1000  # a band of pixels, not one or two order statistics
    grads = [p.grad for p in net.parameters()]
    assert all(g is not None and bool(torch.isfinite(g).all()) for g in grads)
    assert sum(int((g != 0).sum()) for g in grads) > 0.5 * sum(p.numel() for p in net.parameters())
    # The hard half is the hard pipeline's own result (the left logits computed once, with gradients).
    plain = estimate_obstacle_depth(_teddy(data_dir, (240, 180)), PipelineConfig(segmentation=LEARNED),
                                    network=net)
    assert torch.equal(plain.segmentation.left.labels, result.segmentation.left.labels)
    assert torch.equal(plain.depth.objects.depth_median_m, hard.depth_median_m)


def test_without_a_network_the_cached_one_passes_image_gradients_and_keeps_no_grad(data_dir):
    from svs_torch.segmentation.network_files import cached_obstacle_net
    batch = _requiring_grad(_teddy(data_dir, (160, 120)))
    result = estimate_obstacle_depth(batch, PipelineConfig(differentiable=True, segmentation=LEARNED))
    objects = result.depth.objects
    objects.depth_median_m[objects.valid].sum().backward()
    assert int((batch.left.grad != 0).sum()) > 100
    assert all(p.grad is None for p in cached_obstacle_net("learned").parameters())


def test_rectified_pair_keeps_the_hard_values_and_passes_gradients(data_dir):
    batch = _requiring_grad(_teddy(data_dir, (240, 180)))  # F rectifies at this size (degenerate at 160x120)
    result = estimate_obstacle_depth(batch, PipelineConfig(differentiable=True, rectify="required"))
    assert bool(result.rectified.all())
    objects, hard = result.depth.objects, result.hard_depth.objects
    relative = (objects.depth_median_m.detach() - hard.depth_median_m).abs() / hard.depth_median_m.clamp_min(1e-9)
    assert float(relative[objects.valid].max()) < 0.005
    # The homographies are the hard ones, with a graph to both images (matches, F's refit, Hartley's method).
    assert result.H_left.grad_fn is not None and result.H_right.grad_fn is not None
    hard = estimate_obstacle_depth(_teddy(data_dir, (240, 180)), PipelineConfig(rectify="required"))
    assert torch.equal(result.H_left.detach(), hard.H_left) and torch.equal(result.H_right.detach(), hard.H_right)
    loss = objects.depth_median_m[objects.valid].sum()
    through = torch.autograd.grad(loss, (result.H_left, result.H_right), retain_graph=True)
    assert all(bool(torch.isfinite(g).all()) and float(g.abs().max()) > 0 for g in through)
    reaching = torch.autograd.grad((result.H_left * through[0]).sum() + (result.H_right * through[1]).sum(),
                                   (batch.left, batch.right), retain_graph=True)
    assert all(bool(torch.isfinite(g).all()) and int((g != 0).sum()) > 100 for g in reaching)
    loss.backward()
    assert int((batch.left.grad != 0).sum()) > 100 and int((batch.right.grad != 0).sum()) > 100


def test_a_float64_calibration_keeps_the_images_dtype_and_its_gradient(data_dir):
    batch = _requiring_grad(_teddy(data_dir, (160, 120)))
    focal = batch.focal_px.double().requires_grad_(True)
    batch = replace(batch, focal_px=focal, baseline_m=batch.baseline_m.double(), doffs_px=batch.doffs_px.double())
    result = estimate_obstacle_depth(batch, PipelineConfig(differentiable=True))
    depth = result.depth
    for value in (depth.objects.depth_median_m, depth.nearest.depth_m, depth.range.r_min_m, depth.range.d_max_px):
        assert value.dtype == torch.float32  # the hard depths' and the images' dtype, not the calibration's
    depth.nearest.depth_m[depth.nearest.valid].sum().backward()
    assert float(focal.grad.abs().sum()) > 0 and int((batch.left.grad != 0).sum()) > 100


def test_mixed_sizes_pass_gradients_to_each_pair(data_dir):
    pairs = [_teddy(data_dir, (160, 120)), _teddy(data_dir, (200, 150))]
    batch = _requiring_grad(collate_stereo_batches(pairs))
    result = estimate_obstacle_depth(batch, PipelineConfig(differentiable=True))
    valid = result.depth.objects.valid
    assert bool(valid.any(dim=1).all())
    result.depth.objects.depth_median_m[valid].sum().backward()
    assert bool((batch.left.grad.flatten(1) != 0).any(dim=1).all())


def test_a_pairs_calibration_gradient_is_the_same_alone_and_batched(data_dir):
    """Each band's mean depth, and its gradient w.r.t. the calibration, is a sum over the pair's pixels; batched,
    those sums were split among the threads by the batch's size, and Art's surface and R_min gradients w.r.t. its
    baseline moved by 9.5e-7 (2 threads, an audit). Now the same alone and beside Baby1, bit for bit."""
    from svs_torch.data import load_middlebury_2005_2006

    scenes = data_dir / "middlebury_2005_2006_third"
    pairs = [resize_stereo_batch(load_middlebury_2005_2006(scenes / name), (320, 240)) for name in ("Art", "Baby1")]
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    found = []
    try:
        for count in (1, 2):
            batch = collate_stereo_batches(pairs[:count])
            calibration = [v.clone().requires_grad_() for v in (batch.focal_px, batch.baseline_m, batch.doffs_px)]
            batch = replace(batch, focal_px=calibration[0], baseline_m=calibration[1], doffs_px=calibration[2])
            depth = estimate_obstacle_depth(batch, PipelineConfig(differentiable=True)).depth
            outputs = (depth.nearest.surface_m[0], depth.objects.depth_low_m[0, 0], depth.range.r_min_m[0])
            found.append([torch.autograd.grad(out, calibration, retain_graph=True) for out in outputs])
            found[-1].append(torch.stack([out.detach() for out in outputs]))
    finally:
        torch.set_num_threads(before)
    assert bool(found[0][-1].gt(0).all()) and torch.equal(found[0][-1], found[1][-1])
    for alone, batched in zip(found[0][:-1], found[1][:-1]):
        assert all(torch.equal(a[0], b[0]) for a, b in zip(alone, batched))


@pytest.mark.parametrize("preset", ["default", "paper", "learned"])
def test_hard_presets_take_images_that_require_grad(data_dir, preset):
    config = {"default": PipelineConfig(), "paper": PipelineConfig.paper(),
              "learned": PipelineConfig(segmentation=LEARNED)}[preset]
    plain = _teddy(data_dir, (160, 120))
    detached = estimate_obstacle_depth(plain, config)
    result = estimate_obstacle_depth(_requiring_grad(plain), config)  # raised a RuntimeError before issue 31
    assert not result.depth.objects.depth_median_m.requires_grad
    assert torch.equal(result.depth.objects.depth_median_m, detached.depth.objects.depth_median_m)
    assert result.hard_depth is None


def test_arguments_are_checked(data_dir):
    with pytest.raises(InputError, match="differentiable: needs depth.rule 'dense'"):
        replace(PipelineConfig.paper(), differentiable=True)
    batch = _teddy(data_dir, (160, 120))
    with pytest.raises(InputError, match="network: given, but config.segmentation.segmenter is 'otsu'"):
        estimate_obstacle_depth(batch, PipelineConfig(differentiable=True, segmentation=SegmentationConfig()),
                                network=load_obstacle_net())
    with pytest.raises(InputError, match="network: expected a NearnessNet"):
        estimate_obstacle_depth(batch, PipelineConfig(differentiable=True), network=load_obstacle_net())
    with pytest.raises(InputError, match="network: expected its parameters on the batch's device"):
        estimate_obstacle_depth(batch, PipelineConfig(segmentation=LEARNED), network=load_obstacle_net().to("meta"))


def test_results_follow_the_device(data_dir, device):
    net = load_obstacle_net().to(device)
    result = estimate_obstacle_depth(_requiring_grad(_teddy(data_dir, (160, 120), device)),
                                     PipelineConfig(differentiable=True, segmentation=LEARNED), network=net)
    assert result.depth.objects.depth_median_m.device.type == device


def test_no_tensor_is_created_off_the_input_device(data_dir, monkeypatch):
    """Without a GPU: every tensor the torch path creates without naming a device would land on the meta device
    (and fail to mix with the CPU inputs). The compiled kernels are CPU-only by design, so they are off here."""
    monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
    batch = _requiring_grad(_teddy(data_dir, (160, 120)))
    net = load_obstacle_net()
    config = PipelineConfig(differentiable=True, segmentation=LEARNED)
    estimate_obstacle_depth(batch, PipelineConfig())  # imports done outside the guard
    torch.set_default_device("meta")
    try:
        result = estimate_obstacle_depth(batch, config, network=net)
    finally:
        torch.set_default_device(None)
    assert result.depth.objects.depth_median_m.device.type == "cpu"
    assert np.isfinite(result.depth.objects.depth_median_m.detach().numpy()).all()


def _tensors(tree):
    if isinstance(tree, torch.Tensor):
        yield tree
    elif hasattr(tree, "__dataclass_fields__"):
        for name in tree.__dataclass_fields__:
            yield from _tensors(getattr(tree, name))
    elif isinstance(tree, (tuple, list)):
        for item in tree:
            yield from _tensors(item)
    elif isinstance(tree, dict):
        for item in tree.values():
            yield from _tensors(item)


def test_a_batch_run_in_chunks_is_merged_into_ordinary_tensors(data_dir, monkeypatch):
    """A batch over ``CHUNK_PIXELS`` runs its chunks in inference mode and merges them outside it: the merged result
    holds ordinary tensors only (the merge's own, not copied once more), with the values and the shared tensors of
    one call."""
    from svs_torch.pipeline import run

    batch = _teddy(data_dir, (160, 120)).select([0, 0, 0])
    whole = estimate_obstacle_depth(batch, PipelineConfig())
    monkeypatch.setattr(run, "CHUNK_PIXELS", 160 * 120)  # one pair a chunk
    chunked = estimate_obstacle_depth(batch, PipelineConfig())
    tensors = list(_tensors(chunked))
    assert len(tensors) > 50 and not any(t.is_inference() for t in tensors)
    chunked.depth.objects.depth_median_m.mul_(1.0)  # an inference tensor would refuse this
    assert torch.equal(chunked.depth.objects.depth_median_m, whole.depth.objects.depth_median_m)
    assert torch.equal(chunked.object_labels, whole.object_labels) and torch.equal(chunked.status, whole.status)
    # A tensor each chunk's result held in several places is merged once and stays one tensor, as in one call.
    for result in (whole, chunked):
        right = result.segmentation.right
        assert right.binary is right.opened is right.kept_mask


def test_a_caller_in_inference_mode_gets_the_same_result_uncopied(data_dir):
    """A caller already in inference mode (guide's loop) asked for inference tensors: the result is not copied to
    ordinary ones, and holds the same values as an ordinary call's."""
    batch = _teddy(data_dir, (160, 120))
    plain = estimate_obstacle_depth(batch, PipelineConfig())
    with torch.inference_mode():
        inside = estimate_obstacle_depth(batch, PipelineConfig())
    tensors = list(_tensors(inside))
    given = [v for v in vars(batch).values() if isinstance(v, torch.Tensor)]  # the caller's own, passed through
    assert len(tensors) > 50 and all(t.is_inference() for t in tensors if not any(t is g for g in given))
    assert torch.equal(inside.depth.objects.depth_median_m, plain.depth.objects.depth_median_m)
    assert torch.equal(inside.object_labels, plain.object_labels) and torch.equal(inside.status, plain.status)


def test_a_hard_run_in_inference_mode_leaves_nothing_that_stops_training(data_dir):
    # The hard pipeline runs in inference mode (svs_torch.core.inference). Emptied first, the caches it fills (the
    # Hessian's tables, the 7-point solver's mixing matrix, the nearness network) must still train afterwards.
    from svs_torch.features.hessian import _inside_levels
    from svs_torch.geometry.minimal_solvers import _mixing_matrix
    from svs_torch.segmentation import network_files
    _inside_levels.cache_clear()
    _mixing_matrix.cache_clear()
    network_files._NET_CACHE.clear()
    plain = _teddy(data_dir, (160, 120))
    hard = estimate_obstacle_depth(plain, PipelineConfig())
    tensors = list(_tensors(hard))
    assert len(tensors) > 50 and not any(t.is_inference() for t in tensors)
    hard.depth.objects.depth_median_m.mul_(1.0)  # an inference tensor would refuse this
    assert not _mixing_matrix(torch.float64, torch.device("cpu")).is_inference()
    net = next(iter(network_files._NET_CACHE.values()))
    assert not any(p.is_inference() for p in net.parameters())
    batch = _requiring_grad(plain)
    result = estimate_obstacle_depth(batch, PipelineConfig(differentiable=True))
    assert torch.equal(result.hard_depth.objects.depth_median_m, hard.depth.objects.depth_median_m)
    result.depth.objects.depth_median_m[result.depth.objects.valid].sum().backward()
    assert int((batch.left.grad != 0).sum()) > 100


def test_the_nearest_obstacle_is_the_hard_pipelines_choice_with_soft_values():
    """Found by an audit: the differentiable pass chose the nearest obstacle again on its soft medians, so two
    obstacles a few hundredths of a millimetre apart swapped the warned side (slot 0, left -> slot 1, right) and the
    gradient trained the other obstacle. The slot, side and validity are the hard pipeline's; the depth is the soft
    median at that slot."""
    from svs_torch.data.synthetic import render_obstacle_scenes

    count, generator = 32, torch.Generator().manual_seed(2)
    depth = torch.stack([torch.full((count,), 1.5), 1.5 + (torch.rand(count, generator=generator) - 0.5) * 0.002], 1)
    center = torch.tensor([[-0.35, 0.0], [0.35, 0.0]]).expand(count, 2, 2)
    size = torch.tensor([[0.4, 0.6]] * 2).expand(count, 2, 2)
    batch = render_obstacle_scenes(depth, center, size, size_wh=(128, 96), generator=generator).batch
    batch = batch.select(torch.tensor([7]))  # the near tie whose soft medians order the other way
    result = estimate_obstacle_depth(_requiring_grad(batch), PipelineConfig(differentiable=True))
    hard, soft = result.hard_depth.nearest, result.depth.nearest
    for field in ("slot", "side", "valid"):
        assert torch.equal(getattr(soft, field), getattr(hard, field))
    medians = result.depth.objects.depth_median_m
    assert medians[0, 1] < medians[0, 0]  # the soft medians do order the other way
    assert soft.depth_m[0] == medians[0, hard.slot[0]] and soft.depth_m.requires_grad
    assert soft.surface_m[0] == result.depth.objects.depth_low_m[0, hard.slot[0]]
    # R_min is the same object (found by a second audit: it was chosen again on the soft medians, and its gradient
    # trained the other object); R_max the other one.
    depth_range = result.depth.range
    assert depth_range.r_min_m[0] == soft.depth_m[0] and depth_range.r_max_m[0] == medians[0, 1 - hard.slot[0]]
    (grad,) = torch.autograd.grad(depth_range.r_min_m.sum(), medians)
    assert grad[0, hard.slot[0]] == 1 and grad[0, 1 - hard.slot[0]] == 0


def test_without_the_row_fill_the_soft_depths_are_the_hard_ones(data_dir):
    """Found by an audit: the differentiable pass filled invalid pixels from their rows whatever
    DenseConfig.fill_invalid said, so with it off its 90th percentiles were up to 12.7 % from the hard ones."""
    batch = _requiring_grad(_teddy(data_dir, (160, 120)))
    config = PipelineConfig(differentiable=True, segmentation=SegmentationConfig(),
                            dense=DenseConfig(fill_invalid=False))
    result = estimate_obstacle_depth(batch, config)
    soft, hard = result.depth.objects, result.hard_depth.objects
    assert int(soft.valid.sum()) >= 2
    for field in ("depth_median_m", "depth_low_m", "depth_high_m"):
        error = ((getattr(soft, field).detach() - getattr(hard, field)).abs() / getattr(hard, field))[soft.valid]
        assert float(error.max()) < 0.005, field
