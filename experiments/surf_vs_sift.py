"""svs_torch features (a named configuration) against OpenCV SIFT on real stereo pairs with GT disparity (issue:
features, item 3 "precise geometry at the defaults").

For every Middlebury pair of the shared data (41), resampled to 320×240 (SVS size) and/or at native size:
- repeatability: share of left keypoints (with known GT) whose GT-corresponding right location (x − d, y) has a
  right keypoint within 1.5 px and of similar scale (ratio within 1.5);
- matching precision: share of ratio-test matches (among those with GT at the left point) whose disparity
  x_left − x_right is within 1 px of GT, with the number of correct matches (precision alone rewards matching
  almost nothing) and the share with |y_left − y_right| ≤ 0.5 px among the matches within 3 px (localisation).

svs_torch runs each ``--config`` (a named :data:`PRESETS` entry: SURF options, SAD matching with its gates, and
the optional Lucas–Kanade refinement of the matched points); OpenCV SIFT keeps its ``--max-keypoints``
strongest points and is matched by L2 nearest neighbour with the SAME ratio rule (``--ratios``) — nothing else,
unless ``--sift-mutual`` (then both rows are printed). Prints a table and writes JSON with metadata.

    python experiments/surf_vs_sift.py [--config paper --config recommended] [--ratios 0.8 0.6]
        [--resolutions 320x240 native] [--limit N] [--json out.json]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # a shared machine: no spinning OpenMP threads

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
from dataclasses import asdict, dataclass, field, replace  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from svs_torch.data import list_shared_pairs, load_stereo_pair, resize_stereo_batch  # noqa: E402
from svs_torch.features.detector import SurfConfig  # noqa: E402
from svs_torch.features.surf import extract_surf_features  # noqa: E402
from svs_torch.geometry.lk_refinement import refine_matches_lk
from svs_torch.geometry.matched_points import gather_matched_points
from svs_torch.geometry.matching import match_sad

sys.path.insert(0, str(Path(__file__).resolve().parent))
from svs_torch.cli.common import positive_int, unit_interval_float  # noqa: E402
from run_metadata import (add_data_option, command_line, output_path, run_metadata, run_script,  # noqa: E402
                          scene_limit, write_text_whole)

TOLERANCE_PX = 1.5
SCALE_RATIO = 1.5


@dataclass(frozen=True)
class FeatureSetup:
    """Everything that decides svs_torch's matched points and F: the fields of ``PipelineConfig`` that matter
    here, plus the match refinement (``refine``: keyword arguments of :func:`refine_matches_lk`, None = off)."""

    surf: SurfConfig = field(default_factory=SurfConfig)
    max_ratio: float = 0.6
    mutual: bool = False
    laplacian_gate: bool = True
    epipolar_band_px: float | None = None
    refine: dict | None = None
    ransac_threshold_px: float = 1.0
    ransac_scoring: str = "msac"


def _from_pipeline(config) -> FeatureSetup:
    refine = config.refine_matches
    return FeatureSetup(surf=config.surf, max_ratio=config.max_ratio, mutual=config.mutual,
                        laplacian_gate=config.laplacian_gate, epipolar_band_px=config.epipolar_band_px,
                        refine=asdict(refine) if refine is not None else None,
                        ransac_threshold_px=config.ransac_threshold_px, ransac_scoring=config.ransac_scoring)


def _presets() -> dict[str, FeatureSetup]:
    from svs_torch.pipeline import PipelineConfig

    recommended = FeatureSetup(surf=SurfConfig(metric_threshold=300.0, upsample=True), max_ratio=0.8,
                               refine={"radius_scales": 1.5, "min_radius_px": 3.0, "max_radius_px": 12.0,
                                       "iterations": 8, "max_shift_px": 2.0, "min_correlation": 0.0})
    return {
        # MATLAB detectSURFFeatures / matchFeatures defaults (PipelineConfig.paper()'s feature stages).
        "paper": _from_pipeline(PipelineConfig.paper()),
        # Whatever PipelineConfig() (the product) uses today.
        "product": _from_pipeline(PipelineConfig()),
        # The best measured configuration (this issue); see the report in the issue thread.
        "recommended": recommended,
        # The refinement's correlation gate raised: drops matches whose patches disagree after alignment.
        "recommended-ncc50": replace(recommended, refine={**recommended.refine, "min_correlation": 0.5}),
        "recommended-ncc70": replace(recommended, refine={**recommended.refine, "min_correlation": 0.7}),
        # Without the x2 upsampling (a quarter of the detector's work), the same threshold, gates and refinement.
        "noupsample-ncc70": FeatureSetup(surf=SurfConfig(metric_threshold=300.0), max_ratio=0.8,
                                         refine={**recommended.refine, "min_correlation": 0.7}),
        "noupsample100-ncc70": FeatureSetup(surf=SurfConfig(metric_threshold=100.0), max_ratio=0.8,
                                            refine={**recommended.refine, "min_correlation": 0.7}),
        "noupsample100-ncc70-r8": FeatureSetup(surf=SurfConfig(metric_threshold=100.0), max_ratio=0.8,
                                               refine={**recommended.refine, "min_correlation": 0.7,
                                                       "max_radius_px": 8.0}),
        "noupsample100-ncc70-r6": FeatureSetup(surf=SurfConfig(metric_threshold=100.0), max_ratio=0.8,
                                               refine={**recommended.refine, "min_correlation": 0.7,
                                                       "max_radius_px": 6.0}),
        # The same with 128-D (extended) descriptors.
        "recommended-128": replace(recommended, surf=replace(recommended.surf, extended=True)),
        # The earlier tuning: x2 upsampling and MetricThreshold 300, no refinement.
        "upsample300": replace(recommended, refine=None, max_ratio=0.6),
        # MATLAB's detector and matcher defaults plus the match refinement only.
        "paper+refine": replace(_from_pipeline(PipelineConfig.paper()), refine=recommended.refine),
    }


PRESETS = _presets()


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


def l2_ratio_matches(left_desc: np.ndarray, right_desc: np.ndarray, ratio: float, mutual: bool = False
                     ) -> np.ndarray:
    """Nearest-neighbour L2 matches passing the ratio test ``d1 < ratio · d2``: ``(M, 2)`` index pairs."""
    if len(left_desc) < 1 or len(right_desc) < 2:
        return np.zeros((0, 2), int)
    distance = torch.cdist(torch.from_numpy(left_desc).double()[None], torch.from_numpy(right_desc).double()[None])[0]
    best = torch.topk(distance, 2, dim=1, largest=False)
    keep = best.values[:, 0] < ratio * best.values[:, 1]
    if mutual:
        keep &= distance.argmin(dim=0)[best.indices[:, 0]] == torch.arange(len(left_desc))
    left = torch.nonzero(keep).squeeze(1)
    return torch.stack([left, best.indices[keep, 0]], dim=1).numpy()


def match_quality(batch, left_xy: np.ndarray, right_xy: np.ndarray) -> dict:
    """Precision within 1 px of GT disparity, correct count, and |dy| ≤ 0.5 share of the matches within 3 px."""
    if len(left_xy) == 0:
        return {"precision": float("nan"), "correct_matches": 0, "matches_with_gt": 0, "dy_within_half": float("nan")}
    d, ok = gt_disparity_at(batch, left_xy)
    error = np.abs(left_xy[:, 0] - right_xy[:, 0] - d)
    correct = ok & (error <= 1.0)
    near = ok & (error <= 3.0)
    dy = np.abs(left_xy[near, 1] - right_xy[near, 1])
    return {"precision": float(correct[ok].mean()) if ok.any() else float("nan"), "correct_matches": int(correct.sum()),
            "matches_with_gt": int(ok.sum()), "dy_within_half": float((dy <= 0.5).mean()) if len(dy) else float("nan")}


def sift_features(image: torch.Tensor, max_keypoints: int):
    gray = (image[0, 0] * 255).round().to(torch.uint8).numpy()
    sift = cv2.SIFT_create(nfeatures=max_keypoints)
    keypoints, descriptors = sift.detectAndCompute(gray, None)
    xy = np.array([k.pt for k in keypoints], np.float64).reshape(-1, 2)
    scale = np.array([k.size for k in keypoints], np.float64)
    return xy, scale, (descriptors if descriptors is not None else np.zeros((0, 128), np.float32))


def evaluate_sift(batch, max_keypoints: int, ratio: float, mutual: bool) -> dict:
    left_xy, left_scale, left_desc = sift_features(batch.left, max_keypoints)
    right_xy, right_scale, right_desc = sift_features(batch.right, max_keypoints)
    matches = l2_ratio_matches(left_desc, right_desc, ratio, mutual)
    return {"keypoints": int(len(left_xy)),
            "repeatability": repeatability(batch, left_xy, left_scale, right_xy, right_scale),
            **match_quality(batch, left_xy[matches[:, 0]], right_xy[matches[:, 1]])}


def svs_matched_points(left: torch.Tensor, right: torch.Tensor, setup: FeatureSetup, max_ratio: float | None = None):
    """Features of both sides (one batch of 2B images), SAD matches with the setup's gates, and the (optionally
    refined) matched points: ``(features_left_keypoints, features_right_keypoints, MatchedPoints)``."""
    b = left.shape[0]
    both = extract_surf_features(torch.cat([left, right]), setup.surf)
    kp, desc = both.keypoints, both.descriptors
    gate = setup.laplacian_gate
    matches = match_sad(desc[:b], desc[b:], kp.valid[:b], kp.valid[b:],
                        max_ratio=setup.max_ratio if max_ratio is None else max_ratio, mutual=setup.mutual,
                        laplacian_left=kp.laplacian_sign[:b] if gate else None,
                        laplacian_right=kp.laplacian_sign[b:] if gate else None,
                        xy_left=kp.xy[:b], xy_right=kp.xy[b:], epipolar_band_px=setup.epipolar_band_px)
    points = gather_matched_points(kp.xy[:b].double(), kp.xy[b:].double(), matches)
    if setup.refine is not None:
        points = refine_matches_lk(left, right, points, kp.scale[:b], **setup.refine)
    return kp, points


def evaluate_svs(batch, setup: FeatureSetup, ratio: float) -> dict:
    kp, points = svs_matched_points(batch.left, batch.right, setup, ratio)
    valid = kp.valid.numpy()
    xy, scale = kp.xy.double().numpy(), kp.scale.double().numpy()
    keep = points.valid[0].numpy()
    return {"keypoints": int(valid[0].sum()),
            "repeatability": repeatability(batch, xy[0][valid[0]], scale[0][valid[0]], xy[1][valid[1]],
                                           scale[1][valid[1]]),
            **match_quality(batch, points.left[0].numpy()[keep], points.right[0].numpy()[keep])}


def summarise(rows: list[dict], key: str) -> float:
    values = [r[key] for r in rows if not np.isnan(r[key])]
    return statistics.mean(values) if values else float("nan")


def setup_json(setup: FeatureSetup) -> dict:
    return {**asdict(setup), "surf": asdict(setup.surf)}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_option(parser)
    parser.add_argument("--config", action="append", choices=sorted(PRESETS),
                        help="svs_torch configuration(s) to evaluate (default: paper, product, recommended)")
    parser.add_argument("--max-keypoints", type=positive_int, default=512, help="keypoints per image, SURF and SIFT")
    parser.add_argument("--ratios", type=unit_interval_float, nargs="+", default=[0.8, 0.6],
                        help="ratio rules, applied to all")
    parser.add_argument("--resolutions", nargs="+", default=["320x240", "native"], choices=["320x240", "native"],
                        help="320x240 and/or native (default: %(default)s)")
    parser.add_argument("--sift-mutual", action="store_true", help="also SIFT with a mutual nearest-neighbour check")
    parser.add_argument("--limit", type=scene_limit, help="only the first N pairs (0: all)")
    parser.add_argument("--threads", type=positive_int, default=1, help="torch and OpenCV threads (default 1)")
    parser.add_argument("--json", type=output_path, metavar="FILE", help="write the report as JSON to FILE")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    names = args.config or ["paper", "product", "recommended"]
    setups = {name: replace(PRESETS[name], surf=replace(PRESETS[name].surf, max_keypoints=args.max_keypoints))
              for name in names}
    paths = [p for p in list_shared_pairs(Path(args.data)) if "middlebury" in str(p)]
    paths = paths[:args.limit] if args.limit else paths
    report = {"metadata": {**run_metadata(args.threads, command=command_line("experiments/surf_vs_sift.py", argv)),
                           "max_keypoints": args.max_keypoints,
                           "configs": {n: setup_json(s) for n, s in setups.items()}}, "results": {}}
    print("mean over pairs; precision = share of ratio-test matches within 1 px of GT disparity; "
          "dy<=.5 = share of matches within 3 px with |y_l - y_r| <= 0.5 px")
    sift_variants = [False, True] if args.sift_mutual else [False]
    for resolution in args.resolutions:
        batches = [load_stereo_pair(p) for p in paths]
        if resolution == "320x240":
            batches = [resize_stereo_batch(b, (320, 240)) for b in batches]
        for ratio in args.ratios:
            methods = {f"svs_torch {n}": (lambda b, s=s: evaluate_svs(b, s, ratio)) for n, s in setups.items()}
            for mutual in sift_variants:
                methods[f"OpenCV SIFT{' mutual' if mutual else ''}"] = (
                    lambda b, m=mutual: evaluate_sift(b, args.max_keypoints, ratio, m))
            for name, evaluate in methods.items():
                rows = [{"pair": b.names[0], **evaluate(b)} for b in batches]
                report["results"][f"{resolution} ratio {ratio} {name}"] = rows
                print(f"{resolution:8s} ratio {ratio} {name:26s} pairs {len(rows):3d}  keypoints "
                      f"{summarise(rows, 'keypoints'):6.1f}  repeat {summarise(rows, 'repeatability'):.3f}  "
                      f"precision {summarise(rows, 'precision'):.3f}  correct {summarise(rows, 'correct_matches'):6.1f}"
                      f"  dy<=.5 {summarise(rows, 'dy_within_half'):.3f}", flush=True)
    if args.json:
        write_text_whole(args.json, json.dumps(report, indent=2))
    return report


if __name__ == "__main__":
    run_script(main)
