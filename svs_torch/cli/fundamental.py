"""``svs-depth fundamental``: the fundamental matrix of a stereo pair by batched RANSAC (Sec. 3.3 (3))."""

from __future__ import annotations

import argparse
import time

from .common import dumps_strict, positive_float, seed_int, too_small_reason
from .features import add_feature_options, add_pair_options, load_pair, nothing_kept_reason, to_input_pixels
from .segment import add_segmentation_options, refuse_unused_segmentation_options

HELP = "fundamental matrix of a stereo pair from SURF matches by RANSAC"

DESCRIPTION = """\
Estimate the fundamental matrix of a stereo pair as estimate does (Sec. 3.3): SURF keypoints, SAD matches with
a ratio test, then RANSAC over random 7-point samples with local optimisation. Under --preset default the
keypoints are found on the whole images, as estimate finds them (a turned or shifted camera segments each view a
little differently); under --preset paper on the segmented obstacles, with MATLAB's ratio test (--no-segment:
the whole images). F maps a left point to its right epipolar line: x_right^T F x_left = 0, in input-image
pixels, unit Frobenius norm; null (text: "no F") where no sample gave a model (TOO_FEW_MATCHES, DEGENERATE).
JSON "inliers": one [x_left, y_left, x_right, y_right] per inlier match, the points RANSAC judged (the right one
refined to sub-pixel, as estimate ranges it), input-image pixels (pixel centres at whole numbers).
"homography_share": the share of the inliers that one homography maps onto the right view within the threshold;
near 1 they lie on one plane, or the views differ by a shift (a wall facing the camera), and F is not determined
by them: every F = [e']x H fits them whatever its epipole (a warning from 0.9, on stderr). "reason" (only then): the
segmentation kept no region in a view, so the segmented obstacles held nothing to match.
"""

EPILOG = """\
examples:
  svs-depth fundamental left.png right.png
  svs-depth fundamental left.png right.png --no-segment --size 320x240 --seed 3 --json
"""


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "fundamental", help=HELP, description=DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("left", help="left image file")
    parser.add_argument("right", help="right image file, the same size as the left")
    add_pair_options(parser)
    parser.add_argument("--no-segment", action="store_true",
                        help="match features of the whole images (what --preset default does already)")
    add_segmentation_options(parser)
    add_feature_options(parser)
    parser.add_argument("--threshold-px", type=positive_float, metavar="PX",
                        help="RANSAC Sampson-distance threshold, in pixels of the pair RANSAC runs on: with --size "
                             "the resampled pair's, not the input's that F and the inliers are given in (--preset "
                             "default: 1; paper: 0.1, MATLAB's DistanceThreshold 0.01 on its square)")
    parser.add_argument("--seed", type=seed_int, default=0,
                        help="RANSAC seed: the same seed gives the same F (default: 0)")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    parser.set_defaults(func=run)


def to_input_fundamental(fundamental, factors: tuple[float, float]) -> list[list[float]]:
    """F of the working (resampled) pixels as F of the input pixels: Tᵀ F T with x_work = T x_input."""
    import torch

    fx, fy = factors
    transform = torch.tensor([[1 / fx, 0, 0.5 / fx - 0.5], [0, 1 / fy, 0.5 / fy - 0.5], [0, 0, 1]],
                             dtype=torch.float64)
    f = transform.T @ fundamental.to(torch.float64) @ transform
    norm = f.norm()
    f = f / norm if norm > 0 else f
    return [[float(v) for v in row] for row in f.tolist()]


def _inlier_points(result, factors: tuple[float, float]) -> list[list[float]]:
    """``[x_left, y_left, x_right, y_right]`` of each RANSAC inlier in input pixels, at the points RANSAC judged
    (``result.points``: the right ones refined to sub-pixel), not the keypoints: reported at the keypoints, 8 of
    Teddy's 274 inliers lay up to 1.86 px from their epipolar lines, over the 1 px threshold (an audit)."""
    points = result.points
    kept = (points.valid[0] & result.fundamental.inliers[0]).nonzero().flatten().tolist()  # one mask, not a test a slot
    return [to_input_pixels(points.left[0, i], factors) + to_input_pixels(points.right[0, i], factors) for i in kept]


#: From this share of the inliers on one homography, the text warns that they do not determine F.
PLANAR_SHARE = 0.9


def homography_share(inliers: list[list[float]], threshold_px: float) -> float | None:
    """The share of ``inliers`` (``[x_left, y_left, x_right, y_right]`` rows) that one homography, fitted by OpenCV's
    RANSAC, maps left to right within ``threshold_px``; None under 8 inliers. A pure shift of the view gave status
    OK, 478 of 478 inliers and an F whose epipolar lines stood at 68 degrees (Teddy's left view cut 12 px apart; the
    shared real pairs read 0.25-0.60) (an audit)."""
    fit = homography_fit(inliers, threshold_px)
    return None if fit is None else fit[0]


def homography_fit(inliers: list[list[float]], threshold_px: float, max_iterations: int = 2000
                   ) -> tuple[float, list[float]] | None:
    """:func:`homography_share` and each row's distance (pixels) from where that homography maps its left point in
    the right view; None under 8 inliers or where OpenCV fits none. ``max_iterations``: OpenCV's RANSAC bound (its
    default 2000), which a caller asking only whether a large share fits may lower."""
    if len(inliers) < 8:
        return None
    import cv2
    import numpy as np

    points = np.asarray(inliers, dtype=np.float64)
    homography, mask = cv2.findHomography(points[:, :2], points[:, 2:], cv2.RANSAC, threshold_px,
                                          maxIters=max_iterations)
    if mask is None:
        return None
    mapped = cv2.perspectiveTransform(points[None, :, :2], homography)[0]
    return round(float(mask.mean()), 3), np.linalg.norm(mapped - points[:, 2:], axis=1).tolist()


def _refuse_segmentation_options(args: argparse.Namespace) -> None:
    """Refuse a segmentation option given to a run that finds F from the whole images, naming the cause to drop:
    under --preset paper it is --no-segment ("use --preset paper" was the advice to a run with --preset paper; an
    audit)."""
    how, fix = (("--no-segment", " or --no-segment") if args.no_segment else
                ("as --preset default does", ", or use --preset paper (the segmented obstacles)"))
    refuse_unused_segmentation_options(args, f"this run finds F from the whole images' features ({how})", fix)


def run(args: argparse.Namespace) -> int:
    from ..core.workers import imports_without_collection

    with imports_without_collection():  # see there: the imports' objects are frozen
        from dataclasses import replace

        from ..depth.depth_types import DepthConfig
        from ..pipeline import PipelineConfig, estimate_obstacle_depth
        from ..core.types import FundamentalStatus
        from .estimate_report import IDENTICAL_VIEWS, views_identical
        from .features import preset_config

    preset = PipelineConfig.paper() if args.preset == "paper" else PipelineConfig()
    if args.no_segment or preset.features_on == "image":  # F from the whole images: segmentation changes nothing
        _refuse_segmentation_options(args)
    batch, factors = load_pair(args.left, args.right, args)
    reason = too_small_reason(batch.size_hw)
    if reason:
        report = {"status": "TOO_SMALL", "reason": reason, "F": None, "num_matches": 0, "num_inliers": 0,
                  "iterations": 0, "inliers": [], "homography_share": None, "time_s": 0.0}
        print(dumps_strict(report) if args.json else f"status TOO_SMALL: {reason}; no F")
        return 0
    base = preset_config(args)
    # F needs no depth: the paper's sparse rule skips the dense stage.
    config = replace(base, features_on="image" if args.no_segment else base.features_on, seed=args.seed,
                     ransac_threshold_px=args.threshold_px or base.ransac_threshold_px,
                     depth=DepthConfig(rule="paper"))
    started = time.perf_counter()
    result = estimate_obstacle_depth(batch, config)
    elapsed = time.perf_counter() - started
    fundamental = result.fundamental
    inliers = _inlier_points(result, factors)
    report = {
        "status": FundamentalStatus(int(fundamental.status[0])).name,
        # No sample gave a model (too few matches, or only degenerate ones): no F, not a zero matrix.
        "F": to_input_fundamental(fundamental.F[0], factors) if bool(fundamental.F[0].any()) else None,
        "num_matches": int(result.num_matches[0]),
        "num_inliers": int(fundamental.num_inliers[0]),
        "iterations": int(fundamental.iterations[0]),
        "inliers": inliers,
        "homography_share": homography_share(inliers, config.ransac_threshold_px * max(factors)),
        "time_s": round(elapsed, 6),
    }
    if config.features_on != "image":  # matched on the segmented obstacles: were there any?
        empty = nothing_kept_reason(result.segmentation, config.segmentation.segmenter)
        report.update({"reason": empty} if empty else {})
    if report["status"] != "OK" and "reason" not in report and views_identical(result, 0):
        # One image given twice read "DEGENERATE ... no sample of seven matches gave a model", where estimate says
        # what it is (an audit).
        report["reason"] = IDENTICAL_VIEWS
    _warn_if_planar(report)
    if args.json:
        print(dumps_strict(report))
        return 0
    _print_text(report, elapsed)
    return 0


def _warn_if_planar(report: dict) -> None:
    """A warning on stderr, as the other commands' are, when one homography fits the inliers (from
    :data:`PLANAR_SHARE`): it was a line of the text answer, and --json said nothing (an audit)."""
    share = report["homography_share"]
    if report["F"] is not None and share is not None and share >= PLANAR_SHARE:
        import warnings

        warnings.warn(f"{share:.0%} of the inliers fit one homography (one plane, or the view shifted): they do not "
                      "determine F, whose epipolar lines may be far from the true ones", stacklevel=3)


def _print_text(report: dict, elapsed: float) -> None:
    """The text answer: the status and counts, then F, or why there is none (the segmentation kept no region,
    the JSON's "reason", or no sample gave a model)."""
    print(f"status {report['status']}: {report['num_inliers']} inliers of {report['num_matches']} matches, "
          f"{report['iterations']} samples, {elapsed * 1e3:.0f} ms")
    if report["F"] is None:
        print(f"no F: {report.get('reason') or 'no sample of seven matches gave a model'}")
        return
    print("F (x_right^T F x_left = 0, input pixels):")
    for row in report["F"]:
        print("  " + "  ".join(f"{v: .6e}" for v in row))
