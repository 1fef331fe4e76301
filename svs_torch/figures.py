"""Figures for the command line, drawn with OpenCV (no plotting dependency): panels of images and masks.

Figures are for people; nothing here feeds back into the pipeline.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import cv2
import numpy as np
import torch

from .checks import InputError
from .types import Segmentation

__all__ = [
    "PALETTE_BGR", "compose_grid", "estimate_figure", "gray_to_bgr", "labels_image", "matches_figure",
    "segmentation_panels", "titled_panel", "write_image_atomic",
]

#: Colours of kept objects, largest first (BGR).
PALETTE_BGR = [(0, 165, 255), (255, 128, 0), (0, 200, 0), (200, 0, 200), (0, 220, 220), (128, 0, 255)]


def gray_to_bgr(gray: torch.Tensor) -> np.ndarray:
    """``(H, W)`` float in [0, 1] → uint8 BGR image."""
    u8 = (gray.detach().cpu().clamp(0, 1) * 255).round().to(torch.uint8).numpy()
    return cv2.cvtColor(u8, cv2.COLOR_GRAY2BGR)


def titled_panel(panel: np.ndarray, title: str) -> np.ndarray:
    """Put a title strip above a panel."""
    strip = np.full((22, panel.shape[1], 3), 255, np.uint8)
    cv2.putText(strip, title, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([strip, panel])


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
        cv2.putText(panel, f"#{rank + 1} {area}px", (x0 + 2, max(y0 + 12, 12)), cv2.FONT_HERSHEY_SIMPLEX,
                    0.4, tuple(int(c) for c in colour), 1, cv2.LINE_AA)
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


def write_image_atomic(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Write ``image`` to ``path`` all at once: encode to a temporary file beside it, then rename.

    Raises :class:`InputError` naming the path if its folder is missing or the extension is not an image format.
    """
    target = Path(path)
    if not target.parent.exists():
        raise InputError(f"out: folder {str(target.parent)!r} does not exist")
    suffix = target.suffix.lower()
    if suffix not in (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"):
        raise InputError(f"out: expected a .png, .jpg, .bmp or .tif file name, got {str(target)!r}")
    ok, encoded = cv2.imencode(suffix, image)
    if not ok:
        raise InputError(f"out: OpenCV could not encode a {suffix} image")
    handle, temporary = tempfile.mkstemp(suffix=suffix, dir=target.parent)
    try:
        with os.fdopen(handle, "wb") as stream:
            stream.write(encoded.tobytes())
        os.replace(temporary, target)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
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


def estimate_figure(batch, result, index: int) -> np.ndarray:
    """The pipeline on one pair: kept objects with their depths, and the matches (inliers green, outliers red)."""
    seg = result.segmentation
    objects = result.depth.objects
    left_panel = _objects_panel(batch.left, seg.left, index)
    for slot, label in enumerate(seg.left.kept_labels[index].tolist()):
        if label < 0 or not bool(objects.valid[index, slot]):
            continue
        cx, cy = seg.left.regions.centroid_xy[index, label - 1].tolist()
        text = f"{float(objects.depth_median_m[index, slot]):.2f} m"
        cv2.putText(left_panel, text, (int(cx) - 20, int(cy)), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 2,
                    cv2.LINE_AA)
        cv2.putText(left_panel, text, (int(cx) - 20, int(cy)), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1,
                    cv2.LINE_AA)
    kp_left, kp_right = result.features_left.keypoints, result.features_right.keypoints
    both = type(kp_left)(*(torch.stack([getattr(kp_left, f)[index], getattr(kp_right, f)[index]])
                           for f in ("xy", "scale", "score", "laplacian_sign", "orientation", "valid")))
    idx = result.matches.idx[index].tolist()
    pairs = [[i, j] for i, j in enumerate(idx) if j >= 0]
    inlier = [bool(result.fundamental.inliers[index, i]) for i, _ in pairs]
    matches = matches_figure(seg.left.masked[index, 0], seg.right.masked[index, 0], both, pairs, inlier)
    nearest = result.depth.nearest
    title = "no obstacle ranged"
    if bool(nearest.valid[index]):
        title = f"nearest obstacle {float(nearest.depth_m[index]):.2f} m"
    return compose_grid([[titled_panel(left_panel, f"left: kept objects, median depth; {title}")], [matches]])
