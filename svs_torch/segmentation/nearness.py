"""Nearness segmentation: the obstacles are what is near, read from the pair's disparity (issue 32).

The paper's Otsu on intensity keeps the brightest large regions (often a wall, Sec. 3.2). The truth of an
obstacle (:func:`svs_torch.segmentation.learned.obstacle_truth`) is instead the near side of the Otsu split of
the scene's disparity. This segmenter applies that rule to a measured disparity and lets a small network correct
it:

1. **Disparity** (:func:`measure_nearness_disparity`): the dense stage's SAD block matcher over the whole left
   view (:func:`svs_torch.depth.dense.block_match_sad`: x-Sobel pre-filter, texture, uniqueness and left–right
   rejections; the fused C kernel, about 0.5 ms a pair at 160 px) at ``working_width_px`` (a camera frame whose
   noise the matching residual shows matched again with a wider window: :mod:`.nearness_denoise`), its rejected
   pixels filled along their rows from the nearest measured ones, the farther side at an occlusion
   (:func:`svs_torch.depth.block_matching.fill_invalid_rows`): a rejection left as a hole breaks a region apart;
   then a median over about 14 working pixels removes the specks and one-row streaks that JPEG frames with sensor
   noise leave (optionally, a pair whose matcher accepted little of the view has its matches checked against
   the pair measured at half that width: :mod:`.nearness_denoise`). Width, window and keep rule were chosen on
   the train scenes only (``experiments/select_nearness_rule.md``), the uniqueness ratio and the median on them
   clean and as camera frames (``select_nearness_denoise.md``).
2. **Rule logits**: ``gain · (d − split) / spread``, ``split`` the Otsu split of the filled disparity up to its
   99.5th percentile (the truth's rule, without a block matcher's outliers; taken again where too little is near:
   :mod:`.nearness_split`), ``spread`` its 10–90 % range (≥ 1 px). With ``SegmentationConfig.ground`` (off by
   default: ``experiments/walker_floor.md``), the floor, found as a plane in the map (:mod:`.ground_plane`), is
   left out of the split and its pixels are made far: for a walker the floor is not an obstacle.
3. **Correction** (:class:`NearnessNet`, 25.6k parameters): a three-level U-Net at ``network_width_px`` over the
   disparity, its validity, the rule's relative nearness, the left image and the column, whose output is added
   to the rule's logits. Its last layer starts at zero, so an untrained network is the rule itself. The shipped
   network is that: leave-scenes-out validation on the train scenes scored the rule above every trained
   correction (``experiments/validate_nearness.md``), and deployment then skips the network's pass.
4. **Regions**: probability above the threshold, the paper's opening and components, then the ``num_keep``
   regions by ``SegmentationConfig.keep``: ``"nearest"`` ranks the regions of at least ``min_area_fraction`` of
   the image by their median disparity (a small near obstacle is kept before a large far wall; one of at least
   ``near_min_area_fraction`` where it is nearer than all of those, a thin pole), ``"largest"`` by area (the
   paper's rule). The area held to that least is the region's pixels the block matcher measured where
   the right camera sees them: a band of filled rows, or one only the left camera sees, cannot be ranged.
5. **Right view**: each kept left region shifted left by its own median disparity (a region's pixels sit at
   ``x − d`` in the right view). One network pass per pair, not two.

Gradients: in a differentiable run (images that require grad) the disparity's forward value is the hard
measurement above and its gradient is that of the soft-argmin over the same SAD cost volume
(:func:`svs_torch.depth.dense.soft_block_match`, straight-through), so the logits are differentiable w.r.t. the
network's parameters and both images. The split, the spread, the fill's choices and the kept regions are
constants of the hard pass.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from ..core.checks import InputError, check_count, check_flag, check_instance, check_stereo_views
from ..core.pair_trees import take_pairs
from ..core.size_groups import merge_groups
from ..core.types import Segmentation, SegmentationStatus, StereoBatch, StereoSegmentation
from ..depth.dense_config import DenseConfig
from .components import connected_components_with_stats, region_properties
from .ground_plane import GroundPlane, GroundPlaneConfig, fit_ground_plane
from .morphology import open_binary, structuring_element
from .nearness_denoise import (check_denoise_settings, denoised_map, match_by_noise, reduced_to_width,
                               soft_match_by_noise)
from .nearness_regions import (_area_measured_in_view, _region_median_disparity, _without_clipped,
                               shift_regions_to_right)
from .nearness_split import nearness_split
from .network import ThreeLevelUNet, check_finite_logits
from .segment import SegmentationConfig, _status, keep_regions, segment_stereo, without_kept_regions
from .threshold import gray_levels_and_histogram

__all__ = ["NearnessDisparity", "NearnessNet", "NearnessNetConfig", "measure_nearness_disparity", "nearness_logits",
           "segment_stereo_nearness", "shift_regions_to_right"]


NUM_FEATURES = 5  # channels of _network_features
#: The rule's relative nearness of a floor pixel: as far as a pixel one spread behind the split (logit −8 at the
#: rule's gain), whatever the floor's own disparity.
GROUND_RELATIVE = 1.0


@dataclass(frozen=True)
class NearnessNetConfig:
    """Settings of the nearness segmenter (stored beside its weights; module docstring). A weights file written
    before a setting existed (the shipped one among them) takes its default.

    Attributes:
        working_width_px: the disparity is measured on both images reduced (area average) to this width, pixels,
            when wider: an integer factor left a 460-pixel scene at its own width, where the window and the median
            span less of it (native train scenes' IoU 0.676 against 0.726; experiments/select_nearness_denoise.md).
        window_size: SAD window side at that width, pixels, odd.
        max_disparity_fraction: disparities ``[0, fraction · working width)`` are searched.
        network_width_px: the network sees its features reduced to this width, pixels.
        channels: widths of the three U-Net levels.
        rule_gain: logits per spread of the rule ``(d − split) / spread``.
        uniqueness_ratio: the block matcher's uniqueness rule (:class:`~svs_torch.depth.dense_config.DenseConfig`).
        median_window: side of the median filter over the filled disparity, taken on the map halved (box
            average) so a side of 7 spans about 14 working pixels; 1: no filter.
        noisy_window_size, noisy_min_residual_levels: a pair whose matching residual at ``window_size`` (the median
            winning SAD per window pixel, 8-bit levels of the clipped x-Sobel) reaches ``noisy_min_residual_levels``
            is matched again with a ``noisy_window_size`` window (a camera frame's noise: :mod:`.nearness_denoise`);
            ``noisy_window_size == window_size``: never. Chosen on the tuning sets (select_nearness_setting.md,
            third selection; real_rig.md, "A wider window for noisy pairs").
        sparse_median_window, sparse_share: the median's side for a pair whose block matcher accepted less than
            ``sparse_share`` of the left view: a camera frame's noise (JPEG, sensor noise, a dim scene), whose map
            is then sparse specks that a 7×7 median keeps as regions. Clean pairs accept 41 % or more
            (experiments/nearness_fallback.md), so they keep ``median_window``.
        sparse_reduction, sparse_agreement_px: such a sparse pair is also measured at ``1 / sparse_reduction`` of
            the working width; its matches within ``sparse_agreement_px`` working pixels of that coarse map are
            kept and the coarse map stands in for the rest (:mod:`.nearness_denoise`); ``sparse_reduction=1`` (the
            default): never.
        disparity_temperature: the soft-argmin's temperature (pre-filtered intensity units) of the gradient path.
        probability_threshold: a pixel is an obstacle where its probability exceeds this.
        min_near_share: where the Otsu split leaves less than this share of the view near, it is taken again under
            the 90th percentile (:mod:`.nearness_split`); 0: never (experiments/select_min_near_share.md).
        max_retaken_near_share, min_retaken_gap: a split taken again is not taken where it leaves more than
            ``max_retaken_near_share`` of the view near, or where its two sides' median disparities differ by less
            than ``min_retaken_gap`` of the near side's: it lies inside one surface's disparities (a small near object
            before a flat wall), and the first split stands (experiments/small_near_obstacles.md); 1 and 0: taken.
        max_fill_px: on a noisy pair (``noisy_min_residual_levels``), the row fill of step 1 fills a run of
            rejected pixels longer than this many working pixels only between two measured pixels that agree or
            in the left band; other long runs stay far (:mod:`.nearness_denoise`, "Why long runs stay unfilled").
            None (the default): every run is filled.
    """

    working_width_px: int = 320
    window_size: int = 7  # with working_width_px: experiments/select_nearness_rule.md
    max_disparity_fraction: float = 0.3
    uniqueness_ratio: float = 0.2  # DenseConfig's 0.10 keeps more noise matches on camera frames
    median_window: int = 7  # with uniqueness_ratio: experiments/select_nearness_denoise.md
    noisy_window_size: int = 11  # with the next: experiments/real_rig.md, "A wider window for noisy pairs"
    noisy_min_residual_levels: float = 7.5
    # 7 -> 11 (5b3c383's message the record): real_rig.py --splits tuned [--contrast 0.5] --no-rival, 320x240, per
    # object over 8 JPEG digits, PianoL aside: 96.26 -> 96.72 %, half contrast 85.07 -> 91.29 %.
    sparse_median_window: int = 11
    sparse_share: float = 0.3
    # Off: chosen twice (experiments/select_nearness_setting.md: the tuned split, then rendered scenes too), not taken
    # either time: the held-out split fell at the board's default JPEG digit (its "Shipped" paragraphs).
    sparse_reduction: int = 1
    sparse_agreement_px: float = 3.0
    network_width_px: int = 80
    channels: tuple[int, int, int] = (8, 16, 16)
    rule_gain: float = 8.0
    disparity_temperature: float = 0.003
    probability_threshold: float = 0.5
    min_near_share: float = 0.1  # experiments/select_min_near_share.md
    max_retaken_near_share: float = 0.9  # experiments/small_near_obstacles.md
    min_retaken_gap: float = 0.1
    max_fill_px: int | None = None

    def __post_init__(self) -> None:
        for name in ("working_width_px", "network_width_px"):
            check_count(getattr(self, name), name, least=16)
        for name in ("window_size", "median_window", "sparse_median_window", "noisy_window_size"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1 or value % 2 == 0:
                raise InputError(f"{name}: expected an odd positive int, got {value!r}")
        check_denoise_settings(self)
        shares = (self.min_near_share, self.max_retaken_near_share, self.min_retaken_gap)
        if not (0 <= shares[0] < 1 and 0 < shares[1] <= 1 and 0 <= shares[2] < 1):
            raise InputError(f"min_near_share, max_retaken_near_share, min_retaken_gap: expected shares in [0, 1), "
                             f"(0, 1] and [0, 1), got {shares}")
        if not 0 <= self.uniqueness_ratio < 1:
            raise InputError(f"uniqueness_ratio: expected a value in [0, 1), got {self.uniqueness_ratio!r}")
        if not 0 < self.max_disparity_fraction < 1:
            raise InputError(f"max_disparity_fraction: expected a value in (0, 1), got {self.max_disparity_fraction!r}")
        if len(self.channels) != 3 or any(not isinstance(c, int) or c < 4 or c % 4 for c in self.channels):
            raise InputError(f"channels: expected three multiples of 4, got {self.channels!r}")
        if not (0 < self.rule_gain < math.inf and 0 < self.disparity_temperature < math.inf):  # inf: NaN logits
            raise InputError(f"rule_gain, disparity_temperature: expected positive finite values, got "
                             f"{self.rule_gain!r}, {self.disparity_temperature!r}")
        if not 0 < self.probability_threshold < 1:
            raise InputError(f"probability_threshold: expected a value in (0, 1), got {self.probability_threshold!r}")

    def working_factor(self, width_px: int) -> float:
        """The reduction of an image ``width_px`` wide: ``width_px / working_width_px``, or 1 (matched at its own
        size) when it is not wider."""
        return max(1.0, width_px / self.working_width_px)


class NearnessNet(ThreeLevelUNet):
    """:class:`~svs_torch.segmentation.network.ThreeLevelUNet` from the features ``(B, 5, h, w)`` to a correction
    of the rule's logits ``(B, 1, h, w)``. The head starts at zero: an untrained network leaves the rule's logits
    unchanged. Differentiable w.r.t. its parameters and its input.
    """

    def __init__(self, config: NearnessNetConfig = NearnessNetConfig()) -> None:
        super().__init__(NUM_FEATURES, config.channels)
        self.config = config
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def adds_nothing(self) -> bool:
        """Whether the correction is exactly zero for every input: the head's weights and bias are all zero (an
        untrained network, or the shipped one: leave-scenes-out validation chose the rule alone,
        experiments/validate_nearness.md). Its 1×1 head then multiplies finite features by zero."""
        return not bool(self.head.weight.any()) and not bool(self.head.bias.any())


@dataclass(frozen=True)
class NearnessDisparity:
    """The measured disparity of B left views, at the input size.

    Attributes:
        disparity_px: ``(B, 1, H, W)`` input pixels, filled (module docstring, step 1).
        measured: ``(B, 1, H, W)`` bool, the block matcher accepted the pixel (not filled).
        split_px: ``(B,)`` the Otsu split of the filled disparity; spread_px ``(B,)`` its 10–90 % range (≥ 1).
        relative: ``(B, 1, H, W)`` ``(disparity − split) / spread``, the rule's nearness.
        split_retaken: ``(B,)`` bool, the split was taken again under the 90th percentile
            (``NearnessNetConfig.min_near_share``, :mod:`.nearness_split`).
        matched_share: ``(B,)`` the share of the left view the block matcher accepted, before any coarse check:
            what tells views of two scenes from one (``SegmentationConfig.min_measured_share``,
            experiments/nearness_fallback.md). The coarse check (:mod:`.nearness_denoise`) adds the coarse map's
            acceptances to ``measured``, chance matches between unrelated views among them (at a quarter of the
            width: views of two tuning scenes 0.14–0.30 of the view, their camera frames 0.30 and more), so
            ``measured`` cannot tell them apart.
        ground: ``(B, 1, H, W)`` bool, the floor (:mod:`.ground_plane`), left out of the split and made far in
            ``relative``; None: not looked for.
        ground_plane: the floor's :class:`~.ground_plane.GroundPlane` in these pixels; None: not looked for.
    """

    disparity_px: torch.Tensor
    measured: torch.Tensor
    split_px: torch.Tensor
    spread_px: torch.Tensor
    relative: torch.Tensor
    split_retaken: torch.Tensor
    matched_share: torch.Tensor
    ground: torch.Tensor | None = None
    ground_plane: GroundPlane | None = None


def measure_nearness_disparity(left: torch.Tensor, right: torch.Tensor,
                               config: NearnessNetConfig = NearnessNetConfig(),
                               ground: GroundPlaneConfig | None = None, baseline_m: torch.Tensor | None = None,
                               focal_px: torch.Tensor | None = None, camera_frames: bool = False
                               ) -> NearnessDisparity:
    """Step 1–2 of the module docstring on images ``(B, 1, H, W)`` in [0, 1]; with ``ground``, the floor of rigs
    of ``baseline_m`` ``(B,)`` metres and ``focal_px`` ``(B,)`` (at the images' size; None: no pitch limit) found
    (:mod:`.ground_plane`), left out of the split and made far. ``camera_frames``: images no wider than the working
    width are matched with ``config.noisy_window_size`` at once (``SegmentationConfig.camera_frames``).

    Differentiable w.r.t. both images when they require grad (straight-through: the hard value, the soft-argmin's
    gradient; the floor's pixels, a constant of the hard pass, get none); otherwise it runs without building a graph.
    """
    b = check_stereo_views(left, right)["B"]
    check_instance(config, "config", NearnessNetConfig)  # another kind failed on its first field (an audit)
    if ground is not None:
        check_instance(ground, "ground", GroundPlaneConfig)
    check_flag(camera_frames, "camera_frames")  # a string ("no") was taken as True
    h, w = left.shape[-2:]
    small_left, small_right = (reduced_to_width(view, config.working_width_px) for view in (left, right))
    factor = w / small_left.shape[-1]  # working pixels to input pixels
    num_disparities = max(2, math.ceil(config.max_disparity_fraction * small_left.shape[-1]))
    if camera_frames and small_left.shape[-1] == w:  # not reduced, so its noise is not averaged away
        config = dataclasses.replace(config, noisy_min_residual_levels=0.0)
    dense = DenseConfig(window_size=config.window_size, uniqueness_ratio=config.uniqueness_ratio)
    with torch.no_grad():
        found, widened = match_by_noise(small_left.detach(), small_right.detach(), num_disparities, dense, config)
        filled, valid = denoised_map(small_left, small_right, found, num_disparities, dense, config, widened)
    if torch.is_grad_enabled() and (left.requires_grad or right.requires_grad):
        soft = soft_match_by_noise(small_left, small_right, num_disparities, dense, config, widened)
        filled = filled + (soft - soft.detach())  # straight-through: forward hard, gradient of the soft-argmin
    # matched: the fine matcher's own acceptances, resampled as measured is; without the coarse check (or where it
    # changed no pair) they are measured itself, resampled once.
    disparity, measured, matched = filled * factor, valid, found.valid
    if disparity.shape[-2:] != (h, w):  # (at the working size already, nearest resampling would copy it)
        disparity = F.interpolate(disparity, size=(h, w), mode="nearest")
        same = matched is measured
        measured = F.interpolate(measured.to(left.dtype), size=(h, w), mode="nearest") > 0.5
        matched = measured if same else F.interpolate(matched.to(left.dtype), size=(h, w), mode="nearest") > 0.5
    plane = None if ground is None else fit_ground_plane(disparity, measured, baseline_m, ground, factor,
                                                         noisy=widened, focal_px=focal_px)
    floor = None if plane is None else plane.mask
    split, spread, retaken = nearness_split(disparity, config.min_near_share, floor, config.max_retaken_near_share,
                                            config.min_retaken_gap)
    relative = (disparity - split.view(b, 1, 1, 1)) / spread.view(b, 1, 1, 1)
    if floor is not None:
        relative = relative.masked_fill(floor, -GROUND_RELATIVE)
    return NearnessDisparity(disparity, measured, split, spread, relative, retaken,
                             matched.flatten(1).to(torch.float32).mean(1), floor, plane)


def _network_features(left: torch.Tensor, measured: NearnessDisparity, width: int) -> torch.Tensor:
    """The network's input ``(B, 5, h, w)`` at ``width`` px: relative nearness, disparity / image width × 4,
    measured share, the standardised left image, the column ``x / w``."""
    h, w = left.shape[-2:]
    size = (max(1, round(h * width / w)), width)
    mean = left.mean((1, 2, 3), keepdim=True)
    std = left.std((1, 2, 3), keepdim=True).clamp_min(1e-3)
    full = torch.cat([measured.relative, measured.disparity_px * (4.0 / w), measured.measured.to(left.dtype),
                      (left - mean) / std], 1)
    small = F.interpolate(full, size=size, mode="area")
    column = torch.linspace(0, 1, size[1], dtype=left.dtype, device=left.device).expand(left.shape[0], 1, *size)
    return torch.cat([small, column], 1)


def nearness_logits(net: NearnessNet, left: torch.Tensor, right: torch.Tensor, ground: GroundPlaneConfig | None = None,
                    baseline_m: torch.Tensor | None = None, focal_px: torch.Tensor | None = None,
                    camera_frames: bool = False) -> tuple[torch.Tensor, NearnessDisparity]:
    """Obstacle logits ``(B, 1, H, W)`` of the left views: the rule's plus the network's correction (resized
    bilinearly from its width), and the measured disparity (``ground``, ``baseline_m``, ``focal_px``,
    ``camera_frames``: as :func:`measure_nearness_disparity`'s). Differentiable w.r.t. the network's parameters and
    both images (module docstring)."""
    check_instance(net, "net", NearnessNet)  # an ObstacleNet or None failed on its config (an audit)
    measured = measure_nearness_disparity(left, right, net.config, ground, baseline_m, focal_px, camera_frames)
    rule = net.config.rule_gain * measured.relative
    training = torch.is_grad_enabled() and any(p.requires_grad for p in net.parameters())
    if not training and net.adds_nothing():
        return rule, measured  # the same logits without the network's pass (a quarter of the segmenter's time)
    features = _network_features(left, measured, net.config.network_width_px)
    dtype = next(net.parameters()).dtype
    correction = net(features.to(dtype))
    correction = F.interpolate(correction, size=left.shape[-2:], mode="bilinear", align_corners=False)
    return rule + correction.to(left.dtype), measured


def segment_stereo_nearness(batch: StereoBatch, config: SegmentationConfig, net: NearnessNet,
                            left_logits: torch.Tensor | None = None,
                            measured: NearnessDisparity | None = None) -> StereoSegmentation:
    """Both views of every pair (module docstring, steps 3–5), the drop-in for
    :func:`~svs_torch.segmentation.segment_stereo`. ``left_logits`` and ``measured``: from :func:`nearness_logits`,
    already computed by the caller (e.g. with gradients; ``net``'s threshold and matcher are still read). Not
    differentiable. ``threshold`` holds the probability threshold, the right view's ``binary`` and ``opened`` its
    shifted kept regions. Status as Otsu's (``UNIFORM_IMAGE``: a one-level view). A pair whose matcher accepted under
    ``config.min_measured_share`` of its left view (a chance disparity) gets Otsu and the two largest regions."""
    check_instance(batch, "batch", StereoBatch)
    check_instance(config, "config", SegmentationConfig)
    check_instance(net, "net", NearnessNet)  # read with left_logits too: None failed on net.config from inside
    b, rig = batch.batch_size, (config.ground, batch.baseline_m, batch.focal_px, config.camera_frames)
    source = "network" if left_logits is None else "left_logits"
    with torch.no_grad():
        if left_logits is None:
            left_logits, measured = nearness_logits(net, batch.left, batch.right, *rig)
        elif measured is None:
            measured = measure_nearness_disparity(batch.left, batch.right, net.config, *rig)
    check_finite_logits(left_logits, source)
    fallback = measured.matched_share < config.min_measured_share
    if not bool(fallback.any()):
        return _segment_measured(batch, config, net, left_logits, measured)
    # Too little of the view measured (SegmentationConfig.min_measured_share): Otsu and the two largest regions.
    otsu = dataclasses.replace(config, segmenter="otsu", keep="largest", min_measured_share=0.0)
    low, rest = fallback.nonzero().flatten(), (~fallback).nonzero().flatten()
    # Segmented by Otsu, their nearness split and floor play no part.
    none = torch.zeros(len(low), dtype=torch.bool, device=batch.left.device)
    floor = {} if config.ground is None else {"floor_plane_px": left_logits.new_zeros(len(low), 3), "floor_found": none}
    otsu_part = dataclasses.replace(segment_stereo(batch.select(low), otsu), split_retaken=none,
                                    from_disparity=none, **floor)
    parts, indices = [otsu_part], [low]
    if len(rest):
        parts.append(_segment_measured(batch.select(rest), config, net, left_logits[rest],
                                       take_pairs(measured, rest, b)))
        indices.append(rest)
    return merge_groups(parts, indices, batch.size_hw, [batch.size_hw] * len(parts))


def _segment_measured(batch: StereoBatch, config: SegmentationConfig, net: NearnessNet, left_logits: torch.Tensor,
                      measured: NearnessDisparity) -> StereoSegmentation:
    """:func:`segment_stereo_nearness` from the left views' logits and measured disparity."""
    b, image = batch.batch_size, batch.left
    threshold_value = net.config.probability_threshold
    binary = left_logits.detach() > math.log(threshold_value / (1 - threshold_value))
    element = structuring_element(config.kernel_shape, config.kernel_size, device=image.device)
    opened = open_binary(binary, element)
    labels, num_regions, regions = connected_components_with_stats(opened, config.connectivity, image.dtype)
    disparity = measured.disparity_px.detach()
    region_disparity = _region_median_disparity(disparity, labels, num_regions)
    h, w = image.shape[-2:]
    min_area_px = config.min_area_fraction * h * w
    candidate_area_px = _area_measured_in_view(labels, regions, region_disparity, measured.measured, min_area_px)
    candidate_area_px = _without_clipped(candidate_area_px, labels, regions, image, config.max_clipped_share)
    kept_labels, kept_mask = keep_regions(labels, regions, config.num_keep, config.keep, min_area_px=min_area_px,
                                          near_min_area_px=config.near_min_area_fraction * h * w,
                                          nearness=region_disparity, candidate_area_px=candidate_area_px)
    # A view of one gray level holds no disparity: the pair has no information (the Otsu stage's UNIFORM_IMAGE).
    uniform = (gray_levels_and_histogram(torch.cat([image, batch.right]))[1] > 0).sum(1).view(2, b).eq(1).any(0)
    kept_labels, kept_mask = without_kept_regions(uniform, kept_labels, kept_mask)
    threshold = torch.full((b,), threshold_value, dtype=image.dtype, device=image.device)
    level = (threshold * 255).round().long()
    status = _status(uniform, opened)
    left = Segmentation(threshold=threshold, threshold_level=level, binary=binary, opened=opened, labels=labels,
                        num_regions=num_regions, regions=regions, kept_labels=kept_labels, kept_mask=kept_mask,
                        masked=image * kept_mask.to(image.dtype), status=status)
    slot = (kept_labels - 1).clamp(min=0)
    shift = torch.where(kept_labels > 0, torch.gather(region_disparity, 1, slot) if region_disparity.shape[1]
                        else torch.zeros_like(kept_labels, dtype=disparity.dtype), 0.0)
    right_labels = shift_regions_to_right(labels, kept_labels, shift)
    right_mask = right_labels > 0
    right = Segmentation(threshold=threshold, threshold_level=level, binary=right_mask, opened=right_mask,
                         labels=right_labels, num_regions=num_regions,
                         regions=region_properties(right_labels, num_regions, image.dtype), kept_labels=kept_labels,
                         kept_mask=right_mask, masked=batch.right * right_mask.to(image.dtype),
                         status=torch.where(right_mask.flatten(1).any(1) | (status != SegmentationStatus.OK),
                                            status, torch.full_like(status, SegmentationStatus.NO_FOREGROUND)))
    pair_status = torch.where(left.status != SegmentationStatus.OK, left.status, right.status)
    plane = measured.ground_plane  # the floor's plane, in these pixels (svs_torch.depth.floor_distance reads it)
    return StereoSegmentation(left=left, right=right, status=pair_status, split_retaken=measured.split_retaken,
                              from_disparity=torch.ones(b, dtype=torch.bool, device=image.device),
                              floor_plane_px=None if plane is None else plane.refitted.to(image.dtype),
                              floor_found=None if plane is None else plane.found)
