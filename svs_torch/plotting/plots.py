"""The figures drawn with matplotlib (Agg canvas: no display, no pyplot state): the whole pipeline on one pair,
and keypoint matches. Each returns a uint8 BGR image for :func:`svs_torch.plotting.figures.write_image_atomic`.

Readable by construction: every title is wrapped to its panel's width (nothing is clipped, which the tests
check on the rendered text), labels on images are white on a dark box, match lines have a legend, a depth map
has a colour bar (metres), and where the batch has ground truth it is shown beside the estimate on the same
scale, with each object's true median depth next to the estimated one. The title names the truly nearest
obstacle's distance where it is known (:func:`true_nearest_obstacle`, or the caller's :class:`NearestTruth`) and
says when no kept region holds it: the obstacle the pipeline ranges nearest is then the "nearest kept obstacle".

Figures are for people: nothing here feeds the pipeline or is differentiable; matplotlib loads on first use."""

from __future__ import annotations

import textwrap
from typing import NamedTuple

import cv2
import numpy as np
import torch

from ..core.checks import check_instance
from ..core.mask_reductions import share_of_smaller
from ..core.types import StereoBatch
from .figures import LABEL_PAD_POINTS, floor_summary, objects_panel, place_depth_labels, render

__all__ = ["NearestTruth", "estimate_figure", "matches_figure", "pipeline_figure", "render", "true_nearest_obstacle"]

PANEL_IN = 4.2  # the longer side of an image panel, inches
MIN_PANEL_W_IN = 2.6  # narrower panels would clip their titles
TITLE_CHARS_PER_IN = 12  # characters per inch of a 10-point title
INLIER, OUTLIER, MATCH, KEYPOINT = "#2ca02c", "#d62728", "#e6b800", "#1f77b4"
LABEL_BOX = {"facecolor": "black", "alpha": 0.75, "edgecolor": "none", "pad": LABEL_PAD_POINTS}
NO_DEPTH_GRAY = "0.82"  # pixels without a depth: gray, not the white of the page
# true_nearest_obstacle's two tolerances. A kept region holds the truly nearest truth region when their overlap is
# at least this fraction of the smaller of the two: a kept neighbour's edge spills a pixel or two onto it (the 5x5
# opening, the learned segmenter's mask resized from 160 px), 2 px of a 40 px wide region being 5 %, while a kept
# region inside a large merged truth region (real scenes: one region for a whole table top) still counts.
MIN_NEAREST_OVERLAP = 0.2
# A truth region is "nearer" than the obstacle the pipeline ranges nearest only when its depth is below that
# obstacle's own true depth by more than this fraction: on real scenes the GT regions merge neighbouring surfaces,
# whose medians differ from a kept region's by a few per cent (Teddy, Art: the ranged region's truth is nearer).
NEARER_MARGIN = 0.03


class NearestTruth(NamedTuple):
    """The truly nearest obstacle of one pair, for :func:`pipeline_figure`'s title.

    Attributes:
        depth_m: its true distance, metres; inf: the truth holds no obstacle in view (only a wall, say).
        kept_slot: the kept slot (column of ``result.segmentation.left.kept_labels``) whose region holds it; −1:
            no kept region does (the pipeline missed it); None: not known (only the distance was given).
    """

    depth_m: float
    kept_slot: int | None = None


def _panel_size_in(height: int, width: int) -> tuple[float, float]:
    """(width, height) in inches of one image panel: the longer side PANEL_IN, never narrower than
    MIN_PANEL_W_IN (a very tall image gets white space beside it, not a clipped title)."""
    aspect = height / max(width, 1)
    width_in = PANEL_IN if aspect <= 1 else PANEL_IN / aspect
    return max(width_in, MIN_PANEL_W_IN), min(PANEL_IN * aspect, PANEL_IN)


def _title(ax, text: str, width_in: float, fontsize: float = 10) -> None:
    """A title wrapped to the panel's width, so that it never runs past the panel or the page."""
    ax.set_title(textwrap.fill(text, max(int(width_in * TITLE_CHARS_PER_IN * 10 / fontsize), 12)), fontsize=fontsize)


def _depth_map(disparity: torch.Tensor, valid: torch.Tensor, focal_px: float, baseline_m: float,
               doffs_px: float) -> np.ndarray:
    """``Z = f·B / (d + doffs)`` in metres as a float array, NaN where not valid or not a finite positive depth."""
    denom = disparity.detach().double().cpu() + doffs_px
    ok = valid.cpu() & (denom > 0)
    depth = torch.where(ok, focal_px * baseline_m / torch.where(ok, denom, torch.ones_like(denom)),
                        torch.full_like(denom, float("nan")))
    depth = depth.numpy()
    return np.where(np.isfinite(depth) & (depth > 0), depth, np.nan)


def _depth_maps(batch, result, index: int) -> list[tuple[str, np.ndarray]]:
    """The depth maps to show with their titles: the dense estimate, and the ground truth when the batch has it."""
    height, width = (int(v) for v in batch.image_hw[index].tolist())
    camera = (float(batch.focal_px[index]), float(batch.baseline_m[index]), float(batch.doffs_px[index]))
    maps = []
    if result.dense is not None:
        dense = _depth_map(result.dense.disparity_px[index, 0], result.dense.valid[index, 0], *camera)
        pixels = " in rectified pixels" if bool(result.rectified[index]) else ""
        maps.append((f"dense depth estimate{pixels} (gray: no depth)", dense[:height, :width]))
    if batch.disparity_px is not None:
        truth = _depth_map(batch.disparity_px[index, 0], batch.disparity_valid[index, 0], *camera)
        nominal = "" if bool(batch.calibrated[index]) else " (nominal calibration)"
        maps.append((f"ground-truth depth{nominal}", truth[:height, :width]))
    return maps


def _true_object_depths(batch, seg, index: int) -> dict[int, float]:
    """Each kept object's true median depth over its region (slot -> metres), from the batch's ground truth with
    the batch's calibration (the estimate's): empty without ground truth."""
    if batch.disparity_px is None:
        return {}
    height, width = (int(v) for v in batch.image_hw[index].tolist())
    camera = (float(batch.focal_px[index]), float(batch.baseline_m[index]), float(batch.doffs_px[index]))
    truth = _depth_map(batch.disparity_px[index, 0], batch.disparity_valid[index, 0], *camera)[:height, :width]
    labels = seg.labels[index, 0, :height, :width].cpu().numpy()
    depths = {}
    for slot, label in enumerate(seg.kept_labels[index].tolist()):
        values = truth[labels == label] if label > 0 else np.zeros(0)
        values = values[np.isfinite(values)]
        if values.size:
            depths[slot] = float(np.median(values))
    return depths


def _objects_axis(ax, batch, result, index: int, width_in: float, area_scale: float = 1.0) -> dict[int, float]:
    """The kept objects tinted, boxed and labelled with their median (and true) depths; returns the true depths. An
    unranged repeated pattern reads "no depth: it repeats" (as estimate says; a bare "no depth" read as unmeasured)."""
    height, width = (int(v) for v in batch.image_hw[index].tolist())
    seg = result.segmentation.left
    panel = objects_panel(batch.left, seg, index, area_scale)[:height, :width]
    ax.imshow(cv2.cvtColor(panel, cv2.COLOR_BGR2RGB), interpolation="nearest")
    objects, repeats = result.depth.objects, result.unranged_repeated
    truth, labels = _true_object_depths(batch, seg, index), []
    for slot, label in enumerate(seg.kept_labels[index].tolist()):
        if label < 0:  # a kept object without depth or truth is labelled too (it was left bare: an audit)
            continue
        estimate = (f"{float(objects.depth_median_m[index, slot]):.2f} m" if bool(objects.valid[index, slot])
                    else "no depth: it repeats" if repeats is not None and bool(repeats[index, slot]) else "no depth")
        true = f"\ntrue {truth[slot]:.2f} m" if slot in truth else ""
        top = float(seg.regions.bbox_xyxy[index, label - 1, 1])
        labels.append((*seg.regions.centroid_xy[index, label - 1].tolist(), top, f"#{slot + 1}: {estimate}{true}"))
    for (x, y), (*_, text) in zip(place_depth_labels(labels, (height, width), width_in), labels):
        ax.text(x, y, text, color="white", fontsize=9, ha="center", va="center", bbox=LABEL_BOX, clip_on=True)
    _title(ax, "left: kept objects, median depth" + (" (and true depth)" if truth else ""), width_in)
    ax.set_axis_off()
    return truth


def _depth_axes(figure, grid, maps, width_in: float) -> None:
    """The depth maps side by side on one colour scale (2nd to 98th percentile, 10 cm at least), a bar in metres."""
    import matplotlib

    colours = matplotlib.colormaps["turbo_r"].with_extremes(bad=NO_DEPTH_GRAY)
    finite = np.concatenate([m[np.isfinite(m)] for _, m in maps]) if maps else np.zeros(0)
    low, high = (float(v) for v in np.percentile(finite, [2, 98])) if finite.size else (0.0, 1.0)
    low, high = min(low, (low + high) / 2 - 0.05), max(high, (low + high) / 2 + 0.05)  # a lone wall: not 4-4.001 m
    axes, image = [], None
    for column, (title, depth) in enumerate(maps, start=1):
        ax = figure.add_subplot(grid[0, column])
        image = ax.imshow(depth, cmap=colours, vmin=low, vmax=high, interpolation="nearest")
        _title(ax, title, width_in)
        ax.set_xticks([])
        ax.set_yticks([])
        axes.append(ax)
    if image is not None:
        figure.colorbar(image, ax=axes, label="depth (m)", shrink=0.9)


def _match_segments(keypoints_left, keypoints_right, idx: list[int], inliers, index: int, offset: float):
    """Line segments of the matches, split into RANSAC inliers and outliers (all "matches" without inliers)."""
    segments: dict[str, list] = {"inlier": [], "outlier": [], "match": []}
    for i, j in enumerate(idx):
        if j < 0:
            continue
        x0, y0 = keypoints_left.xy[index, i].tolist()
        x1, y1 = keypoints_right.xy[index, j].tolist()
        kind = "match" if inliers is None else ("inlier" if bool(inliers[index, i]) else "outlier")
        segments[kind].append([(x0, y0), (x1 + offset, y1)])
    return segments


#: The most match lines a figure draws (an even share of each kind beyond it).
MAX_DRAWN_MATCHES = 200


def _matches_axis(ax, left: np.ndarray, right: np.ndarray, keypoints_left, keypoints_right, idx: list[int],
                  inliers, index: int, title: str, width_in: float) -> None:
    """Both images side by side (gray), keypoints as circles, matches as lines with a legend below."""
    from matplotlib.collections import LineCollection
    from matplotlib.lines import Line2D

    height, width = left.shape
    gap = max(4, width // 50)
    canvas = np.ones((height, 2 * width + gap))
    canvas[:, :width], canvas[:, width + gap:] = left, right
    ax.imshow(canvas, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
    for keypoints, offset in ((keypoints_left, 0), (keypoints_right, width + gap)):
        xy = keypoints.xy[index][keypoints.valid[index]].detach().cpu().numpy()
        ax.scatter(xy[:, 0] + offset, xy[:, 1], s=10, facecolors="none", edgecolors=KEYPOINT, linewidths=0.6)
    segments = _match_segments(keypoints_left, keypoints_right, idx, inliers, index, width + gap)
    styles = {"outlier": (OUTLIER, "outlier"), "inlier": (INLIER, "RANSAC inlier"), "match": (MATCH, "SAD match")}
    handles = []
    # Every stride-th match of each kind where there are more than MAX_DRAWN_MATCHES (a native pair's thousand
    # lines hid the images); the legend gives every count.
    stride = max(1, -(-sum(len(v) for v in segments.values()) // MAX_DRAWN_MATCHES))
    for kind in (("inlier", "outlier") if inliers is not None else ("match",)):
        colour, name = styles[kind]
        if segments[kind]:
            ax.add_collection(LineCollection(segments[kind][::stride], colors=colour, linewidths=0.8))
        drawn = f", {len(segments[kind][::stride])} drawn" if stride > 1 else ""
        handles.append(Line2D([], [], color=colour, label=f"{name} ({len(segments[kind])}{drawn})"))
    handles.append(Line2D([], [], marker="o", linestyle="none", markerfacecolor="none", markeredgecolor=KEYPOINT,
                          label="SURF keypoint"))
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.02), ncol=len(handles), fontsize=9,
              frameon=False)
    _title(ax, title, width_in)
    ax.set_axis_off()


def _region_lower_medians(values: torch.Tensor, known: torch.Tensor, labels: torch.Tensor,
                          num_labels: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Lower median (``torch.median``'s) of ``values`` ``(H, W)`` over each region 1..n of ``labels`` ``(H, W)``
    where ``known``: ``(n,)`` medians (0 where empty) and ``(n,)`` int64 counts. Two stable sorts (by value, then
    by label) put every region's values in order side by side: memory O(H·W) whatever n, where
    :func:`svs_torch.depth.kept_region_lower_median` needs O(n·H·W)."""
    take = known & (labels > 0)
    region, value = labels[take], values[take]
    order = torch.argsort(value, stable=True)
    region, value = region[order], value[order]
    order = torch.argsort(region, stable=True)
    region, value = region[order], value[order]
    count = torch.bincount(region, minlength=num_labels + 1)[1:]
    start = torch.cumsum(count, 0) - count
    at = (start + (count - 1).clamp(min=0) // 2).clamp(max=max(value.numel() - 1, 0))
    median = value[at] if value.numel() else torch.zeros(num_labels, dtype=values.dtype, device=values.device)
    return torch.where(count > 0, median, torch.zeros_like(median)), count


def _truth_nearest_region(batch, index: int) -> tuple[float, torch.Tensor] | None:
    """The truth region of pair ``index`` with the smallest lower-median GT depth: (metres, ``(H, W)`` mask), or
    None without ground-truth depth or without a region. Every region of
    :func:`svs_torch.segmentation.learned.obstacle_truth` counts, not only the two largest it keeps as the
    segmenter's target: a smaller obstacle can be the nearer one (the demo's scene 3 with four objects)."""
    from ..segmentation.learned import obstacle_truth

    if batch.disparity_px is None:
        return None
    pair = batch.select([index])
    labels = obstacle_truth(pair).labels[0, 0]
    depth, known = pair.ground_truth_depth_m()
    region_depth, count = _region_lower_medians(depth[0, 0], known[0, 0], labels, int(labels.max()))
    if not bool((count > 0).any()):
        return None
    nearest = int(torch.where(count > 0, region_depth, torch.inf).argmin())  # ties: the lower label
    return float(region_depth[nearest]), labels == nearest + 1


def true_nearest_obstacle(batch, result, index: int) -> NearestTruth | None:
    """The truly nearest obstacle of pair ``index`` from the batch's ground truth, and the kept region of
    ``result`` (a :class:`~svs_torch.pipeline.PipelineResult`) that holds it.

    The obstacle the pipeline ranges nearest is the nearest (its slot, its own true median depth) unless a truth
    region (:func:`_truth_nearest_region`) is nearer by more than ``NEARER_MARGIN``; that region is then held by
    the kept region overlapping it most, when the overlap reaches ``MIN_NEAREST_OVERLAP`` of the smaller of the
    two, and missed (``kept_slot`` −1) otherwise. None without ground truth, for an uncalibrated pair (no GT
    depth) or when the truth has no region. Not differentiable (ground-truth statistics).
    """
    found = _truth_nearest_region(batch, index)
    if found is None:
        return None
    depth_m, region = found
    seg = result.segmentation.left
    ranged = result.depth.nearest
    own = _true_object_depths(batch, seg, index)
    slot = int(ranged.slot[index]) if ranged is not None and bool(ranged.valid[index]) else -1
    if slot in own and depth_m >= own[slot] * (1 - NEARER_MARGIN):
        return NearestTruth(own[slot], slot)
    overlap = []
    for label in seg.kept_labels[index].tolist():
        kept = seg.labels[index, 0] == label
        overlap.append(share_of_smaller(region, kept) if label > 0 else 0.0)
    best = max(range(len(overlap)), key=overlap.__getitem__, default=-1)
    return NearestTruth(depth_m, best if best >= 0 and overlap[best] >= MIN_NEAREST_OVERLAP else -1)


def _nearest_summary(result, index: int, truth: dict[int, float], true_nearest: NearestTruth | None) -> list[str]:
    """The title's parts about the nearest obstacle. The one the pipeline ranges nearest is "the nearest obstacle"
    only where no truth says otherwise; where the truly nearest one is known to be another (or not known to be
    it), it is "the nearest kept obstacle", and the true nearest distance follows, with whether it was kept. Its
    "true" is its own median (its label's); a truly nearer part its fatter region holds is named apart."""
    nearest = result.depth.nearest
    slot = int(nearest.slot[index]) if nearest is not None and bool(nearest.valid[index]) else None
    is_nearest = true_nearest is None or (slot is not None and true_nearest.kept_slot == slot)
    parts = []
    if slot is not None:
        true_m = truth.get(slot, true_nearest.depth_m if true_nearest is not None and is_nearest else None)
        true = f", true {true_m:.2f} m" if true_m is not None else ""
        name = "nearest obstacle" if is_nearest else "nearest kept obstacle"
        parts.append(f"{name} {float(nearest.depth_m[index]):.2f} m{true} (nearest surface "
                     f"{float(nearest.surface_m[index]):.2f} m)")
        if is_nearest and true_nearest is not None and true_nearest.depth_m < (true_m or 0) * (1 - NEARER_MARGIN):
            parts.append(f"the truly nearest part of it {true_nearest.depth_m:.2f} m")
    if not is_nearest:
        depth, kept_slot = true_nearest
        if kept_slot is None:
            parts.append(f"true nearest obstacle {depth:.2f} m" if np.isfinite(depth) else "no true obstacle in view")
        else:  # #k's region holds it, whose own median (its label's) may be farther; nothing ranged: #k unranged
            where = ("was not kept" if kept_slot < 0 else f"lies in #{kept_slot + 1}, "
                     + ("not ranged nearest" if slot is not None else "which got no distance"))
            parts.append(f"the nearest obstacle, true {depth:.2f} m, {where}")
    return parts


def pipeline_figure(batch, result, index: int, *, true_nearest: NearestTruth | float | None = None,
                    area_scale: float = 1.0):
    """The matplotlib :class:`~matplotlib.figure.Figure` of :func:`estimate_figure` (for tests and notebooks).

    ``true_nearest``: the truly nearest obstacle for the title, a :class:`NearestTruth` or only its distance in
    metres (the title then cannot say whether it was kept); None: :func:`true_nearest_obstacle` of the batch's
    ground truth, where it has one. ``area_scale``: input pixels a pixel of ``batch`` (areas said as the report's).
    """
    from matplotlib.figure import Figure

    from ..pipeline import PipelineResult, PipelineStatus

    # Swapped or missing, each failed deep inside with an AttributeError ('PipelineResult' has no 'disparity_px').
    check_instance(batch, "batch", StereoBatch)
    check_instance(result, "result", PipelineResult)
    if true_nearest is None:
        true_nearest = true_nearest_obstacle(batch, result, index)
    elif not isinstance(true_nearest, NearestTruth):
        true_nearest = NearestTruth(float(true_nearest))
    height, width = (int(v) for v in batch.image_hw[index].tolist())
    maps = _depth_maps(batch, result, index)
    columns = 1 + len(maps)
    panel_w, panel_h = _panel_size_in(height, width)
    match_w = panel_w * columns
    match_h = min(match_w * height / (2 * width + max(4, width // 50)), PANEL_IN)
    figure = Figure(figsize=(match_w + 1.2, panel_h + match_h + 2.4), dpi=100, layout="constrained")
    grid = figure.add_gridspec(2, columns, height_ratios=[panel_h, match_h])
    truth = _objects_axis(figure.add_subplot(grid[0, 0]), batch, result, index, panel_w, area_scale)
    _depth_axes(figure, grid, maps, panel_w)
    seg = result.segmentation
    # The whole views, dimmed outside the kept regions: the default finds its features on the whole images, the
    # paper's preset on the masked ones (inside the regions), and either is drawn where it was found.
    images = [(view[index, 0, :height, :width] * (0.35 + 0.65 * kept[index, 0, :height, :width].to(view.dtype)))
              .detach().cpu().numpy() for view, kept in ((batch.left, seg.left.kept_mask),
                                                         (batch.right, seg.right.kept_mask))]
    _matches_axis(figure.add_subplot(grid[1, :]), *images, result.features_left.keypoints,
                  result.features_right.keypoints, result.matches.idx[index].tolist(), result.fundamental.inliers,
                  index, f"matches (the kept regions bright): {int(result.num_keypoints[index, 0])} + "
                         f"{int(result.num_keypoints[index, 1])} keypoints, {int(result.num_matches[index])} matches",
                  match_w)
    kept = result.verified is not None and bool((seg.left.kept_labels[index] > 0).any())  # the text's rule
    status = f"status {PipelineStatus(int(result.status[index])).name}, {result.range_rule} rule" + (
        "; geometry not verified (the text says why)" if kept and not bool(result.verified[index]) else "")
    summary = "; ".join([*_nearest_summary(result, index, truth, true_nearest), *floor_summary(result, index), status])
    name = batch.names[index].encode("utf-8", "backslashreplace").decode() if batch.names else ""  # (surrogates)
    figure.suptitle(textwrap.fill(f"{name + ': ' if name else ''}{summary}", int(match_w * 11)), fontsize=11)
    return figure


def estimate_figure(batch, result, index: int, **keywords) -> np.ndarray:
    """The pipeline on pair ``index`` as a uint8 BGR image: the kept objects with their median (and true) depths,
    the dense depth map with a colour bar in metres (the ground truth on the same scale where the batch has it), and
    the matches with a legend (RANSAC inliers green, outliers red). ``keywords``: :func:`pipeline_figure`'s."""
    return render(pipeline_figure(batch, result, index, **keywords))


def matches_figure(left: torch.Tensor, right: torch.Tensor, keypoints, pairs: list[list[int]],
                   inlier: list[bool] | None = None) -> np.ndarray:
    """Left and right images side by side, keypoints as circles, matches as lines, with a legend.

    Args:
        left, right: ``(H, W)`` float images in [0, 1].
        keypoints: :class:`~svs_torch.core.types.Keypoints` of a 2-image batch: row 0 left, row 1 right.
        pairs: ``[[i_left, i_right], ...]`` keypoint rows.
        inlier: optional flag per pair: inliers green, outliers red; otherwise every match is yellow.
    """
    from matplotlib.figure import Figure

    from ..core.types import Keypoints

    height, width = left.shape
    num_left = keypoints.valid.shape[1]
    idx = [-1] * num_left
    flags = torch.zeros(1, num_left, dtype=torch.bool)
    for n, (i, j) in enumerate(pairs):
        idx[i] = j
        flags[0, i] = bool(inlier[n]) if inlier is not None else False
    panel_w, _ = _panel_size_in(height, width)
    match_w = 2 * panel_w
    match_h = min(match_w * height / (2 * width + max(4, width // 50)), 2 * PANEL_IN)
    figure = Figure(figsize=(match_w + 0.4, match_h + 1.3), dpi=100, layout="constrained")

    def side(row: int) -> Keypoints:
        return Keypoints(*(getattr(keypoints, f)[row:row + 1] for f in ("xy", "scale", "score", "laplacian_sign",
                                                                       "orientation", "valid")))

    _matches_axis(figure.add_subplot(), left.detach().cpu().numpy(), right.detach().cpu().numpy(), side(0),
                  side(1), idx, flags if inlier is not None else None, 0,
                  f"{int(keypoints.valid[0].sum())} + {int(keypoints.valid[1].sum())} keypoints, {len(pairs)} matches",
                  match_w)
    return render(figure)
