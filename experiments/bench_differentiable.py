"""Benchmark (issue 31): ``estimate_obstacle_depth`` under ``PipelineConfig(differentiable=True)``, forward +
backward on B = 8 real pairs at 320×240, against the hard pipeline's forward on the same batch in the same run: the
default (the nearness segmenter), the paper's Otsu and the learned segmenter (gradients to both images, and to the
network's weights for the learned one). Median and spread of several runs, and per configuration the ratio of the
two medians (differentiable forward + backward time / hard forward time, both of svs_torch: no other library runs
this pipeline differentiably), peak memory of one forward + backward (how far the peak resident set rises above the
resident set before it, in a fresh process), thread count and load recorded.

    python experiments/bench_differentiable.py [--threads 2] [--repeats 5] [--batch 8] [--json out.json]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # spinning OpenMP threads on a shared CPU, see bench_ransac.py

import argparse
import json
import resource
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import torch

from svs_torch import StereoBatch
from svs_torch.segmentation.network_files import load_obstacle_net
from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth
from svs_torch.segmentation.segment import SegmentationConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
from svs_torch.cli.common import positive_int  # noqa: E402
from run_metadata import add_common_options, command_line, run_metadata, run_script, write_text_whole  # noqa: E402
from bench_segmentation import load_pairs, timed  # noqa: E402

#: What each configuration's ratio is, as the report prints it and its JSON's metadata says.
RATIOS = "differentiable forward + backward time / hard forward time (the two medians, same batch, same run)"


def forward_backward(batch: StereoBatch, config: PipelineConfig, net) -> None:
    """One differentiable run and the backward pass of a loss on every ranged object's depth and the nearest."""
    images = replace(batch, left=batch.left.clone().requires_grad_(), right=batch.right.clone().requires_grad_())
    result = estimate_obstacle_depth(images, config, network=net)
    objects = result.depth.objects
    loss = (objects.depth_median_m * objects.valid).sum() + result.depth.nearest.depth_m.sum()
    if loss.requires_grad:
        loss.backward()
    if net is not None:
        net.zero_grad(set_to_none=True)


def _status_mb(field: str) -> float:
    """A ``/proc/self/status`` memory field (``VmRSS``, ``VmHWM``), MB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    raise KeyError(field)


def configurations(net) -> dict:
    """The default pipeline (the nearness segmenter), the paper's Otsu and the learned segmenter."""
    otsu, learned = SegmentationConfig(segmenter="otsu"), SegmentationConfig(segmenter="learned")
    return {"default": (PipelineConfig(), None), "otsu": (PipelineConfig(segmentation=otsu), None),
            "learned": (PipelineConfig(segmentation=learned), net)}


def peak_growth_mb(batch: StereoBatch, config: PipelineConfig, net) -> float:
    """How much one differentiable forward + backward raises the process's peak resident set above its resident set
    before it, MB, after the hard path ran once (kernels built, kornia loaded, the network's forward done).

    The peak is reset first (``/proc/self/clear_refs``): a process started by another inherits the peak of the
    memory it was forked with (Linux keeps the old image's high-water mark across ``exec``), so ``ru_maxrss`` alone
    showed the parent's peak, and no growth, for the second configuration."""
    estimate_obstacle_depth(batch, config, network=net)
    try:
        Path("/proc/self/clear_refs").write_text("5")  # the peak resident set := the resident set now
    except OSError:  # not Linux: the peak since the process started, which the fresh process keeps small
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        forward_backward(batch, replace(config, differentiable=True), net)
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 - before
    before = _status_mb("VmRSS")
    forward_backward(batch, replace(config, differentiable=True), net)
    return _status_mb("VmHWM") - before


def fresh_peak_mb(args: argparse.Namespace, name: str) -> float:
    """:func:`peak_growth_mb` of configuration ``name`` in a fresh process: the peak resident set only shows what
    exceeds every earlier peak."""
    command = [sys.executable, __file__, "--data", args.data, "--threads", str(args.threads), "--batch",
               str(args.batch), "--peak-of", name]
    return float(subprocess.run(command, capture_output=True, text=True, check=True).stdout.split()[-1])


def print_report(args: argparse.Namespace, results: dict, ratios: dict) -> None:
    print(f"threads {args.threads}, B = {args.batch} real pairs at 320x240, median of {args.repeats} runs")
    for key, value in results.items():
        if isinstance(value, dict):
            print(f"  {key:34s} {value['median_ms'] / 1e3:7.3f} s  (min {value['min_ms'] / 1e3:.3f}, "
                  f"max {value['max_ms'] / 1e3:.3f})")
        else:
            print(f"  {key:34s} {value:9.1f} MB")
    print(f"ratio: {RATIOS}")
    for name, ratio in ratios.items():
        print(f"  {name:34s} {ratio:7.2f}")


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_options(parser, threads=2, repeats=5, json=True)
    parser.add_argument("--batch", type=positive_int, default=8, help="pairs per batched call (default: %(default)s)")
    parser.add_argument("--peak-of", choices=["default", "otsu", "learned"], help=argparse.SUPPRESS)  # a fresh process
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    left, right = load_pairs(Path(args.data), args.batch)
    batch = StereoBatch.from_images(left, right, 276.0, 0.1075)
    net = load_obstacle_net()
    if args.peak_of:
        print(peak_growth_mb(batch, *configurations(net)[args.peak_of]))
        return {}
    results, ratios = {}, {}
    for name, (config, network) in configurations(net).items():
        results[f"{name}_peak_growth_mb"] = fresh_peak_mb(args, name)
        hard = results[f"{name}_hard"] = timed(lambda: estimate_obstacle_depth(batch, config, network=network),
                                               args.repeats, pairs=args.batch)
        soft = results[f"{name}_differentiable_fwd_bwd"] = timed(
            lambda: forward_backward(batch, replace(config, differentiable=True), network), args.repeats,
            pairs=args.batch)
        ratios[f"{name}_differentiable_over_hard"] = soft["median_ms"] / hard["median_ms"]
    print_report(args, results, ratios)
    report = {"metadata": run_metadata(args.threads, command=command_line("experiments/bench_differentiable.py", argv),
                                       batch=args.batch, ratios=RATIOS), "results": results, "ratios": ratios}
    if args.json:
        write_text_whole(args.json, json.dumps(report, indent=2))
    return report


if __name__ == "__main__":
    run_script(main)
