"""The segmenters on the held-out scenes: mask IoU with the truth obstacles and the pipeline's nearest-obstacle
accuracy (issues 13 and 32): the default (the nearness segmenter), Otsu, the learned one, and OpenCV StereoSGBM's
disparity under the truth's own rule.

Truth (:func:`svs_torch.segmentation.learned.obstacle_truth`): Otsu of the valid GT disparity (near against far),
5×5 opening, the two largest regions; the nearest obstacle's distance is the median GT depth over the nearer of
them (scenes without a shipped calibration use the nominal one for truth and estimate alike, as in
experiments/paper_table1.py; a KITTI pair keeps its rig's focal and baseline). ``--truth walker``: a walker's truth
instead, the ground plane of the valid GT disparity (:mod:`svs_torch.segmentation.ground_plane`, the nearness
segmenter's own fit, here on the true disparity) left out before the split: for a walker the floor or the road
is not an obstacle (issue 32), and the issue's truth counts the floor of Motorcycle and Piano as one. Per scene:

- IoU of the left kept mask with the truth mask: the default (the nearness segmenter), Otsu (the paper's
  segmentation), the learned segmenter, SGBM, and with ``--reference``, as a reference that learns nothing, Otsu
  of the soft-argmin disparity the older network sees (its own input at 160 px, resized back);
- Acc (Eq. (9)) of the whole pipeline's ``nearest_m`` (default configuration, only the segmenter changed)
  against the truth distance; a pair that is not OK, or without a nearest obstacle, counts 0 %;
- the warning's Acc: the distance ``svs-depth guide`` speaks, the nearest object's nearest visible surface
  (``NearestObstacle.surface_m``, its :data:`WARNING_PERCENTILE`-th depth percentile), against the same percentile of
  the GT depth over the nearer truth region. A region that joins a near obstacle to the wall behind it has its median
  on the wall, and its near surface on the obstacle: the warning is what a walker hears, the median what the issue's
  table scores. SGBM's is the same percentile of its nearest region.

``--camera-frames D``: each scene's views made the frames a real SVS sends first, JPEG at the board's quality digit
D with the sensor noise experiments/real_rig.py pairs with it (``real_rig.JPEG_NOISE``; each view's own noise, seeded
by the scene's index in its split), the truth unchanged (it is the left view's): what a walker's warning rests on.

Scenes: the held-out split of paper_table1.py (Middlebury 2005/2006 and 2003, never trained on; their duplicates
ArtL and Teddy are left out of training, see train_segmentation.py), at 320 px wide (the SVS's size) by default.

    python experiments/eval_segmentation.py [--weights FILE] [--splits held-out] [--sizes 320]
                                            [--truth issue|walker] [--camera-frames D] [--set KEY=VALUE ...]
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
from svs_torch.data import camera_frame_pairs, list_shared_pairs
from svs_torch.depth import DepthConfig
from svs_torch.evaluation import accuracy_pct
from svs_torch.evaluation.overrides import apply_overrides, parse_assignment
from svs_torch.segmentation.ground_plane import GroundPlaneConfig
from svs_torch.segmentation.learned import mask_iou, obstacle_truth
from svs_torch.segmentation.network import stereo_features
from svs_torch.segmentation.network_files import SHIPPED_WEIGHTS, check_weights_file, load_obstacle_net
from svs_torch.pipeline import PipelineConfig, PipelineStatus, estimate_obstacle_depth
from svs_torch.segmentation.segment import SegmentationConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
from paper_table1 import load_scene, opencv_disparity, resample, split_scenes  # noqa: E402
from real_rig import JPEG_NOISE  # noqa: E402
from svs_torch.cli.common import positive_int  # noqa: E402
from svs_torch.core.errors import InputError  # noqa: E402
from run_metadata import (add_data_option, check_reports_apart, command_line, output_path, run_metadata,  # noqa: E402
                          run_script, scene_limit, size_list, write_text_whole)


def disparity_otsu_mask(batch, net_config) -> torch.Tensor:
    """The reference without learning: the truth's own rule applied to the old network's input disparity."""
    _, disparity = stereo_features(batch.left, batch.right, net_config)
    disparity = F.interpolate(disparity, size=batch.size_hw, mode="bilinear", align_corners=False)
    estimated = dataclasses.replace(batch, disparity_px=disparity, disparity_valid=torch.ones_like(disparity,
                                                                                                  dtype=torch.bool))
    return obstacle_truth(estimated).kept_mask


#: The depth percentile of the nearest object that guide speaks (``NearestObstacle.surface_m``).
WARNING_PERCENTILE = DepthConfig().object_percentiles[0]


def sgbm_rival(batch) -> tuple[torch.Tensor, float | None, float | None]:
    """The classical stereo-aware rival: the truth's own procedure (Otsu of the disparity, 5×5 opening, two
    largest regions) on OpenCV StereoSGBM's disparity (experiments/paper_table1.py's settings); its nearest
    obstacle is the smaller median SGBM depth of its two regions, its warning that region's
    :data:`WARNING_PERCENTILE`-th depth percentile. Returns the kept mask, the nearest and the warning (None: none)."""
    disparity = torch.from_numpy(opencv_disparity(batch, "sgbm"))
    disparity = disparity.view(1, 1, *disparity.shape)
    valid = disparity > 0
    truth = obstacle_truth(dataclasses.replace(batch, disparity_px=disparity, disparity_valid=valid))
    scale, doffs = float(batch.focal_px[0] * batch.baseline_m[0]), float(batch.doffs_px[0])
    regions = []  # (median depth, warning depth) of each kept region
    for label in truth.kept_labels[0].tolist():
        region = (truth.labels == label) & valid
        if label > 0 and bool(region.any()):
            values = disparity[region]
            regions.append((scale / (float(values.median()) + doffs),
                            float(torch.quantile(scale / (values.double() + doffs), WARNING_PERCENTILE / 100))))
    nearest = min(regions, default=(None, None))
    return truth.kept_mask, nearest[0], nearest[1]


def truth_warning_m(batch, truth) -> float:
    """The :data:`WARNING_PERCENTILE`-th percentile of the GT depth over the nearer truth region (the one whose
    depth is ``truth.nearest_m``), over its pixels with a known depth."""
    slot = int(torch.where(truth.region_valid[0], truth.region_depth_m[0], torch.inf).argmin())
    depth, known = batch.ground_truth_depth_m()
    region = (truth.labels[0, 0] == truth.kept_labels[0, slot]) & known[0, 0]
    return float(torch.quantile(depth[0, 0][region].double(), WARNING_PERCENTILE / 100))


def nearest_estimates(batch, config: PipelineConfig) -> tuple[float | None, float | None, str, torch.Tensor]:
    """The whole pipeline's nearest obstacle and warning (``nearest_m``, ``surface_m``; None where the pair is not
    OK or has none), its status and the left kept mask."""
    result = estimate_obstacle_depth(batch, config)
    status = PipelineStatus(int(result.status[0])).name
    nearest = result.depth.nearest
    ranged = status == "OK" and bool(nearest.valid[0])
    return (float(nearest.depth_m[0]) if ranged else None, float(nearest.surface_m[0]) if ranged else None, status,
            result.segmentation.left.kept_mask)


def method_configs(args) -> dict[str, PipelineConfig | str]:
    """The compared segmenters: each a whole-pipeline configuration (or the SGBM rival); ``--set``'s overrides
    apply to every pipeline."""
    default = apply_overrides(PipelineConfig(), dict(parse_assignment(text) for text in args.set))
    methods = {"default": default,
               "otsu": PipelineConfig.paper() if args.otsu_preset == "paper" else dataclasses.replace(
                   default, segmentation=SegmentationConfig()),
               "learned": dataclasses.replace(default, segmentation=SegmentationConfig(segmenter="learned:"
                                                                                         + args.weights)),
               "sgbm": "sgbm"}
    for spec in args.nearness or []:
        name, _, path = spec.partition("=")
        methods[name] = dataclasses.replace(default, segmentation=dataclasses.replace(
            default.segmentation, segmenter="nearness:" + path))
    unknown = [name for name in args.methods.split(",") if name not in methods]
    if unknown:  # (a KeyError traceback before)
        raise InputError(f"--methods: unknown {', '.join(unknown)}; expected among "
                         f"{', '.join(methods)} (a NAME of --nearness NAME=FILE too)")
    chosen = {name: methods[name] for name in args.methods.split(",")}
    # Given for a method not run: '--weights my_net.pt --methods default,otsu' scored no learned method, and the
    # report named my_net.pt nowhere (an audit). --reference reads --weights too.
    unused = [option for option, given, name in (
        ("--weights", args.weights != str(SHIPPED_WEIGHTS) and not args.reference, "learned"),
        ("--otsu-preset", args.otsu_preset != "default", "otsu")) if given and name not in chosen]
    unused += [f"--nearness {spec}" for spec in args.nearness or [] if spec.partition("=")[0] not in chosen]
    if unused:
        raise InputError(f"{unused[0]}: its method is not in --methods ({args.methods}); add it, or drop the option")
    # Each weights file read now: a bad one was refused after the first scene's work, naming "segmenter" (an audit).
    options = {"learned": "--weights", **{spec.partition("=")[0]: "--nearness" for spec in args.nearness or []}}
    for name, config in chosen.items():
        if name in options:
            try:
                check_weights_file(config.segmentation.segmenter)
            except InputError as error:
                raise InputError(f"{options[name]}: {str(error).removeprefix('segmenter: ')}") from None
    return chosen


def evaluate_scene(path: Path, size: str, methods: dict, old_net, floor: GroundPlaneConfig | None = None,
                   frames: tuple[int, int] | None = None) -> dict | None:
    """One scene's row; ``frames``: (JPEG digit, seed) to make its views camera frames first (module docstring)."""
    batch = resample(load_scene(path), size)
    if frames is not None:
        digit, seed = frames
        batch = camera_frame_pairs(batch, digit, dict(JPEG_NOISE)[digit], torch.Generator().manual_seed(seed))
    truth = obstacle_truth(batch, floor=floor)
    if not bool(truth.nearest_valid[0]):
        return None
    real, real_warning = float(truth.nearest_m[0]), truth_warning_m(batch, truth)
    row = {"scene": batch.names[0] if batch.names else path.name, "size": size, "truth_nearest_m": real,
           "truth_warning_m": real_warning, "truth_area_share": float(truth.kept_mask.float().mean())}
    for name, config in methods.items():
        if config == "sgbm":
            mask, estimate, warning = sgbm_rival(batch)
            status = "OK" if estimate is not None else "NO_DEPTH"
        else:
            estimate, warning, status, mask = nearest_estimates(batch, config)
        row.update({f"iou_{name}": float(mask_iou(mask, truth.kept_mask)[0]),
                    f"acc_{name}": accuracy_pct(real, estimate), f"nearest_{name}_m": estimate,
                    f"status_{name}": status, f"warning_{name}_m": warning,
                    f"warning_acc_{name}": accuracy_pct(real_warning, warning)})
    if old_net is not None:
        row["iou_disparity_otsu"] = float(mask_iou(disparity_otsu_mask(batch, old_net.config), truth.kept_mask)[0])
    return row


def markdown(rows: list[dict], names: list[str]) -> str:
    def number(value: float | None, digits: int) -> str:
        return "—" if value is None else f"{value:.{digits}f}"

    lines = ["| scene | size | truth nearest m | " + " | ".join(f"IoU {n}" for n in names) + " | "
             + " | ".join(f"nearest {n} m" for n in names) + " | " + " | ".join(f"Acc {n} %" for n in names)
             + " | truth warning m | " + " | ".join(f"warning Acc {n} %" for n in names) + " |",
             "|" + "---|" * (4 + 4 * len(names))]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['size']} | {r['truth_nearest_m']:.3f} | "
                     + " | ".join(f"{r[f'iou_{n}']:.3f}" for n in names) + " | "
                     + " | ".join(number(r[f"nearest_{n}_m"], 3) for n in names) + " | "
                     + " | ".join(f"{r[f'acc_{n}']:.1f}" for n in names) + f" | {r['truth_warning_m']:.3f} | "
                     + " | ".join(f"{r[f'warning_acc_{n}']:.1f}" for n in names) + " |")
    for size in sorted({r["size"] for r in rows}):
        group = [r for r in rows if r["size"] == size]
        iou = [statistics.mean(r[f"iou_{n}"] for r in group) for n in names]
        acc = [statistics.mean(r[f"acc_{n}"] for r in group) for n in names]
        warning = [statistics.mean(r[f"warning_acc_{n}"] for r in group) for n in names]
        lines.append(f"| **mean of {len(group)}** | {size} | | " + " | ".join(f"**{v:.3f}**" for v in iou) + " | "
                     + " | " * (len(names) - 1) + " | " + " | ".join(f"**{v:.1f}**" for v in acc) + " | | "
                     + " | ".join(f"**{v:.1f}**" for v in warning) + " |")
    return "\n".join(lines)


def summary(rows: list[dict], names: list[str]) -> str:
    """One line per size and method: mean IoU, mean nearest Acc, median Acc, scenes under 95 %, the warning's Acc."""
    lines = []
    for size in sorted({r["size"] for r in rows}):
        group = [r for r in rows if r["size"] == size]
        for n in names:
            acc = [r[f"acc_{n}"] for r in group]
            low = [r["scene"] for r in group if r[f"acc_{n}"] < 95]
            warning = statistics.mean(r[f"warning_acc_{n}"] for r in group)
            lines.append(f"{size:>6} {n:>12}: IoU {statistics.mean(r[f'iou_{n}'] for r in group):.3f}, nearest Acc "
                         f"mean {statistics.mean(acc):.1f} % (median {statistics.median(acc):.1f}); under 95 %: "
                         f"{', '.join(low) or 'none'}; the warning's Acc {warning:.1f} %")
    return "\n".join(lines)


LEGEND = ("default = the default pipeline (the nearness segmenter: the Otsu split of the pair's measured disparity, "
          "the nearest region then the largest; svs_torch/segmentation/weights/nearness_net.pt adds no correction, "
          "experiments/validate_nearness.md); otsu = the paper's segmentation in the default pipeline; learned = "
          "the network of issue 13; sgbm = the truth's own procedure on OpenCV StereoSGBM's disparity; NAME = the "
          "nearness segmenter with the weights a --nearness NAME=FILE names. IoU: the left kept mask against the "
          "truth obstacles; Acc: Eq. (9) of the nearest obstacle (the whole pipeline's nearest_m; SGBM's own median "
          f"depth); warning Acc: Eq. (9) of the distance guide speaks (the nearest object's {WARNING_PERCENTILE:g}th "
          "depth percentile, surface_m; SGBM's nearest region's) against the nearer truth region's same GT depth "
          "percentile.")


def header(argv: list[str], camera_frames: int | None = None) -> list[str]:
    """The markdown report's title, the command that made it and the methods' legend."""
    frames = "" if camera_frames is None else (f", on camera frames (JPEG digit {camera_frames} with its sensor noise, "
                                               "both views; the truth is the clean left view's)")
    return [f"# Segmenters against the truth obstacles (issue 32){frames}", "", "Made by:", "",
            "    " + command_line("experiments/eval_segmentation.py", argv), "", LEGEND, ""]


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_option(parser)
    parser.add_argument("--weights", default=str(SHIPPED_WEIGHTS), help="the 'learned' method's weights file "
                        "(default: the shipped one)")
    parser.add_argument("--nearness", action="append", metavar="NAME=FILE",
                        help="another method: the default pipeline with the nearness segmenter of FILE")
    parser.add_argument("--methods", default="default,otsu,learned,sgbm",
                        help="comma-separated: default, otsu, learned, sgbm, or a --nearness NAME")
    parser.add_argument("--otsu-preset", choices=("default", "paper"), default="default",
                        help="the otsu method: the default pipeline with Otsu, or the whole paper preset")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a pipeline override for every method (e.g. segmentation.ground=true)")
    parser.add_argument("--truth", choices=("issue", "walker"), default="issue",
                        help="the truth obstacles: the issue's (Otsu of the true disparity, floors included) or a "
                             "walker's (the true disparity's ground plane left out: a floor is not an obstacle)")
    parser.add_argument("--reference", action="store_true", help="also the old network's disparity-Otsu IoU")
    parser.add_argument("--camera-frames", type=int, choices=sorted(dict(JPEG_NOISE)), metavar="D",
                        help="make each pair's views camera frames first: JPEG at the board's digit D (1-8) with its "
                             "sensor noise (experiments/real_rig.py)")
    parser.add_argument("--splits", default="held-out", help="comma-separated: held-out, tuned, kitti")
    parser.add_argument("--sizes", type=size_list("width"), default="320",
                        help="comma-separated: a width in pixels, or native")
    parser.add_argument("--limit", type=scene_limit, help="only the first N scenes of each split (0: all)")
    parser.add_argument("--threads", type=positive_int, default=2, help="torch threads (default: %(default)s)")
    parser.add_argument("--markdown", type=output_path, metavar="FILE", help="write the table as Markdown to FILE")
    parser.add_argument("--json", type=output_path, metavar="FILE", help="write the report as JSON to FILE")
    args = parser.parse_args(argv)
    check_reports_apart(parser, args, (("--weights", args.weights),
                                       *(("--nearness", spec.partition("=")[2]) for spec in args.nearness or [])))
    unknown = sorted(set(args.splits.split(",")) - {"held-out", "tuned", "kitti"})
    if unknown:
        parser.error(f"--splits: unknown {', '.join(unknown)}; expected among held-out, tuned, kitti")
    torch.set_num_threads(args.threads)
    methods = method_configs(args)
    names = list(methods)
    old_net = load_obstacle_net("learned:" + args.weights) if args.reference else None
    scenes = split_scenes(Path(args.data))
    scenes["kitti"] = [p for p in list_shared_pairs(Path(args.data)) if "kitti" in str(p)]
    report = {"metadata": {**run_metadata(args.threads, command=command_line("experiments/eval_segmentation.py", argv)),
                           "methods": {n: str(c) for n, c in methods.items()}},
              "tables": {}}
    text = []
    for split in args.splits.split(","):
        paths = scenes[split][:args.limit] if args.limit else scenes[split]
        jobs = [(index, path, size) for size in args.sizes.split(",") for index, path in enumerate(paths)]
        rows, skipped = [], []
        for index, path, size in Progress(len(jobs), split, unit="scene").over(jobs):
            frames = None if args.camera_frames is None else (args.camera_frames, index)
            row = evaluate_scene(path, size, methods, old_net, GroundPlaneConfig() if args.truth == "walker" else None,
                                 frames)
            (rows.append(row) if row else skipped.append(path.name))
        text += [f"## {split}", "", markdown(rows, names), "", summary(rows, names),
                 f"scenes without a truth distance (counted, not scored): {skipped or 'none'}", ""]
        report["tables"][split] = {"rows": rows, "skipped": skipped}
    print("\n".join(text))
    if args.markdown:
        write_text_whole(args.markdown, "\n".join(header(argv if argv is not None else sys.argv[1:],
                                                         args.camera_frames) + text))
    if args.json:
        write_text_whole(args.json, json.dumps(report, indent=2, default=str))
    return report


if __name__ == "__main__":
    run_script(main)
