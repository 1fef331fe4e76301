"""Measurement (issue 31, item 2): each object's depth from ``estimate_obstacle_depth`` under
``PipelineConfig(differentiable=True)`` against the hard pipeline's in the same call (``result.hard_depth``), on the
28 held-out shared scenes (middlebury_2005_2006_third and middlebury_2003_quarter, ``paper_table1.split_scenes``) at
320×240 and at native size, for the default (the nearness segmenter), the paper's Otsu and the learned segmenter.
Prints, per setting, the share of ranged objects whose differentiable median depth is within 0.5 % of the hard one,
and the quantiles of |relative difference| (median, low and high percentile, the nearest obstacle's depth).

    python experiments/differentiable_agreement.py [--threads 2] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import torch

from svs_torch.core.files import write_bytes_atomic
from svs_torch.data import collate_stereo_batches, resize_stereo_batch
from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth
from svs_torch.segmentation.network_files import load_obstacle_net
from svs_torch.segmentation.segment import SegmentationConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
from paper_table1 import load_scene, split_scenes  # noqa: E402
from svs_torch.cli.common import positive_int  # noqa: E402
from run_metadata import add_data_option, output_path, run_metadata, run_script  # noqa: E402

QUANTILES = (0.5, 0.9, 0.95, 0.99, 1.0)


def relative_differences(batch, config, net, chunk: int = 8) -> dict[str, list[float]]:
    """|soft − hard| / hard over every valid object (and each pair's nearest obstacle), in chunks of pairs."""
    found: dict[str, list[float]] = {"median": [], "low": [], "high": [], "nearest": []}
    for start in range(0, batch.batch_size, chunk):
        part = batch.select(torch.arange(start, min(start + chunk, batch.batch_size)))
        part = replace(part, left=part.left.clone().requires_grad_(), right=part.right.clone().requires_grad_())
        result = estimate_obstacle_depth(part, config, network=net)
        soft, hard = result.depth.objects, result.hard_depth.objects
        valid = hard.valid
        for key, field in (("median", "depth_median_m"), ("low", "depth_low_m"), ("high", "depth_high_m")):
            a, b = getattr(soft, field).detach()[valid], getattr(hard, field)[valid]
            found[key] += ((a - b).abs() / b).tolist()
        near = result.hard_depth.nearest
        a, b = result.depth.nearest.depth_m.detach()[near.valid], near.depth_m[near.valid]
        found["nearest"] += ((a - b).abs() / b).tolist()
    return found


def summary(values: list[float]) -> dict:
    t = torch.tensor(values, dtype=torch.float64)
    if not len(values):
        return {"count": 0}
    return {"count": len(values), "within_0.5pct": float((t <= 0.005).double().mean() * 100),
            **{f"q{int(q * 100)}": float(t.quantile(q)) for q in QUANTILES}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_option(parser)
    parser.add_argument("--threads", type=positive_int, default=2, help="torch threads (default: %(default)s)")
    parser.add_argument("--json", type=output_path, metavar="FILE", help="write the report as JSON to FILE")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    scenes = split_scenes(Path(args.data))["held-out"]
    pairs = [load_scene(path) for path in scenes]
    sizes = {"320x240": collate_stereo_batches([resize_stereo_batch(p, (320, 240)) for p in pairs]),
             "native": collate_stereo_batches(pairs, mode="pad")}
    net = load_obstacle_net()
    configs = {"default": (PipelineConfig(differentiable=True), None),
               "otsu": (PipelineConfig(differentiable=True, segmentation=SegmentationConfig(segmenter="otsu")), None),
               "learned": (PipelineConfig(differentiable=True, segmentation=SegmentationConfig(segmenter="learned")),
                           net)}
    report = {}
    print(f"{len(scenes)} held-out scenes; |differentiable - hard| / hard per object")
    for size, batch in sizes.items():
        for name, (config, network) in configs.items():
            found = relative_differences(batch, config, network)
            report[f"{name}_{size}"] = {key: summary(values) for key, values in found.items()}
            for key, stats in report[f"{name}_{size}"].items():
                if not stats["count"]:
                    continue
                print(f"  {name:8s} {size:8s} {key:8s} n={stats['count']:3d}  within 0.5 %: "
                      f"{stats['within_0.5pct']:5.1f} %  " + "  ".join(
                          f"q{int(q * 100)} {stats[f'q{int(q * 100)}'] * 100:.3f} %" for q in QUANTILES))
    if args.json:
        write_bytes_atomic(args.json, json.dumps({"metadata": run_metadata(args.threads), "results": report},
                                                 indent=2).encode())


if __name__ == "__main__":
    run_script(main)
