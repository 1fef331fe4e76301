"""Choose a setting of the nearness segmenter on the tuned scenes only (issues 32 and 33).

Each variant (one or more ``NearnessNetConfig`` fields, e.g. ``min_near_share=0.05`` or
``sparse_reduction=2,sparse_agreement_px=1.5``) is written beside the shipped nearness weights into a temporary
weights file and scored on the ``tuned`` split of experiments/paper_table1.py, at 320×240 and native size, twice:

- clean pairs against the truth obstacles (experiments/eval_segmentation.py): IoU of the left kept mask and the
  nearest obstacle's Acc (Eq. (9));
- camera frames and a loose rig (experiments/real_rig.py, no rival; every condition unless ``--conditions``
  names some; at each ``--contrasts`` factor, 0.5 being the tuned split's stand-in for weakly textured scenes):
  per object Acc;
- with ``--synthetic``, the same on real_rig.py's rendered weakly textured scenes (``--splits synthetic``, one
  size): our own pairs, a tuning set for what plain surfaces lose to JPEG.

The held-out split is never read. Chosen: the variant with the largest sum of the mean of (IoU, Acc / 100) over
both sizes and the mean per object Acc / 100 over both sizes and contrasts (and the rendered split); the first
listed on a tie (list the one that changes least first).

    python experiments/select_nearness_setting.py --variants min_near_share=0 min_near_share=0.1 \\
        [--contrasts 1,0.5] [--conditions clean,jpeg] [--synthetic] [--markdown FILE]

``experiments/select_min_near_share.md`` was made by this script's first form (``--shares``, since folded into
``--variants``); ``experiments/select_nearness_setting.md`` chose the sparse pairs' coarse check.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import tempfile
from pathlib import Path

from svs_torch.core.errors import InputError
from svs_torch.core.files import write_bytes_atomic
from svs_torch.segmentation.nearness import NearnessNet, NearnessNetConfig
from svs_torch.segmentation.network_files import load_obstacle_net, save_obstacle_net

sys.path.insert(0, str(Path(__file__).resolve().parent))
import eval_segmentation  # noqa: E402
import real_rig  # noqa: E402
from svs_torch.cli.common import unit_interval_float  # noqa: E402
from run_metadata import (add_data_option, comma_list, command_line, output_path, run_script,  # noqa: E402
                          use_two_threads)

SIZES = {"320": "320x240", "native": "native"}


def parse_variant(text: str, shipped: NearnessNetConfig) -> dict:
    """``"name=value[,name=value]"`` to ``{name: value}``, each value of its field's type in ``shipped``."""
    fields = {f.name: type(getattr(shipped, f.name)) for f in dataclasses.fields(shipped)}
    out = {}
    for item in text.split(","):
        name, _, value = item.partition("=")
        if name not in fields or not value:
            raise InputError(f"--variants: expected NAME=VALUE with NAME a NearnessNetConfig field, got {item!r}")
        try:
            out[name] = fields[name](value)
        except (TypeError, ValueError):
            raise InputError(f"--variants: {name}: expected a {fields[name].__name__}, got {value!r}") from None
    try:
        dataclasses.replace(shipped, **out)  # the config's own range checks, before any scene is measured
    except InputError as error:
        raise InputError(f"--variants: {text!r}: {error}") from None
    return out


def weights_with(folder: Path, shipped: NearnessNet, variant: dict, number: int) -> Path:
    """The ``shipped`` nearness network with ``variant``'s fields set, saved in ``folder``."""
    net = NearnessNet(dataclasses.replace(shipped.config, **variant))
    net.load_state_dict(shipped.state_dict())
    path = folder / f"nearness_{number}.pt"
    save_obstacle_net(path, net, {"made_by": "experiments/select_nearness_setting.py", **variant})
    return path


def segmentation_scores(data: Path, name: str, path: Path) -> dict[str, tuple[float, float]]:
    """{size: (mean IoU, mean nearest Acc %)} on the tuned split's clean pairs."""
    report = eval_segmentation.main(["--data", str(data), "--splits", "tuned", "--sizes", ",".join(SIZES),
                                     "--methods", name, "--nearness", f"{name}={path}"])
    rows = report["tables"]["tuned"]["rows"]
    return {size: (statistics.fmean(r[f"iou_{name}"] for r in rows if r["size"] == size),
                   statistics.fmean(r[f"acc_{name}"] for r in rows if r["size"] == size)) for size in SIZES}


def rig_scores(data: Path, path: Path, contrast: float, conditions: str | None, split: str = "tuned"
               ) -> dict[str, float]:
    """{size: mean per object Acc %} over the ``split``'s real_rig.py conditions at ``contrast`` (the rendered
    ``synthetic`` split: its one size, as "320")."""
    argv = ["--data", str(data), "--splits", split, "--sizes", ",".join(SIZES.values()), "--no-rival",
            "--contrast", str(contrast), "--set", f"segmentation.segmenter=nearness:{path}"]
    rows = real_rig.main(argv + (["--conditions", conditions] if conditions else []))["rows"]
    return {size: statistics.fmean(r["acc_objects"] or 0.0 for r in rows if r["size"] == rig_size)
            for size, rig_size in SIZES.items() if any(r["size"] == rig_size for r in rows)}


def score(data: Path, path: Path, variant: dict, number: int, contrasts: list[float],
          conditions: str | None, synthetic: bool = False) -> dict:
    """The variant's (its weights file at ``path``) clean segmentation and rig scores and its total (module
    docstring)."""
    seg = segmentation_scores(data, f"variant{number}", path)
    rig = {(size, contrast): acc for contrast in contrasts
           for size, acc in rig_scores(data, path, contrast, conditions).items()}
    if synthetic:
        rig[("synthetic", 1.0)] = rig_scores(data, path, 1.0, conditions, "synthetic")["320"]
    segmentation = statistics.fmean(v for iou, acc in seg.values() for v in (iou, acc / 100))
    return {"variant": variant, "seg": seg, "rig": rig, "score": segmentation + statistics.fmean(rig.values()) / 100}


def table(results: list[dict], best: dict, command: str, conditions: str | None) -> str:
    """The markdown report: a column per rig score of the results (each contrast and size, then the synthetic
    split's)."""
    rig_columns = list(results[0]["rig"])
    lines = ["# A setting of the nearness segmenter, chosen on the tuned split", "", "Made by:", "",
             "    " + command, "", "Clean: IoU with the truth obstacles and the nearest obstacle's Acc "
             "(eval_segmentation.py).", f"Frames: per object Acc over real_rig.py's {conditions or 'every'} "
             "condition(s) on the tuned split, at each contrast"
             + (", and on the rendered synthetic split (real_rig.py --splits synthetic)." if ("synthetic", 1.0)
                in results[0]["rig"] else "."),
             "Score: mean of (IoU, Acc / 100) over both sizes + mean frames Acc / 100.", "",
             "| variant | IoU 320 | Acc 320 % | IoU native | Acc native % | "
             + " | ".join("frames synthetic %" if s == "synthetic" else f"frames {s} ×{c} %"
                          for s, c in rig_columns) + " | score |",
             "|---" * (6 + len(rig_columns)) + "|"]
    for r in results:
        name = ", ".join(f"{k}={v}" for k, v in r["variant"].items())
        mark = "**" if r is best else ""
        lines.append(f"| {mark}{name}{mark} | {r['seg']['320'][0]:.3f} | {r['seg']['320'][1]:.1f} | "
                     f"{r['seg']['native'][0]:.3f} | {r['seg']['native'][1]:.1f} | "
                     + " | ".join(f"{r['rig'][key]:.2f}" for key in rig_columns) + f" | {r['score']:.4f} |")
    chosen = ", ".join(f"{k}={v}" for k, v in best["variant"].items())
    return "\n".join(lines + ["", f"Chosen: {chosen} (the largest score; the first listed on a tie)."]) + "\n"


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_option(parser, Path)
    parser.add_argument("--variants", nargs="+", required=True, metavar="NAME=VALUE[,NAME=VALUE]",
                        help="the settings compared, each NAME=VALUE[,NAME=VALUE] (--set keys)")
    parser.add_argument("--contrasts", default="1", type=comma_list(unit_interval_float, "factors"),
                        help="comma-separated real_rig.py --contrast factors")
    parser.add_argument("--conditions", default=None, type=real_rig.condition_prefixes,
                        help="real_rig.py --conditions (default: every one)")
    parser.add_argument("--synthetic", action="store_true",
                        help="also score real_rig.py's rendered weakly textured scenes (--splits synthetic)")
    parser.add_argument("--markdown", type=output_path, help="write the table as Markdown to FILE")
    args = parser.parse_args(argv)
    shipped = load_obstacle_net("nearness")  # read once: every variant is its weights with other settings
    variants = [parse_variant(text, shipped.config) for text in args.variants]
    contrasts = [float(text) for text in args.contrasts.split(",")]
    use_two_threads()
    with tempfile.TemporaryDirectory() as folder:
        results = [score(args.data, weights_with(Path(folder), shipped, variant, number), variant, number, contrasts,
                         args.conditions, args.synthetic) for number, variant in enumerate(variants)]
    best = max(results, key=lambda r: round(r["score"], 4))  # max keeps the first of equal scores
    command = command_line("experiments/select_nearness_setting.py", argv)
    report = table(results, best, command, args.conditions)
    print(report)
    if args.markdown:
        write_bytes_atomic(args.markdown, report.encode("utf-8"))
    return results


if __name__ == "__main__":
    run_script(main)
