"""The ratio test's two thresholds (Sec. 3.3 (2)) as plain numbers, importable without torch: the matching and the
pipeline's configuration take their defaults from them, and the command line's ``--help`` quotes them without loading
torch.
"""

from __future__ import annotations

__all__ = ["LOWE_MAX_RATIO", "MATLAB_MAX_RATIO"]

#: MATLAB ``matchFeatures``' ``MaxRatio`` default: the paper's matching (``PipelineConfig.paper()``) and
#: :func:`~.matching.match_sad`'s default.
MATLAB_MAX_RATIO = 0.6
#: Lowe's ratio (Lowe 2004, Sec. 7.1): the pipeline's default, measured more precise with refined matches
#: (``experiments/surf_vs_sift.py``; the README's "Precise geometry").
LOWE_MAX_RATIO = 0.8
