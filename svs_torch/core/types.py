"""Containers passed between pipeline stages.

Shape letters: B pairs (or images), H and W pixels, L region slots, N kept regions, K keypoints,
D descriptor length, M hypotheses.
All containers are frozen dataclasses of tensors with a leading batch dimension B; a pair's row never
depends on another pair's.
"""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass

import torch

from .checks import (InputError, check_dtype, check_finite, check_finite_where, check_image, check_same_shape,
                     check_shape, check_stereo_views)
from .kernels.checks import check_image_hw

__all__ = ["FundamentalResult", "FundamentalStatus", "Keypoints", "Matches", "StereoBatch", "RegionProperties",
           "Segmentation", "StereoSegmentation", "SegmentationStatus"]


@dataclass(frozen=True)
class StereoBatch:
    """A batch of rectified (or nearly rectified) grayscale stereo pairs.

    Attributes:
        left: left images ``(B, 1, H, W)``, float in [0, 1].
        right: right images ``(B, 1, H, W)``, float in [0, 1].
        focal_px: focal length in pixels along x ``(B,)``.
        baseline_m: stereo baseline in metres ``(B,)``.
        doffs_px: x-difference of the principal points, ``cx_right − cx_left``, in pixels ``(B,)`` (Middlebury
            ``doffs``); depth is ``Z = f·B / (d + doffs)``. Zero for an ideal parallel rig such as the SVS.
        calibrated: ``(B,)`` bool; True where focal, baseline and doffs are the data's measured calibration, so
            depth from disparity is meaningful. False where they are nominal guesses (e.g. the SVS defaults for
            plain image files, or a dataset that ships no calibration).
        image_hw: ``(B, 2)`` int64, each pair's own (height, width) before padding; padding is at the bottom
            and right, so pixel coordinates of the pair are unchanged.
        disparity_px: optional ground-truth disparity of the left view ``(B, 1, H, W)``: a left pixel x maps to
            the right pixel x − d.
        disparity_valid: ``(B, 1, H, W)`` bool, where ``disparity_px`` is known; required with it.
        names: one name per pair (scene or file name), for reports.
        disparity_nonoccluded: optional ``(B, 1, H, W)`` bool, where the GT pixel is also seen by the right
            view (MiddEval3 ``mask0nocc.png`` = 255, KITTI ``disp_noc``); a subset of ``disparity_valid``. None
            where the data has no such mask; in a batch where only some pairs have one, the others' are all
            False (no pixel of theirs is known to be non-occluded, so their non-occluded metrics are null).
    """

    left: torch.Tensor
    right: torch.Tensor
    focal_px: torch.Tensor
    baseline_m: torch.Tensor
    doffs_px: torch.Tensor
    calibrated: torch.Tensor
    image_hw: torch.Tensor
    disparity_px: torch.Tensor | None = None
    disparity_valid: torch.Tensor | None = None
    names: tuple[str, ...] = ()
    disparity_nonoccluded: torch.Tensor | None = None

    def __post_init__(self) -> None:
        dims = check_stereo_views(self.left, self.right)  # one dtype: the differentiable pass followed the right's
        b = dims["B"]
        if min(dims["H"], dims["W"]) < 1:
            raise InputError(f"left: expected images of at least 1x1 pixels, got {dims['W']}x{dims['H']} (WxH)")
        for name in ("focal_px", "baseline_m", "doffs_px"):
            value = getattr(self, name)
            check_shape(value, name, [b])
            check_dtype(value, name, "float")
            # Depth is f·B / (d + doffs): an infinite or NaN calibration value would turn every depth into
            # inf / NaN, and a zero or negative focal or baseline into a meaningless or negative depth.
            check_finite(value, name, positive=name != "doffs_px")
        check_shape(self.calibrated, "calibrated", [b])
        check_dtype(self.calibrated, "calibrated", "bool")
        # At least 1 pixel (else a later stage blamed left's 0x0 "image") and within the tensors (the paper's path
        # ranged a larger size in silence): the kernels' own check of it.
        check_image_hw(self.image_hw, b, dims["H"], dims["W"])
        if (self.disparity_px is None) != (self.disparity_valid is None):
            raise InputError("disparity_valid: expected it together with disparity_px (both or neither)")
        if self.disparity_px is not None:
            check_same_shape(self.left, "left", self.disparity_px, "disparity_px")
            check_dtype(self.disparity_px, "disparity_px", "float")
            check_same_shape(self.left, "left", self.disparity_valid, "disparity_valid")
            check_dtype(self.disparity_valid, "disparity_valid", "bool")
            check_finite_where(self.disparity_px, "disparity_px", self.disparity_valid, "disparity_valid")
        if self.disparity_nonoccluded is not None:
            if self.disparity_px is None:
                raise InputError("disparity_nonoccluded: expected it only with disparity_px (a GT mask)")
            check_same_shape(self.left, "left", self.disparity_nonoccluded, "disparity_nonoccluded")
            check_dtype(self.disparity_nonoccluded, "disparity_nonoccluded", "bool")
        if isinstance(self.names, (str, bytes)):  # "Teddy" was read as 5 names, and "T" kept as one (an audit)
            raise InputError(f"names: expected a sequence of {b} name{'s' * (b != 1)}, one per pair, got one string "
                             f"{self.names!r}" + (f" (for one pair: ({self.names!r},))" if b == 1 else ""))
        if self.names and len(self.names) != b:
            raise InputError(f"names: expected {b} names, one per pair, got {len(self.names)}")

    @classmethod
    def from_images(
        cls,
        left: torch.Tensor,
        right: torch.Tensor,
        focal_px: float | torch.Tensor,
        baseline_m: float | torch.Tensor,
        doffs_px: float | torch.Tensor = 0.0,
        calibrated: bool | torch.Tensor = False,
        disparity_px: torch.Tensor | None = None,
        disparity_valid: torch.Tensor | None = None,
        names: tuple[str, ...] = (),
        disparity_nonoccluded: torch.Tensor | None = None,
    ) -> StereoBatch:
        """Build a batch from image tensors, broadcasting scalar calibration to every pair."""
        check_image(left, "left", check_range=False)
        b, _, h, w = left.shape

        def per_pair(name: str, value: float | bool | torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
            # A number, or a tensor of one value or of one value per pair; anything else is named, not a
            # broadcasting error from deep inside torch.
            try:
                tensor = (value.to(left.device) if isinstance(value, torch.Tensor)
                          else torch.as_tensor(value, dtype=dtype, device=left.device))
            except (TypeError, ValueError, RuntimeError):
                raise InputError(f"{name}: expected a number or a ({b},) tensor, got {type(value).__name__}") \
                    from None
            if tensor.numel() not in (1, b) or tensor.dim() > 1 or tensor.dtype.is_complex:
                raise InputError(f"{name}: expected a real number or a ({b},) tensor, got "
                                 f"{tuple(tensor.shape)} {tensor.dtype}")
            return tensor.to(dtype).reshape(-1).expand(b).clone()

        float_dtype = left.dtype
        return cls(
            left=left,
            right=right,
            focal_px=per_pair("focal_px", focal_px, float_dtype),
            baseline_m=per_pair("baseline_m", baseline_m, float_dtype),
            doffs_px=per_pair("doffs_px", doffs_px, float_dtype),
            calibrated=per_pair("calibrated", calibrated, torch.bool),
            image_hw=torch.tensor([[h, w]], dtype=torch.int64, device=left.device).expand(b, 2).clone(),
            disparity_px=disparity_px,
            disparity_valid=disparity_valid,
            names=names,
            disparity_nonoccluded=disparity_nonoccluded,
        )

    @property
    def batch_size(self) -> int:
        return self.left.shape[0]

    @property
    def size_hw(self) -> tuple[int, int]:
        """(H, W) of the padded batch tensors."""
        return self.left.shape[-2], self.left.shape[-1]

    def ground_truth_depth_m(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Ground-truth depth ``Z = f·B / (d + doffs)`` in metres of the left view.

        Returns:
            depth ``(B, 1, H, W)`` (zero where invalid) and its validity mask ``(B, 1, H, W)``: valid where the
            disparity is known, ``d + doffs > 0`` and the pair is ``calibrated``. Never divides by zero.
        """
        if self.disparity_px is None:
            raise InputError("disparity_px: this batch has no ground truth")
        denom = self.disparity_px + self.doffs_px.view(-1, 1, 1, 1)
        valid = self.disparity_valid & (denom > 0) & self.calibrated.view(-1, 1, 1, 1)
        safe = torch.where(valid, denom, torch.ones_like(denom))
        scale = (self.focal_px * self.baseline_m).view(-1, 1, 1, 1)
        return torch.where(valid, scale / safe, torch.zeros_like(denom)), valid

    def select(self, index: torch.Tensor | list[int] | slice) -> StereoBatch:
        """The pairs at ``index`` (a slice, a list of ints or an int64/bool tensor) as a new batch; a negative
        index counts from the end, as in a list."""
        b = self.batch_size
        if isinstance(index, slice):
            keep = list(range(b))[index]
        elif isinstance(index, torch.Tensor) and index.dtype == torch.bool:
            if tuple(index.shape) != (b,):
                raise InputError(f"index: expected a ({b},) bool mask, got {tuple(index.shape)}")
            keep = index.nonzero().flatten().tolist()
        else:
            try:
                keep = [int(i) for i in (index.flatten().tolist() if isinstance(index, torch.Tensor) else index)]
            except (TypeError, ValueError):
                raise InputError(f"index: expected a slice, ints or a bool mask, got {index!r}") from None
            if any(not -b <= i < b for i in keep):
                raise InputError(f"index: expected pair indices in [-{b}, {b}), got {keep}")
            keep = [i % b for i in keep]
        idx = torch.tensor(keep, dtype=torch.int64, device=self.left.device)
        fields = {}
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, torch.Tensor):
                fields[field.name] = value.index_select(0, idx)
            elif field.name == "names":
                fields[field.name] = tuple(value[i] for i in keep) if value else ()
            else:
                fields[field.name] = value
        return StereoBatch(**fields)

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> StereoBatch:
        """Move to ``device``; cast the floating-point fields (images, calibration, disparity) to ``dtype``. A batch
        already there is returned as it is (not copied, not validated again)."""
        target = None if device is None else torch.device(device)
        tensors = [value for value in (getattr(self, field.name) for field in dataclasses.fields(self))
                   if isinstance(value, torch.Tensor)]
        if all((target is None or value.device == target)
               and (dtype is None or not value.dtype.is_floating_point or value.dtype == dtype) for value in tensors):
            return self
        fields = {}
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, torch.Tensor):
                value = value.to(device=device, dtype=dtype if value.dtype.is_floating_point else None)
            fields[field.name] = value
        return StereoBatch(**fields)


class SegmentationStatus(enum.IntEnum):
    """Per-image (and per-pair) outcome of the segmentation stage; stored as int64 in tensors.

    A full-foreground mask needs every pixel above Otsu's threshold, which only a one-level image gives
    (the opening never adds foreground): that case is ``UNIFORM_IMAGE``.

    Values:
        OK (0): at least one region kept.
        UNIFORM_IMAGE (1): the image has a single gray level: Otsu has no split (OpenCV then thresholds at 0).
        NO_FOREGROUND (2): no foreground pixel survives threshold and opening: no obstacle region.
    """

    OK = 0
    UNIFORM_IMAGE = 1
    NO_FOREGROUND = 2


@dataclass(frozen=True)
class RegionProperties:
    """Properties of labelled regions, padded to L slots; slot ``l`` holds label ``l + 1``.

    Attributes:
        area_px: pixel count ``(B, L)`` int64 (MATLAB ``regionprops`` ``Area``; OpenCV ``CC_STAT_AREA``).
        bbox_xyxy: ``(B, L, 4)`` int64 ``x0, y0, x1, y1`` with x1, y1 exclusive (x = column).
        centroid_xy: ``(B, L, 2)`` float (the segmented image's dtype), mean pixel position (x, y) in pixel-centre
            coordinates.
        valid: ``(B, L)`` bool, slots that hold a region of that image.
    """

    area_px: torch.Tensor
    bbox_xyxy: torch.Tensor
    centroid_xy: torch.Tensor
    valid: torch.Tensor


@dataclass(frozen=True)
class Segmentation:
    """What the segmentation stage (paper Sec. 3.2, steps 1–6) produces for a batch of B images.

    Attributes:
        threshold: Otsu threshold ``(B,)`` on the [0, 1] scale; a pixel is foreground where its gray level
            ``round(255·image) > threshold_level`` (``image > threshold`` only for images on the 1/255 grid).
        threshold_level: the same threshold as a 0–255 gray level ``(B,)`` int64 (OpenCV's return value).
        binary: thresholded image ``(B, 1, H, W)`` bool (the Canny edge map for the Canny method).
        opened: binary image after erosion then dilation ``(B, 1, H, W)`` bool (edges after dilation then
            erosion for the Canny method).
        labels: connected-component labels of ``opened`` ``(B, 1, H, W)`` int64, 0 = background, 1..n
            contiguous in raster order of each region's first pixel.
        num_regions: n per image ``(B,)`` int64.
        regions: properties of every region (:class:`RegionProperties`, L = max n over the batch).
        kept_labels: labels of the kept regions ``(B, N)`` int64 in the order the keep rule ranks them (the
            paper's "largest": largest area first; the nearness segmenter's: nearest first,
            :func:`svs_torch.segmentation.segment.keep_regions`), −1 where an image has fewer than N regions, and
            in a pipeline result's left view where the region was dropped as unmeasured
            (``PipelineConfig.drop_unmeasured_below_share``; the slots after it stay where they were).
        kept_mask: union of the kept regions ``(B, 1, H, W)`` bool.
        masked: the grayscale image where ``kept_mask`` holds, 0 elsewhere ``(B, 1, H, W)``.
        status: :class:`SegmentationStatus` per image ``(B,)`` int64.
    """

    threshold: torch.Tensor
    threshold_level: torch.Tensor
    binary: torch.Tensor
    opened: torch.Tensor
    labels: torch.Tensor
    num_regions: torch.Tensor
    regions: RegionProperties
    kept_labels: torch.Tensor
    kept_mask: torch.Tensor
    masked: torch.Tensor
    status: torch.Tensor


@dataclass(frozen=True)
class StereoSegmentation:
    """Segmentation of both images of a stereo batch.

    Attributes:
        left, right: :class:`Segmentation` of the left and right images.
        status: per-pair status ``(B,)`` int64: the left image's status where it is not OK, else the right's.
        split_retaken: ``(B,)`` bool, the nearness segmenter's split was taken again under the 90th percentile of
            the measured disparity (:mod:`svs_torch.segmentation.nearness_split`): a map with more wrong matches
            than usual, which the pipeline's exposure retry also tries. None from segmenters without a split.
        from_disparity: ``(B,)`` bool, the kept regions were cut from a block-matched disparity map (the nearness
            segmenter; False for a pair it segmented by Otsu instead, too little of its view measured): the
            pipeline measures them over their interior (:mod:`svs_torch.segmentation.interior`). None from
            segmenters without such a map.
        floor_plane_px: ``(B, 3)`` the floor's plane ``a, b, c`` of ``d = a·x + b·y + c`` in input pixels (0 where
            not found; :mod:`svs_torch.segmentation.ground_plane`): what the distances ahead along the floor read
            (:mod:`svs_torch.depth.floor_distance`). None where the floor was not looked for
            (``SegmentationConfig.ground``).
        floor_found: ``(B,)`` bool, a floor was found; None with ``floor_plane_px``.
    """

    left: Segmentation
    right: Segmentation
    status: torch.Tensor
    split_retaken: torch.Tensor | None = None
    from_disparity: torch.Tensor | None = None
    floor_plane_px: torch.Tensor | None = None
    floor_found: torch.Tensor | None = None


@dataclass(frozen=True)
class Keypoints:
    """A fixed number K of keypoints per image, padded; the strongest first.

    Attributes:
        xy: ``(B, K, 2)`` float, sub-pixel position (x = column, y = row) in pixel-centre coordinates.
        scale: ``(B, K)`` float, SURF scale s (the Gaussian σ the box filters approximate: 1.2 · size / 9).
        score: ``(B, K)`` float, detector response (det of the Hessian, on the [0, 1] intensity scale).
        laplacian_sign: ``(B, K)`` int64, sign of the Hessian's trace (+1 dark blob on bright, −1 bright
            blob on dark; 0 in padding); matching only compares keypoints of the same sign.
        orientation: ``(B, K)`` float, radians; 0 for upright (U-SURF) keypoints.
        valid: ``(B, K)`` bool; padding rows are zero and False.
    """

    xy: torch.Tensor
    scale: torch.Tensor
    score: torch.Tensor
    laplacian_sign: torch.Tensor
    orientation: torch.Tensor
    valid: torch.Tensor


@dataclass(frozen=True)
class Matches:
    """Left-to-right descriptor matches.

    Attributes:
        idx: ``(B, K)`` int64, index into the right keypoints for each left keypoint, −1 for no match.
        cost: ``(B, K)`` float, the match's descriptor distance (SAD), ``inf`` where ``idx`` is −1.
    """

    idx: torch.Tensor
    cost: torch.Tensor

    @property
    def valid(self) -> torch.Tensor:
        """``(B, K)`` bool, left keypoints that have a match."""
        return self.idx >= 0


class FundamentalStatus(enum.IntEnum):
    """Per-pair outcome of the fundamental-matrix stage; stored as int64 in tensors.

    Values:
        OK (0): F found, with at least the inliers the caller asked for.
        TOO_FEW_MATCHES (1): fewer than 7 valid correspondences: no minimal sample exists.
        DEGENERATE (2): every hypothesis was degenerate (collinear or repeated points, no real root of the cubic).
        TOO_FEW_INLIERS (3): a model was found, but it has fewer inliers than the minimum the caller asked for.
    """

    OK = 0
    TOO_FEW_MATCHES = 1
    DEGENERATE = 2
    TOO_FEW_INLIERS = 3


@dataclass(frozen=True)
class FundamentalResult:
    """The robust fundamental matrix of each pair.

    Attributes:
        F: ``(B, 3, 3)``, maps a left point to its right epipolar line: ``x_rightᵀ F x_left = 0`` (pixels);
            rank 2, unit Frobenius norm; zeros where ``status`` is not OK.
        inliers: ``(B, K)`` bool over the input correspondences.
        num_inliers: ``(B,)`` int64.
        status: :class:`FundamentalStatus` per pair ``(B,)`` int64.
        iterations: ``(B,)`` int64, hypotheses drawn for each pair before it stopped.
    """

    F: torch.Tensor
    inliers: torch.Tensor
    num_inliers: torch.Tensor
    status: torch.Tensor
    iterations: torch.Tensor
