"""Benchmark: the whole pipeline per pair at 320×240, svs_torch batched vs the OpenCV pipeline of REFERENCE.md
(Otsu + morphology + components + SIFT + brute-force ratio matching + findFundamentalMat) in a loop, same run,
same real pairs. Median of several runs, thread count and OMP policy recorded, JSON with metadata.

    python experiments/bench_pipeline.py [--threads 2] [--repeats 5] [--json out.json]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # spinning OpenMP threads on a shared CPU, see bench_ransac.py

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import torch

from svs_torch import StereoBatch
from svs_torch.features.detector import SurfConfig
from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth

sys.path.insert(0, str(Path(__file__).resolve().parent))
from svs_torch.cli.common import positive_int  # noqa: E402
from run_metadata import add_data_option, output_path, run_metadata, run_script, write_text_whole  # noqa: E402
from bench_segmentation import load_pairs, opencv_segment, timed  # noqa: E402


def opencv_pipeline(left: np.ndarray, right: np.ndarray, kernel: np.ndarray, sift, matcher) -> int:
    masked = [opencv_segment(g, kernel, 2) for g in (left, right)]
    (kl, dl), (kr, dr) = (sift.detectAndCompute(m, None) for m in masked)
    if dl is None or dr is None or len(kr) < 2:
        return 0
    good = [m[0] for m in matcher.knnMatch(dl, dr, k=2) if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
    if len(good) < 8:
        return 0
    pl = np.float32([kl[m.queryIdx].pt for m in good])
    pr = np.float32([kr[m.trainIdx].pt for m in good])
    _, mask = cv2.findFundamentalMat(pl, pr, cv2.FM_RANSAC, 1.0, 0.99)
    return 0 if mask is None else int(mask.sum())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_option(parser)
    parser.add_argument("--threads", type=positive_int, default=2, help="torch threads (default: %(default)s)")
    parser.add_argument("--repeats", type=positive_int, default=5,
                        help="timed runs of each; the median is reported (default: %(default)s)")
    parser.add_argument("--json", type=output_path, metavar="FILE", help="write the report as JSON to FILE")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    left, right = load_pairs(Path(args.data), 32)
    lefts = list((left[:, 0] * 255).round().to(torch.uint8).numpy())
    rights = list((right[:, 0] * 255).round().to(torch.uint8).numpy())
    kernel = np.ones((5, 5), np.uint8)
    sift, matcher = cv2.SIFT_create(), cv2.BFMatcher(cv2.NORM_L2)
    results = {"opencv_loop": timed(lambda: [opencv_pipeline(a, b, kernel, sift, matcher)
                                             for a, b in zip(lefts, rights)], args.repeats, pairs=32)}
    configs = {"svs_torch": PipelineConfig(),
               "svs_torch_compiled": replace(PipelineConfig(), surf=SurfConfig(compiled=True))}
    for name, config in configs.items():
        for b in (1, 32):  # the loop's 32 pairs in batches of B (B = 1 timed the first pair alone: an audit)
            batches = [StereoBatch.from_images(left[i:i + b], right[i:i + b], 276.0, 0.1075) for i in range(0, 32, b)]
            key = f"{name}_B{b}"
            results[key] = timed(lambda: [estimate_obstacle_depth(batch, config) for batch in batches], args.repeats,
                                 pairs=32)
    base = results["opencv_loop"]["ms_per_pair"]
    # The speed-ups printed are the JSON's too, so a script comparing runs reads them rather than working them out.
    speedups = {key: round(base / value["ms_per_pair"], 3) for key, value in results.items()}
    print(f"threads {args.threads}, 320x240 real pairs, whole pipeline, median of {args.repeats} runs")
    for key, value in results.items():
        print(f"  {key:26s} {value['ms_per_pair']:8.2f} ms/pair  {1e3 / value['ms_per_pair']:7.1f} pairs/s  "
              f"x OpenCV pairs/s {speedups[key]:5.2f}")
    if args.json:
        report = {"metadata": run_metadata(args.threads), "results": results, "speedup_vs_opencv_loop": speedups}
        write_text_whole(args.json, json.dumps(report, indent=2))


if __name__ == "__main__":
    run_script(main)
