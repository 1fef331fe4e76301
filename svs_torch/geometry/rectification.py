"""Uncalibrated stereo rectification from F and the inliers (paper Sec. 3.3, the step before depth, Sec. 3.4).

Hartley's method (Hartley & Zisserman, *Multiple View Geometry*, 2nd ed., Sec. 11.12; MATLAB
``estimateUncalibratedRectification``; OpenCV ``stereoRectifyUncalibrated``), batched over B pairs:

1. Epipoles from F's null spaces: for a rank-2 F the adjugate is ``adj(F) = e e'ᵀ`` (up to scale), so
   ``e'`` (right, ``e'ᵀ F = 0``) is its largest row and ``e`` (left, ``F e = 0``) its largest column. Unlike an
   SVD this is a polynomial in F, exact for rank 2 and smooth where the epipole is at infinity — the usual
   case for the SVS's fixed parallel rig, where ``F ≈ [e']ₓ`` with ``e' = (1, 0, 0)``.
2. Right homography ``H' = G R`` in a frame centred on the image: R rotates the epipole onto the x axis by the
   smallest angle (≤ 90°, no flip), G sends it to infinity (``G = I`` when it already is there).
3. Left homography ``[r; h₁; h₂]``: its y and w rows are those of ``H' M`` with ``F = [e']ₓ M``, so that
   matching points land on the same row (H&Z Sec. 11.12.2; independent of the choice of M). Its x row r is free
   (H&Z's affine correction ``H_A``) and the configuration chooses it:

   - ``"parallel"`` (default): the left map is conformal at the image centre and the two centres keep the same
     x. This is the identity for an already rectified pair, and it keeps disparity metric as far as the rig is
     parallel (a residual toe-in ψ shifts every disparity by about ``f·ψ``; no uncalibrated method can see it).
   - ``"hartley"``: r minimises the squared x-disparity over the inliers (least squares, H&Z Sec. 11.12.2),
     as MATLAB and OpenCV do. The rectified disparities are then scene-relative (their mean is driven to
     about zero), so depth by Eq. (7)–(8) needs the parallel mode or a calibrated offset.

Homographies map pixel-centre coordinates (x = column) of the original image to the rectified one, keep the
image centre fixed (``w = 1`` there) and its scale near 1. Pairs whose warp would split, flip or wildly rescale
the image get a status and identity homographies; no pair raises.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import NamedTuple

import torch

from ..core.checks import InputError, check_dtype, check_image, check_instance, check_same_shape, check_shape
from ..core.kernels.checks import canonical_bool, check_positive_hw
from ..core.numerics import per_pair
from . import kernels

__all__ = ["MappedPoints", "Rectification", "RectificationConfig", "RectificationStatus", "apply_homography",
           "map_points", "rectify_uncalibrated", "warp_rectified", "warp_views"]

#: F is treated as rank < 2 (no epipole) when ``‖adj F‖ ≤`` this times ``‖F‖²`` (``‖adj F‖ = σ₁σ₂`` for rank 2).
_RANK_TOLERANCE = 1e-9
#: The affine least squares (``"hartley"``) is singular below this eigenvalue ratio (< 3 non-collinear inliers).
_LSTSQ_TOLERANCE = 1e-12


class RectificationStatus(enum.IntEnum):
    """Per-pair outcome of :func:`rectify_uncalibrated`; stored as int64 in tensors. Values: OK (0) both homographies
    found, within the limits; NOT_ENOUGH_INLIERS (1) fewer than ``min_inliers`` inlier correspondences; DEGENERATE
    (2) F has rank < 2 or is not finite (a failed RANSAC leaves zeros), or the ``"hartley"`` fit is singular;
    EPIPOLE_IN_IMAGE (3) an epipole lies in the image, or so close that the line sent to infinity crosses it (``w ≤ 0``
    at a corner): the warp would split the image (forward motion, strongly converging cameras); DISTORTED (4) a
    homography would flip the image, scale its area at a corner or the centre by more than ``max_area_scale`` (or
    less than its inverse), or rotate it by more than ``max_rotation_deg``."""

    OK = 0
    NOT_ENOUGH_INLIERS = 1
    DEGENERATE = 2
    EPIPOLE_IN_IMAGE = 3
    DISTORTED = 4


@dataclass(frozen=True)
class RectificationConfig:
    """Options of :func:`rectify_uncalibrated`.

    Attributes:
        x_alignment: ``"parallel"`` or ``"hartley"``: how the left homography's free x row is chosen (module
            docstring). The paper's MATLAB call is ``"hartley"``; ``"parallel"`` keeps disparity for depth.
        min_inliers: fewest inliers to rectify a pair; 7 is the minimal sample of the 7-point F (Sec. 3.3).
        max_area_scale: largest area magnification (and inverse of the smallest) a homography may apply at the
            image corners and centre; 4 allows an epipole about two image widths away.
        max_rotation_deg: largest rotation of either image at its centre; beyond 45° the baseline is more
            vertical than horizontal, which is not a side-by-side rig. Tighten it for a rig known to be level.
    """

    x_alignment: str = "parallel"
    min_inliers: int = 7  # Sec. 3.3: the 7-point minimal sample
    max_area_scale: float = 4.0
    max_rotation_deg: float = 45.0

    def __post_init__(self) -> None:
        if self.x_alignment not in ("parallel", "hartley"):
            raise InputError(f"x_alignment: expected 'parallel' or 'hartley', got {self.x_alignment!r}")
        if not (isinstance(self.min_inliers, int) and self.min_inliers >= 0):
            raise InputError(f"min_inliers: expected an int >= 0, got {self.min_inliers!r}")
        # inf is no limit; below 1 (or 0°) every pair would be refused as DISTORTED.
        if not (isinstance(self.max_area_scale, (int, float)) and self.max_area_scale >= 1):
            raise InputError(f"max_area_scale: expected a number >= 1, got {self.max_area_scale!r}")
        if not (isinstance(self.max_rotation_deg, (int, float)) and self.max_rotation_deg > 0):
            raise InputError(f"max_rotation_deg: expected degrees > 0, got {self.max_rotation_deg!r}")


@dataclass(frozen=True)
class Rectification:
    """Rectifying homographies of each pair.

    Attributes:
        H_left: ``(B, 3, 3)``, left image pixels to rectified pixels; identity where ``status`` is not OK.
        H_right: ``(B, 3, 3)``, the same for the right image. Rectified, matching points share a row and
            ``x_left − x_right`` is the disparity (positive in front for ``"parallel"``).
        status: :class:`RectificationStatus` per pair ``(B,)`` int64.
        num_inliers: ``(B,)`` int64, inliers used (those at finite points in both views).
        epipole_left, epipole_right: ``(B, 3)`` unit homogeneous epipoles in pixels (``F e = 0``, ``e'ᵀ F = 0``;
            third entry 0 at infinity, as for a rectified rig); zeros where F has rank < 2.
        rms_row_error_px: ``(B,)``, RMS of ``y_left − y_right`` over the inliers under the returned homographies
            (pixels); 0 where a pair has no inlier.
    """

    H_left: torch.Tensor
    H_right: torch.Tensor
    status: torch.Tensor
    num_inliers: torch.Tensor
    epipole_left: torch.Tensor
    epipole_right: torch.Tensor
    rms_row_error_px: torch.Tensor


class MappedPoints(NamedTuple):
    """Points mapped by a homography: ``xy`` ``(B, K, 2)`` pixels (0 where not ``valid``) and ``valid`` ``(B, K)``
    bool, False where the point maps to or beyond the line at infinity (``w ≤ 0``)."""

    xy: torch.Tensor
    valid: torch.Tensor


def apply_homography(H: torch.Tensor, points: torch.Tensor) -> MappedPoints:
    """Map points by homographies: ``(x', y') = (H (x, y, 1)ᵀ)₁,₂ / w``.

    Args:
        H: ``(B, 3, 3)``; points: ``(B, K, 2)`` pixels.

    Returns:
        :class:`MappedPoints` in the dtype of ``points``. Differentiable w.r.t. ``H`` and ``points`` where valid;
        never divides by ``w ≤ 0``.
    """
    dims = check_shape(H, "H", ["B", 3, 3])
    check_dtype(H, "H", "float")
    check_shape(points, "points", [dims["B"], "K", 2])
    check_dtype(points, "points", "float")
    return map_points(H.to(points.dtype), points)


def map_points(H: torch.Tensor, points: torch.Tensor) -> MappedPoints:
    """``points`` ``(B, K, 2)`` through the homographies ``H`` ``(B, 3, 3)``, with where each lands in front of
    the camera (positive homogeneous w). Differentiable w.r.t. ``H`` and ``points`` where valid."""
    mapped = points @ H[:, :2, :2].transpose(1, 2) + H[:, :2, 2].unsqueeze(1)  # (B, K, 2)
    w = points @ H[:, 2, :2].unsqueeze(-1) + H[:, 2, 2].view(-1, 1, 1)  # (B, K, 1)
    valid = w > 0
    safe_w = torch.where(valid, w, torch.ones_like(w))
    xy = torch.where(valid, mapped / safe_w, torch.zeros_like(mapped))
    return MappedPoints(xy, valid.squeeze(-1))


def warp_rectified(images: torch.Tensor, homographies: torch.Tensor, mode: str = "bilinear") -> torch.Tensor:
    """Warp images ``(B, 1, H, W)`` by ``homographies`` ``(B, 3, 3)`` (original to rectified pixels) into the same
    size, zeros outside (kornia ``warp_perspective``, pixel-centre convention as OpenCV's ``warpPerspective``).
    ``mode="nearest"`` for label images, whose values must not be blended (passed as float, e.g. ``labels.double()``,
    and rounded back: an integer tensor is refused). A singular or non-finite homography gives that pair NaN (the
    pipeline passes only invertible ones). Differentiable w.r.t. the images and the homographies (bilinear), pair by
    pair where these take a gradient: batched, its sum over pixels moved with the other pairs (an audit)."""
    dims = check_image(images, "images", check_range=False)
    check_shape(homographies, "homographies", [dims["B"], 3, 3])
    check_dtype(homographies, "homographies", "float")
    if mode not in ("bilinear", "nearest"):
        raise InputError(f"mode: expected 'bilinear' or 'nearest', got {mode!r}")
    # Imported here: kornia takes 0.27 s to import, a tenth of a worker's start-up, and most batches of
    # aligned pairs (rectify="auto") never warp.
    from kornia.geometry.transform import warp_perspective
    return per_pair(lambda image, homography: warp_perspective(image, homography, (dims["H"], dims["W"]), mode=mode,
                    align_corners=True), images, homographies.to(images.dtype), split=homographies.requires_grad)


def warp_views(images: torch.Tensor, homographies: torch.Tensor) -> torch.Tensor:
    """:func:`warp_rectified` of views ``(B, 1, H, W)`` in [0, 1] (bilinear), held to [0, 1]: a blend of saturated
    pixels (1.0) can round a few ulps above 1, which every stage that takes a view refuses (a right camera 30 %
    brighter and 2 % larger than the left, clipped at white, then row-aligned and rectified, stopped the whole
    batch). Only such ulps move; differentiable as :func:`warp_rectified` inside the range."""
    return warp_rectified(images, homographies).clamp(0.0, 1.0)


def _skew(v: torch.Tensor) -> torch.Tensor:
    """``[v]ₓ`` ``(B, 3, 3)`` of ``v`` ``(B, 3)``."""
    zero = torch.zeros_like(v[:, 0])
    rows = [[zero, -v[:, 2], v[:, 1]], [v[:, 2], zero, -v[:, 0]], [-v[:, 1], v[:, 0], zero]]
    return torch.stack([torch.stack(row, -1) for row in rows], -2)


def _normalisers(image_hw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Similarities ``N`` ``(B, 3, 3)`` taking pixels to a frame centred on the image, scale ``2 / (W + H)``, their
    inverses, and the four corners ``(B, 4, 3)`` of the image (pixel centres) in that frame."""
    hw = image_hw.to(torch.float64)
    scale = 2.0 / (hw[:, 0] + hw[:, 1])
    centre = (hw.flip(-1) - 1) / 2  # (B, 2) as (cx, cy)
    b = hw.shape[0]
    forward = torch.eye(3, dtype=torch.float64, device=hw.device).repeat(b, 1, 1)
    inverse = forward.clone()
    forward[:, 0, 0] = forward[:, 1, 1] = scale
    forward[:, :2, 2] = -centre * scale.unsqueeze(-1)
    inverse[:, 0, 0] = inverse[:, 1, 1] = 1 / scale
    inverse[:, :2, 2] = centre
    half = centre * scale.unsqueeze(-1)  # (B, 2)
    signs = torch.tensor([[-1, -1], [1, -1], [-1, 1], [1, 1]], dtype=torch.float64, device=hw.device)
    corners = torch.cat([signs * half.unsqueeze(1), torch.ones(b, 4, 1, dtype=torch.float64, device=hw.device)], -1)
    return forward, inverse, corners


def _epipoles(F: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Unit right epipole ``e'`` ``(B, 3)`` (``e'ᵀ F = 0``), unit left epipole ``e`` ``(B, 3)`` (``F e = 0``), and
    ``(B,)`` bool where F has rank ≥ 2, from the adjugate ``adj F = λ e e'ᵀ`` (its rows are the cross products
    of F's columns). Smooth in F, except for which row/column is picked."""
    c0, c1, c2 = F[:, :, 0], F[:, :, 1], F[:, :, 2]
    adjugate = torch.stack([torch.linalg.cross(c1, c2), torch.linalg.cross(c2, c0), torch.linalg.cross(c0, c1)], 1)
    rank2 = adjugate.flatten(1).norm(dim=1) > _RANK_TOLERANCE * F.flatten(1).norm(dim=1) ** 2
    adjugate = torch.where(rank2.view(-1, 1, 1), adjugate, torch.eye(3, dtype=F.dtype, device=F.device))
    row = adjugate.norm(dim=2).argmax(dim=1)  # (B,)
    column = adjugate.norm(dim=1).argmax(dim=1)
    right = adjugate.gather(1, row.view(-1, 1, 1).expand(-1, 1, 3)).squeeze(1)
    left = adjugate.gather(2, column.view(-1, 1, 1).expand(-1, 3, 1)).squeeze(2)
    return right / right.norm(dim=1, keepdim=True), left / left.norm(dim=1, keepdim=True), rank2


def _right_homography(epipole: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``H' = G R`` ``(B, 3, 3)`` in the centred frame (H&Z Sec. 11.12.1), and ``(B,)`` bool where the epipole is
    off the centre (else R is undefined; such an epipole is in the image anyway).

    R rotates ``(e_x, e_y)`` onto the x axis by the smallest angle (``|θ| ≤ 90°``, the sign of ``e_x`` picks
    +x or −x), giving ``(u, 0, e_w)``; G's last row ``(−e_w / u, 0, 1)`` sends it to ``(u, 0, 0)``. An epipole
    at infinity (``e_w = 0``) gives ``G = I``.
    """
    ex, ey, ew = epipole.unbind(-1)
    norm = torch.hypot(ex, ey)
    off_centre = norm > 1e-12
    norm = torch.where(off_centre, norm, torch.ones_like(norm))
    side = torch.where(ex >= 0, 1.0, -1.0).to(epipole.dtype)
    cos, sin, u = side * ex / norm, side * ey / norm, side * norm
    zero, one = torch.zeros_like(ex), torch.ones_like(ex)
    g = -ew / u
    rows = [[cos, sin, zero], [-sin, cos, zero], [g * cos, g * sin, one]]
    return torch.stack([torch.stack(r, -1) for r in rows], -2), off_centre


def _hartley_x_row(rows_yw: torch.Tensor, H_right: torch.Tensor, left_h: torch.Tensor, right_h: torch.Tensor,
                   weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """x row ``r`` ``(B, 3)`` minimising ``Σ wᵢ (r·pᵢ / (h₂·pᵢ) − x'ᵢ)²`` — the rectified x-disparity of the
    inliers (H&Z Sec. 11.12.2) — and ``(B,)`` bool where the fit is well posed. Points ``(B, K, 3)`` homogeneous
    in the centred frame; ``weights`` ``(B, K)``."""
    w_left = left_h @ rows_yw[:, 1].unsqueeze(-1)  # (B, K, 1)
    mapped = right_h @ H_right.transpose(1, 2)  # (B, K, 3)
    usable = (weights > 0) & (w_left.squeeze(-1) > 0) & (mapped[..., 2] > 0)
    weights = torch.where(usable, weights, torch.zeros_like(weights)).unsqueeze(-1)
    design = left_h / torch.where(w_left > 0, w_left, torch.ones_like(w_left))
    target = mapped[..., :1] / torch.where(mapped[..., 2:] > 0, mapped[..., 2:], torch.ones_like(w_left))
    # Zero the unused rows, not just their weights: padding may hold anything (0 · inf is NaN).
    design = torch.where(usable.unsqueeze(-1), design, torch.zeros_like(design))
    target = torch.where(usable.unsqueeze(-1), target, torch.zeros_like(target))
    normal = design.transpose(1, 2) @ (weights * design)  # (B, 3, 3)
    rhs = design.transpose(1, 2) @ (weights * target)  # (B, 3, 1)
    eig = torch.linalg.eigvalsh(normal)
    posed = eig[:, 0] > _LSTSQ_TOLERANCE * eig[:, 2].clamp_min(torch.finfo(eig.dtype).tiny)
    eye = torch.eye(3, dtype=normal.dtype, device=normal.device)
    normal = torch.where(posed.view(-1, 1, 1), normal, eye)
    return torch.linalg.solve(normal, rhs).squeeze(-1), posed


def _left_homography(F: torch.Tensor, epipole: torch.Tensor, H_right: torch.Tensor, left_h: torch.Tensor,
                     right_h: torch.Tensor, weights: torch.Tensor,
                     x_alignment: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Left homography ``(B, 3, 3)`` in the centred frame, scaled to ``w = 1`` at the centre; ``(B,)`` bool where
    its line at infinity misses the centre, and ``(B,)`` bool where the x row is well posed."""
    # F = [e']ₓ M with M = −[e']ₓ F for a unit e' (e'ᵀF = 0); H'M's y and w rows align rows (H&Z Sec. 11.12.2).
    rows_yw = (H_right @ (-_skew(epipole) @ F))[:, 1:]  # (B, 2, 3)
    centre_w = rows_yw[:, 1, 2]
    finite = centre_w.abs() > 1e-9 * rows_yw[:, 1].norm(dim=-1)
    rows_yw = rows_yw / torch.where(finite, centre_w, torch.ones_like(centre_w)).view(-1, 1, 1)
    if x_alignment == "hartley":
        x_row, posed = _hartley_x_row(rows_yw, H_right, left_h, right_h, weights)
    else:
        # Conformal at the centre: the x gradient is the y gradient turned by −90°; x(centre) = 0 as for H'.
        h1, h2 = rows_yw[:, 0], rows_yw[:, 1]
        grad_y = h1[:, :2] - h1[:, 2:] * h2[:, :2]
        x_row = torch.stack([grad_y[:, 1], -grad_y[:, 0], torch.zeros_like(h1[:, 0])], -1)
        posed = torch.ones_like(finite)
    return torch.cat([x_row.unsqueeze(1), rows_yw], 1), finite, posed


def _shape_status(H: torch.Tensor, corners: torch.Tensor,
                  config: RectificationConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """For centred-frame homographies ``(B, 3, 3)`` (``w = 1`` at the centre): ``(B,)`` bool where ``w > 0`` at
    every corner, and ``(B,)`` bool where there is no flip, the area scale ``det H / w³`` at the corners and
    centre stays within ``[1 / max_area_scale, max_area_scale]`` and the rotation at the centre (of the image's
    y axis) within ``max_rotation_deg``."""
    w = corners @ H[:, 2].unsqueeze(-1)  # (B, 4, 1)
    split = (w <= 0).flatten(1).any(dim=1)
    w = torch.cat([torch.where(w > 0, w, torch.ones_like(w)).squeeze(-1), torch.ones_like(w[:, :1, 0])], 1)
    area = torch.linalg.det(H).unsqueeze(-1) / w ** 3  # (B, 5)
    shaped = ((area >= 1 / config.max_area_scale) & (area <= config.max_area_scale)).all(dim=1)
    grad_y = H[:, 1, :2] - H[:, 1, 2:] * H[:, 2, :2]  # ∂y'/∂(x, y) at the centre; (0, 1) when unrotated
    angle = torch.atan2(grad_y[:, 0], grad_y[:, 1]).abs().rad2deg()
    return ~split, shaped & (angle <= config.max_rotation_deg)


def _check_inputs(F: torch.Tensor, points_left: torch.Tensor, points_right: torch.Tensor, inliers: torch.Tensor,
                  image_hw: torch.Tensor | tuple[int, int], config: RectificationConfig) -> torch.Tensor:
    dims = check_shape(F, "F", ["B", 3, 3])
    check_dtype(F, "F", "float")
    for name, points in (("points_left", points_left), ("points_right", points_right)):
        check_shape(points, name, [dims["B"], "K", 2])
        check_dtype(points, name, "float")
    check_same_shape(points_left, "points_left", points_right, "points_right")
    check_shape(inliers, "inliers", [dims["B"], points_left.shape[1]])
    check_dtype(inliers, "inliers", "bool")
    check_instance(config, "config", RectificationConfig)  # another kind failed on its first field (an audit)
    if config.x_alignment not in ("parallel", "hartley"):
        raise InputError(f"x_alignment: expected 'parallel' or 'hartley', got {config.x_alignment!r}")
    if not isinstance(image_hw, torch.Tensor):
        # A float (120.5) was cut to an int, a NaN failed in torch's conversion, an int or None in len() (audits).
        if (not isinstance(image_hw, (tuple, list)) or len(image_hw) != 2
                or not all(isinstance(v, int) and not isinstance(v, bool) for v in image_hw)):
            shown = tuple(image_hw) if isinstance(image_hw, (tuple, list)) else image_hw
            raise InputError(f"image_hw: expected (height, width) as two ints or a (B, 2) int tensor, got {shown!r}")
        image_hw = torch.tensor(list(image_hw), dtype=torch.int64, device=F.device).expand(dims["B"], 2)
    # int64, the C kernel's (an int32 size ran the torch path: 1 ulp off the kernel's)
    return check_positive_hw(image_hw, dims["B"]).long()


def rectify_uncalibrated(F: torch.Tensor, points_left: torch.Tensor, points_right: torch.Tensor,
                         inliers: torch.Tensor, image_hw: torch.Tensor | tuple[int, int],
                         config: RectificationConfig = RectificationConfig()) -> Rectification:
    """Rectifying homographies of B pairs by Hartley's method (module docstring; paper Sec. 3.3).

    Args:
        F: ``(B, 3, 3)`` with ``x_rightᵀ F x_left = 0`` in pixels (``FundamentalResult.F``), any scale.
        points_left, points_right: ``(B, K, 2)`` correspondences in pixels (x = column).
        inliers: ``(B, K)`` bool (``FundamentalResult.inliers``); only these, at finite points, are used.
        image_hw: each pair's ``(height, width)``, ``(B, 2)`` int (``StereoBatch.image_hw``) or one tuple.
        config: :class:`RectificationConfig`.

    Returns:
        :class:`Rectification` in the dtype of ``F`` (computed in float64).

    Differentiable (almost everywhere) w.r.t. ``F``, and for ``"hartley"`` also w.r.t. the points; which
    adjugate row is used, the rotation's side and the status are discrete. Where no gradient is asked for, the
    ``"parallel"`` mode runs as a C kernel (``kernels/rectify_parallel.c``; this torch code is its reference): the
    same homographies to their last bits, a pair in one pass instead of about 180 small torch operations.
    """
    image_hw = _check_inputs(F, points_left, points_right, inliers, image_hw, config)
    inliers = canonical_bool(inliers)  # a mask viewed from other bytes: nonzero is True, on both paths
    inliers = inliers & torch.isfinite(points_left).all(-1) & torch.isfinite(points_right).all(-1)  # (skipped)
    if config.x_alignment == "parallel" and not (torch.is_grad_enabled() and any(
            t.requires_grad for t in (F, points_left, points_right))):
        fast = kernels.rectify_parallel(F, points_left, points_right, inliers, image_hw, config.min_inliers,
                                        config.max_area_scale, config.max_rotation_deg)
        if fast is not None:
            return Rectification(*fast)
    f64 = torch.float64
    forward, inverse, corners = _normalisers(image_hw)
    F_n = inverse.transpose(1, 2) @ F.to(f64) @ inverse  # x_rᵀ F x_l = (N x_r)ᵀ (N⁻ᵀ F N⁻¹) (N x_l)
    F_n = torch.where(torch.isfinite(F_n).flatten(1).all(dim=1).view(-1, 1, 1), F_n, 0)  # → DEGENERATE

    def centred(points: torch.Tensor) -> torch.Tensor:
        homogeneous = torch.cat([points.to(f64), torch.ones_like(points[..., :1], dtype=f64)], -1)
        return homogeneous @ forward.transpose(1, 2)

    right_epipole, left_epipole, rank2 = _epipoles(F_n)
    H_right, off_centre = _right_homography(right_epipole)
    H_left, left_finite, posed = _left_homography(F_n, right_epipole, H_right, centred(points_left),
                                                  centred(points_right), inliers.to(f64), config.x_alignment)
    unsplit_left, shaped_left = _shape_status(H_left, corners, config)
    unsplit_right, shaped_right = _shape_status(H_right, corners, config)
    num_inliers = inliers.sum(dim=1)
    status = torch.full_like(num_inliers, int(RectificationStatus.OK))
    checks = [(shaped_left & shaped_right, RectificationStatus.DISTORTED),
              (unsplit_left & unsplit_right & left_finite & off_centre, RectificationStatus.EPIPOLE_IN_IMAGE),
              (rank2 & posed, RectificationStatus.DEGENERATE),
              (num_inliers >= config.min_inliers, RectificationStatus.NOT_ENOUGH_INLIERS)]
    for passed, failure in checks:  # the last failed check wins: the most basic problem is reported
        status = torch.where(passed, status, int(failure))
    ok = (status == RectificationStatus.OK).view(-1, 1, 1)
    eye = torch.eye(3, dtype=f64, device=F.device)
    H_left = torch.where(ok, inverse @ H_left @ forward, eye).to(F.dtype)
    H_right = torch.where(ok, inverse @ H_right @ forward, eye).to(F.dtype)
    epipoles = [(inverse @ e.unsqueeze(-1)).squeeze(-1) for e in (left_epipole, right_epipole)]
    epipoles = [torch.where(rank2.unsqueeze(-1), e / e.norm(dim=-1, keepdim=True), 0).to(F.dtype) for e in epipoles]
    return Rectification(H_left, H_right, status, num_inliers, *epipoles,
                         _rms_row_error(H_left, H_right, points_left, points_right, inliers))


def _rms_row_error(H_left: torch.Tensor, H_right: torch.Tensor, points_left: torch.Tensor,
                   points_right: torch.Tensor, inliers: torch.Tensor) -> torch.Tensor:
    left = map_points(H_left, points_left.to(H_left.dtype))
    right = map_points(H_right, points_right.to(H_left.dtype))
    used = inliers & left.valid & right.valid
    error = torch.where(used, left.xy[..., 1] - right.xy[..., 1], torch.zeros_like(left.xy[..., 1]))
    count = used.sum(dim=1).clamp_min(1)  # 0 / 1 = 0 for a pair with no inlier
    return ((error ** 2).sum(dim=1) / count).sqrt()
