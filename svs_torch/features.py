"""SURF features of a batch in one call: detection (:mod:`svs_torch.detector`) then description
(:mod:`svs_torch.descriptor`), paper Sec. 3.3 (1)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .descriptor import describe_surf, surf_orientation, with_orientation
from .detector import SurfConfig, detect_surf_keypoints
from .types import Keypoints

__all__ = ["SurfFeatures", "extract_surf_features"]


@dataclass(frozen=True)
class SurfFeatures:
    """Keypoints and their descriptors.

    Attributes:
        keypoints: :class:`~svs_torch.types.Keypoints`, K rows per image, padded.
        descriptors: ``(B, K, D)`` unit-length SURF descriptors (D = 64 or 128), zero rows for padding.
    """

    keypoints: Keypoints
    descriptors: torch.Tensor


def extract_surf_features(
    image: torch.Tensor, config: SurfConfig = SurfConfig(), mask: torch.Tensor | None = None
) -> SurfFeatures:
    """Detect and describe SURF features on a batch of images.

    Args:
        image: ``(B, 1, H, W)`` float in [0, 1].
        config: :class:`~svs_torch.detector.SurfConfig` (upright by default; ``extended`` for 128-D).
        mask: optional ``(B, 1, H, W)`` bool; keypoints only where it holds.

    Returns:
        :class:`SurfFeatures`. Descriptors are differentiable with respect to ``image`` for the detected
        keypoints; the detection itself is not.
    """
    keypoints = detect_surf_keypoints(image, config, mask)
    if not config.upright:
        keypoints = with_orientation(keypoints, surf_orientation(image, keypoints))
    return SurfFeatures(keypoints, describe_surf(image, keypoints, config.extended, config.compiled))
