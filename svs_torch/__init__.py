"""svs_torch: batched, differentiable stereo obstacle ranging for the Surveyor SVS camera.

A PyTorch reimplementation of an SVS obstacle-warning pipeline for visually impaired users: segment the
obstacles (Otsu, opening, the largest regions), find SURF features, match by SAD, estimate the fundamental
matrix by RANSAC, and range the obstacles from disparity. Every stage runs on a whole batch of pairs.
"""

from .camera import SVS_CAMERA, SVS_RESOLUTIONS, SVSCamera
from .checks import InputError
from .types import (
    FundamentalResult,
    FundamentalStatus,
    Keypoints,
    Matches,
    RegionProperties,
    Segmentation,
    SegmentationStatus,
    StereoBatch,
    StereoSegmentation,
)

__version__ = "0.1.0"

__all__ = [
    "FundamentalResult",
    "FundamentalStatus",
    "InputError",
    "Keypoints",
    "Matches",
    "RegionProperties",
    "SVSCamera",
    "SVS_CAMERA",
    "SVS_RESOLUTIONS",
    "Segmentation",
    "SegmentationStatus",
    "StereoBatch",
    "StereoSegmentation",
]
