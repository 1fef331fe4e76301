"""``PipelineConfig.paper()`` against the MATLAB functions the paper calls, each written here in numpy from
MathWorks' own sources (``matchFeatures.m``, ``estimateFundamentalMatrix.m``), on real pairs at the SVS's 320×240."""

from __future__ import annotations

import numpy as np
import pytest

from svs_torch.data import load_middlebury_eval3, resize_stereo_batch
from svs_torch.pipeline import PipelineConfig, PipelineStatus, estimate_obstacle_depth


def matlab_match_sad(desc_left: np.ndarray, desc_right: np.ndarray, max_ratio: float = 0.6) -> np.ndarray:
    """``matchFeatures(f1, f2, 'Metric', 'SAD', 'MaxRatio', max_ratio)`` (``Unique`` false) without a
    ``MatchThreshold``: rows made unit-L2 (``normalizeX``), each left row's nearest right row by SAD, kept where
    nearest / second nearest ≤ MaxRatio (a second distance under 1e-6 counts as ratio 1, MATLAB's guard). The
    descriptors alone decide: nothing else about a keypoint reaches the function. Right row index, −1 unmatched."""
    left = desc_left / np.linalg.norm(desc_left, axis=1, keepdims=True)
    right = desc_right / np.linalg.norm(desc_right, axis=1, keepdims=True)
    sad = np.abs(left[:, None, :] - right[None, :, :]).sum(-1)
    order = np.argsort(sad, axis=1, kind="stable")
    rows = np.arange(len(sad))
    best, second = sad[rows, order[:, 0]], sad[rows, order[:, 1]]
    tiny = second < 1e-6
    ratio = np.where(tiny, 1.0, best) / np.where(tiny, 1.0, second)
    return np.where(ratio <= max_ratio, order[:, 0], -1)


def matlab_sampson_sq(fundamental: np.ndarray, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """``estimateFundamentalMatrix``'s ``computeDistance('sampson', ...)``: (x_rᵀ F x_l)² over the squared first
    two coefficients of both epipolar lines, in pixels² of the points given (no normalisation)."""
    h_left, h_right = np.c_[left, np.ones(len(left))].T, np.c_[right, np.ones(len(right))].T
    algebraic = ((h_right.T @ fundamental).T * h_left).sum(0) ** 2
    line_right, line_left = fundamental @ h_left, fundamental.T @ h_right
    return algebraic / (line_right[0] ** 2 + line_right[1] ** 2 + line_left[0] ** 2 + line_left[1] ** 2)


def _paper_result(data_dir, scene: str):
    batch = resize_stereo_batch(load_middlebury_eval3(data_dir / "middlebury_eval3_Q" / scene), (320, 240))
    return estimate_obstacle_depth(batch, PipelineConfig.paper())


@pytest.mark.parametrize("scene", ["MotorcycleE", "Teddy"])
def test_the_paper_preset_matches_as_matlab_matchfeatures(data_dir, scene):
    """Sec. 3.3 (2): ``matchFeatures`` with SAD and MATLAB's MaxRatio 0.6. It sees only the descriptors, so the
    preset has no Laplacian-sign gate: with one, MotorcycleE at 320×240 matched a keypoint MATLAB leaves out."""
    result = _paper_result(data_dir, scene)
    valid_left = result.features_left.keypoints.valid[0]
    valid_right = result.features_right.keypoints.valid[0]
    expected = matlab_match_sad(result.features_left.descriptors[0][valid_left].double().numpy(),
                                result.features_right.descriptors[0][valid_right].double().numpy())
    right_rows = np.flatnonzero(valid_right.numpy())
    expected = np.where(expected >= 0, right_rows[np.maximum(expected, 0)], -1)
    assert (expected >= 0).sum() >= 7
    np.testing.assert_array_equal(result.matches.idx[0][valid_left].numpy(), expected)


@pytest.mark.parametrize("scene", ["ArtL", "Teddy"])
def test_the_paper_preset_keeps_matlabs_ransac_inliers_and_trials(data_dir, scene):
    """Sec. 3.3 (3): ``estimateFundamentalMatrix``'s DistanceThreshold 0.01 bounds the squared Sampson distance in
    pixels² (``findInliers``: d ≤ 0.01, i.e. 0.1 px; it was 1 px here, 100× that square), and NumTrials 500 bounds
    the samples. The inliers are exactly the matched points within it under the F returned (ArtL at 320×240 drew
    1024 samples before)."""
    result = _paper_result(data_dir, scene)
    assert int(result.status[0]) == PipelineStatus.OK
    valid = result.points.valid[0].numpy()
    distance_sq = matlab_sampson_sq(result.fundamental.F[0].double().numpy(),
                                    result.points.left[0][valid].double().numpy(),
                                    result.points.right[0][valid].double().numpy())
    inliers = result.fundamental.inliers[0].numpy()[valid]
    assert inliers.sum() >= 7
    np.testing.assert_array_equal(inliers, distance_sq <= 0.01 * (1 + 1e-4))  # float32 scores: a hair of slack
    assert 0 < int(result.fundamental.iterations[0]) <= 500
