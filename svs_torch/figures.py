"""Figures for the command line: panels of images and masks drawn with OpenCV, and the pipeline figure drawn
with matplotlib (Agg, no display; imported inside the functions so that ``svs-depth --help`` stays fast).

Figures are for people; nothing here feeds back into the pipeline. Files are written whole (a temporary file
beside the target, then a rename) with the permissions the umask gives a new file.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path

import cv2
import numpy as np
import torch

from .checks import InputError
from .types import Segmentation

__all__ = [
    "FIGURE_SUFFIXES", "LOSSLESS_SUFFIXES", "PALETTE_BGR", "check_output_path", "compose_grid", "estimate_figure",
    "gray_to_bgr", "labels_image", "matches_figure", "segmentation_panels", "titled_panel", "write_image_atomic",
]

#: Colours of kept objects, largest first (BGR).
PALETTE_BGR = [(0, 165, 255), (255, 128, 0), (0, 200, 0), (200, 0, 200), (0, 220, 220), (128, 0, 255)]
#: File name endings a figure can be written as, and those that keep every value exactly (label images).
FIGURE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
LOSSLESS_SUFFIXES = (".png", ".bmp", ".tif", ".tiff")
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def gray_to_bgr(gray: torch.Tensor) -> np.ndarray:
    """``(H, W)`` float in [0, 1] → uint8 BGR image."""
    u8 = (gray.detach().cpu().clamp(0, 1) * 255).round().to(torch.uint8).numpy()
    return cv2.cvtColor(u8, cv2.COLOR_GRAY2BGR)


def _wrap(text: str, width_px: int, scale: float) -> list[str]:
    """Greedy word wrap of ``text`` so that each line is at most ``width_px`` wide at font ``scale``."""
    lines: list[str] = []
    for word in text.split():
        candidate = f"{lines[-1]} {word}" if lines else word
        if lines and cv2.getTextSize(candidate, _FONT, scale, 1)[0][0] <= width_px:
            lines[-1] = candidate
        else:
            lines.append(word)
    return lines or [""]


def titled_panel(panel: np.ndarray, title: str) -> np.ndarray:
    """Put a title strip above a panel; a title wider than the panel is wrapped onto more lines, never clipped."""
    width = panel.shape[1]
    scale = 0.45 if width >= 160 else 0.35
    lines = _wrap(title, max(width - 8, 1), scale)
    line_h = int(round(36 * scale))
    strip = np.full((line_h * len(lines) + 6, width, 3), 255, np.uint8)
    for n, line in enumerate(lines):
        cv2.putText(strip, line, (4, line_h * (n + 1)), _FONT, scale, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([strip, panel])


def _label(panel: np.ndarray, text: str, origin: tuple[int, int], colour: tuple[int, int, int],
           scale: float = 0.4) -> None:
    """Text in ``colour`` on a black box (readable on any texture and on the object's own tint), kept inside."""
    (w, h), base = cv2.getTextSize(text, _FONT, scale, 1)
    x = int(min(max(origin[0], 0), max(panel.shape[1] - w - 2, 0)))
    y = int(min(max(origin[1], h + 2), max(panel.shape[0] - base - 1, h + 2)))
    cv2.rectangle(panel, (x - 1, y - h - 2), (x + w + 1, y + base), (0, 0, 0), cv2.FILLED)
    cv2.putText(panel, text, (x, y), _FONT, scale, colour, 1, cv2.LINE_AA)


def _objects_panel(image: torch.Tensor, seg: Segmentation, index: int) -> np.ndarray:
    """The grayscale image dimmed outside the kept objects, each object tinted, boxed and numbered."""
    gray = image[index, 0]
    panel = gray_to_bgr(gray * 0.35)
    base = gray_to_bgr(gray)
    labels = seg.labels[index, 0].cpu().numpy()
    for rank, label in enumerate(seg.kept_labels[index].tolist()):
        if label < 0:
            continue
        colour = np.array(PALETTE_BGR[rank % len(PALETTE_BGR)], np.float32)
        region = labels == label
        panel[region] = (0.6 * base[region] + 0.4 * colour).astype(np.uint8)
        x0, y0, x1, y1 = seg.regions.bbox_xyxy[index, label - 1].tolist()
        area = int(seg.regions.area_px[index, label - 1])
        cv2.rectangle(panel, (x0, y0), (x1 - 1, y1 - 1), tuple(int(c) for c in colour), 1)
        _label(panel, f"#{rank + 1} {area}px", (x0 + 2, y0 + 12), tuple(int(c) for c in colour))
    return panel


def segmentation_panels(image: torch.Tensor, seg: Segmentation, index: int, side: str) -> list[np.ndarray]:
    """Three titled panels of one image: the input, the opened binary mask, the kept objects."""
    threshold = int(seg.threshold_level[index])
    mask = seg.opened[index, 0].to(image.dtype)
    num_kept = int((seg.kept_labels[index] >= 0).sum())
    return [
        titled_panel(gray_to_bgr(image[index, 0]), f"{side} image"),
        titled_panel(gray_to_bgr(mask), f"{side} binary (Otsu {threshold}) + opening"),
        titled_panel(_objects_panel(image, seg, index), f"{side}: {num_kept} kept"),
    ]


def compose_grid(columns: list[list[np.ndarray]], gap: int = 6) -> np.ndarray:
    """Stack panels: each inner list is a column, top to bottom; columns side by side, white gaps."""
    height = max(sum(p.shape[0] for p in col) + gap * (len(col) - 1) for col in columns)
    stacked = []
    for col in columns:
        width = max(p.shape[1] for p in col)
        parts = []
        for i, p in enumerate(col):
            padded = np.full((p.shape[0], width, 3), 255, np.uint8)
            padded[:, :p.shape[1]] = p
            parts.append(padded)
            if i < len(col) - 1:
                parts.append(np.full((gap, width, 3), 255, np.uint8))
        block = np.vstack(parts)
        block = np.vstack([block, np.full((height - block.shape[0], width, 3), 255, np.uint8)])
        stacked.append(block)
        stacked.append(np.full((height, gap, 3), 255, np.uint8))
    return np.hstack(stacked[:-1])


def check_output_path(path: str | os.PathLike, name: str = "figure", lossless: bool = False) -> Path:
    """``path`` as a :class:`Path` if an image can be written there, else :class:`InputError` naming ``name``.

    The folder must exist, the path must not be a folder, and the ending must be an image format OpenCV writes
    (``lossless``: only PNG, BMP or TIFF, which keep label values exact; JPEG would invent new ones).
    """
    target = Path(path)
    suffixes = LOSSLESS_SUFFIXES if lossless else FIGURE_SUFFIXES
    if target.is_dir():
        raise InputError(f"{name}: expected a file name, got the folder {str(target)!r}")
    if not target.parent.is_dir():
        raise InputError(f"{name}: folder {str(target.parent)!r} does not exist")
    if target.suffix.lower() not in suffixes:
        kinds = "a lossless .png, .bmp or .tif" if lossless else "a .png, .jpg, .bmp or .tif"
        raise InputError(f"{name}: expected {kinds} file name, got {str(target)!r}")
    return target


def write_image_atomic(path: str | os.PathLike, image: np.ndarray, name: str = "figure",
                       lossless: bool = False) -> Path:
    """Write ``image`` to ``path`` all at once: encode, write a temporary file beside it, then rename.

    The file gets the permissions of any new file (``0666`` less the umask). Raises :class:`InputError` naming
    ``name`` as :func:`check_output_path` does, or when the file cannot be written.
    """
    target = check_output_path(path, name, lossless)
    ok, encoded = cv2.imencode(target.suffix.lower(), image)
    if not ok:
        raise InputError(f"{name}: OpenCV could not encode a {target.suffix} image")
    temporary = target.with_name(f".{target.name}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        # os.open with 0o666 lets the umask decide the mode (tempfile.mkstemp would force 0600).
        handle = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        with os.fdopen(handle, "wb") as stream:
            stream.write(encoded.tobytes())
        os.replace(temporary, target)
    except OSError as error:
        temporary.unlink(missing_ok=True)
        raise InputError(f"{name}: cannot write {str(target)!r}: {error.strerror or error}") from None
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    return target


def matches_figure(left: torch.Tensor, right: torch.Tensor, keypoints, pairs: list[list[int]],
                   inlier: list[bool] | None = None) -> np.ndarray:
    """Left and right images side by side, keypoints as circles (radius 2.5 × scale), matches as lines.

    Args:
        left, right: ``(H, W)`` float images in [0, 1].
        keypoints: :class:`~svs_torch.types.Keypoints` of a 2-image batch: row 0 left, row 1 right.
        pairs: ``[[i_left, i_right], ...]`` keypoint rows.
        inlier: optional flag per pair: inliers green, outliers red; otherwise every match is yellow.
    """
    h, w = left.shape
    gap = 8
    canvas = np.full((h, 2 * w + gap, 3), 255, np.uint8)
    canvas[:, :w] = gray_to_bgr(left)
    canvas[:, w + gap:] = gray_to_bgr(right)
    for side, offset in ((0, 0), (1, w + gap)):
        valid = keypoints.valid[side]
        for (x, y), s in zip(keypoints.xy[side][valid].tolist(), keypoints.scale[side][valid].tolist()):
            cv2.circle(canvas, (int(round(x)) + offset, int(round(y))), max(2, int(round(2.5 * s))),
                       (255, 160, 0), 1, cv2.LINE_AA)
    for n, (i, j) in enumerate(pairs):
        colour = (0, 220, 220) if inlier is None else ((0, 190, 0) if inlier[n] else (0, 0, 230))
        x0, y0 = keypoints.xy[0, i].tolist()
        x1, y1 = keypoints.xy[1, j].tolist()
        cv2.line(canvas, (int(round(x0)), int(round(y0))), (int(round(x1)) + w + gap, int(round(y1))), colour, 1,
                 cv2.LINE_AA)
    return titled_panel(canvas, f"{int(keypoints.valid[0].sum())} + {int(keypoints.valid[1].sum())} keypoints, "
                                f"{len(pairs)} matches")


def labels_image(seg: Segmentation, index: int, factors: tuple[float, float] = (1.0, 1.0)) -> np.ndarray:
    """uint8 label image of the kept regions of image ``index``: 0 background, 1..N largest first, resized
    (nearest) by ``factors`` (x, y) back to the input image's pixel grid."""
    labels = seg.labels[index, 0]
    out = torch.zeros_like(labels, dtype=torch.uint8)
    for rank, label in enumerate(seg.kept_labels[index].tolist(), start=1):
        if label > 0:
            out[labels == label] = rank
    image = out.cpu().numpy()
    h, w = image.shape
    size = (int(round(w * factors[0])), int(round(h * factors[1])))
    if size != (w, h):
        image = cv2.resize(image, size, interpolation=cv2.INTER_NEAREST)
    return image


def _depth_map(disparity: torch.Tensor, valid: torch.Tensor, focal_px: float, baseline_m: float,
               doffs_px: float) -> np.ndarray:
    """``Z = f·B / (d + doffs)`` in metres as a float array, NaN where not valid (blank in the figure)."""
    denom = disparity.detach().double().cpu() + doffs_px
    ok = valid.cpu() & (denom > 0)
    depth = torch.where(ok, focal_px * baseline_m / torch.where(ok, denom, torch.ones_like(denom)),
                        torch.full_like(denom, float("nan")))
    return depth.numpy()


def _pipeline_panels(batch, result, index: int) -> tuple[list[tuple[str, np.ndarray]], str]:
    """The depth maps to show (dense estimate, ground truth) with their titles, and a note on their pixels."""
    height, width = (int(v) for v in batch.image_hw[index].tolist())
    camera = (float(batch.focal_px[index]), float(batch.baseline_m[index]), float(batch.doffs_px[index]))
    maps = []
    note = ""
    if result.dense is not None:
        dense = _depth_map(result.dense.disparity_px[index, 0], result.dense.valid[index, 0], *camera)
        rectified = bool(result.rectified[index])
        note = " (rectified pixels)" if rectified else ""
        maps.append((f"dense depth estimate{note}", dense[:height, :width]))
    if batch.disparity_px is not None:
        truth = _depth_map(batch.disparity_px[index, 0], batch.disparity_valid[index, 0], *camera)
        maps.append(("ground-truth depth" + ("" if bool(batch.calibrated[index]) else " (nominal calibration)"),
                     truth[:height, :width]))
    return maps, note


def _render(figure) -> np.ndarray:
    """A matplotlib figure as a uint8 BGR array (Agg canvas: no display, no global pyplot state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(figure)
    canvas.draw()
    return cv2.cvtColor(np.asarray(canvas.buffer_rgba()), cv2.COLOR_RGBA2BGR)


def estimate_figure(batch, result, index: int) -> np.ndarray:
    """The pipeline on pair ``index`` as a uint8 BGR image: the kept objects with their median depths, the dense
    depth map with a colour bar (and the ground truth on the same scale when the batch has it), and the matches
    with a legend (RANSAC inliers green, outliers red)."""
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    from .pipeline import PipelineStatus

    seg = result.segmentation
    height, width = (int(v) for v in batch.image_hw[index].tolist())
    maps, _ = _pipeline_panels(batch, result, index)
    columns = 1 + len(maps)
    aspect = height / max(width, 1)
    panel_w = 4.2
    figure = Figure(figsize=(panel_w * columns, panel_w * aspect * 2 + 1.6), dpi=100, layout="constrained")
    grid = figure.add_gridspec(2, columns)

    objects_ax = figure.add_subplot(grid[0, 0])
    panel = _objects_panel(batch.left, seg.left, index)[:height, :width]
    objects_ax.imshow(cv2.cvtColor(panel, cv2.COLOR_BGR2RGB), interpolation="nearest")
    objects = result.depth.objects
    for slot, label in enumerate(seg.left.kept_labels[index].tolist()):
        if label < 0 or not bool(objects.valid[index, slot]):
            continue
        cx, cy = seg.left.regions.centroid_xy[index, label - 1].tolist()
        objects_ax.text(cx, cy, f"#{slot + 1}: {float(objects.depth_median_m[index, slot]):.2f} m", color="white",
                        fontsize=9, ha="center", va="center",
                        bbox={"facecolor": "black", "alpha": 0.75, "edgecolor": "none", "pad": 2})
    objects_ax.set_title("left: kept objects, median depth", fontsize=10)
    objects_ax.set_axis_off()

    finite = np.concatenate([m[np.isfinite(m)] for _, m in maps]) if maps else np.zeros(0)
    low, high = (np.percentile(finite, [2, 98]) if finite.size else (0.0, 1.0))
    high = max(high, low + 1e-3)
    image = None
    for column, (title, depth) in enumerate(maps, start=1):
        ax = figure.add_subplot(grid[0, column])
        image = ax.imshow(depth, cmap="turbo_r", vmin=low, vmax=high, interpolation="nearest")
        ax.set_title(f"{title}\n(blank: no depth)", fontsize=10)
        ax.set_axis_off()
    if image is not None:
        figure.colorbar(image, ax=[figure.axes[i] for i in range(1, columns)], label="depth (m)", shrink=0.9)

    matches_ax = figure.add_subplot(grid[1, :])
    left, right = seg.left.masked[index, 0, :height, :width], seg.right.masked[index, 0, :height, :width]
    gap = max(4, width // 50)
    canvas = np.ones((height, 2 * width + gap))
    canvas[:, :width], canvas[:, width + gap:] = left.detach().cpu().numpy(), right.detach().cpu().numpy()
    matches_ax.imshow(canvas, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
    kp_left, kp_right = result.features_left.keypoints, result.features_right.keypoints
    for keypoints, offset in ((kp_left, 0), (kp_right, width + gap)):
        xy = keypoints.xy[index][keypoints.valid[index]].detach().cpu().numpy()
        matches_ax.scatter(xy[:, 0] + offset, xy[:, 1], s=10, facecolors="none", edgecolors="#1f77b4",
                           linewidths=0.6)
    idx = result.matches.idx[index].tolist()
    pairs = [(i, j) for i, j in enumerate(idx) if j >= 0]
    inlier = [bool(result.fundamental.inliers[index, i]) for i, _ in pairs]
    segments = {True: [], False: []}
    for (i, j), is_inlier in zip(pairs, inlier):
        x0, y0 = kp_left.xy[index, i].tolist()
        x1, y1 = kp_right.xy[index, j].tolist()
        segments[is_inlier].append([(x0, y0), (x1 + width + gap, y1)])
    for is_inlier, colour in ((False, "#d62728"), (True, "#2ca02c")):
        if segments[is_inlier]:
            matches_ax.add_collection(LineCollection(segments[is_inlier], colors=colour, linewidths=0.8))
    num_in = sum(inlier)
    matches_ax.legend(handles=[
        Line2D([], [], color="#2ca02c", label=f"RANSAC inlier ({num_in})"),
        Line2D([], [], color="#d62728", label=f"outlier ({len(pairs) - num_in})"),
        Line2D([], [], marker="o", linestyle="none", markerfacecolor="none", markeredgecolor="#1f77b4",
               label="SURF keypoint")], loc="upper center", bbox_to_anchor=(0.5, -0.02), ncol=3, fontsize=9,
        frameon=False)
    matches_ax.set_title(f"matches on the segmented images: {int(result.num_keypoints[index, 0])} + "
                         f"{int(result.num_keypoints[index, 1])} keypoints, {len(pairs)} matches", fontsize=10)
    matches_ax.set_axis_off()

    status = PipelineStatus(int(result.status[index])).name
    nearest = result.depth.nearest
    summary = f"status {status}, {result.range_rule} rule"
    if bool(nearest.valid[index]):
        summary = (f"nearest obstacle {float(nearest.depth_m[index]):.2f} m (surface "
                   f"{float(nearest.surface_m[index]):.2f} m); " + summary)
    name = batch.names[index] if batch.names else ""
    figure.suptitle(f"{name + ': ' if name else ''}{summary}", fontsize=11, wrap=True)
    return _render(figure)
