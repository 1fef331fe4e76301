"""depth.periodicity: a region that repeats itself along the rows, told from a natural texture."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from svs_torch.core.errors import InputError
from svs_torch.depth.periodicity import (object_periods, period_along_rows, period_at_working_width,
                                        repeated_along_rows, repeated_at_working_width, row_autocorrelation)

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from real_images import PAIRS, read_gray  # noqa: E402


def as_batch(*images: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.stack(images).astype(np.float32)).unsqueeze(1)


@pytest.mark.parametrize("height, width, max_lag_px", [(30, 50, 6), (240, 320, 24), (17, 43, 5)])
def test_row_autocorrelation_is_numpy_corrcoef_over_the_masked_pairs(height, width, max_lag_px):
    # Padded rows of 56 and 344 the FFT takes at 60 and 352, and of 48 at its own length; a batch of two pairs, each
    # summed over its own rows.
    rng = np.random.default_rng(0)
    images = [cv2.GaussianBlur(rng.random((height, width)).astype(np.float32), (0, 0), sigma) for sigma in (1.5, 3.0)]
    masks = [rng.random((height, width)) > share for share in (0.3, 0.6)]
    r = row_autocorrelation(as_batch(*images), torch.from_numpy(np.stack(masks))[:, None], max_lag_px).numpy()
    for pair, (image, mask) in enumerate(zip(images, masks)):
        image = image.astype(np.float64)
        centred = np.where(mask, image - image[mask].mean(), 0.0)
        for lag in range(1, max_lag_px + 1):
            both = mask[:, :-lag] & mask[:, lag:]
            a, b = centred[:, :-lag][both], centred[:, lag:][both]
            expected = float(a @ b / np.sqrt((a @ a) * (b @ b)))
            assert r[pair, lag - 1] == pytest.approx(expected, abs=1e-5)  # float32 FFTs


def test_bars_and_grates_repeat_and_a_natural_texture_does_not():
    rows, cols = np.mgrid[0:60, 0:120]
    bars = ((cols // 5) % 2).astype(np.float32)  # a 10 px period
    grate = (((cols % 12) < 4) | ((rows % 12) < 4)).astype(np.float32)  # never below 0.1: its rows of bar
    texture = cv2.GaussianBlur(np.random.default_rng(1).random((60, 120)).astype(np.float32), (0, 0), 2.0)
    whole = torch.ones(3, 1, 60, 120, dtype=torch.bool)
    assert repeated_along_rows(as_batch(bars, grate, texture), whole, 0.5).tolist() == [True, True, False]
    r = row_autocorrelation(as_batch(bars), whole[:1])[0]
    assert float(r[9]) == pytest.approx(1.0, abs=0.02) and float(r[4]) == pytest.approx(-1.0, abs=0.02)
    # A period past the lags looked at is not found.
    assert not bool(repeated_along_rows(as_batch(bars), whole[:1], 0.5, max_lag_px=8)[0])


def test_the_period_is_the_first_peak_in_the_pixels_given():
    """Bars of 10 px and a grate of 12 px (its first peak, not a harmonic), none for a texture; measured at the
    working width and given in input pixels: the bars drawn at 640 px wide (a 20 px period, reduced twice)."""
    rows, cols = np.mgrid[0:60, 0:120]
    bars = ((cols // 5) % 2).astype(np.float32)
    grate = (((cols % 12) < 4) | ((rows % 12) < 4)).astype(np.float32)
    texture = cv2.GaussianBlur(np.random.default_rng(1).random((60, 120)).astype(np.float32), (0, 0), 2.0)
    whole = torch.ones(3, 1, 60, 120, dtype=torch.bool)
    assert period_along_rows(as_batch(bars, grate, texture), whole, 0.5).tolist() == [10, 12, 0]
    wide = ((np.mgrid[0:480, 0:640][1] // 10) % 2).astype(np.float32)
    period = period_at_working_width(as_batch(wide), torch.ones(1, 1, 480, 640, dtype=torch.bool), 0.5)
    assert period.tolist() == [20] and period.dtype == torch.int64


def test_a_railings_period_past_32_px_is_found_up_to_the_default_longest_lag():
    """A railing near the walker: bars every 40 px at the working width (12 cm apart at 0.8 m). Lags up to 32 px
    (the functions' default) do not reach it; the coarse grid's gate's, up to 64
    (DepthConfig.coarse_retry_max_period_px), does."""
    bars = ((np.mgrid[0:120, 0:320][1] // 20) % 2).astype(np.float32)
    whole = torch.ones(1, 1, 120, 320, dtype=torch.bool)
    assert period_along_rows(as_batch(bars), whole, 0.5, 32).tolist() == [0]
    assert period_at_working_width(as_batch(bars), whole, 0.5, max_lag_px=64).tolist() == [40]


def test_two_like_regions_side_by_side_do_not_repeat_though_their_union_does():
    """Was: the coarse grid's gate tested the kept regions' union, which correlates at the lag separating two like
    regions (the tuned Piano at half contrast as JPEG digit 8 frames: two regions 48 px apart read a period of 48,
    and the pair lost its coarse retry, 91.5 -> 72.3 % per object). Each object is tested on its own."""
    texture = cv2.GaussianBlur(np.random.default_rng(2).random((100, 40)).astype(np.float32), (0, 0), 1.5)
    image = np.full((100, 320), 0.5, dtype=np.float32)
    image[:, 100:140] = texture
    image[:, 148:188] = texture  # the same patch 48 px further right
    bars = ((np.mgrid[0:100, 0:60][1] // 5) % 2).astype(np.float32)
    image[:, 240:300] = bars  # and a third object that does repeat, every 10 px
    objects = torch.zeros(2, 2, 100, 320, dtype=torch.bool)
    objects[:, 0, :, 100:140] = True
    objects[:, 1, :, 148:188] = True
    objects[1, 1] = False
    objects[1, 1, :, 240:300] = True
    views = as_batch(image, image)
    assert period_at_working_width(views[:1], objects[:1].any(1, keepdim=True), 0.5, max_lag_px=64).tolist() == [48]
    assert object_periods(views, objects, 0.5, max_lag_px=64).tolist() == [[0, 0], [0, 10]]


def test_real_scenes_do_not_repeat_and_a_real_chessboard_does(data_dir):
    """The shared scenes' whole left views at 320 × 240 are natural textures; OpenCV's sample chessboard over the
    hull of the corners OpenCV finds on it repeats with its two squares' period (34 px there: past the
    default's 32, found with lags up to 64)."""
    scenes = [read_gray(data_dir, left, (320, 240)) for left, _ in PAIRS if "opencv_samples" not in left]
    whole = torch.ones(len(scenes), 1, 240, 320, dtype=torch.bool)
    assert not repeated_at_working_width(as_batch(*scenes) / 255, whole, 0.5).any()
    board = read_gray(data_dir, "opencv_samples/left01.jpg", (320, 240))
    found, corners = cv2.findChessboardCorners(board, (9, 6))
    assert found
    hull = np.zeros_like(board)
    cv2.fillConvexPoly(hull, cv2.convexHull(corners.astype(np.int32)), 1)
    assert bool(repeated_along_rows(as_batch(board) / 255, torch.from_numpy(hull > 0)[None, None], 0.5, 64)[0])


def test_a_mask_of_another_shape_or_dtype_and_settings_out_of_range_are_refused_by_name():
    image = torch.zeros(1, 1, 8, 8)
    with pytest.raises(InputError, match="mask"):
        row_autocorrelation(image, torch.ones(1, 1, 8, 9, dtype=torch.bool))
    with pytest.raises(InputError, match="mask"):
        repeated_at_working_width(image, torch.ones(1, 1, 8, 8), 0.5)
    with pytest.raises(InputError, match="max_lag_px"):
        row_autocorrelation(image, torch.ones(1, 1, 8, 8, dtype=torch.bool), max_lag_px=0)
    with pytest.raises(InputError, match="min_peak"):
        repeated_along_rows(image, torch.ones(1, 1, 8, 8, dtype=torch.bool), 1.5)
    with pytest.raises(InputError, match="objects"):
        object_periods(image, torch.ones(1, 2, 8, 8), 0.5)
    with pytest.raises(InputError, match="objects"):
        object_periods(image, torch.ones(2, 2, 8, 8, dtype=torch.bool), 0.5)


def test_a_pattern_needs_contrast_to_count_and_a_pairs_floor_where_set(monkeypatch):
    """A region spreading under MIN_PATTERN_SPREAD is a blank view's noise, no pattern: the same bars at 2 levels
    of contrast are not found, at 10 they are. The pairs floor (off by default, experiments/blank_views.md) keeps a
    peak over a 3 x 12 px patch (24 pairs at the 4 px lag) out where it is set, not one over 6 x 20 px (96)."""
    import svs_torch.depth.periodicity as periodicity

    cols = np.mgrid[0:40, 0:60][1]
    faint, clear = (0.5 + level / 255 * ((cols // 2) % 2).astype(np.float32) for level in (2, 10))  # a 4 px period
    whole = torch.ones(2, 1, 40, 60, dtype=torch.bool)
    assert period_along_rows(as_batch(faint, clear), whole, 0.5).tolist() == [0, 4]
    bars = 0.5 + 0.2 * ((cols // 2) % 2).astype(np.float32)
    patch, wider = np.zeros((40, 60), bool), np.zeros((40, 60), bool)
    patch[10:13, 10:22], wider[10:16, 10:30] = True, True
    masks = torch.from_numpy(np.stack([patch, wider]))[:, None]
    assert period_along_rows(as_batch(bars, bars), masks, 0.5).tolist() == [4, 4]
    monkeypatch.setattr(periodicity, "MIN_PERIOD_PAIRS", 64)
    assert period_along_rows(as_batch(bars, bars), masks, 0.5).tolist() == [0, 4]


def test_a_blank_noisy_view_as_camera_frames_holds_no_repeated_pattern():
    """A covered lens or a grey wall, as the board's frames (sensor noise, JPEG): its noise regions were taken for
    repeated patterns 0.4-0.6 m away (15 of 216 such pairs, 0 now), and guide said "Repeated pattern ahead" in place of
    "Cannot see ahead" (an audit)."""
    from svs_torch.core.types import StereoBatch
    from svs_torch.data import camera_frame_pairs
    from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth

    n = 4  # light grey, σ 2 at the default digit: two of these four were said to repeat
    views = torch.full((n, 1, 240, 320), 200 / 255)
    batch = StereoBatch(views, views.clone(), torch.full((n,), 276.0), torch.full((n,), 0.1075), torch.zeros(n),
                        torch.ones(n, dtype=torch.bool), torch.tensor([[240, 320]] * n))
    frames = camera_frame_pairs(batch, 4, 2.0, torch.Generator().manual_seed(202))
    assert torch.isnan(estimate_obstacle_depth(frames, PipelineConfig()).nearest_unranged_alias_m).all()
