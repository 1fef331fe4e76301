"""Figures for the command line: panels of images and masks drawn with OpenCV, label images, and writing an
image file (the matplotlib figures are in :mod:`svs_torch.plotting.plots`).

Figures are for people; nothing here feeds back into the pipeline. Files are written whole (a temporary file
beside the target, then a rename, :mod:`svs_torch.core.files`) with the permissions the umask gives a new file.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import torch

from ..core.checks import InputError
from ..core.files import atomic_output, check_output_file, write_bytes_atomic, write_errors_named
from ..core.types import Segmentation

__all__ = [
    "FIGURE_SUFFIXES", "LOSSLESS_SUFFIXES", "PALETTE_BGR", "binary_title", "check_output_path", "compose_grid",
    "floor_summary", "gray_to_bgr", "image_written_after", "labels_image", "objects_panel", "plain_texts", "render",
    "segmentation_panels", "titled_panel", "write_image_atomic",
]

#: Colours of kept objects, largest first (BGR).
PALETTE_BGR = [(0, 165, 255), (255, 128, 0), (0, 200, 0), (200, 0, 200), (0, 220, 220), (128, 0, 255),
               (255, 255, 0), (0, 0, 200), (160, 60, 0), (0, 128, 128)]  # 10: --keep 8 repeated colours at 6
#: File name endings a figure can be written as, and those that keep every value exactly (label images).
FIGURE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
LOSSLESS_SUFFIXES = (".png", ".bmp", ".tif", ".tiff")
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def plain_texts(figure) -> None:
    """Every text of the matplotlib ``figure`` drawn as written, not read as mathtext: a file or folder name holding
    '$' (l$x_1$.png) was drawn as a formula, and one that is no formula (l$bad\\frac$.png) ended estimate --figure
    in "internal error: ValueError" after the report (an audit)."""
    from matplotlib.text import Text

    for text in figure.findobj(Text):
        text.set_parse_math(False)


def render(figure) -> np.ndarray:
    """A matplotlib figure as a uint8 BGR array, its texts as written (:func:`plain_texts`)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    plain_texts(figure)
    canvas = FigureCanvasAgg(figure)
    canvas.draw()
    return cv2.cvtColor(np.asarray(canvas.buffer_rgba()), cv2.COLOR_RGBA2BGR)


def gray_to_bgr(gray: torch.Tensor) -> np.ndarray:
    """``(H, W)`` float in [0, 1] → uint8 BGR image."""
    u8 = (gray.detach().cpu().clamp(0, 1) * 255).round().to(torch.uint8).numpy()
    return cv2.cvtColor(u8, cv2.COLOR_GRAY2BGR)


def _wrap(text: str, width_px: int, scale: float) -> list[str]:
    """Greedy word wrap of ``text`` so that each line is at most ``width_px`` wide at font ``scale``; a word wider
    than that is broken (a 24 px panel clipped 'image' to 'imag': an audit's find), down to one character a line."""
    def fits(line: str) -> bool:
        return cv2.getTextSize(line, _FONT, scale, 1)[0][0] <= width_px

    lines: list[str] = []
    for word in text.split():
        if lines and fits(f"{lines[-1]} {word}"):
            lines[-1] = f"{lines[-1]} {word}"
            continue
        while len(word) > 1 and not fits(word):
            cut = max([k for k in range(1, len(word)) if fits(word[:k])], default=1)
            lines.append(word[:cut])
            word = word[cut:]
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
    """White text on a black box, led by a swatch of the object's ``colour``, kept inside the panel: readable on
    any texture and on the object's own tint (coloured text on a tint of its own colour is not)."""
    thickness = max(1, round(scale / 0.6))  # strokes that grow with the size (one pixel up to 0.89)
    (w, h), base = cv2.getTextSize(text, _FONT, scale, thickness)
    total = h + 3 + w  # swatch, space, text
    x = int(min(max(origin[0], 1), max(panel.shape[1] - total - 2, 1)))
    y = int(min(max(origin[1], h + 2), max(panel.shape[0] - base - 1, h + 2)))
    cv2.rectangle(panel, (x - 1, y - h - 2), (x + total + 1, y + base), (0, 0, 0), cv2.FILLED)
    cv2.rectangle(panel, (x, y - h), (x + h - 1, y - 1), colour, cv2.FILLED)
    cv2.putText(panel, text, (x + h + 3, y), _FONT, scale, (255, 255, 255), thickness, cv2.LINE_AA)


#: Rows of the objects panel the area label (``#1 928px``, :func:`~svs_torch.plotting.figures.objects_panel`)
#: takes at the top of each object's box, image pixels, in an image up to 320 px wide (times
#: :func:`panel_scale` in a wider one).
AREA_LABEL_ROWS = 16


#: The padding of a depth label's box (``plots.LABEL_BOX``), points.
LABEL_PAD_POINTS = 2


def panel_scale(width_px: int) -> float:
    """How much larger the objects panel draws its labels and box lines in an image ``width_px`` wide: 1 up to
    320 px (the SVS's width), in proportion beyond, so that a figure, drawn at one size whatever the image's, shows
    them alike (at 1282 px a 1-pixel box and a 0.4 label were a hairline and an unreadable speck)."""
    return max(1.0, width_px / 320)


def depth_label_y(centroid_y: float, box_top: float, lines: int, size_hw: tuple[int, int], width_in: float) -> float:
    """The row of an object's depth label (``lines`` lines of 9 pt, centred on it): its centroid's, or lower
    where the label would cover the area label at the top of its box (a short region, e.g. a far window whose
    centroid lies near its top), kept inside the image. ``width_in``: the panel's width in inches at 100 dpi,
    ``size_hw`` the image's."""
    height, width = size_hw
    points_to_px = width / (72 * width_in)  # image pixels per point on the drawn panel (72 points an inch)
    half = (lines * 9 * 1.25 + 2 * LABEL_PAD_POINTS) * points_to_px / 2
    y = max(centroid_y, box_top + AREA_LABEL_ROWS * panel_scale(width) + half)
    return min(y, max(height - half, 0.0))


def place_depth_labels(labels: list[tuple[float, float, float, str]], size_hw: tuple[int, int],
                       width_in: float) -> list[tuple[float, float]]:
    """Centres of the objects' depth labels, ``labels`` ``(centroid x, centroid y, box top, text)`` in drawing
    order (9 pt, ``size_hw`` and ``width_in`` as :func:`depth_label_y`'s): each at its :func:`depth_label_y` row and
    its centroid's column, moved inside the panel sideways, and to the nearest row just below or above a label
    placed before it where it covers none (else left where it was). An audit's finds: PianoL's second label lay
    over the first's, eval3 Playroom's eight over each other, and a label at the left edge was cut ('e 2.60 m').
    The boxes' sizes are estimated (0.65 em a character), with a 4 pt margin."""
    height, width = size_hw
    points_to_px = width / (72 * width_in)
    placed: list[tuple[float, float, float, float]] = []  # x0, y0, x1, y1 of each label box, image pixels
    centres = []
    for cx, cy, top, text in labels:
        rows = text.split("\n")
        half_w = (max(len(row) for row in rows) * 9 * 0.65 + 2 * LABEL_PAD_POINTS + 4) * points_to_px / 2
        half_h = (len(rows) * 9 * 1.25 + 2 * LABEL_PAD_POINTS + 4) * points_to_px / 2
        x = min(max(cx, half_w), max(width - half_w, half_w))
        first = depth_label_y(cy, top, len(rows), size_hw, width_in)
        rows_tried = [first] + sorted((v for b in placed for v in (b[3] + half_h, b[1] - half_h)
                                       if half_h <= v <= height - half_h), key=lambda v: abs(v - first))
        y = next((v for v in rows_tried if not any(x - half_w < b[2] and b[0] < x + half_w and v - half_h < b[3]
                                                     and b[1] < v + half_h for b in placed)), first)
        placed.append((x - half_w, y - half_h, x + half_w, y + half_h))
        centres.append((x, y))
    return centres


def floor_summary(result, index: int) -> list[str]:
    """The title's part about the floor where the floor rule found it (``--floor on``; ``guide`` records): the
    camera's pose over it and the nearest obstacle's distance ahead along it, what ``guide`` says
    (:mod:`svs_torch.depth.floor_distance`), which the depths drawn (along the camera's axis) are not."""
    floor = getattr(result, "floor", None)
    if floor is None or not bool(floor.floor.found[index]) or not bool(floor.nearest.valid[index]):
        return []
    from ..depth.floor_distance import describe_floor

    return [describe_floor(float(floor.floor.camera_height_m[index]), float(floor.floor.pitch_deg[index]),
                           f"#{int(floor.nearest.slot[index]) + 1}", float(floor.nearest.depth_m[index]),
                           float(floor.nearest.surface_m[index]))]


def objects_panel(image: torch.Tensor, seg: Segmentation, index: int, area_scale: float = 1.0) -> np.ndarray:
    """The grayscale image dimmed outside the kept objects, each object tinted, boxed and numbered with its area in
    input pixels: ``area_scale`` input pixels a pixel of ``image`` (a pair reduced by ``--size``: the report's
    factors' product; an audit found the label at the working size beside the report's input count)."""
    gray = image[index, 0]
    panel = gray_to_bgr(gray * 0.35)
    base = gray_to_bgr(gray)
    labels = seg.labels[index, 0].cpu().numpy()
    scale = panel_scale(panel.shape[1])
    for rank, label in enumerate(seg.kept_labels[index].tolist()):
        if label < 0:
            continue
        colour = np.array(PALETTE_BGR[rank % len(PALETTE_BGR)], np.float32)
        region = labels == label
        panel[region] = (0.6 * base[region] + 0.4 * colour).astype(np.uint8)
        x0, y0, x1, y1 = seg.regions.bbox_xyxy[index, label - 1].tolist()
        area = int(round(int(seg.regions.area_px[index, label - 1]) * area_scale))
        cv2.rectangle(panel, (x0, y0), (x1 - 1, y1 - 1), tuple(int(c) for c in colour), round(scale))
        text = f"#{rank + 1} {area}px"
        # Not where it would not fit across the view (an audit: in a 64x48 view the enlarged label was cut off and
        # hid a third of it): its box and colour only.
        (text_w, text_h), _ = cv2.getTextSize(text, _FONT, 0.4 * scale, 1)
        if text_h + 3 + text_w + 2 <= 0.9 * panel.shape[1]:  # swatch, space, text, border (as _label draws it)
            _label(panel, text, (x0 + round(2 * scale), y0 + round(12 * scale)), tuple(int(c) for c in colour),
                   0.4 * scale)
    return panel


def binary_title(seg: Segmentation, index: int, segmenter: str = "otsu", method: str = "otsu") -> str:
    """What made the binary mask, for its panel: ``binary (Otsu 128) + opening``, ``binary (nearness segmenter,
    p > 0.50) + opening`` (or the learned one's) or ``Canny edges + closing`` (``segmenter`` and ``method`` as in
    :class:`~svs_torch.segmentation.SegmentationConfig`)."""
    threshold = int(seg.threshold_level[index])
    if segmenter != "otsu":  # a network's ("nearness", "learned", either ":PATH"): its probability threshold, 0-255
        name = segmenter.split(":", 1)[0]
        return f"binary ({name} segmenter, p > {threshold / 255:.2f}) + opening"
    return "Canny edges + closing" if method == "canny" else f"binary (Otsu {threshold}) + opening"


def segmentation_panels(image: torch.Tensor, seg: Segmentation, index: int, side: str, segmenter: str = "otsu",
                        method: str = "otsu", min_width_px: int = 0) -> list[np.ndarray]:
    """Three titled panels of one image: the input, the opened binary mask (titled by what made it:
    :func:`binary_title`), the kept objects. A panel narrower than ``min_width_px`` is first enlarged by a whole
    factor, pixels kept square (nearest neighbour), for a caller that scales the row up to a wide figure after:
    its title was wrapped a letter a line at the image's width, and ``demo --size 16x12``'s figure was 10 473 px
    tall (an audit)."""
    mask = seg.opened[index, 0].to(image.dtype)
    num_kept = int((seg.kept_labels[index] >= 0).sum())
    made = binary_title(seg, index, segmenter, method)
    if side == "right" and segmenter.split(":", 1)[0] == "nearness":
        # The nearness segmenter thresholds the left view only; the right's mask is the left's kept regions moved
        # by their disparity (an audit: one region under a "binary ... + opening" title beside the left's four).
        made = "mask: the left's regions moved by disparity"  # one line, as its neighbours' titles

    def titled(panel: np.ndarray, title: str) -> np.ndarray:
        factor = -(-min_width_px // panel.shape[1])
        if factor > 1:
            panel = cv2.resize(panel, None, fx=factor, fy=factor, interpolation=cv2.INTER_NEAREST)
        return titled_panel(panel, title)

    return [
        titled(gray_to_bgr(image[index, 0]), f"{side} image"),
        titled(gray_to_bgr(mask), f"{side} {made}"),
        titled(objects_panel(image, seg, index), f"{side}: {num_kept} kept"),
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
    if lossless:
        return check_output_file(path, name, LOSSLESS_SUFFIXES, "a lossless .png, .bmp or .tif")
    return check_output_file(path, name, FIGURE_SUFFIXES, "a .png, .jpg, .bmp or .tif")


def write_image_atomic(path: str | os.PathLike, image: np.ndarray, name: str = "figure",
                       lossless: bool = False) -> Path:
    """Write ``image`` to ``path`` all at once (:func:`svs_torch.core.files.atomic_output`: a temporary file beside
    it, then a rename), with the permissions of any new file (``0o666`` less the umask).

    Raises :class:`InputError` naming ``name`` as :func:`check_output_path` does (a usage error: exit 2), and
    :class:`OSError` naming ``name`` and the file when it cannot be written (a full disk, an I/O error: the
    command's failure, exit 1, as ``--disparity-out``'s).
    """
    target = check_output_path(path, name, lossless)
    with write_errors_named(name, target):
        write_bytes_atomic(target, _encoded(target, image, name))
    return target


def _encoded(target: Path, image: np.ndarray, name: str) -> bytes:
    ok, encoded = cv2.imencode(target.suffix.lower(), image)
    if not ok:
        raise InputError(f"{name}: OpenCV could not encode a {target.suffix} image")
    return encoded.tobytes()


class _Abandoned(Exception):
    """The block of :func:`image_written_after` raised: its image is dropped and that error raised as it was."""


@contextlib.contextmanager
def image_written_after(path: str | os.PathLike, image: np.ndarray, name: str = "figure",
                        lossless: bool = False) -> Iterator[Path]:
    """:func:`write_image_atomic` in two steps, for a figure that must not outlive another file: the image is
    written in full before the ``with`` block runs (a full disk refuses it there, the block never runs), but
    takes the name ``path`` only when the block ends normally. A block that raises leaves ``path`` as it was,
    an earlier figure there kept (``calibrate``: a calibration that could not be written removed the figure it
    had just replaced). Errors as :func:`write_image_atomic`'s; the block's own are raised unchanged."""
    target = check_output_path(path, name, lossless)
    data, failure = _encoded(target, image, name), None
    try:
        with write_errors_named(name, target), atomic_output(target) as stream:
            stream.write(data)
            stream.flush()  # the image's own write errors are raised here, named, before the block runs
            try:
                yield target
            except BaseException as error:  # not the figure's: kept out of write_errors_named's naming
                failure = error
                raise _Abandoned from None
    except _Abandoned:
        raise failure  # noqa: B904 (the block's exception, its traceback kept)


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
