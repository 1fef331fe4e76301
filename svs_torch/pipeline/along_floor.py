"""The kept objects' distances ahead along the floor, from the pipeline's own maps
(:mod:`svs_torch.depth.floor_distance`): along the floor the pair's segmenter found, or along one found before
(``guide``'s frames where the floor rule finds none: its camera is worn on the same body, and its pose over the
floor changes slowly).
"""

from __future__ import annotations

import torch

from ..core.checks import check_instance
from ..core.errors import InputError
from ..core.types import StereoBatch, StereoSegmentation
from ..depth.dense_config import DenseDisparity
from ..depth.depth_types import DepthResult
from ..depth.floor_distance import FloorDistances, FloorGeometry, floor_distances, floor_geometry
from .config import PipelineConfig, PipelineResult
from .near_surface import _in_map_pixels
from .stages import without_failed_pairs

__all__ = ["along_floor", "result_along_floor"]


def along_floor(batch: StereoBatch, seg: StereoSegmentation, depth: DepthResult, status: torch.Tensor,
                dense: DenseDisparity | None, object_labels: torch.Tensor, rectified: torch.Tensor,
                H_left: torch.Tensor, config: PipelineConfig) -> FloorDistances | None:
    """The objects of ``depth`` (measured on ``dense`` over ``object_labels``, input pixels; ``rectified`` pairs by
    ``H_left``) ahead along the floor ``seg`` found, a pair whose ``status`` is not OK left unranged (none found
    where the segmenter did not look for one, ``SegmentationConfig.ground``: the rig is still recorded, which
    :func:`result_along_floor` reads); None without a dense map."""
    if dense is None or depth.objects is None:
        return None
    depth = without_failed_pairs(depth, status)
    plane, found = seg.floor_plane_px, seg.floor_found
    if found is None:
        plane, found = batch.left.new_zeros(batch.batch_size, 3), torch.zeros_like(status, dtype=torch.bool)
    floor = floor_geometry(plane, found, batch.focal_px, batch.baseline_m, batch.doffs_px, batch.size_hw)
    return floor_distances(floor, dense, _in_map_pixels(object_labels, rectified, H_left), depth.objects,
                           batch.focal_px, batch.baseline_m, batch.doffs_px, rectified, H_left,
                           config.depth.object_percentiles, config.dense.fill_invalid,
                           config.depth.surface_within_in_view_top)


def result_along_floor(result: PipelineResult, floor: FloorGeometry,
                       config: PipelineConfig = PipelineConfig()) -> FloorDistances | None:
    """``result``'s objects ahead along ``floor`` (a pose over the floor, e.g. found on an earlier pair of the same
    camera, with as many rows as ``result`` has pairs), with the rig its ``floor`` field recorded and ``config``'s
    percentiles; None where ``result`` has no such field (no dense map: the paper's rule)."""
    check_instance(result, "result", PipelineResult)
    check_instance(floor, "floor", FloorGeometry)
    check_instance(config, "config", PipelineConfig)
    if result.floor is None or result.dense is None or result.object_labels is None:
        return None
    if floor.found.shape != result.status.shape:
        raise InputError(f"floor: expected one row per pair of result ({result.status.shape[0]}), got "
                         f"{tuple(floor.found.shape)}")
    distances = result.floor
    return floor_distances(floor, result.dense, _in_map_pixels(result.object_labels, result.rectified,
                                                               result.H_left),
                           result.depth.objects, distances.focal_px, distances.baseline_m, distances.doffs_px,
                           result.rectified, result.H_left, config.depth.object_percentiles,
                           config.dense.fill_invalid, config.depth.surface_within_in_view_top)
