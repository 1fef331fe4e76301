"""SURF keypoint detection, batched: strongest K scale-space maxima per image, refined to sub-pixel and sub-scale.

Paper Sec. 3.3 (1) detects SURF points on the masked obstacle images with MATLAB's ``detectSURFFeatures``;
its options and defaults are mirrored by :class:`SurfConfig`. The maths is in :mod:`svs_torch.features.hessian`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..core.checks import (InputError, check_dtype, check_flag, check_image, check_instance, check_real, check_shape,
                           real_or_nan)
from ..core.kernels.checks import check_nonempty
from ..core.types import Keypoints
from . import kernels
from .hessian import HessianOctave, hessian_octaves, local_maxima_scores, maxima_support
from .limits import DEFAULT_MAX_KEYPOINTS, MAX_KEYPOINTS, MAX_OCTAVES, MAX_SCALE_LEVELS  # noqa: F401 (re-exported)
from .limits import MATLAB_METRIC_THRESHOLD

__all__ = ["SurfConfig", "detect_surf_keypoints", "metric_threshold_01"]

#: Gray levels of the uint8 scale that MATLAB's MetricThreshold refers to.
_U8 = 255.0


@dataclass(frozen=True)
class SurfConfig:
    """SURF options, MATLAB ``detectSURFFeatures`` / ``extractFeatures`` names and defaults where they exist.

    Attributes:
        metric_threshold: minimum det(H) of a keypoint on 0–255 intensities (MATLAB ``MetricThreshold``,
            default 1000; det(H) on [0, 1] images is 255² times smaller, see :func:`metric_threshold_01`).
        num_octaves: MATLAB ``NumOctaves`` (default 3): filter sizes up to 99 px.
        num_scale_levels: MATLAB ``NumScaleLevels`` (default 4): filter sizes per octave, ≥ 3.
        max_keypoints: K, keypoints kept per image, the strongest; rows beyond the detections are padding.
        upright: U-SURF, no orientation (default True: the SVS is a fixed, roll-free rig; MATLAB's
            ``Upright`` defaults to false).
        extended: 128-long descriptor instead of 64 (MATLAB ``FeatureSize``).
        max_offset: the quadratic refinement may move a maximum by at most this many grid steps in x, y and
            scale (OpenCV's SURF, which MATLAB uses, accepts up to 1); farther fits are rejected.
        upsample: detect on the image enlarged twice (bilinear), as SIFT does (Lowe 2004, Sec. 3.3); not part of
            SURF or MATLAB. On 320×240 SVS frames it doubles the keypoints of the smallest scales and
            localises them better (``experiments/surf_vs_sift.py``); detection costs about 4× more.
        compiled: run the response and maxima kernels through ``torch.compile`` (identical keypoints; the first
            call in a fresh environment compiles for about 30 s). On CPU the default path's C kernels are faster:
            ``experiments/bench_features.py`` on 32 real 320×240 pairs, 2 threads (2026-12-05): 3.3 ms a pair at
            B = 32 against 10.1 compiled (6.0 against 19.0 at B = 1). torch.compile was several times faster than
            the eager torch ops before those kernels.
    """

    metric_threshold: float = MATLAB_METRIC_THRESHOLD  # MATLAB detectSURFFeatures default, 1000
    num_octaves: int = 3  # MATLAB default
    num_scale_levels: int = 4  # MATLAB default
    max_keypoints: int = DEFAULT_MAX_KEYPOINTS
    upright: bool = True  # Sec. 3.3 (1): fixed stereo rig, no roll
    extended: bool = False  # MATLAB FeatureSize 64
    max_offset: float = 1.0
    upsample: bool = False
    compiled: bool = False

    def __post_init__(self) -> None:
        if not real_or_nan(self.metric_threshold) >= 0:
            raise InputError(f"metric_threshold: expected a non-negative number, got {self.metric_threshold!r}")
        if not isinstance(self.num_octaves, int) or not 1 <= self.num_octaves <= MAX_OCTAVES:
            raise InputError(f"num_octaves: expected an integer from 1 to {MAX_OCTAVES}, got {self.num_octaves!r}")
        if not isinstance(self.num_scale_levels, int) or not 3 <= self.num_scale_levels <= MAX_SCALE_LEVELS:
            raise InputError(f"num_scale_levels: expected an integer from 3 to {MAX_SCALE_LEVELS}, got "
                             f"{self.num_scale_levels!r}")
        if not isinstance(self.max_keypoints, int) or not 0 <= self.max_keypoints <= MAX_KEYPOINTS:
            raise InputError(f"max_keypoints: expected an integer from 0 to {MAX_KEYPOINTS}, got "
                             f"{self.max_keypoints!r}")
        check_real(self.max_offset, "max_offset", 0.0)
        for name in ("upright", "extended", "upsample", "compiled"):
            check_flag(getattr(self, name), name)


def metric_threshold_01(metric_threshold: float) -> float:
    """MATLAB's MetricThreshold (det(H) on 0–255 intensities) as a det(H) threshold on [0, 1] images.

    det(H) is quadratic in intensity, so the threshold divides by 255²: 1000 becomes 0.01538.
    """
    return metric_threshold / (_U8 * _U8)


def _candidates(octaves: list[HessianOctave], threshold: float, mask: torch.Tensor | None, compiled: bool):
    """``(B, N)`` det at the interior scale-space maxima of every octave, −inf elsewhere (concatenated)."""
    return torch.cat([local_maxima_scores(o, threshold, mask, compiled).flatten(1) for o in octaves], dim=1)


def _strongest_maxima(octaves: list[HessianOctave], threshold: float, mask: torch.Tensor | None,
                      max_keypoints: int) -> tuple[torch.Tensor, torch.Tensor] | None:
    """:func:`_candidates` and its ``torch.topk`` in one C pass (:func:`svs_torch.features.kernels.strongest_maxima`):
    the same values and indices, equal scores in index order (which ``torch.topk`` leaves open). The dense maps of
    the octaves (−inf at all but a few hundred of ~200 000 points at 320×240) are never written, concatenated or
    partially sorted: 16 real images of 320×240, one thread, about 19 → 12 ms. None when the kernel cannot run."""
    total = sum(max(s - 2, 0) * max(ny - 2, 0) * max(nx - 2, 0) for s, ny, nx in (o.det.shape[1:] for o in octaves))
    supports = [maxima_support(o, mask) for o in octaves]
    return kernels.strongest_maxima([o.det for o in octaves], supports, threshold, min(max_keypoints, total))


def _octave_tables(octaves: list[HessianOctave], device) -> dict[str, torch.Tensor]:
    """Per-octave constants indexed by octave id: offset and strides of the interior candidate block, strides
    of the full response maps, grid step, first filter size and size increment."""
    columns: dict[str, list[int]] = {name: [] for name in (
        "offset", "inner_nx", "inner_plane", "nx", "plane", "step", "size0", "size_inc")}
    inner_total = 0
    for octave in octaves:
        s, ny, nx = octave.det.shape[1:]
        for name, value in (("offset", inner_total), ("inner_nx", nx - 2), ("inner_plane", (ny - 2) * (nx - 2)),
                            ("nx", nx), ("plane", ny * nx), ("step", octave.step),
                            ("size0", octave.sizes[0]), ("size_inc", octave.sizes[1] - octave.sizes[0])):
            columns[name].append(value)
        inner_total += (s - 2) * (ny - 2) * (nx - 2)
    return {name: torch.tensor(values, device=device) for name, values in columns.items()}


def _octave_reader(maps: list[torch.Tensor], octave_id: torch.Tensor, index: torch.Tensor, nx: torch.Tensor,
                   plane: torch.Tensor, radius: int = 1) -> Callable[..., torch.Tensor]:
    """``at(dx, dy, ds)``: each keypoint's value in its own octave's map ``(B, S, ny, nx)``, offset by whole grid
    steps up to ``radius``; small per-octave gathers instead of concatenating every map of the batch. The whole
    neighbourhood is gathered at once (one gather per octave, not one per offset and octave)."""
    flats = [m.flatten(1) for m in maps]
    steps = torch.arange(-radius, radius + 1, device=index.device)
    width = 2 * radius + 1
    # (B, K, width³) flat indices, offset ds slowest and dx fastest.
    neighbour = (index.unsqueeze(-1) + steps.repeat(width * width)
                 + steps.repeat_interleave(width).repeat(width) * nx.unsqueeze(-1)
                 + steps.repeat_interleave(width * width) * plane.unsqueeze(-1)).flatten(1)
    shape = (*index.shape, width ** 3)
    value = torch.gather(flats[0], 1, neighbour.clamp(0, flats[0].shape[1] - 1)).view(shape)
    for o, flat in enumerate(flats[1:], start=1):
        value = torch.where((octave_id == o).unsqueeze(-1),
                            torch.gather(flat, 1, neighbour.clamp(0, flat.shape[1] - 1)).view(shape), value)
    value = value.to(torch.float64)

    def at(dx: int = 0, dy: int = 0, ds: int = 0) -> torch.Tensor:
        return value[..., ((ds + radius) * width + dy + radius) * width + dx + radius]

    return at


def _refine(at: Callable[..., torch.Tensor]):
    """Quadratic fit of det around each maximum (Brown & Lowe): offset (x, y, s) in grid steps, peak value."""
    centre = at()
    gradient = torch.stack([(at(1) - at(-1)) / 2, (at(0, 1) - at(0, -1)) / 2, (at(0, 0, 1) - at(0, 0, -1)) / 2], -1)
    dxx = at(1) + at(-1) - 2 * centre
    dyy = at(0, 1) + at(0, -1) - 2 * centre
    dss = at(0, 0, 1) + at(0, 0, -1) - 2 * centre
    dxy = (at(1, 1) - at(-1, 1) - at(1, -1) + at(-1, -1)) / 4
    dxs = (at(1, 0, 1) - at(-1, 0, 1) - at(1, 0, -1) + at(-1, 0, -1)) / 4
    dys = (at(0, 1, 1) - at(0, -1, 1) - at(0, 1, -1) + at(0, -1, -1)) / 4
    hessian = torch.stack([torch.stack([dxx, dxy, dxs], -1), torch.stack([dxy, dyy, dys], -1),
                           torch.stack([dxs, dys, dss], -1)], -2)  # (B, K, 3, 3)
    offset, info = torch.linalg.solve_ex(hessian, -gradient)
    solved = (info == 0) & torch.isfinite(offset).all(-1)
    offset = torch.where(solved.unsqueeze(-1), offset, torch.zeros_like(offset))
    peak = centre + 0.5 * (gradient * offset).sum(-1)
    return offset, peak, solved


def detect_surf_keypoints(
    image: torch.Tensor, config: SurfConfig = SurfConfig(), mask: torch.Tensor | None = None
) -> Keypoints:
    """Detect the K strongest SURF keypoints of each image of a batch.

    Args:
        image: ``(B, 1, H, W)`` float in [0, 1] (e.g. the masked obstacle images of the segmentation stage).
        config: :class:`SurfConfig`.
        mask: optional ``(B, 1, H, W)`` bool; keypoints only where it holds.

    Returns:
        :class:`~svs_torch.core.types.Keypoints` with K = ``config.max_keypoints`` rows, strongest first, padded
        (``valid`` False, zeros) where an image has fewer detections. Keypoint choice is not differentiable;
        :func:`svs_torch.features.hessian.hessian_octaves` gives the differentiable response maps.
    """
    check_image(image, "image")
    check_nonempty(image, "image")
    check_instance(config, "config", SurfConfig)
    b = image.shape[0]
    if mask is not None:
        check_shape(mask, "mask", [b, 1, image.shape[2], image.shape[3]])
        check_dtype(mask, "mask", "bool")
    factor = 2 if config.upsample else 1
    source = image.detach()
    if factor > 1:
        source = F.interpolate(source, scale_factor=factor, mode="bilinear", align_corners=False).clamp_(0, 1)
        if mask is not None:
            mask = F.interpolate(mask.to(torch.uint8), scale_factor=factor, mode="nearest").bool()
    octaves = hessian_octaves(source, config.num_octaves, config.num_scale_levels, config.compiled)
    threshold = metric_threshold_01(config.metric_threshold)
    top = None if config.compiled else _strongest_maxima(octaves, threshold, mask, config.max_keypoints)
    if top is None:
        scores = _candidates(octaves, threshold, mask, config.compiled)
        top = torch.topk(scores, min(config.max_keypoints, scores.shape[1]), dim=1)
    top_score, index = top  # (B, k), strongest first; index into the octaves' concatenated interiors
    # The compiled fit (svs_torch/features/kernels/refine_maxima.c): one loop over the keypoints instead of about fifty
    # small ops on (B, k) tensors; the same keypoints, its 3 × 3 solve's rounding aside.
    fitted = kernels.refine_maxima([o.det for o in octaves], [o.trace for o in octaves], [o.step for o in octaves],
                                   [list(o.sizes) for o in octaves], top_score, index, factor, config.max_offset)
    if fitted is not None:
        valid, xy, size, peak, sign = fitted
        return _pack(valid, xy, 1.2 * size / 9.0, peak, sign, image.dtype, config.max_keypoints)
    return _fit_keypoints(octaves, top_score, index, factor, config, image.dtype)


def _fit_keypoints(octaves: list[HessianOctave], top_score: torch.Tensor, index: torch.Tensor, factor: int,
                   config: SurfConfig, dtype: torch.dtype) -> Keypoints:
    """The torch path of the keypoints' fit: each maximum's octave, level, row and column from its index into
    the octaves' concatenated interiors, the quadratic fit of its 3 × 3 × 3 neighbourhood (:func:`_refine`),
    its position and size in input pixels, and its Laplacian sign."""
    tables = _octave_tables(octaves, top_score.device)
    octave_id = (torch.searchsorted(tables["offset"], index, right=True) - 1).clamp(min=0)
    local = index - tables["offset"][octave_id]
    inner_plane, inner_nx = tables["inner_plane"][octave_id], tables["inner_nx"][octave_id]
    level = local // inner_plane + 1
    row = local % inner_plane // inner_nx + 1
    col = local % inner_nx + 1
    nx, plane = tables["nx"][octave_id], tables["plane"][octave_id]
    found = torch.isfinite(top_score)
    position = level * plane + row * nx + col  # flat index within the octave's (S, ny, nx) maps
    offset, peak, solved = _refine(_octave_reader([o.det for o in octaves], octave_id, position, nx, plane))
    valid = found & solved & (offset.abs() <= config.max_offset).all(-1)
    step = tables["step"][octave_id].to(torch.float64)
    xy = torch.stack([(col + offset[..., 0]) * step, (row + offset[..., 1]) * step], dim=-1)
    xy = (xy + 0.5) / factor - 0.5  # pixel centres of the enlarged image back to the input's
    size = (tables["size0"][octave_id] + (level + offset[..., 2]) * tables["size_inc"][octave_id]) / factor
    trace = _octave_reader([o.trace for o in octaves], octave_id, position, nx, plane, radius=0)()
    sign = torch.where(trace >= 0, 1, -1).to(torch.int64)
    return _pack(valid, xy, 1.2 * size / 9.0, peak, sign, dtype, config.max_keypoints)


def _pack(valid, xy, scale, score, sign, dtype, k_total: int) -> Keypoints:
    """Strongest (refined score) valid keypoints first, invalid rows zeroed, padded to ``k_total`` rows."""
    order = torch.argsort(torch.where(valid, score, torch.full_like(score, float("-inf"))), dim=1, descending=True,
                          stable=True)
    valid = torch.gather(valid, 1, order)
    v = valid.to(torch.float64)
    xy = torch.gather(xy, 1, order.unsqueeze(-1).expand(-1, -1, 2)) * v.unsqueeze(-1)
    scale = torch.gather(scale, 1, order) * v
    score = torch.gather(score, 1, order) * v
    sign = torch.gather(sign, 1, order) * valid.to(torch.int64)
    b, k = valid.shape
    extra = k_total - k
    if extra > 0:
        def pad(t):
            return torch.cat([t, t.new_zeros((b, extra) + t.shape[2:])], dim=1)
        valid, xy, scale, score, sign = map(pad, (valid, xy, scale, score, sign))
    return Keypoints(xy=xy.to(dtype), scale=scale.to(dtype), score=score.to(dtype), laplacian_sign=sign,
                     orientation=torch.zeros_like(scale, dtype=dtype), valid=valid)
