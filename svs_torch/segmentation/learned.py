"""Learned obstacle segmentation: find what is near, not what is bright (the paper's "next step", Sec. 5).

Otsu on intensity (:mod:`svs_torch.segmentation`) keeps the brightest large regions, often a wall. Here:

- **Truth** (:func:`obstacle_truth`): the obstacles of a pair with ground-truth disparity are the Otsu threshold of
  its valid GT disparity (near against far), a 5×5 opening and the two largest regions, with the same threshold,
  morphology and component code as the paper's stage; the nearest obstacle's distance is the median GT depth
  over the nearer of those regions.
- **Network** (:class:`ObstacleNet`, ~80k parameters, torch only): a small U-Net with a global-context bottleneck
  over stereo features at a working width of 160 px (:func:`stereo_features`: both images, and the soft-argmin
  SAD disparity of :func:`svs_torch.depth.dense.soft_block_match`, absolute and relative to the image's median), giving
  per-pixel obstacle logits (:func:`predict_obstacle_logits`).
- **Segmenter** (:func:`segment_stereo_learned`): the probability thresholded, the same opening, components and
  two largest regions; the same :class:`~svs_torch.core.types.StereoSegmentation` as
  :func:`~svs_torch.segmentation.segment_stereo`, so the rest of the pipeline is unchanged
  (``SegmentationConfig.segmenter``: ``"otsu"``, ``"learned"`` = the shipped weights, ``"learned:PATH"``).
- **Soft path** (:func:`soft_object_depths`): soft masks ``sigmoid(logit / T)`` gated by the hard kept regions
  become soft region weights; each object's disparity is the weighted mean of the soft-argmin disparity, its
  depth ``f·B / (d + doffs)``; the nearest obstacle is the smallest. Gradients reach the logits (hence the
  network) and both images. The weighted mean stands in for the hard stage's median (a median passes gradient to
  one pixel only); on an object of one depth both agree.

Weights are written by ``experiments/train_segmentation.py`` with their configuration and the split they were
trained on (:func:`save_obstacle_net`); the shipped file lives in ``svs_torch/weights/``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from ..core.checks import InputError, check_dtype, check_image, check_shape
from .components import connected_components_with_stats
from ..depth.dense import DenseConfig, soft_block_match
from ..depth.sparse import kept_region_lower_median
from .morphology import open_binary, structuring_element
from .segment import SegmentationConfig, _status, keep_largest_regions
from .threshold import gray_histogram, gray_levels, gray_levels_and_histogram, otsu_threshold_level
from ..core.types import Segmentation, SegmentationStatus, StereoBatch, StereoSegmentation

__all__ = [
    "SHIPPED_WEIGHTS", "ObstacleNet", "ObstacleNetConfig", "ObstacleTruth", "SoftObjectDepths", "cached_obstacle_net",
    "load_obstacle_net",
    "mask_iou", "obstacle_truth", "predict_obstacle_logits", "save_obstacle_net", "segment_learned",
    "segment_stereo_learned", "soft_nearest_depth", "soft_object_depths", "stereo_features",
]

#: The weights shipped inside the package (``SegmentationConfig(segmenter="learned")``).
SHIPPED_WEIGHTS = Path(__file__).resolve().parent / "weights" / "obstacle_net.pt"
#: The nearness segmenter's shipped correction network (``SegmentationConfig(segmenter="nearness")``, issue 32).
NEARNESS_WEIGHTS = Path(__file__).resolve().parent / "weights" / "nearness_net.pt"
_FORMAT = "svs_torch.obstacle_net/1"
#: Each segmenter kind's weights-file format (the classes: :func:`_network_classes`).
_KINDS = {"learned": _FORMAT, "nearness": "svs_torch.nearness_net/1"}
NUM_FEATURES = 6  # channels of stereo_features


# ----------------------------------------------------------------------------------------------------- truth
@dataclass(frozen=True)
class ObstacleTruth:
    """Truth obstacles of B pairs from their ground-truth disparity (N = ``num_keep`` slots).

    Attributes:
        near: ``(B, 1, H, W)`` bool, valid GT disparity above its Otsu threshold.
        opened: ``(B, 1, H, W)`` bool, ``near`` after the opening.
        labels: ``(B, 1, H, W)`` int64 components of ``opened``; kept_labels ``(B, N)`` int64 (−1: none).
        kept_mask: ``(B, 1, H, W)`` bool, the union of the kept regions: the truth mask.
        region_depth_m: ``(B, N)`` lower-median GT depth over each kept region's pixels with a known depth.
        region_valid: ``(B, N)`` bool, the slot holds a region with at least one such pixel.
        nearest_m: ``(B,)`` the smallest valid ``region_depth_m`` (0 where none); nearest_valid ``(B,)`` bool.
    """

    near: torch.Tensor
    opened: torch.Tensor
    labels: torch.Tensor
    kept_labels: torch.Tensor
    kept_mask: torch.Tensor
    region_depth_m: torch.Tensor
    region_valid: torch.Tensor
    nearest_m: torch.Tensor
    nearest_valid: torch.Tensor


def _disparity_levels(disparity: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Valid disparities mapped linearly from each image's [min, max] to gray levels 0..255 (0 where invalid)."""
    b = disparity.shape[0]
    some = valid.flatten(1).any(1).view(b, 1, 1, 1)
    low = torch.where(some, torch.where(valid, disparity, torch.inf).flatten(1).amin(1).view(b, 1, 1, 1), 0.0)
    high = torch.where(some, torch.where(valid, disparity, -torch.inf).flatten(1).amax(1).view(b, 1, 1, 1), 0.0)
    spread = high - low
    scale = torch.where(spread > 0, 1 / torch.where(spread > 0, spread, 1.0), 0.0)  # one level: all at 0
    return gray_levels(torch.where(valid, (disparity - low) * scale, 0.0))


def obstacle_truth(batch: StereoBatch, config: SegmentationConfig = SegmentationConfig()) -> ObstacleTruth:
    """The truth obstacles (module docstring) with ``config``'s element, connectivity and ``num_keep``.

    Depths need a calibrated pair (:meth:`StereoBatch.ground_truth_depth_m`); an uncalibrated one still gets its
    masks, with ``nearest_valid`` False. Not differentiable.

    Raises:
        InputError: the batch has no ground-truth disparity.
    """
    if batch.disparity_px is None:
        raise InputError("batch: expected ground-truth disparity (disparity_px), got none")
    valid = batch.disparity_valid
    levels = _disparity_levels(batch.disparity_px, valid)
    histogram = gray_histogram(levels)
    histogram[:, 0] -= (~valid).flatten(1).sum(1)  # invalid pixels were put at level 0: take them out again
    level = otsu_threshold_level(histogram)
    near = valid & (levels > level.to(torch.uint8).view(-1, 1, 1, 1))
    element = structuring_element(config.kernel_shape, config.kernel_size, device=near.device)
    opened = open_binary(near, element)
    labels, _, regions = connected_components_with_stats(opened, config.connectivity)
    kept_labels, kept_mask = keep_largest_regions(labels, regions, config.num_keep)
    depth, known = batch.ground_truth_depth_m()
    region_depth, count = kept_region_lower_median(depth, known, labels, kept_labels)
    region_valid = count > 0
    nearest = torch.where(region_valid, region_depth, torch.inf).amin(1)
    nearest_valid = torch.isfinite(nearest)
    return ObstacleTruth(near, opened, labels, kept_labels, kept_mask, region_depth, region_valid,
                         torch.where(nearest_valid, nearest, 0.0), nearest_valid)


def mask_iou(mask: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Intersection over union ``(B,)`` of two ``(B, 1, H, W)`` bool masks; 1 where both are empty."""
    check_shape(mask, "mask", ["B", 1, "H", "W"])
    check_shape(truth, "truth", list(mask.shape))
    inter = (mask & truth).flatten(1).sum(1)
    union = (mask | truth).flatten(1).sum(1)
    return torch.where(union > 0, inter / union.clamp(min=1), 1.0)


# --------------------------------------------------------------------------------------------------- network
@dataclass(frozen=True)
class ObstacleNetConfig:
    """Architecture and input settings of :class:`ObstacleNet` (stored beside its weights).

    Attributes:
        working_width_px: the network sees both images reduced (antialiased) to this width, pixels; its logits
            are resized back. 160 px keeps the cost volume and the network small; the kept regions are large.
        max_disparity_fraction: the soft-argmin searches disparities ``[0, fraction · width)``: 48 px at 160,
            above the largest disparity of the shared scenes there (35 px) and of the SVS at 0.5 m (30 px).
        disparity_temperature: soft-argmin temperature, pre-filtered intensity units (``DenseConfig``): Otsu of
            that disparity alone matched the truth with IoU 0.66 on the held-out scenes at 0.003, 0.59 at 0.01.
        channels: widths of the three U-Net levels.
        probability_threshold: a pixel is an obstacle where its probability exceeds this.
    """

    working_width_px: int = 160
    max_disparity_fraction: float = 0.3
    disparity_temperature: float = 0.003
    channels: tuple[int, int, int] = (16, 24, 32)
    probability_threshold: float = 0.5

    def __post_init__(self) -> None:
        if not isinstance(self.working_width_px, int) or self.working_width_px < 16:
            raise InputError(f"working_width_px: expected an int >= 16, got {self.working_width_px!r}")
        if not 0 < self.max_disparity_fraction < 1:
            raise InputError(f"max_disparity_fraction: expected a value in (0, 1), got {self.max_disparity_fraction!r}")
        if not self.disparity_temperature > 0:
            raise InputError(f"disparity_temperature: expected a positive value, got {self.disparity_temperature!r}")
        if len(self.channels) != 3 or any(not isinstance(c, int) or c < 4 for c in self.channels):
            raise InputError(f"channels: expected three ints >= 4, got {self.channels!r}")
        if not 0 < self.probability_threshold < 1:
            raise InputError(f"probability_threshold: expected a value in (0, 1), got {self.probability_threshold!r}")

    @property
    def num_disparities(self) -> int:
        return math.ceil(self.max_disparity_fraction * self.working_width_px)


def _block(inputs: int, outputs: int) -> nn.Sequential:
    """Two 3×3 convolutions with group normalisation (batch-size independent: training and use agree)."""
    return nn.Sequential(nn.Conv2d(inputs, outputs, 3, padding=1), nn.GroupNorm(4, outputs), nn.ReLU(inplace=True),
                         nn.Conv2d(outputs, outputs, 3, padding=1), nn.GroupNorm(4, outputs), nn.ReLU(inplace=True))


class ThreeLevelUNet(nn.Module):
    """Three-level U-Net from ``inputs`` channels to one logit channel, ``channels`` wide at its three levels; the
    bottleneck sees the image's mean feature beside its own (global context: nearness is relative to the rest of
    the scene, as the truth's Otsu split is). Differentiable w.r.t. its parameters and its input."""

    def __init__(self, inputs: int, channels: tuple[int, int, int]) -> None:
        super().__init__()
        c1, c2, c3 = channels
        self.down1, self.down2, self.down3 = _block(inputs, c1), _block(c1, c2), _block(c2, c3)
        self.middle = _block(2 * c3, c3)
        self.up2, self.up1 = _block(c3 + c2, c2), _block(c2 + c1, c1)
        self.head = nn.Conv2d(c1, 1, 1)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        x1 = self.down1(features)  # (B, c1, h, w)
        x2 = self.down2(F.max_pool2d(x1, 2, ceil_mode=True))  # (B, c2, h/2, w/2)
        x3 = self.down3(F.max_pool2d(x2, 2, ceil_mode=True))  # (B, c3, h/4, w/4)
        x3 = self.middle(torch.cat([x3, x3.mean((2, 3), keepdim=True).expand_as(x3)], 1))
        y2 = self.up2(torch.cat([F.interpolate(x3, size=x2.shape[-2:], mode="bilinear"), x2], 1))
        y1 = self.up1(torch.cat([F.interpolate(y2, size=x1.shape[-2:], mode="bilinear"), x1], 1))
        return self.head(y1)


class ObstacleNet(ThreeLevelUNet):
    """:class:`ThreeLevelUNet` from :func:`stereo_features` ``(B, 6, h, w)`` to obstacle logits ``(B, 1, h, w)``."""

    def __init__(self, config: ObstacleNetConfig = ObstacleNetConfig()) -> None:
        super().__init__(NUM_FEATURES, config.channels)
        self.config = config


def _working_size(image: torch.Tensor, width: int) -> tuple[int, int]:
    h, w = image.shape[-2:]
    return max(1, round(h * width / w)), width


def _standardize(x: torch.Tensor) -> torch.Tensor:
    """Zero mean, unit spread per image; a flat image (spread below 1e-3) is only centred."""
    mean = x.mean((1, 2, 3), keepdim=True)
    std = x.std((1, 2, 3), keepdim=True)
    return (x - mean) / std.clamp_min(1e-3)


def _otsu_disparity(disparity: torch.Tensor) -> torch.Tensor:
    """``(B,)`` the disparity at the Otsu split of each map (the truth's rule on an estimate). Not differentiable."""
    flat = disparity.detach().flatten(1)
    low, high = flat.amin(1), flat.amax(1)
    level = otsu_threshold_level(gray_histogram(_disparity_levels(disparity.detach(), torch.ones_like(
        disparity, dtype=torch.bool))))
    return low + (level.to(flat.dtype) + 0.5) / 255 * (high - low)


def stereo_features(left: torch.Tensor, right: torch.Tensor, config: ObstacleNetConfig = ObstacleNetConfig()
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """Network input at the working size: ``(B, 6, h, w)`` and the soft-argmin disparity ``(B, 1, h, w)``.

    Channels: left and right standardised per image; the disparity divided by the searched count D (absolute
    nearness); the disparity minus its median, and minus its Otsu split (the truth's rule applied to this
    estimate), each divided by its 10–90 % spread (at least 1 px): relative nearness; the column ``x / w`` (the
    left border, where the right view has no match). Images ``(B, 1, H, W)`` in [0, 1]. Differentiable w.r.t.
    both images (the median and the split themselves are taken as constants).
    """
    size = _working_size(left, config.working_width_px)
    small = [F.interpolate(image, size=size, mode="bilinear", antialias=True, align_corners=False).clamp(0, 1)
             for image in (left, right)]
    num_disparities = config.num_disparities
    disparity = soft_block_match(small[0], small[1], 0, num_disparities, config.disparity_temperature)
    flat = disparity.detach().flatten(1)
    q = torch.quantile(flat, torch.tensor([0.1, 0.5, 0.9], dtype=flat.dtype, device=flat.device), dim=1)  # (3, B)
    spread = (q[2] - q[0]).clamp_min(1.0).view(-1, 1, 1, 1)
    column = torch.linspace(0, 1, size[1], dtype=left.dtype, device=left.device).expand_as(disparity)
    features = torch.cat([_standardize(small[0]), _standardize(small[1]), disparity / num_disparities,
                          (disparity - q[1].view(-1, 1, 1, 1)) / spread,
                          (disparity - _otsu_disparity(disparity).view(-1, 1, 1, 1)) / spread, column], 1)
    return features, disparity


def predict_obstacle_logits(net: ObstacleNet, left: torch.Tensor, right: torch.Tensor) -> torch.Tensor:
    """Obstacle logits ``(B, 1, H, W)`` of the left view of images ``(B, 1, H, W)``, bilinearly resized from the
    working size. Differentiable w.r.t. the network's parameters and both images."""
    check_image(left, "left")
    check_image(right, "right")
    if left.shape != right.shape:
        raise InputError(f"right: expected the shape of left {tuple(left.shape)}, got {tuple(right.shape)}")
    if not isinstance(net, ObstacleNet):  # the nearness segmenter's correction network
        from .nearness import nearness_logits
        return nearness_logits(net, left, right)[0]
    features, _ = stereo_features(left, right, net.config)
    logits = net(features.to(next(net.parameters()).dtype))
    return F.interpolate(logits, size=left.shape[-2:], mode="bilinear", align_corners=False).to(left.dtype)


# ------------------------------------------------------------------------------------------------- segmenter
def segment_learned(image: torch.Tensor, logits: torch.Tensor, config: SegmentationConfig = SegmentationConfig(),
                    probability_threshold: float = 0.5) -> Segmentation:
    """The hard segmentation of images ``(B, 1, H, W)`` from their obstacle logits ``(B, 1, H, W)``: probability
    above ``probability_threshold``, ``config``'s opening, components and ``num_keep`` largest regions.

    ``threshold`` holds the probability threshold and ``threshold_level`` it on the 0–255 scale; ``binary`` is
    the thresholded probability. Status as the Otsu stage's: ``UNIFORM_IMAGE`` for a one-level image (no
    information), ``NO_FOREGROUND`` when nothing survives the opening. Not differentiable.
    """
    dims = check_image(image, "image")
    check_shape(logits, "logits", [dims["B"], 1, dims["H"], dims["W"]])
    check_dtype(logits, "logits", "float")
    b = dims["B"]
    binary = logits.detach() > math.log(probability_threshold / (1 - probability_threshold))
    element = structuring_element(config.kernel_shape, config.kernel_size, device=image.device)
    opened = open_binary(binary, element)
    labels, num_regions, regions = connected_components_with_stats(opened, config.connectivity)
    kept_labels, kept_mask = keep_largest_regions(labels, regions, config.num_keep)
    uniform = (gray_levels_and_histogram(image)[1] > 0).sum(1) == 1
    threshold = torch.full((b,), probability_threshold, dtype=image.dtype, device=image.device)
    return Segmentation(threshold=threshold, threshold_level=(threshold * 255).round().long(), binary=binary,
                        opened=opened, labels=labels, num_regions=num_regions, regions=regions,
                        kept_labels=kept_labels, kept_mask=kept_mask, masked=image * kept_mask.to(image.dtype),
                        status=_status(uniform, opened))


def segment_stereo_learned(batch: StereoBatch, config: SegmentationConfig = SegmentationConfig(segmenter="learned"),
                           net: ObstacleNet | None = None, left_logits: torch.Tensor | None = None
                           ) -> StereoSegmentation:
    """Segment both views of every pair with the network: the drop-in for
    :func:`~svs_torch.segmentation.segment_stereo` (same structure, same ``config`` fields).

    The network is ``net``, or loaded from ``config.segmenter`` (:func:`load_obstacle_net`). The right view is
    segmented as the left view of the mirrored pair (both images flipped and swapped: right columns stay at
    ``x − d``), one batch of 2B; ``left_logits`` ``(B, 1, H, W)`` (the left views' logits, already computed by
    the caller, e.g. with gradients) leaves only the right views to the network. Not differentiable; see
    :func:`soft_object_depths`.
    """
    if net is None:
        net = cached_obstacle_net(config.segmenter)
    if not isinstance(net, ObstacleNet):
        from .nearness import segment_stereo_nearness
        return segment_stereo_nearness(batch, config, net, left_logits)
    b = batch.batch_size
    with torch.no_grad():
        if left_logits is None:
            logits = predict_obstacle_logits(net, torch.cat([batch.left, batch.right.flip(-1)]),
                                             torch.cat([batch.right, batch.left.flip(-1)]))
        else:
            check_shape(left_logits, "left_logits", list(batch.left.shape))
            logits = torch.cat([left_logits.detach().to(batch.left.dtype),
                                predict_obstacle_logits(net, batch.right.flip(-1), batch.left.flip(-1))])
    threshold = net.config.probability_threshold
    left = segment_learned(batch.left, logits[:b], config, threshold)
    right = segment_learned(batch.right, logits[b:].flip(-1), config, threshold)
    status = torch.where(left.status != SegmentationStatus.OK, left.status, right.status)
    return StereoSegmentation(left=left, right=right, status=status)


def weights_path(segmenter: str) -> Path:
    """The weights file of a ``SegmentationConfig.segmenter`` value: ``"learned"`` / ``"nearness"`` the shipped
    one, ``"learned:PATH"`` / ``"nearness:PATH"`` PATH."""
    kind, _, path = segmenter.partition(":")
    if kind in _KINDS and path:
        return Path(path).expanduser()
    if kind in _KINDS and ":" not in segmenter:
        return SHIPPED_WEIGHTS if kind == "learned" else NEARNESS_WEIGHTS
    raise InputError(f"segmenter: expected learned, learned:PATH, nearness or nearness:PATH, got {segmenter!r}")


def _network_classes(kind: str) -> tuple[type[nn.Module], type]:
    from .nearness import NearnessNet, NearnessNetConfig
    return (ObstacleNet, ObstacleNetConfig) if kind == "learned" else (NearnessNet, NearnessNetConfig)


def load_obstacle_net(segmenter: str = "learned") -> nn.Module:
    """The network of ``"learned"`` / ``"nearness"`` (shipped) or ``"learned:PATH"`` / ``"nearness:PATH"``: an
    :class:`ObstacleNet` or a :class:`~svs_torch.segmentation.nearness.NearnessNet`, in float32 and eval mode.

    Raises:
        InputError: one line, naming the file, when it is missing, not a weights file, or does not fit.
    """
    path = weights_path(segmenter)
    if not path.is_file():
        raise InputError(f"segmenter: no weights file at {str(path)!r}")
    try:
        stored = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch.load raises many types (zip, pickle, EOF, OS); all mean "not a weights file"
        reason = " ".join(str(error).split())[:200] or type(error).__name__
        raise InputError(f"segmenter: {str(path)!r} is not a weights file ({reason})") from None
    kind = segmenter.partition(":")[0]
    expected = _KINDS[kind]
    if not isinstance(stored, dict) or stored.get("format") != expected:
        found = f", found {stored.get('format')!r}" if isinstance(stored, dict) and "format" in stored else ""
        raise InputError(f"segmenter: {str(path)!r} is not a svs_torch {kind} network file (format {expected}"
                         f"{found})")
    network_class, config_class = _network_classes(kind)
    try:
        settings = dict(stored["config"])
        net = network_class(config_class(**{**settings, "channels": tuple(settings["channels"])}))
        net.load_state_dict(stored["state_dict"])
    except (KeyError, TypeError, RuntimeError) as error:
        reason = " ".join(str(error).split())[:200]
        raise InputError(f"segmenter: {str(path)!r}: the weights do not fit the network ({reason})") from None
    return net.float().eval()


_NET_CACHE: dict[tuple[str, str, int, int], nn.Module] = {}


def cached_obstacle_net(segmenter: str) -> nn.Module:
    """:func:`load_obstacle_net` once per weights file and version (a batch loop or a sweep does not re-read it
    for every batch; a file rewritten in place, e.g. by a training run, is read again)."""
    path = weights_path(segmenter)
    try:
        stat = path.stat()
    except OSError:
        return load_obstacle_net(segmenter)  # its one-line error
    key = (segmenter.partition(":")[0], str(path.resolve()), stat.st_mtime_ns, stat.st_size)
    if key not in _NET_CACHE:
        _NET_CACHE.clear()  # one network at a time: a sweep over weights files does not pile them up
        _NET_CACHE[key] = load_obstacle_net(segmenter)
    return _NET_CACHE[key]


def save_obstacle_net(path: str | Path, net: nn.Module, metadata: dict | None = None) -> None:
    """Write ``net``'s weights, its configuration and ``metadata`` (training settings, split) atomically, in a
    file :func:`load_obstacle_net` reads. ``metadata`` is stored as its JSON form (strings for anything else),
    so the file holds only tensors and plain values and loads with ``weights_only``."""
    path = Path(path)
    kind = "learned" if isinstance(net, ObstacleNet) else "nearness"
    stored = {"format": _KINDS[kind], "config": dataclasses.asdict(net.config),
              "state_dict": {k: v.detach().cpu().float() for k, v in net.state_dict().items()},
              "metadata": json.loads(json.dumps(metadata or {}, default=str))}
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    os.close(handle)
    try:
        torch.save(stored, temporary)
        os.chmod(temporary, 0o644)
        os.replace(temporary, path)
    finally:
        if os.path.exists(temporary):
            os.unlink(temporary)


# ------------------------------------------------------------------------------------------------- soft path
@dataclass(frozen=True)
class SoftObjectDepths:
    """Soft per-object depths of B pairs, N kept regions.

    Attributes:
        weights: ``(B, N, H, W)`` soft region weights, ``sigmoid(logit / T)`` inside kept region n, 0 outside.
        disparity_px: ``(B, N)`` weighted mean disparity of each region (0 where not ``valid``).
        depth_m: ``(B, N)`` ``f·B / (disparity + doffs)`` (0 where not ``valid``).
        valid: ``(B, N)`` bool, a kept region with positive weight and ``disparity + doffs > 0``.
        nearest_m: ``(B,)`` the smallest valid depth (0 where none); nearest_valid ``(B,)`` bool.
    """

    weights: torch.Tensor
    disparity_px: torch.Tensor
    depth_m: torch.Tensor
    valid: torch.Tensor
    nearest_m: torch.Tensor
    nearest_valid: torch.Tensor


def soft_object_depths(logits: torch.Tensor, segmentation: Segmentation, disparity_px: torch.Tensor,
                       focal_px: torch.Tensor, baseline_m: torch.Tensor, doffs_px: torch.Tensor,
                       mask_temperature: float = 1.0) -> SoftObjectDepths:
    """Soft region weights → weighted mean disparity per kept region → depth → nearest obstacle.

    Args:
        logits: ``(B, 1, H, W)`` obstacle logits; ``segmentation``: the hard :class:`Segmentation` of the same
            view, whose kept regions gate the weights (which regions are kept carries no gradient, as in
            :mod:`svs_torch.segmentation.soft`).
        disparity_px: ``(B, 1, H, W)`` e.g. :func:`~svs_torch.depth.dense.soft_block_match`'s.
        focal_px, baseline_m, doffs_px: ``(B,)`` calibration at this image size.
        mask_temperature: ``T`` of ``sigmoid(logit / T)``; ``→ 0`` gives the hard regions (a weighted mean over
            them), so the result tends to the hard regions' mean disparity.

    Returns:
        :class:`SoftObjectDepths`, differentiable w.r.t. ``logits`` and ``disparity_px`` (``nearest_m`` through
        the nearest object only).
    """
    dims = check_shape(logits, "logits", ["B", 1, "H", "W"])
    check_shape(disparity_px, "disparity_px", list(logits.shape))
    check_shape(segmentation.labels, "segmentation.labels", list(logits.shape))
    if not mask_temperature > 0:
        raise InputError(f"mask_temperature: expected a positive number, got {mask_temperature!r}")
    b, n = dims["B"], segmentation.kept_labels.shape[1]
    kept = segmentation.kept_labels.view(b, n, 1, 1)
    region = (segmentation.labels == kept) & (kept > 0)  # (B, N, H, W)
    weights = torch.sigmoid(logits / mask_temperature) * region
    total = weights.flatten(2).sum(-1)  # (B, N)
    has = region.flatten(2).any(-1) & (total > 0)
    mean = (weights * disparity_px).flatten(2).sum(-1) / torch.where(has, total, 1.0)
    denominator = mean + doffs_px.view(b, 1)
    valid = has & (denominator > 0)
    depth = torch.where(valid, (focal_px * baseline_m).view(b, 1) / torch.where(valid, denominator, 1.0), 0.0)
    nearest = torch.where(valid, depth, torch.inf).amin(1) if n else depth.new_full((b,), torch.inf)
    nearest_valid = torch.isfinite(nearest)
    return SoftObjectDepths(weights, torch.where(valid, mean, 0.0), depth, valid,
                            torch.where(nearest_valid, nearest, 0.0), nearest_valid)


def soft_nearest_depth(batch: StereoBatch, logits: torch.Tensor, segmentation: Segmentation, num_disparities: int,
                       mask_temperature: float = 1.0, disparity_temperature: float = 0.003,
                       dense: DenseConfig = DenseConfig()) -> SoftObjectDepths:
    """The whole soft path on the left views of ``batch``: :func:`~svs_torch.depth.dense.soft_block_match` over
    ``[0, num_disparities)`` then :func:`soft_object_depths`. Differentiable w.r.t. ``logits`` and both images;
    as both temperatures ``→ 0`` it tends to the mean winner-takes-all disparity over each hard kept region."""
    disparity = soft_block_match(batch.left, batch.right, 0, num_disparities, disparity_temperature, dense)
    return soft_object_depths(logits, segmentation, disparity, batch.focal_px, batch.baseline_m, batch.doffs_px,
                              mask_temperature)
