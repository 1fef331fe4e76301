"""What ``svs-depth estimate`` says of each kept object of a pair: its JSON entry (depth, support, side, distance
ahead along the floor) and its text line. Of an object that repeats itself along the rows (a fence, a railing, a
grate) it also says its period, and, where its alias could not be told and it was left without a distance, the
distances its aliases would give (:func:`~svs_torch.depth.alias_choice.alias_depths_m`). Without them such an
object read "no depth" like one nothing could be measured on, and the pair's nearest obstacle named a farther one
with no hint that a pattern ahead had been seen (the rendered panels of ``experiments/repeated_patterns.py``).
"""

from __future__ import annotations

__all__ = ["MAX_ALIASES_SAID", "object_lines", "object_reports", "report_number", "repeated_fields",
           "repeated_words", "unranged_repeated_note"]

#: The most alias distances a text line lists; more are said as their span.
MAX_ALIASES_SAID = 4


def report_number(value, valid) -> float | None:
    """A tensor's value rounded for a report, None where not ``valid``."""
    return round(float(value), 4) if bool(valid) else None


def _ahead(result, index: int, slot: int, square: bool) -> dict:
    """An object's distance ahead along the floor (median and low percentile), null where no floor was found or
    the pixels are not square (``square`` False)."""
    if result.floor is None or not square:
        return {"ahead_m": None, "ahead_p10_m": None}
    objects = result.floor.objects
    valid = objects.valid[index, slot]
    return {"ahead_m": report_number(objects.depth_median_m[index, slot], valid),
            "ahead_p10_m": report_number(objects.depth_low_m[index, slot], valid)}


def object_reports(result, index: int, factors: tuple[float, float], square: bool) -> list[dict]:
    """The kept objects of pair ``index``, in input pixels (``factors``: input over working pixels, x and y;
    ``square``: those pixels are square, so the distances ahead along the floor hold)."""
    from ..depth.depth_types import ObstacleSide

    objects, regions = result.depth.objects, result.segmentation.left.regions
    fx, fy = factors
    repeated = repeated_fields(result, index, factors)
    reports = []
    for slot, label in enumerate(result.segmentation.left.kept_labels[index].tolist()):
        if label < 0:
            continue
        x0, y0, x1, y1 = regions.bbox_xyxy[index, label - 1].tolist()
        reports.append({
            "label": slot + 1,
            "area_px": int(round(int(regions.area_px[index, label - 1]) * fx * fy)),
            "bbox_xyxy": [int(round(x0 * fx)), int(round(y0 * fy)), int(round(x1 * fx)), int(round(y1 * fy))],
            # the pixels its depth is measured over: the region's interior (PipelineResult.object_labels)
            "measured_area_px": int(round(int(objects.area_px[index, slot]) * fx * fy)),
            "depth_m": report_number(objects.depth_median_m[index, slot], objects.valid[index, slot]),
            "depth_p10_m": report_number(objects.depth_low_m[index, slot], objects.valid[index, slot]),
            "depth_p90_m": report_number(objects.depth_high_m[index, slot], objects.valid[index, slot]),
            # where the floor was found: its distance ahead along it, what guide says (svs_torch.depth.floor_distance)
            **_ahead(result, index, slot, square),
            "num_inliers": int(objects.num_inliers[index, slot]),
            "num_valid_px": (int(objects.num_valid_px[index, slot]) if objects.num_valid_px is not None else None),
            "num_in_view_px": (int(objects.num_in_view_px[index, slot]) if objects.num_in_view_px is not None
                               else None),
            "side": ObstacleSide(int(objects.side[index, slot])).name.lower(),
            # its region spanned two surfaces far apart: ranged over the nearer (PipelineConfig.measure_near_surface)
            "near_surface": bool(result.near_surface[index, slot]) if result.near_surface is not None else False,
            # a fence, a railing, a grate: its period, and where left without a distance, its aliases' distances
            **repeated[slot],
        })
    return reports


def object_lines(report: dict) -> list[str]:
    """A text line for each of ``report``'s objects (:func:`~svs_torch.cli.estimate_report.format_report`)."""
    lines = []
    # The dense counts are of the image the pipeline ran on; the areas and boxes of the input (--size resamples).
    sizes = report.get("image_size_px"), report.get("working_size_px")
    working = f" at the working {sizes[1][0]}x{sizes[1][1]}" if sizes[1] and sizes[0] != sizes[1] else ""
    for obj in report["objects"]:
        depth = repeated_words(obj) or "no depth"
        if obj["depth_m"] is not None:
            depth = f"{obj['depth_m']:.3f} m (p10 {obj['depth_p10_m']:.3f}, p90 {obj['depth_p90_m']:.3f})"
        support = f"{obj['num_inliers']} inliers"
        if obj["num_valid_px"] is not None:
            support = f"{obj['num_valid_px']} valid px{working}"
            if obj["num_in_view_px"] < obj["num_valid_px"]:  # some near the left border, where a match may be lost
                support += f" ({obj['num_in_view_px']} where the right view holds every searched disparity)"
        if obj.get("near_surface"):  # a report read back from an older JSON has no such key
            depth += f" over the near surface ({obj['measured_area_px']} px) of a region spanning two"
        lines.append(f"  object {obj['label']}: {depth}, {support}, {obj['side']}, {obj['area_px']} px, "
                     f"box {obj['bbox_xyxy']}")
    return lines


def repeated_fields(result, index: int, factors: tuple[float, float]) -> list[dict]:
    """Per kept slot of pair ``index`` of a :class:`~svs_torch.pipeline.PipelineResult`: ``period_px`` (input
    pixels along the rows; None: it does not repeat, or the check did not run) and ``alias_depths_m`` (nearest
    first, where it repeats and was left without a distance; else None). ``factors``: input pixels per pipeline
    pixel, x and y."""
    import torch

    from ..core.pair_trees import take_pairs
    from ..depth.alias_choice import alias_depths_m

    dense = result.dense
    slots = result.depth.objects.valid.shape[1]
    if dense is None or dense.repeated is None or result.focal_px is None:
        return [{"period_px": None, "alias_depths_m": None} for _ in range(slots)]
    periods = dense.repeated.period_px[index].tolist()
    unranged = result.unranged_repeated[index].tolist()
    aliases: list[list[float] | None] = [None] * slots
    if any(unranged):  # the distances a repeat fits, only where one was left without a distance: the pair's dense
        one = slice(index, index + 1)  # map taken out for each pair reported took 0.5 ms of estimate --pairs' 46
        depth_m, valid = alias_depths_m(take_pairs(dense, torch.tensor([index]), dense.valid.shape[0]),
                                        result.focal_px[one], result.baseline_m[one], result.doffs_px[one])
        aliases = [[round(float(z), 3) for z, ok in zip(depth_m[0, slot].tolist(), valid[0, slot].tolist()) if ok]
                   if unranged[slot] else None for slot in range(slots)]
    return [{"period_px": round(periods[slot] * factors[0], 1) if periods[slot] > 0 else None,
             "alias_depths_m": aliases[slot]} for slot in range(slots)]


def repeated_words(obj: dict) -> str | None:
    """What an object line says in place of "no depth" of a repeated object left without one; None for any other
    object (a report read back from an older JSON has no such keys)."""
    aliases = obj.get("alias_depths_m")
    if obj.get("depth_m") is not None or obj.get("period_px") is None or aliases is None:
        return None
    words = f"no depth: a pattern repeating every {obj['period_px']:g} px along the rows"
    if len(aliases) > MAX_ALIASES_SAID:
        return f"{words} (it fits any of {len(aliases)} distances, {aliases[0]:.2f}-{aliases[-1]:.2f} m)"
    if len(aliases) > 1:
        return f"{words} (it fits {', '.join(f'{z:.2f}' for z in aliases[:-1])} or {aliases[-1]:.2f} m alike)"
    return words


def unranged_repeated_note(report: dict) -> str | None:
    """A line for a pair with a repeated object left without a distance (None where there is none): a fence, a
    railing or a grate was seen, and the nearest obstacle said, if any, is of the ranged objects only."""
    labels = [str(obj["label"]) for obj in report.get("objects", []) if repeated_words(obj) is not None]
    if not labels:
        return None
    which = f"object{'s' if len(labels) > 1 else ''} {', '.join(labels)}"
    if report.get("nearest_m") is None:
        return f"  {which}: a repeated pattern (a fence, a railing, a grate?) seen, whose distance cannot be told"
    return f"  {which}: a repeated pattern seen but not ranged; the nearest obstacle said is of the ranged ones only"
