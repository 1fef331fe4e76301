"""Choose the nearness segmenter's ``min_near_share`` on the tuned scenes only (issues 32 and 33).

Where the Otsu split of the measured disparity leaves less than ``min_near_share`` of the view nearer than it, the
segmenter takes the split again over the disparity clipped at its 90th percentile
(:func:`svs_torch.segmentation.nearness_split.nearness_split`). Each candidate share is written beside the shipped
nearness weights into a temporary weights file and scored on the ``tuned`` split of experiments/paper_table1.py,
at 320×240 and native size, twice:

- clean pairs against the truth obstacles (experiments/eval_segmentation.py): IoU of the left kept mask and the
  nearest obstacle's Acc (Eq. (9));
- camera frames and a loose rig (experiments/real_rig.py, every condition, no rival): per object Acc.

The held-out split is never read. Chosen: the share with the largest sum of the mean of (IoU, Acc / 100) over
both sizes and the mean per object Acc / 100 over both sizes; the smallest such share on a tie (it fires least).

    python experiments/select_min_near_share.py [--shares 0,0.05,0.1,0.2] [--markdown FILE]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import tempfile
from pathlib import Path

import torch

from svs_torch.core.files import write_bytes_atomic
from svs_torch.segmentation.nearness import NearnessNet
from svs_torch.segmentation.network_files import load_obstacle_net, save_obstacle_net

sys.path.insert(0, str(Path(__file__).resolve().parent))
import eval_segmentation  # noqa: E402
import real_rig  # noqa: E402
from run_metadata import default_data_dir  # noqa: E402

SIZES = {"320": "320x240", "native": "native"}


def weights_with_share(folder: Path, share: float) -> Path:
    """The shipped nearness network with ``min_near_share`` set to ``share``, saved in ``folder``."""
    shipped = load_obstacle_net("nearness")
    net = NearnessNet(dataclasses.replace(shipped.config, min_near_share=share))
    net.load_state_dict(shipped.state_dict())
    path = folder / f"nearness_{share}.pt"
    save_obstacle_net(path, net, {"made_by": "experiments/select_min_near_share.py", "min_near_share": share})
    return path


def segmentation_scores(data: Path, name: str, path: Path) -> dict[str, tuple[float, float]]:
    """{size: (mean IoU, mean nearest Acc %)} on the tuned split's clean pairs."""
    report = eval_segmentation.main(["--data", str(data), "--splits", "tuned", "--sizes", ",".join(SIZES),
                                     "--methods", name, "--nearness", f"{name}={path}"])
    rows = report["tables"]["tuned"]["rows"]
    return {size: (statistics.fmean(r[f"iou_{name}"] for r in rows if r["size"] == size),
                   statistics.fmean(r[f"acc_{name}"] for r in rows if r["size"] == size)) for size in SIZES}


def rig_scores(data: Path, path: Path) -> dict[str, float]:
    """{size: mean per object Acc %} over the tuned split's every real_rig.py condition."""
    report = real_rig.main(["--data", str(data), "--splits", "tuned", "--sizes", ",".join(SIZES.values()),
                            "--no-rival", "--set", f"segmentation.segmenter=nearness:{path}"])
    rows = report["rows"]
    return {size: statistics.fmean(r["acc_objects"] or 0.0 for r in rows if r["size"] == rig_size)
            for size, rig_size in SIZES.items()}


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=default_data_dir())
    parser.add_argument("--shares", default="0,0.05,0.1,0.2")
    parser.add_argument("--markdown", type=Path)
    args = parser.parse_args(argv)
    torch.set_num_threads(2)
    results = []
    with tempfile.TemporaryDirectory() as folder:
        for share in (float(text) for text in args.shares.split(",")):
            path = weights_with_share(Path(folder), share)
            seg = segmentation_scores(args.data, f"share{share}", path)
            rig = rig_scores(args.data, path)
            segmentation = statistics.fmean(v for iou, acc in seg.values() for v in (iou, acc / 100))
            results.append({"share": share, "seg": seg, "rig": rig,
                            "score": segmentation + statistics.fmean(rig.values()) / 100})
    best = max(results, key=lambda r: (round(r["score"], 4), -r["share"]))
    lines = ["# The nearness segmenter's min_near_share, chosen on the tuned split", "", "Made by:", "",
             "    python experiments/select_min_near_share.py " + " ".join(argv if argv is not None else sys.argv[1:]),
             "", "Clean: IoU with the truth obstacles and the nearest obstacle's Acc (eval_segmentation.py).",
             "Frames: per object Acc over every real_rig.py condition (clean, JPEG digits 1-8 with noise,",
             "misalignments, gain). Score: mean of (IoU, Acc / 100) over both sizes + mean frames Acc / 100.",
             "", "| min_near_share | IoU 320 | Acc 320 % | IoU native | Acc native % | frames 320 % | frames native % "
             "| score |", "|---|---|---|---|---|---|---|---|"]
    for r in results:
        mark = "**" if r is best else ""
        lines.append(f"| {mark}{r['share']}{mark} | {r['seg']['320'][0]:.3f} | {r['seg']['320'][1]:.1f} | "
                     f"{r['seg']['native'][0]:.3f} | {r['seg']['native'][1]:.1f} | {r['rig']['320']:.2f} | "
                     f"{r['rig']['native']:.2f} | {r['score']:.4f} |")
    lines += ["", f"Chosen: {best['share']} (the largest score; the smallest share on a tie)."]
    table = "\n".join(lines) + "\n"
    print(table)
    if args.markdown:
        write_bytes_atomic(args.markdown, table.encode("utf-8"))
    return results


if __name__ == "__main__":
    main()
