"""What the second passes cost ``svs-depth guide`` a frame, with and without them (issue 32, item 4: guide ≤ 50 ms
a frame at B = 1).

The pipeline measures some pairs twice: a pair whose dense map measured too little of its kept regions again at
half the working width (the coarse retry, ``PipelineConfig.coarse_retry_below_share``), and one left unfinished
whose views' exposures differ again on matched views (the exposure retry, ``PipelineConfig.exposure_retry``, a
whole second run). A walker waits for them. Here every shared real pair at 320×240 is made a camera frame (JPEG
``--digit``, the board's default 4, with sensor noise) and timed alone, as guide runs it
(the frames of :func:`svs_torch.evaluation.frame_latency.real_frame_latency`, the median of ``--repeats`` calls a
frame), under guide's configuration with both passes (its default), without each, and without either
(``guide --second-passes off``), the four taken in turn on each frame. What the passes buy in accuracy is
measured on the tuning sets with ``experiments/real_rig.py`` (its ``--set`` turns them off); the record of both is
``experiments/guide_second_passes.md``. About 2 minutes on a 2-core machine.

    python experiments/guide_second_passes.py [--data DIR] [--digit D] [--repeats N] [--limit N] [--json F]
"""

from __future__ import annotations

import os

# Timed as guide's own process runs: it sets no OpenMP wait policy. A shell that exports PASSIVE for bulk runs on a
# shared machine (the experiments' own default, real_rig.py's) puts OpenMP's threads to sleep between the many small
# parallel regions of a one-pair frame: on the AMD VM on 2026-11-30 median 22.5 against 15.2 ms a frame, 6 frames
# over 50 ms against 1. The OpenMP runtime reads the variable when torch loads it, so it is dropped before that.
os.environ.pop("OMP_WAIT_POLICY", None)

import argparse
import dataclasses
import json
import statistics
import sys
import time
from pathlib import Path

import torch

from svs_torch.evaluation.frame_latency import GOAL_MS, latency_summary, real_camera_frames
from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_rig import JPEG_NOISE  # noqa: E402
from svs_torch.cli.common import positive_int  # noqa: E402
from svs_torch.core.errors import InputError  # noqa: E402
from run_metadata import (add_data_option, command_line, output_path, run_metadata, run_script,  # noqa: E402
                          scene_limit, write_text_whole)

# real_rig.py sets PASSIVE again on import, after torch loaded OpenMP: the runtime keeps its policy, but the report's
# metadata read the variable and called this run PASSIVE (an audit).
os.environ.pop("OMP_WAIT_POLICY", None)

#: Each digit's sensor noise, 8-bit levels, as experiments/real_rig.py pairs them.
NOISE_FOR_DIGIT = dict(JPEG_NOISE)


def configurations() -> dict[str, PipelineConfig]:
    """guide's configuration (:meth:`PipelineConfig.for_guide`) with both second passes (its default), without the
    exposure retry, without the coarse retry, and without either (``guide --second-passes off``)."""
    both = PipelineConfig().for_guide()
    return {"both passes": both,
            "no exposure retry": dataclasses.replace(both, exposure_retry=None),
            "no coarse retry": dataclasses.replace(both, coarse_retry_below_share=None),
            "neither": dataclasses.replace(both, exposure_retry=None, coarse_retry_below_share=None)}


def interleaved_latency(data: Path, configs: dict[str, PipelineConfig], repeats: int, digit: int,
                        limit: int | None = None) -> dict[str, dict]:
    """:func:`~svs_torch.evaluation.frame_latency.real_frame_latency`'s frames and summary, with the configurations
    taken in turn on each frame (and their order turned each repeat), so that the machine's load drifting during
    the run falls on all of them alike."""
    frames = real_camera_frames(data, digit, NOISE_FOR_DIGIT[digit], limit=limit)
    times = {name: [[] for _ in frames] for name in configs}
    with torch.inference_mode():
        for config in configs.values():  # warm-up
            if frames:
                estimate_obstacle_depth(frames[0], config)
        for repeat in range(max(1, repeats)):
            for index, frame in enumerate(frames):
                order = list(configs.items())
                for name, config in order[repeat % len(order):] + order[:repeat % len(order)]:
                    started = time.perf_counter()
                    estimate_obstacle_depth(frame, config)
                    times[name][index].append(time.perf_counter() - started)
    return {name: latency_summary([statistics.median(runs) * 1e3 for runs in per_frame])
            for name, per_frame in times.items() if per_frame}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_data_option(parser, Path)
    parser.add_argument("--digit", type=int, default=4, choices=sorted(NOISE_FOR_DIGIT),
                        help="the frames' JPEG quality digit (default: 4, the board's)")
    parser.add_argument("--repeats", type=positive_int, default=3, help="calls a frame, their median kept (default: 3)")
    parser.add_argument("--limit", type=scene_limit, help="the first N shared pairs only")
    parser.add_argument("--json", type=output_path, default=None, help="write the report as JSON to FILE")
    args = parser.parse_args(argv)
    rows = interleaved_latency(args.data, configurations(), args.repeats, args.digit, args.limit)
    if not rows:
        raise InputError(f"--data: no shared pair under {args.data}")
    print(f"guide frame by frame, shared real pairs at 320x240 as JPEG digit {args.digit} frames (noise σ "
          f"{NOISE_FOR_DIGIT[args.digit]:g}), B = 1, {torch.get_num_threads()} threads, OpenMP wait policy unset "
          f"(as guide's process); goal {GOAL_MS:g} ms")
    print("\n| second passes | frames | median ms | 90th percentile ms | max ms | frames over the goal |")
    print("|---|---|---|---|---|---|")
    for name, row in rows.items():
        print(f"| {name} | {row['frames']} | {row['median_ms']} | {row['p90_ms']} | {row['max_ms']} | "
              f"{row['over_goal']} |")
    # The machine and its load with the times (an audit: this report alone had no metadata block; times do not carry
    # from machine to machine).
    command = command_line("experiments/guide_second_passes.py", argv)
    report = {"metadata": run_metadata(torch.get_num_threads(), command=command, digit=args.digit, repeats=args.repeats,
                                       limit=args.limit),
              "digit": args.digit, "threads": torch.get_num_threads(), "rows": rows}
    if args.json:
        write_text_whole(args.json, json.dumps(report, indent=2))
    return report


if __name__ == "__main__":
    run_script(main)
