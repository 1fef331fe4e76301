"""Pairs rectified by a chessboard calibration: should the pipeline rectify them again from F (``rectify="auto"``,
``"required"``) or not (``"off"``, what ``--calibration`` sets)?

The shared OpenCV chessboard pairs are calibrated (:mod:`svs_torch.geometry.chessboard`, nominal 25 mm squares),
rectified with it (:func:`svs_torch.geometry.calibration.rectify_with_calibration`) and ranged under each setting. The
truth is the calibration's own: each corner's disparity after rectification (x_left − x_right of the corners found by
OpenCV, mapped by the rectification), so a corner's depth is f·B / d. Reported per setting: how many pairs the pipeline
rectified again from F, the pipeline's dense disparity at the corners against the corners' (median |error| per
pair, over the pairs it did not rectify again: after a second rectification the maps are in other pixels), and the
nearest obstacle's distance per pair against the board's nearest corner (the board is the nearest object in every
pair).

Second, a loosely mounted rig with exact truth: synthetic SVS scenes (:func:`svs_torch.data.random_obstacle_scenes`)
whose right camera is turned (roll, tilt, pan in degrees, ``--turn-deg``): its raw right view is the perfect one
warped by K·R·K⁻¹, and its calibration is what ``cv2.stereoRectify`` makes of that R and T. Reported: each
object's distance on the perfect rig, on the raw pairs by the uncalibrated path (the paper's), and on the raw pairs
rectified by the calibration (what ``--calibration`` runs), against the truth.

    python experiments/calibrated_rectify.py [--data DIR] [--scenes 8] [--limit N] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import torch

from svs_torch.core.files import write_bytes_atomic
from svs_torch.data import collate_stereo_batches, load_image_pair
from svs_torch.geometry.calibration import rectify_with_calibration
from svs_torch.geometry.chessboard import calibrate_stereo_rig, collect_board_views, rectified_corners
from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth

sys.path.insert(0, str(Path(__file__).resolve().parent))
from svs_torch.cli.common import positive_int, finite_float  # noqa: E402
from run_metadata import add_data_option, output_path, run_metadata, run_script, scene_limit  # noqa: E402

BOARD, SQUARE_M = (9, 6), 0.025


def measure(data: Path, limit: int | None = None) -> dict:
    """The calibration of all the chessboard pairs, and the first ``limit`` of them (None: all) ranged under each
    setting."""
    lefts = sorted((data / "opencv_samples").glob("left*.jpg"))
    rights = [left.with_name(left.name.replace("left", "right")) for left in lefts]
    pairs = [(str(left), cv2.imread(str(left), 0), cv2.imread(str(right), 0)) for left, right in zip(lefts, rights)]
    views = collect_board_views(pairs, BOARD)
    rig = calibrate_stereo_rig(views, SQUARE_M, BOARD, "experiment")
    corners_left, corners_right = rectified_corners(rig, views)
    lefts, rights = lefts[:limit], rights[:limit]
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


def loose_rig(num_scenes: int, turn_deg: tuple[float, float, float]) -> dict:
    """Object distances of the perfect rig, the loose rig uncalibrated and the loose rig calibrated (see above)."""
    from argparse import Namespace

    from svs_torch.geometry.calibration import StereoCalibration
    from svs_torch.cli.rig import with_calibrated_rectification
    from svs_torch.data import random_obstacle_scenes

    scenes = random_obstacle_scenes(num_scenes, 2, generator=torch.Generator().manual_seed(5))
    perfect = scenes.batch
    height, width = perfect.size_hw
    focal = float(perfect.focal_px[0])
    K = np.array([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1.0]])
    turn, _ = cv2.Rodrigues(np.deg2rad(np.array([turn_deg[1], turn_deg[2], turn_deg[0]])))  # about x, y, z
    T = turn @ np.array([-float(perfect.baseline_m[0]), 0, 0])  # x_right = R x_left + T
    warp = K @ turn @ np.linalg.inv(K)
    right = torch.stack([torch.from_numpy(cv2.warpPerspective(image[0].numpy(), warp, (width, height),
                                                              borderMode=cv2.BORDER_REPLICATE))
                         for image in perfect.right]).unsqueeze(1)
    raw = replace(perfect, right=right, disparity_px=None, disparity_valid=None)
    no_distortion = np.zeros(5)
    R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(K, no_distortion, K, no_distortion, (width, height), turn,
                                                T.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
    rig = StereoCalibration((width, height), K, no_distortion, K, no_distortion, turn, T, R1, R2, P1, P2, Q)
    calibrated_config = with_calibrated_rectification(PipelineConfig(), Namespace(calibration="rig"))
    runs = {"perfect rig": (perfect, PipelineConfig()), "loose rig, uncalibrated": (raw, PipelineConfig()),
            "loose rig, calibrated": (rectify_with_calibration(raw, rig), calibrated_config)}
    truth = scenes.object_depth_m.sort(dim=1).values
    out = {"turn_deg": list(turn_deg), "truth_m": truth.tolist()}
    for name, (batch, config) in runs.items():
        with torch.no_grad():
            objects = estimate_obstacle_depth(batch, config).depth.objects
        depth = torch.where(objects.valid, objects.depth_median_m, torch.full_like(objects.depth_median_m, np.nan))
        error = (depth.sort(dim=1).values - truth).abs()
        ranged = error[~error.isnan()]  # an unranged object is counted, not an infinite error (invalid JSON)
        listed = [[None if value != value else value for value in row] for row in depth.tolist()]  # NaN: None
        out[name] = {"depth_m": listed, "max_error_m": float(ranged.max()) if ranged.numel() else None,
                     "median_error_m": float(error.nanmedian()), "unranged": int((~objects.valid).sum())}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_data_option(parser)
    parser.add_argument("--scenes", type=positive_int, default=8, help="synthetic scenes of the loose rig")
    parser.add_argument("--turn-deg", type=finite_float, nargs=3, default=(1.5, 0.7, -0.5),
                        metavar=("ROLL", "TILT", "PAN"),
                        help="the loose rig's right camera turn, degrees")
    parser.add_argument("--limit", type=scene_limit,
                        help="range only the first N chessboard pairs (0: all); the calibration uses them all")
    parser.add_argument("--json", type=output_path, help="write the rows here")
    args = parser.parse_args()
    out = measure(Path(args.data), args.limit)
    print(f"calibration: RMS stereo {out['rms_stereo_px']:.3f} px, rectified row error "
          f"{out['row_error_mean_px']:.3f} px")
    for mode, rows in out["settings"].items():
        errors = [r["corner_disparity_error_px"] for r in rows if r["corner_disparity_error_px"] is not None]
        # No pair measured at its corners (rectify=required leaves them unranged): said, not a NaN median.
        spread = (f"median {np.median(errors):.2f} px over {len(errors)} pairs, within 1 px on "
                  f"{sum(e <= 1 for e in errors)}" if errors else "no pair measured at its corners")
        print(f"rectify={mode}: rectified again from F {sum(r['rectified_again'] for r in rows)}/{len(rows)}; "
              f"corner disparity |error| per pair: {spread}")
        for r in rows:
            nearest = "-" if r["nearest_m"] is None else f"{r['nearest_m']:.3f}"
            error = "-" if r["corner_disparity_error_px"] is None else f"{r['corner_disparity_error_px']:.2f}"
            print(f"  {r['pair']:<11} again {str(r['rectified_again']):<5} corner error {error:>6} px  nearest "
                  f"{nearest:>6} m  board's nearest corner {r['board_nearest_corner_m']:.3f} m")
    loose = loose_rig(args.scenes, tuple(args.turn_deg))
    print(f"loose rig, right camera turned {loose['turn_deg']} deg (roll, tilt, pan), {args.scenes} synthetic scenes:")
    for name in ("perfect rig", "loose rig, uncalibrated", "loose rig, calibrated"):
        row = loose[name]
        worst = "-" if row["max_error_m"] is None else f"{row['max_error_m']:.3f} m"
        print(f"  {name:<24} object distance error: median {row['median_error_m']:.3f} m, max of those ranged "
              f"{worst}, unranged objects {row['unranged']}")
    out["loose_rig"] = loose
    out["metadata"] = run_metadata(torch.get_num_threads())
    if args.json:
        write_bytes_atomic(args.json, json.dumps(out, indent=1).encode())


if __name__ == "__main__":
    run_script(main)
