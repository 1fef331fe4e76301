"""The learned segmenters' network: a three-level U-Net (:class:`ThreeLevelUNet`, the nearness segmenter's
base too), the older obstacle network on it (:class:`ObstacleNet`), the stereo features it reads
(:func:`stereo_features`: the images, their difference and a soft disparity) and its logits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import nn

from ..core.checks import InputError, all_finite, check_image, check_instance, check_stereo_views
from ..depth.soft_dense import soft_block_match
from .ground_plane import GroundPlaneConfig
from .threshold import gray_histogram, gray_levels, otsu_threshold_level

if TYPE_CHECKING:  # (nearness imports this module)
    from .nearness import NearnessNet

__all__ = ["NUM_FEATURES", "ObstacleNet", "ObstacleNetConfig", "ThreeLevelUNet", "check_finite_logits",
           "predict_obstacle_logits", "stereo_features"]


def _disparity_levels(disparity: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Valid disparities mapped linearly from each image's [min, max] to gray levels 0..255 (0 where invalid)."""
    b = disparity.shape[0]
    some = valid.flatten(1).any(1).view(b, 1, 1, 1)
    low = torch.where(some, torch.where(valid, disparity, torch.inf).flatten(1).amin(1).view(b, 1, 1, 1), 0.0)
    high = torch.where(some, torch.where(valid, disparity, -torch.inf).flatten(1).amax(1).view(b, 1, 1, 1), 0.0)
    spread = high - low
    scale = torch.where(spread > 0, 1 / torch.where(spread > 0, spread, 1.0), 0.0)  # one level: all at 0
    return gray_levels(torch.where(valid, (disparity - low) * scale, 0.0))


NUM_FEATURES = 6  # channels of stereo_features


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
        if not 0 < self.disparity_temperature < math.inf:
            raise InputError(f"disparity_temperature: expected a positive finite value, got "
                             f"{self.disparity_temperature!r}")
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


#: The tallest working size, in working widths: a portrait image is brought to ``working_width_px`` wide but at
#: most this many widths high (its aspect squeezed beyond). Why: a 10 x 8000 pair, scaled up to 160 px wide,
#: became 160 x 128000 and took 24 GB and two minutes before torch.quantile refused it (an audit of hostile
#: images); every shared and SVS frame is landscape, untouched by the bound.
MAX_WORKING_HEIGHT_WIDTHS = 4


def _working_size(image: torch.Tensor, width: int) -> tuple[int, int]:
    h, w = image.shape[-2:]
    return min(max(1, round(h * width / w)), MAX_WORKING_HEIGHT_WIDTHS * width), width


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
    both images with the median, the split and the 10–90 % spread taken as constants: the image gradient leaves
    out how they move, so it is not the full derivative (gradcheck fails on it; an audit measured −1.05 against
    −2.9 by finite differences on one pair).
    """
    # Views of two sizes were each resized to the working size in silence; another config failed on a field.
    check_stereo_views(left, right)
    check_instance(config, "config", ObstacleNetConfig)
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


def check_finite_logits(logits: torch.Tensor, name: str) -> None:
    """Obstacle logits ``(B, ...)`` with a NaN or an infinity are refused, naming the pairs: thresholded, a NaN is
    "not an obstacle", and a diverged network (or a caller's broken ``left_logits``) would tell a walker the way is
    clear. ``name``: the argument they came from."""
    if all_finite(logits):
        return
    bad = ~torch.isfinite(logits.detach()).flatten(1).all(1)
    if bool(bad.any()):
        raise InputError(f"{name}: expected finite obstacle logits, got NaN or inf for pair(s) "
                         f"{bad.nonzero().flatten().tolist()} (a diverged or corrupted network?)")


def predict_obstacle_logits(net: ObstacleNet | NearnessNet, left: torch.Tensor, right: torch.Tensor,
                            ground: GroundPlaneConfig | None = None,
                            baseline_m: torch.Tensor | None = None, focal_px: torch.Tensor | None = None,
                            camera_frames: bool = False) -> torch.Tensor:
    """Obstacle logits ``(B, 1, H, W)`` of the left view of images ``(B, 1, H, W)``, bilinearly resized from the
    working size. Differentiable w.r.t. the network's parameters (exactly) and both images (with
    :func:`stereo_features`' statistics held constant). ``ground``
    (:class:`~svs_torch.segmentation.ground_plane.GroundPlaneConfig` or None), ``baseline_m``, ``focal_px``
    ``(B,)``: the nearness segmenter's floor, and ``camera_frames`` its noise gate
    (:func:`~svs_torch.segmentation.nearness.nearness_logits`); other networks ignore them."""
    check_image(left, "left")
    check_image(right, "right")
    if left.shape != right.shape:
        raise InputError(f"right: expected the shape of left {tuple(left.shape)}, got {tuple(right.shape)}")
    if not isinstance(net, ObstacleNet):  # the nearness segmenter's correction network
        from .nearness import nearness_logits
        return nearness_logits(net, left, right, ground, baseline_m, focal_px, camera_frames)[0]
    features, _ = stereo_features(left, right, net.config)
    logits = net(features.to(next(net.parameters()).dtype))
    return F.interpolate(logits, size=left.shape[-2:], mode="bilinear", align_corners=False).to(left.dtype)
