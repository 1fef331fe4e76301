"""Which kept object is the nearest obstacle: the one of smallest median depth, or of nearest surface? (issue 32)

The pipeline names the nearest obstacle as the valid object of smallest median depth and speaks that object's
nearest visible surface, its 10th depth percentile (:func:`svs_torch.depth.sparse.nearest_obstacle`,
``NearestObstacle.surface_m``). A walker meets the nearest surface first, so ranking the objects by that percentile
instead could name an obstacle whose body lies farther but whose front is nearer (a slanted piano beside a box).
This scores both rules on the same pipeline results (the default configuration; the rules only pick among the
objects it measured), per scene of the tuned and held-out splits of experiments/paper_table1.py, clean and as the
board's camera frames at digits 4 and 8 (the noise experiments/real_rig.py pairs with each, seeded by the scene's
index), against a walker's truth (:func:`svs_torch.segmentation.learned.obstacle_truth` with the true disparity's
ground plane left out, as ``eval_segmentation.py --truth walker``):

- **median Acc**: Eq. (9) of the chosen object's median depth against the nearer truth region's median (the
  issue's score);
- **warning Acc**: the chosen object's surface against the same truth region's 10th percentile (what guide says);
- **surface Acc**: the chosen object's surface against the nearest surface of any truth region (the walker's
  first contact).

A pair without an OK status or a valid object scores 0. About 1 minute at 320 px on a 2-core machine.

    python experiments/nearest_rule.py [--sizes 320] [--markdown FILE] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from paper_table1 import load_scene, resample, split_scenes  # noqa: E402
from real_rig import JPEG_NOISE  # noqa: E402
from run_metadata import (add_data_option, command_line, output_path, run_metadata, run_script,  # noqa: E402
                          size_list, write_text_whole)

from svs_torch.cli.progress import Progress  # noqa: E402
from svs_torch.data import camera_frame_pairs  # noqa: E402
from svs_torch.evaluation import accuracy_pct  # noqa: E402
from svs_torch.pipeline import PipelineConfig, PipelineStatus, estimate_obstacle_depth  # noqa: E402
from svs_torch.segmentation.ground_plane import GroundPlaneConfig  # noqa: E402
from svs_torch.segmentation.learned import obstacle_truth  # noqa: E402

DIGITS = (None, 4, 8)
RULES = ("median", "surface")
SCORES = ("median", "warning", "surface")


def truth_regions(batch) -> list[tuple[float, float]] | None:
    """(median, 10th percentile) of the GT depth over each walker's truth region, None where it has none."""
    truth = obstacle_truth(batch, floor=GroundPlaneConfig())
    if not bool(truth.nearest_valid[0]):
        return None
    depth, known = batch.ground_truth_depth_m()
    regions = []
    for slot in range(truth.kept_labels.shape[1]):
        if bool(truth.region_valid[0, slot]):
            values = depth[0, 0][(truth.labels[0, 0] == truth.kept_labels[0, slot]) & known[0, 0]].double()
            regions.append((float(values.median()), float(torch.quantile(values, 0.1))))
    return regions


def scene_row(batch, regions: list[tuple[float, float]]) -> dict:
    """Both rules' choice among one pair's measured objects, and their scores (module docstring)."""
    result = estimate_obstacle_depth(batch, PipelineConfig())
    ok = PipelineStatus(int(result.status[0])) == PipelineStatus.OK
    objects = result.depth.objects
    nearer = min(regions)  # the nearer truth region, by its median
    row = {"truth_median_m": nearer[0], "truth_warning_m": nearer[1], "truth_surface_m": min(r[1] for r in regions)}
    for rule, key in zip(RULES, (objects.depth_median_m, objects.depth_low_m)):
        candidates = torch.where(objects.valid[0], key[0], torch.inf)
        chosen = int(candidates.argmin()) if ok and bool(torch.isfinite(candidates).any()) else None
        median = None if chosen is None else float(objects.depth_median_m[0, chosen])
        surface = None if chosen is None else float(objects.depth_low_m[0, chosen])
        row.update({f"{rule}_slot": chosen, f"{rule}_median_m": median, f"{rule}_surface_m": surface,
                    f"{rule}_acc_median": accuracy_pct(nearer[0], median),
                    f"{rule}_acc_warning": accuracy_pct(nearer[1], surface),
                    f"{rule}_acc_surface": accuracy_pct(row["truth_surface_m"], surface)})
    return row


def markdown(rows: list[dict]) -> str:
    lines = ["| split | size | frames | pairs | rules differ | " + " | ".join(
        f"{score} Acc %: {rule}" for score in SCORES for rule in RULES) + " |", "|---|---|---|---|---|" +
        "---|" * (len(SCORES) * len(RULES))]
    for key in dict.fromkeys((r["split"], r["size"], r["frames"]) for r in rows):
        group = [r for r in rows if (r["split"], r["size"], r["frames"]) == key]
        differ = sum(r["median_slot"] != r["surface_slot"] for r in group)
        means = [statistics.mean(r[f"{rule}_acc_{score}"] for r in group) for score in SCORES for rule in RULES]
        lines.append(f"| {' | '.join(map(str, key))} | {len(group)} | {differ} | "
                     + " | ".join(f"{m:.2f}" for m in means) + " |")
    differing = [r for r in rows if r["median_slot"] != r["surface_slot"]]
    lines += ["", "Pairs whose rules differ (truth: nearer region's median / its 10th percentile / nearest surface; "
              "each rule's choice: median / surface, metres):", ""]
    lines += [f"- {r['split']} {r['scene']} at {r['size']}, {r['frames']}: truth {r['truth_median_m']:.2f} / "
              f"{r['truth_warning_m']:.2f} / {r['truth_surface_m']:.2f}; " + "; ".join(
                  f"{rule} {r[f'{rule}_median_m'] or 0:.2f} / {r[f'{rule}_surface_m'] or 0:.2f}" for rule in RULES)
              for r in differing]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_option(parser)
    parser.add_argument("--sizes", type=size_list("width"), default="320",
                        help="comma-separated: a width in pixels, or native (default 320)")
    parser.add_argument("--markdown", type=output_path, metavar="FILE", help="write the table as Markdown to FILE")
    parser.add_argument("--json", type=output_path, metavar="FILE", help="write the rows as JSON to FILE")
    args = parser.parse_args(argv)
    torch.set_num_threads(2)
    scenes = split_scenes(Path(args.data))
    jobs = [(split, index, path, size) for size in args.sizes.split(",") for split in ("tuned", "held-out")
            for index, path in enumerate(scenes[split])]
    rows = []
    with torch.inference_mode():
        for split, index, path, size in Progress(len(jobs), "scenes", unit="scene").over(jobs):
            base = resample(load_scene(path), size)
            for digit in DIGITS:
                batch = base if digit is None else camera_frame_pairs(
                    base, digit, dict(JPEG_NOISE)[digit], torch.Generator().manual_seed(index))
                regions = truth_regions(batch)
                if regions is not None:
                    rows.append({"split": split, "scene": path.name, "size": size,
                                 "frames": "clean" if digit is None else f"digit {digit}",
                                 **scene_row(batch, regions)})
    table = markdown(rows)
    print(table)
    command = command_line("experiments/nearest_rule.py", argv)
    if args.markdown:
        write_text_whole(args.markdown, f"`{command}`\n\n{table}")
    if args.json:
        write_text_whole(args.json, json.dumps({"metadata": run_metadata(2, command=command), "rows": rows},
                                               indent=2))
    return rows


if __name__ == "__main__":
    run_script(main)
