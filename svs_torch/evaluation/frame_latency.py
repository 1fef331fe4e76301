"""guide's one-frame latency on real scenes, frame by frame (issue 32, item 4: guide ≤ 50 ms a frame at B = 1).

Why frame by frame and on real scenes: the benchmark's synthetic camera frames are all ranged by one pass, so
their mean is a typical frame's. Real scenes as camera frames are not: a pair whose dense map measured too little
of its kept regions is measured again at half the working width (``PipelineConfig.coarse_retry_below_share``),
and one left unfinished whose views' exposures differ is run again with them matched
(``PipelineConfig.exposure_retry``); with both, at the board's default digit, 11 of the 45 shared real pairs end
on the coarse grid and (before the retry asked the map at the matched points first) 6 were run again on matched
views, 2–4 times a frame's usual time: the frames a walker waits longest for (``guide --second-passes off`` runs
neither, at a cost in accuracy: :meth:`~svs_torch.pipeline.PipelineConfig.for_guide`). So each frame is timed on
its own and the distribution reported: its median, 90th percentile and maximum, and how many frames took longer
than the goal.
"""

from __future__ import annotations

import math
import statistics
import time
from pathlib import Path

__all__ = ["GOAL_MS", "latency_summary", "real_camera_frames", "real_frame_latency"]

#: guide's latency goal a frame at B = 1 (issue 32, item 4), in ms.
GOAL_MS = 50.0


def real_frame_latency(data_dir: Path, configs: dict, repeats: int, digit: int, sigma_levels: float,
                       size: tuple[int, int] = (320, 240), limit: int | None = None) -> dict[str, dict]:
    """Each shared real pair (:func:`svs_torch.data.list_shared_pairs`, the first ``limit``) resampled to ``size``
    and made a camera frame (JPEG ``digit``, sensor noise of ``sigma_levels`` in each view, seeded by the pair's
    index), timed alone under inference mode as guide runs it, with each of ``configs`` (name → PipelineConfig):
    the median of ``repeats`` calls a frame, after one call that warms the pipeline up. Returns, by name,
    ``{"frames", "median_ms", "p90_ms", "max_ms", "over_goal"}`` (the 90th percentile by nearest rank; over_goal:
    frames slower than :data:`GOAL_MS`); an empty dict where the folder holds no pair."""
    import torch

    from ..pipeline import estimate_obstacle_depth

    frames = real_camera_frames(data_dir, digit, sigma_levels, size, limit)
    report = {}
    for name, config in configs.items():
        times = []
        with torch.inference_mode():
            for index, frame in enumerate(frames):
                if index == 0:
                    estimate_obstacle_depth(frame, config)
                runs = []
                for _ in range(max(1, repeats)):
                    started = time.perf_counter()
                    estimate_obstacle_depth(frame, config)
                    runs.append(time.perf_counter() - started)
                times.append(statistics.median(runs) * 1e3)
        if times:
            report[name] = latency_summary(times)
    return report


def real_camera_frames(data_dir: Path, digit: int, sigma_levels: float, size: tuple[int, int] = (320, 240),
                       limit: int | None = None) -> list:
    """The first ``limit`` shared real pairs (:func:`svs_torch.data.list_shared_pairs`), each resampled to ``size``
    and made a camera frame (JPEG ``digit``, sensor noise of ``sigma_levels`` in each view, seeded by the pair's
    index), each a :class:`~svs_torch.core.types.StereoBatch` of one pair: the frames :func:`real_frame_latency`
    times."""
    import torch

    from ..data import camera_frame_pairs, list_shared_pairs, load_stereo_pair, resize_stereo_batch

    return [camera_frame_pairs(resize_stereo_batch(load_stereo_pair(path), size), digit, sigma_levels,
                               torch.Generator().manual_seed(index))
            for index, path in enumerate(list_shared_pairs(data_dir)[:limit])]


def latency_summary(times_ms: list[float]) -> dict:
    """``{"frames", "median_ms", "p90_ms", "max_ms", "over_goal"}`` of frame times in ms (:func:`real_frame_latency`'s
    rows)."""
    ordered = sorted(times_ms)
    p90 = ordered[max(0, math.ceil(0.9 * len(ordered)) - 1)]
    return {"frames": len(ordered), "median_ms": round(statistics.median(ordered), 1), "p90_ms": round(p90, 1),
            "max_ms": round(ordered[-1], 1), "over_goal": sum(t > GOAL_MS for t in ordered)}
