"""``svs-depth features``: SURF keypoints of a stereo pair and their SAD + ratio-test matches (Sec. 3.3 (1)–(2))."""

from __future__ import annotations

import argparse
import time

from ..features.limits import (DEFAULT_MAX_KEYPOINTS, MATLAB_METRIC_THRESHOLD, MAX_KEYPOINTS,
                               PIPELINE_METRIC_THRESHOLD)
from ..geometry.match_ratios import LOWE_MAX_RATIO, MATLAB_MAX_RATIO
from .common import (_number, add_figure_option, check_outputs_apart, dumps_strict, non_negative_float, options_named,
                     too_small_reason, unit_interval_float)
from .segment import add_segmentation_options, refuse_unused_segmentation_options, warn_if_one_image_twice

HELP = "SURF keypoints of a stereo pair (on the segmented obstacles) and their matches"

DESCRIPTION = """\
Detect SURF keypoints (box-filter Hessian, upright 64-D descriptors) on both images of a pair, by default on
the segmented obstacle images as the paper does (Sec. 3.3 (1)): the regions 'svs-depth segment' shows, the
nearness segmenter's (Otsu's two largest under --preset paper). Match them by SAD with a ratio test
(--max-ratio; MATLAB's MaxRatio in --preset paper) and SURF's Laplacian-sign check (Sec. 3.3 (2); not
under --preset paper: MATLAB's matchFeatures sees only the descriptors).

Under --preset default this command keeps every keypoint the detector finds (up to 10000 per image, as
cv2.SIFT_create() keeps all) and detects on the image enlarged twice for pairs up to 1 megapixel, unless
--max-keypoints / --no-upsample say otherwise: on the shared real pairs at native size with --no-segment,
0.84-0.92 of its matched points lie within 1 px of the ground truth, against 0.77-0.86 for a plain OpenCV SIFT
loop, with 3-5x as many correct matches (experiments/features_cli_vs_sift.py). The pipeline (estimate, eval)
keeps its own settings, and detects on the whole images unless --preset paper: --no-segment --max-keypoints 512
--no-upsample shows the keypoints and matches estimate counts (num_keypoints, num_matches); --preset paper
already matches estimate --preset paper.

Keypoint positions and scales are in input-image pixels, also when --size resamples the pair first. In --json,
each keypoint has "xy_px" and "scale_px", "matches" pairs keypoint indices (their detected positions) and
"matched_xy_px" gives each match's points as the pipeline uses them, the right point refined to sub-pixel: score
matched_xy_px, not the keypoints. Where the segmentation keeps no region in a view, the status is NO_OBJECTS (as
estimate's), with the reason.
"""

EPILOG = """\
examples:
  svs-depth features left.png right.png
  svs-depth features left.png right.png --size 320x240 --figure matches.png
  svs-depth features left.png right.png --no-segment --max-keypoints 300 --json
"""


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "features", help=HELP, description=DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("left", help="left image file")
    parser.add_argument("right", help="right image file, the same size as the left")
    add_pair_options(parser)
    parser.add_argument("--no-segment", action="store_true",
                        help="detect on the whole images instead of the segmented obstacles")
    add_segmentation_options(parser)
    add_feature_options(parser, command_defaults=True)
    add_figure_option(parser, "write a figure of the keypoints and matches", "--plot", "--out")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    parser.set_defaults(func=run)


#: The largest pair the command line works on (a 4096 x 4096 frame); larger ones are resampled with --size.
MAX_PIXELS = 4096 * 4096
#: ``features``' own keypoint cap under ``--preset default``: the detector's limit
#: (:data:`svs_torch.features.limits.MAX_KEYPOINTS`), i.e. no cap in practice, as ``cv2.SIFT_create()``. The
#: pipeline's 512 suits 320x240 and RANSAC; at native size it kept a third of SIFT's correct matches
#: (``experiments/features_cli_vs_sift.py``, tuned split: 0.36 of SIFT's; 4.6x with this default and x2 detection).
COMMAND_MAX_KEYPOINTS = MAX_KEYPOINTS
#: ``features`` detects on the image enlarged twice (``--upsample``) up to this many pixels by default (more and
#: better-placed keypoints: precision 0.79 -> 0.84 on the tuned split); larger frames have keypoints enough, and
#: their enlarged scale space would cost gigabytes.
COMMAND_UPSAMPLE_MAX_PIXELS = 1024 * 1024


def add_pair_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--size", metavar="WxH",
                        help="resample the pair to this size first (e.g. 320x240, the SVS default; at most 16 "
                             "megapixels, and a pair over 16 megapixels needs it)")


def keypoint_count(text: str) -> int:
    """argparse type of ``--max-keypoints``: an integer from 1 to :data:`MAX_KEYPOINTS`."""
    value = _number(text, int)
    if not 1 <= value <= MAX_KEYPOINTS:
        raise argparse.ArgumentTypeError(f"expected an integer from 1 to {MAX_KEYPOINTS}, got {text!r}")
    return value


def add_feature_options(parser: argparse.ArgumentParser, command_defaults: bool = False) -> None:
    """The preset and the feature/matching options; each option left out keeps the preset's value (with
    ``command_defaults``, the ``features`` command's own keypoint cap and upsampling, see :func:`command_config`)."""
    parser.add_argument("--preset", choices=("default", "paper"), default="default",
                        help="'default': svs_torch's best measured settings (dense depth over the obstacles); "
                             "'paper': the paper's steps, MATLAB's defaults and R = f*B/d over the RANSAC "
                             "inliers (Eq. 5-8)")
    # The configuration's own defaults (SurfConfig, PipelineConfig), from the modules they take them from: without
    # torch, so that '--help' answers at once (2.3-3.0 s when it read them from PipelineConfig).
    keypoints_default = (f"{COMMAND_MAX_KEYPOINTS}, every keypoint found; --preset paper: {DEFAULT_MAX_KEYPOINTS}"
                         if command_defaults else f"{DEFAULT_MAX_KEYPOINTS}")
    parser.add_argument("--max-keypoints", type=keypoint_count, metavar="K",
                        help=f"strongest keypoints kept per image (default: {keypoints_default})")
    parser.add_argument("--metric-threshold", type=non_negative_float, metavar="T",
                        help=f"SURF det(H) threshold on 0-255 intensities (default: {PIPELINE_METRIC_THRESHOLD:g}; "
                             f"--preset paper: {MATLAB_METRIC_THRESHOLD:g}, MATLAB's MetricThreshold)")
    parser.add_argument("--upsample", action=argparse.BooleanOptionalAction,
                        help="detect on the image enlarged twice, as SIFT does: more and better-placed "
                             "keypoints on small frames, about 4x slower detection" + (
                                 f" (default: on up to {COMMAND_UPSAMPLE_MAX_PIXELS // 2**20} megapixel; "
                                 "--preset paper: off)" if command_defaults else " (default: off)"))
    parser.add_argument("--max-ratio", type=unit_interval_float, metavar="R",
                        help=f"ratio test of the matching (default: {LOWE_MAX_RATIO}; --preset paper: "
                             f"{MATLAB_MAX_RATIO}, MATLAB's MaxRatio)")
    parser.add_argument("--refine", action=argparse.BooleanOptionalAction,
                        help="refine each matched point to sub-pixel (Lucas-Kanade on the patches) and drop "
                             "matches whose patches disagree (preset default: on; paper: off)")


def preset_config(args: argparse.Namespace):
    """The :class:`~svs_torch.pipeline.PipelineConfig` of ``--preset`` with the feature, matching and
    segmentation options the user gave."""
    from dataclasses import replace

    from ..pipeline import PipelineConfig
    from .segment import config_from_args

    base = PipelineConfig.paper() if getattr(args, "preset", "default") == "paper" else PipelineConfig()
    surf_changes = {name: value for name, value in (("max_keypoints", args.max_keypoints),
                                                    ("metric_threshold", args.metric_threshold),
                                                    ("upsample", args.upsample)) if value is not None}
    with options_named(max_keypoints="--max-keypoints", metric_threshold="--metric-threshold"):
        surf = replace(base.surf, **surf_changes)
    changes = {"surf": surf, "segmentation": config_from_args(args, base.segmentation)}
    if args.max_ratio is not None:
        changes["max_ratio"] = args.max_ratio
    refine = getattr(args, "refine", None)
    if refine is not None:
        from ..geometry.lk_refinement import MatchRefinementConfig

        changes["refine_matches"] = (base.refine_matches or MatchRefinementConfig()) if refine else None
    return replace(base, **changes)


def command_config(args: argparse.Namespace, size_hw: tuple[int, int]):
    """``features``' configuration: :func:`preset_config`, and under ``--preset default`` (where the user did not
    set them) every keypoint up to :data:`COMMAND_MAX_KEYPOINTS` and ``upsample`` on pairs of at most
    :data:`COMMAND_UPSAMPLE_MAX_PIXELS` (``size_hw``: the working size). Its own defaults, not the pipeline's:
    a user of this command looks at the matches themselves, at native size, where the pipeline's cap (chosen for
    320x240 and RANSAC's time) kept a third as many correct matches as plain SIFT. An upsampled detection past
    :data:`MAX_PIXELS` is warned of (:func:`warn_if_upsampled_large`)."""
    from dataclasses import replace

    config = preset_config(args)
    if getattr(args, "preset", "default") == "default":
        changes = {}
        if args.max_keypoints is None:
            changes["max_keypoints"] = COMMAND_MAX_KEYPOINTS
        if args.upsample is None:
            changes["upsample"] = size_hw[0] * size_hw[1] <= COMMAND_UPSAMPLE_MAX_PIXELS
        config = replace(config, surf=replace(config.surf, **changes))
    warn_if_upsampled_large(config.surf.upsample, size_hw)
    return config


#: A --size that enlarges a pair more than this many times (either side) is warned of, once a process.
MAX_QUIET_ENLARGEMENT = 2.0
_ENLARGEMENT_WARNED: list[bool] = []


def warn_if_enlarged(size_hw: tuple[int, int], new_wh: tuple[int, int]) -> None:
    """Say once that ``--size`` enlarges a pair of ``size_hw`` more than :data:`MAX_QUIET_ENLARGEMENT` times: it
    adds no detail, only time (an audit: 5000x5000 on a 450x375 pair took 71 s without a word)."""
    (height, width), (new_w, new_h) = size_hw, new_wh
    if not _ENLARGEMENT_WARNED and max(new_w / width, new_h / height) > MAX_QUIET_ENLARGEMENT:
        import warnings

        _ENLARGEMENT_WARNED.append(True)
        warnings.warn(f"--size {new_w}x{new_h} enlarges the {width}x{height} pair "
                      f"{max(new_w / width, new_h / height):.1f} times: that adds no detail, only time (the SVS "
                      "sends 320x240; leave --size out to range the pair as it is)", stacklevel=2)


_UPSAMPLE_WARNED: list[bool] = []


def warn_if_upsampled_large(upsample: bool, size_hw: tuple[int, int]) -> None:
    """Say once that ``--upsample`` detects on a pair enlarged past :data:`MAX_PIXELS`: memory grows with the
    enlarged pixels (an audit: 3000x2000 took 3.0 GB with it, 1.2 GB without; a 16-megapixel pair would take
    about 7.7 GB, where the process was killed without a word on a smaller machine)."""
    height, width = size_hw
    if upsample and not _UPSAMPLE_WARNED and 4 * height * width > MAX_PIXELS:
        import warnings

        _UPSAMPLE_WARNED.append(True)
        warnings.warn(f"--upsample detects on the {width}x{height} pair enlarged to {2 * width}x{2 * height}: "
                      "about 2.5 times the memory without it (3 GB at 3000x2000); --no-upsample or a smaller "
                      "--size keep it down", stacklevel=2)


def load_pair(left: str, right: str, args: argparse.Namespace):
    """The pair ``left``/``right`` with the calibration options ``args`` carries (``focal_px``, ``baseline_m``,
    ``doffs_px``; SVS defaults otherwise; or rectified by ``--calibration``'s rig, before any resampling),
    resampled to ``--size`` if given; and the x, y factors that map working pixels back to input pixels."""
    from ..core.image_files import MAX_DECODED_PIXELS, declared_file_size
    from ..data import load_image_pair, resize_stereo_batch

    from .rig import calibration_from_args, rectified_by_rig

    new_size = checked_size(args.size)
    # Refused before decoding where the left file's header says (a 25-megapixel PNG of 200 kB was decoded into 740 MB
    # over 4.7 s, then refused: an audit); past what is decoded at all, the reader's own refusal says it.
    declared = None if new_size is not None else declared_file_size(left)
    if declared is not None and declared[0] * declared[1] <= MAX_DECODED_PIXELS:
        check_native_pixels(declared[::-1])
    batch = load_image_pair(left, right, focal_px=getattr(args, "focal_px", None),
                            baseline_m=getattr(args, "baseline_m", None), doffs_px=getattr(args, "doffs_px", 0.0))
    calibration = calibration_from_args(args)
    if calibration is not None:  # --calibration: rectified by the rig, its focal / baseline / doffs
        batch = rectified_by_rig(batch, calibration, left)
    height, width = batch.size_hw
    if new_size is None:
        check_native_pixels(batch.size_hw)
        return batch, (1.0, 1.0)
    new_w, new_h = new_size
    warn_if_enlarged((height, width), new_size)
    return resize_stereo_batch(batch, (new_w, new_h)), (width / new_w, height / new_h)


def checked_size(text: str | None) -> tuple[int, int] | None:
    """``--size`` as (width, height), None when not given; one of over :data:`MAX_PIXELS` refused
    (:class:`~svs_torch.core.errors.InputError`). ``""`` is an error, not the native size (``--size "$SIZE"``)."""
    from ..core.camera import parse_size
    from ..core.errors import InputError

    if text is None:
        return None
    new_size = parse_size(text, "--size")
    if new_size[0] * new_size[1] > MAX_PIXELS:
        raise InputError(f"--size: expected at most {MAX_PIXELS // 10**6} megapixels, got {text!r}")
    return new_size


def check_native_pixels(size_hw: tuple[int, int], name: str = "left") -> None:
    """Refuse (:class:`~svs_torch.core.errors.InputError`) a pair of this (H, W) over :data:`MAX_PIXELS`, run at
    its own size."""
    from ..core.camera import too_many_pixels
    from ..core.errors import InputError

    reason = too_many_pixels(size_hw, MAX_PIXELS, name)
    if reason:
        raise InputError(reason)


def to_input_pixels(xy, factors: tuple[float, float]) -> list[float]:
    """Working pixel-centre coordinates → input-image pixel-centre coordinates."""
    fx, fy = factors
    return [round((float(xy[0]) + 0.5) * fx - 0.5, 3), round((float(xy[1]) + 0.5) * fy - 0.5, 3)]


def keypoint_list(keypoints, index: int, factors: tuple[float, float]) -> list[dict]:
    valid = keypoints.valid[index]
    scale_factor = (factors[0] + factors[1]) / 2
    return [{"xy_px": to_input_pixels(xy, factors), "scale_px": round(float(s) * scale_factor, 3),
             "score": float(r)}
            for xy, s, r in zip(keypoints.xy[index][valid], keypoints.scale[index][valid],
                                keypoints.score[index][valid])]


def settings_json(config) -> dict:
    """The detector and matcher settings the command ran with (its defaults or the options given)."""
    return {"max_keypoints": config.surf.max_keypoints, "metric_threshold": config.surf.metric_threshold,
            "upsample": config.surf.upsample, "max_ratio": config.max_ratio, "mutual": config.mutual,
            "laplacian_gate": config.laplacian_gate}


def nothing_kept_reason(seg, segmenter: str) -> str | None:
    """Why a segmented run has nothing to match, or None: no region kept in the left or the right view, estimate's
    NO_OBJECTS (an audit: Otsu on noise kept nothing, and the answer read "status OK", "0 keypoints", as if SURF
    found nothing on a textured pair)."""
    from ..core.types import SegmentationStatus

    empty = [name for name, side in (("left", seg.left), ("right", seg.right))
             if not bool((side.kept_labels[0] >= 0).any()) or int(side.status[0]) != SegmentationStatus.OK]
    if not empty:
        return None
    where = "either view" if len(empty) == 2 else f"the {empty[0]} view"
    left, right = (SegmentationStatus(int(side.status[0])).name for side in (seg.left, seg.right))
    return (f"the {segmenter.partition(':')[0]} segmenter kept no region in {where} (left {left}, right {right}); "
            "--no-segment detects on the whole images")


def _check_before_work(args: argparse.Namespace, check_output_path) -> None:
    """The options no image is needed to refuse: segmentation options a whole-image run would ignore, and a figure
    that cannot be written or would be written over an input."""
    if args.no_segment:
        refuse_unused_segmentation_options(args, "--no-segment matches the whole images' features", " or --no-segment")
    if args.figure:
        check_output_path(args.figure, args.figure_option)
        check_outputs_apart([(args.figure_option, args.figure)],
                            [("left image", args.left), ("right image", args.right)])


def run(args: argparse.Namespace) -> int:
    from ..core.workers import imports_without_collection

    with imports_without_collection():  # see there: the imports' objects are frozen
        import torch

        from ..features.surf import extract_surf_features
        from ..plotting.figures import check_output_path, write_image_atomic
        from ..plotting.plots import matches_figure
        from ..pipeline import segment_pair

    _check_before_work(args, check_output_path)
    batch, factors = load_pair(args.left, args.right, args)
    warn_if_one_image_twice(batch)
    config = command_config(args, batch.size_hw)  # (--upsample on a large pair warned of)
    reason = too_small_reason(batch.size_hw)
    # What ran: refinement, masking (by which segmenter) and settings, in every JSON answer, TOO_SMALL's too.
    masked = {"refined": config.refine_matches is not None, "segmented": not args.no_segment,
              "segmenter": None if args.no_segment else config.segmentation.segmenter,
              "settings": settings_json(config)}
    if reason:
        if args.json:
            print(dumps_strict({"status": "TOO_SMALL", "reason": reason, "left": [], "right": [], "matches": [],
                                "matched_xy_px": [], **masked, "time_s": 0.0}))
        else:
            print(f"status TOO_SMALL: {reason}; no keypoints, no file written")
        return 0
    started = time.perf_counter()
    left_image, right_image, empty = batch.left, batch.right, None
    if not args.no_segment:
        seg = segment_pair(batch, config.segmentation)  # the preset's segmenter, as segment runs it
        left_image, right_image = seg.left.masked, seg.right.masked
        empty = nothing_kept_reason(seg, config.segmentation.segmenter)
    both = extract_surf_features(torch.cat([left_image, right_image]), config.surf)
    kp = both.keypoints
    points, matches = _match_features(both, left_image, right_image, config)
    elapsed = time.perf_counter() - started
    pairs = [[i, int(j)] for i, j in enumerate(matches.idx[0].tolist()) if j >= 0]
    matched_xy = [to_input_pixels(points.left[0, i], factors) + to_input_pixels(points.right[0, i], factors)
                  for i, _ in pairs]
    left, right = keypoint_list(kp, 0, factors), keypoint_list(kp, 1, factors)
    if args.json:
        status = {"status": "OK"} if empty is None else {"status": "NO_OBJECTS", "reason": empty}
        print(dumps_strict({**status, "left": left, "right": right, "matches": pairs, "matched_xy_px": matched_xy,
                            **masked, "time_s": round(elapsed, 6)}))
    else:
        _print_text(left, right, pairs, matched_xy, elapsed, args, empty)
    if args.figure:  # after the answer, as estimate's: a disk that refuses the figure keeps it (an audit)
        write_image_atomic(args.figure, matches_figure(left_image[0, 0], right_image[0, 0], kp, pairs),
                           args.figure_option)
        if not args.json:
            print(f"figure written to {args.figure}")
    return 0


def _print_text(left: list, right: list, pairs: list, matched_xy: list, elapsed: float, args: argparse.Namespace,
                empty: str | None) -> None:
    """The text answer: the counts and the first ten matches (the figure's line follows); first, where the
    segmentation kept nothing (``empty``, :func:`nothing_kept_reason`), the status that says so."""
    if empty is not None:
        print(f"status NO_OBJECTS: {empty}")
    # Said to be SAD matches: some are wrong (tens of pixels off the row), and nothing here has yet checked them
    # against the epipolar geometry (an audit read the first lines as the pipeline's result; svs-depth fundamental
    # gives RANSAC's inliers).
    print(f"left: {len(left)} keypoints, right: {len(right)} keypoints, {len(pairs)} SAD matches before RANSAC "
          f"({'segmented obstacles' if not args.no_segment else 'whole images'}; svs-depth fundamental keeps the "
          f"epipolar inliers), {elapsed * 1e3:.0f} ms")
    for (i, _), (xl, yl, xr, yr) in zip(pairs[:10], matched_xy):
        print(f"  left ({xl:.1f}, {yl:.1f}) s {left[i]['scale_px']:.2f} -> right ({xr:.2f}, {yr:.2f}), disparity "
              f"{xl - xr:.2f} px")
    if len(pairs) > 10:
        print(f"  … {len(pairs) - 10} more (--json for all)")


def _match_features(both, left_image, right_image, config) -> tuple:
    """The matched points and matches of the pair's features (``both``: left then right), as the pipeline
    makes them: SAD matching with the preset's gates, then the right point refined to sub-pixel (and matches
    whose patches disagree dropped) unless the preset turns refinement off."""
    from ..geometry.lk_refinement import refine_matched_points
    from ..geometry.matched_points import gather_matched_points
    from ..geometry.matching import match_sad

    kp, desc = both.keypoints, both.descriptors
    gate = config.laplacian_gate
    matches = match_sad(desc[:1], desc[1:], kp.valid[:1], kp.valid[1:], max_ratio=config.max_ratio,
                        mutual=config.mutual, laplacian_left=kp.laplacian_sign[:1] if gate else None,
                        laplacian_right=kp.laplacian_sign[1:] if gate else None, xy_left=kp.xy[:1],
                        xy_right=kp.xy[1:], epipolar_band_px=config.epipolar_band_px)
    points = gather_matched_points(kp.xy[:1], kp.xy[1:], matches)
    return refine_matched_points(left_image, right_image, points, matches, kp.scale[:1], config.refine_matches)
