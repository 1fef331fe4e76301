"""Does a camera's frame need the nearness segmenter's noise gate (``SegmentationConfig.camera_frames``)?

The nearness map of a pair is matched with a 7×7 window and, where that pass's matching residual reaches
``NearnessNetConfig.noisy_min_residual_levels`` (a camera frame's noise), matched again with an 11×11 window
(:mod:`svs_torch.segmentation.nearness_denoise`). A real SVS always sends JPEG frames with sensor noise; if the gate
widens every such frame anyway, ``guide`` can match with the wider window at once and save the first pass. Per
split, contrast and condition (real_rig.py's clean pair and its eight camera-frame conditions, JPEG digit D with
noise σ, seeded as there), at 320×240 (the SVS's size, which the segmenter matches unreduced):

- **widened**: the pairs whose residual reaches the gate (the decision the default takes);
- per object Acc (Eq. 9, real_rig.py's score) of the default pipeline and of the same with
  ``segmentation.camera_frames=true``, and the pairs whose result differs (any object's Acc).

Tuning data by default (the tuned split at full and half contrast, the rendered scenes). ``--splits held-out``
reports the held-out split; it chose nothing here.

    python experiments/camera_frames_gate.py [--splits tuned,synthetic] [--contrasts 1,0.5] [--limit N] [--markdown F]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_rig import conditions, dimmed, load_scene, resample, run, scene_splits  # noqa: E402
from svs_torch.cli.common import unit_interval_float  # noqa: E402
from run_metadata import (add_data_option, check_reports_apart, comma_list, command_line, output_path,  # noqa: E402
                          run_metadata, run_script, scene_limit, write_report)

from svs_torch.depth.block_matching import block_match_sad_with_residual  # noqa: E402
from svs_torch.depth.dense_config import DenseConfig  # noqa: E402
from svs_torch.pipeline import PipelineConfig  # noqa: E402
from svs_torch.segmentation.network_files import cached_obstacle_net  # noqa: E402

SIZE = "320x240"


def gate_decisions(scenes: list, contrast: float) -> dict[str, list[bool]]:
    """Per condition name, each scene's gate decision (the residual of the 7×7 pass reaches the gate)."""
    nearness = cached_obstacle_net(PipelineConfig().segmentation.segmenter).config
    dense = DenseConfig(window_size=nearness.window_size, uniqueness_ratio=nearness.uniqueness_ratio)
    out: dict[str, list[bool]] = {}
    for index, scene in enumerate(scenes):
        batch = scene if not isinstance(scene, Path) else resample(load_scene(scene), SIZE)
        batch = dimmed(batch, contrast)
        if batch.left.shape[-1] > nearness.working_width_px:
            raise SystemExit(f"{batch.names[0]}: wider than the working width; this measures unreduced pairs")
        count = max(2, math.ceil(nearness.max_disparity_fraction * batch.left.shape[-1]))
        for name, left, right in conditions(batch, index):
            if name == "clean" or name.startswith("jpeg"):
                residual = block_match_sad_with_residual(left, right, 0, count, dense)[1]
                out.setdefault(name, []).append(bool(residual[0] >= nearness.noisy_min_residual_levels))
    return out


def compare(splits: dict, contrast: float) -> list[dict]:
    """One row per (split, condition): the gate's decisions and both configurations' results."""
    gate = PipelineConfig()
    camera = dataclasses.replace(gate, segmentation=dataclasses.replace(gate.segmentation, camera_frames=True))
    only = ("clean", "jpeg")
    first = run(splits, [SIZE], gate, rival=False, only=only, contrast=contrast)
    second = run(splits, [SIZE], camera, rival=False, only=only, contrast=contrast)
    rows = []
    for split, scenes in splits.items():
        widened = gate_decisions(scenes, contrast)
        for name, decisions in widened.items():
            a = [r for r in first if r["split"] == split and r["condition"] == name]
            b = [r for r in second if r["split"] == split and r["condition"] == name]
            differ = sum(x["acc_objects"] != y["acc_objects"] for x, y in zip(a, b))
            rows.append({"split": split, "contrast": contrast, "condition": name, "pairs": len(decisions),
                         "widened": sum(decisions), "acc_gate": statistics.fmean(r["acc_objects"] for r in a),
                         "acc_camera_frames": statistics.fmean(r["acc_objects"] for r in b), "differ": differ})
    return rows


def markdown(rows: list[dict], command: str) -> str:
    lines = [f"`{command}`", "", "| split | contrast | condition | pairs | widened by the gate | Acc objects % gate | "
             "Acc objects % camera_frames | pairs with another result |", "|" + "---|" * 8]
    for r in rows:
        lines.append(f"| {r['split']} | {r['contrast']:g} | {r['condition']} | {r['pairs']} | {r['widened']} | "
                     f"{r['acc_gate']:.2f} | {r['acc_camera_frames']:.2f} | {r['differ']} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_data_option(parser, Path)
    parser.add_argument("--splits", default="tuned,synthetic",
                        help="comma-separated: held-out, tuned, or the rendered synthetic, synthetic-wall, "
                             "synthetic-plain, synthetic-border, synthetic-slant (default: %(default)s)")
    parser.add_argument("--contrasts", default="1,0.5", type=comma_list(unit_interval_float, "factors"),
                        help="the shared splits at each contrast (rendered: 1)")
    parser.add_argument("--limit", type=scene_limit, help="first N scenes of each split")
    parser.add_argument("--json", type=output_path, help="write the report as JSON to FILE")
    parser.add_argument("--markdown", type=output_path, help="write the table as Markdown to FILE")
    args = parser.parse_args(argv)
    check_reports_apart(parser, args)
    started = time.perf_counter()
    splits = scene_splits(args.data, args.splits.split(","), args.limit)
    rows = []
    for contrast in (float(c) for c in args.contrasts.split(",")):
        at_contrast = {k: v for k, v in splits.items() if k != "synthetic" or contrast == 1}
        if at_contrast:
            rows += compare(at_contrast, contrast)
    command = command_line("experiments/camera_frames_gate.py", argv)
    table = markdown(rows, command)
    print(table)
    report = {"metadata": run_metadata(torch.get_num_threads(), command=command,
                                        time_s=time.perf_counter() - started), "rows": rows}
    write_report(report, table, args.json, args.markdown)
    return rows


if __name__ == "__main__":
    run_script(main)
