"""Pairs whose geometry cannot give a distance are not ranged (an audit of degenerate geometry): a repeated pattern
(a chessboard, tiles, a fence) shifted by d is pixel for pixel the pair shifted by d plus its period, so no
disparity of it can be told; an obstacle nearer than the dense stage searches has no true match in its range."""

from __future__ import annotations

import cv2
import numpy as np
import torch

from svs_torch.core.types import StereoBatch
from svs_torch.depth.dense import DenseConfig, coarse_search_range
from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth
from svs_torch.pipeline.config import PipelineStatus

#: The board's period and square side, pixels.
_PERIOD_PX, _SQUARE_PX = 32, 16


def _board(shift_px: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A 320 × 240 chessboard and the same board seen ``shift_px`` further left (right view), ``(1, 1, H, W)``."""
    y, x = torch.meshgrid(torch.arange(240), torch.arange(320), indexing="ij")
    board = (((x // _SQUARE_PX + y // _SQUARE_PX) % 2) * 200 + 30).to(torch.float32) / 255
    return board[None, None], torch.roll(board, -shift_px, dims=1)[None, None]


def test_a_board_and_its_alias_are_the_same_pair() -> None:
    assert torch.equal(_board(8)[1], _board(8 + _PERIOD_PX)[1])


def test_coarse_range_of_a_repeated_pattern_is_the_whole_fallback_range() -> None:
    # Before: only the left band, where the border hides the aliases, survived the uniqueness check, and the range
    # was [2, 14): the farthest alias, then ranged without a doubt.
    left, right = _board(8)
    mask = torch.ones(1, 1, 240, 320, dtype=torch.bool)
    config = DenseConfig()
    search = coarse_search_range(left, right, mask, torch.tensor([[240, 320]]), config)
    assert int(search.min_disparity_px[0]) == 0
    assert int(search.min_disparity_px[0]) + search.num_disparities - 1 >= 320 * config.fallback_max_disparity_fraction


def test_repeated_pattern_is_not_ranged() -> None:
    # Before: "OK" at 3.71 m (shift 8), 1.86 m (16) and 1.24 m (24, through the smoothed retries), where the same
    # images fit a board 32 px nearer in disparity (0.74 m for shift 8) as well.
    boards = [_board(shift) for shift in (8, 16, 24)]
    batch = StereoBatch.from_images(torch.cat([b[0] for b in boards]), torch.cat([b[1] for b in boards]),
                                    focal_px=276.0, baseline_m=0.1075)
    result = estimate_obstacle_depth(batch, PipelineConfig())
    assert (result.status != PipelineStatus.OK).all(), result.status.tolist()
    assert not result.depth.objects.valid.any()


def test_an_obstacle_nearer_than_the_range_searched_is_not_ranged_at_the_background(data_dir):
    # Before: a textured box 110 px of disparity away (0.27 m by the SVS model) before Teddy's view shifted 20 px
    # was ranged "OK" at 1.45 m, the background's distance, over a range searched up to 95 px, while every RANSAC
    # inlier on its kept regions read 110 px.
    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    gray = cv2.resize(cv2.imread(str(teddy / "im0.png"), cv2.IMREAD_GRAYSCALE), (320, 267))[13:253]
    patch = cv2.resize(cv2.imread(str(teddy / "im1.png"), cv2.IMREAD_GRAYSCALE), (320, 267))[53:173, 60:200]
    right = cv2.warpAffine(gray, np.float32([[1, 0, -20], [0, 1, 0]]), (320, 240), borderMode=cv2.BORDER_REFLECT)
    left = gray.copy()
    left[60:180, 150:290] = patch
    right[60:180, 40:180] = patch
    views = [torch.from_numpy(view).to(torch.float32)[None, None] / 255 for view in (left, right)]
    result = estimate_obstacle_depth(StereoBatch.from_images(*views, focal_px=276.0, baseline_m=0.1075))
    ranged = result.depth.objects.depth_median_m[result.depth.objects.valid]
    assert not (ranged > 0.5).any(), ranged.tolist()
