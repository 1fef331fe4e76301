"""SURF features of a batch in one call: detection (:mod:`svs_torch.features.detector`) then description
(:mod:`svs_torch.features.descriptor`), paper Sec. 3.3 (1)."""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch

from ..core.checks import check_dtype, check_image, check_shape, checked_images
from ..core.types import Keypoints
from .descriptor import describe_surf, surf_orientation, with_orientation
from .detector import SurfConfig, detect_surf_keypoints

__all__ = ["SurfFeatures", "extract_surf_features"]


@dataclass(frozen=True)
class SurfFeatures:
    """Keypoints and their descriptors.

    Attributes:
        keypoints: :class:`~svs_torch.core.types.Keypoints`, K rows per image, padded.
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
        config: :class:`~svs_torch.features.detector.SurfConfig` (upright by default; ``extended`` for 128-D).
        mask: optional ``(B, 1, H, W)`` bool; keypoints only where it holds.

    Returns:
        :class:`SurfFeatures`. Descriptors are differentiable with respect to ``image`` for the detected
        keypoints; the detection itself is not. A batch of more than ``BLOCK_IMAGES`` images runs in blocks of
        that many (cache), padded to one K.
    """
    check_shape(image, "image", ["B", 1, "H", "W"])  # before the blocks read its shape (an array has no dim())
    # A strided view (a crop, a channel of a colour batch) is summed in another order by the integral image and
    # gave slightly different keypoints than the same pixels copied: one layout, one answer.
    image = image.contiguous()
    if mask is not None:
        # Checked against the whole batch before the blocks slice it: a block's check named the block's shape,
        # "expected (8, 1, H, W)" for a mask of the wrong size beside 9 images.
        check_shape(mask, "mask", [image.shape[0], 1, image.shape[2], image.shape[3]])
        check_dtype(mask, "mask", "bool")
        mask = mask.contiguous()
    if image.shape[0] > BLOCK_IMAGES:
        # Blocks of images, each batched, then padded to one K: the integral images and box-filter responses of
        # a block stay in cache, of a whole batch they do not (320x240, ms per image: 6.5 in blocks of 8 against
        # 19 for 64 images at once and 28 for 128; in the pipeline on the 45 shared pairs, features 44 -> 10 ms a
        # pair). Keypoints are those of one block; orientations and descriptors agree to the round-off of the
        # integral image, whose border already depends on the batch (below 2e-3; depths unchanged).
        # The images ranged once here, not again by each block's detection and description (0.2 ms a pair of
        # estimate --pairs at 320x240: two scans of every image).
        check_image(image, "image")
        starts = range(0, image.shape[0], BLOCK_IMAGES)
        parts = [image[i:i + BLOCK_IMAGES] for i in starts]
        with checked_images(*parts):
            blocks = [_extract(part, config, None if mask is None else mask[i:i + BLOCK_IMAGES])
                      for i, part in zip(starts, parts)]
        return _concatenate(blocks)
    return _extract(image, config, mask)


#: Images per block in :func:`extract_surf_features` (fastest measured on this CPU: 8 against 16 and whole).
BLOCK_IMAGES = 8


def _extract(image: torch.Tensor, config: SurfConfig, mask: torch.Tensor | None) -> SurfFeatures:
    keypoints = detect_surf_keypoints(image, config, mask)
    if not config.upright:
        keypoints = with_orientation(keypoints, surf_orientation(image, keypoints))
    return SurfFeatures(keypoints, describe_surf(image, keypoints, config.extended, config.compiled))


def _concatenate(blocks: list[SurfFeatures]) -> SurfFeatures:
    """Blocks of features joined along B, each padded with zero / False rows to the largest K."""
    k = max(block.descriptors.shape[1] for block in blocks)

    def pad(tensor: torch.Tensor) -> torch.Tensor:
        extra = k - tensor.shape[1]
        if extra == 0:
            return tensor
        return torch.cat([tensor, tensor.new_zeros((tensor.shape[0], extra, *tensor.shape[2:]))], dim=1)

    columns = [[pad(getattr(block.keypoints, name)) for block in blocks] for name in KEYPOINT_FIELDS]
    keypoints = Keypoints(*(torch.cat(parts) for parts in columns))
    return SurfFeatures(keypoints, torch.cat([pad(block.descriptors) for block in blocks]))


KEYPOINT_FIELDS = tuple(field.name for field in fields(Keypoints))
