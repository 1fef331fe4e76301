"""Pairs rectified by a chessboard calibration: should the pipeline rectify them again from F (``rectify="auto"``,
``"required"``) or not (``"off"``, what ``--calibration`` sets)?

The shared OpenCV chessboard pairs are calibrated (:mod:`svs_torch.chessboard`, nominal 25 mm squares), rectified
with it (:func:`svs_torch.calibration.rectify_with_calibration`) and ranged under each setting. The truth is the
calibration's own: each corner's disparity after rectification (x_left − x_right of the corners found by OpenCV,
mapped by the rectification), so a corner's depth is f·B / d. Reported per setting: how many pairs the pipeline
rectified again from F, the pipeline's dense disparity at the corners against the corners' (median |error| per
pair, over the pairs it did not rectify again: after a second rectification the maps are in other pixels), and the
nearest obstacle's distance per pair against the board's nearest corner (the board is the nearest object in every
pair).

    python experiments/calibrated_rectify.py [--data DIR] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import torch

from svs_torch.calibration import rectify_with_calibration
from svs_torch.chessboard import calibrate_stereo_rig, collect_board_views, rectified_corners
from svs_torch.data import collate_stereo_batches, load_image_pair
from svs_torch.files import write_bytes_atomic
from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth

BOARD, SQUARE_M = (9, 6), 0.025


def measure(data: Path) -> dict:
    lefts = sorted((data / "opencv_samples").glob("left*.jpg"))
    rights = [left.with_name(left.name.replace("left", "right")) for left in lefts]
    pairs = [(str(left), cv2.imread(str(left), 0), cv2.imread(str(right), 0)) for left, right in zip(lefts, rights)]
    views = collect_board_views(pairs, BOARD)
    rig = calibrate_stereo_rig(views, SQUARE_M, BOARD, "experiment")
    corners_left, corners_right = rectified_corners(rig, views)
    batch = collate_stereo_batches([rectify_with_calibration(load_image_pair(left, right), rig)
                                    for left, right in zip(lefts, rights)])
    out = {"rms_stereo_px": rig.rms_stereo_px, "row_error_mean_px": rig.row_error_mean_px, "settings": {}}
    for mode in ("off", "auto", "required"):
        with torch.no_grad():
            result = estimate_obstacle_depth(batch, replace(PipelineConfig(), rectify=mode))
        rows = []
        for i, left in enumerate(lefts):
            truth_px = corners_left[i][:, 0] - corners_right[i][:, 0]
            nearest_corner_m = float(rig.focal_px * rig.baseline_m / truth_px.max())
            x, y = (np.round(corners_left[i][:, k]).astype(int) for k in (0, 1))
            error = None
            if not bool(result.rectified[i]):
                found = result.dense.disparity_px[i, 0].numpy()[y, x]
                valid = result.dense.valid[i, 0].numpy()[y, x]
                error = float(np.median(np.abs(found[valid] - truth_px[valid]))) if valid.any() else None
            nearest = float(result.depth.nearest.depth_m[i]) if bool(result.depth.nearest.valid[i]) else None
            rows.append({"pair": left.name, "rectified_again": bool(result.rectified[i]),
                         "corner_disparity_error_px": error, "nearest_m": nearest,
                         "board_nearest_corner_m": nearest_corner_m})
        out["settings"][mode] = rows
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    parser.add_argument("--json", help="write the rows here")
    args = parser.parse_args()
    out = measure(Path(args.data))
    print(f"calibration: RMS stereo {out['rms_stereo_px']:.3f} px, rectified row error {out['row_error_mean_px']:.3f} px")
    for mode, rows in out["settings"].items():
        errors = [r["corner_disparity_error_px"] for r in rows if r["corner_disparity_error_px"] is not None]
        print(f"rectify={mode}: rectified again from F {sum(r['rectified_again'] for r in rows)}/{len(rows)}; "
              f"corner disparity |error| per pair: median {np.median(errors):.2f} px over {len(errors)} pairs, "
              f"within 1 px on {sum(e <= 1 for e in errors)}")
        for r in rows:
            nearest = "-" if r["nearest_m"] is None else f"{r['nearest_m']:.3f}"
            error = "-" if r["corner_disparity_error_px"] is None else f"{r['corner_disparity_error_px']:.2f}"
            print(f"  {r['pair']:<11} again {str(r['rectified_again']):<5} corner error {error:>6} px  nearest "
                  f"{nearest:>6} m  board's nearest corner {r['board_nearest_corner_m']:.3f} m")
    if args.json:
        write_bytes_atomic(args.json, json.dumps(out, indent=1).encode())


if __name__ == "__main__":
    main()
