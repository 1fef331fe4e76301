"""svs_torch: batched, differentiable stereo obstacle ranging for the Surveyor SVS camera.

A PyTorch reimplementation of an SVS obstacle-warning pipeline for visually impaired users: segment the
obstacles (Otsu, opening, the largest regions), find SURF features, match by SAD, estimate the fundamental
matrix by RANSAC, and range the obstacles from disparity. Every stage runs on a whole batch of pairs.
"""

# The public names load on first use (PEP 562): ``import svs_torch.cli`` (and ``svs-depth --help``) must not pay
# for torch, kornia and OpenCV. ``from svs_torch import PipelineConfig`` works as before.
_EXPORTS = {
    "SVS_CAMERA": "camera", "SVS_RESOLUTIONS": "camera", "SVSCamera": "camera",
    "InputError": "errors",
    "SurfConfig": "detector",
    "SurfFeatures": "features", "extract_surf_features": "features",
    "match_sad": "matching",
    "PipelineConfig": "pipeline", "PipelineResult": "pipeline", "PipelineStatus": "pipeline",
    "estimate_obstacle_depth": "pipeline",
    "estimate_fundamental_ransac": "ransac",
    "SegmentationConfig": "segmentation", "segment_images": "segmentation", "segment_stereo": "segmentation",
    **{name: "types" for name in ("FundamentalResult", "FundamentalStatus", "Keypoints", "Matches",
                                  "RegionProperties", "Segmentation", "SegmentationStatus", "StereoBatch",
                                  "StereoSegmentation")},
}


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'svs_torch' has no attribute {name!r}")
    from importlib import import_module

    value = getattr(import_module(f".{module}", __name__), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))


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
