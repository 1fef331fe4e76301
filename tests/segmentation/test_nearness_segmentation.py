"""The nearness segmenter (issue 32): the rule against the truth's own procedure, the keep rules, the right view's
shifted regions, gradients, the default pipeline and clear errors."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from svs_torch.core.checks import InputError
from svs_torch.data.synthetic import random_obstacle_scenes
from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth
from svs_torch.segmentation.components import connected_components_with_stats, region_properties
from svs_torch.segmentation.learned import mask_iou, obstacle_truth
from svs_torch.segmentation.nearness import (NearnessNet, NearnessNetConfig, measure_nearness_disparity,
                                             nearness_logits, segment_stereo_nearness)
from svs_torch.segmentation.nearness_regions import shift_regions_to_right
from svs_torch.segmentation.network_files import load_obstacle_net, save_obstacle_net
from svs_torch.segmentation.segment import SegmentationConfig, keep_regions


@pytest.fixture(scope="module")
def scenes():
    return random_obstacle_scenes(3, 2, depth_range_m=(1.0, 1.8), background_depth_m=4.0, noise_std=0.01,
                                  generator=torch.Generator().manual_seed(3))


def test_untrained_network_is_the_truths_rule_on_the_measured_disparity(scenes):
    """A zero head leaves the rule: the near side of the Otsu split of the measured disparity, as
    obstacle_truth computes it from a disparity map (its own, independent histogram code)."""
    batch = scenes.batch
    net = NearnessNet().eval()
    logits, measured = nearness_logits(net, batch.left, batch.right)
    as_truth = obstacle_truth(dataclasses.replace(batch, disparity_px=measured.disparity_px,
                                                  disparity_valid=torch.ones_like(batch.disparity_valid),
                                                  disparity_nonoccluded=None))
    rule = logits > 0
    agree = (rule == as_truth.near).float().mean()
    assert agree > 0.995  # the two map disparities to 256 levels the same way; only split-level pixels may differ


def test_rule_finds_the_synthetic_obstacles(scenes):
    batch = scenes.batch
    seg = segment_stereo_nearness(batch, PipelineConfig().segmentation, NearnessNet().eval())
    truth = obstacle_truth(batch)
    assert bool((mask_iou(seg.left.kept_mask, truth.kept_mask) > 0.8).all())
    # The right view holds the same regions shifted by their disparity: compare with the truth's right view,
    # the synthetic scene's left truth moved by the true disparity of each object.
    assert bool((seg.right.kept_mask.flatten(1).sum(1) > 0.8 * seg.left.kept_mask.flatten(1).sum(1)).all())


def test_keep_rules_keep_a_small_near_region_before_a_large_far_one():
    mask = torch.zeros(1, 1, 40, 80, dtype=torch.bool)
    mask[..., 0:30, 0:40] = True  # a large region (label 1)
    mask[..., 0:20, 50:75] = True  # a medium region (label 2)
    mask[..., 34:39, 60:66] = True  # a small region, nearest (label 3, 30 px)
    labels, _, regions = connected_components_with_stats(mask, 8)
    nearness = torch.tensor([[3.0, 5.0, 20.0]])  # median disparities: label 3 is the nearest
    assert keep_regions(labels, regions, 2, "largest")[0].tolist() == [[1, 2]]
    assert keep_regions(labels, regions, 2, "nearest", 0, nearness)[0].tolist() == [[3, 2]]
    assert keep_regions(labels, regions, 2, "nearest_first", 0, nearness)[0].tolist() == [[3, 1]]
    # Below the least area it is no candidate: the paper's rule then decides.
    assert keep_regions(labels, regions, 2, "nearest_first", 31, nearness)[0].tolist() == [[2, 1]]
    kept, kept_mask = keep_regions(labels, regions, 3, "nearest_first", 0, nearness)
    assert kept.tolist() == [[3, 1, 2]] and int(kept_mask.sum()) == int(mask.sum())
    # A region under the least area is never kept beside one over it (a speck would be ranged from a handful
    # of pixels); with none over it, the paper's two largest.
    assert keep_regions(labels, regions, 2, "nearest_first", 600, nearness)[0].tolist() == [[1, -1]]
    assert keep_regions(labels, regions, 2, "nearest", 600, nearness)[0].tolist() == [[1, -1]]
    assert keep_regions(labels, regions, 2, "nearest_first", 5000, nearness)[0].tolist() == [[1, 2]]
    # The area held to the least area can be another count (the nearness segmenter's: pixels both cameras see).
    seen = torch.tensor([[0.0, 500.0, 30.0]])
    assert keep_regions(labels, regions, 2, "nearest_first", 31, nearness, seen)[0].tolist() == [[2, -1]]
    # No candidate by that count (every region in the band the right camera does not see): the largest regions,
    # but a region under the least area never beside one over it (an audit: guide on a floor 0.8 m below the camera
    # kept a 32-pixel scrap at the image's foot beside an unseen region of 652 and said "Stop" of it).
    assert keep_regions(labels, regions, 2, "nearest_first", 600, nearness, torch.zeros(1, 3))[0].tolist() == [[1, -1]]


def test_a_small_region_under_the_least_area_is_kept_only_where_it_is_the_nearest():
    """``near_min_area_px``: a thin near pole (30 px here) under the least area is still kept first where it is
    nearer than every region of the least area; a small region behind them, or one in a pair with none of the
    least area, stays out."""
    mask = torch.zeros(2, 1, 40, 80, dtype=torch.bool)
    mask[..., 0:30, 0:40] = True  # a large region (label 1)
    mask[..., 0:20, 50:75] = True  # a medium region (label 2)
    mask[..., 34:39, 60:66] = True  # a small region (label 3, 30 px)
    labels, _, regions = connected_components_with_stats(mask, 8)
    nearness = torch.tensor([[3.0, 5.0, 20.0],  # the small region is the nearest
                             [3.0, 5.0, 4.0]])  # the small region lies behind the medium one
    kept = keep_regions(labels, regions, 2, "nearest_first", 31, nearness, near_min_area_px=20)[0]
    assert kept.tolist() == [[3, 1], [2, 1]]
    assert keep_regions(labels, regions, 2, "nearest", 31, nearness, near_min_area_px=20)[0].tolist() == [
        [3, 2], [2, 1]]
    # The rule off (0), or its least area not below the least area (31, 40): as before.
    for near in (31, 0, 40):
        assert keep_regions(labels, regions, 2, "nearest_first", 31, nearness, near_min_area_px=near)[0].tolist() \
            == [[2, 1], [2, 1]]
    # Counted (e.g. measured) on under half its pixels, the small near region is filled rows: it stays out.
    seen = regions.area_px.clone()
    seen[:, 2] = 14
    assert keep_regions(labels, regions, 2, "nearest_first", 31, nearness, seen, near_min_area_px=10)[0].tolist() \
        == [[2, 1], [2, 1]]
    seen[:, 2] = 15
    assert keep_regions(labels, regions, 2, "nearest_first", 31, nearness, seen, near_min_area_px=10)[0].tolist() \
        == [[3, 1], [2, 1]]
    # A view without any region keeps none.
    empty = torch.zeros(1, 1, 8, 8, dtype=torch.long)
    none = region_properties(empty, torch.zeros(1, dtype=torch.long))
    assert keep_regions(empty, none, 2, "nearest_first", 31, torch.zeros(1, 0), near_min_area_px=10)[0].tolist() \
        == [[-1, -1]]
    # No region of the least area: the paper's two largest, the small near region not among them.
    assert keep_regions(labels, regions, 2, "nearest_first", 5000, nearness, near_min_area_px=20)[0].tolist() == [
        [1, 2], [1, 2]]


def test_the_least_areas_hold_at_their_value_and_a_tie_in_nearness_is_not_nearer():
    """The boundaries of the keep rule: a region of exactly ``min_area_px`` is a candidate, one of exactly
    ``near_min_area_px`` is a small near candidate, and a small region only as near as the nearest candidate (a
    tie) is not nearer than it, so it stays out."""
    mask = torch.zeros(1, 1, 40, 80, dtype=torch.bool)
    mask[..., 0:30, 0:40] = True  # a large region (label 1)
    mask[..., 0:20, 50:75] = True  # a medium region (label 2)
    mask[..., 34:39, 60:66] = True  # a small region (label 3, 30 px)
    labels, _, regions = connected_components_with_stats(mask, 8)
    assert regions.area_px[0, 2].item() == 30
    nearest = torch.tensor([[3.0, 5.0, 20.0]])
    assert keep_regions(labels, regions, 2, "nearest_first", 30, nearest)[0].tolist() == [[3, 1]]
    assert keep_regions(labels, regions, 2, "nearest_first", 31, nearest, near_min_area_px=30)[0].tolist() == [[3, 1]]
    assert keep_regions(labels, regions, 2, "nearest_first", 31, nearest, near_min_area_px=30.5)[0].tolist() == [
        [2, 1]]
    tied = torch.tensor([[3.0, 5.0, 5.0]])  # as near as the medium region
    assert keep_regions(labels, regions, 2, "nearest", 31, tied, near_min_area_px=20)[0].tolist() == [[2, 1]]
    assert keep_regions(labels, regions, 2, "nearest", 31, tied + torch.tensor([[0, 0, 1e-6]]),
                        near_min_area_px=20)[0].tolist() == [[3, 2]]


def test_near_min_area_fraction_is_checked():
    with pytest.raises(InputError, match="near_min_area_fraction"):
        SegmentationConfig(near_min_area_fraction=1.5)
    with pytest.raises(InputError, match="near_min_area_fraction"):
        SegmentationConfig(near_min_area_fraction="0.1")


def test_regions_without_stereo_are_not_kept():
    """A region in the band only the left camera sees, or of filled rows only (nothing measured), cannot be
    ranged by the dense stage: the nearness segmenter does not keep it (shared Midd1, Lampshade1, Rocks1 did)."""
    from svs_torch.segmentation.nearness_regions import _area_measured_in_view

    labels = torch.zeros(1, 1, 40, 100, dtype=torch.int64)
    labels[..., 5:35, 40:90] = 1  # near (disparity 20), seen by both cameras
    labels[..., 5:35, 2:15] = 2  # left of column 20: only the left camera sees it at the nearest disparity
    labels[..., 36:40, 30:90] = 3  # nothing measured (filled rows)
    regions = region_properties(labels, torch.tensor([3]))
    measured = torch.ones(1, 1, 40, 100, dtype=torch.bool)
    measured[..., 36:40, :] = False
    area = _area_measured_in_view(labels, regions, torch.tensor([[20.0, 5.0, 6.0]]), measured, 10.0)
    assert area.tolist() == [[1500.0, 0.0, 0.0]]


def test_regions_mostly_clipped_at_white_are_not_candidates():
    """``SegmentationConfig.max_clipped_share``: a region with at least that share of its left-view pixels at the
    clipped level (255 / 255, and the round-off above 254.5 / 255) gets no candidate area; one just under keeps
    its area, and so does every region with the rule off (None)."""
    from svs_torch.core.levels import CLIPPED_LEVEL
    from svs_torch.segmentation.nearness_regions import _without_clipped

    labels = torch.zeros(1, 1, 10, 40, dtype=torch.int64)
    labels[..., :, 0:10], labels[..., :, 10:20], labels[..., :, 20:30] = 1, 2, 3  # 100 pixels each
    left = torch.full((1, 1, 10, 40), 0.5)
    left[..., :5, 0:10] = 1.0  # region 1: 50 % clipped
    left[..., :4, 10:20] = 254.6 / 255  # region 2: 40 % clipped (round-off above the level counts)
    left[..., 4, 10:20] = 254.4 / 255  # ... and just under the level does not
    left[..., :, 20:30] = 1.0  # region 3: all clipped
    assert float(left[0, 0, 0, 10]) >= CLIPPED_LEVEL > float(left[0, 0, 4, 10])
    regions = region_properties(labels, torch.tensor([3]))
    area = torch.tensor([[80.0, 70.0, 60.0]])
    assert _without_clipped(area, labels, regions, left, 0.5).tolist() == [[0.0, 70.0, 0.0]]
    assert _without_clipped(area, labels, regions, left, 0.4).tolist() == [[0.0, 0.0, 0.0]]
    assert torch.equal(_without_clipped(area, labels, regions, left, None), area)
    assert PipelineConfig().segmentation.max_clipped_share == 0.5 and SegmentationConfig().max_clipped_share is None
    for bad in (0, 1.5, True, "0.5"):
        with pytest.raises(InputError, match="max_clipped_share"):
            SegmentationConfig(max_clipped_share=bad)


def test_shift_regions_to_right_moves_each_region_by_its_disparity():
    labels = torch.zeros(1, 1, 6, 30, dtype=torch.int64)
    labels[..., 1:3, 10:20] = 1
    labels[..., 3:5, 22:28] = 2
    right = shift_regions_to_right(labels, torch.tensor([[1, 2]]), torch.tensor([[4.0, 6.4]]))
    expected = torch.zeros_like(labels)
    expected[..., 1:3, 6:16] = 1
    expected[..., 3:5, 16:22] = 2
    assert torch.equal(right, expected)
    # Left alone at the last two stops: float labels were taken in silence (float labels out).
    for args, name in (((labels.float(), torch.tensor([[1, 2]]), torch.tensor([[4.0, 6.4]])), "labels"),
                       ((labels, torch.tensor([[1.0, 2.0]]), torch.tensor([[4.0, 6.4]])), "kept_labels"),
                       ((labels, torch.tensor([[1, 2]]), torch.tensor([[4, 6]])), "shift_px")):
        with pytest.raises(InputError, match=f"^{name}: expected a"):
            shift_regions_to_right(*args)


def test_segment_stereo_nearness_refuses_no_net_even_with_the_left_logits(scenes):
    """``net=None`` with ``left_logits`` failed with an AttributeError on ``net.config`` from inside: the net's
    configuration (its probability threshold, its matcher) is read with the caller's logits too."""
    batch = scenes.batch
    logits, measured = nearness_logits(NearnessNet().eval(), batch.left, batch.right)
    for extra in ({}, {"measured": measured}):
        with pytest.raises(InputError, match="^net: expected a NearnessNet, got NoneType$"):
            segment_stereo_nearness(batch, PipelineConfig().segmentation, None, left_logits=logits, **extra)


@pytest.mark.parametrize("threads", [1, 2])
def test_shift_regions_kernel_gives_the_torch_paths_labels(monkeypatch, threads):
    # Overlapping regions (the nearer wins, the earlier slot on equal shifts), shifts off either side, halves that
    # round to even, empty (0) and dropped (-1) slots: the kernel's labels are the torch path's exactly.
    generator = torch.Generator().manual_seed(7)
    labels = torch.randint(0, 5, (3, 1, 9, 40), generator=generator)
    kept = torch.tensor([[1, 2, 3], [4, 0, 2], [3, -1, 3]])
    shift = torch.tensor([[2.5, 3.5, 3.5], [-4.0, 5.0, 45.0], [39.6, 1.0, -0.5]])
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        fused = shift_regions_to_right(labels, kept, shift)
        monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
        eager = shift_regions_to_right(labels, kept, shift)
    finally:
        torch.set_num_threads(before)
    assert torch.equal(fused, eager) and int((eager > 0).sum()) > 100


def test_gradients_reach_the_network_and_both_images(scenes):
    torch.manual_seed(0)
    net = NearnessNet(NearnessNetConfig(working_width_px=160, network_width_px=48))
    torch.nn.init.normal_(net.head.weight, std=0.1)
    batch = scenes.batch
    left = batch.left[:1, :, :120, :160].clone().requires_grad_()
    right = batch.right[:1, :, :120, :160].clone().requires_grad_()
    logits, _ = nearness_logits(net, left, right)
    logits.sigmoid().mean().backward()
    assert left.grad.abs().sum() > 0 and right.grad.abs().sum() > 0
    assert all(p.grad is not None and bool(torch.isfinite(p.grad).all()) for p in net.parameters())
    assert net.head.weight.grad.abs().sum() > 0


def test_network_gradcheck_float64():
    net = NearnessNet(NearnessNetConfig(channels=(4, 4, 4))).double()
    torch.nn.init.normal_(net.head.weight, std=0.1)
    features = torch.randn(1, 5, 8, 12, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(net, (features,), eps=1e-6, atol=1e-5)


def test_measured_disparity_is_hard_forward_soft_backward(scenes):
    batch = scenes.batch
    config = NearnessNetConfig(working_width_px=160)
    with torch.no_grad():
        hard = measure_nearness_disparity(batch.left, batch.right, config)
    left = batch.left.clone().requires_grad_()
    soft = measure_nearness_disparity(left, batch.right, config)
    assert torch.equal(soft.disparity_px.detach(), hard.disparity_px)
    soft.disparity_px.sum().backward()
    assert left.grad.abs().sum() > 0


def test_default_pipeline_runs_the_nearness_segmenter_and_trains_through_it(scenes):
    config = PipelineConfig()
    assert config.segmentation.segmenter == "nearness" and config.segmentation.keep == "nearest_first"
    assert PipelineConfig.paper().segmentation == SegmentationConfig()  # the paper: Otsu, the two largest
    result = estimate_obstacle_depth(scenes.batch, config)
    assert bool((result.status == 0).all())
    net = load_obstacle_net("nearness")
    batch = dataclasses.replace(scenes.batch, left=scenes.batch.left.clone().requires_grad_())
    differentiable = estimate_obstacle_depth(batch, dataclasses.replace(config, differentiable=True), network=net)
    depth = differentiable.depth.objects.depth_median_m
    valid = differentiable.depth.objects.valid
    depth[valid].sum().backward()
    assert batch.left.grad.abs().sum() > 0
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in net.parameters())


def test_clear_errors(tmp_path):
    with pytest.raises(InputError, match="keep: .nearest. ranks"):
        SegmentationConfig(keep="nearest")
    with pytest.raises(InputError, match="min_area_fraction"):
        SegmentationConfig(segmenter="nearness", keep="nearest", min_area_fraction=2)
    with pytest.raises(InputError, match="segmenter: expected otsu, nearness"):
        SegmentationConfig(segmenter="nearnes")
    with pytest.raises(InputError, match="no weights file"):
        SegmentationConfig(segmenter="nearness:/no/such/file.pt")
    old = tmp_path / "old.pt"
    from svs_torch.segmentation.network import ObstacleNet
    save_obstacle_net(old, ObstacleNet())
    with pytest.raises(InputError, match="is a learned network file, not a nearness one \\(give it as learned:PATH\\)"):
        load_obstacle_net(f"nearness:{old}")
    new = tmp_path / "new.pt"
    save_obstacle_net(new, NearnessNet())
    assert isinstance(load_obstacle_net(f"nearness:{new}"), NearnessNet)
    with pytest.raises(InputError, match="window_size"):
        NearnessNetConfig(window_size=8)


@pytest.mark.parametrize("flags, message", [
    (torch.tensor([True]), r"^{name}: expected \(2\), got \(1\)$"),
    (torch.tensor([True, False, True]), r"^{name}: expected \(2\), got \(3\)$"),
    (torch.tensor([1, 0]), r"^{name}: expected a bool tensor, got torch.int64$"),
    ([True, False], r"^{name}: expected a torch.Tensor of shape \(2\), got list$")], ids=["one", "three", "int", "list"])
def test_the_denoising_steps_called_by_hand_name_their_pairs_flags(flags, message):
    """Found by an audit of the nearness segmenter's pieces called by hand: soft_match_by_noise given ``widened`` of
    one flag for two pairs returned a map of one pair in silence, and denoised_map (with max_fill_px) flagged both
    pairs with it; three flags failed in index_select, int flags in a bool where, a list on ``.any``."""
    from svs_torch.depth.dense_config import DenseConfig
    from svs_torch.segmentation.nearness_denoise import denoised_map, match_by_noise, soft_match_by_noise
    views = torch.rand(2, 2, 1, 20, 30, generator=torch.Generator().manual_seed(0)).unbind(1)
    dense, config = DenseConfig(window_size=5), NearnessNetConfig(max_fill_px=2)
    found, widened = match_by_noise(*views, 8, dense, config)
    assert soft_match_by_noise(*views, 8, dense, config, widened).shape == (2, 1, 20, 30)
    with pytest.raises(InputError, match=message.format(name="widened")):
        soft_match_by_noise(*views, 8, dense, config, flags)
    with pytest.raises(InputError, match=message.format(name="noisy")):
        denoised_map(*views, found, 8, dense, config, flags)


def test_the_denoising_steps_called_by_hand_name_a_wrong_setting():
    """Found by the same audit: a DenseConfig given for the nearness settings failed on its first field
    (AttributeError), and reduced_to_width took 0 columns (an empty map) and failed deep in torch for -5 or 2.5."""
    from svs_torch.depth.dense_config import DenseConfig
    from svs_torch.segmentation.nearness_denoise import match_by_noise, reduced_to_width, soft_match_by_noise
    views = torch.rand(2, 2, 1, 20, 30, generator=torch.Generator().manual_seed(0)).unbind(1)
    dense = DenseConfig(window_size=5)
    with pytest.raises(InputError, match="^config: expected a NearnessNetConfig, got DenseConfig$"):
        match_by_noise(*views, 8, dense, dense)
    with pytest.raises(InputError, match="^dense: expected a DenseConfig, got NearnessNetConfig$"):
        soft_match_by_noise(*views, 8, NearnessNetConfig(), NearnessNetConfig(), torch.tensor([True, False]))
    for width in (0, -5, 2.5, "10"):
        with pytest.raises(InputError, match=f"^width: expected an int >= 1, got {width!r}$"):
            reduced_to_width(views[0], width)
    assert reduced_to_width(views[0], 10).shape == (2, 1, 7, 10)


def test_measuring_nearness_by_hand_names_a_wrong_setting_or_network():
    """Found by an audit of the nearness segmenter called by hand: measure_nearness_disparity given a DenseConfig for
    its settings or its floor's failed on their first field (AttributeError), took camera_frames="no" as True, and
    nearness_logits given an ObstacleNet or None failed on its config."""
    from svs_torch.depth.dense_config import DenseConfig
    from svs_torch.segmentation.ground_plane import GroundPlaneConfig
    from svs_torch.segmentation.network import ObstacleNet
    left = torch.rand(2, 1, 20, 30, generator=torch.Generator().manual_seed(0))
    right, rig = torch.roll(left, -2, -1), torch.full((2,), 0.1)
    with pytest.raises(InputError, match="^config: expected a NearnessNetConfig, got DenseConfig$"):
        measure_nearness_disparity(left, right, DenseConfig())
    with pytest.raises(InputError, match="^ground: expected a GroundPlaneConfig, got DenseConfig$"):
        measure_nearness_disparity(left, right, NearnessNetConfig(), DenseConfig(), rig)
    with pytest.raises(InputError, match="^camera_frames: expected a bool, got 'no'$"):
        measure_nearness_disparity(left, right, camera_frames="no")
    with pytest.raises(InputError, match="^right: expected the left view's dtype torch.float32, got torch.float64$"):
        measure_nearness_disparity(left, right.double())
    for net, kind in ((ObstacleNet(), "ObstacleNet"), (None, "NoneType")):
        with pytest.raises(InputError, match=f"^net: expected a NearnessNet, got {kind}$"):
            nearness_logits(net, left, right)
    assert measure_nearness_disparity(left, right, NearnessNetConfig(), GroundPlaneConfig(), rig).ground is not None


def test_the_split_called_by_hand_names_a_bad_argument():
    """Found by an audit of the nearness segmenter's pieces called by hand: nearness_split took no look at its
    arguments, so a float exclude mask failed in a bitwise and (NotImplementedError), one of another size in the
    quantiles naming their labels, and a map without its channel axis was taken as one of B = 1."""
    from svs_torch.segmentation.nearness_split import nearness_split
    disparity = torch.rand(1, 1, 10, 10, generator=torch.Generator().manual_seed(0)) * 20
    half = torch.zeros(1, 1, 10, 10, dtype=torch.bool)
    half[..., :2, :] = True
    with pytest.raises(InputError, match="^exclude: expected a bool tensor, got torch.float32$"):
        nearness_split(disparity, 0.1, half.float())
    with pytest.raises(InputError, match=r"^exclude: expected \(1, 1, 10, 10\), got \(1, 1, 5, 10\)$"):
        nearness_split(disparity, 0.1, half[..., :5, :])
    with pytest.raises(InputError, match=r"^disparity: expected \(B, 1, H, W\), got \(1, 10, 10\)$"):
        nearness_split(disparity[:, 0], 0.1)
    with pytest.raises(InputError, match="^min_near_share: expected a finite number"):
        nearness_split(disparity, "0.1")
    assert nearness_split(disparity, 2.0, half)[2].tolist() == [True]  # a share past 1: always taken again


def test_region_medians_equal_the_kept_region_lower_median():
    """The two-sort median per region equals depth.kept_region_lower_median over every label (its (B, L, P) form)."""
    from svs_torch.depth.quantiles import kept_region_lower_median
    from svs_torch.segmentation.nearness_regions import _region_median_disparity

    generator = torch.Generator().manual_seed(1)
    for _ in range(30):
        labels = torch.randint(0, 6, (3, 1, 7, 9), generator=generator)
        values = torch.randint(0, 5, (3, 1, 7, 9), generator=generator).float()  # ties, as filled disparities
        count = labels.flatten(1).amax(1)
        every = torch.arange(1, int(count.max()) + 1).expand(3, -1)
        expected, _ = kept_region_lower_median(values, torch.ones_like(labels, dtype=torch.bool), labels, every)
        assert torch.equal(_region_median_disparity(values, labels, count), expected)


def test_a_zero_head_skips_the_network_with_the_same_logits(scenes):
    """The shipped correction adds nothing (validate_nearness.py chose the rule): deployment skips its pass, and
    the logits are those the network's pass gives (training, which needs its graph, still runs it)."""
    batch = scenes.batch
    net = NearnessNet().eval()
    assert net.adds_nothing()
    with torch.no_grad():
        skipped, _ = nearness_logits(net, batch.left, batch.right)
    full, _ = nearness_logits(net, batch.left, batch.right)  # parameters require grad: the network runs
    assert full.requires_grad and torch.equal(skipped, full.detach())
    with torch.no_grad():
        net.head.bias.fill_(0.5)
        assert not net.adds_nothing()
        shifted, _ = nearness_logits(net, batch.left, batch.right)
    assert torch.allclose(shifted, skipped + 0.5)


def test_every_region_the_default_keeps_on_real_scenes_is_ranged(data_dir):
    """Real scenes where the nearness segmenter once kept a region the dense stage cannot range (a band of
    filled rows in Midd1, a strip only the left camera sees in Lampshade1 and Rocks1; eval scored them 0 %): every
    kept region now has a depth, at 320 px and native size."""
    from svs_torch.data import load_stereo_pair, resize_stereo_batch

    for name in ("Midd1", "Lampshade1", "Rocks1"):
        native = load_stereo_pair(data_dir / "middlebury_2005_2006_third" / name)
        for batch in (native, resize_stereo_batch(native, (320, 240))):
            result = estimate_obstacle_depth(batch, PipelineConfig())
            kept = result.segmentation.left.kept_labels >= 0
            assert int(result.status[0]) == 0 and bool(kept.any())
            assert torch.equal(result.depth.objects.valid[:, :kept.shape[1]] & kept, kept), name


def test_views_of_two_scenes_fall_back_to_otsu_pair_by_pair(data_dir):
    """A misconnected camera (left of one scene, right of another): the block matcher accepts little of the view,
    and the default segments that pair as Otsu and the paper's two largest regions, while the real pair beside it
    in the batch keeps the nearness segmenter (experiments/nearness_fallback.md)."""
    from svs_torch.data import collate_stereo_batches, load_stereo_pair, resize_stereo_batch
    from svs_torch.segmentation.segment import segment_stereo

    teddy, cones = (resize_stereo_batch(load_stereo_pair(data_dir / "middlebury_2003_quarter" / name), (320, 240))
                    for name in ("Teddy", "Cones"))
    mixed = dataclasses.replace(teddy, right=cones.right)
    batch = collate_stereo_batches([teddy, mixed])
    config = PipelineConfig().segmentation
    seg = segment_stereo_nearness(batch, config, NearnessNet().eval())
    alone = segment_stereo_nearness(teddy, config, NearnessNet().eval())
    otsu = segment_stereo(mixed, SegmentationConfig())
    assert torch.equal(seg.left.kept_mask[:1], alone.left.kept_mask)
    assert torch.equal(seg.left.kept_mask[1:], otsu.left.kept_mask)
    assert torch.equal(seg.right.kept_mask[1:], otsu.right.kept_mask)
    never = dataclasses.replace(config, min_measured_share=0.0)
    assert not torch.equal(segment_stereo_nearness(mixed, never, NearnessNet().eval()).left.kept_mask,
                           otsu.left.kept_mask)
    # With the coarse check on, whose map accepts chance matches of unrelated views too, the pair still falls back:
    # the fallback reads the fine matcher's share.
    checked = NearnessNet(NearnessNetConfig(sparse_reduction=4)).eval()
    assert torch.equal(segment_stereo_nearness(mixed, config, checked).left.kept_mask, otsu.left.kept_mask)
    with pytest.raises(InputError, match="min_measured_share"):
        SegmentationConfig(min_measured_share=1.5)


def _camera_frame(image: torch.Tensor, quality: int, sigma_levels: float, seed: int) -> torch.Tensor:
    """One view as an SVS board sends it: Gaussian sensor noise, then a baseline JPEG at OpenCV ``quality``."""
    import cv2
    import numpy as np

    noise = torch.randn(image.shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    levels = (image.double() * 255 + sigma_levels * noise).round().clamp(0, 255).to(torch.uint8)[0, 0].numpy()
    decoded = cv2.imdecode(cv2.imencode(".jpg", levels, [cv2.IMWRITE_JPEG_QUALITY, quality])[1], cv2.IMREAD_GRAYSCALE)
    return torch.from_numpy(decoded.astype(np.float32) / 255)[None, None]


def test_camera_frames_keep_the_clean_pairs_obstacles(data_dir):
    """Shelves (a train scene) at 320×240 as camera frames (JPEG 95 and 70 with σ 2 and 4 levels of noise in each
    view): the noise matches in flat areas once moved the Otsu split from 14 to 31 px and the kept "nearest" regions
    shrank from 21 065 to 225 px of specks. The median over the halved map keeps the clean pair's obstacles; without
    it (median_window=1, the block matcher's own uniqueness) and without the split taken again under the 90th
    percentile (min_near_share=0) they are lost; the split taken again alone recovers most of them."""
    from svs_torch.data import load_stereo_pair, resize_stereo_batch

    clean = resize_stereo_batch(load_stereo_pair(data_dir / "middlebury_eval3_Q" / "Shelves"), (320, 240))
    config = PipelineConfig().segmentation
    reference = segment_stereo_nearness(clean, config, NearnessNet().eval()).left.kept_mask
    for quality, sigma in ((95, 2.0), (70, 4.0)):
        frames = dataclasses.replace(clean, left=_camera_frame(clean.left, quality, sigma, 1),
                                     right=_camera_frame(clean.right, quality, sigma, 2))
        kept = segment_stereo_nearness(frames, config, NearnessNet().eval()).left.kept_mask
        assert float(mask_iou(kept, reference)[0]) > 0.7, quality  # 0.83 and 0.76
        raw = NearnessNet(NearnessNetConfig(median_window=1, uniqueness_ratio=0.1, min_near_share=0.0)).eval()
        assert float(mask_iou(segment_stereo_nearness(frames, config, raw).left.kept_mask, reference)[0]) < 0.1
        retaken = NearnessNet(NearnessNetConfig(median_window=1, uniqueness_ratio=0.1)).eval()
        segmented = segment_stereo_nearness(frames, config, retaken)
        assert bool(segmented.split_retaken[0]), quality
        assert float(mask_iou(segmented.left.kept_mask, reference)[0]) > 0.5, quality


def test_median_of_the_halved_map_against_a_per_pixel_reference():
    from svs_torch.segmentation.nearness_denoise import _median_halved

    generator = torch.Generator().manual_seed(0)
    disparity = torch.randint(0, 40, (2, 1, 11, 14), generator=generator).float()
    out = _median_halved(disparity, 3)
    halved = torch.nn.functional.avg_pool2d(disparity, 2, ceil_mode=True)  # (2, 1, 6, 7)
    h, w = halved.shape[-2:]
    for b in range(2):
        for y in range(11):
            for x in range(14):
                ys = [min(max(y // 2 + dy, 0), h - 1) for dy in (-1, 0, 1)]
                xs = [min(max(x // 2 + dx, 0), w - 1) for dx in (-1, 0, 1)]
                values = sorted(float(halved[b, 0, yy, xx]) for yy in ys for xx in xs)
                assert float(out[b, 0, y, x]) == values[4]
    assert torch.equal(_median_halved(disparity, 1), disparity)
    assert _median_halved(torch.ones(1, 1, 1, 1), 7).shape == (1, 1, 1, 1)  # a map smaller than the window
    with pytest.raises(InputError, match="median_window"):
        NearnessNetConfig(median_window=4)


def test_a_sparse_map_gets_the_wider_median():
    """A map whose block matcher accepted less than ``sparse_share`` of the view (a camera frame's noise) is
    filtered by ``sparse_median_window``, the others by ``median_window``, pair by pair in one batch; settings
    out of range are refused by name."""
    from svs_torch.segmentation.nearness_denoise import _median_by_share, _median_halved

    generator = torch.Generator().manual_seed(3)
    disparity = torch.randint(0, 40, (3, 1, 30, 40), generator=generator).float()
    valid = torch.zeros(3, 1, 30, 40, dtype=torch.bool)
    valid[0] = True  # all accepted
    valid[1, ..., :8] = True  # 20 %: sparse
    valid[2, ..., :20] = True  # 50 %
    config = NearnessNetConfig()
    sparse = valid.flatten(1).float().mean(1) < config.sparse_share
    assert sparse.tolist() == [False, True, False]
    out = _median_by_share(disparity, sparse, config)
    for b, window in ((0, config.median_window), (1, config.sparse_median_window), (2, config.median_window)):
        assert torch.equal(out[b:b + 1], _median_halved(disparity[b:b + 1], window)), b
    assert not torch.equal(out[1:2], _median_halved(disparity[1:2], config.median_window))
    assert torch.equal(_median_by_share(disparity[1:2], sparse[1:2], config),
                       _median_halved(disparity[1:2], config.sparse_median_window))
    with pytest.raises(InputError, match="sparse_median_window"):
        NearnessNetConfig(sparse_median_window=10)
    with pytest.raises(InputError, match="sparse_share"):
        NearnessNetConfig(sparse_share=1.5)


def test_a_split_above_nearly_every_pixel_is_taken_again_under_the_90th_percentile():
    """Wrong matches far above the scene (4 % of the map at 60–70 px where the scene lies at 8–18 px) draw the
    Otsu split between them and the scene: the near side is those outliers alone. Under ``min_near_share`` the
    split is taken again over the map clipped at its 90th percentile, pair by pair; a pair whose split leaves a
    near side keeps it; 0 turns the rule off; out of range is refused by name."""
    from svs_torch.segmentation.nearness_split import nearness_split

    generator = torch.Generator().manual_seed(5)
    disparity = 8 + 10 * torch.rand(2, 1, 40, 50, generator=generator)
    disparity[0, :, :, :2] = 60 + 10 * torch.rand(40, 2, generator=generator)  # 4 % outliers
    disparity[1, :, 20:] += 12  # a near half (20–30 px), no outliers
    split_off, _, retaken_off = nearness_split(disparity, 0.0)
    assert float((disparity[0] > split_off[0]).float().mean()) < 0.05  # the outliers alone are near
    assert not bool(retaken_off.any())
    split, spread, retaken = nearness_split(disparity, 0.1)
    assert retaken.tolist() == [True, False]
    assert 8 < float(split[0]) < 18 and float((disparity[0] > split[0]).float().mean()) > 0.2
    assert float(split[1]) == float(split_off[1]) and 18 < float(split[1]) < 22
    assert bool((spread >= 1).all())
    with pytest.raises(InputError, match="min_near_share"):
        NearnessNetConfig(min_near_share=1.0)


def test_a_second_split_inside_one_surface_is_not_taken():
    """A small near object before a flat wall (4 % of the map at 20 px; the wall at 10 px within 0.05, as the
    filled and median-filtered map of a rendered wall is, with 0.5 % of unfilled pixels at 0) leaves the same
    small near share as wrong matches do, but the wall holds the 90th percentile, so the second split falls between
    the unfilled pixels and the wall and leaves nearly every pixel near. Such a split is not taken
    (``max_retaken_near_share``): the first split, between the wall and the object, stands; at 1 it is taken."""
    from svs_torch.segmentation.nearness_split import nearness_split

    generator = torch.Generator().manual_seed(7)
    disparity = 10 + 0.05 * torch.rand(1, 1, 50, 50, generator=generator)
    disparity[..., 20:30, 20:30] = 20.0  # 4 % of the map
    disparity[..., 0, :12] = 0.0  # 0.5 %
    split, _, retaken = nearness_split(disparity, 0.1, None, 0.9)
    assert not bool(retaken[0]) and 10.05 < float(split[0]) < 20
    assert float((disparity > split[0]).float().mean()) == pytest.approx(0.04)
    split_always, _, retaken_always = nearness_split(disparity, 0.1, None, 1.0)
    assert bool(retaken_always[0]) and float((disparity > split_always[0]).float().mean()) > 0.99
    with pytest.raises(InputError, match="max_retaken_near_share"):
        NearnessNetConfig(max_retaken_near_share=0.0)
    with pytest.raises(InputError, match="max_retaken_near_share"):
        NearnessNetConfig(max_retaken_near_share=1.5)


def test_a_second_split_through_one_walls_noise_is_not_taken():
    """A camera frame's wall is no flat level but noise (here 10 px ± 0.5): the second split cuts it in two, about
    half the view near, both sides' medians about 5 % apart. Such a split is not taken (``min_retaken_gap``), and
    the first, between the wall and the object, stands; wrong matches far above a scene still take it again."""
    from svs_torch.segmentation.nearness_split import nearness_split

    generator = torch.Generator().manual_seed(7)
    wall = 10 + torch.rand(1, 1, 50, 50, generator=generator) - 0.5
    wall[..., 20:30, 20:30] = 20.0  # 4 % of the map
    split, _, retaken = nearness_split(wall, 0.1, None, 0.9, 0.1)
    assert not bool(retaken[0]) and 10.5 < float(split[0]) < 20
    cut, _, retaken_cut = nearness_split(wall, 0.1, None, 0.9, 0.0)
    assert bool(retaken_cut[0]) and 0.3 < float((wall > cut[0]).float().mean()) < 0.7
    scene = 8 + 10 * torch.rand(1, 1, 40, 50, generator=generator)
    scene[..., :2] = 60 + 10 * torch.rand(40, 2, generator=generator)  # 4 % wrong matches far above it
    assert bool(nearness_split(scene, 0.1, None, 0.9, 0.1)[2][0])
    with pytest.raises(InputError, match="min_retaken_gap"):
        NearnessNetConfig(min_retaken_gap=1.0)


@pytest.mark.parametrize("depth_m, digit", [(1.25, None), (1.75, None), (1.5, 4)])
def test_a_small_obstacle_before_a_flat_wall_is_named_the_nearest(depth_m, digit):
    """Issue 32: a small near obstacle is never dropped for a large far wall. A 0.25 x 0.4 m box 1.25-1.75 m ahead
    of a textured wall at 4.5 m (3-6 % of a 320x240 view), clean or as the board's digit 4 frames, is kept and
    ranged within 2 %; with every second split taken (``max_retaken_near_share=1``, ``min_retaken_gap=0``, the rule
    before) the wall was kept with it: nearly the whole view clean, about half of it in a camera frame
    (experiments/small_near_obstacles.md)."""
    from svs_torch.data import camera_frame_pairs
    from svs_torch.data.synthetic import render_obstacle_scenes

    scenes = render_obstacle_scenes(torch.tensor([[depth_m]]), torch.tensor([[[0.2, 0.1]]]),
                                    torch.tensor([[[0.25, 0.4]]]), background_depth_m=4.5,
                                    generator=torch.Generator().manual_seed(0))
    batch = scenes.batch if digit is None else camera_frame_pairs(scenes.batch, digit, 4.0,
                                                                  torch.Generator().manual_seed(1))
    result = estimate_obstacle_depth(batch, PipelineConfig())
    assert abs(float(result.depth.nearest.depth_m[0]) - depth_m) < 0.02 * depth_m
    box = scenes.object_ids > 0
    assert float(mask_iou(result.segmentation.left.kept_mask, box)[0]) > 0.6
    config = dataclasses.replace(load_obstacle_net("nearness").config, max_retaken_near_share=1.0, min_retaken_gap=0.0)
    seg_before = segment_stereo_nearness(batch, PipelineConfig().segmentation, NearnessNet(config).eval())
    assert float(seg_before.left.kept_mask.float().mean()) > (0.9 if digit is None else 0.3)


def test_pianol_is_ranged_at_its_obstacle(data_dir):
    """The tuned PianoL at 320×240 (the two views lit differently): 2.6 % of the measured map lies above 25 working
    px where 90 % lies under 18, the Otsu split fell above the scene, the kept regions were specks and the pair went
    unranged (NO_DENSE_DEPTH). Taken again under the 90th percentile, the split keeps the piano, ranged within 2 %
    of its true distance (experiments/select_min_near_share.md); with the rule off the pair is still lost."""
    from svs_torch.data import load_stereo_pair, resize_stereo_batch
    from svs_torch.pipeline import PipelineStatus

    batch = resize_stereo_batch(load_stereo_pair(data_dir / "middlebury_eval3_Q" / "PianoL"), (320, 240))
    truth = obstacle_truth(batch)
    result = estimate_obstacle_depth(batch, PipelineConfig())
    assert int(result.status[0]) == PipelineStatus.OK
    real = float(truth.nearest_m[0])
    assert abs(float(result.depth.nearest.depth_m[0]) - real) < 0.02 * real
    assert float(mask_iou(result.segmentation.left.kept_mask, truth.kept_mask)[0]) > 0.5
    off = NearnessNet(NearnessNetConfig(min_near_share=0.0)).eval()
    seg_off = segment_stereo_nearness(batch, PipelineConfig().segmentation, off)
    assert float(mask_iou(seg_off.left.kept_mask, truth.kept_mask)[0]) < 0.1


def _dim_piano_frames(data_dir, quality: int, sigma: float):
    """Piano (a tuned scene) at 320×240 with both views' contrast halved about the left view's mean, as
    experiments/real_rig.py --contrast 0.5 makes it, and the same pair as camera frames."""
    from svs_torch.data import load_stereo_pair, resize_stereo_batch

    clean = resize_stereo_batch(load_stereo_pair(data_dir / "middlebury_eval3_Q" / "Piano"), (320, 240))
    mean = clean.left.mean()
    clean = dataclasses.replace(clean, left=(mean + 0.5 * (clean.left - mean)).clamp(0, 1),
                                right=(mean + 0.5 * (clean.right - mean)).clamp(0, 1))
    frames = dataclasses.replace(clean, left=_camera_frame(clean.left, quality, sigma, 1),
                                 right=_camera_frame(clean.right, quality, sigma, 2))
    return clean, frames


def test_a_sparse_camera_frame_is_checked_against_the_coarse_map(data_dir):
    """Dim Piano as camera frames (JPEG 50, the board's digit 6, with σ 6 levels): the block matcher accepts 17 %
    of the view, under ``sparse_share``, and the segmenter kept noise matches (IoU with the clean pair's kept
    regions 0.15). Its matches checked against the pair measured at half the working width
    (:mod:`svs_torch.segmentation.nearness_denoise`, ``sparse_reduction=2``) keep the clean pair's obstacles;
    without the check (``sparse_reduction=1``, the default) they are lost. The pair's result is the same alone
    and beside a clean pair, which never takes the coarse path. The fallback to Otsu (``min_measured_share``)
    reads the fine matcher's share (``matched_share``), which the coarse map does not raise (it raises
    ``measured``), for views of two scenes leave about as much. Both with the working window alone
    (``noisy_window_size=7``): the wider window of noisy pairs (the next test) keeps them too."""
    clean, frames = _dim_piano_frames(data_dir, 50, 6.0)
    config = dataclasses.replace(PipelineConfig().segmentation, min_measured_share=0.0)
    fine_only = NearnessNet(NearnessNetConfig(noisy_window_size=7)).eval()
    net = NearnessNet(dataclasses.replace(fine_only.config, sparse_reduction=2)).eval()
    reference = segment_stereo_nearness(clean, config, net).left.kept_mask
    measured = measure_nearness_disparity(frames.left, frames.right, net.config)
    unchecked = measure_nearness_disparity(frames.left, frames.right, fine_only.config)
    assert float(unchecked.measured.float().mean()) < net.config.sparse_share  # the fine matcher's share
    assert float(measured.measured.float().mean()) > float(unchecked.measured.float().mean())
    assert torch.equal(measured.matched_share, unchecked.matched_share)
    kept = segment_stereo_nearness(frames, config, net).left.kept_mask
    lost = segment_stereo_nearness(frames, config, fine_only).left.kept_mask
    assert float(mask_iou(kept, reference)[0]) > 0.6  # 0.72
    assert float(mask_iou(lost, reference)[0]) < 0.3  # 0.15
    both = measure_nearness_disparity(torch.cat([clean.left, frames.left]), torch.cat([clean.right, frames.right]),
                                      net.config)
    assert torch.equal(both.disparity_px[1:], measured.disparity_px)
    assert torch.equal(both.disparity_px[:1], measure_nearness_disparity(clean.left, clean.right,
                                                                         fine_only.config).disparity_px)


def test_fine_matches_are_kept_where_they_agree_with_the_coarse_map():
    """:func:`~svs_torch.segmentation.nearness_denoise._checked_against_coarse` on views whose coarse map is a
    known constant: a fine match within ``sparse_agreement_px`` of it stays, one farther off takes the coarse
    value, and a pixel the fine matcher rejected is valid where the coarse matcher accepted it."""
    from svs_torch.segmentation.nearness_denoise import _checked_against_coarse
    from svs_torch.depth.dense_config import DenseConfig

    generator = torch.Generator().manual_seed(5)
    texture = torch.rand(1, 1, 60, 120, generator=generator)
    texture = torch.nn.functional.interpolate(texture, size=(120, 240), mode="bilinear", align_corners=False)
    shift = 8  # working pixels: 4 at half width
    left, right = texture[..., :200], texture[..., shift:shift + 200]
    config = NearnessNetConfig()
    fine = torch.full((1, 1, 120, 200), float(shift))
    fine[..., 60, 100] = shift + 1.0  # agrees within 1.5
    fine[..., 60, 101] = shift + 4.0  # does not
    valid = torch.ones_like(fine, dtype=torch.bool)
    valid[..., 61, 100] = False
    merged, merged_valid = _checked_against_coarse(left, right, fine, valid, 40, DenseConfig(window_size=7),
                                                   config)
    assert float(merged[..., 60, 100]) == shift + 1.0
    assert abs(float(merged[..., 60, 101]) - shift) < 0.5  # the coarse map's value, in working pixels
    assert bool(merged_valid[..., 61, 100])
    with pytest.raises(InputError, match="sparse_reduction"):
        NearnessNetConfig(sparse_reduction=0)
    with pytest.raises(InputError, match="sparse_agreement_px"):
        NearnessNetConfig(sparse_agreement_px=-1.0)


def test_a_noisy_camera_frame_is_matched_with_the_wider_window(data_dir):
    """Dim Piano as camera frames (JPEG 50 with σ 6 levels): its matching residual at the working window reaches
    ``noisy_min_residual_levels`` while the clean pair's does not, so it alone is matched again with
    ``noisy_window_size`` (:func:`~svs_torch.segmentation.nearness_denoise.match_by_noise`). That keeps the clean
    pair's obstacles, which the 7×7 window's specks lose; a clean pair's map is the working window's, alone or in
    one batch with the noisy pair; and the gradient is the soft-argmin's over the same wider window, its edge rows
    taken from the same rows as the hard map's."""
    from svs_torch.depth.block_matching import block_match_sad_with_residual
    from svs_torch.depth.dense_config import DenseConfig
    from svs_torch.depth.soft_dense import soft_block_match

    clean, frames = _dim_piano_frames(data_dir, 50, 6.0)
    config = dataclasses.replace(PipelineConfig().segmentation, min_measured_share=0.0)
    net, narrow = NearnessNet().eval(), NearnessNet(NearnessNetConfig(noisy_window_size=7)).eval()
    gate = net.config.noisy_min_residual_levels
    dense = DenseConfig(window_size=net.config.window_size, uniqueness_ratio=net.config.uniqueness_ratio)
    residual = block_match_sad_with_residual(torch.cat([clean.left, frames.left]),
                                             torch.cat([clean.right, frames.right]), 0, 96, dense)[1]
    assert float(residual[0]) < gate <= float(residual[1])
    reference = segment_stereo_nearness(clean, config, net).left.kept_mask
    kept = segment_stereo_nearness(frames, config, net).left.kept_mask
    assert float(mask_iou(kept, reference)[0]) > 0.6  # 0.66
    assert float(mask_iou(segment_stereo_nearness(frames, config, narrow).left.kept_mask, reference)[0]) < 0.3
    # The default keeps this real frame on the nearness segmenter (its 14 % accepted is above the fallback's share).
    assert bool(segment_stereo_nearness(frames, PipelineConfig().segmentation, net).from_disparity[0])
    both = measure_nearness_disparity(torch.cat([clean.left, frames.left]), torch.cat([clean.right, frames.right]),
                                      net.config)
    assert torch.equal(both.disparity_px[:1], measure_nearness_disparity(clean.left, clean.right,
                                                                         narrow.config).disparity_px)
    assert torch.equal(both.disparity_px[1:], measure_nearness_disparity(frames.left, frames.right,
                                                                         net.config).disparity_px)
    left = frames.left.clone().requires_grad_()
    measure_nearness_disparity(left, frames.right, net.config).disparity_px.sum().backward()
    wide = dataclasses.replace(dense, window_size=net.config.noisy_window_size)
    expected_left = frames.left.clone().requires_grad_()
    soft = soft_block_match(expected_left, frames.right, 0, 96, net.config.disparity_temperature, wide)
    # The edge rows are the nearest rows whose window lies inside the view, in the soft map as in the hard one.
    reach = wide.window_size // 2
    soft.index_select(-2, torch.arange(soft.shape[-2]).clamp(reach, soft.shape[-2] - 1 - reach)).sum().backward()
    assert torch.allclose(left.grad, expected_left.grad)
    with pytest.raises(InputError, match="noisy_window_size"):
        NearnessNetConfig(noisy_window_size=8)
    with pytest.raises(InputError, match="noisy_min_residual_levels"):
        NearnessNetConfig(noisy_min_residual_levels=-1.0)


def test_camera_frames_skip_the_noise_gate_with_the_maps_the_gate_gives(data_dir):
    """``SegmentationConfig.camera_frames``: a frame the gate widens gets the same map, segmentation, pipeline result
    and gradient without the first pass; a clean pair at the working width is matched with the wider window as a
    noisy one is; a pair wider than the working width keeps the gate."""
    import torch.nn.functional as F

    from svs_torch.depth.dense_config import DenseConfig
    from svs_torch.segmentation.nearness_denoise import match_by_noise

    clean, frames = _dim_piano_frames(data_dir, 50, 6.0)
    net = NearnessNet().eval()
    skipping = dataclasses.replace(net.config, noisy_min_residual_levels=0.0)
    gated = measure_nearness_disparity(frames.left, frames.right, net.config)
    assert gated.relative.shape[-1] == net.config.working_width_px
    for name in ("disparity_px", "measured", "split_px", "relative"):
        assert torch.equal(getattr(gated, name), getattr(measure_nearness_disparity(
            frames.left, frames.right, net.config, camera_frames=True), name)), name
    assert torch.equal(measure_nearness_disparity(clean.left, clean.right, net.config, camera_frames=True).disparity_px,
                       measure_nearness_disparity(clean.left, clean.right, skipping).disparity_px)
    assert not torch.equal(measure_nearness_disparity(clean.left, clean.right, net.config).disparity_px,
                           measure_nearness_disparity(clean.left, clean.right, skipping).disparity_px)
    dense = DenseConfig(window_size=net.config.window_size, uniqueness_ratio=net.config.uniqueness_ratio)
    views = (torch.cat([clean.left, frames.left]), torch.cat([clean.right, frames.right]))
    found, widened = match_by_noise(*views, 96, dense, skipping)
    assert widened.tolist() == [True, True]
    gate_found, gate_widened = match_by_noise(*views, 96, dense, net.config)
    assert gate_widened.tolist() == [False, True]
    assert torch.equal(found.disparity_px[1:], gate_found.disparity_px[1:])
    assert torch.equal(found.valid[1:], gate_found.valid[1:])
    # Wider than the working width: averaged down before matching, so the gate still decides.
    wide = [F.interpolate(v, size=(336, 448), mode="bilinear", align_corners=False).clamp(0, 1)
            for v in (clean.left, clean.right)]
    assert torch.equal(measure_nearness_disparity(*wide, net.config).disparity_px,
                       measure_nearness_disparity(*wide, net.config, camera_frames=True).disparity_px)
    # Through the segmenter and the whole pipeline, with gradients.
    config = PipelineConfig()
    camera = dataclasses.replace(config, segmentation=dataclasses.replace(config.segmentation, camera_frames=True))
    assert torch.equal(segment_stereo_nearness(frames, config.segmentation, net).left.kept_mask,
                       segment_stereo_nearness(frames, camera.segmentation, net).left.kept_mask)
    first, second = estimate_obstacle_depth(frames, config), estimate_obstacle_depth(frames, camera)
    assert torch.equal(first.depth.objects.depth_median_m, second.depth.objects.depth_median_m)
    grads = []
    for camera_frames in (False, True):
        left = frames.left.clone().requires_grad_()
        measure_nearness_disparity(left, frames.right, net.config, camera_frames=camera_frames).disparity_px.sum(
            ).backward()
        grads.append(left.grad)
    assert torch.equal(grads[0], grads[1])
    with pytest.raises(InputError, match="^camera_frames: "):
        SegmentationConfig(camera_frames=1)


def test_a_noisy_pairs_edge_rows_take_the_nearest_row_whose_window_is_inside(data_dir):
    """The block matcher crops with a replicated border, so on a noisy pair a window within K // 2 rows of the top
    or bottom edge repeats the edge row and its noise decides the match. A widened (noisy) pair's edge rows are
    the nearest row whose window lies inside the view; a clean pair's map is the block matcher's, untouched. On
    the tuned Shelves at 448×336 as a JPEG digit 7 frame this removes a strip along the top that was kept as an
    object and ranged near (2.42 m for 3.52: 83.4 % per object, now over 99 %)."""
    import sys

    import torch.nn.functional as F
    from conftest import REPO_ROOT

    from svs_torch.depth.block_matching import block_match_sad
    from svs_torch.depth.dense_config import DenseConfig
    from svs_torch.evaluation import evaluate_result
    from svs_torch.segmentation.nearness_denoise import match_by_noise

    sys.path.insert(0, str(REPO_ROOT / "experiments"))
    import real_rig
    shelves = real_rig.resample(real_rig.load_scene(data_dir / "middlebury_eval3_Q" / "Shelves"), "448x336")
    # 8: Shelves's index in real_rig.py's tuned split, which seeds the scene's noise (its rows' frame).
    frame = next(view for view in real_rig.conditions(shelves, 8) if view[0] == "jpeg q7 + noise s6")
    batch = real_rig.stack_conditions(shelves, [("clean", shelves.left, shelves.right), frame])
    net = NearnessNetConfig()
    dense = DenseConfig(window_size=net.window_size, uniqueness_ratio=net.uniqueness_ratio)
    small = [F.interpolate(v, size=(240, 320), mode="area") for v in (batch.left, batch.right)]
    found, widened = match_by_noise(*small, 80, dense, net)
    assert widened.tolist() == [False, True]
    reach = net.noisy_window_size // 2
    wide = block_match_sad(small[0][1:], small[1][1:], 0, 80, dataclasses.replace(dense, window_size=11))
    for rows, source in ((slice(0, reach), reach), (slice(240 - reach, 240), 239 - reach)):
        assert torch.equal(found.disparity_px[1, :, rows], wide.disparity_px[0, :, source:source + 1].expand(
            -1, reach, -1))
    assert torch.equal(found.disparity_px[1, :, reach:240 - reach], wide.disparity_px[0, :, reach:240 - reach])
    assert torch.equal(found.disparity_px[:1], block_match_sad(small[0][:1], small[1][:1], 0, 80, dense).disparity_px)
    evaluations = evaluate_result(batch, estimate_obstacle_depth(batch, PipelineConfig()))
    assert evaluations[1].status == "OK" and evaluations[1].acc_objects_pct > 99


def _reference_fillable(disparity: list[float], valid: list[bool], max_px: int) -> list[bool]:
    """Written from the docstring of ``fillable_runs``: a loop over one row's runs of rejected pixels."""
    width, out, x = len(valid), list(valid), 0
    while x < width:
        if valid[x]:
            x += 1
            continue
        end = x
        while end < width and not valid[end]:
            end += 1
        before, after = x - 1, end  # the measured pixels around the run (-1 / width: the row's ends)
        short = end - x <= max_px
        one_surface = before >= 0 and after < width and abs(disparity[before] - disparity[after]) <= 1
        band = before < 0 and after < width and after <= disparity[after] + max_px
        out[x:end] = [short or one_surface or band] * (end - x)
        x = end
    return out


def test_fillable_runs_fill_short_runs_one_surface_and_the_left_band_only():
    """``NearnessNetConfig.max_fill_px``'s rule (nearness_denoise, "Why long runs stay unfilled") on random rows: equal
    to a loop over each row's runs written from the docstring, and on a row by hand: a long run between two
    surfaces, or to the right edge, stays unfilled; a long one inside one surface, or the left band, is filled."""
    from svs_torch.segmentation.nearness_denoise import fillable_runs

    generator = torch.Generator().manual_seed(4)
    valid = torch.rand(6, 1, 5, 90, generator=generator) < torch.linspace(0.03, 0.6, 6).view(6, 1, 1, 1)
    disparity = torch.randint(0, 40, valid.shape, generator=generator).to(torch.float32)
    found = fillable_runs(disparity, valid, 8)
    for b in range(6):
        for y in range(5):
            row = _reference_fillable(disparity[b, 0, y].tolist(), valid[b, 0, y].tolist(), 8)
            assert found[b, 0, y].tolist() == row
    row_valid = torch.zeros(1, 60, dtype=torch.bool)
    row_valid[0, [12, 30, 42, 48]] = True
    row_disparity = torch.zeros(1, 60)
    row_disparity[0, [12, 30, 42, 48]] = torch.tensor([10.0, 20.0, 20.5, 5.0])
    fill = fillable_runs(row_disparity, row_valid, 5)[0]
    assert fill[:12].all()  # the left band: 12 <= 10 + 5
    assert not fill[13:30].any()  # 17 px between 10 and 20 px: two surfaces
    assert fill[31:42].all()  # 11 px between 20 and 20.5 px: one surface
    assert fill[43:48].all()  # 5 px: short
    assert not fill[49:].any()  # 11 px to the right edge
    with pytest.raises(InputError, match="max_fill_px: expected None or an int >= 0"):
        NearnessNetConfig(max_fill_px=-1)


def test_max_fill_px_ranges_boxes_before_a_plain_wall_as_camera_frames():
    """The rendered boxes before a plain wall at 5 m (experiments/real_rig.py ``--splits synthetic-wall``), pair 6,
    as the board's default frame (JPEG digit 4, σ 4): by default the row fill carries the boxes' disparity across
    the rejected wall, the kept region is mostly wall and is ranged at the box's distance (30 % per object);
    with ``max_fill_px=16`` the long runs stay far, the region is the box's and it is ranged within 1 %. The clean
    pair, not noisy, is the same either way."""
    import sys

    from conftest import REPO_ROOT

    from svs_torch.evaluation import evaluate_result

    sys.path.insert(0, str(REPO_ROOT / "experiments"))
    import real_rig

    scene = real_rig.wall_scenes()[6]
    pair = real_rig.stack_conditions(scene, [v for v in real_rig.conditions(scene, 6)
                                             if v[0] in ("clean", "jpeg q4 + noise s4")])
    shipped = load_obstacle_net("nearness")
    limited = NearnessNet(dataclasses.replace(shipped.config, max_fill_px=16)).eval()
    limited.load_state_dict(shipped.state_dict())
    default, with_limit = (evaluate_result(pair, estimate_obstacle_depth(pair, network=net))
                           for net in (shipped, limited))
    assert default[1].acc_objects_pct < 50 and with_limit[1].acc_objects_pct > 99
    assert default[0].acc_objects_pct == with_limit[0].acc_objects_pct > 99


@pytest.mark.parametrize("segmenter", ["nearness", "learned"])
@pytest.mark.parametrize("differentiable", [False, True])
def test_a_network_that_outputs_nan_is_refused_not_read_as_no_obstacle(scenes, segmenter, differentiable):
    """A diverged network's NaN logits were thresholded to "not an obstacle": NO_OBJECTS, the way clear."""
    net = load_obstacle_net(segmenter)
    with torch.no_grad():
        for parameter in net.parameters():
            parameter.fill_(float("nan"))
    config = PipelineConfig(segmentation=SegmentationConfig(segmenter=segmenter), differentiable=differentiable)
    with pytest.raises(InputError, match=r"network: expected finite obstacle logits, got NaN or inf for pair\(s\)"):
        estimate_obstacle_depth(scenes.batch, config, network=net)


def test_a_pixel_is_an_obstacle_where_its_probability_exceeds_the_threshold(scenes):
    """``NearnessNetConfig.probability_threshold``: the logit that is exactly the threshold's is not an obstacle,
    one just above it is; a higher threshold moves that logit."""
    batch = scenes.batch
    for threshold in (0.5, 0.7):
        net = NearnessNet(NearnessNetConfig(probability_threshold=threshold)).eval()
        logit = math.log(threshold / (1 - threshold))
        logits = torch.full_like(batch.left, -5.0)
        logits[..., 10:30, 10:40] = logit
        logits[..., 40:60, 50:90] = logit + 1e-4
        binary = segment_stereo_nearness(batch, SegmentationConfig(), net, left_logits=logits).left.binary
        assert not bool(binary[..., 10:30, 10:40].any()) and bool(binary[..., 40:60, 50:90].all())
        assert int(binary.sum()) == batch.batch_size * 20 * 40


def test_segment_pair_checks_its_network_its_batch_and_given_logits(scenes):
    from svs_torch.pipeline import segment_pair

    learned = SegmentationConfig(segmenter="learned")
    with pytest.raises(InputError, match="network: expected an ObstacleNet for segmenter 'learned', got NearnessNet"):
        segment_pair(scenes.batch, learned, network=NearnessNet())  # ran the nearness segmenter in silence
    with pytest.raises(InputError, match="network: expected an ObstacleNet for segmenter 'learned', got Linear"):
        segment_pair(scenes.batch, learned, network=torch.nn.Linear(2, 2))  # an AttributeError from inside
    with pytest.raises(InputError, match="batch: expected at least one pair, got an empty batch"):
        segment_pair(scenes.batch.select(torch.tensor([], dtype=torch.int64)), SegmentationConfig())
    nan_logits = torch.full_like(scenes.batch.left, float("nan"))
    with pytest.raises(InputError, match="left_logits: given, but config.segmenter is 'otsu', which reads none"):
        segment_pair(scenes.batch, SegmentationConfig(segmenter="otsu"), left_logits=nan_logits)  # ignored
    for config in (SegmentationConfig(segmenter="nearness"), learned):
        with pytest.raises(InputError, match=r"left_logits: expected finite obstacle logits, got NaN or inf for "
                                             r"pair\(s\) \[0, 1, 2\]"):
            segment_pair(scenes.batch, config, left_logits=nan_logits)
