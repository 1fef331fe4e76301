"""Stage 4, depth: the obstacles' distances.

``depth_types`` (:class:`DepthConfig` and the depth results), ``quantiles`` (medians and percentiles over masks
and labels), ``sparse`` (the paper's rule, Eq. (5)–(8): depth from the RANSAC inliers' disparities, per object
and over the pair); the dense stage: ``dense_config`` (its options and results), ``cost_volume`` (pre-filter,
crops, window sums), ``winner`` (winner takes all, rejections, the right view's winner and the left-right
check), ``semi_global`` (semi-global aggregation of the cost volume, for noisy pairs), ``block_matching`` (the
hard matcher and the row fill), ``soft_dense`` (its differentiable
soft-argmin), ``pooling``, ``search_range`` (each pair's disparity range), ``dense`` (the working resolution and
:func:`~svs_torch.depth.dense.estimate_dense_disparity`), ``dense_objects`` (each object's depth from the dense
map, and the verification that both views show one scene), ``floor_distance`` (how far ahead along the floor,
where the floor was found); ``kernels/`` holds the C kernels of the block
matching, the row fill, the order statistics by label and the objects' statistics, beside their torch paths.

May import: ``svs_torch.core`` and ``geometry``'s public names (homographies). Never segmentation, the
pipeline, ``evaluation``, ``data`` or the CLI.

The names below were the old ``svs_torch.depth`` module's, and stay importable from here.
"""

from .depth_types import (Accuracy, DepthConfig, DepthResult, Disparities, NearestObstacle, ObjectDepths, ObstacleSide,
                          PointDepths, RangeEstimate)
from .quantiles import Quantiles, kept_region_lower_median, labelled_quantile, masked_lower_median, masked_quantile
from .sparse import (accuracy_percent, estimate_depth, estimate_range, nearest_obstacle, object_depths, point_depths,
                     rectified_disparity, slot_labels)

__all__ = [
    "Accuracy", "DepthConfig", "DepthResult", "Disparities", "NearestObstacle", "ObjectDepths", "ObstacleSide",
    "PointDepths", "Quantiles", "RangeEstimate", "accuracy_percent", "estimate_depth", "estimate_range",
    "kept_region_lower_median", "labelled_quantile", "masked_lower_median", "masked_quantile", "nearest_obstacle",
    "object_depths", "point_depths", "rectified_disparity", "slot_labels"
]
