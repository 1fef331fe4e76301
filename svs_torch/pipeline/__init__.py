"""The pipeline: the stages composed, one batch of pairs from images to obstacle distances.

``config`` (:class:`PipelineConfig`; :class:`PipelineStatus` and :class:`PipelineResult`, defined in ``result``),
``stages`` (each stage as the pipeline calls it), ``ranging`` (the rectification choice and the dense depth with its
retry), ``run`` (:func:`estimate_obstacle_depth`: segmentation → features → matching → RANSAC → rectification →
dense depth, each batch run as groups of one size), ``exposure`` (the two views' exposures matched),
``exposure_retry`` and ``features_retry`` (second runs, with the exposures matched or SURF on smoothed views, of the
pairs the first run left unranged or unverified), ``beyond_range`` (an object whose inliers lie nearer than the
dense range searched left unranged), ``near_surface`` (an object spanning two surfaces ranged over the nearer),
``along_floor`` (the objects' distances ahead along the floor), ``soft`` (the differentiable pass over the hard
pass's decisions) and ``preload`` (worker processes that import the pipeline before their first task).

May import: ``svs_torch.core`` and every stage's public names. Only ``evaluation``, ``plotting`` and the CLI
import the pipeline; a stage never does.
"""

from ..segmentation.stereo import segment_pair
from .along_floor import result_along_floor
from .config import PipelineConfig, PipelineResult, PipelineStatus
from .run import estimate_obstacle_depth
from .stages import measured_labels

__all__ = ["PipelineConfig", "PipelineResult", "PipelineStatus", "estimate_obstacle_depth", "measured_labels",
           "result_along_floor", "segment_pair"]
