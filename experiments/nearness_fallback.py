"""How much of a view the nearness segmenter's block matcher accepts: real pairs against views of two scenes (issue 32).

The nearness segmenter ranks regions by a disparity measured by SAD block matching with left–right and uniqueness
rejections. Between views of two different scenes (a swapped, frozen or misconnected camera) some windows still
match by chance, and the segmenter keeps exactly those as "near" regions, which the dense stage then ranges
(16 of 80 such pairs got an object ranged, against none with Otsu's regions). The share of the left view the block
matcher accepts separates the two; below ``SegmentationConfig.min_measured_share`` a pair falls back to Otsu and
the paper's two largest regions.

Scenes: every shared pair outside the held-out split of experiments/paper_table1.py (MiddEval3, Middlebury 2001,
KITTI, the OpenCV sample), at 320×240. Positives: each pair clean, and as real_rig.py's camera frames at the SVS's
worst quality digit (8) with Gaussian noise of σ 8 levels in each view. Negatives: the left view of one scene with
the right view of another, every ordered pair of distinct scenes (one scene under two names, such as Piano /
PianoL, is not paired: verify_views.SAME_SCENE). The default threshold: the value of the grid farthest from both
the largest negative and the smallest positive (clean or JPEG): a real pair keeps the nearness segmenter, a pair
of two scenes does not.

    python experiments/nearness_fallback.py [--markdown FILE]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from svs_torch.data import camera_frame_pairs, list_shared_pairs, load_stereo_pair, resize_stereo_batch
from svs_torch.segmentation.nearness import NearnessNetConfig, measure_nearness_disparity

sys.path.insert(0, str(Path(__file__).resolve().parent))
from paper_table1 import is_held_out  # noqa: E402
from verify_views import SAME_SCENE  # noqa: E402
from run_metadata import add_data_option, output_path, run_script, use_two_threads, write_text_whole  # noqa: E402

# Steps of 0.025: with the denoised measurement (select_nearness_denoise.md) the gap between views of two scenes
# and the worst camera frames is 0.04 wide.
GRID = tuple(round(0.1 + 0.025 * i, 3) for i in range(13))


def accepted_share(left: torch.Tensor, right: torch.Tensor) -> float:
    return float(measure_nearness_disparity(left, right, NearnessNetConfig()).matched_share[0])


def main(argv: list[str] | None = None) -> float:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_option(parser)
    parser.add_argument("--markdown", type=output_path, metavar="FILE", help="write the table as Markdown to FILE")
    args = parser.parse_args(argv)
    use_two_threads()
    paths = [p for p in list_shared_pairs(Path(args.data)) if not is_held_out(p)]
    pairs = [resize_stereo_batch(load_stereo_pair(p), (320, 240)) for p in paths]
    generator = torch.Generator().manual_seed(0)
    clean = [accepted_share(b.left, b.right) for b in pairs]
    jpeg = [accepted_share(frames.left, frames.right)
            for frames in (camera_frame_pairs(b, 8, 8.0, generator) for b in pairs)]
    scene = [SAME_SCENE.get(p.name, p.name) for p in paths]
    negative = [accepted_share(pairs[i].left, pairs[j].right) for i in range(len(pairs)) for j in range(len(pairs))
                if scene[i] != scene[j]]
    quantiles = (lambda v: " / ".join(f"{q:.3f}" for q in np.quantile(v, [0, 0.05, 0.5, 0.95, 1])))
    lines = [f"# Accepted share of the left view: {len(pairs)} pairs outside the held-out split, 320×240", "",
             "Made by `python experiments/nearness_fallback.py" + (f" --markdown {args.markdown}`" if args.markdown
                                                                   else "`"), "",
             "| pairs | count | min / 5 % / median / 95 % / max |", "|---|---|---|",
             f"| clean | {len(clean)} | {quantiles(clean)} |",
             f"| JPEG quality 20 + noise σ 8 | {len(jpeg)} | {quantiles(jpeg)} |",
             f"| views of two scenes | {len(negative)} | {quantiles(negative)} |", "",
             "| threshold | clean below (Otsu instead) | JPEG below | views of two scenes below |", "|---|---|---|---|"]
    share = (lambda values, t: f"{np.mean(np.array(values) < t) * 100:.1f} %")
    for t in GRID:
        lines.append(f"| {t} | {share(clean, t)} | {share(jpeg, t)} | {share(negative, t)} |")
    chosen = max(GRID, key=lambda t: min(min(clean + jpeg) - t, t - max(negative)))
    lines += ["", f"chosen: {chosen} (the farthest from both the largest negative and the smallest real pair)"]
    print("\n".join(lines))
    if args.markdown:
        write_text_whole(args.markdown, "\n".join(lines) + "\n")
    return chosen


if __name__ == "__main__":
    run_script(main)
