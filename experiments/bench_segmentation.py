"""Benchmark: segmentation stage (paper Sec. 3.2) and connected components, svs_torch vs OpenCV vs kornia.

Real pairs from the shared data, resampled to 320×240 (the SVS default size). Every timing is the median of
several runs in this process, with the spread (min–max) and the thread count recorded; rivals run on the same
images in the same run. Prints a table and writes JSON with the run's metadata.

    python experiments/bench_segmentation.py [--threads 2] [--repeats 7] [--json out.json]
"""

from __future__ import annotations

import os

# Idle OpenMP threads that spin while another process holds the cores slow torch 10-30x on a shared machine.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse
import json
import statistics
import time
from pathlib import Path

import cv2
import kornia
import numpy as np
import torch

import svs_torch
from svs_torch.segmentation.components import connected_components_with_stats
from svs_torch.data import list_shared_pairs, load_stereo_pair, resize_stereo_batch
from svs_torch.segmentation.segment import SegmentationConfig, segment_stereo

from svs_torch.cli.common import positive_int
from run_metadata import add_data_option, output_path, run_metadata, run_script, write_text_whole

SIZE_WH = (320, 240)


def timed(fn, repeats: int, pairs: int = 1) -> dict:
    """Median and spread of ``repeats`` runs of ``fn`` (one warm-up run first), in milliseconds; with the
    median per pair when ``fn`` handles ``pairs`` pairs, and the counts of runs the median is of and of pairs a run."""
    fn()
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        runs.append((time.perf_counter() - start) * 1e3)
    median = statistics.median(runs)
    return {"median_ms": median, "min_ms": min(runs), "max_ms": max(runs), "ms_per_pair": median / pairs,
            "runs": repeats, "pairs": pairs}


def load_pairs(data_dir: Path, count: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``count`` real pairs at 320×240 (repeating the shared set if needed): left, right ``(count, 1, H, W)``. A
    ``--data`` folder with no Middlebury pair is refused (an audit: a folder of KITTI alone, which ``--data`` takes,
    was "ValueError: torch.cat(): expected a non-empty list of Tensors"; a missing default, a line naming data_dir)."""
    from svs_torch.core.errors import InputError
    from svs_torch.data.scene_batch import named_folder

    if not Path(data_dir).is_dir():
        raise InputError(f"--data: expected the shared data folder, got {str(data_dir)!r}: no such folder")
    # Its data sets by their own folder's name: the whole path's held "middlebury" for every pair of a data folder
    # kept at /data/middlebury_work/shared, KITTI's timed as Middlebury's (an audit).
    # (named_folder: the folder as list_shared_pairs names its pairs, '..' resolved)
    paths = [p for p in list_shared_pairs(data_dir) if p.relative_to(named_folder(data_dir)).parts[0].startswith(
        "middlebury")]
    if not paths:
        raise InputError(f"--data: expected the shared data folder with Middlebury pairs (middlebury_*/), got "
                         f"{str(data_dir)!r}, which holds none")
    batches = [resize_stereo_batch(load_stereo_pair(p), SIZE_WH) for p in paths[:count]]
    left = torch.cat([b.left for b in batches])
    right = torch.cat([b.right for b in batches])
    repeat = -(-count // left.shape[0])
    return left.repeat(repeat, 1, 1, 1)[:count], right.repeat(repeat, 1, 1, 1)[:count]


def opencv_segment(gray: np.ndarray, kernel: np.ndarray, num_keep: int) -> np.ndarray:
    """The same stage in OpenCV: Otsu, erode, dilate, components with stats, keep the largest, mask."""
    _, binary = cv2.threshold(gray, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
    opened = cv2.dilate(cv2.erode(binary, kernel), kernel)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(opened, connectivity=8)
    keep = 1 + np.argsort(-stats[1:, cv2.CC_STAT_AREA], kind="stable")[:num_keep]
    return np.where(np.isin(labels, keep), gray, 0)


def to_u8(images: torch.Tensor) -> list[np.ndarray]:
    return list((images[:, 0] * 255).round().to(torch.uint8).numpy())


def bench(left: torch.Tensor, right: torch.Tensor, repeats: int) -> dict:
    config = SegmentationConfig()
    kernel = np.ones((config.kernel_size, config.kernel_size), np.uint8)
    results: dict[str, dict] = {}
    for b in (1, 32):
        batch = svs_torch.StereoBatch.from_images(left[:b], right[:b], 276.0, 0.1075)
        grays = to_u8(torch.cat([left[:b], right[:b]]))
        results[f"segment_pairs_svs_torch_B{b}"] = timed(lambda: segment_stereo(batch, config), repeats, b)
        results[f"segment_pairs_opencv_loop_B{b}"] = timed(
            lambda: [opencv_segment(g, kernel, config.num_keep) for g in grays], repeats, b)
        seg = segment_stereo(batch, config)
        masks = torch.cat([seg.left.opened, seg.right.opened])
        masks_u8 = [m.astype(np.uint8) for m in masks[:, 0].numpy()]
        results[f"components_images_svs_torch_B{b}"] = timed(lambda: connected_components_with_stats(masks), repeats, b)
        results[f"components_images_opencv_loop_B{b}"] = timed(
            lambda: [cv2.connectedComponentsWithStats(m, connectivity=8) for m in masks_u8], repeats, b)
        if b == 1:
            float_masks = masks.to(torch.float32)
            results["components_images_kornia_unionfind_B1"] = timed(
                lambda: kornia.contrib.connected_components_union_find(float_masks), max(3, repeats // 2))
            results["components_images_kornia_maxpool100_B1"] = timed(
                lambda: kornia.contrib.connected_components(float_masks, num_iterations=100), 3)
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_option(parser)
    parser.add_argument("--threads", type=positive_int, default=2, help="torch and OpenCV threads (default: 2)")
    parser.add_argument("--repeats", type=positive_int, default=7, help="timed runs per measurement (median reported)")
    parser.add_argument("--json", type=output_path, metavar="FILE", help="also write the results and metadata as JSON")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    left, right = load_pairs(Path(args.data), 32)
    results = bench(left, right, args.repeats)
    print(f"threads {args.threads}, {SIZE_WH[0]}x{SIZE_WH[1]}, median of {args.repeats} runs (min-max)")
    ratios = {}  # the ratios printed, kept in the JSON too (a script reads them, not works them out)
    for b in (1, 32):
        ours = results[f"segment_pairs_svs_torch_B{b}"]["median_ms"] / b
        theirs = results[f"segment_pairs_opencv_loop_B{b}"]["median_ms"] / b
        ratios[f"segment_pairs_B{b}_svs_torch_over_opencv"] = round(ours / theirs, 3)
        print(f"segmentation  B={b:2d}: svs_torch {ours:7.3f} ms/pair   OpenCV loop {theirs:7.3f} ms/pair   "
              f"ratio svs_torch/OpenCV {ours / theirs:5.2f}")
    for b in (1, 32):
        images = 2 * b
        ours = results[f"components_images_svs_torch_B{b}"]["median_ms"] / images
        theirs = results[f"components_images_opencv_loop_B{b}"]["median_ms"] / images
        ratios[f"components_images_B{b}_svs_torch_over_opencv"] = round(ours / theirs, 3)
        print(f"components    B={b:2d}: svs_torch {ours:7.3f} ms/image  OpenCV loop {theirs:7.3f} ms/image  "
              f"ratio svs_torch/OpenCV {ours / theirs:5.2f}")
    for name in ("unionfind", "maxpool100"):
        kornia_ms = results[f"components_images_kornia_{name}_B1"]["median_ms"] / 2
        ours = results["components_images_svs_torch_B1"]["median_ms"] / 2
        runs = results[f"components_images_kornia_{name}_B1"]["runs"]  # (its own count: each run is slow)
        ratios[f"components_images_B1_kornia_{name}_over_svs_torch"] = round(kornia_ms / ours, 3)
        print(f"components    B= 1: kornia {name:10s} {kornia_ms:8.3f} ms/image  ratio kornia/svs_torch "
              f"{kornia_ms / ours:6.1f}  (median of {runs} runs)")
    report = {"metadata": run_metadata(args.threads, size_wh=list(SIZE_WH)), "results": results, "ratios": ratios}
    if args.json:
        write_text_whole(args.json, json.dumps(report, indent=2))


if __name__ == "__main__":
    run_script(main)
