"""SURF's limits and its keypoint cap as plain numbers, importable without torch: :class:`~.detector.SurfConfig`
checks against them and takes its default from them, and the command line's ``--help`` quotes them without loading
torch (``svs-depth estimate --help`` took 2.3 s when its text read the values from the configuration).
"""

from __future__ import annotations

__all__ = ["DEFAULT_MAX_KEYPOINTS", "MATLAB_METRIC_THRESHOLD", "MAX_KEYPOINTS", "MAX_OCTAVES", "MAX_SCALE_LEVELS",
           "PIPELINE_METRIC_THRESHOLD"]

#: Limits that keep a mistyped setting from asking for gigabytes (MATLAB recommends 1-4 octaves and 3-6 levels): the
#: largest filter, 3 + 6·2⁵·8 = 1539 px at 6 octaves of 8 levels, pads the integral image by half its size; the SAD
#: matching compares every pair of keypoints (10⁸ at 10⁴ per image).
MAX_OCTAVES = 6
MAX_SCALE_LEVELS = 8
MAX_KEYPOINTS = 10_000
#: Keypoints kept per image by default (``SurfConfig.max_keypoints``): the strongest 512 suit 320×240 frames and
#: RANSAC.
DEFAULT_MAX_KEYPOINTS = 512
#: SURF's det(H) threshold on 0-255 intensities: MATLAB detectSURFFeatures' MetricThreshold (``SurfConfig``'s default,
#: the paper's preset) and the pipeline's own (``PipelineConfig.surf``: more keypoints on small frames, the best
#: measured, ``experiments/surf_vs_sift.py``).
MATLAB_METRIC_THRESHOLD = 1000.0
PIPELINE_METRIC_THRESHOLD = 100.0
