"""SURF (svs_torch) against OpenCV SIFT on real stereo pairs with ground-truth disparity (issue: features).

For every Middlebury pair of the shared data, resampled to 320×240 (SVS size) and at native size:
- repeatability: share of left keypoints (with known GT) whose GT-corresponding right location
  (x − d, y) has a right keypoint within 1.5 px and of similar scale (ratio within 1.5);
- matching precision: share of nearest-neighbour + ratio-test matches (among those with GT at the left point)
  whose disparity x_left − x_right is within 1 px of GT, with the number of correct matches (precision alone
  rewards matching almost nothing). Ratios 0.8 (Lowe) and 0.6 (MATLAB ``matchFeatures`` MaxRatio).
Both detectors keep their strongest ``--max-keypoints`` points. SURF runs twice: with MATLAB's defaults, and
enlarged twice before detection (``SurfConfig.upsample``, as SIFT does) with MetricThreshold 300. Prints a table and writes JSON with metadata.

    python experiments/surf_vs_sift.py [--max-keypoints 512] [--ratio 0.8] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

from svs_torch.data import list_shared_pairs, load_stereo_pair, resize_stereo_batch
from svs_torch.detector import SurfConfig
from svs_torch.features import extract_surf_features

sys.path.insert(0, str(Path(__file__).resolve().parent))
from run_metadata import run_metadata  # noqa: E402

TOLERANCE_PX = 1.5
SCALE_RATIO = 1.5


def gt_disparity_at(batch, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """GT disparity and validity at (rounded) left positions ``(N, 2)``."""
    disparity = batch.disparity_px[0, 0].numpy()
    valid = batch.disparity_valid[0, 0].numpy()
    h, w = disparity.shape
    cols = np.clip(np.round(xy[:, 0]).astype(int), 0, w - 1)
    rows = np.clip(np.round(xy[:, 1]).astype(int), 0, h - 1)
    return disparity[rows, cols], valid[rows, cols]


def repeatability(batch, left_xy, left_scale, right_xy, right_scale) -> float:
    d, ok = gt_disparity_at(batch, left_xy)
    if ok.sum() == 0 or len(right_xy) == 0:
        return float("nan")
    target = left_xy[ok] - np.stack([d[ok], np.zeros_like(d[ok])], axis=1)
    distance = np.linalg.norm(target[:, None, :] - right_xy[None, :, :], axis=2)
    ratio = left_scale[ok][:, None] / right_scale[None, :]
    close = (distance <= TOLERANCE_PX) & (ratio <= SCALE_RATIO) & (ratio >= 1 / SCALE_RATIO)
    return float(close.any(axis=1).mean())


def ratio_matches(left_desc: np.ndarray, right_desc: np.ndarray, ratio: float, metric: str) -> np.ndarray:
    """Nearest-neighbour matches passing the ratio test: ``(M, 2)`` index pairs."""
    if len(left_desc) < 1 or len(right_desc) < 2:
        return np.zeros((0, 2), int)
    p = 1.0 if metric == "sad" else 2.0
    distance = torch.cdist(torch.from_numpy(left_desc).double()[None], torch.from_numpy(right_desc).double()[None],
                           p=p)[0]
    best = torch.topk(distance, 2, dim=1, largest=False)
    keep = best.values[:, 0] < ratio * best.values[:, 1]
    left = torch.nonzero(keep).squeeze(1)
    return torch.stack([left, best.indices[keep, 0]], dim=1).numpy()


def match_precision(batch, left_xy, right_xy, matches) -> tuple[float, int, int]:
    if len(matches) == 0:
        return float("nan"), 0, 0
    d, ok = gt_disparity_at(batch, left_xy[matches[:, 0]])
    disparity = left_xy[matches[:, 0], 0] - right_xy[matches[:, 1], 0]
    correct = ok & (np.abs(disparity - d) <= 1.0)
    return float(correct[ok].mean()) if ok.any() else float("nan"), int(correct.sum()), int(ok.sum())


def sift_features(image: torch.Tensor, max_keypoints: int):
    gray = (image[0, 0] * 255).round().to(torch.uint8).numpy()
    sift = cv2.SIFT_create(nfeatures=max_keypoints)
    keypoints, descriptors = sift.detectAndCompute(gray, None)
    xy = np.array([k.pt for k in keypoints], np.float64).reshape(-1, 2)
    scale = np.array([k.size for k in keypoints], np.float64)
    return xy, scale, (descriptors if descriptors is not None else np.zeros((0, 128), np.float32))


def surf_features(image: torch.Tensor, config: SurfConfig):
    features = extract_surf_features(image, config)
    valid = features.keypoints.valid[0].numpy()
    return (features.keypoints.xy[0].numpy()[valid].astype(np.float64),
            features.keypoints.scale[0].numpy()[valid].astype(np.float64),
            features.descriptors[0].numpy()[valid])


def evaluate(batch, extract, ratio: float, metric: str) -> dict:
    left_xy, left_scale, left_desc = extract(batch.left)
    right_xy, right_scale, right_desc = extract(batch.right)
    matches = ratio_matches(left_desc, right_desc, ratio, metric)
    precision, correct, judged = match_precision(batch, left_xy, right_xy, matches)
    return {"keypoints": int(len(left_xy)), "repeatability": repeatability(batch, left_xy, left_scale, right_xy,
                                                                           right_scale),
            "precision": precision, "correct_matches": correct, "matches_with_gt": judged}


def summarise(rows: list[dict], key: str) -> float:
    values = [r[key] for r in rows if not np.isnan(r[key])]
    return statistics.mean(values) if values else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data"))
    parser.add_argument("--max-keypoints", type=int, default=512)
    parser.add_argument("--metric-threshold", type=float, default=1000.0,
                        help="MetricThreshold of the MATLAB-default SURF row (0-255 scale)")
    parser.add_argument("--limit", type=int, default=0, help="only the first N pairs (0: all)")
    parser.add_argument("--json", metavar="FILE")
    args = parser.parse_args()
    torch.set_num_threads(2)
    cv2.setNumThreads(2)
    matlab = SurfConfig(max_keypoints=args.max_keypoints, metric_threshold=args.metric_threshold)
    tuned = SurfConfig(max_keypoints=args.max_keypoints, metric_threshold=300.0, upsample=True)
    paths = [p for p in list_shared_pairs(Path(args.data)) if "middlebury" in str(p)]
    paths = paths[:args.limit] if args.limit else paths
    methods = {
        "SURF MATLAB defaults, SAD": (lambda im: surf_features(im, matlab), "sad"),
        "SURF x2 thr 300, SAD": (lambda im: surf_features(im, tuned), "sad"),
        "OpenCV SIFT, L2": (lambda im: sift_features(im, args.max_keypoints), "l2"),
    }
    report = {"metadata": {**run_metadata(2), "max_keypoints": args.max_keypoints,
                           "metric_threshold": args.metric_threshold}, "results": {}}
    print("mean over pairs; precision = share of ratio-test matches within 1 px of GT disparity")
    for resolution in ("320x240", "native"):
        batches = [load_stereo_pair(p) for p in paths]
        if resolution == "320x240":
            batches = [resize_stereo_batch(b, (320, 240)) for b in batches]
        for ratio in (0.8, 0.6):
            for name, (extract, metric) in methods.items():
                rows = [{"pair": b.names[0], **evaluate(b, extract, ratio, metric)} for b in batches]
                report["results"][f"{resolution} ratio {ratio} {name}"] = rows
                print(f"{resolution:8s} ratio {ratio} {name:26s} pairs {len(rows):3d}  keypoints "
                      f"{summarise(rows, 'keypoints'):6.1f}  repeatability {summarise(rows, 'repeatability'):.3f}  "
                      f"precision {summarise(rows, 'precision'):.3f}  correct {summarise(rows, 'correct_matches'):6.1f}")
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
