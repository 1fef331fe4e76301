"""``svs-depth estimate``: the distance to the obstacles of a stereo pair (or of many pairs, in batches)."""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

from .common import (add_disparity_export_options, add_figure_option, dumps_strict, finite_float, positive_float,
                     positive_int, seed_int, too_small_reason)
from .features import add_feature_options, add_pair_options, load_pair
from .progress import Progress
from .rig import (add_calibration_option, calibration_file_source, calibration_from_args, check_no_manual_calibration,
                  with_calibrated_rectification)
from .segment import add_segmentation_options, add_segmenter_option

HELP = "distance to the obstacles of a stereo pair: the whole pipeline"

DESCRIPTION = """\
Run the whole pipeline on a stereo pair: segment the obstacles (Otsu, opening, the largest regions), SURF
features, SAD matching, fundamental matrix by RANSAC, rectification, then range the obstacles.

By default (--range dense) a dense SAD block matcher measures the disparity at every pixel of the kept
regions (on the rectified pair, or the raw one when its rows already agree); each object's distance is the
median depth over its region, with its 10th/90th percentiles and the count of valid pixels; R_min / R_max are
the nearest / farthest object, and the nearest object's 10th percentile is its nearest visible surface. An
object with fewer than 20 valid pixels where the right view holds every searched disparity (a near strip on
the left border) gets no depth ("num_in_view_px" in the JSON). On the shared Middlebury scenes this is
98-99 % accurate where its settings were tuned and 92-98 % on held-out scenes (experiments/paper_table1.py).
--range paper uses the paper's own rule instead: R_min = f*B/d_max and R_max = f*B/d_min over the RANSAC
inliers (Eq. (5)-(8)), and each object's median inlier depth. --preset paper runs the paper exactly (MATLAB
defaults, --range paper). The JSON says which rule produced the numbers ("range_rule").

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
  svs-depth estimate --pairs captured/index.jsonl --size 320x240
  svs-depth estimate ../shared/data/middlebury_eval3_Q/Teddy --disparity-out maps   (maps/Teddy/disp0SVSTorch.pfm)
  svs-depth estimate --pairs list.txt --disparity-out maps --disparity-format kitti   (maps/<left name>.png)
list lines: 'LEFT RIGHT' (the calibration options, or the SVS model), 'LEFT RIGHT FOCAL_PX BASELINE_M
[DOFFS_PX]' (that pair's own), or a scene folder (MiddEval3, Middlebury, KITTI: its own calibration).

status: "OK" when the obstacles were ranged; otherwise the stage that stopped (NO_OBJECTS, TOO_FEW_KEYPOINTS,
TOO_FEW_MATCHES, RANSAC_FAILED, ...), TOO_SMALL for a pair under 5x5 pixels, or (with --pairs) BAD_INPUT for
a pair whose files cannot be read, with the reason in "reason". Numbers that do not exist are null.
"verified": at least 6 RANSAC inliers have the disparity the dense map measures at their pixel, so both views
show one scene; where not (a swapped, frozen or unplugged camera), an object needs 40 % of its region
measured instead of 10 % ("num_agreeing_inliers"; experiments/verify_views.py).
exit status: 0 every pair has its line (whatever its status); 2 bad arguments, or a single pair that cannot be
read, or (with --pairs, after every listed pair has its line, in order) at least one BAD_INPUT pair.
"""


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
                             "[DOFFS_PX]' or scene folder per line, or capture's index.jsonl; every pair gets "
                             "its line, and the exit status is 2 if any listed pair is BAD_INPUT")
    # 8: whole process over 96 shared pairs at 320x240, 9.3 / 9.5-9.8 / 11.0-11.6 s at 8 / 16 / 32 (larger
    # batches pad more and leave the cache).
    parser.add_argument("--batch-size", type=positive_int, default=8,
                        help="pairs per batch with --pairs (default: 8, the fastest measured)")
    # One single-threaded worker per core: on this project's 2-core machine, 512 real pairs at 320x240 took
    # 24.8 s in one process of 2 torch threads and 17.2 s as two processes of one thread each (torch's
    # intra-op threads split ops too small to pay for it; separate processes also decode while computing).
    parser.add_argument("--workers", type=positive_int, metavar="N",
                        help="with --pairs: worker processes, each with cores / N torch threads (default: one per "
                             "core, or per OMP_NUM_THREADS if that is fewer; 1 runs in this process). The lines "
                             "come out in list order whatever N is, and each pair's numbers do not depend on it")
    parser.add_argument("--focal-px", type=positive_float,
                        help="focal length of the input images, pixels (default: the SVS model for the width)")
    parser.add_argument("--baseline-m", type=positive_float, help="stereo baseline, metres (default: SVS 0.1075)")
    parser.add_argument("--doffs-px", type=finite_float, default=0.0,
                        help="principal-point offset cx_right - cx_left, pixels (default: 0)")
    add_calibration_option(parser, "LEFT RIGHT (and listed pairs without their own calibration)")
    add_pair_options(parser)
    add_segmentation_options(parser)
    add_segmenter_option(parser)
    parser.add_argument("--canny", action="store_true", help="segment with Canny edges (the paper's comparison)")
    add_feature_options(parser)
    parser.add_argument("--range", choices=("dense", "paper"), dest="range_rule",
                        help="how to range the obstacles: 'dense' (default) the median of dense disparity over "
                             "each region, 'paper' Eq. (5)-(8) over the RANSAC inliers (default of --preset paper)")
    parser.add_argument("--seed", type=seed_int, default=0, help="RANSAC seed (default: 0)")
    add_figure_option(parser, "figure: kept objects with depths, dense depth (and ground truth), matches, and a "
                      "rectified pair: its rectified views with epipolar lines",
                      "--plot", "--out")
    parser.add_argument("--masks-out", metavar="LABELS.png",
                        help="kept objects of the left image as a uint8 label image (0 background, 1..N); "
                             "lossless: .png, .bmp or .tif")
    parser.add_argument("--json", action="store_true", help="one JSON object per pair (JSON lines)")
    add_disparity_export_options(parser)
    parser.set_defaults(func=run)


def pipeline_config_from_args(args: argparse.Namespace):
    """``--preset`` with every option the user gave (``--range``, ``--canny``, features, segmentation)."""
    from dataclasses import replace

    from .features import preset_config

    config = replace(preset_config(args), seed=args.seed)
    if args.canny:
        config = replace(config, segmentation=replace(config.segmentation, method="canny"))
    if args.range_rule:
        config = replace(config, depth=replace(config.depth, rule=args.range_rule))
    return with_calibrated_rectification(config, args)


def _read_pair_list(path: str):
    """The entries of a pair list (:func:`svs_torch.data.read_pair_list`): lines ``LEFT RIGHT``, ``LEFT RIGHT
    FOCAL_PX BASELINE_M [DOFFS_PX]`` or a scene folder, or capture's ``index.jsonl``. An entry that is not a pair
    keeps its ``problem``: it still gets its own output line."""
    from ..data import read_pair_list

    return read_pair_list(path, "pairs")


def unranged_report(status: str, reason: str, range_rule: str) -> dict:
    """The report of a pair the pipeline did not run on (``TOO_SMALL``, ``BAD_INPUT``): the keys of
    :func:`pair_report`, with null numbers, and the reason."""
    return {"status": status, "reason": reason, "range_rule": range_rule, "r_min_m": None, "r_max_m": None,
            "d_min_px": None, "d_max_px": None, "nearest_m": None, "nearest_side": "none", "nearest_surface_m": None,
            "objects": [], "num_keypoints": [0, 0], "num_matches": 0, "num_inliers": 0, "rectified": False,
            "dense_box_xywh": None, "time_s": 0.0, "calibration": None}


def _calibration_source(source, args) -> str:
    """Where pair ``source``'s calibration comes from: ``--calibration``'s file, its own data or list line, the
    command's options, or the SVS model."""
    from ..data import pair_calibration_source

    return calibration_file_source(args, source) or pair_calibration_source(source, args.focal_px, args.baseline_m)


def with_calibration(report: dict, batch, index: int, factors: tuple[float, float], source: str) -> dict:
    """``report`` with the calibration its metres use, for the INPUT image size, and where it came from
    (:func:`svs_torch.data.calibration_record`)."""
    from ..data import calibration_record

    return {**report, "calibration": calibration_record(batch, index, source, factors[0])}


def pair_report(result, index: int, factors: tuple[float, float], elapsed_s: float) -> dict:
    """JSON-ready summary of pair ``index`` of a :class:`~svs_torch.pipeline.PipelineResult`."""
    from ..depth.sparse import ObstacleSide
    from ..pipeline import PipelineStatus

    rng, objects = result.depth.range, result.depth.objects
    regions = result.segmentation.left.regions
    fx, fy = factors

    def number(value, valid) -> float | None:
        return round(float(value), 4) if bool(valid) else None

    report_objects = []
    for slot, label in enumerate(result.segmentation.left.kept_labels[index].tolist()):
        if label < 0:
            continue
        x0, y0, x1, y1 = regions.bbox_xyxy[index, label - 1].tolist()
        report_objects.append({
            "label": slot + 1,
            "area_px": int(round(int(regions.area_px[index, label - 1]) * fx * fy)),
            "bbox_xyxy": [int(round(x0 * fx)), int(round(y0 * fy)), int(round(x1 * fx)), int(round(y1 * fy))],
            "depth_m": number(objects.depth_median_m[index, slot], objects.valid[index, slot]),
            "depth_p10_m": number(objects.depth_low_m[index, slot], objects.valid[index, slot]),
            "depth_p90_m": number(objects.depth_high_m[index, slot], objects.valid[index, slot]),
            "num_inliers": int(objects.num_inliers[index, slot]),
            "num_valid_px": (int(objects.num_valid_px[index, slot]) if objects.num_valid_px is not None else None),
            "num_in_view_px": (int(objects.num_in_view_px[index, slot]) if objects.num_in_view_px is not None
                               else None),
            "side": ObstacleSide(int(objects.side[index, slot])).name.lower(),
        })
    nearest = result.depth.nearest
    return {
        "status": PipelineStatus(int(result.status[index])).name,
        "range_rule": result.range_rule,
        "r_min_m": number(rng.r_min_m[index], rng.valid[index]),
        "r_max_m": number(rng.r_max_m[index], rng.valid[index]),
        "d_min_px": number(rng.d_min_px[index], rng.valid[index]),
        "d_max_px": number(rng.d_max_px[index], rng.valid[index]),
        "nearest_m": number(nearest.depth_m[index], nearest.valid[index]),
        "nearest_side": ObstacleSide(int(nearest.side[index])).name.lower(),
        "nearest_surface_m": number(nearest.surface_m[index], nearest.valid[index]),
        "objects": report_objects,
        "num_keypoints": [int(v) for v in result.num_keypoints[index].tolist()],
        "num_matches": int(result.num_matches[index]),
        "num_inliers": int(result.num_inliers[index]),
        "num_agreeing_inliers": (int(result.num_agreeing_inliers[index]) if result.num_agreeing_inliers is not None
                                 else None),
        "verified": bool(result.verified[index]) if result.verified is not None else None,
        "rectified": bool(result.rectified[index]),
        # The box the dense stage searched (x0, y0, width, height; the pixels of the image it ran on, e.g. of
        # --disparity-out's map; rectified pixels for a rectified pair): each object's depth statistics are over
        # its region's pixels inside it.
        "dense_box_xywh": ([int(v) for v in result.dense.crop_xywh[index].tolist()] if result.dense is not None
                           else None),
        "time_s": round(elapsed_s, 6),
    }


def format_report(report: dict, nearest_name: str = "nearest obstacle") -> list[str]:
    """The text lines of :func:`pair_report`'s ``report``. ``nearest_name``: what the obstacle ranged nearest is
    called (``demo`` says "nearest kept obstacle" when its ground truth holds a nearer one that was not kept)."""
    if report.get("reason"):
        return [f"status {report['status']}: {report['reason']}"]
    lines = [f"status {report['status']}: {report['num_keypoints'][0]}+{report['num_keypoints'][1]} keypoints, "
             f"{report['num_matches']} matches, {report['num_inliers']} inliers, {report['time_s'] * 1e3:.0f} ms"]
    if report.get("calibration"):
        from ..data import format_calibration

        lines.append(f"  {format_calibration(report['calibration'])}")
    if report["r_min_m"] is not None:
        lines.append(f"  R_min {report['r_min_m']:.3f} m (d_max {report['d_max_px']:.2f} px), "
                     f"R_max {report['r_max_m']:.3f} m (d_min {report['d_min_px']:.2f} px), "
                     f"{report['range_rule']} rule")
    for obj in report["objects"]:
        depth = "no depth"
        if obj["depth_m"] is not None:
            depth = f"{obj['depth_m']:.3f} m (p10 {obj['depth_p10_m']:.3f}, p90 {obj['depth_p90_m']:.3f})"
        support = f"{obj['num_inliers']} inliers"
        if obj["num_valid_px"] is not None:
            support = f"{obj['num_valid_px']} valid px"
            if obj["num_in_view_px"] < obj["num_valid_px"]:  # some near the left border, where a match may be lost
                support += f" ({obj['num_in_view_px']} where the right view holds every searched disparity)"
        lines.append(f"  object {obj['label']}: {depth}, {support}, {obj['side']}, {obj['area_px']} px, "
                     f"box {obj['bbox_xyxy']}")
    if report["nearest_m"] is not None:
        lines.append(f"  {nearest_name}: {report['nearest_m']:.2f} m, {report['nearest_side']} "
                     f"(nearest surface {report['nearest_surface_m']:.2f} m)")
    return lines


def _write_outputs(args, batch, result, factors) -> None:
    from ..plotting.figures import labels_image, write_image_atomic
    from ..plotting.plots import estimate_figure

    if args.figure:
        from ..plotting.rectified import pipeline_rectified_figure, stack_images

        figure = estimate_figure(batch, result, 0)
        # A rectified pair also shows as rectified, with epipolar lines: the user sees that rectification worked.
        rectified = pipeline_rectified_figure(batch, result, 0, args.calibration)
        write_image_atomic(args.figure, figure if rectified is None else stack_images(figure, rectified),
                           args.figure_option)
    if args.masks_out:
        write_image_atomic(args.masks_out, labels_image(result.segmentation.left, 0, factors), "--masks-out",
                           lossless=True)


def _check_disparity_out(args: argparse.Namespace, range_rule: str | None) -> None:
    """``--disparity-out``'s folder made, or its error raised, before any work (standard library only)."""
    if args.disparity_out:
        from ..core.errors import InputError
        from ..core.files import make_output_folder

        if range_rule == "paper":
            raise InputError("--disparity-out: expected the dense range rule (the paper's rule measures no dense "
                             "map), got --range paper")
        make_output_folder(args.disparity_out, "--disparity-out")


#: This process's export of ``--disparity-out`` (one per worker), so two listed pairs of one name are caught.
_EXPORTS: dict[tuple, object] = {}


def _write_disparity(args: argparse.Namespace, batch, result, time_s: float) -> None:
    """Write the run's dense maps into ``--disparity-out`` (a pair that would overwrite another of this
    process's is skipped with a warning naming both)."""
    if not args.disparity_out:
        return
    import warnings

    from ..core.errors import InputError
    from ..evaluation.export import DisparityExport

    key = (args.disparity_out, args.disparity_format, args.method_name)
    export = _EXPORTS.setdefault(key, DisparityExport(Path(args.disparity_out), args.disparity_format,
                                                      args.method_name))
    try:
        export.write(batch, result, time_s)
    except InputError as error:
        warnings.warn(str(error), RuntimeWarning, stacklevel=2)


def run(args: argparse.Namespace) -> int:
    if args.pairs:  # before any heavy import: the workers may be started without torch in this process
        from . import CliError

        if args.left or args.right or args.figure or args.masks_out:
            raise CliError("pairs: give either LEFT RIGHT or --pairs (--figure and --masks-out need one pair)")
        _check_disparity_out(args, args.range_rule or ("paper" if getattr(args, "preset", None) == "paper"
                                                       else None))
        return _run_many(args)
    from ..core.workers import imports_without_collection

    with imports_without_collection():  # see there: the imports' objects are frozen
        from ..core.errors import InputError
        from ..data import PairSource, detect_stereo_layout
        from ..plotting.figures import check_output_path
        from ..pipeline import estimate_obstacle_depth

    config = pipeline_config_from_args(args)
    scene = bool(args.left) and not args.right and detect_stereo_layout(args.left) is not None
    if not (args.left and args.right) and not scene:
        raise InputError("left, right: expected two image files, or a scene folder (or --pairs LIST.txt)")
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
    _check_disparity_out(args, config.depth.rule)
    source = PairSource(left=args.left, right=None if scene else args.right, scene=scene)
    if scene:
        batch, factors = _load_source(source, args)
    else:
        batch, factors = load_pair(args.left, args.right, args)
    reason = too_small_reason(batch.size_hw)
    if reason:
        report = unranged_report("TOO_SMALL", reason + "; nothing to range, no file written", config.depth.rule)
    else:
        started = time.perf_counter()
        result = estimate_obstacle_depth(batch, config)
        report = pair_report(result, 0, factors, time.perf_counter() - started)
        report = with_calibration(report, batch, 0, factors, _calibration_source(source, args))
        _write_outputs(args, batch, result, factors)
        _write_disparity(args, batch, result, report["time_s"])
    print(dumps_strict(report) if args.json else "\n".join(format_report(report)), flush=True)
    return 0


def _load_source(source, args: argparse.Namespace):
    """A scene folder or a pair with its own calibration, resampled to ``--size`` as :func:`load_pair` does."""
    from ..core.camera import parse_size
    from ..data import load_pair_source, resize_stereo_batch

    batch = load_pair_source(source)
    if not args.size:
        return batch, (1.0, 1.0)
    (height, width), (new_w, new_h) = batch.size_hw, parse_size(args.size, "--size")
    return resize_stereo_batch(batch, (new_w, new_h)), (width / new_w, height / new_h)


def _load_entry(source, args) -> tuple[str | None, str | None, object]:
    """(status, reason, loaded pair) of one list entry: a pair to run has status None. Scenes and pairs listed
    with a calibration keep their own; the others take the command's (or the SVS model)."""
    from ..core.errors import InputError

    if source.problem:
        return "BAD_INPUT", source.problem, None
    try:
        own = source.scene or source.focal_px is not None
        loaded = _load_source(source, args) if own else load_pair(source.left, source.right, args)
    except (InputError, OSError) as error:
        return "BAD_INPUT", " ".join(str(error).split()), None
    reason = too_small_reason(loaded[0].size_hw)
    return ("TOO_SMALL", reason, None) if reason else (None, None, loaded)


def _estimate_chunk(chunk, args: argparse.Namespace, config) -> list[tuple[dict, str | None]]:
    """One batch of list entries run through the pipeline: each entry's report (with its ``left`` and
    ``right``) and, for a BAD_INPUT entry, the reason."""
    from ..data import collate_stereo_batches
    from ..pipeline import estimate_obstacle_depth

    entries = [_load_entry(entry, args) for entry in chunk]
    runnable = [loaded for _, _, loaded in entries if loaded is not None]
    result, per_pair = None, 0.0
    if runnable:
        # Pairs of different sizes are padded at the bottom/right: their pixel coordinates stay as they are.
        batch = collate_stereo_batches([b for b, _ in runnable], mode="pad")
        started = time.perf_counter()
        result = estimate_obstacle_depth(batch, config)
        per_pair = (time.perf_counter() - started) / len(runnable)
        _write_disparity(args, batch, result, per_pair)
    row, out = 0, []
    for source, (status, reason, loaded) in zip(chunk, entries):
        if loaded is None:
            report, bad = unranged_report(status, reason, config.depth.rule), reason if status == "BAD_INPUT" else None
        else:
            report, bad = pair_report(result, row, loaded[1], per_pair), None
            report = with_calibration(report, batch, row, loaded[1], _calibration_source(source, args))
            row += 1
        out.append(({"left": source.left, "right": source.right, **report}, bad))
    return out


#: This worker process's pair list and pipeline configuration, made once per list (every worker reads the list
#: itself: the parent never imports torch).
_WORKER_SETUP: dict[str, tuple[list, object]] = {}


def _worker_setup(args: argparse.Namespace) -> tuple[list, object]:
    if args.pairs not in _WORKER_SETUP:
        config = pipeline_config_from_args(args)  # first, as in one process: a bad option is the error shown
        check_no_manual_calibration(args)
        calibration_from_args(args)
        _WORKER_SETUP[args.pairs] = _read_pair_list(args.pairs), config
    return _WORKER_SETUP[args.pairs]


def _worker_count(args: argparse.Namespace) -> tuple[int, str | None]:
    """Worker task: the number of listed pairs, or the one-line error of a bad list or bad options (sent back
    as text: the parent, which has not imported torch, raises it)."""
    from ..core.errors import InputError

    try:
        return len(_worker_setup(args)[0]), None
    except InputError as error:
        return 0, str(error)


def _worker_chunk(args: argparse.Namespace, start: int, stop: int, decoded: dict | None = None
                  ) -> tuple[list[tuple[dict, str | None]], list[str]]:
    """Worker task: :func:`_estimate_chunk` of the list's entries ``[start, stop)``, and the warnings it raised
    (the parent shows them as its own one-line warnings). ``decoded``: image arrays the parent decoded for
    these entries (:data:`svs_torch.core.image_files.PRELOADED`), used instead of reading those files again."""
    import warnings

    from ..core.image_files import PRELOADED

    pairs, config = _worker_setup(args)
    PRELOADED.update(decoded or {})
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("default")
            lines = _estimate_chunk(pairs[start:stop], args, config)
    finally:
        PRELOADED.clear()
    return lines, [str(warning.message) for warning in caught]


def _listed_lines(path: str) -> list[tuple[str, str] | None]:
    """The list's lines read without torch, one item per non-blank, non-comment line: its two image paths for a
    plain pair line (``LEFT RIGHT`` with or without a calibration; relative to the list's folder, as
    :func:`svs_torch.data.read_pair_list` resolves them), None for any other line (an ``index.jsonl``'s all).
    Their number is about how many pairs the list holds (a scene-folder line may hold more), to choose the
    number of workers; the paths say which files to decode ahead. Neither decides a result: a list that cannot
    be read gives [] (the real reading reports why), and a line that turns into several entries only shifts
    which files are decoded ahead."""
    import shlex

    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError:
        return []
    if path.endswith(".jsonl"):
        return [None for line in text.splitlines() if line.strip()]
    lines: list[tuple[str, str] | None] = []
    for line in text.splitlines():
        try:
            fields = shlex.split(line, comments=True)
        except ValueError:
            fields = [line]
        if fields:
            paths = [str(p if Path(p).is_absolute() else Path(path).parent / p) for p in fields[:2]]
            lines.append((paths[0], paths[1]) if len(fields) in (2, 4, 5) else None)
    return lines


def _decode_while(starting, lines: list[tuple[str, str] | None], batch_size: int) -> dict[int, dict]:
    """While the thread ``starting`` waits for the workers (their server imports torch, 1.0–1.5 s, on one
    core), decode the first images of the list's ``lines`` (:func:`_listed_lines`) here on the other (cv2 and
    numpy only): {chunk index: {file key: array}}, sent with each chunk so that its worker skips those reads. A
    file that does not decode is left to the worker, which reports it as it would."""
    from ..core.errors import InputError
    from ..core.image_files import preload_key, read_image_array

    decoded: dict[int, dict] = {}
    for index, pair in enumerate(lines):
        if not starting.is_alive():
            break
        for path in pair or ():
            try:
                decoded.setdefault(index // batch_size, {})[preload_key(path)] = read_image_array(path, "pairs")
            except (InputError, OSError):
                pass
    return decoded


def _worker_results(args: argparse.Namespace, lines: list[tuple[str, str] | None], workers: int, threads: int
                    ) -> tuple[int, Iterator[list]]:
    """The number of listed pairs, and the chunks' results in list order from ``workers`` processes of
    :func:`svs_torch.core.workers.worker_pool`, each with ``threads`` torch threads (``lines``: the list's lines
    as :func:`_listed_lines` read them, for the images to decode ahead)."""
    from ..core.workers import worker_pool
    from . import CliError

    executor = worker_pool(workers, threads, ("svs_torch.pipeline",))
    counted: dict = {}

    def start() -> None:
        # One count task per worker: each starts its process now (which waits for the server's imports), and
        # every worker reads the list it will need.
        try:
            counts = [executor.submit(_worker_count, args) for _ in range(workers)]
            counted["count"] = counts[0].result()
        except BaseException as error:  # raised again in the calling thread
            counted["error"] = error

    starting = threading.Thread(target=start, name="start-workers", daemon=True)
    try:
        starting.start()
        decoded = _decode_while(starting, lines, args.batch_size)
        starting.join()
        if "error" in counted:
            raise counted["error"]
        total, problem = counted["count"]
        if problem:
            raise CliError(problem)
    except BaseException:
        executor.shutdown(wait=False, cancel_futures=True)
        raise
    return total, _ordered_chunks(executor, args, total, decoded)


def _ordered_chunks(executor, args: argparse.Namespace, total: int, decoded: dict[int, dict]) -> Iterator[list]:
    """Every chunk of the list submitted to ``executor``, its lines yielded in list order; the workers'
    warnings shown here as this process's own."""
    import warnings

    from ..core.workers import stop_worker_server

    try:
        futures = [executor.submit(_worker_chunk, args, start, min(start + args.batch_size, total),
                                   decoded.pop(start // args.batch_size, None))
                   for start in range(0, total, args.batch_size)]
        for future in futures:
            lines, messages = future.result()
            for message in messages:
                warnings.warn(message, RuntimeWarning, stacklevel=2)
            yield lines
        executor.shutdown(wait=True)  # every task is done: the workers exit before this process does
        stop_worker_server()  # and their server, waited for: their CPU time counts as this process's children's
    finally:  # an error, Ctrl-C or a closed pipe: drop what has not started, do not wait for it
        executor.shutdown(wait=False, cancel_futures=True)


def _run_many(args: argparse.Namespace) -> int:
    """Every listed pair gets exactly one line, in list order; exit 2 (after all lines) if any was BAD_INPUT.
    With more than one worker the batches run in worker processes and this process only prints."""
    from ..core.workers import imports_without_collection, thread_budget

    budget = thread_budget()
    listed = _listed_lines(args.pairs)
    chunks = -(-len(listed) // args.batch_size)
    workers = max(1, min(budget if args.workers is None else args.workers, chunks))
    if workers == 1:
        with imports_without_collection():  # the pipeline's imports (see there)
            config = pipeline_config_from_args(args)
            check_no_manual_calibration(args)
            calibration_from_args(args)
        pairs = _read_pair_list(args.pairs)
        total = len(pairs)
        results = (_estimate_chunk(pairs[start:start + args.batch_size], args, config)
                   for start in range(0, total, args.batch_size))
    else:
        total, results = _worker_results(args, listed, workers, max(1, budget // workers))
    bad = []
    # A bar for a person watching; in a log or a pipe, a plain line every few seconds and a summary.
    with Progress(total, "estimate") as progress:
        for lines in results:
            for report, reason in lines:
                if reason is not None:
                    bad.append(reason)
                heading = f"{report['left']} {report['right'] or ''}".rstrip()
                progress.write(dumps_strict(report) if args.json else "\n".join([heading, *format_report(report)]))
            progress.update(len(lines))
    if bad:
        print(f"svs-depth estimate: error: pairs: {len(bad)} of {total} pairs are BAD_INPUT (first: {bad[0]})",
              file=sys.stderr)
        return 2
    return 0
