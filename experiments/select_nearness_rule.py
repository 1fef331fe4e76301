"""Choose the nearness segmenter's measurement and keep rule on the tuned scenes only (issue 32).

With an untrained correction network (its head is zero: the segmenter is then the rule alone, the Otsu split of
the measured disparity), every combination of working width, SAD window, keep rule and least area is scored on
the training scenes (the ``tuned`` split of experiments/paper_table1.py without ArtL and Teddy, which duplicate
held-out scenes: ``train_segmentation.train_scenes``) at 320 px and at native size: the left kept mask's IoU with the
truth obstacles, and the Acc (Eq. (9)) of the truth's depth over the nearer kept region (segmentation alone, no
ranging). The held-out split is never read. The best mean of IoU and Acc / 100 over both sizes among the rules that
keep by nearness is printed last.

    python experiments/select_nearness_rule.py [--markdown FILE]
"""

from __future__ import annotations

import argparse
import itertools
import statistics
import sys
from pathlib import Path

import torch

from svs_torch.core.types import StereoBatch
from svs_torch.depth.quantiles import kept_region_lower_median
from svs_torch.segmentation.learned import ObstacleTruth, mask_iou, obstacle_truth
from svs_torch.segmentation.nearness import NearnessNet, NearnessNetConfig, segment_stereo_nearness
from svs_torch.segmentation.segment import SegmentationConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
from paper_table1 import load_scene, resample  # noqa: E402
from run_metadata import add_data_option, output_path, run_script, use_two_threads, write_text_whole  # noqa: E402
from train_segmentation import train_scenes  # noqa: E402

GRID = {"working_width_px": (160, 240, 320), "window_size": (7, 9, 13)}
KEEP = [("largest", 0.0), ("nearest", 0.001), ("nearest", 0.003), ("nearest", 0.01), ("nearest_first", 0.003),
        ("nearest_first", 0.01)]


def segmentation_scores(batch: StereoBatch, truth: ObstacleTruth, config: SegmentationConfig, net: NearnessNet
                        ) -> tuple[float, float]:
    """The IoU of the left kept mask with the truth obstacles and the segmentation-only nearest Acc (Eq. (9), %):
    the truth's depth median over the nearer kept region against ``truth.nearest_m`` (0 when nothing is kept). One
    pair (B = 1) whose truth has a nearest obstacle (``truth.nearest_valid``)."""
    seg = segment_stereo_nearness(batch, config, net).left
    depth, known = batch.ground_truth_depth_m()
    median, count = kept_region_lower_median(depth, known, seg.labels, seg.kept_labels)
    near = torch.where(count > 0, median, torch.inf).amin(1)
    real = float(truth.nearest_m[0])
    acc = max(0.0, 100 * (1 - abs(real - float(near[0])) / real)) if bool(torch.isfinite(near[0])) else 0.0
    return float(mask_iou(seg.kept_mask, truth.kept_mask)[0]), acc


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_option(parser)
    parser.add_argument("--markdown", type=output_path, metavar="FILE", help="write the table as Markdown to FILE")
    args = parser.parse_args(argv)
    use_two_threads()
    scenes = []
    for size in ("320", "native"):
        for path in train_scenes(Path(args.data)):
            batch = resample(load_scene(path), size)
            truth = obstacle_truth(batch)
            if bool(truth.nearest_valid[0]):
                scenes.append((size, batch, truth))
    lines = ["| working width px | window | keep | least area | IoU 320 | Acc 320 % | IoU native | Acc native % |",
             "|---|---|---|---|---|---|---|---|"]
    best = None
    for width, window in itertools.product(*GRID.values()):
        net = NearnessNet(NearnessNetConfig(working_width_px=width, window_size=window)).eval()
        for keep, area in KEEP:
            config = SegmentationConfig(segmenter="nearness", keep=keep, min_area_fraction=area)
            scores = {"320": ([], []), "native": ([], [])}
            for size, batch, truth in scenes:
                iou, acc = segmentation_scores(batch, truth, config, net)
                scores[size][0].append(iou)
                scores[size][1].append(acc)
            means = {size: (statistics.mean(v[0]), statistics.mean(v[1])) for size, v in scores.items()}
            lines.append(f"| {width} | {window} | {keep} | {area} | {means['320'][0]:.3f} | {means['320'][1]:.1f} | "
                         f"{means['native'][0]:.3f} | {means['native'][1]:.1f} |")
            print(lines[-1], flush=True)
            score = statistics.mean(m[0] + m[1] / 100 for m in means.values())
            # Only a rule that keeps by nearness can be chosen: the second requirement (a small near
            # obstacle is never dropped for a large far wall). "largest" is scored beside them for reference: the
            # truth keeps the two largest regions, so it is favoured by construction.
            if keep != "largest" and (best is None or score > best[0]):
                best = (score, width, window, keep, area)
    lines.append(f"\nbest keeping by nearness (mean of IoU + Acc/100 over both sizes): working width {best[1]} px, "
                 f"window {best[2]}, keep {best[3]}, least area {best[4]} (score {best[0]:.3f})")
    print(lines[-1])
    if args.markdown:
        write_text_whole(args.markdown, "\n".join(lines) + "\n")


if __name__ == "__main__":
    run_script(main)
