"""Benchmark: the dense stage (coarse range pass + SAD block matching over the kept regions) per pair at
320×240, svs_torch batched vs OpenCV ``StereoBM`` and ``StereoSGBM`` over the whole frame in a loop, same run,
same pairs: synthetic SVS scenes and real Middlebury pairs resized to 320×240. Median of several runs, the
spread, thread count and OMP policy recorded, JSON with metadata.

The OpenCV rivals search the same fallback range svs_torch's coarse pass starts from ([0, W/4) rounded up to
16 disparities) over the whole frame; svs_torch searches only the kept regions, over the range its coarse pass
finds.

    python experiments/bench_dense.py [--threads 2] [--repeats 5] [--batch 32] [--json out.json]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # spinning OpenMP threads on a shared CPU, see bench_ransac.py

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

from svs_torch.data.synthetic import random_obstacle_scenes
from svs_torch.depth.dense import estimate_dense_disparity
from svs_torch.depth.dense_config import DenseConfig
from svs_torch.segmentation.segment import segment_stereo

sys.path.insert(0, str(Path(__file__).resolve().parent))
from svs_torch.cli.common import positive_int  # noqa: E402
from run_metadata import add_common_options, command_line, run_metadata, run_script, write_text_whole  # noqa: E402
from bench_segmentation import load_pairs, timed, to_u8  # noqa: E402

CONFIGS = {"default": DenseConfig(), "working 160 px": DenseConfig(working_width_px=160, coarse_width_px=80)}


def opencv_loop(lefts: list[np.ndarray], rights: list[np.ndarray], matcher) -> list[np.ndarray]:
    return [matcher.compute(a, b) for a, b in zip(lefts, rights)]


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_options(parser, threads=2, repeats=5, json=True)
    parser.add_argument("--batch", type=positive_int, default=32, help="pairs per batched call (default: %(default)s)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    real_left, real_right = load_pairs(Path(args.data), args.batch)  # (first: a folder it refuses, before any work)
    synthetic = random_obstacle_scenes(args.batch, 2, generator=torch.Generator().manual_seed(0)).batch
    inputs = {"synthetic SVS": (synthetic.left, synthetic.right), "Middlebury": (real_left, real_right)}
    num_disparities = 16 * int(np.ceil(0.25 * 320 / 16))
    rivals = {"OpenCV StereoBM loop": cv2.StereoBM_create(numDisparities=num_disparities, blockSize=9),
              "OpenCV StereoSGBM loop": cv2.StereoSGBM_create(0, num_disparities, 5, P1=200, P2=800)}
    results: dict[str, dict] = {}
    for data_name, (left, right) in inputs.items():
        masks = segment_stereo(dataclasses.replace(synthetic, left=left, right=right)).left.kept_mask
        lefts, rights = to_u8(left), to_u8(right)
        for name, matcher in rivals.items():
            results[f"{data_name} | {name}"] = timed(lambda: opencv_loop(lefts, rights, matcher), args.repeats,
                                                     pairs=len(lefts))
        for name, config in CONFIGS.items():
            for b in sorted({1, args.batch}):
                key = f"{data_name} | svs_torch {name} B={b}"
                starts = range(0, len(lefts), b)  # the rivals' pairs in batches of B (B = 1 timed the first alone)
                results[key] = timed(lambda: [estimate_dense_disparity(left[i:i + b], right[i:i + b], masks[i:i + b],
                                                                       config) for i in starts],
                                     args.repeats, pairs=len(lefts))
                results[key]["num_disparities"] = estimate_dense_disparity(
                    left[:b], right[:b], masks[:b], config).num_disparities
    # Each time over StereoBM's on the same inputs, printed and in the JSON (a script reads it, not works it out).
    ratios = {}
    for key, value in results.items():
        stereobm = results[key.split(" | ")[0] + " | OpenCV StereoBM loop"]
        ratios[key] = round(value["ms_per_pair"] / stereobm["ms_per_pair"], 3)
    print(f"threads {args.threads}, 320x240, dense stage per pair, median of {args.repeats} runs")
    for key, value in results.items():
        least = value['min_ms'] / (value['median_ms'] / value['ms_per_pair'])
        print(f"  {key:52s} {value['ms_per_pair']:8.2f} ms/pair (min {least:.2f})"
              f"  x StereoBM time {ratios[key]:6.2f}")
    report = {"metadata": run_metadata(args.threads, command=command_line("experiments/bench_dense.py", argv),
                                       batch=args.batch, configs={k: repr(v) for k, v in CONFIGS.items()}),
              "results": results, "time_x_stereobm": ratios}
    if args.json:
        write_text_whole(args.json, json.dumps(report, indent=2))
    return report


if __name__ == "__main__":
    run_script(main)
