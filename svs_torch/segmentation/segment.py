"""Object segmentation, the paper's pre-processing (Sec. 3.2, steps 1–6), batched over images.

1. grayscale (the loaders deliver it), 2. binary image by Otsu's threshold, 3. erosion then dilation,
4. connected regions, 5. region properties, 6. keep the N largest regions (paper: the two largest obstacles),
re-accumulate them into one mask and apply it to the grayscale image.

Nothing here is differentiable (threshold, morphology and labels are piecewise constant); the soft variant
in :mod:`svs_torch.segmentation.soft` carries gradients to the image and the threshold.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from typing import Literal

import torch

from ..core.checks import InputError, check_image, check_instance
from ..core.mask_reductions import any_along
from ..core.size_groups import run_by_size
from ..core.types import RegionProperties, Segmentation, SegmentationStatus, StereoBatch, StereoSegmentation
from .canny import canny_edges
from .components import MAX_KEEP, check_keep_arguments, connected_components_with_stats
from .ground_plane import GroundPlaneConfig
from .morphology import dilate, erode, open_binary, structuring_element
from .threshold import gray_levels_and_histogram, otsu_threshold_level, threshold_binary

__all__ = ["SegmentationConfig", "segment_images", "segment_stereo", "segment_stereo_otsu", "keep_largest_regions",
           "keep_regions", "kept_regions_mask"]


#: The widest structuring element, pixels: the opening pads the image by the element and passes over it once per
#: row and column of it, so a mistyped 99999 would need gigabytes; 255 is far beyond any obstacle's speckle.
MAX_KERNEL_SIZE = 255
#: A region under the least area kept because it is the nearest (``near_min_area_fraction``) must have at least this
#: share of its pixels counted (by the nearness segmenter's block matcher, where the right camera sees them): on the
#: tuning sets most small near regions that were wrong were rows filled in from their neighbours (the dense stage
#: measured 18–31 % of their pixels, the poles of experiments/thin_obstacles.md 86 % or more; read before it runs).
NEAR_MIN_COUNTED_SHARE = 0.5


@dataclass(frozen=True)
class SegmentationConfig:
    """Settings of the segmentation stage; defaults follow the paper where it states them.

    Attributes:
        kernel_size: side of the structuring element in pixels, used for the erosion and the dilation. The
            paper does not give its size; 5 (``strel('square', 5)``) removes the texture specks Otsu leaves on
            320×240 images of textured scenes while keeping obstacles of a few tens of pixels.
        kernel_shape: ``"square"`` (MATLAB ``strel('square', n)``), ``"cross"`` or ``"ellipse"``.
        num_keep: how many of the largest regions to keep (Sec. 3.2 step 6: the two largest).
        connectivity: 8 (``bwlabel``'s default, Sec. 3.2 step 4) or 4.
        foreground: ``"bright"`` keeps pixels above the threshold (``im2bw``); ``"dark"`` keeps those at or
            below it, for dark obstacles on a bright background.
        method: ``"otsu"`` (the paper's pre-processing: Otsu threshold, erosion, dilation) or ``"canny"`` (the
            paper's comparison variant: Canny edges, dilation, erosion; :mod:`svs_torch.segmentation.canny`).
        segmenter: which segmenter the pipeline runs: ``"otsu"`` (this module, by ``method``), ``"learned"``
            (the network shipped in ``svs_torch/segmentation/weights/``, :mod:`svs_torch.segmentation.learned`) or
            ``"learned:PATH"`` (weights written by ``experiments/train_segmentation.py``). The learned one
            replaces the threshold (``method`` and ``foreground`` then do nothing) and keeps the opening,
            ``connectivity`` and ``num_keep``. ``"nearness"`` (or ``"nearness:PATH"``): the disparity-based
            segmenter with its shipped (or PATH's) correction network, :mod:`svs_torch.segmentation.nearness`.
        keep: which ``num_keep`` regions are kept: ``"largest"`` by area (Sec. 3.2 step 6), ``"nearest"``
            by their median disparity (a small near obstacle before a large far wall), or ``"nearest_first"``: the
            nearest region, then the largest of the others (the nearest obstacle is never dropped, and the rest
            is the paper's rule). ``"nearest"`` needs the stereo segmenter (``"nearness"``); under the others, which
            measure no disparity, ``"nearest_first"`` keeps the largest regions.
        min_area_fraction: under ``keep="nearest"`` / ``"nearest_first"``, regions smaller than this share of the
            image (e.g. 0.003 = 230 px at 320×240) are not candidates: a speck of wrong disparity is not an
            obstacle.
        near_min_area_fraction: under the same rules, a region of at least this share but under
            ``min_area_fraction`` is still a candidate where it is nearer (a larger median disparity) than every
            region of ``min_area_fraction`` and measured on at least half its pixels (:data:`NEAR_MIN_COUNTED_SHARE`):
            a pole 3 cm wide 1.6 m ahead is 5 px wide at 320×240, and the nearness segmenter's median-filtered map
            leaves it a region of a few hundred pixels (experiments/thin_obstacles.md). A speck behind the near
            regions, or of filled rows, stays out. 0: off.
        min_measured_share: the nearness segmenter's pairs whose block matcher accepted less than this share of
            the left view are segmented by Otsu and the paper's two largest regions instead: views of two
            different scenes (a misconnected camera) leave up to about 10 % accepted by chance, and a disparity so
            sparse is not worth ranking by (experiments/nearness_fallback.md). 0: never.
        max_clipped_share: the nearness segmenter's regions with at least this share of their left-view pixels
            clipped at white are not candidates: a saturated patch has no texture, so no matcher measures it, and
            kept it stays unranged and takes a slot from a real obstacle (experiments/real_rig.md, "Clipped
            regions"). None: every region is a candidate.
        ground: the nearness segmenter's floor (:class:`~svs_torch.segmentation.ground_plane.GroundPlaneConfig`):
            the ground plane found in the pair's disparity is not an obstacle (a walker's floor, a street's road);
            None: not looked for (the other segmenters never look).
        camera_frames: the pairs are a camera's frames, JPEG with sensor noise (``svs-depth guide`` sets it, as
            does ``estimate --camera-frames``): the nearness segmenter matches those no wider than its working
            width (320 px) with its wider noise window at once, instead of a first pass whose matching residual
            decides (``NearnessNetConfig.noisy_min_residual_levels``). At 320×240 that gate widened every camera
            frame of the tuning sets at the board's digits 3–8, whose results are then the same, and 63 of 72 at
            digits 1–2, whose means moved by 0.00 to +0.05 points (``experiments/camera_frames_gate.md``); a
            frame saves the first pass, about a ninth of its time at B = 1. Wider pairs, averaged down before
            matching, keep the gate. Leave it off where pairs may be clean: the gate keeps them at the narrow
            window (the tuned split matched wider: 99.28 → 99.47 % per object, at half contrast 99.08 → 98.95).
    """

    kernel_size: int = 5  # pixels; not stated in the paper, see above; experiments/sweep_defaults.md
    kernel_shape: str = "square"  # Sec. 3.2 step 3
    num_keep: int = 2  # Sec. 3.2 step 6
    connectivity: int = 8  # Sec. 3.2 step 4, MATLAB default
    foreground: Literal["bright", "dark"] = "bright"  # Sec. 3.2 step 2, im2bw
    method: Literal["otsu", "canny"] = "otsu"  # Sec. 3.2; "canny" is the paper's comparison row
    segmenter: str = "otsu"  # Sec. 3.2; "learned" is the paper's next step (Sec. 5), issue 13; "nearness" issue 32
    keep: Literal["largest", "nearest", "nearest_first"] = "largest"  # Sec. 3.2 step 6
    min_area_fraction: float = 0.0  # of the image's area
    near_min_area_fraction: float = 0.0  # of the image's area
    min_measured_share: float = 0.0  # of the left view's pixels; the nearness segmenter only
    max_clipped_share: float | None = None  # of a region's pixels; the nearness segmenter only
    ground: GroundPlaneConfig | None = None
    camera_frames: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.kernel_size, int) or not 1 <= self.kernel_size <= MAX_KERNEL_SIZE:
            raise InputError(f"kernel_size: expected a positive integer up to {MAX_KERNEL_SIZE}, got "
                             f"{self.kernel_size!r}")
        if not isinstance(self.num_keep, int) or not 1 <= self.num_keep <= MAX_KEEP:
            raise InputError(f"num_keep: expected a positive integer up to {MAX_KEEP}, got {self.num_keep!r}")
        if self.connectivity not in (4, 8):
            raise InputError(f"connectivity: expected 4 or 8, got {self.connectivity!r}")
        if self.foreground not in ("bright", "dark"):
            raise InputError(f"foreground: expected 'bright' or 'dark', got {self.foreground!r}")
        if self.method not in ("otsu", "canny"):
            raise InputError(f"method: expected 'otsu' or 'canny', got {self.method!r}")
        kind, _, path = self.segmenter.partition(":") if isinstance(self.segmenter, str) else ("", "", "")
        if kind not in ("otsu", "learned", "nearness") or (kind == "otsu" and self.segmenter != "otsu") \
                or (":" in self.segmenter and not path):
            raise InputError(f"segmenter: expected otsu, nearness, nearness:PATH, learned or learned:PATH, got "
                             f"{self.segmenter!r}")
        if path and not os.path.isfile(os.path.expanduser(path)):
            # Checked here so that a sweep or a batch run with a wrong path stops before any work starts.
            raise InputError(f"segmenter: no weights file at {path!r}")
        if self.keep not in ("largest", "nearest", "nearest_first"):
            raise InputError(f"keep: expected 'largest', 'nearest' or 'nearest_first', got {self.keep!r}")
        if self.keep == "nearest" and kind != "nearness":
            raise InputError(f"keep: {self.keep!r} ranks regions by their disparity, which only the nearness segmenter "
                             f"measures; got segmenter {self.segmenter!r} (use segmenter='nearness')")
        for name in ("min_area_fraction", "near_min_area_fraction"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0 <= value < 1):
                raise InputError(f"{name}: expected a share of the image in [0, 1), got {value!r}")
        if not (isinstance(self.min_measured_share, (int, float)) and 0 <= self.min_measured_share <= 1):
            raise InputError(f"min_measured_share: expected a share of the image in [0, 1], got "
                             f"{self.min_measured_share!r}")
        share = self.max_clipped_share
        if share is not None and (isinstance(share, bool) or not isinstance(share, (int, float))
                                  or not 0 < share <= 1):
            raise InputError(f"max_clipped_share: expected None or a share of a region in (0, 1], got {share!r}")
        if self.ground is not None and not isinstance(self.ground, GroundPlaneConfig):
            raise InputError(f"ground: expected a GroundPlaneConfig or None, got {self.ground!r}")
        if not isinstance(self.camera_frames, bool):
            raise InputError(f"camera_frames: expected True or False, got {self.camera_frames!r}")
        structuring_element(self.kernel_shape, self.kernel_size)  # validates the shape name

    def with_floor(self, left_out: bool) -> SegmentationConfig:
        """These settings with the floor left out (``ground``: its own settings where given, else the defaults) or
        kept (None): ``--floor on`` / ``off``."""
        return replace(self, ground=(self.ground or GroundPlaneConfig()) if left_out else None)

    def for_guide(self, floor_left_out: bool = True) -> SegmentationConfig:
        """These settings as ``svs-depth guide`` runs them, which its benchmark times too: a camera's frames
        (``camera_frames``) and, unless ``floor_left_out`` is False (``--floor off``), the floor left out."""
        return replace(self.with_floor(floor_left_out), camera_frames=True)


def keep_largest_regions(labels: torch.Tensor, regions: RegionProperties,
                         num_keep: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Labels of the ``num_keep`` largest regions and the mask of their union.

    Args:
        labels: ``(B, 1, H, W)`` int64 label images.
        regions: their :class:`RegionProperties` (L slots).
        num_keep: N, how many regions to keep per image.

    Returns:
        ``kept_labels`` ``(B, N)`` int64, largest area first, ties by label (raster) order, −1 where an image
        has fewer than N regions; ``kept_mask`` ``(B, 1, H, W)`` bool. Not differentiable.
    """
    check_keep_arguments(labels, regions, num_keep)
    return _keep_largest(labels, regions, num_keep)


def _keep_largest(labels: torch.Tensor, regions: RegionProperties, num_keep: int) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`keep_largest_regions` of arguments already checked."""
    area = torch.where(regions.valid, regions.area_px, torch.full_like(regions.area_px, -1))
    order = torch.sort(area, dim=1, descending=True, stable=True).indices  # (B, L)
    return _keep_in_order(labels, regions, order, num_keep)


def keep_regions(labels: torch.Tensor, regions: RegionProperties, num_keep: int, keep: str = "largest",
                 min_area_px: float = 0.0, nearness: torch.Tensor | None = None,
                 candidate_area_px: torch.Tensor | None = None, near_min_area_px: float = 0.0
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`keep_largest_regions`, or under ``keep="nearest"`` the ``num_keep`` regions of at least
    ``min_area_px`` pixels with the largest ``nearness`` ``(B, L)`` (e.g. median disparity; ties by area, then
    label), nearest first; under ``"nearest_first"`` the nearest such region, then the largest of the other such
    regions (a pair with no such candidate: the largest regions, as the paper, but of at least ``min_area_px`` where
    any region is). Under both
    nearness rules a region smaller than ``min_area_px`` is never kept beside one that is not: a speck left by
    the opening next to a near region covering most of the view would otherwise be ranged as an obstacle, from
    a handful of pixels. ``candidate_area_px`` ``(B, L)``: the area held to ``min_area_px`` and ranking the
    regions after the nearest (default: ``regions.area_px``; e.g. the pixels the other camera sees). A region of
    at least ``near_min_area_px`` (below ``min_area_px``) is a candidate too where it is nearer than every region
    of ``min_area_px`` and that count holds at least :data:`NEAR_MIN_COUNTED_SHARE` of its pixels, so ranked
    first. Not differentiable."""
    check_keep_arguments(labels, regions, num_keep, keep, nearness, min_area_px, candidate_area_px,
                         near_min_area_px)
    if keep == "largest":
        return _keep_largest(labels, regions, num_keep)  # (checked above: the labels' pass not made twice)
    if nearness is None:
        raise InputError("nearness: keep='nearest' needs a nearness per region, got none")
    area = regions.area_px if candidate_area_px is None else candidate_area_px.to(regions.area_px.dtype)
    candidate = regions.valid & (area >= min_area_px)
    if 0 < near_min_area_px < min_area_px and candidate.shape[1]:  # no region at all: nothing to compare
        small = regions.valid & ~candidate & (area >= near_min_area_px)
        candidate = candidate | _small_near_regions(small & (area >= NEAR_MIN_COUNTED_SHARE * regions.area_px),
                                                    candidate, nearness)
    order_area = torch.sort(torch.where(candidate, area, -1), dim=1, descending=True, stable=True).indices
    ranked = torch.gather(torch.where(candidate, nearness.to(torch.float64), -torch.inf), 1, order_area)
    order = torch.gather(order_area, 1, torch.sort(ranked, dim=1, descending=True, stable=True).indices)
    filtered = RegionProperties(area_px=regions.area_px, bbox_xyxy=regions.bbox_xyxy,
                                centroid_xy=regions.centroid_xy, valid=candidate)
    if keep == "nearest":
        return _keep_in_order(labels, filtered, order, num_keep)
    # nearest_first: the nearest candidate, then the other candidates by area (order_area without it).
    if not order.shape[1]:
        return _keep_in_order(labels, regions, order_area, num_keep)
    first = order[:, :1]
    moved = (order_area == first).to(torch.int8)  # the first, moved to the end (stable)
    rest = torch.gather(order_area, 1, torch.sort(moved, dim=1, stable=True).indices)
    has_candidate = candidate.any(1, keepdim=True)
    kept, kept_mask = _keep_in_order(labels, filtered, torch.cat([first, rest[:, :-1]], 1), num_keep)
    if bool(has_candidate.all()):
        return kept, kept_mask
    # The largest regions, as the paper, but a speck under min_area_px never beside a region of it (as above): on
    # a walker's floor, 0.8 m below the camera, a 32-pixel scrap at the image's foot was kept beside a 652-pixel
    # region in the band the right camera does not see, ranged at 1.15 m, and guide said "Stop" of it (an audit).
    big = regions.valid & (regions.area_px >= min_area_px)
    fallback = replace(regions, valid=torch.where(big.any(1, keepdim=True), big, regions.valid))
    largest, largest_mask = _keep_largest(labels, fallback, num_keep)
    return (torch.where(has_candidate, kept, largest),
            torch.where(has_candidate.view(-1, *([1] * (labels.dim() - 1))), kept_mask, largest_mask))


def _small_near_regions(small: torch.Tensor, candidate: torch.Tensor, nearness: torch.Tensor) -> torch.Tensor:
    """``(B, L)``: the ``small`` regions nearer (a larger ``nearness``) than every ``candidate`` region. A thin near
    obstacle, not a speck beside the regions already ranked: in a pair with no candidate it stays out too."""
    nearness = nearness.to(torch.float64)
    nearest_candidate = torch.where(candidate, nearness, -torch.inf).amax(1, keepdim=True)
    return small & (nearness > nearest_candidate) & candidate.any(1, keepdim=True)


def _keep_in_order(labels: torch.Tensor, regions: RegionProperties, order: torch.Tensor, num_keep: int
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """The first ``num_keep`` valid region slots of ``order`` ``(B, L)`` as labels ``(B, N)`` (−1 for none) and
    the mask of their union."""
    b, slots = regions.area_px.shape
    order = order[:, :num_keep]
    kept_valid = torch.gather(regions.valid, 1, order)
    kept = torch.where(kept_valid, order + 1, torch.full_like(order, -1))
    if kept.shape[1] < num_keep:
        kept = torch.cat([kept, kept.new_full((b, num_keep - kept.shape[1]), -1)], dim=1)
    return kept, kept_regions_mask(labels, kept, slots)


def kept_regions_mask(labels: torch.Tensor, kept_labels: torch.Tensor, num_slots: int) -> torch.Tensor:
    """The union of the regions ``kept_labels`` ``(B, N)`` (−1: none) of ``labels`` ``(B, 1, H, W)``, whose labels
    are at most ``num_slots``, as a bool mask of ``labels``' shape. Not differentiable (a bool mask)."""
    # Lookup table label -> kept, then one gather over the label image.
    table = torch.zeros(kept_labels.shape[0], num_slots + 1, dtype=torch.bool, device=labels.device)
    table.scatter_(1, kept_labels.clamp(min=0), kept_labels >= 0)
    table[:, 0] = False
    return torch.gather(table, 1, labels.flatten(1)).view_as(labels)


def without_kept_regions(drop: torch.Tensor, kept_labels: torch.Tensor, kept_mask: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """``kept_labels`` ``(B, N)`` and ``kept_mask`` ``(B, 1, H, W)`` with nothing kept in the images ``drop``
    ``(B,)``: a one-level image (``UNIFORM_IMAGE``) is wholly foreground, as Otsu leaves it, but holds no
    obstacle to report."""
    return (torch.where(drop.view(-1, 1), torch.full_like(kept_labels, -1), kept_labels),
            kept_mask & ~drop.view(-1, 1, 1, 1))


def _status(levels_uniform: torch.Tensor, opened: torch.Tensor) -> torch.Tensor:
    """Per-image :class:`SegmentationStatus` from a uniform-image flag ``(B,)`` and the opened mask."""
    any_fg = any_along(opened.flatten(1), dim=1)
    status = torch.where(any_fg, SegmentationStatus.OK, SegmentationStatus.NO_FOREGROUND).to(torch.int64)
    return torch.where(levels_uniform, SegmentationStatus.UNIFORM_IMAGE, status)


def segment_images(image: torch.Tensor, config: SegmentationConfig = SegmentationConfig()) -> Segmentation:
    """Segment the obstacles of a batch of grayscale images (paper Sec. 3.2, steps 2–6).

    Args:
        image: ``(B, 1, H, W)`` float in [0, 1].
        config: :class:`SegmentationConfig`.

    Returns:
        :class:`Segmentation`. Each image is independent: a blank, saturated or textureless image gets an
        empty or full mask and a non-OK ``status`` instead of failing the batch. Each step equals OpenCV on
        the uint8 image: ``threshold(THRESH_OTSU)``, ``erode``, ``dilate``, ``connectedComponentsWithStats``.
        Not differentiable (``masked`` carries the image's gradient inside the kept mask only).
    """
    if check_image(image, "image")["B"] == 0:  # a reshape deep in the histogram said it before
        raise InputError("image: expected at least one image, got an empty batch")
    check_instance(config, "config", SegmentationConfig)
    if config.segmenter != "otsu":  # it ran Otsu in silence
        raise InputError(f"config: segment_images runs the Otsu segmenter on single images; segmenter "
                         f"{config.segmenter!r} segments both views of a pair: use segment_stereo")
    levels, histogram = gray_levels_and_histogram(image)
    level = otsu_threshold_level(histogram)
    threshold = level.to(image.dtype) / 255
    element = structuring_element(config.kernel_shape, config.kernel_size, device=image.device)
    if config.method == "canny":
        # Edges closed into blobs: dilation then erosion (Balakrishnan et al.'s pre-processing).
        binary = canny_edges(image)
        opened = erode(dilate(binary, element), element)
    else:
        binary = threshold_binary(levels, level)
        if config.foreground == "dark":
            binary = ~binary
        opened = open_binary(binary, element)
    labels, num_regions, regions = connected_components_with_stats(opened, config.connectivity, image.dtype)
    kept_labels, kept_mask = keep_largest_regions(labels, regions, config.num_keep)
    uniform = (histogram > 0).sum(dim=1) == 1  # one gray level: Otsu has no split
    kept_labels, kept_mask = without_kept_regions(uniform, kept_labels, kept_mask)
    return Segmentation(
        threshold=threshold,
        threshold_level=level,
        binary=binary,
        opened=opened,
        labels=labels,
        num_regions=num_regions,
        regions=regions,
        kept_labels=kept_labels,
        kept_mask=kept_mask,
        # The mask as 0/1 in the image's dtype first: a float × bool product casts every element on the fly
        # (measured 3.9 ms against 1.3 for 16 images of 320×240; the same values).
        masked=image * kept_mask.to(image.dtype),
        status=_status(uniform, opened),
    )


def segment_stereo(batch: StereoBatch, config: SegmentationConfig = SegmentationConfig()) -> StereoSegmentation:
    """Segment both images of every pair by ``config.segmenter``: Otsu (left and right as one batch of 2B
    images, :func:`segment_images`), or the learned / nearness segmenter as the pipeline runs it
    (:func:`svs_torch.segmentation.stereo.segment_pair`, with the shipped or named weights). Each pair is segmented
    on its own ``image_hw`` pixels (:mod:`svs_torch.core.size_groups`): a padded pair's border never enters its
    threshold's histogram or a region.

    Not differentiable but for ``masked`` (each view times its hard mask), which carries the image's gradient inside
    the kept mask only; :mod:`svs_torch.segmentation.soft` is the differentiable variant.

    Returns:
        :class:`StereoSegmentation`; its pair ``status`` is the left image's where not OK, else the right's.
    """
    check_instance(batch, "batch", StereoBatch)
    check_instance(config, "config", SegmentationConfig)
    if config.segmenter != "otsu":  # it ran Otsu in silence
        from .stereo import segment_pair  # which builds on this module

        return segment_pair(batch, config)
    return run_by_size(batch, lambda group: segment_stereo_otsu(group, config))


def segment_stereo_otsu(batch: StereoBatch, config: SegmentationConfig) -> StereoSegmentation:
    """:func:`segment_stereo`'s Otsu branch on a batch whose pairs fill its tensors (one size group, as
    :func:`svs_torch.segmentation.stereo.segment_same_size` gets). Not differentiable (``masked`` carries the
    image's gradient inside the kept mask only)."""
    b = batch.batch_size
    both = segment_images(torch.cat([batch.left, batch.right], dim=0), config)
    left, right = _split(both, b)
    status = torch.where(left.status != SegmentationStatus.OK, left.status, right.status)
    return StereoSegmentation(left=left, right=right, status=status)


def _split(seg: Segmentation, b: int) -> tuple[Segmentation, Segmentation]:
    """Split a segmentation of 2B images into the first B and the last B (regions trimmed to their own L)."""
    def part(sl: slice) -> Segmentation:
        regions = seg.regions
        slots = int(seg.num_regions[sl].max()) if seg.num_regions[sl].numel() else 0
        sub = RegionProperties(
            area_px=regions.area_px[sl, :slots],
            bbox_xyxy=regions.bbox_xyxy[sl, :slots],
            centroid_xy=regions.centroid_xy[sl, :slots],
            valid=regions.valid[sl, :slots],
        )
        fields = {name: getattr(seg, name)[sl] for name in (
            "threshold", "threshold_level", "binary", "opened", "labels", "num_regions",
            "kept_labels", "kept_mask", "masked", "status")}
        return Segmentation(regions=sub, **fields)

    return part(slice(0, b)), part(slice(b, 2 * b))
