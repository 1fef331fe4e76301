"""Stage 3, geometry: from matched features to a rectified pair.

``matching`` (SAD matching of descriptors; ``match_ratios``, its ratio tests' thresholds, without torch),
``matched_points`` (the points of the matches), ``lk_refinement`` (the Lucas–Kanade refinement of matched points),
``epipolar`` (the 7- and 8-point fundamental matrix, on ``point_pairs``' checks and normalisation and
``minimal_solvers``' linear algebra), ``epipolar_distance`` (Sampson and symmetric distances), ``ransac`` (the batched
RANSAC / MSAC / LMedS search, with ``ransac_sampling``, ``ransac_scoring`` and ``ransac_refine``), ``rectification``
(the paper's uncalibrated rectification), ``row_alignment`` (a similarity that aligns the rows when rectifying would not
help, with ``row_alignment_keystone``, its model of a right camera turned about its y or x axis), ``soft`` (their
differentiable versions), ``calibration`` and ``chessboard`` (a calibrated rig: its file, its rectification, and
calibrating it from chessboards); ``kernels/`` holds the C kernels of the matching and the refinement.

May import: ``svs_torch.core`` only. Never another stage, the pipeline, ``evaluation``, ``data`` or the CLI.
"""
