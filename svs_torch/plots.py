"""The figures drawn with matplotlib (Agg canvas: no display, no pyplot state): the whole pipeline on one pair,
and keypoint matches. Each returns a uint8 BGR image for :func:`svs_torch.figures.write_image_atomic`.

Readable by construction: every title is wrapped to its panel's width (nothing is clipped, which the tests
check on the rendered text), labels on images are white on a dark box, match lines have a legend, a depth map
has a colour bar (metres), and where the batch has ground truth it is shown beside the estimate on the same
scale, with each object's true median depth next to the estimated one.

Figures are for people; nothing here feeds back into the pipeline or is differentiable. matplotlib is imported
inside the functions so that ``svs-depth --help`` stays fast.
"""

from __future__ import annotations

import textwrap

import cv2
import numpy as np
import torch

from .figures import objects_panel

__all__ = ["estimate_figure", "matches_figure", "pipeline_figure", "render"]

PANEL_IN = 4.2  # the longer side of an image panel, inches
MIN_PANEL_W_IN = 2.6  # narrower panels would clip their titles
TITLE_CHARS_PER_IN = 12  # characters per inch of a 10-point title
INLIER, OUTLIER, MATCH, KEYPOINT = "#2ca02c", "#d62728", "#e6b800", "#1f77b4"
LABEL_BOX = {"facecolor": "black", "alpha": 0.75, "edgecolor": "none", "pad": 2}
NO_DEPTH_GRAY = "0.82"  # pixels without a depth: gray, not the white of the page


def render(figure) -> np.ndarray:
    """A matplotlib figure as a uint8 BGR array."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(figure)
    canvas.draw()
    return cv2.cvtColor(np.asarray(canvas.buffer_rgba()), cv2.COLOR_RGBA2BGR)


def _panel_size_in(height: int, width: int) -> tuple[float, float]:
    """(width, height) in inches of one image panel: the longer side PANEL_IN, never narrower than
    MIN_PANEL_W_IN (a very tall image gets white space beside it, not a clipped title)."""
    aspect = height / max(width, 1)
    width_in = PANEL_IN if aspect <= 1 else PANEL_IN / aspect
    return max(width_in, MIN_PANEL_W_IN), min(PANEL_IN * aspect, PANEL_IN)


def _title(ax, text: str, width_in: float, fontsize: float = 10) -> None:
    """A title wrapped to the panel's width, so that it never runs past the panel or the page."""
    ax.set_title(textwrap.fill(text, max(int(width_in * TITLE_CHARS_PER_IN * 10 / fontsize), 12)),
                 fontsize=fontsize)


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


def _objects_axis(ax, batch, result, index: int, width_in: float) -> dict[int, float]:
    """The kept objects tinted and boxed, each labelled with its median depth (and true depth). Returns the true
    depths shown."""
    height, width = (int(v) for v in batch.image_hw[index].tolist())
    seg = result.segmentation.left
    panel = objects_panel(batch.left, seg, index)[:height, :width]
    ax.imshow(cv2.cvtColor(panel, cv2.COLOR_BGR2RGB), interpolation="nearest")
    objects = result.depth.objects
    truth = _true_object_depths(batch, seg, index)
    for slot, label in enumerate(seg.kept_labels[index].tolist()):
        if label < 0 or not (bool(objects.valid[index, slot]) or slot in truth):
            continue
        estimate = (f"{float(objects.depth_median_m[index, slot]):.2f} m" if bool(objects.valid[index, slot])
                    else "no depth")
        true = f"\ntrue {truth[slot]:.2f} m" if slot in truth else ""
        cx, cy = seg.regions.centroid_xy[index, label - 1].tolist()
        ax.text(cx, cy, f"#{slot + 1}: {estimate}{true}", color="white", fontsize=9, ha="center", va="center",
                bbox=LABEL_BOX, clip_on=True)
    _title(ax, "left: kept objects, median depth" + (" (and true depth)" if truth else ""), width_in)
    ax.set_axis_off()
    return truth


def _depth_axes(figure, grid, maps, width_in: float) -> None:
    """The depth maps side by side on one colour scale (2nd to 98th percentile), one colour bar in metres."""
    import matplotlib

    colours = matplotlib.colormaps["turbo_r"].with_extremes(bad=NO_DEPTH_GRAY)
    finite = np.concatenate([m[np.isfinite(m)] for _, m in maps]) if maps else np.zeros(0)
    low, high = (float(v) for v in np.percentile(finite, [2, 98])) if finite.size else (0.0, 1.0)
    high = max(high, low + 1e-3)
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
    for kind in (("inlier", "outlier") if inliers is not None else ("match",)):
        colour, name = styles[kind]
        if segments[kind]:
            ax.add_collection(LineCollection(segments[kind], colors=colour, linewidths=0.8))
        handles.append(Line2D([], [], color=colour, label=f"{name} ({len(segments[kind])})"))
    handles.append(Line2D([], [], marker="o", linestyle="none", markerfacecolor="none", markeredgecolor=KEYPOINT,
                          label="SURF keypoint"))
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.02), ncol=len(handles), fontsize=9,
              frameon=False)
    _title(ax, title, width_in)
    ax.set_axis_off()


def pipeline_figure(batch, result, index: int):
    """The matplotlib :class:`~matplotlib.figure.Figure` of :func:`estimate_figure` (for tests and notebooks)."""
    from matplotlib.figure import Figure

    from .pipeline import PipelineStatus

    height, width = (int(v) for v in batch.image_hw[index].tolist())
    maps = _depth_maps(batch, result, index)
    columns = 1 + len(maps)
    panel_w, panel_h = _panel_size_in(height, width)
    match_w = panel_w * columns
    match_h = min(match_w * height / (2 * width + max(4, width // 50)), PANEL_IN)
    figure = Figure(figsize=(match_w + 1.2, panel_h + match_h + 2.4), dpi=100, layout="constrained")
    grid = figure.add_gridspec(2, columns, height_ratios=[panel_h, match_h])
    truth = _objects_axis(figure.add_subplot(grid[0, 0]), batch, result, index, panel_w)
    _depth_axes(figure, grid, maps, panel_w)
    seg = result.segmentation
    images = [image[index, 0, :height, :width].detach().cpu().numpy() for image in (seg.left.masked,
                                                                                     seg.right.masked)]
    _matches_axis(figure.add_subplot(grid[1, :]), *images, result.features_left.keypoints,
                  result.features_right.keypoints, result.matches.idx[index].tolist(), result.fundamental.inliers,
                  index, f"matches on the segmented images: {int(result.num_keypoints[index, 0])} + "
                         f"{int(result.num_keypoints[index, 1])} keypoints, {int(result.num_matches[index])} matches",
                  match_w)
    nearest = result.depth.nearest
    summary = f"status {PipelineStatus(int(result.status[index])).name}, {result.range_rule} rule"
    if bool(nearest.valid[index]):
        slot = int(nearest.slot[index])
        true = f", true {truth[slot]:.2f} m" if slot in truth else ""
        summary = (f"nearest obstacle {float(nearest.depth_m[index]):.2f} m{true} (nearest surface "
                   f"{float(nearest.surface_m[index]):.2f} m); " + summary)
    name = batch.names[index] if batch.names else ""
    figure.suptitle(textwrap.fill(f"{name + ': ' if name else ''}{summary}", int(match_w * 11)), fontsize=11)
    return figure


def estimate_figure(batch, result, index: int) -> np.ndarray:
    """The pipeline on pair ``index`` as a uint8 BGR image: the kept objects with their median depths (and true
    depths), the dense depth map with a colour bar in metres (and the ground truth on the same scale when the
    batch has it), and the matches with a legend (RANSAC inliers green, outliers red)."""
    return render(pipeline_figure(batch, result, index))


def matches_figure(left: torch.Tensor, right: torch.Tensor, keypoints, pairs: list[list[int]],
                   inlier: list[bool] | None = None) -> np.ndarray:
    """Left and right images side by side, keypoints as circles, matches as lines, with a legend.

    Args:
        left, right: ``(H, W)`` float images in [0, 1].
        keypoints: :class:`~svs_torch.types.Keypoints` of a 2-image batch: row 0 left, row 1 right.
        pairs: ``[[i_left, i_right], ...]`` keypoint rows.
        inlier: optional flag per pair: inliers green, outliers red; otherwise every match is yellow.
    """
    from matplotlib.figure import Figure

    from .types import Keypoints

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
