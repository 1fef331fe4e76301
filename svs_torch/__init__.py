"""svs_torch: batched, differentiable stereo obstacle ranging for the Surveyor SVS camera.

A PyTorch reimplementation of an SVS obstacle-warning pipeline for visually impaired users: segment the
obstacles (by default what is near in the pair's own disparity; the paper's Otsu, opening and largest regions in
``PipelineConfig.paper()``), find SURF features, match by SAD, estimate the fundamental matrix by RANSAC, and
range the obstacles from disparity. Every stage runs on a whole batch of pairs.

The folders follow the data: ``segmentation/`` → ``features/`` → ``geometry/`` (matching, RANSAC,
rectification) → ``depth/``, each stage with its C kernels in its own ``kernels/``; ``pipeline/`` composes them;
``evaluation/``, ``plotting/``, ``data/``, ``capture/`` and ``cli/`` sit around it, and ``core/`` holds the small
parts they all share. Imports go one way: every package may use ``core``, a stage only other stages' public
names, the pipeline the stages, and only ``evaluation``, ``plotting`` and ``cli`` the pipeline (the README's
"Layout"; ``tests/test_layout.py`` checks it). Modules that moved keep their old paths for one release
(``moved.py``).
"""

from . import moved
from .core.lazy_names import lazy_names

moved.install()

# The public names load on first use (PEP 562): ``import svs_torch.cli`` (and ``svs-depth --help``) must not pay
# for torch, kornia and OpenCV. ``from svs_torch import PipelineConfig`` works as before.
_EXPORTS = {
    "SVS_CAMERA": "core.camera", "SVS_RESOLUTIONS": "core.camera", "SVSCamera": "core.camera",
    "InputError": "core.errors",
    "SurfConfig": "features.detector",
    "SurfFeatures": "features.surf", "extract_surf_features": "features.surf",
    "match_sad": "geometry.matching",
    "PipelineConfig": "pipeline", "PipelineResult": "pipeline", "PipelineStatus": "pipeline",
    "estimate_obstacle_depth": "pipeline",
    "estimate_fundamental_ransac": "geometry.ransac",
    "SegmentationConfig": "segmentation", "segment_images": "segmentation", "segment_stereo": "segmentation",
    **{name: "core.types" for name in ("FundamentalResult", "FundamentalStatus", "Keypoints", "Matches",
                                       "RegionProperties", "Segmentation", "SegmentationStatus", "StereoBatch",
                                       "StereoSegmentation")},
}


__getattr__, __dir__ = lazy_names(__name__, _EXPORTS)


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
