"""``svs-depth segment``: the obstacle segmentation of one stereo pair, the pipeline's (what ``estimate`` keeps) or
the paper's (Sec. 3.2, ``--preset paper``)."""

from __future__ import annotations

import argparse
import time

from .common import (add_figure_option, check_outputs_apart, dumps_strict, options_named, positive_int,
                     too_small_reason)

HELP = "segment the obstacles of a stereo pair (what estimate keeps; --preset paper: Otsu, largest regions)"

DESCRIPTION = """\
Segment the obstacles of a stereo pair as 'svs-depth estimate' does by default: the nearness segmenter keeps
what is near in the pair's own disparity (a block matcher over the left view, the near side of its Otsu
split, the paper's opening and connected regions), the nearest region first, then the largest other one.
The same regions estimate ranges (unless it segments a pair again, on exposure-matched or row-aligned views),
before its depth stage cuts each to its interior.

--preset paper is the paper's pre-processing (Sec. 3.2) instead: grayscale, Otsu threshold, erosion then
dilation with an N x N square, connected regions, keep the N largest: the brightest large regions, often a
wall (--segmenter otsu is the same with the default's other settings).

Prints, for the left and the right image, the threshold (Otsu's level, or the nearness segmenter's obstacle
probability; in --json "threshold", both as levels 0-255), the count of regions found, kept or not
("num_regions"), and the kept objects in the order kept ("objects"): area in pixels ("area_px"), bounding box
("bbox_xyxy": x0, y0 inclusive; x1, y1 exclusive) and centroid ("centroid_xy": the mean column and row of its
pixels), in the pixels segmented: the input image's, or with --size the resampled pair's ("image_size_wh" in
--json, width then height). The right view's regions are the left ones moved by their disparity under the
nearness segmenter (its region count: those that land in the right view).
"""

EPILOG = """\
examples:
  svs-depth segment left.png right.png                          # the regions estimate keeps
  svs-depth segment left.png right.png --preset paper           # the paper's: Otsu, two largest
  svs-depth segment left.png right.png --kernel-size 7 --keep 3 --figure seg.png
  svs-depth segment left.png right.png --json | jq '.left.objects[0].area_px'
"""


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "segment", help=HELP, description=DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("left", help="left image file (gray or color, 8 or 16 bit)")
    parser.add_argument("right", help="right image file, the same size as the left")
    parser.add_argument("--preset", choices=("default", "paper"), default="default",
                        help="'default': the segmentation estimate runs (the nearness segmenter); 'paper': the "
                             "paper's Otsu threshold and N largest regions (Sec. 3.2); the options below change "
                             "either")
    from .features import add_pair_options  # (features imports this module)

    add_pair_options(parser)  # --size: and above 16 megapixels refused, as estimate's (an audit: 56 MP took 2.3 GB+)
    add_segmentation_options(parser)
    add_segmenter_option(parser)
    add_figure_option(parser, "write a figure: both images, their binary masks and the kept objects", "--out",
                      "--plot")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    parser.set_defaults(func=run)


def add_segmentation_options(parser: argparse.ArgumentParser) -> None:
    """The segmentation options shared by the commands that segment."""
    # No argparse defaults: the preset's values stand unless given, and a command can tell what was given
    # (given_segmentation_options).
    parser.add_argument("--kernel-size", type=positive_int, metavar="N",
                        help="side of the square structuring element for erosion and dilation, pixels "
                             "(default: 5)")
    parser.add_argument("--keep", type=positive_int, metavar="N",
                        help="how many regions to keep (default: 2, the paper's)")
    parser.add_argument("--keep-rule", choices=("largest", "nearest", "nearest_first"),
                        help="which regions are kept: 'largest' by area (the paper's rule, and the only one of the "
                             "Otsu and learned segmenters), 'nearest' by median disparity, 'nearest_first' the "
                             "nearest region then the largest others (default: 'nearest_first' with the nearness "
                             "segmenter, the product's default, 'largest' with the others)")
    parser.add_argument("--min-area-fraction", type=float, metavar="SHARE",
                        help="regions smaller than this share of the image are never kept by the nearness rules "
                             "(default: 0.003, 230 px at 320x240)")
    parser.add_argument("--near-min-area-fraction", type=float, metavar="SHARE",
                        help="a region under --min-area-fraction but at least this share is still kept where it is "
                             "nearer than every larger region: a thin pole ahead (default 0.0015; 0: off)")
    add_floor_option(parser)
    parser.add_argument("--connectivity", type=int, choices=(4, 8),
                        help="pixel connectivity of regions (default: 8, as MATLAB bwlabel)")
    parser.add_argument("--dark-objects", action="store_true",
                        help="obstacles are darker than the background: keep pixels at or below the threshold "
                             "(the Otsu segmenter's threshold, as the paper's preset runs it)")


#: The options of :func:`add_segmentation_options` (and ``--segmenter``) with the ``args`` field each sets.
SEGMENTATION_OPTIONS = (("--segmenter", "segmenter"), ("--kernel-size", "kernel_size"), ("--keep", "keep"),
                        ("--keep-rule", "keep_rule"), ("--min-area-fraction", "min_area_fraction"),
                        ("--near-min-area-fraction", "near_min_area_fraction"), ("--floor", "floor"),
                        ("--connectivity", "connectivity"), ("--dark-objects", "dark_objects"))


def given_segmentation_options(args: argparse.Namespace) -> list[str]:
    """The segmentation options the user gave (a command that segments nothing refuses them, rather than ignore
    them: ``features --no-segment --keep 3`` ran as without it)."""
    return [option for option, field in SEGMENTATION_OPTIONS if getattr(args, field, None) not in (None, False)]


def refuse_unused_segmentation_options(args: argparse.Namespace, reason: str, fix: str) -> None:
    """An InputError naming the first segmentation option given (:func:`given_segmentation_options`) to a run that
    segments nothing (``reason``), with ``fix``, the clause after "drop the option"."""
    from ..core.errors import InputError

    given = given_segmentation_options(args)
    if given:
        raise InputError(f"{given[0]}: {reason}, which no segmentation option changes; drop {given[0]}{fix}")


#: The camera heights over the floor the floor rule finds it at, metres (GroundPlaneConfig's min_camera_height_m and
#: max_camera_height_m, said in --floor's help without importing torch): a camera 0.6 m over a floor heard the floor
#: itself warned of, "Stop. Obstacle at 0.8 metres", and no help said why (an audit of the walker's guide).
FLOOR_CAMERA_HEIGHTS_M = (0.8, 3.0)


def add_floor_option(parser: argparse.ArgumentParser, default: str = "off",
                     why: str = "a pile of rocks or cloth can read as a floor: experiments/walker_floor.md") -> None:
    """``--floor on|off``: whether the nearness segmenter leaves the floor out (:func:`with_floor`). ``default``: the
    command's choice without the option ("off" leaves the configuration as it is), and ``why``, a clause giving its
    reason, shown in the help. The floor's own settings (``svs-depth eval --set segmentation.ground.KEY=VALUE``)
    are named only by the commands that take ``--set``, not here: none of this option's commands does."""
    parser.add_argument("--floor", choices=("on", "off"), default=None if default == "off" else default,
                        help="'on': the floor (the road) that the nearness segmenter finds as a plane in the pair's "
                             "disparity is not an obstacle, as for a walker whose cameras are "
                             f"{FLOOR_CAMERA_HEIGHTS_M[0]:g} to {FLOOR_CAMERA_HEIGHTS_M[1]:g} m over it (a floor "
                             "nearer the cameras is kept, and warned of, as any near surface); 'off': it is kept like "
                             f"any near surface (default: {default}, {why})")


def with_floor(config, choice: str | None):
    """The ``SegmentationConfig`` ``config`` with ``--floor``'s ``choice``: ``"on"`` looks for the floor (its own
    settings, or the defaults), ``"off"`` does not, None leaves it as it is."""
    return config if choice is None else config.with_floor(choice == "on")


def segmenter_choice(text: str) -> str:
    """argparse type: ``otsu``, ``nearness``, ``learned``, or ``nearness:PATH`` / ``learned:PATH`` naming a weights
    file of that kind, checked by :class:`~svs_torch.segmentation.SegmentationConfig` itself and read (imported only
    when the option is given): a truncated or foreign file was refused only once the run reached it, after the
    pairs of a ``--pairs`` list were read and the workers started (an audit)."""
    from ..core.errors import InputError
    from ..segmentation.network_files import check_weights_file
    from ..segmentation.segment import SegmentationConfig

    try:
        SegmentationConfig(segmenter=text)
        check_weights_file(text)
    except InputError as error:
        raise argparse.ArgumentTypeError(str(error).removeprefix("segmenter: ")) from None
    return text


def add_segmenter_option(parser: argparse.ArgumentParser) -> None:
    """``--segmenter``, for the commands that run the whole pipeline."""
    parser.add_argument("--segmenter", type=segmenter_choice, metavar="nearness[:PATH]|otsu|learned[:PATH]",
                        help="how obstacles are found: 'nearness' (the pipeline's default: the near side of "
                             "the pair's measured disparity, the nearest region always kept), 'otsu' (the "
                             "paper's: the brightest large regions), "
                             "'learned' (the older network of issue 13), or 'nearness:PATH' / 'learned:PATH' "
                             "(weights written by experiments/train_nearness.py / train_segmentation.py)")


def config_from_args(args: argparse.Namespace, base=None):
    """The segmentation options over ``base`` (a ``SegmentationConfig``; default the class defaults)."""
    from dataclasses import replace

    from ..segmentation.segment import SegmentationConfig

    base = base or SegmentationConfig()
    # First, before the configuration checks itself: '--segmenter otsu --keep-rule nearest' read "keep: ... (use
    # segmenter='nearness')", the library's words, where 'nearest_first' got this command line's (an audit).
    check_segmenter_options(getattr(args, "segmenter", None) or base.segmenter, dark_objects=args.dark_objects,
                            floor=getattr(args, "floor", None), segmenter_option=hasattr(args, "segmenter"),
                            keep_rule=getattr(args, "keep_rule", None),
                            area_options=[option for option, field in SEGMENTATION_OPTIONS
                                          if field.endswith("area_fraction") and getattr(args, field) is not None])
    with options_named(kernel_size="--kernel-size", num_keep="--keep", segmenter="--segmenter", keep="--keep-rule",
                       min_area_fraction="--min-area-fraction", near_min_area_fraction="--near-min-area-fraction"):
        config = replace(base, kernel_size=base.kernel_size if args.kernel_size is None else args.kernel_size,
                         num_keep=base.num_keep if args.keep is None else args.keep,
                         connectivity=base.connectivity if args.connectivity is None else args.connectivity,
                         foreground="dark" if args.dark_objects else "bright")
        if getattr(args, "segmenter", None):
            # Only the nearness segmenter measures disparity: the others keep the largest regions.
            stereo = args.segmenter.startswith("nearness")
            config = replace(config, segmenter=args.segmenter, keep=config.keep if stereo else "largest")
        if getattr(args, "keep_rule", None):
            config = replace(config, keep=args.keep_rule)
        if getattr(args, "min_area_fraction", None) is not None:
            config = replace(config, min_area_fraction=args.min_area_fraction)
        if getattr(args, "near_min_area_fraction", None) is not None:
            config = replace(config, near_min_area_fraction=args.near_min_area_fraction)
        config = with_floor(config, getattr(args, "floor", None))
    return config


def check_segmenter_options(segmenter: str, dark_objects: bool = False, floor: str | None = None,
                            canny: bool = False, segmenter_option: bool = True, keep_rule: str | None = None,
                            area_options: list[str] | tuple[str, ...] = (), camera_frames: bool = False) -> None:
    """Reject an option that the chosen ``segmenter`` would silently ignore: ``--dark-objects`` and ``--canny``
    change the brightness threshold, which only the Otsu segmenter has; ``--floor on`` leaves out a plane found
    in the measured disparity, which only the nearness segmenter measures; so do a nearness ``keep_rule``
    (``--keep-rule nearest_first`` kept the largest regions under Otsu, and the JSON named the rule) and the
    nearness rules' area options (``area_options``, the names given) and ``--camera-frames`` (only the nearness
    map has a noise window). ``segmenter_option``: the command takes ``--segmenter`` (the message then names it)."""
    from ..core.errors import InputError

    kind = segmenter.partition(":")[0]
    fix = "add --segmenter otsu (or --preset paper)" if segmenter_option else "add --preset paper"
    for option, given in (("--dark-objects", dark_objects), ("--canny", canny)):
        if given and kind != "otsu":
            raise InputError(f"{option}: only the Otsu segmenter thresholds brightness, and this run segments with "
                             f"{segmenter!r}; {fix}")
    # (features and fundamental have no --segmenter: "use --segmenter nearness" failed as an unknown option, an audit)
    nearness = "--segmenter nearness" if segmenter_option else "--preset default"
    if kind != "nearness" and (keep_rule in ("nearest", "nearest_first") or area_options):
        option = f"--keep-rule {keep_rule}" if keep_rule in ("nearest", "nearest_first") else area_options[0]
        raise InputError(f"{option}: only the nearness segmenter ranks regions by disparity, and this run segments "
                         f"with {segmenter!r}; drop it or use {nearness}")
    if camera_frames and kind != "nearness":  # the learned and Otsu runs were the ones without it, in silence
        raise InputError(f"--camera-frames: only the nearness segmenter matches a camera frame's noise with its wider "
                         f"window, and this run segments with {segmenter!r}; drop it or use {nearness}")
    if floor == "on" and kind != "nearness":
        raise InputError(f"--floor: 'on' leaves out the floor the nearness segmenter finds in the measured "
                         f"disparity, and this run segments with {segmenter!r}; drop --floor or use {nearness}")


def warn_if_one_image_twice(batch) -> None:
    """A warning where a pair's two views are one image, pixel for pixel: segment and features answered a bare
    NO_FOREGROUND (no disparity anywhere for the nearness segmenter to measure), where fundamental and estimate
    say what it is (an audit)."""
    from ..capture.frozen import one_image_twice

    if one_image_twice(batch.left, batch.right):
        import warnings

        warnings.warn("left, right: the same image, pixel for pixel (one camera's frame given twice?): no disparity "
                      "anywhere, so no obstacle stands nearer than the rest", stacklevel=3)


def image_report(seg, index: int) -> dict:
    """JSON-ready summary of image ``index`` of a :class:`~svs_torch.core.types.Segmentation`."""
    from ..core.types import SegmentationStatus

    objects = []
    for label in seg.kept_labels[index].tolist():
        if label < 0:
            continue
        slot = label - 1
        objects.append({
            "label": label,
            "area_px": int(seg.regions.area_px[index, slot]),
            "bbox_xyxy": [int(v) for v in seg.regions.bbox_xyxy[index, slot].tolist()],
            "centroid_xy": [round(float(v), 3) for v in seg.regions.centroid_xy[index, slot].tolist()],
        })
    return {
        "threshold": int(seg.threshold_level[index]),
        "status": SegmentationStatus(int(seg.status[index])).name,
        # The regions in this view's labels: under the nearness segmenter the right's are only the left's kept ones
        # moved there (its num_regions is the left's count, which the right's line printed as its own).
        "num_regions": int((seg.regions.area_px[index] > 0).sum()),
        "objects": objects,
    }


def format_report(side: str, report: dict, segmenter: str = "otsu") -> list[str]:
    """Human-readable lines for one image's report."""
    if report["status"] == "TOO_SMALL":
        return [f"{side}: status TOO_SMALL: {report['reason']}; nothing segmented"]
    rule = (f"Otsu threshold {report['threshold']}/255" if segmenter == "otsu"
            else f"{segmenter} segmenter, obstacle probability above {report['threshold'] / 255:.2f}")
    if report["status"] == "UNIFORM_IMAGE":  # its threshold and its one "region" (the whole image) mean nothing
        return [f"{side}: status UNIFORM_IMAGE, one level everywhere: nothing to segment", "  no object kept"]
    count = report["num_regions"]
    lines = [f"{side}: {rule}, {count} region{'' if count == 1 else 's'}, status {report['status']}"]
    if not report["objects"]:
        lines.append("  no object kept")
    for rank, obj in enumerate(report["objects"], start=1):
        x0, y0, x1, y1 = obj["bbox_xyxy"]
        cx, cy = obj["centroid_xy"]
        lines.append(f"  #{rank} label {obj['label']}: {obj['area_px']} px, box x {x0}..{x1} y {y0}..{y1}, "
                     f"centroid ({cx:.1f}, {cy:.1f})")
    return lines


def run(args: argparse.Namespace) -> int:
    from ..core.workers import imports_without_collection

    with imports_without_collection():  # see there: the imports' objects are frozen
        from ..plotting.figures import check_output_path, compose_grid, segmentation_panels, write_image_atomic
        from ..pipeline import PipelineConfig, segment_pair
        from .features import load_pair

    base = PipelineConfig.paper() if args.preset == "paper" else PipelineConfig()
    config = config_from_args(args, base.segmentation)
    if args.figure:
        check_output_path(args.figure, args.figure_option)
        check_outputs_apart([(args.figure_option, args.figure)],
                            [("left image", args.left), ("right image", args.right)])
    batch, _ = load_pair(args.left, args.right, args)  # resampled to --size; at most 16 megapixels
    warn_if_one_image_twice(batch)
    started = time.perf_counter()
    reason = too_small_reason(batch.size_hw)  # as estimate and features: no segmentation of a 320x1 pair
    seg = segment_pair(batch, config) if reason is None else None
    elapsed = time.perf_counter() - started
    if reason is not None:
        left = right = {"threshold": None, "status": "TOO_SMALL", "reason": reason, "num_regions": 0, "objects": []}
    if seg is not None:
        left, right = image_report(seg.left, 0), image_report(seg.right, 0)
    if args.json:
        height, width = batch.size_hw
        print(dumps_strict({
            "left": left, "right": right,
            "image_size_wh": [width, height],
            "config": {"preset": args.preset, "segmenter": config.segmenter, "keep_rule": config.keep,
                       "kernel_size": config.kernel_size, "keep": config.num_keep,
                       "connectivity": config.connectivity, "foreground": config.foreground},
            "time_s": round(elapsed, 6),
        }))
    else:
        for line in format_report("left", left, config.segmenter) + format_report("right", right, config.segmenter):
            print(line)
    if seg is not None and args.figure:  # after the report, as estimate's: a disk that refuses it keeps the report
        figure = compose_grid([segmentation_panels(batch.left, seg.left, 0, "left", config.segmenter, config.method),
                               segmentation_panels(batch.right, seg.right, 0, "right", config.segmenter,
                                                   config.method)])
        write_image_atomic(args.figure, figure, args.figure_option)
    if not args.json:
        print(f"segmented in {elapsed * 1e3:.1f} ms" + (f"; figure written to {args.figure}" if args.figure and seg
                                                        else "; no figure written" if args.figure else ""))
    return 0
