"""Leave-scenes-out cross-validation of the nearness segmenter's correction network over the train scenes only
(issue 32): how many training steps, if any, to choose without reading the held-out split.

The 8 train scenes of experiments/train_nearness.py (``train_segmentation.train_scenes``: the MiddEval3 Q tuned
split minus ArtL and Teddy) are split into ``--folds`` folds. MiddEval3's variants of one scene (MotorcycleE:
another exposure of Motorcycle, PianoL: other lighting of Piano; a name ending in E or L whose stem is also a
train scene) are one unit, as ArtL / Teddy are kept out of training for duplicating held-out scenes: the sorted
units are dealt out, unit i to fold i % K (``--ungrouped``: every scene its own unit, which puts Motorcycle and
MotorcycleE, Piano and PianoL on opposite sides of each fold).

For every fold, the training pool is built exactly as train_nearness.py builds it (``real_pairs`` at 320×240,
``synthetic_pairs``, ``build_pool``; crops and whole views of the fold's training scenes, ``--num-synthetic``
synthetic pairs, the same augmentation, one ``torch.Generator(seed)``), and stage 1 (``train_masks``) is run once
per step count of ``--checkpoints``: separate runs, each with its own cosine schedule over its own length, from
the same initial weights and the same generator state after the pool (a 300-step candidate is what
``train_nearness.py --steps 300`` would train on those scenes, not a snapshot of a longer run). Step count 0 is
the rule alone (an untrained ``NearnessNet()``: its head is zero). Stage 2 of train_nearness.py (the fine-tuning
through the pipeline) is not run.

Every candidate is scored on the fold's validation scenes with the shipped segmentation settings
(``PipelineConfig().segmentation``: nearest first, select_nearness_rule.py's least area), as
experiments/select_nearness_rule.py scores it (``segmentation_scores``): the left kept mask's IoU with the truth
obstacles and the segmentation-only nearest Acc (the truth's depth median over the nearer kept region against the
truth's nearest distance), on whole views 320 px wide and at native size, and separately on ``--val-crops`` random
320×240 crops per validation scene (train_segmentation.random_crop, from a generator seeded with ``--seed`` over
the sorted train scenes, so a scene's crops do not depend on the folds). A view whose truth has no nearest
obstacle is left out (none of the whole views). The held-out split is never read. The candidate with the best
mean of IoU + Acc / 100 over the whole validation views at both sizes (the mean over the two sizes, as
select_nearness_rule.py) is printed last.

    python experiments/validate_nearness.py --markdown experiments/validate_nearness.md --json /tmp/cv.json \
        [--folds 2] [--checkpoints 0,300,1200] [--num-synthetic 160] [--val-crops 4] [--seed 0] [--limit N]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # see bench_ransac.py: spinning OpenMP threads on a shared CPU

import argparse
import dataclasses
import json
import statistics
import sys
import time
from pathlib import Path

import torch

from svs_torch.segmentation.learned import obstacle_truth
from svs_torch.segmentation.nearness import NearnessNet, NearnessNetConfig
from svs_torch.pipeline import PipelineConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
from paper_table1 import load_scene, resample  # noqa: E402
from svs_torch.cli.common import non_negative_int, positive_int  # noqa: E402
from svs_torch.core.errors import InputError  # noqa: E402
from run_metadata import (add_data_option, check_reports_apart, comma_list, command_line, output_path,  # noqa: E402
                          run_metadata, run_script, scene_limit, write_text_whole)
from select_nearness_rule import segmentation_scores  # noqa: E402
from train_nearness import SIZE_WH, NearnessTrainConfig, build_pool, synthetic_pairs, train_masks  # noqa: E402
from train_segmentation import add_config_options, random_crop, real_pairs, train_scenes  # noqa: E402

#: The shipped segmentation settings (keep rule and least area: experiments/select_nearness_rule.md).
KEEP = PipelineConfig().segmentation
VARIANT_SUFFIXES = ("E", "L")  # MiddEval3: another exposure, other lighting of the same scene
WHOLE_SIZES = ("320", "native")


def scene_units(scenes: list[Path], grouped: bool = True) -> list[list[Path]]:
    """The sorted scenes as units dealt to the folds: a variant (``MotorcycleE``) joins its stem's unit when
    ``grouped``, else every scene is its own unit."""
    scenes = sorted(scenes, key=lambda p: p.name)
    names = {p.name for p in scenes}
    units: dict[str, list[Path]] = {}
    for path in scenes:
        stem = path.name[:-1] if grouped and path.name[-1:] in VARIANT_SUFFIXES and path.name[:-1] in names \
            else path.name
        units.setdefault(stem, []).append(path)
    return [units[stem] for stem in sorted(units)]


def fold_count(text: str) -> int:
    """An ``argparse`` type for ``--folds``: 2 or more (``--folds 1`` was refused only after the scenes were
    loaded, exit 1; ``--folds 0`` a traceback: an audit)."""
    value = positive_int(text)
    if value < 2:
        raise argparse.ArgumentTypeError(f"expected 2 or more folds, got {text!r}")
    return value


def assign_folds(scenes: list[Path], folds: int, grouped: bool = True) -> list[list[Path]]:
    """The validation scenes of each fold: unit i of :func:`scene_units` to fold ``i % folds``."""
    units = scene_units(scenes, grouped)
    if not 2 <= folds <= len(units):
        raise InputError(f"--folds: expected 2..{len(units)} (units of scenes), got {folds}")
    return [sorted((p for i, unit in enumerate(units) if i % folds == k for p in unit), key=lambda p: p.name)
            for k in range(folds)]


def train_candidates(scenes: list[Path], config: NearnessTrainConfig, step_counts: list[int],
                     net_config: NearnessNetConfig = NearnessNetConfig()) -> tuple[dict[int, NearnessNet], dict]:
    """One network per step count, trained on ``scenes`` as train_nearness.py's stage 1 (``config.steps`` is
    ignored): the pool once, then every count from the same generator state and initial weights. With all the
    train scenes and one count, the weights are those of ``train_nearness.py --steps N --fine-tune-steps 0``."""
    generator = torch.Generator().manual_seed(config.seed)
    torch.manual_seed(config.seed)  # as train_nearness.py: the network's initial weights
    started = time.perf_counter()
    pairs = real_pairs(scenes, config, generator, SIZE_WH) + synthetic_pairs(config.num_synthetic, generator)
    pool = build_pool(pairs, net_config, generator)
    info = {"num_samples": len(pairs), "pool_time_s": round(time.perf_counter() - started, 1), "runs": {}}
    generator_state, global_state = generator.get_state(), torch.get_rng_state()
    nets = {}
    for steps in step_counts:
        generator.set_state(generator_state)
        torch.set_rng_state(global_state)
        net = NearnessNet(net_config)
        started = time.perf_counter()
        history = train_masks(pool, net, dataclasses.replace(config, steps=steps), generator) if steps else []
        nets[steps] = net.eval()
        info["runs"][steps] = {"time_s": round(time.perf_counter() - started, 1), "mask_history": history}
    return nets, info


def validation_views(path: Path, crops: list) -> list[tuple[str, object]]:
    """(view name, pair) of one validation scene: whole at 320 px and native size, then its crops."""
    batch = load_scene(path)
    return [(size, resample(batch, size)) for size in WHOLE_SIZES] + \
        [(f"crop {k}", crop) for k, crop in enumerate(crops)]


def candidate_name(steps: int) -> str:
    return "rule (0 steps)" if steps == 0 else f"{steps} steps"


def summarise(rows: list[dict], step_counts: list[int]) -> dict[int, dict]:
    """Per candidate: mean IoU and Acc per size and over the crops, and the whole-view score (the mean over both
    sizes of IoU + Acc / 100)."""
    out = {}
    for steps in step_counts:
        mine = [r for r in rows if r["steps"] == steps]
        means = {}
        for view in (*WHOLE_SIZES, "crops"):
            chosen = [r for r in mine if (r["view"].startswith("crop") if view == "crops" else r["view"] == view)]
            means[view] = {"n": len(chosen),
                           "iou": statistics.mean(r["iou"] for r in chosen) if chosen else float("nan"),
                           "acc": statistics.mean(r["acc"] for r in chosen) if chosen else float("nan")}
        means["score"] = statistics.mean(means[s]["iou"] + means[s]["acc"] / 100 for s in WHOLE_SIZES)
        means["crop_score"] = means["crops"]["iou"] + means["crops"]["acc"] / 100
        out[steps] = means
    return out


def means_table(summary: dict[int, dict]) -> list[str]:
    lines = ["| candidate | IoU 320 | Acc 320 % | IoU native | Acc native % | score (whole) | IoU crops | Acc crops % "
             "| score (crops) |", "|---|---|---|---|---|---|---|---|---|"]
    for steps, m in summary.items():
        lines.append(f"| {candidate_name(steps)} | {m['320']['iou']:.3f} | {m['320']['acc']:.1f} | "
                     f"{m['native']['iou']:.3f} | {m['native']['acc']:.1f} | {m['score']:.3f} | "
                     f"{m['crops']['iou']:.3f} | {m['crops']['acc']:.1f} | {m['crop_score']:.3f} |")
    return lines


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_option(parser)
    parser.add_argument("--folds", type=fold_count, default=2,
                        help="folds of the train scenes, a scene and its E/L variant in one (default: %(default)s)")
    parser.add_argument("--checkpoints", default="0,300,1200", type=comma_list(non_negative_int, "step counts"),
                        help="step counts, comma-separated (0: the rule)")
    parser.add_argument("--val-crops", type=positive_int, default=4, help="random 320x240 crops per validation scene")
    parser.add_argument("--limit", type=scene_limit, help="only the first N train scenes (sorted), for a quick run")
    parser.add_argument("--ungrouped", action="store_true", help="a scene's E/L variant is a unit of its own")
    # train_nearness.py's stage-1 settings as options (steps come from --checkpoints), 160 synthetic pairs a fold.
    train_fields = add_config_options(parser, dataclasses.replace(NearnessTrainConfig(), num_synthetic=160),
                                      skip=("steps", "fine_tune_steps", "fine_tune_learning_rate"), crop_wh=SIZE_WH)
    parser.add_argument("--threads", type=positive_int, default=2, help="torch threads (default: %(default)s)")
    parser.add_argument("--markdown", type=output_path, metavar="FILE", help="write the table as Markdown to FILE")
    parser.add_argument("--json", type=output_path, metavar="FILE", help="write the report as JSON to FILE")
    args = parser.parse_args(argv)
    check_reports_apart(parser, args)
    torch.set_num_threads(args.threads)
    started = time.perf_counter()
    step_counts = sorted({int(s) for s in args.checkpoints.split(",")})
    config = NearnessTrainConfig(**{name: getattr(args, name) for name in train_fields}, fine_tune_steps=0)
    data = Path(args.data)
    scenes = sorted(train_scenes(data), key=lambda p: p.name)[:args.limit]
    folds = assign_folds(scenes, args.folds, grouped=not args.ungrouped)
    crop_generator = torch.Generator().manual_seed(args.seed)
    crops = {p: [random_crop(load_scene(p), crop_generator, SIZE_WH) for _ in range(args.val_crops)] for p in scenes}

    rows, fold_info, skipped = [], [], []
    for k, validation in enumerate(folds):
        training = [p for p in scenes if p not in validation]
        print(f"fold {k}: train on {', '.join(p.name for p in training)}; validate on "
              f"{', '.join(p.name for p in validation)}", flush=True)
        nets, info = train_candidates(training, config, step_counts)
        fold_info.append({"fold": k, "train": [p.name for p in training], "validate": [p.name for p in validation],
                          **info})
        for path in validation:
            for view, batch in validation_views(path, crops[path]):
                truth = obstacle_truth(batch)
                if not bool(truth.nearest_valid[0]):
                    skipped.append(f"{path.name} {view}")
                    continue
                for steps, net in nets.items():
                    iou, acc = segmentation_scores(batch, truth, KEEP, net)
                    rows.append({"fold": k, "scene": path.name, "view": view, "steps": steps, "iou": round(iou, 4),
                                 "acc": round(acc, 2)})
        fold_summary = summarise([r for r in rows if r["fold"] == k], step_counts)
        print("\n".join(means_table(fold_summary)), flush=True)
        fold_info[-1]["summary"] = fold_summary
    summary = summarise(rows, step_counts)
    best = max(step_counts, key=lambda s: summary[s]["score"])
    elapsed = time.perf_counter() - started
    rule = f"; rule {summary[0]['score']:.3f}" if 0 in summary else ""
    verdict = (f"best (mean of IoU + Acc/100 over the whole validation views at both sizes): {candidate_name(best)} "
               f"(score {summary[best]['score']:.3f}{rule})")
    command = command_line("experiments/validate_nearness.py", argv)
    report = {"summary": {str(s): m for s, m in summary.items()}, "best_steps": best, "rows": rows,
              "folds": fold_info, "skipped_views": skipped,
              "metadata": {"train": dataclasses.asdict(config), "step_counts": step_counts,
                           "folds": args.folds, "grouped": not args.ungrouped, "val_crops": args.val_crops,
                           "limit": args.limit, "keep": dataclasses.asdict(KEEP), "time_s": round(elapsed, 1),
                           **run_metadata(args.threads, command=command)}}
    if args.json:
        write_text_whole(args.json, json.dumps(report, indent=1, default=str) + "\n")
    if args.markdown:
        write_text_whole(args.markdown, _markdown(report, summary, fold_info, rows, step_counts, verdict))
    print("\n".join(means_table(summary)))
    print(f"{elapsed:.0f} s")
    print(verdict)
    return report


def _markdown(report: dict, summary: dict, fold_info: list[dict], rows: list[dict], step_counts: list[int],
              verdict: str) -> str:
    meta = report["metadata"]
    train = meta["train"]
    lines = ["# Leave-scenes-out validation of the nearness correction network", "",
             f"`{meta['command']}` (commit {meta['commit']}, {meta['threads']} threads, {meta['time_s']:.0f} s). "
             f"{meta['folds']} folds over the train scenes of train_nearness.py"
             f"{', a scene and its E/L variant in the same fold' if meta['grouped'] else ''}; per fold, stage 1 of "
             f"train_nearness.py on the other folds' scenes ({train['crops_per_scene']} crop(s) and "
             f"{train['views_per_scene']} whole view(s) per scene, {train['num_synthetic']} synthetic pairs, batch "
             f"{train['batch_size']}, seed {train['seed']}), one separate run per step count (its own cosine "
             f"schedule), no fine-tuning through the pipeline; step count 0 is the rule alone. Keep rule: "
             f"nearest_first, least area 0.01. The held-out split is never read.", "",
             "## Means per candidate (all validation views of all folds)", "",
             "Whole views: each train scene once, 320 px wide and native; crops: "
             f"{meta['val_crops']} random 320×240 crop(s) per scene. Score: IoU + Acc / 100 (whole: mean of both "
             "sizes).",
             "", *means_table(summary), "", "## Per fold", ""]
    for info in fold_info:
        times = ", ".join(f"{candidate_name(int(s))} {r['time_s']:.0f} s" for s, r in info["runs"].items() if int(s))
        lines += [f"### Fold {info['fold']}: validate on {', '.join(info['validate'])}", "",
                  f"Trained on {', '.join(info['train'])} ({info['num_samples']} samples, pool "
                  f"{info['pool_time_s']:.0f} s; {times or 'no training'}).", "", *means_table(info["summary"]), ""]
    lines += ["## Per scene and view (IoU / Acc %)", "",
              "| fold | scene | view | " + " | ".join(candidate_name(s) for s in step_counts) + " |",
              "|---|---|---|" + "---|" * len(step_counts)]
    keyed = {(r["fold"], r["scene"], r["view"], r["steps"]): r for r in rows}
    for fold, scene, view in dict.fromkeys((r["fold"], r["scene"], r["view"]) for r in rows):
        cells = [keyed[fold, scene, view, s] for s in step_counts]
        lines.append(f"| {fold} | {scene} | {view} | " + " | ".join(f"{c['iou']:.3f} / {c['acc']:.1f}" for c in cells)
                     + " |")
    if report["skipped_views"]:
        lines += ["", "Left out (no nearest obstacle in the truth): " + ", ".join(report["skipped_views"])]
    lines += ["", verdict, ""]
    return "\n".join(lines)


if __name__ == "__main__":
    run_script(main)
