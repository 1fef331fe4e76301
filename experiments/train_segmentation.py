"""Train the learned obstacle segmenter (svs_torch.segmentation.learned) through the depth, on the CPU in minutes.

Data, all at 160×120 (the network's working width):
- **real**: the ``tuned`` split of experiments/paper_table1.py (MiddEval3 quarter size), **minus ArtL and Teddy**:
  they are the 2005 Art and 2003 Teddy scenes of the held-out split under other lighting or sampling, so
  training on them would leak the held-out scenes. Each scene gives random crops at random scales (the scene
  resized to 160–280 px wide, a 160×120 window) and whole views (resized to 160×120);
- **synthetic**: :func:`svs_torch.data.synthetic.random_obstacle_scenes`, 1–3 boxes 0.7–2.5 m away before a wall
  3–6 m away (exact masks and depths).
Augmentation, drawn once per sample from a seeded ``torch.Generator``: gamma, contrast, brightness, intensity
inversion (nearness must not be read from brightness: the synthetic boxes are brighter than their wall), a
right-view exposure change (as MotorcycleE / PianoL), sensor noise, a vertical flip (rows stay epipolar lines).

Truth of every sample: :func:`~svs_torch.segmentation.learned.obstacle_truth` of its GT disparity. Loss: binary
cross-entropy + Dice on the opened near mask (the segmenter keeps the two largest regions itself, as the truth
does), plus ``--depth-weight`` × the relative error ``|Z − Z_true| / Z_true`` of the nearest obstacle's depth
through the soft path (soft region weights over the network's own kept regions, the soft-argmin disparity:
:func:`~svs_torch.segmentation.learned.soft_object_depths`). The disparity does not depend on the network, so
it is computed once per sample with the features.

Writes the weights with their configuration, the training settings and the scenes used (default: the shipped
file, svs_torch/segmentation/weights/obstacle_net.pt). Then ``experiments/eval_segmentation.py`` scores them on the
held-out split.

    python experiments/train_segmentation.py [--steps 700] [--batch-size 8] [--seed 0] [--out FILE]

``--through-pipeline`` fine-tunes instead (issue 31): from ``--init`` (default: the shipped weights), on the pairs
of ``--pairs`` (a pair list, as ``svs-depth`` reads; default: the training scenes above) at ``--size``, through the
product's own entry, ``estimate_obstacle_depth(..., differentiable=True)`` with the network: every step runs the
whole pipeline (the network's hard segmentation, SURF, RANSAC, the dense stage) with images that require grad,
and the loss is the mean relative error of every ranged object's depth against the median ground-truth depth over
its kept region (``svs_torch.evaluation.object_truth``, the accuracy's own truth), so training computes what
deployment computes, plus the relative error of each pair's nearest ranged obstacle against the true nearest
obstacle (``obstacle_truth``; a pair that ranged none counts 100 %: the per-object term alone, over the regions the
network keeps, was lowered by losing hard regions while the warned obstacle moved farther), plus
``--region-weight`` (default 1) × the per-object error of the probability-weighted mean depth over the whole kept
region (its gradient reaches every pixel of the region, not only the median's band; pairs rectified from F, whose
map is in rectified pixels, are left out of this term). With ``--batch-size`` at least the number of pairs every
step sees every pair, and the weights written are those of the lowest loss (the first two terms). The printed depth
loss per step is that of the weights before the step. Its defaults: 20 steps at learning rate 1e-4 (training from
scratch: 700 at 3e-3). Listed pairs without ground truth are left out, and said; those without a calibration take a
nominal one for their truth's depth (``with_nominal_calibration``, as ``svs-depth eval`` scores them), and said.

    python experiments/train_segmentation.py --through-pipeline [--pairs FILE] [--steps 20] [--out FILE]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # see bench_ransac.py: spinning OpenMP threads on a shared CPU

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from svs_torch.cli.common import non_negative_float, non_negative_int, positive_float, positive_int, seed_int
from svs_torch.cli.features import checked_size
from svs_torch.cli.segment import segmenter_choice
from svs_torch.core.errors import InputError
from svs_torch.core.workers import signals_held
from svs_torch.cli.progress import Progress
from svs_torch.data.synthetic import random_obstacle_scenes
from svs_torch.data import (collate_stereo_batches, load_pair_source, load_stereo_pair, read_pair_list,
                            resize_stereo_batch)
from svs_torch.evaluation import measured_regions, object_truth, with_nominal_calibration
from svs_torch.segmentation.learned import obstacle_truth, segment_learned, soft_object_depths
from svs_torch.segmentation.network import ObstacleNet, ObstacleNetConfig, predict_obstacle_logits, stereo_features
from svs_torch.segmentation.network_files import SHIPPED_WEIGHTS, load_obstacle_net, save_obstacle_net
from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth
from svs_torch.segmentation.segment import SegmentationConfig
from svs_torch.core.types import StereoBatch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from paper_table1 import split_scenes  # noqa: E402
from run_metadata import (add_data_option, command_line, default_data_dir, output_path,  # noqa: E402
                          refuse_unread_options, run_metadata, run_script)

#: Tuned-split scenes that are held-out scenes under another name (module docstring): never trained on.
HELD_OUT_DUPLICATES = {"ArtL": "middlebury_2005_2006_third/Art", "Teddy": "middlebury_2003_quarter/Teddy"}
CROP_WH = (160, 120)


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Training settings (recorded in the weights file)."""

    steps: int = 700  # 4-7 minutes on 2 cores (231 s for the shipped file; 376-394 s on a shared machine)
    batch_size: int = 8
    learning_rate: float = 3e-3  # AdamW, cosine decay to 0
    weight_decay: float = 1e-4
    depth_weight: float = 0.5  # × relative depth error of the nearest obstacle, beside BCE + Dice
    crops_per_scene: int = 40  # random-scale 160×120 crops per real scene
    views_per_scene: int = 8  # whole views per real scene (differently augmented)
    num_synthetic: int = 384
    seed: int = 0


def train_scenes(data_dir: Path) -> list[Path]:
    """The tuned split without the scenes that duplicate held-out ones.

    Raises:
        InputError: ``data_dir`` holds none of them."""
    scenes = [path for path in split_scenes(data_dir)["tuned"] if path.name not in HELD_OUT_DUPLICATES]
    if not scenes:  # '--data /work/shared' (one level off) trained on synthetic scenes alone, recording none (an audit)
        raise InputError(f"--data: no training scene (middlebury_eval3_Q/*) in {str(data_dir)!r}; expected the shared "
                         "data folder (its MANIFEST.md)")
    return scenes


def _uniform(generator: torch.Generator, low: float, high: float) -> float:
    return low + (high - low) * float(torch.rand((), generator=generator))


def crop_batch(batch: StereoBatch, x0: int, y0: int, width: int, height: int) -> StereoBatch:
    """The window ``[x0, x0 + width) × [y0, y0 + height)`` of every pair (calibration unchanged: a crop moves
    both principal points alike)."""
    window = (..., slice(y0, y0 + height), slice(x0, x0 + width))
    hw = torch.tensor([[height, width]]).expand(batch.batch_size, 2).clone()
    nonoccluded = None if batch.disparity_nonoccluded is None else batch.disparity_nonoccluded[window]
    return dataclasses.replace(batch, left=batch.left[window], right=batch.right[window], image_hw=hw,
                               disparity_px=batch.disparity_px[window], disparity_valid=batch.disparity_valid[window],
                               disparity_nonoccluded=nonoccluded)


def random_crop(batch: StereoBatch, generator: torch.Generator, crop_wh: tuple[int, int] = CROP_WH) -> StereoBatch:
    """The scene resized to a random width from the crop's to 1.75 times it (160–280 px for the default 160×120;
    at least high enough for the crop's rows), then a random ``crop_wh`` window."""
    height, width = batch.size_hw
    new_width = max(round(_uniform(generator, crop_wh[0], crop_wh[0] * 7 / 4)), math.ceil(crop_wh[1] * width / height))
    new_height = round(height * new_width / width)
    scaled = resize_stereo_batch(batch, (new_width, new_height))
    x0 = int(torch.randint(0, new_width - crop_wh[0] + 1, (), generator=generator))
    y0 = int(torch.randint(0, new_height - crop_wh[1] + 1, (), generator=generator))
    return crop_batch(scaled, x0, y0, *crop_wh)


def jpeg_frame(image: torch.Tensor, quality: int) -> torch.Tensor:
    """A ``(1, 1, H, W)`` image through an 8-bit JPEG encode and decode at ``quality`` (the SVS sends JPEG)."""
    pixels = (image[0, 0].clamp(0, 1) * 255).round().byte().numpy()
    _, data = cv2.imencode(".jpg", pixels, [cv2.IMWRITE_JPEG_QUALITY, quality])
    decoded = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)
    return torch.from_numpy(decoded.astype(np.float32) / 255).view_as(image).to(image.dtype)


def augment(batch: StereoBatch, generator: torch.Generator, right_gain: tuple[float, float] = (0.85, 1.15),
            right_offset: float = 0.05, max_noise: float = 0.02, jpeg_share: float = 0.0) -> StereoBatch:
    """Photometric changes (module docstring), on ``jpeg_share`` of the calls JPEG frames of quality 40–95, and a
    vertical flip, one draw per call (B = 1). The right view's exposure differs by a gain in ``right_gain`` and an
    offset up to ``±right_offset``; the noise's standard deviation is up to ``max_noise``. With ``jpeg_share`` 0
    no JPEG draw is made (the draws of the runs that made the shipped weights)."""
    def photometric(image: torch.Tensor, gamma: float, gain: float, offset: float) -> torch.Tensor:
        return (image.clamp_min(0) ** gamma * gain + offset).clamp(0, 1)

    gamma = math.exp(_uniform(generator, math.log(0.5), math.log(2.0)))
    gain, offset = _uniform(generator, 0.6, 1.2), _uniform(generator, -0.15, 0.15)
    left = photometric(batch.left, gamma, gain, offset)
    right = photometric(batch.right, gamma, gain, offset)
    right = (right * _uniform(generator, *right_gain) + _uniform(generator, -right_offset, right_offset)).clamp(0, 1)
    if float(torch.rand((), generator=generator)) < 0.35:
        left, right = 1 - left, 1 - right
    noise = _uniform(generator, 0.0, max_noise)
    left = (left + noise * torch.randn(left.shape, generator=generator)).clamp(0, 1)
    right = (right + noise * torch.randn(right.shape, generator=generator)).clamp(0, 1)
    if jpeg_share > 0 and float(torch.rand((), generator=generator)) < jpeg_share:
        quality = int(torch.randint(40, 96, (), generator=generator))
        left, right = jpeg_frame(left, quality), jpeg_frame(right, quality)
    out = dataclasses.replace(batch, left=left, right=right)
    if float(torch.rand((), generator=generator)) < 0.5:
        nonoccluded = None if out.disparity_nonoccluded is None else out.disparity_nonoccluded.flip(-2)
        out = dataclasses.replace(out, left=out.left.flip(-2), right=out.right.flip(-2),
                                  disparity_px=out.disparity_px.flip(-2), disparity_valid=out.disparity_valid.flip(-2),
                                  disparity_nonoccluded=nonoccluded)
    return out


def synthetic_pairs(count: int, generator: torch.Generator) -> list[StereoBatch]:
    """``count`` synthetic pairs of 1–3 boxes 0.7–2.5 m away before a wall 3–6 m away, 160×120."""
    pairs = []
    for _ in range(count):
        scene = random_obstacle_scenes(1, int(torch.randint(1, 4, (), generator=generator)), size_wh=CROP_WH,
                                       depth_range_m=(0.7, 2.5), background_depth_m=_uniform(generator, 3.0, 6.0),
                                       noise_std=0.01, generator=generator)
        pairs.append(scene.batch)
    return pairs


def real_pairs(scenes: list[Path], config, generator: torch.Generator, crop_wh: tuple[int, int] = CROP_WH
               ) -> list[StereoBatch]:
    """Random crops and whole views of the real training scenes at ``crop_wh`` (module docstring):
    ``config.crops_per_scene`` and ``config.views_per_scene`` of each (a :class:`TrainConfig` or
    train_nearness.py's)."""
    pairs = []
    for path in scenes:
        batch = with_nominal_calibration(load_stereo_pair(path))
        pairs += [random_crop(batch, generator, crop_wh) for _ in range(config.crops_per_scene)]
        whole = resize_stereo_batch(batch, crop_wh)
        pairs += [whole] * config.views_per_scene
    return pairs


@dataclasses.dataclass
class Pool:
    """Training samples stacked, with what the loss needs: features, soft disparity, truth, calibration."""

    features: torch.Tensor  # (S, 6, h, w)
    disparity: torch.Tensor  # (S, 1, h, w)
    target: torch.Tensor  # (S, 1, h, w) float: the opened near mask
    nearest_m: torch.Tensor  # (S,)
    nearest_valid: torch.Tensor  # (S,) bool
    calibration: torch.Tensor  # (S, 3): focal_px, baseline_m, doffs_px
    images: torch.Tensor  # (S, 1, h, w) left, for the hard segmentation's status


def build_pool(pairs: list[StereoBatch], net_config: ObstacleNetConfig, generator: torch.Generator) -> Pool:
    rows = {name: [] for name in ("features", "disparity", "target", "nearest_m", "nearest_valid", "calibration",
                                  "images")}
    with torch.no_grad():
        for pair in Progress(len(pairs), "samples").over(pairs):
            pair = augment(pair, generator)
            truth = obstacle_truth(pair)
            features, disparity = stereo_features(pair.left, pair.right, net_config)
            rows["features"].append(features)
            rows["disparity"].append(disparity)
            rows["target"].append(truth.opened.float())
            rows["nearest_m"].append(truth.nearest_m)
            rows["nearest_valid"].append(truth.nearest_valid)
            rows["calibration"].append(torch.stack([pair.focal_px, pair.baseline_m, pair.doffs_px], 1))
            rows["images"].append(pair.left)
    return Pool(**{name: torch.cat(values) for name, values in rows.items()})


def mask_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Binary cross-entropy + soft Dice (the Dice term weighs small obstacles as much as big walls)."""
    probability = torch.sigmoid(logits)
    overlap = (probability * target).flatten(1).sum(1)
    dice = 1 - (2 * overlap + 1) / (probability.flatten(1).sum(1) + target.flatten(1).sum(1) + 1)
    return F.binary_cross_entropy_with_logits(logits, target) + dice.mean()


def depth_loss(logits: torch.Tensor, pool: Pool, index: torch.Tensor) -> torch.Tensor:
    """Mean relative error of the nearest obstacle's soft depth, over samples where it and the truth exist."""
    segmentation = segment_learned(pool.images[index], logits.detach())
    calibration = pool.calibration[index]
    soft = soft_object_depths(logits, segmentation, pool.disparity[index], calibration[:, 0], calibration[:, 1],
                              calibration[:, 2])
    both = soft.nearest_valid & pool.nearest_valid[index]
    truth = torch.where(both, pool.nearest_m[index], 1.0)
    error = torch.where(both, (soft.nearest_m - truth).abs() / truth, 0.0)
    return error.sum() / both.sum().clamp(min=1)


def adamw(net: torch.nn.Module, config) -> torch.optim.AdamW:
    """AdamW over ``net``'s parameters at ``config``'s ``learning_rate`` and ``weight_decay``, made with Ctrl-C held
    back until it is made (:func:`~svs_torch.core.workers.signals_held`). Why: torch's first optimizer imports
    torch._dynamo, hence sympy and mpmath, and mpmath's bare ``except:`` around its import of gmpy swallowed a
    Ctrl-C that arrived then; the run trained on as if never interrupted (seen once in CI, then reproduced by
    signalling during that import)."""
    with signals_held():
        return torch.optim.AdamW(net.parameters(), lr=config.learning_rate, weight_decay=config.weight_decay)


def check_not_diverged(loss: torch.Tensor, step: int, name: str) -> None:
    """Refuse a NaN or infinite ``loss`` at ``step``, saying the run diverged. Why: '--learning-rate 1e30' ended in
    "logits: expected numbers, got NaN", the soft depth's check of its input, as if an input were broken (an audit)."""
    if not bool(torch.isfinite(loss.detach())):
        raise InputError(f"--learning-rate: the training diverged at step {step} ({name} loss {loss.item()}); nothing "
                         "written: try a lower rate")


def train(pool: Pool, net: ObstacleNet, config: TrainConfig, generator: torch.Generator) -> list[dict]:
    optimizer = adamw(net, config)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, config.steps)
    history = []
    net.train()
    bar = Progress(config.steps, "train", unit="step")
    for step in bar.over(range(config.steps)):
        index = torch.randint(0, pool.features.shape[0], (config.batch_size,), generator=generator)
        features, target = pool.features[index], pool.target[index]
        # Vertical flips only: rows stay epipolar lines (a horizontal flip would need the views swapped).
        flipped = float(torch.rand((), generator=generator)) < 0.5
        if flipped:
            features, target = features.flip(-2), target.flip(-2)
        logits = net(features)
        masks = mask_loss(logits, target)
        check_not_diverged(masks, step, "mask")
        depth = depth_loss(logits.flip(-2) if flipped else logits, pool, index)
        loss = masks + config.depth_weight * depth
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        schedule.step()
        history.append({"step": step, "mask_loss": masks.item(), "depth_loss": depth.item()})
        bar.set_postfix(mask=f"{masks.item():.3f}", depth=f"{depth.item():.3f}")
    net.eval()
    return history


def region_mean_depth_m(batch: StereoBatch, result, net: ObstacleNet) -> torch.Tensor:
    """``(B, N)``: each ranged object's mean depth over its whole kept region, every measured pixel weighted by
    the network's obstacle probability (from the hard dense map, in the pairs measured on their raw rows; 0
    elsewhere). Differentiable w.r.t. the network's weights: the gradient reaches every pixel of the region, where
    the median's reaches only its band, so the probabilities, which the hard masks threshold, learn which of
    the region's pixels belong to the object."""
    probability = torch.sigmoid(predict_obstacle_logits(net, batch.left, batch.right)).flatten(1)  # (B, P)
    # A rectified pair's dense map is in its rectified pixels, not the network's: the term leaves such pairs out
    # (pipeline_depth_loss counts them apart), where it read 0 m and added a constant 100 % per object.
    dense = result.dense
    disparity = dense.disparity_px.flatten(1) + batch.doffs_px.view(-1, 1)
    measured = dense.valid.flatten(1) & (disparity > 0) & ~result.rectified.view(-1, 1)
    depth = torch.where(measured, (batch.focal_px * batch.baseline_m).view(-1, 1) / torch.where(
        measured, disparity, 1.0), 0.0)
    slots = result.depth.objects.label  # (B, N)
    member = (result.object_labels.flatten(1).unsqueeze(1) == slots.unsqueeze(-1)) & measured.unsqueeze(1)
    weights = member * probability.unsqueeze(1)  # (B, N, P)
    return (weights * depth.unsqueeze(1)).sum(-1) / weights.sum(-1).clamp_min(1e-6)


def nearest_obstacle_error(batch: StereoBatch, result) -> torch.Tensor:
    """The mean relative error of each pair's nearest ranged obstacle against the truth's nearest obstacle
    (:func:`~svs_torch.segmentation.learned.obstacle_truth`: what ``eval_segmentation.py`` scores, issue 32), a
    pair whose truth has one and whose pipeline ranged none counting 1 (100 %). The per-object error alone is
    measured over the regions the network keeps: a fine-tune lowered it by losing hard regions while the warned
    obstacle moved farther away (an audit: the training scenes' nearest-obstacle accuracy 95.3 -> 89.9 %)."""
    truth = obstacle_truth(batch)
    nearest = result.depth.nearest
    has = truth.nearest_valid
    true_m = torch.where(has, truth.nearest_m.to(nearest.depth_m.dtype), 1.0)
    error = torch.where(nearest.valid & has, (nearest.depth_m - true_m).abs() / true_m, 1.0)
    return torch.where(has, error, 0.0).sum() / has.sum().clamp(min=1)


def pipeline_depth_loss(batch: StereoBatch, net: ObstacleNet, region_weight: float = 0.0, segmenter: str = "learned"
                        ) -> tuple[torch.Tensor, int, torch.Tensor]:
    """The loss to judge weights by: the mean relative error of every ranged object's differentiable depth against
    its region's median GT depth, through ``estimate_obstacle_depth(..., differentiable=True)``, plus
    :func:`nearest_obstacle_error` (against the true obstacles, so that losing a hard one does not pay); the number
    of objects the first term averages; and the loss to descend: that plus ``region_weight`` × the per-object
    error of :func:`region_mean_depth_m` (pairs measured on their raw rows)."""
    images = dataclasses.replace(batch, left=batch.left.clone().requires_grad_(),
                                 right=batch.right.clone().requires_grad_())
    segmentation = PipelineConfig().segmentation if segmenter == "nearness" else SegmentationConfig()
    config = PipelineConfig(differentiable=True, segmentation=dataclasses.replace(segmentation, segmenter=segmenter))
    result = estimate_obstacle_depth(images, config, network=net)
    truth = object_truth(batch, measured_regions(result))
    objects = result.depth.objects
    both = objects.valid & truth.valid
    true_m = torch.where(both, truth.depth_m.to(objects.depth_median_m.dtype), 1.0)
    count = both.sum().clamp(min=1)
    error = torch.where(both, (objects.depth_median_m - true_m).abs() / true_m, 0.0).sum() / count
    error = error + nearest_obstacle_error(batch, result)
    total = error
    if region_weight > 0 and torch.is_grad_enabled():
        mean_m = region_mean_depth_m(batch, result, net)
        raw = both & ~result.rectified.view(-1, 1)
        total = total + region_weight * torch.where(raw, (mean_m - true_m).abs() / true_m, 0.0).sum() / raw.sum(
            ).clamp(min=1)
    return error, int(both.sum()), total


def fine_tune_through_pipeline(pairs: list[StereoBatch], net: ObstacleNet, config: TrainConfig,
                               generator: torch.Generator, region_weight: float = 0.0, segmenter: str = "learned"
                               ) -> list[dict]:
    """``config.steps`` AdamW steps on batches of ``config.batch_size`` pairs drawn from ``pairs`` (every pair, a
    full batch, when it holds them all: the loss is then the same quantity at every step), the loss of
    :func:`pipeline_depth_loss` (with ``region_weight``). The network stays in eval mode (its hard segmentation is
    deployment's).

    The hard masks move with the weights and the gradient does not see them, so a step can raise the loss: with a
    full batch the weights left in ``net`` are those of the lowest loss seen (the loss printed at a step is that
    of the weights before it; one more forward scores the last step's weights)."""
    optimizer = adamw(net, config)
    full_batch = config.batch_size >= len(pairs)
    history, best = [], (math.inf, None, -1)
    for step in range(config.steps + full_batch):
        index = torch.randperm(len(pairs), generator=generator)[:config.batch_size].tolist()
        loss, count, total = pipeline_depth_loss(collate_stereo_batches([pairs[i] for i in index]), net,
                                                 region_weight, segmenter)
        history.append({"step": step, "depth_loss": loss.item(), "num_objects": count})
        print(f"step {step:3d}  depth loss {loss.item():.5f}  ({count} objects)", flush=True)
        if full_batch and loss.item() < best[0]:
            best = (loss.item(), {k: v.detach().clone() for k, v in net.state_dict().items()}, step)
        if step == config.steps:  # the extra forward of a full batch: the last step's weights scored
            break
        optimizer.zero_grad()
        total.backward()
        optimizer.step()
    if best[1] is not None:
        net.load_state_dict(best[1])
        print(f"kept the weights before step {best[2]} (depth loss {best[0]:.5f})", flush=True)
    return history


def listed_pairs(list_file: str) -> list[StereoBatch]:
    """The pairs of the pair list ``list_file`` (``--pairs``) that have ground truth, each left out said; those
    without a calibration given a nominal one (:func:`~svs_torch.evaluation.with_nominal_calibration`), as
    ``svs-depth eval`` scores them and as the training scenes are read. Why: a shared KITTI frame loads uncalibrated,
    so its truth had no depth, and a fine-tune on such pairs printed a loss of 0 over 0 objects at every step and
    wrote its starting weights as trained, without a word (an audit)."""
    sources = read_pair_list(list_file, "--pairs")
    bad = [source.problem for source in sources if source.problem]
    # InputError, as run_script ends every refused input (exit status 2; SystemExit of the text was status 1)
    if bad:  # a traceback from inside before
        raise InputError(bad[0])
    pairs = [load_pair_source(source) for source in sources]
    without = [p.names[0] if p.names else "?" for p in pairs if p.disparity_px is None]
    pairs = [p for p in pairs if p.disparity_px is not None]
    if without:  # they add nothing to a loss against ground truth: said, not silently skipped
        print(f"--pairs: {len(without)} pair(s) without ground truth left out: {', '.join(without[:5])}",
              file=sys.stderr)
    if not pairs:
        raise InputError("--pairs: no listed pair has ground truth (a scene folder with its disparity); nothing "
                         "to train on")
    nominal = [p.names[0] if p.names else "?" for p in pairs if not bool(p.calibrated.all())]
    if nominal:
        print(f"--pairs: {len(nominal)} pair(s) without a calibration given a nominal one for their truth's depth, as "
              f"svs-depth eval scores them: {', '.join(nominal[:5])}", file=sys.stderr)
    return [with_nominal_calibration(p) for p in pairs]


def through_pipeline_main(args: argparse.Namespace, config: TrainConfig, command: str) -> Path:
    generator = torch.Generator().manual_seed(config.seed)
    if args.pairs is not None:  # "" is a list file name to refuse, not the training scenes (an audit)
        pairs = listed_pairs(args.pairs)
    else:
        pairs = [with_nominal_calibration(load_stereo_pair(path)) for path in train_scenes(Path(args.data))]
    pairs = [resize_stereo_batch(pair, checked_size(args.size)) for pair in pairs]
    net = load_obstacle_net(args.init)
    started = time.perf_counter()
    history = fine_tune_through_pipeline(pairs, net, config, generator, args.region_weight)
    with torch.no_grad():
        final, count, _ = pipeline_depth_loss(collate_stereo_batches(pairs), net)
    metadata = {"train": dataclasses.asdict(config), "mode": "through-pipeline", "init": args.init,
                "command": command, "region_weight": args.region_weight,
                "pairs": [p.names[0] if p.names else "" for p in pairs], "size": args.size, "history": history,
                "final_depth_loss_all_pairs": final.item(), "train_time_s": round(time.perf_counter() - started, 1),
                "run": run_metadata(args.threads, command=command)}
    save_obstacle_net(args.out, net, metadata)
    print(f"{len(pairs)} pairs, {config.steps} steps; depth loss over all pairs {final.item():.5f} ({count} "
          f"objects); weights written to {args.out}")
    return Path(args.out)


#: What each training setting is, for the training scripts' --help (an audit: they showed a default alone).
SETTING_HELP = {
    "steps": "optimiser steps", "batch_size": "pairs per step",
    "learning_rate": "AdamW's learning rate, decayed to 0 on a cosine", "weight_decay": "AdamW's weight decay",
    "depth_weight": "weight of the nearest obstacle's relative depth error in the loss, beside BCE + Dice",
    "crops_per_scene": "random-scale {crop} crops of each real training scene",
    "views_per_scene": "whole views of each real training scene, each augmented anew",
    "num_synthetic": "rendered synthetic SVS scenes", "seed": "seed of every random draw (torch.Generator)",
    "fine_tune_steps": "steps through the differentiable pipeline after the mask steps (stage 2)",
    "fine_tune_learning_rate": "the learning rate of those steps",
}


def _setting_types() -> dict:
    """Each training setting's argparse type: counts and rates in their ranges, refused when parsed (an audit:
    ``--steps -5`` built 704 samples for 80 s and wrote weights recording -5 steps; ``--batch-size 0`` and
    ``--learning-rate nan`` were taken; ``--threads 0`` was a traceback)."""
    return {"steps": non_negative_int, "fine_tune_steps": non_negative_int, "batch_size": positive_int,
            "crops_per_scene": non_negative_int, "views_per_scene": non_negative_int,
            "num_synthetic": non_negative_int, "seed": seed_int, "learning_rate": positive_float,
            "fine_tune_learning_rate": positive_float, "weight_decay": non_negative_float,
            "depth_weight": non_negative_float}


def add_config_options(parser: argparse.ArgumentParser, defaults, skip: tuple[str, ...] = (),
                       said: dict[str, str] | None = None, crop_wh: tuple[int, int] = CROP_WH) -> list[str]:
    """One typed ``--option`` per field of the dataclass instance ``defaults`` but ``skip``, defaulting to its
    value, its help from :data:`SETTING_HELP` (and ``said``'s default text where the script chooses it later;
    ``crop_wh``: the size of the script's crops); returns the fields' names (the training scripts' settings as
    command-line options)."""
    names = [field.name for field in dataclasses.fields(defaults) if field.name not in skip]
    types = _setting_types()
    for name in names:
        value = getattr(defaults, name)
        default = (said or {}).get(name, "%(default)s")
        parser.add_argument("--" + name.replace("_", "-"), type=types.get(name, type(value)), default=value,
                            help=f"{SETTING_HELP.get(name, name.replace('_', ' '))} (default: {default})".replace(
                                "{crop}", "x".join(map(str, crop_wh))))
    return names


def samples_per_run(config) -> int:
    """How many samples per real scene and synthetic ones a run with ``config`` builds (0: nothing to train on)."""
    return config.crops_per_scene + config.views_per_scene + config.num_synthetic


def init_weights(text: str) -> str:
    """argparse type of ``--init``: ``learned`` or ``learned:PATH`` naming obstacle-network weights, read now. Found
    by an audit: ``--init nearness`` failed after the pairs were read with "network: expected an ObstacleNet for
    segmenter 'learned'", and a bad file's line named "segmenter", not --init."""
    if text.partition(":")[0] != "learned":
        raise argparse.ArgumentTypeError(f"expected 'learned' or 'learned:PATH' (obstacle-network weights; nearness "
                                         f"weights are trained by train_nearness.py), got {text!r}")
    try:
        return segmenter_choice(text)  # svs-depth's --segmenter check: the file read, its error one line
    except argparse.ArgumentTypeError as error:
        # Its advice for a nearness file, "give it as nearness:PATH", is svs-depth's; --init refused that in turn
        # (an audit: each message sent the user to the other).
        raise argparse.ArgumentTypeError(str(error).replace(
            "(give it as nearness:PATH)", "(--init takes obstacle-network weights; nearness weights are trained by "
            "train_nearness.py)")) from None


def size_text(text: str) -> str:
    """argparse type of ``--size``: ``WxH`` as svs-depth's --size takes it (``--size 320`` was a ValueError
    traceback once the pairs were read: an audit)."""
    try:
        checked_size(text)
    except InputError as error:
        raise argparse.ArgumentTypeError(str(error).removeprefix("--size: ")) from None
    return text


def main(argv: list[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_option(parser)
    parser.add_argument("--out", type=output_path, help="weights file, checked before any work (default: the "
                        "shipped one, whose tensors the defaults reproduce, its record of the run this one's; any "
                        "other run, and --through-pipeline, needs one: it never replaces the shipped weights)")
    defaults = TrainConfig()
    names = add_config_options(parser, defaults, said={
        "steps": f"{defaults.steps}; 20 with --through-pipeline",
        # (fine_tune_through_pipeline has no schedule: its rate stays as given)
        "learning_rate": f"{defaults.learning_rate:g}; 1e-4 and constant with --through-pipeline"})
    parser.add_argument("--threads", type=positive_int, default=2, help="torch threads (default: %(default)s)")
    parser.add_argument("--through-pipeline", action="store_true",
                        help="fine-tune through estimate_obstacle_depth(..., differentiable=True) (docstring)")
    parser.add_argument("--pairs", help="--through-pipeline: a pair list (default: the training scenes)")
    parser.add_argument("--init", default="learned", type=init_weights, help="--through-pipeline: starting weights, "
                        "'learned' or 'learned:PATH' (read when the option is checked)")
    parser.add_argument("--size", default="320x240", type=size_text, help="--through-pipeline: pairs resized to WxH")
    parser.add_argument("--region-weight", type=non_negative_float, default=1.0, help="--through-pipeline: weight "
                        "of the probability-weighted mean depth over each whole kept region in the loss (0: the "
                        "median's)")
    parser.set_defaults(steps=None, learning_rate=None)  # each mode's own (below)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    # A fine-tune takes few small steps (20 at 1e-4, about 3 minutes on 8 pairs); the 700 steps at 3e-3 of
    # training from scratch took about an hour through the pipeline.
    fine_tune = {"steps": 20, "learning_rate": 1e-4} if args.through_pipeline else {}
    for name in ("steps", "learning_rate"):
        if getattr(args, name) is None:
            setattr(args, name, fine_tune.get(name, getattr(TrainConfig(), name)))
    config = TrainConfig(**{name: getattr(args, name) for name in names})
    command = command_line("experiments/train_segmentation.py", argv)
    if args.through_pipeline:
        refuse_unread_options(parser, args, ["crops_per_scene", "views_per_scene", "num_synthetic", "depth_weight"],
                              "training from scratch (without --through-pipeline)")
        if args.pairs is not None:
            refuse_unread_options(parser, args, ["data"], "without --pairs (the pairs of the training scenes)")
    else:
        refuse_unread_options(parser, args, ["pairs", "init", "size", "region_weight"], "with --through-pipeline")
    if args.through_pipeline:
        if args.out is None:
            parser.error("--through-pipeline: expected --out FILE for the fine-tuned weights")
        return through_pipeline_main(args, config, command)
    if config.steps < 1 or not samples_per_run(config):  # history[-1] / torch.cat([]) once samples were built
        parser.error("--steps, and --crops-per-scene, --views-per-scene or --num-synthetic: training from scratch "
                     "expects at least 1 step on at least 1 sample")
    shipped = config == TrainConfig() and args.threads == 2 and args.data == default_data_dir()
    if args.out is None and not shipped:  # a quick trial once replaced the shipped weights without a word
        parser.error("--out: expected a file for weights that are not the shipped ones (those are the defaults' "
                     "at --threads 2 on the shared data)")
    args.out = args.out or str(SHIPPED_WEIGHTS)
    generator = torch.Generator().manual_seed(config.seed)
    torch.manual_seed(config.seed)  # the network's initial weights (nn.Module draws from the global generator)
    net_config = ObstacleNetConfig()
    scenes = train_scenes(Path(args.data))
    started = time.perf_counter()
    pairs = real_pairs(scenes, config, generator) + synthetic_pairs(config.num_synthetic, generator)
    pool = build_pool(pairs, net_config, generator)
    net = ObstacleNet(net_config)
    history = train(pool, net, config, generator)
    elapsed = time.perf_counter() - started
    split = split_scenes(Path(args.data))
    metadata = {
        "train": dataclasses.asdict(config), "train_time_s": round(elapsed, 1), "num_samples": len(pairs),
        "train_scenes": [str(p.relative_to(args.data)) for p in scenes],
        "excluded_duplicates": HELD_OUT_DUPLICATES,
        "held_out_scenes": [str(p.relative_to(args.data)) for p in split["held-out"]],
        "final_losses": history[-1], "run": run_metadata(args.threads, command=command),
        "num_parameters": sum(p.numel() for p in net.parameters()),
        "command": command,
    }
    save_obstacle_net(args.out, net, metadata)
    print(f"{len(pairs)} samples, {config.steps} steps, {elapsed:.0f} s; weights written to {args.out}")
    return Path(args.out)


if __name__ == "__main__":
    run_script(main)
