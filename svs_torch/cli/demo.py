"""``svs-depth demo``: the pipeline on a synthetic SVS scene with exact ground truth (no camera, no download)."""

from __future__ import annotations

import argparse
import time

from .common import add_figure_option, dumps_strict, non_negative_int, options_named, seed_int, too_small_reason

HELP = "render a synthetic SVS scene, run the pipeline on it, compare with the truth"

DESCRIPTION = """\
Render a synthetic scene as the SVS would see it (3.6 mm lenses, 10.75 cm baseline): textured obstacles at
1-2 m in front of a wall, left and right views with exact ground-truth depth. Then run the whole pipeline
(segmentation, SURF, SAD matching, RANSAC, rectification, depth) on the pair, print the true and the
estimated depth of every obstacle, and write a figure of every step to svs_demo.png (or --figure FILE).
A size under 5x5 pixels gives the status TOO_SMALL and no figure.
"""


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "demo", help=HELP, description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=seed_int, default=7,
                        help="scene seed; the same seed renders the same scene (default: 7)")
    parser.add_argument("--size", default="320x240", metavar="WxH", help="image size (default: 320x240)")
    parser.add_argument("--objects", type=non_negative_int, default=2, metavar="K",
                        help="number of obstacles (default: 2)")
    add_figure_option(parser, "figure file to write", "--out", "--plot", default="svs_demo.png")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    parser.set_defaults(func=run)


def _truth_of_objects(scenes, seg) -> list[dict]:
    """For each kept left object: the true obstacle it covers most, its true depth, and the overlap (IoU)."""
    import torch

    found = []
    labels = seg.labels[0, 0]
    ids = scenes.object_ids[0, 0]
    depth = scenes.depth_m[0, 0]
    for label in seg.kept_labels[0].tolist():
        if label < 0:
            continue
        region = labels == label
        covered = ids[region]
        best = int(torch.mode(covered).values) if covered.numel() else 0
        truth = ids == best
        iou = float((region & truth).sum()) / float((region | truth).sum())
        found.append({
            "label": label,
            "true_object": best,
            "iou": round(iou, 3),
            "median_true_depth_m": round(float(depth[region].median()), 3),
        })
    return found


def run(args: argparse.Namespace) -> int:
    from ..workers import imports_without_collection

    with imports_without_collection():  # see there: the imports' objects are frozen
        import cv2
        import torch

        from ..camera import parse_size
        from ..checks import InputError
        from ..data.synthetic import random_obstacle_scenes
        from ..figures import check_output_path, compose_grid, segmentation_panels, write_image_atomic
        from ..pipeline import estimate_obstacle_depth
        from ..plots import estimate_figure
        from .estimate import format_report, pair_report, unranged_report, with_calibration
        from .features import MAX_PIXELS

    width, height = parse_size(args.size, "--size")
    if width * height > MAX_PIXELS:
        raise InputError(f"--size: expected at most {MAX_PIXELS // 10**6} megapixels, got {args.size!r}")
    check_output_path(args.figure, args.figure_option)
    reason = too_small_reason((height, width))
    if reason:
        report = unranged_report("TOO_SMALL", reason + "; no scene rendered, no figure written", "dense")
        print(dumps_strict({"seed": args.seed, "truth": [], **report, "figure": None}) if args.json
              else "\n".join(format_report(report)))
        return 0
    generator = torch.Generator().manual_seed(args.seed)
    with options_named(num_objects="--objects", size_wh="--size"):  # e.g. more obstacles than fit side by side
        scenes = random_obstacle_scenes(1, args.objects, size_wh=(width, height), generator=generator)
    batch = scenes.batch
    started = time.perf_counter()
    result = estimate_obstacle_depth(batch)
    elapsed = time.perf_counter() - started
    report = with_calibration(pair_report(result, 0, (1.0, 1.0), elapsed), batch, 0, (1.0, 1.0),
                              "the SVS model: the synthetic scene's own camera")
    truth = [
        {"object": k + 1, "depth_m": round(float(scenes.object_depth_m[0, k]), 3),
         "bbox_xyxy": [int(v) for v in scenes.object_bbox_xyxy[0, k].tolist()]}
        for k in range(scenes.object_depth_m.shape[1]) if bool(scenes.object_valid[0, k])
    ]
    for obj, match in zip(report["objects"], _truth_of_objects(scenes, result.segmentation.left)):
        obj.update({k: v for k, v in match.items() if k != "label"})

    # The inputs and their masks in one row above the pipeline figure (which shows the true depth beside the
    # estimate), scaled to its width: four 320-wide panels fill it, where two left a third of the row blank.
    left_image, left_binary, _ = segmentation_panels(batch.left, result.segmentation.left, 0, "left")
    right_image, right_binary, _ = segmentation_panels(batch.right, result.segmentation.right, 0, "right")
    pipeline = estimate_figure(batch, result, 0)
    top = compose_grid([[left_image], [right_image], [left_binary], [right_binary]])
    top = cv2.resize(top, (pipeline.shape[1], round(top.shape[0] * pipeline.shape[1] / top.shape[1])),
                     interpolation=cv2.INTER_AREA if top.shape[1] > pipeline.shape[1] else cv2.INTER_CUBIC)
    figure = compose_grid([[top, pipeline]])
    write_image_atomic(args.figure, figure, args.figure_option)
    camera = {"focal_px": round(float(batch.focal_px[0]), 2), "baseline_m": float(batch.baseline_m[0]),
              "image_size_wh": [width, height]}
    if args.json:
        print(dumps_strict({"seed": args.seed, "camera": camera, "truth": truth, **report, "figure": args.figure}))
        return 0
    print(f"synthetic SVS scene (seed {args.seed}): {width}x{height}, focal {camera['focal_px']} px, "
          f"baseline {camera['baseline_m'] * 100:.2f} cm")
    for obj in truth:
        print(f"  true obstacle {obj['object']}: {obj['depth_m']:.2f} m, box {obj['bbox_xyxy']}")
    print("\n".join(format_report(report)))
    for obj in report["objects"]:
        estimate = f"{obj['depth_m']:.3f} m" if obj["depth_m"] is not None else "no depth"
        print(f"  object {obj['label']} is true obstacle {obj['true_object']} (IoU {obj['iou']:.2f}): "
              f"true {obj['median_true_depth_m']:.3f} m, estimated {estimate}")
    print(f"figure written to {args.figure}")
    return 0
