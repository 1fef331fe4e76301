"""What ``svs-depth estimate`` says and writes about a pair: its JSON report (with the calibration its metres
use), the lines printed for it, and its dense disparity map (``--disparity-out``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from .object_report import object_lines, object_reports, unranged_repeated_note
from .object_report import report_number as _number
from .one_homography import one_homography_reason
from .right_camera import RIGHT_CAMERA_KEYS, right_camera_line, right_camera_report
from .rig import calibration_file_source
from .too_near import too_near_reason

__all__ = ["ASPECT_CHANGED", "NO_DENSE_MAP", "format_report", "pair_report", "rig_size", "square_pixels",
           "unranged_report", "with_calibration"]


def unranged_report(status: str, reason: str, range_rule: str) -> dict:
    """The report of a pair the pipeline did not run on (``TOO_SMALL``, ``BAD_INPUT``): the keys of
    :func:`pair_report` in its order (then :func:`with_calibration`'s), with null numbers, and the reason."""
    return {"status": status, "reason": reason, "range_rule": range_rule, "r_min_m": None, "r_max_m": None,
            "d_min_px": None, "d_max_px": None, "nearest_m": None, "nearest_side": "none", "nearest_surface_m": None,
            "floor": None, "nearest_ahead_m": None, "nearest_ahead_surface_m": None, "objects": [],
            "num_keypoints": [0, 0], "num_matches": 0, "num_inliers": 0, "num_agreeing_inliers": None,
            "num_measured_inliers": None, "verified": None, "rectified": False, "row_aligned": False,
            **dict.fromkeys(RIGHT_CAMERA_KEYS), "exposure_matched": False, "coarse_dense": False,
            "features_smoothed": False, "dropped_unmeasured": 0, "dense_box_xywh": None, "time_s": 0.0,
            "calibration_rectified": False, "calibration": None, "image_size_px": None, "working_size_px": None}


def _calibration_source(source, args) -> str:
    """Where pair ``source``'s calibration comes from: ``--calibration``'s file, its own data or list line, the
    command's options, or the SVS model."""
    from ..data import pair_calibration_source

    return calibration_file_source(args, source) or pair_calibration_source(source, args.focal_px, args.baseline_m,
                                                                            args.doffs_px)


def with_calibration(report: dict, batch, index: int, factors: tuple[float, float], source: str,
                     rig_wh: tuple[int, int] | None = None) -> dict:
    """``report`` with the calibration its metres use, for the INPUT image size, and where it came from
    (:func:`svs_torch.data.calibration_record`); ``calibration_rectified``: the pair was rectified by
    ``--calibration``'s file, made at ``rig_wh`` (:func:`rig_size`), before the pipeline (whose own ``rectified``
    says it rectified the pair from its F); and the two sizes its pixel counts are in, ``[width, height]`` each:
    ``image_size_px`` the input's (``area_px``, ``bbox_xyxy``), ``working_size_px`` the image the pipeline ran on
    (``--size``: ``num_valid_px``, ``dense_box_xywh``)."""
    from ..data import calibration_record
    from ..data.calibration import rig_scaled_source

    height, width = (int(v) for v in batch.image_hw[index].tolist())
    input_wh = [int(round(width * factors[0])), int(round(height * factors[1]))]
    source = source if rig_wh is None else rig_scaled_source(source, rig_wh, input_wh)
    return {**report, "calibration_rectified": rig_wh is not None,
            "calibration": calibration_record(batch, index, source, factors[0]),
            "image_size_px": input_wh, "working_size_px": [width, height]}


def rig_size(source, args) -> tuple[int, int] | None:
    """The image size ``--calibration``'s file was made at where it rectified pair ``source``, else None."""
    from .rig import calibration_from_args

    return tuple(calibration_from_args(args).image_wh) if calibration_file_source(args, source) else None


#: What a pair resized to another aspect ratio (``--size``) says of its floor, once a run.
ASPECT_CHANGED = ("--size changes the images' aspect ratio, so their pixels are no longer square: the floor is looked "
                  "for as if they were (a camera height or pitch read wrong can miss it, and a missed floor is kept "
                  "as an obstacle), and its pose and the distances ahead along it are not reported (give a size of "
                  "the images' own aspect, e.g. 320 wide and the height in proportion)")


#: What a pair ranged by the paper's rule says of its floor, once a run: the floor is left out of the obstacles, but
#: its pose and the distances ahead along it are measured on the dense map, which that rule does not make.
NO_DENSE_MAP = ("--floor on with --range paper: the floor is left out of the obstacles, but its pose and the "
                "distances ahead along it are measured on the dense map, which --range paper does not make, so "
                "they are reported null (--range dense reports them)")


def square_pixels(factors: tuple[float, float]) -> bool:
    """The working pixels are square (``factors``: input over working pixels, x and y, within 1 %): what the
    floor's pose needs (:mod:`svs_torch.depth.floor_distance` takes one focal length for both axes; a 707 × 481
    pair at 320 × 240 read Piano's camera 1.41 m up, pitched 21.8°, and 1.32 m / 20.4° at 320 × 221)."""
    return abs(factors[0] / factors[1] - 1) <= 0.01


def _floor_report(result, index: int, factors: tuple[float, float]) -> dict:
    """The floor's keys of pair ``index``'s report: the camera over the floor the segmenter found
    (:mod:`svs_torch.depth.floor_distance`) and the nearest obstacle's distance ahead along it, null where none (or
    where the pixels are not square: :func:`square_pixels`, said once)."""
    import warnings

    floor = result.floor
    found = floor is not None and bool(floor.floor.found[index])
    if floor is None and result.segmentation.floor_found is not None:  # looked for, but not measured
        warnings.warn(NO_DENSE_MAP, RuntimeWarning, stacklevel=2)
    # Said wherever the floor was looked for, found or not: KITTI at 320x240 (rows stretched 2.5 times) read the road
    # 2.5 times too far below the camera, missed it, and kept it as the nearest obstacle without a word (an audit).
    if result.segmentation.floor_found is not None and not square_pixels(factors):
        warnings.warn(ASPECT_CHANGED, RuntimeWarning, stacklevel=2)
        found = False
    if not found:
        return {"floor": None, "nearest_ahead_m": None, "nearest_ahead_surface_m": None}
    nearest = floor.nearest
    return {"floor": {"camera_height_m": round(float(floor.floor.camera_height_m[index]), 4),
                      "pitch_deg": round(float(floor.floor.pitch_deg[index]), 3)},
            "nearest_ahead_m": _number(nearest.depth_m[index], nearest.valid[index]),
            "nearest_ahead_surface_m": _number(nearest.surface_m[index], nearest.valid[index])}


#: What a pair whose views seem swapped is told, ranged or not (an audit: Teddy's views swapped, NO_DENSE_DEPTH after
#: the whole run and no hint): its matches lie to the right of their left points, where a left view's lie to the left.
SWAPPED_VIEWS = ("most matched points lie to the right in the right view (negative disparity): are LEFT and RIGHT "
                 "swapped?")
#: What an unranged pair whose matches lie in front of the rig until its doffs is added is told (an audit: Teddy with
#: its doffs negated, NO_DENSE_DEPTH, the status of a flat or occluded pair, and no hint).
DOFFS_BEHIND = ("most matched points have a positive disparity d but d + doffs <= 0, behind the rig: is the doffs' "
                "sign right (cx_right - cx_left, in pixels)?")
UNRANGED = ("NO_DENSE_DEPTH", "NO_POSITIVE_DISPARITY")
#: What a pair whose two views are one image is told, whatever stage stopped it (an audit: Teddy's left image given
#: twice read "status NO_OBJECTS", what a pair with nothing near reads, and no hint).
IDENTICAL_VIEWS = ("every matched point lies at the same place in both views (zero disparity, no depth anywhere): "
                   "are LEFT and RIGHT the same image, one camera's frame given twice?")
#: What a pair that stopped though both views hold features, almost none of them shared, is told (an audit: Teddy's
#: left view beside Piano's right read NO_DENSE_DEPTH, two noise frames NO_OBJECTS, with no hint).
UNRELATED_VIEWS = ("the views share almost no feature (fewer than 7 matches of 100 or more keypoints each): do both "
                   "cameras see the same scene?")
#: What a pair whose cameras stood one above the other is told, ranged or not (an audit: Teddy's two views each turned
#: 90°, as a camera held on its side writes them without an orientation tag, read "OK", "verified", at 1.08 m for
#: 1.25 m; the row alignment took the parallax along the columns for a 17.9 px shift and a 4.3° roll).
TURNED_RIG = ("the matched points move up or down between the views, not along the rows (epipolar lines steeper than "
              "45°): the cameras stood one above the other, and no distance holds; turn both images a quarter turn "
              "so that the cameras stand side by side (was the camera held on its side?)")
#: The statuses of a pair the pipeline did not run on (:func:`unranged_report`).
NOT_RUN = ("TOO_SMALL", "BAD_INPUT")


def views_swapped(result, index: int) -> bool:
    """Whether at least three quarters of pair ``index``'s RANSAC inliers have a negative disparity."""
    points, inliers = result.points, result.fundamental.inliers[index]
    disparity = (points.left[index, :, 0] - points.right[index, :, 0])[inliers & points.valid[index]]
    return disparity.numel() >= 8 and float((disparity < 0).float().mean()) >= 0.75


def rig_turned(result, index: int) -> bool:
    """Whether pair ``index``'s cameras stood one above the other, by two tests on its RANSAC inliers (8 or more):
    under its F, at least three quarters of them have an epipolar line steeper than 45° in the right view; and
    the right view's columns follow the left view's points by one affine map far better than its rows do (median
    residual under a fifth). A side-by-side rig's rows follow by one similarity, rolled, shifted or scaled, and its
    columns carry the parallax: Teddy turned 90° reads 0.06 px against 1.67, upright the reverse. Either test alone
    misfired on the shared scenes deviated far beyond a loose rig's envelope (a near-planar Monopoly rolled 10°,
    shifted 30 %: F steep, residuals 1.2 against 3.0 px; Lampshade1 shifted 45 %: 3.0 against 11.6, F level);
    together none of 220 pairs (the 44 shared scenes at 320 px, five deviations up to 15° and 45 %) is flagged."""
    import torch

    points = result.points
    kept = points.valid[index] & result.fundamental.inliers[index]
    if int(kept.sum()) < 8:
        return False
    left, right = points.left[index][kept].double(), points.right[index][kept].double()
    design = torch.cat([left, torch.ones_like(left[:, :1])], 1)
    lines = design @ result.fundamental.F[index].double().T  # a·x + b·y + c = 0 in the right view
    if float((lines[:, 0].abs() > lines[:, 1].abs()).double().mean()) < 0.75:
        return False
    fitted = design @ torch.linalg.lstsq(design, right).solution
    residual = (fitted - right).abs().median(dim=0).values
    return float(residual[0]) < float(residual[1]) / 5


def views_identical(result, index: int) -> bool:
    """Whether nine in ten of pair ``index``'s matches (at least 8) lie within 0.05 px of the same place in both
    views: a real pair's sub-pixel keypoints never do, even at infinity (its rows and noise differ)."""
    points = result.points
    valid = points.valid[index]
    offsets = (points.left[index] - points.right[index])[valid].abs().amax(dim=-1)
    return offsets.numel() >= 8 and float((offsets <= 0.05).float().mean()) >= 0.9


def _reason(result, index: int, status: str, width_px: int) -> str | None:
    """What pair ``index``'s matches tell of its views, whatever it was ranged: one image twice or two unrelated
    views (a pair that stopped), views swapped (ranged or not: swapped KITTI, Pipes, Books, Aloe and Cloth1 pairs
    were ranged, "OK", at 0.7-1.7 m, "verified", without a word; an audit), for a ranged pair its matches on one
    homography (:mod:`.one_homography`), or for an unranged pair its matches nearer than the range searched
    (:mod:`.too_near`) or a doffs of the wrong sign."""
    if status != "OK" and views_identical(result, index):
        return IDENTICAL_VIEWS
    few_shared = int(result.num_matches[index]) < 7 and int(result.num_keypoints[index].min()) >= 100
    if status != "OK" and few_shared:
        return UNRELATED_VIEWS
    if views_swapped(result, index):
        return SWAPPED_VIEWS
    if rig_turned(result, index):
        return TURNED_RIG
    if status == "OK":
        return one_homography_reason(result, index, width_px)
    return (too_near_reason(result, index) or _unranged_reason(result, index)) if status in UNRANGED else None


def _unranged_reason(result, index: int) -> str | None:
    """Why an unranged pair may be so, where its matches tell: a doffs that puts in front of the rig (three
    quarters of its ranged inliers at d > 0) what it ranges behind it (three quarters at d + doffs <= 0)."""
    disparities, depths = result.depth.disparities, result.depth.points
    valid = disparities.valid[index]
    if int(valid.sum()) < 8:
        return None
    ahead = float((disparities.disparity_px[index][valid] > 0).float().mean())
    behind = 1.0 - float(depths.valid[index][valid].float().mean())
    return DOFFS_BEHIND if ahead >= 0.75 and behind >= 0.75 else None


def pair_report(result, index: int, factors: tuple[float, float], elapsed_s: float,
                image_hw: tuple[int, int]) -> dict:
    """JSON-ready summary of pair ``index`` of a :class:`~svs_torch.pipeline.PipelineResult`, run at ``image_hw``
    (the pair's own size, pipeline pixels; ``factors``: input pixels per pipeline pixel, x and y)."""
    from ..depth.depth_types import ObstacleSide
    from ..pipeline import PipelineStatus

    rng = result.depth.range
    report_objects = object_reports(result, index, factors, square_pixels(factors))
    nearest = result.depth.nearest
    status = PipelineStatus(int(result.status[index])).name
    return {
        "status": status,
        # (a pair the pipeline did not run on has one: unranged_report; eval's rows alike)
        "reason": _reason(result, index, status, image_hw[1]),
        "range_rule": result.range_rule,
        "r_min_m": _number(rng.r_min_m[index], rng.valid[index]),
        "r_max_m": _number(rng.r_max_m[index], rng.valid[index]),
        # In input pixels, as the calibration's focal and doffs (R = f·B / (d + doffs) holds with the reported values)
        "d_min_px": _number(rng.d_min_px[index] * factors[0], rng.valid[index]),
        "d_max_px": _number(rng.d_max_px[index] * factors[0], rng.valid[index]),
        "nearest_m": _number(nearest.depth_m[index], nearest.valid[index]),
        "nearest_side": ObstacleSide(int(nearest.side[index])).name.lower(),
        "nearest_surface_m": _number(nearest.surface_m[index], nearest.valid[index]),
        **_floor_report(result, index, factors),
        "objects": report_objects,
        "num_keypoints": [int(v) for v in result.num_keypoints[index].tolist()],
        "num_matches": int(result.num_matches[index]),
        "num_inliers": int(result.num_inliers[index]),
        "num_agreeing_inliers": (int(result.num_agreeing_inliers[index]) if result.num_agreeing_inliers is not None
                                 else None),
        "num_measured_inliers": (int(result.num_measured_inliers[index]) if result.num_measured_inliers is not None
                                 else None),
        "verified": bool(result.verified[index]) if result.verified is not None else None,
        "rectified": bool(result.rectified[index]),
        # A loosely mounted right camera: its rows aligned to the left's; its gain or exposure matched. Noisy
        # frames: the dense map measured at half the working width (PipelineConfig.coarse_retry_below_share).
        "row_aligned": bool(result.row_aligned[index]) if result.row_aligned is not None else False,
        **right_camera_report(result, index, factors, image_hw),
        "exposure_matched": bool(result.exposure_matched[index]) if result.exposure_matched is not None else False,
        "coarse_dense": bool(result.coarse[index]) if result.coarse is not None else False,
        # Noisy frames: SURF run again on smoothed views (PipelineConfig.noisy_features_retry_sigma_px).
        "features_smoothed": (bool(result.features_smoothed[index]) if result.features_smoothed is not None
                              else False),
        # Kept regions the dense map could not measure, or left unranged, dropped beside one it ranged: only with
        # PipelineConfig.drop_unmeasured_below_share set (off by default); not in "objects".
        "dropped_unmeasured": (int(result.dropped_objects[index].sum()) if result.dropped_objects is not None
                               else 0),
        # The box the dense stage searched (x0, y0, width, height; the pixels of the image it ran on, e.g. of
        # --disparity-out's map; rectified pixels for a rectified pair): each object's depth statistics are over
        # its region's pixels inside it.
        "dense_box_xywh": ([int(v) for v in result.dense.crop_xywh[index].tolist()] if result.dense is not None
                           else None),
        "time_s": round(elapsed_s, 6),
    }


def format_report(report: dict, nearest_name: str = "nearest obstacle", batched: bool = False) -> list[str]:
    """The text lines of :func:`pair_report`'s ``report``. ``nearest_name``: what the obstacle ranged nearest is
    called (``demo`` says "nearest kept obstacle" when its ground truth holds a nearer one that was not kept).
    ``batched``: its time is its batch's over the batch's pairs (``estimate --pairs``), and says so."""
    if report.get("reason") and report.get("status") in NOT_RUN:  # a pair the pipeline did not run on
        from ..data import format_calibration

        return [f"status {report['status']}: {report['reason']}"] + (
            [f"  {format_calibration(report['calibration'])}"] if report.get("calibration") else [])
    per = " a pair over its batch" if batched else ""  # every pair of a batch read the same ms unexplained (an audit)
    lines = [f"status {report['status']}: {report['num_keypoints'][0]}+{report['num_keypoints'][1]} keypoints, "
             f"{report['num_matches']} matches, {report['num_inliers']} inliers, {report['time_s'] * 1e3:.0f} ms{per}"]
    if report.get("reason"):  # a ranged pair's hint (SWAPPED_VIEWS, IDENTICAL_VIEWS)
        lines.append(f"  {report['reason']}")
    if report.get("calibration"):
        from ..data import format_calibration

        lines.append(f"  {format_calibration(report['calibration'])}")
    corrected = [text for key, text in (("row_aligned", right_camera_line(report)),
                                        ("exposure_matched", "its exposure matched to the left camera's"))
                 if report.get(key)]
    if corrected:
        lines.append("  right camera: " + " and ".join(corrected))
    if report.get("rectified") and not report.get("row_aligned"):  # the JSON and the figure said so, the text not
        lines.append("  pair rectified from its fundamental matrix (uncalibrated, Sec. 3.4): depth measured on it")
    if report.get("verified") is False and report["objects"]:  # the JSON said so; the text did not
        lines.append(f"  geometry not verified: the dense map confirms {report['num_agreeing_inliers']} of "
                     f"{report['num_inliers']} RANSAC inliers, so each object needed more of its region measured "
                     f"(depth.min_object_valid_fraction_unverified)")
    if report.get("features_smoothed"):
        lines.append("  noisy frames: features found on smoothed views")
    if report.get("coarse_dense"):
        lines.append("  noisy frames: depth measured at half the working width")
    if report.get("dropped_unmeasured"):
        count = report["dropped_unmeasured"]
        lines.append(f"  {count} kept region{'s' if count > 1 else ''} the dense map could not measure: dropped")
    if report["r_min_m"] is not None:
        lines.append(f"  R_min {report['r_min_m']:.3f} m (d_max {report['d_max_px']:.2f} px), "
                     f"R_max {report['r_max_m']:.3f} m (d_min {report['d_min_px']:.2f} px), "
                     f"{report['range_rule']} rule")
    lines += object_lines(report)
    if report["nearest_m"] is not None:
        lines.append(f"  {nearest_name}: {report['nearest_m']:.2f} m, {report['nearest_side']} "
                     f"(nearest surface {report['nearest_surface_m']:.2f} m)")
    lines += [note for note in [unranged_repeated_note(report)] if note]
    floor = report.get("floor")  # a report read back from an older JSON has no such key
    if floor and report["nearest_ahead_m"] is not None:
        from ..depth.floor_distance import describe_floor

        lines.append("  " + describe_floor(floor["camera_height_m"], floor["pitch_deg"], "nearest obstacle",
                                           report["nearest_ahead_m"], report["nearest_ahead_surface_m"]))
    return lines


#: This process's export of ``--disparity-out`` (one per worker), so two listed pairs of one name are caught.
_EXPORTS: dict[tuple, object] = {}


def _write_disparity(args: argparse.Namespace, batch, result, time_s: float) -> None:
    """Write the run's dense maps into ``--disparity-out`` (a pair that would overwrite another of this
    process's is skipped with a warning naming both: :meth:`~svs_torch.evaluation.export.DisparityExport.write`)."""
    if not args.disparity_out:
        return
    _export(args).write(batch, result, time_s)


def _export(args: argparse.Namespace):
    """This process's :class:`~svs_torch.evaluation.export.DisparityExport` of ``--disparity-out``."""
    from ..evaluation.export import DisparityExport

    key = (args.disparity_out, args.disparity_format, args.method_name)
    return _EXPORTS.setdefault(key, DisparityExport(Path(args.disparity_out), args.disparity_format,
                                                    args.method_name))


def claim_export_names(args: argparse.Namespace, sources, export=None) -> None:
    """Give each export name to the first listed pair that has it, before any is written: worker processes each
    see a part of the list, and each wrote its own pair of a shared name (``eval3/Teddy`` and ``2003/Teddy``),
    one over the other, the survivor varying from run to run. Every worker claims from the whole list, so the
    later pairs are skipped and warned wherever they run, as in one process (and in ``eval``, whose pairs of
    each size run as one batch, whatever order the sizes run in). ``export``: this process's, by default."""
    if not args.disparity_out:
        return
    if export is None:  # a run starts: a new export (main() called again in one process kept the last run's names)
        _EXPORTS.pop((args.disparity_out, args.disparity_format, args.method_name), None)
        export = _export(args)
    for source in sources:
        # A pair whose files are missing never runs: it claims nothing (one whose file cannot be decoded still
        # does, and its name's later pair is skipped, warned).
        if source.problem is None and all(Path(p).exists() for p in (source.left, source.right) if p):
            export.claim_ahead(export_pair_name(source))


def export_pair_name(source) -> str:
    """The name a listed pair's batch carries (``data.load_pair_source``), which names its exported map."""
    return source.loaded_name


def forget_unrun_map(args: argparse.Namespace, source, status: str, export=None) -> None:
    """A listed pair this run could not range (``status``) loses the map an earlier run left in ``--disparity-out``
    (:meth:`~svs_torch.evaluation.export.DisparityExport.forget_unrun`); ``export``: this process's, by default."""
    if args.disparity_out:
        (_export(args) if export is None else export).forget_unrun(export_pair_name(source), status)
