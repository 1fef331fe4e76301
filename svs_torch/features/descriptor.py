"""SURF descriptor and orientation, batched over all keypoints of all images (Bay et al. 2008, Sec. 4).

Descriptor (Sec. 4.2): a square window of side 20s around the keypoint (s its scale), split into 4 × 4
sub-regions of 5 × 5 samples spaced s apart. At each sample, Haar-wavelet responses dx, dy of size 2s,
weighted by a Gaussian of σ = 3.3s centred on the keypoint; each sub-region contributes Σdx, Σdy, Σ|dx|, Σ|dy|
(64 values; 128 in the extended form, which splits the sums by the sign of the other response), and the
vector is normalised to unit length.

As in OpenCV's SURF (which MATLAB uses), the window is first resampled to a 21 × 21 patch of s × s cell means
(read exactly from the integral image, rotated with the keypoint when it has an orientation), and the Haar
responses are 2 × 2-cell differences on that patch, so their size is 2s.

Orientation (Sec. 4.1): Haar responses of size 4s at the samples within radius 6s, weighted by a Gaussian of
σ = 2s; the dominant direction is the longest sum over a π/3 window sliding in 5° steps (responses binned
by angle to 5°).

Everything is differentiable with respect to the image for fixed keypoints (positions and scales carry no
gradient); padding rows give zero descriptors.
"""

from __future__ import annotations

import math

import torch

from ..core.checks import InputError, all_finite, check_dtype, check_image, check_instance, check_shape
from ..core.compiling import maybe_compiled
from ..core.kernels.checks import check_nonempty
from ..core.types import Keypoints
from . import kernels
from .integral import PaddedIntegral, padded_integral_image, sample_box_means, sample_cell_means

__all__ = ["describe_surf", "surf_orientation"]

_PATCH = 20  # Haar samples per side of the window (Sec. 4.2)
_SIGMA_DESCRIPTOR = 3.3  # in units of s (Sec. 4.2)
_ORIENTATION_RADIUS = 6  # samples, in units of s (Sec. 4.1)
_SIGMA_ORIENTATION = 2.0  # in units of s (Sec. 4.1)
_WINDOW = math.pi / 3  # sliding orientation window (Sec. 4.1)
_NUM_WINDOWS = 72  # window start every 5°, as OpenCV


def _check_keypoints(image: torch.Tensor, keypoints: Keypoints) -> None:
    check_image(image, "image", check_range=False)
    check_instance(keypoints, "keypoints", Keypoints)  # None or a tuple of its fields failed on .xy (an audit)
    b = image.shape[0]
    k = check_shape(keypoints.xy, "keypoints.xy", [b, "K", 2])["K"]
    check_shape(keypoints.scale, "keypoints.scale", [b, k])
    check_shape(keypoints.valid, "keypoints.valid", [b, k])
    check_dtype(keypoints.valid, "keypoints.valid", "bool")
    check_nonempty(image, "image")
    # Any float range is taken (masked or filtered images), but not NaN or inf: surf_orientation cast a NaN angle
    # to an index and failed in scatter_add, naming nothing, and describe_surf gave all-zero descriptors.
    if not all_finite(image):
        raise InputError("image: expected finite values (NaN or inf found)")
    # A NaN position has no pixel to sample (the kernel would cast it to an index, the torch path give NaN).
    if bool((keypoints.xy.detach().isnan().any(-1) & keypoints.valid).any()):
        raise InputError("keypoints.xy: expected no NaN at valid keypoints")
    # A scale of -inf put the patch at -inf px "beyond" the image, which passed the border's memory check and then
    # overflowed math.ceil; a scale of 0 or below has no patch to sample.
    scale = keypoints.scale.detach()[keypoints.valid]
    if not bool((scale.isfinite() & (scale > 0)).all()):
        bad = scale[~(scale.isfinite() & (scale > 0))][0]
        raise InputError(f"keypoints.scale: expected finite positive scales at valid keypoints, got {float(bad):g}")


def _border_px(image: torch.Tensor, keypoints: Keypoints, reach: float) -> int:
    """The replicate border just wide enough for samples ``reach · s`` around every valid keypoint (most
    keypoints lie well inside: the border is usually far narrower than ``reach · s_max``)."""
    h, w = image.shape[-2:]
    valid = keypoints.valid
    if not bool(valid.any()):
        return 1
    radius = keypoints.scale.detach()[valid] * reach
    x, y = keypoints.xy.detach()[valid].unbind(-1)
    beyond = float(torch.stack([radius - x, x + radius - (w - 1), radius - y, y + radius - (h - 1)]).amax())
    # The border is allocated (a table of (H + 2·border)(W + 2·border) per image): a keypoint far outside, or a
    # huge or NaN scale, would ask for memory no machine has.
    if not beyond <= 2 * max(h, w):
        raise InputError(f"keypoints: expected every valid keypoint's patch ({reach:.3g}·scale around xy) within "
                         f"{2 * max(h, w)} px of the {h} x {w} image, got {beyond:.4g} px beyond it")
    return max(0, math.ceil(beyond)) + 2


def _padded_integral(image: torch.Tensor, keypoints: Keypoints, reach: float) -> PaddedIntegral:
    """Integral image with a replicate border of :func:`_border_px`."""
    return padded_integral_image(image, _border_px(image, keypoints, reach))


def _rotated_patch_means(integral: PaddedIntegral, keypoints: Keypoints) -> torch.Tensor:
    """``(B, K, 21, 21)`` means of s × s cells on the keypoint's rotated grid, cell (i, j) centred at
    ``xy + s · R(θ) · (j − 10, i − 10)`` (axis-aligned boxes at the rotated centres, as Bay et al.)."""
    b, k = keypoints.scale.shape
    dtype = integral.table.dtype
    offsets = torch.arange(_PATCH + 1, dtype=dtype, device=integral.table.device) - _PATCH / 2  # −10 … 10
    v, u = torch.meshgrid(offsets, offsets, indexing="ij")  # rows, columns
    scale = keypoints.scale.to(dtype).clamp(min=1e-3)[..., None, None]
    x, y = keypoints.xy[..., 0, None, None].to(dtype), keypoints.xy[..., 1, None, None].to(dtype)
    cos = torch.cos(keypoints.orientation.to(dtype))[..., None, None]
    sin = torch.sin(keypoints.orientation.to(dtype))[..., None, None]
    centres = torch.stack([x + scale * (cos * u - sin * v), y + scale * (sin * u + cos * v)], dim=-1).view(b, -1, 2)
    half = (scale / 2).expand(b, k, _PATCH + 1, _PATCH + 1).reshape(b, -1)
    return sample_box_means(integral, centres, half).view(b, k, _PATCH + 1, _PATCH + 1)


def _gaussian(size: int, sigma: float, dtype, device) -> torch.Tensor:
    """``(size, size)`` Gaussian weights centred between the middle samples (units: samples)."""
    r = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-(r**2) / (2 * sigma**2))
    return g[:, None] * g[None, :]


def _descriptor_from_patch(patch: torch.Tensor, valid: torch.Tensor, extended: bool,
                           flat: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """``(B, K, 21, 21)`` cell means → ``(B, K, D)`` unit descriptors (zero where not ``valid``). ``flat``: the
    upright lattice's :func:`_within_one_pixel` ``(B, K, 20)`` along x and along y, where the extended descriptor
    takes the response as 0 (not negative) whatever its round-off."""
    b, k = valid.shape
    # 2 × 2-cell Haar wavelets (size 2s) centred between cells, OpenCV's layout.
    dx = (patch[..., :-1, 1:] - patch[..., :-1, :-1] + patch[..., 1:, 1:] - patch[..., 1:, :-1]) / 2
    dy = (patch[..., 1:, :-1] - patch[..., :-1, :-1] + patch[..., 1:, 1:] - patch[..., :-1, 1:]) / 2
    weight = _gaussian(_PATCH, _SIGMA_DESCRIPTOR, patch.dtype, patch.device)
    dx, dy = dx * weight, dy * weight  # (B, K, 20, 20)

    def blocks(t: torch.Tensor) -> torch.Tensor:
        """Sum over each 5 × 5 sub-region: (B, K, 20, 20) -> (B, K, 4, 4)."""
        return t.view(b, k, 4, 5, 4, 5).sum(dim=(3, 5))

    if extended:
        neg_dy, neg_dx = dy < 0, dx < 0
        if flat is not None:
            neg_dy, neg_dx = neg_dy & ~flat[1].unsqueeze(-1), neg_dx & ~flat[0].unsqueeze(-2)
        parts = [dx * neg_dy, dx.abs() * neg_dy, dx * ~neg_dy, dx.abs() * ~neg_dy,
                 dy * neg_dx, dy.abs() * neg_dx, dy * ~neg_dx, dy.abs() * ~neg_dx]
    else:
        parts = [dx, dy, dx.abs(), dy.abs()]
    # Sub-region-major layout; the length is spelled out so that no keypoint at all (k = 0) still has a shape.
    descriptor = torch.stack([blocks(p) for p in parts], dim=-1).view(b, k, 16 * len(parts))
    norm = descriptor.norm(dim=-1, keepdim=True)
    usable = valid.unsqueeze(-1) & (norm > 0)
    unit = descriptor / torch.where(usable, norm, torch.ones_like(norm))
    return torch.where(usable, unit, torch.zeros_like(unit))


def describe_surf(
    image: torch.Tensor, keypoints: Keypoints, extended: bool = False, compiled: bool = False
) -> torch.Tensor:
    """SURF descriptors of all keypoints of a batch.

    Args:
        image: ``(B, 1, H, W)`` float images (e.g. the masked obstacle images).
        keypoints: :class:`~svs_torch.core.types.Keypoints` with K rows (orientation 0 = upright, U-SURF).
        extended: 128-long descriptors instead of 64.
        compiled: run the patch-to-descriptor arithmetic through ``torch.compile`` (same values).

    Returns:
        ``(B, K, D)`` unit-length descriptors (D = 64 or 128), zero rows for padding. Differentiable with
        respect to ``image``.
    """
    _check_keypoints(image, keypoints)
    b, k = keypoints.valid.shape
    if not bool((keypoints.orientation != 0).any()):
        return _describe_upright(image, keypoints, extended, compiled)
    # Work on the rows up to the last valid one of any image: detectors pad at the end, often by half.
    rows = torch.arange(1, k + 1, device=keypoints.valid.device)
    used = int((keypoints.valid * rows).amax()) if k else 0
    head = _take_rows(keypoints, used)
    integral = _padded_integral(image, head, 10.5 * math.sqrt(2))  # rotated cells reach 10.5·√2·s
    patch = _rotated_patch_means(integral, head)  # (B, used, 21, 21)
    descriptor = maybe_compiled(_descriptor_from_patch, compiled)(patch, head.valid, extended).to(image.dtype)
    return torch.cat([descriptor, descriptor.new_zeros(b, k - used, descriptor.shape[-1])], dim=1)


def _describe_upright(image: torch.Tensor, keypoints: Keypoints, extended: bool, compiled: bool) -> torch.Tensor:
    """U-SURF on the valid keypoints only, gathered from all images into one ragged set (images differ in
    how many keypoints they have; padding rows are never sampled). Without gradients, float32 on the CPU, the
    compiled kernel (:mod:`svs_torch.features.kernels`) builds each image's integral and describes its keypoints one at
    a time instead: the same arithmetic in double, so it equals this path in float64 to 1e-6 and the float32
    path to that path's own round-off (at most 5e-4). On 64 real 320×240 pairs, one thread: 6.1 → 1.8 ms a
    pair."""
    b, k = keypoints.valid.shape
    pad = _border_px(image, keypoints, 10.5)  # cells reach 10.5·s along each axis
    if image.dtype == torch.float32 and not (torch.is_grad_enabled() and image.requires_grad):
        done = kernels.usurf_describe(image, pad, keypoints.xy.detach(), keypoints.scale.detach(), keypoints.valid,
                                      extended)
        if done is not None:
            return done
    integral = padded_integral_image(image, pad)
    image_index, row = keypoints.valid.nonzero(as_tuple=True)
    dtype = integral.table.dtype
    scale = keypoints.scale[image_index, row].to(dtype).clamp(min=1e-3).unsqueeze(-1)  # (P, 1)
    xy = keypoints.xy[image_index, row].to(dtype)
    edges = torch.arange(_PATCH + 2, dtype=dtype, device=image.device) - (_PATCH + 1) / 2  # −10.5 … 10.5
    patch = sample_cell_means(integral, image_index, xy[:, 0:1] + scale * edges, xy[:, 1:2] + scale * edges)
    everywhere = torch.ones_like(row, dtype=torch.bool)[None]
    steady = None
    if extended:  # the lattice's edges again in double, as the kernel's, for which responses are 0 by definition
        where = keypoints.xy.detach()[image_index, row].double()
        steps = keypoints.scale.detach()[image_index, row].double().clamp(min=1e-3).unsqueeze(-1) * edges.double()
        steady = tuple(_within_one_pixel(where[:, axis:axis + 1] + steps, image.shape[-1 - axis])[None]
                       for axis in (0, 1))
    flat = maybe_compiled(_descriptor_from_patch, compiled)(patch.unsqueeze(0), everywhere, extended, steady)[0]
    out = flat.new_zeros(b, k, flat.shape[-1])
    out[image_index, row] = flat
    return out.to(image.dtype)


def _within_one_pixel(edges: torch.Tensor, size: int) -> torch.Tensor:
    """``(P, 22)`` cell edges along one axis of an image ``size`` pixels long (pixel-centre coordinates, float64)
    → ``(P, 20)``: whether the two cells of each Haar response across that axis, ``[e_i, e_{i+2}]``, lie within one
    pixel (the replicate border beyond the image is its edge pixel repeated: every cell there reads it). Their
    means are then equal, so the response is 0 by definition, and round-off alone gave it a sign: the extended
    descriptor put the other response into one half or the other by that noise, differently in the C kernel (in
    double) and the torch path (up to 0.05 apart on keypoints near the border). The same test, in double, in
    ``usurf_describe.c``."""
    first = torch.clamp(torch.floor(edges[:, :-2] - 0.5) + 1, min=0)  # the first pixel boundary k + 0.5 after e_i
    last = torch.clamp(torch.ceil(edges[:, 2:] - 0.5) - 1, max=size - 2)  # the last one before e_{i+2}
    return first > last


def _take_rows(keypoints: Keypoints, count: int) -> Keypoints:
    """The first ``count`` rows of every image's keypoints."""
    return Keypoints(keypoints.xy[:, :count], keypoints.scale[:, :count], keypoints.score[:, :count],
                     keypoints.laplacian_sign[:, :count], keypoints.orientation[:, :count],
                     keypoints.valid[:, :count])


def surf_orientation(image: torch.Tensor, keypoints: Keypoints) -> torch.Tensor:
    """Dominant orientation of each keypoint, radians in (−π, π] ``(B, K)``; 0 for padding.

    Haar responses of size 4s at the samples within 6s, Gaussian-weighted (σ = 2s); the longest vector sum
    over a π/3 window sliding in 5° steps gives the direction (Bay et al. Sec. 4.1). Not differentiable
    (an argmax over windows).
    """
    _check_keypoints(image, keypoints)
    integral = _padded_integral(image.detach(), keypoints, 9.0)  # samples within 6s, Haar boxes 2s more
    b, k = keypoints.scale.shape
    r = _ORIENTATION_RADIUS
    grid = torch.arange(-r, r + 1, dtype=integral.table.dtype, device=integral.table.device)
    v, u = torch.meshgrid(grid, grid, indexing="ij")
    inside = (u**2 + v**2) < r * r  # 109 samples
    u, v = u[inside], v[inside]
    weight = torch.exp(-(u**2 + v**2) / (2 * _SIGMA_ORIENTATION**2))
    dtype = integral.table.dtype
    s = keypoints.scale.to(dtype).clamp(min=1e-3).unsqueeze(-1)  # (B, K, 1)
    x = keypoints.xy[..., 0:1].to(dtype) + s * u
    y = keypoints.xy[..., 1:2].to(dtype) + s * v

    def half_means(dx_sign: float, dy_sign: float, half_w, half_h) -> torch.Tensor:
        centres = torch.stack([x + dx_sign * s, y + dy_sign * s], dim=-1).view(b, -1, 2)
        return sample_box_means(integral, centres, half_w.expand_as(x).reshape(b, -1),
                                half_h.expand_as(x).reshape(b, -1)).view_as(x)

    # Haar of size 4s: right half minus left half (each 2s × 4s), bottom minus top.
    haar_x = half_means(1, 0, s, 2 * s) - half_means(-1, 0, s, 2 * s)
    haar_y = half_means(0, 1, 2 * s, s) - half_means(0, -1, 2 * s, s)
    haar_x, haar_y = haar_x * weight, haar_y * weight  # (B, K, P)
    # Sum the responses in 5° angle bins, then over every run of 12 bins (a π/3 window, wrapping around):
    # O(bins) per keypoint instead of a (windows × samples) membership table.
    bin_width = 2 * math.pi / _NUM_WINDOWS
    bins = (torch.atan2(haar_y, haar_x) % (2 * math.pi) / bin_width).long().clamp(max=_NUM_WINDOWS - 1)
    per_bin = torch.zeros(b, k, _NUM_WINDOWS, 2, dtype=haar_x.dtype, device=haar_x.device)
    per_bin.scatter_add_(2, bins.unsqueeze(-1).expand(-1, -1, -1, 2), torch.stack([haar_x, haar_y], -1))
    span = round(_WINDOW / bin_width)
    wrapped = torch.cat([per_bin, per_bin[:, :, :span - 1]], dim=2).cumsum(dim=2)
    windows = wrapped[:, :, span - 1:] - torch.cat([torch.zeros_like(wrapped[:, :, :1]), wrapped[:, :, :-span]], 2)
    sum_x, sum_y = windows[..., 0], windows[..., 1]  # (B, K, 72)
    best = (sum_x**2 + sum_y**2).argmax(dim=-1, keepdim=True)
    orientation = torch.atan2(sum_y.gather(-1, best), sum_x.gather(-1, best)).squeeze(-1)
    return torch.where(keypoints.valid, orientation, torch.zeros_like(orientation)).to(image.dtype)


def with_orientation(keypoints: Keypoints, orientation: torch.Tensor) -> Keypoints:
    """The same keypoints with ``orientation`` ``(B, K)`` set."""
    if orientation.shape != keypoints.scale.shape:
        raise InputError(f"orientation: expected {tuple(keypoints.scale.shape)}, got {tuple(orientation.shape)}")
    return Keypoints(keypoints.xy, keypoints.scale, keypoints.score, keypoints.laplacian_sign, orientation,
                     keypoints.valid)
