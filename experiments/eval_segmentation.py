"""Otsu against the learned segmenter on the held-out scenes: mask IoU with the truth obstacles and the pipeline's
nearest-obstacle accuracy (issue 13).

Truth (:func:`svs_torch.learned_segmentation.obstacle_truth`): Otsu of the valid GT disparity (near against far),
5×5 opening, the two largest regions; the nearest obstacle's distance is the median GT depth over the nearer of
them (scenes without a shipped calibration use the nominal one for truth and estimate alike, as in
experiments/paper_table1.py). Per scene:

- IoU of the left kept mask with the truth mask: Otsu (the paper's segmentation, the pipeline's default), the
  learned segmenter, and, as a reference that learns nothing, Otsu of the soft-argmin disparity the network
  sees (its own input at 160 px, resized back);
- Acc (Eq. (9)) of the whole pipeline's ``nearest_m`` (default configuration, only the segmenter changed)
  against the truth distance; a pair that is not OK, or without a nearest obstacle, counts 0 %.

Scenes: the held-out split of paper_table1.py (Middlebury 2005/2006 and 2003, never trained on; their duplicates
ArtL and Teddy are left out of training, see train_segmentation.py), at 320 px wide (the SVS's size) by default.

    python experiments/eval_segmentation.py [--weights FILE] [--splits held-out] [--sizes 320]
                                            [--markdown table.md] [--json out.json]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # see bench_ransac.py: spinning OpenMP threads on a shared CPU

import argparse
import dataclasses
import json
import statistics
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

from svs_torch.cli.progress import Progress
from svs_torch.evaluation import accuracy_pct
from svs_torch.learned_segmentation import (SHIPPED_WEIGHTS, load_obstacle_net, mask_iou, obstacle_truth,
                                            segment_stereo_learned, stereo_features)
from svs_torch.pipeline import PipelineConfig, PipelineStatus, estimate_obstacle_depth
from svs_torch.segmentation import SegmentationConfig, segment_stereo

sys.path.insert(0, str(Path(__file__).resolve().parent))
from paper_table1 import load_scene, resample, split_scenes  # noqa: E402
from run_metadata import default_data_dir, run_metadata  # noqa: E402


def disparity_otsu_mask(batch, net_config) -> torch.Tensor:
    """The reference without learning: the truth's own rule applied to the network's input disparity."""
    _, disparity = stereo_features(batch.left, batch.right, net_config)
    disparity = F.interpolate(disparity, size=batch.size_hw, mode="bilinear", align_corners=False)
    estimated = dataclasses.replace(batch, disparity_px=disparity, disparity_valid=torch.ones_like(disparity,
                                                                                                  dtype=torch.bool))
    return obstacle_truth(estimated).kept_mask


def nearest_accuracy(batch, config: PipelineConfig, real_m: float) -> tuple[float, float | None, str]:
    result = estimate_obstacle_depth(batch, config)
    status = PipelineStatus(int(result.status[0])).name
    nearest = result.depth.nearest
    estimate = float(nearest.depth_m[0]) if status == "OK" and bool(nearest.valid[0]) else None
    return accuracy_pct(real_m, estimate), estimate, status


def evaluate_scene(path: Path, size: str, weights: str, net) -> dict | None:
    batch = resample(load_scene(path), size)
    truth = obstacle_truth(batch)
    if not bool(truth.nearest_valid[0]):
        return None
    real = float(truth.nearest_m[0])
    row = {"scene": batch.names[0] if batch.names else path.name, "size": size, "truth_nearest_m": real,
           "truth_area_share": float(truth.kept_mask.float().mean())}
    learned_config = SegmentationConfig(segmenter="learned:" + weights)
    for name, seg in (("otsu", segment_stereo(batch)), ("learned", segment_stereo_learned(batch, learned_config, net))):
        row[f"iou_{name}"] = float(mask_iou(seg.left.kept_mask, truth.kept_mask)[0])
    row["iou_disparity_otsu"] = float(mask_iou(disparity_otsu_mask(batch, net.config), truth.kept_mask)[0])
    for name, seg_config in (("otsu", SegmentationConfig()), ("learned", learned_config)):
        acc, estimate, status = nearest_accuracy(batch, PipelineConfig(segmentation=seg_config), real)
        row.update({f"acc_{name}": acc, f"nearest_{name}_m": estimate, f"status_{name}": status})
    return row


def markdown(rows: list[dict]) -> str:
    def number(value: float | None, digits: int) -> str:
        return "—" if value is None else f"{value:.{digits}f}"

    lines = ["| scene | size | IoU Otsu | IoU learned | IoU disparity-Otsu (ref.) | truth nearest m | "
             "Otsu nearest m | learned nearest m | Acc Otsu % | Acc learned % |", "|" + "---|" * 10]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['size']} | {r['iou_otsu']:.3f} | {r['iou_learned']:.3f} | "
                     f"{r['iou_disparity_otsu']:.3f} | {r['truth_nearest_m']:.3f} | {number(r['nearest_otsu_m'], 3)} | "
                     f"{number(r['nearest_learned_m'], 3)} | {r['acc_otsu']:.1f} | {r['acc_learned']:.1f} |")
    for size in sorted({r["size"] for r in rows}):
        group = [r for r in rows if r["size"] == size]
        means = {key: statistics.mean(r[key] for r in group)
                 for key in ("iou_otsu", "iou_learned", "iou_disparity_otsu", "acc_otsu", "acc_learned")}
        lines.append(f"| **mean of {len(group)}** | {size} | **{means['iou_otsu']:.3f}** | "
                     f"**{means['iou_learned']:.3f}** | {means['iou_disparity_otsu']:.3f} | | | | "
                     f"**{means['acc_otsu']:.1f}** | **{means['acc_learned']:.1f}** |")
    return "\n".join(lines)


def wins(rows: list[dict]) -> str:
    """One line per size: where the learned segmenter beats Otsu, and where it is worse."""
    lines = []
    for size in sorted({r["size"] for r in rows}):
        group = [r for r in rows if r["size"] == size]
        iou = sum(r["iou_learned"] > r["iou_otsu"] for r in group)
        acc = sum(r["acc_learned"] > r["acc_otsu"] for r in group)
        worse = [r["scene"] for r in group if r["acc_learned"] < r["acc_otsu"] - 1.0]
        lines.append(f"at {size}: learned beats Otsu on IoU in {iou} of {len(group)} scenes and on nearest Acc in "
                     f"{acc}; nearest Acc more than 1 point worse on: {', '.join(worse) or 'none'}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default=default_data_dir())
    parser.add_argument("--weights", default=str(SHIPPED_WEIGHTS), help="weights file (default: the shipped one)")
    parser.add_argument("--splits", default="held-out", help="comma-separated: held-out, tuned")
    parser.add_argument("--sizes", default="320", help="comma-separated: a width in pixels, or native")
    parser.add_argument("--limit", type=int, default=0, help="only the first N scenes of each split (0: all)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--markdown", metavar="FILE")
    parser.add_argument("--json", metavar="FILE")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    net = load_obstacle_net("learned:" + args.weights)
    scenes = split_scenes(Path(args.data))
    report = {"metadata": {**run_metadata(args.threads), "weights": args.weights,
                           "weights_metadata": torch.load(args.weights, weights_only=True)["metadata"]}, "tables": {}}
    text = []
    for split in args.splits.split(","):
        paths = scenes[split][:args.limit] if args.limit else scenes[split]
        jobs = [(path, size) for size in args.sizes.split(",") for path in paths]
        rows, skipped = [], []
        for path, size in Progress(len(jobs), split, unit="scene").over(jobs):
            row = evaluate_scene(path, size, args.weights, net)
            (rows.append(row) if row else skipped.append(path.name))
        text += [f"## {split}", "", markdown(rows), "", wins(rows),
                 f"scenes without a truth distance (counted, not scored): {skipped or 'none'}", ""]
        report["tables"][split] = {"rows": rows, "skipped": skipped}
    print("\n".join(text))
    if args.markdown:
        Path(args.markdown).write_text("\n".join(text))
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2, default=str))
    return report


if __name__ == "__main__":
    main()
