"""``svs-depth estimate``: the distance to the obstacles of a stereo pair (or of many pairs, in batches)."""

from __future__ import annotations

import argparse
import dataclasses
import os
import time

from .common import (add_disparity_export_options, add_figure_option, check_outputs_apart, dumps_strict,
                     non_negative_int, output_file, positive_int, resolve_export_options, seed_int, too_small_reason)
from .estimate_many import _load_source, _run_many, pipeline_config_from_args
from .estimate_report import (_calibration_source, _write_disparity, format_report, pair_report, rig_size,
                              unranged_report, with_calibration)
from .features import (add_feature_options, add_pair_options, checked_size, load_pair,
                       warn_if_upsampled_large)
from .rig import (add_calibration_option, baseline_m_value, calibration_from_args, check_no_manual_calibration,
                  doffs_px_value, focal_px_value)
from .segment import add_segmentation_options, add_segmenter_option

__all__ = []


HELP = "distance to the obstacles of a stereo pair: the whole pipeline"
DESCRIPTION = """\
Run the whole pipeline on a stereo pair: segment the obstacles (by default what is near in the pair's own
disparity, the nearest region first; --floor on leaves out the floor or the road a walker's camera sees;
--segmenter otsu: the paper's brightest largest regions), SURF features, SAD matching, fundamental matrix by
RANSAC, rectification, then range the obstacles.

By default (--range dense) a dense SAD block matcher measures the disparity at every pixel of the kept
regions (on the rectified pair, or the raw one when its rows already agree); each object's distance is the
median depth over its region's interior, with its 10th/90th percentiles and the count of valid pixels (a
pixel the matcher left unmeasured takes its row's nearest measured neighbours' disparity first, so the
median is over the whole region: --disparity-out's map leaves it unknown; DenseConfig.fill_invalid);
R_min / R_max are the nearest / farthest object, and the nearest object's 10th percentile is its nearest
visible surface. An object with fewer than 20 valid pixels where the right view holds every searched
disparity (a near strip on the left border) gets no depth ("num_in_view_px" in the JSON). On the shared
Middlebury scenes (clean pairs) this is 99 % accurate where its settings were tuned and on held-out scenes
too (R_min / R_max / each object at 320 px: 99.0 / 98.8 / 98.9 %, OpenCV StereoSGBM over the same regions
98.0 / 97.9 / 96.3; experiments/paper_table1.py).
--range paper uses the paper's own rule instead: R_min = f*B/d_max and R_max = f*B/d_min over the RANSAC
inliers (Eq. (5)-(8)), and each object's median inlier depth. --preset paper runs the paper's steps (MATLAB
defaults, --range paper) but for two: MSAC scoring, and a pair whose rows already agree ranged unrectified
(the letter is eval's --preset paper --set ransac_scoring=ransac --set rectify=required, whose rectification is
degenerate on 30 of the 45 shared pairs at 320x240; PipelineConfig.paper() says why). The JSON says which rule
produced the numbers ("range_rule").

Without calibration options the SVS camera model is assumed: 3.6 mm lens on a 4.17 mm sensor (focal 276 px at
320x240, scaled with the image width) and a 10.75 cm baseline. Give --focal-px for the INPUT image size.
Every result names the calibration its metres use and where it came from (a scene's calib.txt, the list
line, the options, or "the SVS model assumed"): a "calibration" line, and "calibration" in the JSON.
"""
EPILOG = """\
examples:
  svs-depth estimate left.png right.png
  svs-depth estimate left.png right.png --size 320x240 --figure out.png --masks-out labels.png
  svs-depth estimate ../shared/data/middlebury_eval3_Q/Teddy --size 320x267 --figure teddy.png   (with its truth)
  svs-depth estimate im0.png im1.png --focal-px 1500 --baseline-m 0.08 --doffs-px 52 --json
  svs-depth estimate --pairs list.txt --json > results.jsonl     (list.txt: one 'LEFT RIGHT' per line)
  svs-depth estimate --pairs captured/index.jsonl --camera-frames   (capture's frames: JPEG, sensor noise)
  svs-depth estimate ../shared/data/middlebury_eval3_Q/Teddy --disparity-out maps   (maps/Teddy/disp0SVSTorch.pfm)
  svs-depth estimate --pairs list.txt --disparity-out maps --disparity-format kitti   (maps/<pair>.png: the
      left file's name, or its folder's for a generic one such as im0.png, left.png or L.png)
list lines: 'LEFT RIGHT' (the calibration options, or the SVS model), 'LEFT RIGHT FOCAL_PX BASELINE_M
[DOFFS_PX]' (that pair's own), or a scene folder (MiddEval3, Middlebury, KITTI: its own calibration).

status: "OK" when the obstacles were ranged; otherwise the stage that stopped (NO_OBJECTS, TOO_FEW_KEYPOINTS,
TOO_FEW_MATCHES, RANSAC_FAILED, ...), TOO_SMALL for a pair under 5x5 pixels, or (with --pairs) BAD_INPUT for
a pair whose files cannot be read, with the reason in "reason" (also set for a pair, ranged or not, whose
matches lie to the right in the right view: are LEFT and RIGHT swapped?, for one whose matches move up or down,
not along the rows: cameras one above the other (a camera held on its side), for one whose matches lie at the
same place in both views: LEFT and RIGHT one image, or whose views share almost no feature: two scenes).
Numbers that do not exist are null.
"verified": at least 5 RANSAC inliers have the disparity the dense map measures at their pixel, or RANSAC
kept 60 inliers and the map confirms 1 (a clipped or noisy view confirms few), or kept 20 and the map confirms
every one it measured, at least 3, so both views show one scene; where not (a swapped, frozen or unplugged
camera), an object needs 40 % of its region measured instead of 10 % ("num_agreeing_inliers",
"num_measured_inliers", "num_inliers"; experiments/verify_views.py).
"row_aligned": a loosely mounted right camera's rows were aligned to the left's before depth was measured (and the
pair segmented again on them); "right_camera_roll_deg" (positive: clockwise on the screen),
"right_camera_shift_y_px" (positive: lower) and "right_camera_scale_pct", what the alignment undid of that
camera's view (a rig's roll, height and zoom difference, read from the rows, where a wide lens's distortion and a
near scene add their own; calibrate measures the pose itself), and "right_camera_turn_deg": [about y, about x],
the turn its rows showed (a keystone), all undone with the alignment, or null; "exposure_matched": a pair left
unranged whose right camera is brighter or darker was run again with the two exposures matched, the darker view
mapped onto the brighter one's so that both clip the same highlights, where that map brings the views together at
the matched features (a gain, not a second lamp; PipelineConfig.exposure_retry). "coarse_dense": the
dense map measured too little of the kept regions (noisy or heavily compressed frames) and the depth was
measured again at half the working width, where each pixel averages four times as many
(PipelineConfig.coarse_retry_below_share). "features_smoothed": a pair left unverified (noisy or heavily
compressed frames: few matches) was run again with SURF on views smoothed by a Gaussian of 1.5 px, and that run
was kept (PipelineConfig.noisy_features_retry_sigma_px).
"dropped_unmeasured": 0 by default, which lists every kept region, one the dense map measured on few pixels
with their distance, one it could not range with "no depth". Set PipelineConfig.drop_unmeasured_below_share
(eval and sweep: --set drop_unmeasured_below_share=0.45) and it counts the kept regions dropped for that, not
listed in "objects"; `svs-depth eval` still scores each as an object without a distance, 0 %.
exit status: 0 every pair has its line (whatever its status); 2 bad arguments, or a single pair that cannot be
read, or (with --pairs, after every listed pair has its line, in order) at least one BAD_INPUT pair; 1 an output
(--figure, --masks-out, --disparity-out) that cannot be written, a full disk: the option and the file named, the
report printed before it; and a --disparity-out map left unwritten rather than write over an input image, a ground
truth or another listed pair's map (each warned; the run goes on, and exits 1 at the end).
"""


BATCH_SIZE_HELP = ("pairs read at a time with --pairs, run at most 32 pairs of 320x240 (2.5 megapixels) at a time "
                   "(default: 8, the fastest measured; a larger batch holds more images in memory, about 10 bytes a "
                   "pixel)")


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "estimate", help=HELP, description=DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("left", nargs="?",
                        help="left image file, or alone a scene folder (MiddEval3, Middlebury 2001-2006, KITTI, "
                             "OpenCV aloe: its own calibration, and its ground truth in the figure)")
    parser.add_argument("right", nargs="?", help="right image file, the same size as the left")
    parser.add_argument("--pairs", metavar="LIST.txt",
                        help="run many pairs: a file with one 'LEFT RIGHT', 'LEFT RIGHT FOCAL_PX BASELINE_M "
                             "[DOFFS_PX]' or scene folder per line (paths relative to the list's folder), "
                             "capture's index.jsonl, or a folder of scenes (as eval takes it); every pair gets "
                             "its line, and the exit status is 2 if any listed pair is BAD_INPUT")
    # 8: whole process over 96 shared pairs at 320x240, 9.3 / 9.5-9.8 / 11.0-11.6 s at 8 / 16 / 32 (larger
    # batches pad more and leave the cache).
    parser.add_argument("--batch-size", type=positive_int,
                        help=BATCH_SIZE_HELP)
    # One single-threaded worker per core: on this project's 2-core machine, 512 real pairs at 320x240 took
    # 24.8 s in one process of 2 torch threads and 17.2 s as two processes of one thread each (torch's
    # intra-op threads split ops too small to pay for it; separate processes also decode while computing).
    parser.add_argument("--workers", type=non_negative_int, metavar="N",
                        help="with --pairs: worker processes, each with cores / N torch threads (default: one per "
                             "core, or per OMP_NUM_THREADS if that is fewer; 0 or 1: in this process). The lines "
                             "come out in list order whatever N is, and each pair's numbers do not depend on it")
    parser.add_argument("--focal-px", type=focal_px_value,
                        help="focal length of the input images in pixels (a lens's millimetres, under 0.09 x the "
                             "width, are warned of; default: the SVS model for the width)")
    parser.add_argument("--baseline-m", type=baseline_m_value,
                        help="stereo baseline in metres, up to 2 (default: SVS 0.1075)")
    parser.add_argument("--doffs-px", type=doffs_px_value, default=0.0,
                        help="principal-point offset cx_right - cx_left, pixels (default: 0)")
    add_calibration_option(parser, "LEFT RIGHT (and listed pairs; a list line with its own FOCAL_PX BASELINE_M is "
                                   "BAD_INPUT)", kept_beside=True)
    add_pair_options(parser)
    add_segmentation_options(parser)
    add_segmenter_option(parser)
    _add_camera_frames_options(parser)
    parser.add_argument("--canny", action="store_true",
                        help="segment with Canny edges (the paper's comparison row; with --segmenter otsu or "
                             "--preset paper)")
    add_feature_options(parser)
    parser.add_argument("--range", choices=("dense", "paper"), dest="range_rule",
                        help="how to range the obstacles: 'dense' (default) the median of dense disparity over "
                             "each region, 'paper' Eq. (5)-(8) over the RANSAC inliers (default of --preset paper)")
    parser.add_argument("--seed", type=seed_int, default=0, help="RANSAC seed (default: 0)")
    add_figure_option(parser, "figure: kept objects with depths, dense depth (and ground truth), matches, and a "
                      "rectified pair: its rectified views with epipolar lines",
                      "--plot", "--out")
    parser.add_argument("--masks-out", metavar="LABELS.png", type=output_file,
                        help="kept objects of the left image as a uint8 label image (0 background, 1..N): the "
                             "pixels each object's depth is measured over (a kept region's interior, without the "
                             "band the block matcher adds around a near object); lossless: .png, .bmp or .tif")
    parser.add_argument("--json", action="store_true", help="one JSON object per pair (JSON lines), every key in "
                        "every row (null where a value does not exist); with --pairs a row's time_s is its batch's "
                        "time over the batch's pairs; pixels are the input image's, but num_valid_px, "
                        "num_in_view_px and dense_box_xywh, of the image the pipeline ran on (--size)")
    add_disparity_export_options(parser)
    parser.set_defaults(func=run)


def _add_camera_frames_options(parser: argparse.ArgumentParser) -> None:
    """``--camera-frames`` and ``--second-passes``: the pairs are a camera's, ranged as guide ranges them."""
    parser.add_argument("--camera-frames", action="store_true",
                        help="the pairs are a camera's JPEG frames with sensor noise (svs-depth capture's): the "
                             "nearness map of a pair up to 320 px wide is matched with its wider noise window at "
                             "once, without the gate that measures the noise first; a ninth less time a frame, the "
                             "same results at the board's digits 3-8 (experiments/camera_frames_gate.md). guide "
                             "always does this")
    parser.add_argument("--second-passes", choices=("on", "off"), default="on",
                        help="'off': a pair is never measured again (on a coarser grid, or with its cameras' "
                             "exposures matched), as guide --second-passes off ranges its frames, whose record "
                             "this ranges alike (default: on)")


def _write_outputs(args, batch, result, factors) -> None:
    from ..plotting.figures import labels_image, write_image_atomic
    from ..plotting.plots import estimate_figure

    if args.figure:
        from ..plotting.rectified import pipeline_rectified_figure, stack_images

        from .estimate_report import square_pixels

        # the floor's pose needs square pixels (the report says so): the figure does not draw it either
        figure = estimate_figure(batch, result if square_pixels(factors) else dataclasses.replace(result, floor=None),
                                 0, area_scale=factors[0] * factors[1])  # areas in input pixels, as the report
        # A rectified pair also shows as rectified, with epipolar lines: the user sees that rectification worked.
        rectified = pipeline_rectified_figure(batch, result, 0, args.calibration)
        write_image_atomic(args.figure, figure if rectified is None else stack_images(figure, rectified),
                           args.figure_option)
    if args.masks_out:  # each object's pixels as measured: its depth is the median over them
        from ..evaluation.stereo_metrics import measured_regions

        write_image_atomic(args.masks_out, labels_image(measured_regions(result), 0, factors), "--masks-out",
                           lossless=True)
    # Said as demo, segment and features say it; not under --json, whose caller named the files (stdout is the
    # JSON alone, stderr is for what went wrong).
    written = [f"{kind} written to {path}" for kind, path in (("figure", args.figure), ("masks", args.masks_out))
               if path]
    if written and not args.json:
        print("; ".join(written), flush=True)


def _say_what_is_no_pair(left: str | None) -> None:
    """:class:`InputError` for a run given no pair: what the one path given holds, or that it is not there (a typo
    was told "expected two image files, or a scene folder", the path unnamed: an audit)."""
    from ..core.errors import InputError

    if left and os.path.isdir(left):
        _say_what_the_folder_holds(left)
    missing = f"; no such file or folder: {left}" if left and not os.path.lexists(left) else ""
    raise InputError(f"left, right: expected two image files, or a scene folder (or --pairs LIST.txt){missing}")


def _say_what_the_folder_holds(folder: str) -> None:
    """:class:`InputError` for a folder that is no scene: it holds none, or several (an audit: both were told
    "expected two image files, or a scene folder")."""
    from ..core.errors import InputError
    from ..data.pair_list import capture_folder_hint, read_pair_sources

    try:
        scenes = read_pair_sources([folder], "left")
    except InputError:
        raise InputError(f"left: no stereo scene (MiddEval3, Middlebury 2001–2006, KITTI, OpenCV aloe) in the folder "
                         f"{folder}{capture_folder_hint(folder)}; expected a scene folder, or two image files"
                         ) from None
    whole = [scene for scene in scenes if not scene.problem]  # (not the folders of part of a scene's files)
    if not whole:  # what the folder lacks, not "holds 1 scenes; estimate ranges one scene (e.g. itself)"
        raise InputError(f"left: {scenes[0].problem}")
    raise InputError(f"left: {folder} holds {len(whole)} scenes; estimate ranges one scene (e.g. {whole[0].left}), "
                     f"eval {folder} ranges them all")


def _say_which_frame(folder: str) -> None:
    """A folder of several frames (a KITTI training folder) is ranged at its first frame: said, with how to range
    another or all of them (an audit: one row named only by the folder, and eval ranges both frames)."""
    from ..data.pair_list import read_pair_sources

    frames = read_pair_sources([folder], "left")
    if len(frames) > 1:
        import warnings

        warnings.warn(f"left: {folder} holds {len(frames)} frames; ranged {frames[0].name} alone (give a frame's left "
                      f"image, e.g. {frames[1].left}, or range every frame with eval FOLDER)", stacklevel=2)


def _check_outputs_apart(args: argparse.Namespace) -> None:
    """``--figure`` and ``--masks-out`` neither one file nor an input image. Why: ``--masks-out`` named as the left
    image wrote the labels over it (exit 0), and one name for both outputs kept only the labels."""
    check_outputs_apart([(args.figure_option, args.figure), ("--masks-out", args.masks_out),
                         ("--disparity-out", args.disparity_out)],
                        [("left image", args.left), ("right image", args.right)])


def _check_disparity_out(args: argparse.Namespace, range_rule: str | None) -> None:
    """``--disparity-out``'s folder made, or its error raised, before any work (standard library only)."""
    if args.disparity_out:
        from ..core.dataset_files import make_export_folder
        from ..core.errors import InputError

        if range_rule == "paper":
            raise InputError("--disparity-out: expected the dense range rule (the paper's rule measures no dense "
                             "map), got --range paper")
        size_wh = checked_size(args.size) if args.size else None  # (a bad size refused before the folder is made)
        make_export_folder(args.disparity_out, "--disparity-out")
        if size_wh is not None:  # maps the official tools refuse, said as eval says it (estimate wrote them unsaid)
            import warnings

            from ..core.dataset_files import resized_maps_note

            warnings.warn(resized_maps_note(size_wh), RuntimeWarning, stacklevel=2)


def _check_run_options(args: argparse.Namespace) -> None:
    """Options of a run of many pairs refused without --pairs (they ran without effect), and the export's."""
    resolve_export_options(args)
    if args.pairs is not None:  # '' ran LEFT RIGHT as if --pairs were not given
        from ..core.files import check_path_given

        check_path_given(args.pairs, "--pairs", "a list file name")
    if not args.pairs and (args.workers is not None or args.batch_size is not None):
        from . import CliError

        raise CliError(f"{'--workers' if args.workers is not None else '--batch-size'}: only with --pairs (a run of "
                       "many pairs); one pair runs in this process, as one batch")


def _run_pairs(args: argparse.Namespace) -> int:
    """``estimate --pairs``: checked before any heavy import (the workers may be started without torch here)."""
    from . import CliError

    args.batch_size = args.batch_size or 8
    if args.left or args.right:
        raise CliError("--pairs: give either LEFT RIGHT or --pairs, not both")
    one_pair = [name for name, given in ((args.figure_option, args.figure), ("--masks-out", args.masks_out)) if given]
    if one_pair:  # was "give either LEFT RIGHT or --pairs", when no LEFT RIGHT was given (an audit)
        raise CliError(f"{', '.join(one_pair)}: draws one pair, not a --pairs list: give LEFT RIGHT (or a scene "
                       "folder) instead, or leave it out")
    _check_disparity_out(args, args.range_rule or ("paper" if getattr(args, "preset", None) == "paper" else None))
    return _run_many(args)


def _warn_of_a_scenes_own_calibration(args: argparse.Namespace) -> None:
    """Warn where LEFT is a scene folder's own left view, RIGHT beside it, ranged with the SVS model although the
    folder brings a calibration (no calibration option): 'estimate Teddy/im0.png Teddy/im1.png' gave 1.25 m beside
    Teddy/calib.txt, whose own calibration gives the true 1.40 m, and only the calibration line told (an audit of
    estimate's numbers). Other images in such a folder are not its scene: OpenCV's chessboard pairs beside its Aloe
    were told to range the folder, which ranges Aloe (an audit of odd inputs)."""
    from pathlib import Path

    from ..data.datasets import SCENE_LEFT_VIEWS, detect_stereo_layout
    from ..data.calibration import SVS_MODEL_ASSUMED, scene_calibration_source

    folder = Path(args.left).parent
    if any(getattr(args, name, None) for name in ("focal_px", "baseline_m", "doffs_px", "calibration")) or \
            Path(args.right).parent != folder or \
            Path(args.left).name not in SCENE_LEFT_VIEWS.get(detect_stereo_layout(folder), ()):
        return
    own = scene_calibration_source(folder)
    if not own.startswith(SVS_MODEL_ASSUMED):
        import warnings

        warnings.warn(f"left, right: {folder} is a scene folder with its own calibration ({own}), and these images "
                      f"are ranged with the SVS model; 'svs-depth estimate {folder}' ranges the scene with its own",
                      stacklevel=2)


def run(args: argparse.Namespace) -> int:
    _check_run_options(args)
    if args.pairs:
        return _run_pairs(args)
    from ..core.workers import imports_without_collection

    with imports_without_collection():  # see there: the imports' objects are frozen
        from ..core.errors import InputError
        from ..data import PairSource, detect_stereo_layout
        from ..data.pair_list import is_kitti_left_image
        from ..plotting.figures import check_output_path
        from ..pipeline import estimate_obstacle_depth

    config = pipeline_config_from_args(args)
    # A KITTI frame's left image is its frame's scene, as in eval (a KITTI folder's warning says to give one)
    scene = bool(args.left) and not args.right and (detect_stereo_layout(args.left) is not None
                                                    or is_kitti_left_image(args.left))
    if not (args.left and args.right) and not scene:
        _say_what_is_no_pair(args.left if not args.right else None)
    if scene and (args.focal_px or args.baseline_m or args.doffs_px or args.calibration):
        raise InputError("--focal-px, --baseline-m, --doffs-px, --calibration: a scene folder brings its own "
                         "calibration")
    check_no_manual_calibration(args)
    calibration_from_args(args)  # a bad file is the error, before any work
    # Check the outputs first: a bad file name fails at once, before any work, and nothing is half-written.
    if args.figure:
        check_output_path(args.figure, args.figure_option)
    if args.masks_out:
        check_output_path(args.masks_out, "--masks-out", lossless=True)
    _check_outputs_apart(args)
    _check_disparity_out(args, config.depth.rule)
    source = PairSource(left=args.left, right=None if scene else args.right, scene=scene)
    if scene:
        _say_which_frame(args.left)
        batch, factors = _load_source(source, args)
    else:
        batch, factors = load_pair(args.left, args.right, args)
        _warn_of_a_scenes_own_calibration(args)
    reason = too_small_reason(batch.size_hw)
    warn_if_upsampled_large(config.surf.upsample, batch.size_hw)
    if reason:
        report = unranged_report("TOO_SMALL", reason + "; nothing to range, no file written", config.depth.rule)
    else:
        started = time.perf_counter()
        result = estimate_obstacle_depth(batch, config)
        report = pair_report(result, 0, factors, time.perf_counter() - started, tuple(batch.image_hw[0].tolist()))
    # A pair too small to range names its size and calibration too, as every result does (an audit: both null)
    report = with_calibration(report, batch, 0, factors, _calibration_source(source, args),
                              rig_size(source, args))
    # The pair's files first, as --pairs rows name them (a script reads one schema either way).
    report = {"left": source.left, "right": source.right, **report}
    # The report first: an output that cannot be written (a full disk: exit 1, the option and the file named)
    # does not take the pair's distances with it.
    print(dumps_strict(report) if args.json else "\n".join(format_report(report)), flush=True)
    if not reason:
        _write_outputs(args, batch, result, factors)
        _write_disparity(args, batch, result, report["time_s"])
    return 0


