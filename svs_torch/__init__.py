"""svs_torch: batched, differentiable stereo obstacle ranging for the Surveyor SVS camera.

A PyTorch reimplementation of an SVS obstacle-warning pipeline for visually impaired users: segment the
obstacles (Otsu, opening, the largest regions), find SURF features, match by SAD, estimate the fundamental
matrix by RANSAC, and range the obstacles from disparity. Every stage runs on a whole batch of pairs.
"""

from .camera import SVS_CAMERA, SVS_RESOLUTIONS, SVSCamera
from .checks import InputError
from .detector import SurfConfig
from .features import SurfFeatures, extract_surf_features
from .matching import match_sad
from .pipeline import PipelineConfig, PipelineResult, PipelineStatus, estimate_obstacle_depth
from .ransac import estimate_fundamental_ransac
from .segmentation import SegmentationConfig, segment_images, segment_stereo
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
    "PipelineConfig",
    "PipelineResult",
    "PipelineStatus",
    "SegmentationConfig",
    "SurfConfig",
    "SurfFeatures",
    "estimate_fundamental_ransac",
    "estimate_obstacle_depth",
    "extract_surf_features",
    "match_sad",
    "segment_images",
    "segment_stereo",
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
