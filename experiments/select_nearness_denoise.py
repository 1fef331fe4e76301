"""Choose how the nearness segmenter cleans its disparity for camera frames, on the train scenes only (issue 33).

A real SVS sends JPEG frames with sensor noise in each camera. On such frames the nearness segmenter's block
matcher (:func:`svs_torch.segmentation.nearness.measure_nearness_disparity`) accepts windows of noise in flat
areas, and its map, filled along the rows, turns into specks and one-row streaks: the Otsu split moves onto them
and the kept "nearest" regions are a few hundred pixels of noise (Shelves at 320×240, JPEG digit 1 with σ 2: the
split moves from 14 to 31 px, the kept regions shrink from 21 065 to 225 px).

Every combination of SAD window, uniqueness ratio and median window (on the halved map) is scored with the shipped
keep rule (``PipelineConfig().segmentation``) on the training scenes (``train_segmentation.train_scenes``: the
held-out split is never read) at 320 px and native size, each scene clean and as real_rig.py's eight camera frames
(every JPEG quality digit of the board with its noise σ), by select_nearness_rule.py's measures: the left kept
mask's IoU with the truth obstacles and the segmentation-only nearest Acc. The score is the mean, over the four
groups (two sizes, clean or camera frames), of IoU + Acc / 100; the best is printed last.

Synthetic scenes with weakly textured surfaces (``texture_contrast`` 0.3, at 320×240, clean and as the same camera
frames) are reported beside them, not scored. The train scenes are richly textured and lose little to JPEG, while
the camera's worst digits wipe out the texture of plain fronts, and these scenes show that failure; but their
fronts are bright boxes on a dark wall, where any segmenter does well once it keeps something, and scored they
chose a window of 9 and a uniqueness of 0.3, which lost 0.04 IoU on the train scenes' clean frames at 320 px.
The segmenter's fallback to Otsu for views of two scenes (``min_measured_share``) is off while scoring: it is a
safety net for a misconnected camera (experiments/nearness_fallback.md), and with it a stricter matcher would be
scored on Otsu's regions.

    python experiments/select_nearness_denoise.py [--limit N] [--markdown FILE]

``--limit N`` scores the first N train scenes and N synthetic scenes only: a quick look at the grid (the whole
run takes minutes a combination), never a selection.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import statistics
import sys
from pathlib import Path

from svs_torch.segmentation.learned import obstacle_truth
from svs_torch.segmentation.nearness import NearnessNet, NearnessNetConfig
from svs_torch.cli.common import positive_int
from svs_torch.core.files import write_bytes_atomic
from svs_torch.pipeline import PipelineConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
from paper_table1 import load_scene, resample  # noqa: E402
import real_rig  # noqa: E402
from real_rig import conditions  # noqa: E402
from run_metadata import add_data_option, command_line, output_path, run_script, use_two_threads  # noqa: E402
from select_nearness_rule import segmentation_scores  # noqa: E402
from train_segmentation import train_scenes  # noqa: E402

# Median window 1 (no median) lost in every row of the first selection (score 1.36–1.47 against 1.53–1.57).
GRID = {"window_size": (7, 9, 11), "uniqueness_ratio": (0.1, 0.2, 0.3, 0.4, 0.6), "median_window": (5, 7)}

#: The weak-texture synthetic scenes: real_rig.py's ``--splits synthetic``.
SYNTHETIC_SCENES, SYNTHETIC_CONTRAST = real_rig.SYNTHETIC_SCENES, real_rig.SYNTHETIC_TEXTURE_CONTRAST
LEGEND = (f"320 / native: the train scenes, clean or as the board's eight camera frames (scored); 320 weak: "
          f"{SYNTHETIC_SCENES} synthetic scenes at texture contrast {SYNTHETIC_CONTRAST} (reported, not scored: see "
          f"the script's docstring). The fallback to Otsu is off while scoring.")


def _frames(size: str, batch, index: int) -> list[tuple[str, str, object, object]]:
    """``(size, "clean" | "camera", batch, truth)`` of one pair clean and as real_rig.py's JPEG + noise frames
    (seeded by ``index``, as there); none when its truth has no nearest obstacle."""
    truth = obstacle_truth(batch)
    if not bool(truth.nearest_valid[0]):
        return []
    return [(size, "clean" if name == "clean" else "camera", dataclasses.replace(batch, left=left, right=right),
             truth) for name, left, right in conditions(batch, index) if name == "clean" or name.startswith("jpeg")]


def views(data_dir: Path, limit: int | None = None) -> list[tuple[str, str, object, object]]:
    """Every train scene at 320 px and native size, then the weak-texture synthetic scenes (size "320 weak"),
    each clean and as the camera frames (:func:`_frames`); the first ``limit`` of each when given."""
    out = []
    for size in ("320", "native"):
        for index, path in enumerate(train_scenes(data_dir)[:limit]):
            out += _frames(size, resample(load_scene(path), size), index)
    for index, pair in enumerate(real_rig.synthetic_scenes()[:limit]):
        out += _frames("320 weak", pair, index)
    return out


def main(argv: list[str] | None = None) -> tuple[float, dict]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_option(parser, Path)
    parser.add_argument("--limit", type=positive_int, metavar="N",
                        help="only the first N train and N synthetic scenes (a quick look, not a selection)")
    parser.add_argument("--markdown", type=output_path, metavar="FILE", help="write the table as Markdown to FILE")
    args = parser.parse_args(argv)
    use_two_threads()
    data = views(args.data, args.limit)
    keep = dataclasses.replace(PipelineConfig().segmentation, min_measured_share=0.0)  # (module docstring)
    groups = [(size, group) for size in ("320", "native", "320 weak") for group in ("clean", "camera")]
    scored = [g for g in groups if g[0] != "320 weak"]  # (module docstring)
    lines = ["| window | uniqueness | median | " + " | ".join(f"IoU / Acc % {s} {g}" for s, g in groups)
             + " | score |", "|---|---|---|" + "---|" * (len(groups) + 1)]
    best = None
    for values in itertools.product(*GRID.values()):
        settings = dict(zip(GRID, values))
        net = NearnessNet(dataclasses.replace(NearnessNetConfig(), **settings)).eval()
        scores: dict[tuple[str, str], list[tuple[float, float]]] = {g: [] for g in groups}
        for size, group, batch, truth in data:
            scores[(size, group)].append(segmentation_scores(batch, truth, keep, net))
        means = {g: (statistics.mean(s[0] for s in v), statistics.mean(s[1] for s in v)) for g, v in scores.items()}
        score = statistics.mean(means[g][0] + means[g][1] / 100 for g in scored)
        lines.append(f"| {values[0]} | {values[1]} | {values[2]} | "
                     + " | ".join(f"{means[g][0]:.3f} / {means[g][1]:.1f}" for g in groups) + f" | {score:.3f} |")
        print(lines[-1], flush=True)
        if best is None or score > best[0]:
            best = (score, settings)
    lines.append("\nbest (mean of IoU + Acc/100 over both sizes of the train scenes, clean and camera frames): "
                 + ", ".join(f"{k} {v}" for k, v in best[1].items()) + f" (score {best[0]:.3f})")
    if args.limit:
        lines[-1] += f" -- on the first {args.limit} scenes of each set only (--limit): a quick look, not a selection"
    print(lines[-1])
    if args.markdown:
        command = command_line("experiments/select_nearness_denoise.py", argv)
        text = f"`{command}`\n\n{LEGEND}\n\n" + "\n".join(lines) + "\n"
        write_bytes_atomic(Path(args.markdown), text.encode("utf-8"))
    return best


if __name__ == "__main__":
    run_script(main)
