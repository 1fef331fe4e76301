"""A rectified pair side by side with epipolar lines: after rectification a point and its match lie on the same
image row, so horizontal lines through a few matched points show at a glance whether rectification worked.

Used by ``svs-depth calibrate --figure`` (the chessboard corners after the calibrated rectification) and
``svs-depth estimate --figure`` (the RANSAC inliers after the pipeline's uncalibrated rectification, Sec. 3.4,
or the calibrated one). A figure for people: nothing here feeds back into the pipeline or is differentiable.
"""

from __future__ import annotations

import numpy as np

from .plots import PANEL_IN, _title, render

__all__ = ["pipeline_rectified_figure", "rectified_pair_figure", "spread_rows", "stack_images"]

#: Line colours, one per epipolar line, on the matched points of both views alike.
LINE_COLOURS = ["#e6194b", "#3cb44b", "#ffe119", "#4363d8", "#f58231", "#911eb4", "#42d4f4", "#f032e6",
                "#bfef45", "#fabed4"]


def spread_rows(y: np.ndarray, count: int) -> np.ndarray:
    """Indices of at most ``count`` of the points with rows ``y`` ``(N,)``, spread evenly from top to bottom (the
    points at evenly spaced ranks of y), so the lines cover the image instead of bunching on one object."""
    if y.size == 0 or count <= 0:
        return np.zeros(0, dtype=np.int64)
    order = np.argsort(y, kind="stable")
    ranks = np.unique(np.linspace(0, y.size - 1, min(count, y.size)).round().astype(np.int64))
    return order[ranks]


def rectified_pair_figure(left: np.ndarray, right: np.ndarray, points_left: np.ndarray, points_right: np.ndarray,
                          title: str, num_lines: int = 8, point_label: str = "matched point") -> np.ndarray:
    """The rectified ``left`` and ``right`` images (``(H, W)`` float in [0, 1]) side by side as a uint8 BGR image:
    every matched point drawn in both views (``points_left``, ``points_right`` ``(N, 2)`` x, y in rectified
    pixels, row i of one matching row i of the other), and ``num_lines`` horizontal lines across both views,
    each through one matched pair spread over the rows and drawn in that pair's colour: on a well rectified pair
    each line passes through its point in both views. The legend gives the rows' disagreement over all pairs."""
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    height, width = left.shape
    gap = max(4, width // 50)
    canvas = np.ones((height, 2 * width + gap))
    canvas[:, :width], canvas[:, width + gap:] = left, right
    figure_w = 2 * PANEL_IN
    figure_h = figure_w * height / (2 * width + gap)
    figure = Figure(figsize=(figure_w + 0.4, figure_h + 1.3), dpi=100, layout="constrained")
    ax = figure.add_subplot()
    ax.imshow(canvas, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
    points_left = np.asarray(points_left, dtype=np.float64).reshape(-1, 2)
    points_right = np.asarray(points_right, dtype=np.float64).reshape(-1, 2)
    if len(points_left):
        ax.scatter(points_left[:, 0], points_left[:, 1], s=9, c="#1f77b4", linewidths=0)
        ax.scatter(points_right[:, 0] + width + gap, points_right[:, 1], s=9, c="#1f77b4", linewidths=0)
    chosen = spread_rows(points_left[:, 1], num_lines)
    for n, index in enumerate(chosen):
        colour = LINE_COLOURS[n % len(LINE_COLOURS)]
        y = points_left[index, 1]
        ax.plot([0, 2 * width + gap - 1], [y, y], color=colour, linewidth=0.8)
        ax.scatter([points_left[index, 0], points_right[index, 0] + width + gap],
                   [points_left[index, 1], points_right[index, 1]], s=40, facecolors="none", edgecolors=colour,
                   linewidths=1.2)
    ax.set_xlim(-0.5, 2 * width + gap - 0.5)
    ax.set_ylim(height - 0.5, -0.5)
    rows_apart = np.abs(points_left[:, 1] - points_right[:, 1])
    summary = (f"|y_left - y_right| over {len(rows_apart)} {point_label}s: median {np.median(rows_apart):.2f} px, "
               f"max {rows_apart.max():.2f} px" if rows_apart.size else f"no {point_label}s")
    handles = [Line2D([], [], color=LINE_COLOURS[0], label="epipolar line (one image row) through a matched pair"),
               Line2D([], [], marker="o", linestyle="none", color="#1f77b4", markersize=3, label=summary)]
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.01), ncol=1, fontsize=9, frameon=False)
    _title(ax, title, figure_w)
    ax.set_axis_off()
    return render(figure)


def stack_images(top: np.ndarray, bottom: np.ndarray) -> np.ndarray:
    """Two BGR images one above the other on white, centred (for a figure with a panel added below)."""
    width = max(top.shape[1], bottom.shape[1])

    def padded(image: np.ndarray) -> np.ndarray:
        out = np.full((image.shape[0], width, 3), 255, np.uint8)
        start = (width - image.shape[1]) // 2
        out[:, start:start + image.shape[1]] = image
        return out

    return np.vstack([padded(top), padded(bottom)])


def pipeline_rectified_figure(batch, result, index: int, calibration_name: str | None = None) -> np.ndarray | None:
    """Pair ``index`` of a pipeline run as rectified, with epipolar lines through its RANSAC inliers (a uint8 BGR
    image), or None when the pair was not rectified: by the homographies the pipeline measured its disparities
    after (``result.rectified``; ``result.H_left`` / ``H_right``: the uncalibrated rectification from F, Sec.
    3.4, or the right view's row alignment of a loose rig, ``result.row_aligned``; both views warped by them, the
    inliers mapped by them) or, with ``calibration_name``, by that calibration file before the pipeline (the
    batch's images are the rectified ones)."""
    import torch

    from ..geometry.rectification import apply_homography, warp_rectified

    height, width = (int(v) for v in batch.image_hw[index].tolist())
    inliers = result.fundamental.inliers[index] & result.points.valid[index]
    left, right = batch.left[index:index + 1], batch.right[index:index + 1]
    points = [result.points.left[index:index + 1], result.points.right[index:index + 1]]
    if bool(result.rectified[index]):
        # What the disparities were measured after: F's rectification, or the row alignment, which warps only the
        # right view.
        H = [result.H_left[index:index + 1], result.H_right[index:index + 1]]
        left, right = warp_rectified(left, H[0]), warp_rectified(right, H[1])
        mapped = [apply_homography(h, p) for h, p in zip(H, points)]
        points = [m.xy for m in mapped]
        inliers = inliers & mapped[0].valid[0] & mapped[1].valid[0]
        how = ("the right view's rows aligned to the left view's (its turn, shift and scale fitted to the matches)"
               if bool(result.row_aligned[index])
               else "rectified from F (the paper's uncalibrated rectification, Sec. 3.4)")
    elif calibration_name:
        how = f"rectified by the calibration {calibration_name}"
    else:
        return None
    with torch.no_grad():
        images = [image[0, 0, :height, :width].detach().cpu().clamp(0, 1).numpy() for image in (left, right)]
        chosen = [p[0][inliers].detach().cpu().numpy() for p in points]
    return rectified_pair_figure(images[0], images[1], chosen[0], chosen[1],
                                 f"{how}: each line is one row through a RANSAC inlier and its match",
                                 point_label="RANSAC inlier")
