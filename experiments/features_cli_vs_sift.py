"""``svs-depth features L R --no-segment --json`` against a plain OpenCV SIFT loop on the shared real pairs at
their native size, the way a user meets both (issue 33, item 4).

The command runs in-process through :func:`svs_torch.cli.main` (the same code path as the console script,
without a Python start-up per pair) on the image files themselves; its ``matched_xy_px`` rows are scored against the
ground truth. The rival is what a user writes from OpenCV's tutorial: ``cv2.SIFT_create()`` (no keypoint cap) on
the grayscale files, ``BFMatcher().knnMatch(k=2)`` and Lowe's ratio 0.8. A match is correct when its disparity
``x_left − x_right`` is within 1 px of the GT disparity at the (rounded) left point AND ``|y_left − y_right|`` ≤
1 px; precision is the share of correct matches among those with GT at the left point, pooled over a split.

Splits: ``tuned`` = middlebury_eval3_Q (10 pairs), ``held-out`` = middlebury_2005_2006_third +
middlebury_2003_quarter (28 pairs). Tune on ``tuned``, report both.

    python experiments/features_cli_vs_sift.py [--split tuned --split held-out] [--args "--max-keypoints 2048"]
        [--limit N] [--json out.json]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # a shared machine: no spinning OpenMP threads

import argparse  # noqa: E402
import contextlib  # noqa: E402
import io  # noqa: E402
import json  # noqa: E402
import shlex  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from run_metadata import add_data_option, output_path, run_metadata, run_script, scene_limit  # noqa: E402

SPLITS = {"tuned": ("middlebury_eval3_Q",), "held-out": ("middlebury_2005_2006_third", "middlebury_2003_quarter")}
#: The image files of each layout: (left, right).
IMAGE_NAMES = (("im0.png", "im1.png"), ("view1.png", "view5.png"), ("imL.png", "imR.png"))
TOLERANCE_PX = 1.0
SIFT_RATIO = 0.8


def split_pairs(data_dir: Path, split: str) -> list[Path]:
    """The scene folders of ``split`` (sorted), each with one of :data:`IMAGE_NAMES` and GT."""
    scenes = []
    for folder in SPLITS[split]:
        scenes += sorted(d for d in (data_dir / folder).iterdir() if image_files(d) is not None)
    return scenes


def image_files(scene: Path) -> tuple[Path, Path] | None:
    for left, right in IMAGE_NAMES:
        if (scene / left).is_file() and (scene / right).is_file():
            return scene / left, scene / right
    return None


def command_matches(left: Path, right: Path, extra: list[str]) -> tuple[np.ndarray, dict]:
    """``svs-depth features LEFT RIGHT --no-segment --json EXTRA``: matched points ``(M, 4)`` (x_l, y_l, x_r, y_r
    in input pixels) and the JSON object."""
    from svs_torch.cli import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        status = main(["features", str(left), str(right), "--no-segment", "--json", *extra])
    if status != 0:
        raise RuntimeError(f"svs-depth features exited {status} on {left}")
    report = json.loads(out.getvalue())
    return np.asarray(report["matched_xy_px"], np.float64).reshape(-1, 4), report


def sift_matches(left: Path, right: Path) -> np.ndarray:
    """A plain OpenCV SIFT loop: no cap, brute-force L2 kNN, Lowe's ratio 0.8. ``(M, 4)`` as above."""
    sift = cv2.SIFT_create()
    kl, dl = sift.detectAndCompute(cv2.imread(str(left), cv2.IMREAD_GRAYSCALE), None)
    kr, dr = sift.detectAndCompute(cv2.imread(str(right), cv2.IMREAD_GRAYSCALE), None)
    if dl is None or dr is None or len(kr) < 2:
        return np.zeros((0, 4))
    rows = [kl[m.queryIdx].pt + kr[m.trainIdx].pt
            for m, n in cv2.BFMatcher().knnMatch(dl, dr, k=2) if m.distance < SIFT_RATIO * n.distance]
    return np.asarray(rows, np.float64).reshape(-1, 4)


def score(disparity: np.ndarray, valid: np.ndarray, matched: np.ndarray) -> dict:
    """Matches with GT at the left point, and those within :data:`TOLERANCE_PX` in x (disparity) and y."""
    h, w = disparity.shape
    cols = np.clip(np.round(matched[:, 0]).astype(int), 0, w - 1)
    rows = np.clip(np.round(matched[:, 1]).astype(int), 0, h - 1)
    has_gt = valid[rows, cols]
    error_x = np.abs(matched[:, 0] - matched[:, 2] - disparity[rows, cols])
    error_y = np.abs(matched[:, 1] - matched[:, 3])
    correct = has_gt & (error_x <= TOLERANCE_PX) & (error_y <= TOLERANCE_PX)
    return {"matches": int(len(matched)), "with_gt": int(has_gt.sum()), "correct": int(correct.sum())}


def summary(rows: list[dict]) -> dict:
    with_gt = sum(r["with_gt"] for r in rows)
    correct = sum(r["correct"] for r in rows)
    return {"pairs": len(rows), "matches": sum(r["matches"] for r in rows), "with_gt": with_gt, "correct": correct,
            "precision": correct / with_gt if with_gt else float("nan")}


def run_split(data_dir: Path, split: str, extra: list[str], limit: int | None) -> dict:
    from svs_torch.data import load_stereo_pair

    command, sift, per_pair, seconds = [], [], [], 0.0
    for scene in split_pairs(data_dir, split)[:limit]:
        batch = load_stereo_pair(scene)
        disparity, valid = batch.disparity_px[0, 0].numpy(), batch.disparity_valid[0, 0].numpy()
        left, right = image_files(scene)
        started = time.perf_counter()
        matched, _ = command_matches(left, right, extra)
        seconds += time.perf_counter() - started
        command.append(score(disparity, valid, matched))
        sift.append(score(disparity, valid, sift_matches(left, right)))
        per_pair.append({"scene": f"{scene.parent.name}/{scene.name}", "command": command[-1], "sift": sift[-1]})
    return {"command": summary(command), "sift": summary(sift), "command_s": round(seconds, 2), "pairs": per_pair}


def main(argv: list[str] | None = None) -> dict:
    """Runs the comparison, prints the table, writes ``--json``; returns the report."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--split", action="append", choices=tuple(SPLITS), help="default: both")
    parser.add_argument("--args", default="", help="extra options for the command, one shell-quoted string")
    add_data_option(parser)
    parser.add_argument("--limit", type=scene_limit, help="first N pairs of each split (a quick look)")
    parser.add_argument("--json", type=output_path, metavar="FILE", help="write the report as JSON to FILE")
    args = parser.parse_args(argv)
    extra = shlex.split(args.args)
    command = shlex.join(["python", "experiments/features_cli_vs_sift.py", *(sys.argv[1:] if argv is None else argv)])
    report = {"metadata": run_metadata(threads=int(os.environ.get("OMP_NUM_THREADS", "0") or 0), command=command,
                                       command_args=extra, tolerance_px=TOLERANCE_PX, sift_ratio=SIFT_RATIO),
              "results": {}}
    print(f"svs-depth features L R --no-segment --json {' '.join(extra)}   vs   cv2.SIFT_create() + ratio "
          f"{SIFT_RATIO}; correct = |dx - d_GT| <= {TOLERANCE_PX} px and |dy| <= {TOLERANCE_PX} px")
    print(f"{'split':<9} {'pairs':>5} {'method':<8} {'matches':>8} {'with GT':>8} {'correct':>8} {'precision':>9}")
    for split in args.split or list(SPLITS):
        result = run_split(Path(args.data), split, extra, args.limit)
        report["results"][split] = result
        for method in ("command", "sift"):
            s = result[method]
            print(f"{split:<9} {s['pairs']:>5} {method:<8} {s['matches']:>8} {s['with_gt']:>8} {s['correct']:>8} "
                  f"{s['precision']:>9.3f}")
        ratio = result["command"]["correct"] / max(result["sift"]["correct"], 1)
        print(f"{split:<9} command / SIFT correct matches {ratio:.2f}; command {result['command_s']:.1f} s")
    if args.json:
        from svs_torch.core.files import write_bytes_atomic

        write_bytes_atomic(args.json, json.dumps(report, indent=2).encode())
    return report


if __name__ == "__main__":
    run_script(main)
