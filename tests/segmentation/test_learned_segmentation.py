"""The learned segmenter (svs_torch.segmentation.learned): truth from GT disparity, the network and its shipped
weights, the hard segmenter in the pipeline and the CLI, and the soft path through the depth."""

from __future__ import annotations

import dataclasses
import json
import os
import tomllib

import cv2
import numpy as np
import pytest
import torch
from conftest import REPO_ROOT

from svs_torch.cli import main
from svs_torch.core.checks import InputError
from svs_torch.core.types import StereoBatch
from svs_torch.data.synthetic import random_obstacle_scenes
from svs_torch.depth.block_matching import block_match_sad
from svs_torch.depth.dense_config import DenseConfig
from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth
from svs_torch.segmentation.learned import (mask_iou, obstacle_truth, segment_learned, segment_stereo_learned,
                                            soft_nearest_depth, soft_object_depths)
from svs_torch.segmentation.network import ObstacleNet, ObstacleNetConfig, predict_obstacle_logits
from svs_torch.segmentation.network_files import (NEARNESS_WEIGHTS, SHIPPED_WEIGHTS, load_obstacle_net,
                                                  save_obstacle_net)
from svs_torch.segmentation.segment import SegmentationConfig


@pytest.fixture(scope="module")
def scenes():
    """Two synthetic 160×120 scenes of two boxes each (exact masks and depths)."""
    return random_obstacle_scenes(2, 2, size_wh=(160, 120), generator=torch.Generator().manual_seed(7))


def truth_logits(mask: torch.Tensor, generator: torch.Generator, noise: float = 0.0) -> torch.Tensor:
    """Logits that say "obstacle" on ``mask`` (±4, optionally with noise): the soft path without training."""
    logits = torch.where(mask, 4.0, -4.0)
    return logits + noise * torch.randn(logits.shape, generator=generator, dtype=logits.dtype)


# ------------------------------------------------------------------------------------------------------ truth
def test_truth_of_a_synthetic_scene_is_its_boxes(scenes):
    truth = obstacle_truth(scenes.batch)
    boxes = scenes.object_ids > 0  # exact, from the renderer
    assert torch.equal(truth.kept_mask, boxes)
    assert torch.equal(truth.near, boxes)  # Otsu splits box disparities from the wall's
    # The nearer box's median GT depth is its exact front depth (fronto-parallel boxes).
    torch.testing.assert_close(truth.nearest_m, scenes.object_depth_m.min(1).values)
    assert truth.kept_labels.dtype == torch.int64 and truth.nearest_valid.all()


def test_truth_ignores_invalid_disparity_and_needs_calibration_for_depth(scenes):
    batch = scenes.batch.select([0])
    # Invalidate a box and most of the wall: the other box is then the near class of the remaining pixels.
    first_box = scenes.object_ids[:1] == 1
    invalid = first_box.clone()
    invalid[..., :, :60] |= ~(scenes.object_ids[:1] > 0)[..., :, :60]
    hidden = dataclasses.replace(batch, disparity_valid=~invalid, calibrated=torch.tensor([False]))
    truth = obstacle_truth(hidden)
    assert not (truth.near & invalid).any()
    assert torch.equal(truth.kept_mask, scenes.object_ids[:1] == 2)
    assert not truth.nearest_valid.any() and truth.nearest_m.eq(0).all()  # masks yes, metres no
    with pytest.raises(InputError, match="disparity"):
        obstacle_truth(dataclasses.replace(batch, disparity_px=None, disparity_valid=None))


def test_mask_iou_values():
    a = torch.zeros(3, 1, 2, 2, dtype=torch.bool)
    b = a.clone()
    a[0, 0, 0] = True  # 2 px
    b[0, 0, :, 0] = True  # 2 px, 1 shared: 1 / 3
    a[1, 0, 0, 0] = True  # disjoint: 0; image 2 both empty: 1
    torch.testing.assert_close(mask_iou(a, b), torch.tensor([1 / 3, 0.0, 1.0]))


@pytest.mark.parametrize("dtype, name", [(torch.float32, "mask"), (torch.int64, "truth")])
def test_mask_iou_names_a_mask_that_is_not_bool(dtype, name):
    """A float mask raised NotImplementedError ("bitwise_and_cpu") from deep inside; an int one was taken
    bit by bit in silence (a mask of 2s and 1s met nowhere: IoU 0)."""
    mask = torch.ones(1, 1, 2, 2, dtype=torch.bool)
    other = (mask * 2 if dtype == torch.int64 else mask).to(dtype)
    with pytest.raises(InputError, match=f"^{name}: expected a bool tensor"):
        mask_iou(other, mask) if name == "mask" else mask_iou(mask, other)


# -------------------------------------------------------------------------------------------- network, weights
def test_shipped_weights_load_and_are_package_data():
    net = load_obstacle_net("learned")
    assert 10_000 <= sum(p.numel() for p in net.parameters()) <= 200_000
    assert not net.training and SHIPPED_WEIGHTS.stat().st_size < 1_000_000
    package_data = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    assert any(SHIPPED_WEIGHTS.match(pattern) for pattern in package_data["svs_torch"])
    stored = torch.load(SHIPPED_WEIGHTS, weights_only=True)
    assert stored["metadata"]["train_scenes"] and stored["metadata"]["held_out_scenes"]
    assert not set(stored["metadata"]["train_scenes"]) & set(stored["metadata"]["held_out_scenes"])


@pytest.mark.parametrize("segmenter", ["learned", "nearness"])
def test_loading_weights_leaves_the_global_random_state_alone(segmenter):
    # Building the network drew its throw-away initial weights from torch's global generator: a user's
    # torch.manual_seed(0); estimate_obstacle_depth(...); torch.rand(3) gave other numbers on a process's first
    # call (when the shipped network is loaded) than on later ones.
    torch.manual_seed(123)
    expected = torch.rand(3)
    torch.manual_seed(123)
    net = load_obstacle_net(segmenter)
    assert torch.equal(torch.rand(3), expected)
    shipped = torch.load(SHIPPED_WEIGHTS if segmenter == "learned" else NEARNESS_WEIGHTS, weights_only=True)
    shipped = shipped["state_dict"]
    assert all(torch.equal(value, shipped[name]) for name, value in net.state_dict().items())


def test_saved_weights_round_trip(tmp_path, scenes):
    torch.manual_seed(0)
    net = ObstacleNet(ObstacleNetConfig(channels=(8, 8, 8))).eval()
    path = tmp_path / "net.pt"
    save_obstacle_net(path, net, {"note": "test", "version": torch.__version__})
    again = load_obstacle_net(f"learned:{path}")
    assert again.config == net.config
    with torch.no_grad():
        left, right = scenes.batch.left, scenes.batch.right
        torch.testing.assert_close(predict_obstacle_logits(again, left, right), predict_obstacle_logits(net, left, right))


@pytest.mark.parametrize("content, message", [
    (None, "no weights file"), (b"\x00\x13garbage", "not a weights file"), ({"format": "other"}, "learned network file"),
])
def test_bad_weights_are_one_line_input_errors(tmp_path, content, message):
    path = tmp_path / "bad.pt"
    if isinstance(content, bytes):
        path.write_bytes(content)
    elif content is not None:
        torch.save(content, path)
    with pytest.raises(InputError, match=message) as error:
        load_obstacle_net(f"learned:{path}")
    assert "\n" not in str(error.value)


def test_a_weights_file_whose_settings_are_out_of_range_is_named(tmp_path):
    """Found by an audit of training: a file whose stored setting its configuration refuses said only
    "working_width_px: expected an int >= 16, got 8", naming neither the file nor the option."""
    path = tmp_path / "edited.pt"
    save_obstacle_net(path, ObstacleNet(ObstacleNetConfig(channels=(8, 8, 8))), {"note": "test"})
    stored = torch.load(path, weights_only=True)
    stored["config"]["working_width_px"] = 8
    torch.save(stored, path)
    with pytest.raises(InputError, match=f"^segmenter: '{path}': its stored settings are refused "
                                         r"\(working_width_px: expected an int >= 16, got 8\)$"):
        load_obstacle_net(f"learned:{path}")


@pytest.mark.parametrize("segmenter", ["learned:", "Learned", "otsu:x", 3])
def test_segmenter_choice_is_checked(segmenter):
    with pytest.raises(InputError, match="segmenter"):
        SegmentationConfig(segmenter=segmenter)
    with pytest.raises(InputError, match="no weights file"):  # before any work starts (a sweep's configuration)
        SegmentationConfig(segmenter="learned:/no/such/weights.pt")


def test_the_pipeline_reads_a_weights_file_once_per_version(tmp_path, scenes):
    path = tmp_path / "net.pt"
    save_obstacle_net(path, ObstacleNet())
    config = SegmentationConfig(segmenter=f"learned:{path}")
    first = segment_stereo_learned(scenes.batch, config)
    again = segment_stereo_learned(scenes.batch, config)
    assert torch.equal(first.left.kept_mask, again.left.kept_mask)
    torch.manual_seed(5)
    before = path.stat().st_mtime_ns
    save_obstacle_net(path, ObstacleNet())  # a rewritten file is read again
    os.utime(path, ns=(before + 10**9, before + 10**9))  # a coarse file-system clock must not hide the rewrite
    changed = segment_stereo_learned(scenes.batch, config)
    assert not torch.equal(changed.left.binary, first.left.binary)


# ---------------------------------------------------------------------------------------------- hard segmenter
def test_learned_segmenter_has_the_otsu_structure_and_finds_the_boxes(scenes):
    seg = segment_stereo_learned(scenes.batch)  # the shipped weights
    truth = obstacle_truth(scenes.batch)
    for side in (seg.left, seg.right):
        assert side.kept_labels.shape == (2, 2) and side.kept_labels.dtype == torch.int64
        assert side.labels.dtype == torch.int64 and side.kept_mask.dtype == torch.bool
    torch.testing.assert_close(seg.left.masked, scenes.batch.left * seg.left.kept_mask)
    assert (mask_iou(seg.left.kept_mask, truth.kept_mask) > 0.7).all()
    # The right view is segmented too: its kept area matches the left one's (same boxes, shifted).
    ratio = seg.right.kept_mask.flatten(1).sum(1) / seg.left.kept_mask.flatten(1).sum(1)
    assert ((ratio > 0.8) & (ratio < 1.25)).all()
    one = segment_stereo_learned(scenes.batch.select([1]))  # a pair's result does not depend on its batch
    assert torch.equal(one.left.kept_mask, seg.left.kept_mask[1:])


# --------------------------------------------------------------------------------------------------- soft path
def test_depth_loss_gradient_reaches_the_network(scenes):
    torch.manual_seed(0)
    net = ObstacleNet()
    batch, truth = scenes.batch, obstacle_truth(scenes.batch)
    logits = predict_obstacle_logits(net, batch.left, batch.right)
    hard = segment_learned(batch.left, truth_logits(truth.kept_mask, torch.Generator()))
    soft = soft_nearest_depth(batch, logits, hard, num_disparities=24)
    assert soft.nearest_valid.all()
    loss = ((soft.nearest_m - truth.nearest_m).abs() / truth.nearest_m).mean()
    loss.backward()
    for name in ("down1.0.weight", "middle.0.weight", "head.weight", "head.bias"):
        grad = dict(net.named_parameters())[name].grad
        assert grad is not None and grad.abs().sum() > 0, name


def test_soft_path_gradcheck_float64():
    generator = torch.Generator().manual_seed(3)
    left = 0.1 + 0.8 * torch.rand(1, 1, 7, 12, generator=generator, dtype=torch.float64)
    right = torch.roll(left, -2, dims=-1) * 0.9 + 0.05
    logits = torch.randn(1, 1, 7, 12, generator=generator, dtype=torch.float64)
    regions = torch.zeros(1, 1, 7, 12, dtype=torch.bool)
    regions[..., 1:6, 3:6] = True
    regions[..., 2:6, 8:11] = True
    hard = segment_learned(left, torch.where(regions, 1.0, -1.0).double(), SegmentationConfig(kernel_size=1))

    def depths(logits, left, right):
        batch = StereoBatch.from_images(left, right, 50.0, 0.1, 0.5, calibrated=True)
        soft = soft_nearest_depth(batch, logits, hard, 4, mask_temperature=0.7, disparity_temperature=0.05,
                                  dense=DenseConfig(window_size=3))
        return soft.depth_m

    inputs = [t.clone().requires_grad_() for t in (logits, left, right)]
    assert torch.autograd.gradcheck(depths, inputs, eps=1e-6, atol=1e-5)


@pytest.mark.parametrize("temperature", ["0.05", 0.0, torch.tensor([0.1, 0.2])], ids=["string", "zero", "per-pair"])
def test_a_disparity_temperature_that_is_not_one_positive_number_is_named(scenes, temperature):
    """Found by an audit: soft_nearest_depth's disparity_temperature was refused as soft_block_match's
    'temperature', an argument its caller never passed."""
    batch = scenes.batch
    hard = segment_learned(batch.left, torch.ones_like(batch.left))
    with pytest.raises(InputError, match=r"^disparity_temperature: expected (a|one) positive number, got "):
        soft_nearest_depth(batch, torch.ones_like(batch.left), hard, 8, disparity_temperature=temperature)


def test_soft_path_tends_to_the_hard_one_at_low_temperature(scenes):
    batch, truth = scenes.batch, obstacle_truth(scenes.batch)
    logits = truth_logits(truth.kept_mask, torch.Generator().manual_seed(1), noise=2.0)
    hard = segment_learned(batch.left, logits)
    # Hard: each kept region's mean winner-takes-all disparity, the exact limit of the soft path (the soft-argmin
    # tends to the integer winner, without rejections; block_match_sad's sub-pixel fit stays within ±0.5 px of it,
    # so rounding recovers the winner).
    plain = DenseConfig(uniqueness_ratio=0.0, lr_max_diff_px=None, texture_threshold=0.0)
    dense = block_match_sad(batch.left, batch.right, 0, 24, plain)
    region = (hard.labels == hard.kept_labels.view(2, 2, 1, 1)) & (hard.kept_labels > 0).view(2, 2, 1, 1)
    assert (region & dense.valid).sum() == region.sum()
    values = torch.where(region, dense.disparity_px.round(), torch.nan).flatten(2)
    hard_depth = batch.focal_px.view(2, 1) * batch.baseline_m.view(2, 1) / values.nanmean(-1)
    cold = soft_nearest_depth(batch, logits, hard, 24, mask_temperature=1e-3, disparity_temperature=1e-4)
    warm = soft_nearest_depth(batch, logits, hard, 24, mask_temperature=30.0, disparity_temperature=0.3)
    assert cold.valid.all()
    torch.testing.assert_close(cold.depth_m, hard_depth, rtol=2e-3, atol=0)
    assert (warm.depth_m - hard_depth).abs().max() > 3 * (cold.depth_m - hard_depth).abs().max()
    # And both near the truth: integer disparities of about 12 px at 160 px wide are good to about 4 %.
    torch.testing.assert_close(cold.nearest_m, truth.nearest_m, rtol=0.05, atol=0)


def test_soft_object_depths_invalid_and_empty_slots():
    labels = torch.zeros(1, 1, 4, 4, dtype=torch.int64)
    labels[..., :2, :2] = 1
    hard = segment_learned(torch.full((1, 1, 4, 4), 0.5), torch.where(labels > 0, 1.0, -1.0),
                           SegmentationConfig(kernel_size=1, num_keep=2))
    assert hard.kept_labels.tolist() == [[1, -1]]
    disparity = torch.full((1, 1, 4, 4), -3.0)  # d + doffs <= 0: no depth
    soft = soft_object_depths(torch.zeros(1, 1, 4, 4), hard, disparity, torch.tensor([10.0]), torch.tensor([1.0]),
                              torch.tensor([1.0]))
    assert soft.valid.tolist() == [[False, False]] and not soft.nearest_valid.any()
    assert soft.depth_m.eq(0).all() and soft.nearest_m.eq(0).all()


@pytest.mark.parametrize("argument, value", [("probability_threshold", 0.0), ("probability_threshold", 1.0),
                                             ("probability_threshold", 1.5), ("probability_threshold", float("nan")),
                                             ("config", "otsu")])
def test_segment_learned_names_a_bad_threshold_or_config(argument, value):
    """Were: a threshold of 0 or above 1 raised ValueError ("math domain error"), 1 ZeroDivisionError, from the
    logit; NaN kept no pixel in silence (NO_FOREGROUND); a config string raised AttributeError (an audit)."""
    image, logits = torch.full((1, 1, 8, 8), 0.5), torch.zeros(1, 1, 8, 8)
    with pytest.raises(InputError, match=f"^{argument}: expected"):
        segment_learned(image, logits, **{argument: value})
    assert segment_learned(image, logits, probability_threshold=0.25).binary.all()


def test_the_learned_pieces_name_a_setting_or_view_of_another_kind(scenes):
    """Found by an audit of the learned segmenter's pieces called by hand: stereo_features given a DenseConfig
    failed on a field (AttributeError: num_disparities) and took views of two sizes, each resized to the working
    size in silence; obstacle_truth given a DenseConfig as its floor failed deep in the floor's fit."""
    from svs_torch.segmentation.network import stereo_features
    batch = scenes.batch
    with pytest.raises(InputError, match="^config: expected an ObstacleNetConfig, got DenseConfig$"):
        stereo_features(batch.left, batch.right, DenseConfig())
    with pytest.raises(InputError, match=r"^right: expected the shape of left \("):
        stereo_features(batch.left, batch.right[..., :-2])
    with pytest.raises(InputError, match="^floor: expected a GroundPlaneConfig, got DenseConfig$"):
        obstacle_truth(batch, SegmentationConfig(), DenseConfig())
    assert stereo_features(batch.left, batch.right)[0].shape[:2] == (batch.batch_size, 6)


@pytest.mark.parametrize("segmentation", ["stereo", None])
def test_soft_object_depths_names_a_segmentation_of_another_kind(scenes, segmentation):
    """Was: a StereoSegmentation (what segment_stereo_learned returns) or None raised AttributeError on .labels
    (an audit); soft_nearest_depth already named it."""
    batch = scenes.batch
    stereo = segment_stereo_learned(batch, net=ObstacleNet()) if segmentation == "stereo" else None
    with pytest.raises(InputError, match="^segmentation: expected a Segmentation, got "):
        soft_object_depths(torch.zeros_like(batch.left), stereo, torch.zeros_like(batch.left), batch.focal_px,
                           batch.baseline_m, batch.doffs_px)


# --------------------------------------------------------------------------------------------- pipeline, CLI
def _write_pair(tmp_path, scenes) -> tuple[str, str]:
    paths = []
    for name, image in (("left.png", scenes.batch.left[0, 0]), ("right.png", scenes.batch.right[0, 0])):
        cv2.imwrite(str(tmp_path / name), (image.numpy() * 255).round().astype(np.uint8))
        paths.append(str(tmp_path / name))
    return paths[0], paths[1]


@pytest.fixture(scope="module")
def svs_scene():
    """A 320×240 synthetic SVS pair: the CLI's default camera model is the renderer's."""
    return random_obstacle_scenes(1, 2, size_wh=(320, 240), generator=torch.Generator().manual_seed(11))


def test_pipeline_runs_the_learned_segmenter(svs_scene):
    config = PipelineConfig(segmentation=SegmentationConfig(segmenter="learned"))
    result = estimate_obstacle_depth(svs_scene.batch, config)
    truth = obstacle_truth(svs_scene.batch)
    assert mask_iou(result.segmentation.left.kept_mask, truth.kept_mask).item() > 0.7
    torch.testing.assert_close(result.depth.nearest.depth_m, truth.nearest_m, rtol=0.05, atol=0)


def test_cli_estimate_with_the_learned_segmenter(tmp_path, capsys, svs_scene):
    left, right = _write_pair(tmp_path, svs_scene)
    assert main(["estimate", left, right, "--segmenter", "learned", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["status"] == "OK"
    nearest = float(svs_scene.object_depth_m.min())
    assert abs(report["nearest_m"] - nearest) / nearest < 0.05


@pytest.mark.parametrize("value, message", [
    ("learned:{tmp}/missing.pt", "no weights file"), ("learned:{tmp}/junk.pt", "not a weights file"),
    ("bogus", "expected otsu, nearness, nearness:PATH, learned or learned:PATH"),
])
def test_cli_bad_segmenter_is_one_line_exit_2(tmp_path, capsys, svs_scene, value, message):
    left, right = _write_pair(tmp_path, svs_scene)
    (tmp_path / "junk.pt").write_bytes(b"not a torch file")
    try:
        status = main(["estimate", left, right, "--segmenter", value.format(tmp=tmp_path)])
    except SystemExit as exit_:  # argparse's own exit for a value its type refused
        status = exit_.code
    assert status == 2
    err = capsys.readouterr().err
    assert message in err and "segmenter" in err and err.count("\n") == 1


def test_cli_segment_with_the_learned_segmenter(tmp_path, capsys, svs_scene):
    left, right = _write_pair(tmp_path, svs_scene)
    assert main(["segment", left, right, "--segmenter", "learned", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["config"]["segmenter"] == "learned" and report["left"]["status"] == "OK"
    truth = obstacle_truth(svs_scene.batch)
    assert abs(sum(o["area_px"] for o in report["left"]["objects"]) / truth.kept_mask.sum().item() - 1) < 0.3
    assert main(["segment", left, right, "--segmenter", "learned"]) == 0
    assert "learned segmenter, obstacle probability above 0.50" in capsys.readouterr().out


def test_a_tall_narrow_pair_is_worked_on_at_a_bounded_size():
    """Was (an audit of hostile images): the network's input was every image scaled to 160 px wide at its own
    aspect, so a 10 x 8000 pair became 160 x 128000: 24 GB and two minutes, then 'quantile() input tensor is too
    large' ended the run. Now at most four working widths high, and the logits still cover the whole image."""
    from svs_torch.segmentation.network import MAX_WORKING_HEIGHT_WIDTHS, stereo_features

    with pytest.raises(InputError, match=r"segmenter: expected learned, .* \(a str\), got PosixPath"):
        load_obstacle_net(SHIPPED_WEIGHTS)  # was an AttributeError from str.partition
    net = load_obstacle_net("learned")
    left = torch.rand(1, 1, 2000, 10, generator=torch.Generator().manual_seed(0))
    right = torch.roll(left, -2, dims=-1)
    features, disparity = stereo_features(left, right, net.config)
    width = net.config.working_width_px
    assert features.shape[-2:] == disparity.shape[-2:] == (MAX_WORKING_HEIGHT_WIDTHS * width, width)
    logits = predict_obstacle_logits(net, left, right)
    assert logits.shape[-2:] == (2000, 10) and bool(torch.isfinite(logits).all())
    wide = torch.rand(1, 1, 90, 400, generator=torch.Generator().manual_seed(1))
    assert stereo_features(wide, wide, net.config)[0].shape[-2:] == (36, width)  # a landscape view as before
