"""How far ahead along the floor: the distance a walker means, where the floor was found (issue 32).

Why: the paper's range ``R = f·B / d`` (Eq. 5–8) is depth along the camera's optical axis. A walker's camera is
worn on the chest and pitched down to see the floor in front of the feet (``hw.frames.WALKER_PITCH_DEG``: 20°),
so its axis runs into the floor: a point ``g`` metres ahead and ``z`` below the camera lies at depth
``g·cos θ + z·sin θ``. At 1.3 m and 20°, the foot of an obstacle 1.0 m ahead is at depth 1.38 m, and the part of
a low heap the camera sees reads 0.2–0.4 m farther than it stands: "Stop" (under 1 m) is never said of what lies
on the floor, the obstacle a walker trips on.

Where the nearness segmenter found the floor (:mod:`svs_torch.segmentation.ground_plane`), its plane in disparity
``d + doffs = a·x + b·y + c`` holds the floor's unit normal ``n`` in the camera's frame: a floor ``h`` metres below
the camera holds the points ``Z·r`` with ``Z·(n · r) = h`` for the ray ``r = ((x − cx)/f, (y − cy)/f, 1)``, so
``d + doffs = f·B / Z = (B / h)·(n_x (x − cx) + n_y (y − cy) + f·n_z)``: ``n ∝ (a, b, d₀ / f)``, ``d₀`` the
plane's ``d + doffs`` at the principal point, and ``h = B / |(a, b, d₀ / f)|``. Ahead along the floor is the
optical axis laid flat on it, ``u = normalise(ẑ − n_z·n)``, and the point at depth ``Z`` on pixel ``(x, y)``
lies ``Z·(r · u)`` ahead: the same for every point of an upright obstacle, its foot's distance. Each object's
median and percentiles are taken over those distances pixel by pixel, exactly as its depth's
(:func:`~svs_torch.depth.dense_objects.dense_object_depths` on the disparities ``d'`` with
``f·B / (d' + doffs) = Z·(r · u)``), and the nearest obstacle is the one nearest along the floor.

A pair rectified by homographies (``PipelineResult.rectified``) is measured in rectified pixels: each is taken back
to its input pixel by ``H_left⁻¹`` for its ray (the floor was fitted on the input views); the rectified depth is
read as the camera's (the rectifying homographies of a rig whose rows nearly agree are close to the identity).

Not differentiable: the floor is a constant of the hard pass, as in the segmenter that found it.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch

from ..core.checks import check_count, check_dtype, check_instance, check_real, check_shape
from ..core.errors import InputError
from ..core.kernels.checks import check_rows
from ..geometry.rectification import apply_homography
from .dense_config import DenseDisparity
from .dense_objects import dense_object_depths, surface_pixels
from .depth_types import NearestObstacle, ObjectDepths
from .sparse import nearest_obstacle

__all__ = ["FloorDistances", "FloorGeometry", "describe_floor", "floor_distances", "floor_geometry", "pitched_camera",
           "refit_floor_plane"]

#: The least ``r · u`` a pixel's ray may have: a ray nearly at right angles to the way ahead (looking straight down,
#: 87°) has almost none, and a point on it is taken at least a twentieth of its depth ahead, never at 0 or behind.
_MIN_AHEAD_PER_DEPTH = 0.05
#: The refits of the floor's plane for its geometry (:func:`refit_floor_plane`): the lower share of the rows they
#: read, and each refit's tolerance as a share of the floor rule's. Chosen on the rendered walker scenes
#: (``experiments/floor_distance.py``'s boxes and heaps, clean and at digit 4; tuning data): the mean pitch error
#: 3.1° with the floor rule's own lower 40 % and four refits at its tolerance, 1.4° so (10° pitched cameras
#: 6.8° -> 2.3°, 20° 1.1° -> 1.0°, 30° 0.9° -> 0.9°); a quarter of the rows gave 1.7°, 60 % 4.6°.
REFIT_LOWER_ROWS_FRACTION = 1 / 3
REFIT_TOLERANCE_SHARES = (1.0, 0.7, 0.5, 0.35, 0.35)
#: The refit reads the map on a grid about this many columns wide.
REFIT_GRID_COLUMNS = 160


@dataclass(frozen=True)
class FloorGeometry:
    """The camera over the floor of B pairs, from the floor's plane in disparity (module docstring).

    Attributes:
        found: ``(B,)`` bool, a floor was found (the rest are 0 where not).
        camera_height_m: ``(B,)`` the camera's height over the floor, metres.
        pitch_deg: ``(B,)`` the optical axis below the horizontal, degrees (negative: above).
        ahead: ``(B, 3)`` the unit vector ahead along the floor, in the camera's frame (x right, y down, z along
            the axis).
    """

    found: torch.Tensor
    camera_height_m: torch.Tensor
    pitch_deg: torch.Tensor
    ahead: torch.Tensor


@dataclass(frozen=True)
class FloorDistances:
    """The kept objects' distances ahead along the floor (module docstring).

    Attributes:
        floor: the :class:`FloorGeometry` they were measured with.
        objects: the pipeline's :class:`~svs_torch.depth.depth_types.ObjectDepths` with ``depth_median_m``,
            ``depth_low_m`` and ``depth_high_m`` the median and percentiles of the distances ahead, metres; an
            object is ``valid`` where its depth is and its pair's floor was found.
        nearest: the valid object nearest along the floor (its ``surface_m``: its low percentile, the part a
            walker reaches first).
        focal_px, baseline_m, doffs_px: ``(B,)`` the rigs they were measured with (what measures the same maps
            along another floor: :func:`svs_torch.pipeline.result_along_floor`).
    """

    floor: FloorGeometry
    objects: ObjectDepths
    nearest: NearestObstacle
    focal_px: torch.Tensor
    baseline_m: torch.Tensor
    doffs_px: torch.Tensor


def _check_rig(focal_px: torch.Tensor, baseline_m: torch.Tensor, doffs_px: torch.Tensor, b: int) -> None:
    """The rigs' ``focal_px``, ``baseline_m`` and ``doffs_px``, each ``(B,)`` float."""
    for name, value in (("focal_px", focal_px), ("baseline_m", baseline_m), ("doffs_px", doffs_px)):
        check_rows(value, name, b, kinds="float")


def _check_floor(floor: FloorGeometry) -> int:
    """``floor``'s fields checked (a pose made by hand, e.g. for ``result_along_floor``); returns its B. A way ahead
    that is not a unit vector where found (all zeros read every object 0.1 m ahead: a false "Stop") is refused."""
    check_instance(floor, "floor", FloorGeometry)
    b = check_rows(floor.found, "floor.found", "B", kinds="bool").shape[0]
    check_rows(floor.camera_height_m, "floor.camera_height_m", b, kinds="float")
    check_rows(floor.pitch_deg, "floor.pitch_deg", b, kinds="float")
    check_rows(floor.ahead, "floor.ahead", b, 3, kinds="float")
    norm = floor.ahead.detach().to(torch.float64).norm(dim=1)
    if not bool(((norm - 1).abs() < 1e-3)[floor.found].all()):
        raise InputError(f"floor.ahead: expected unit vectors where floor.found, got lengths "
                         f"{norm[floor.found].tolist()[:4]}")
    # Backwards or sideways read a 0.6 m object 0.03 m ahead, the same false "Stop": the optical axis laid flat
    # on a floor below a camera pitched under 90° points forward (z = cos pitch > 0).
    if not bool((floor.ahead.detach()[:, 2] > 0)[floor.found].all()):
        raise InputError(f"floor.ahead: expected a way ahead in front of the camera (z > 0) where floor.found, got "
                         f"{floor.ahead.detach()[floor.found].tolist()[:4]}")
    if not bool((floor.camera_height_m.detach() >= 0)[floor.found].all()):  # NaN fails too; 0: unknown
        raise InputError(f"floor.camera_height_m: expected heights >= 0 (0: unknown) where floor.found, got "
                         f"{floor.camera_height_m.detach()[floor.found].tolist()[:4]}")
    return b


def refit_floor_plane(disparity: torch.Tensor, on_plane: torch.Tensor, coefficients: torch.Tensor,
                      found: torch.Tensor, tolerance_px: torch.Tensor,
                      lower_rows_fraction: float = REFIT_LOWER_ROWS_FRACTION,
                      tolerance_shares: tuple[float, ...] = REFIT_TOLERANCE_SHARES) -> torch.Tensor:
    """``(B, 3)`` the floor's plane refitted for its geometry: least squares of ``d = a·x + b·y + c`` over the pixels
    ``on_plane`` ``(B, 1, H, W)`` (the found plane's, measured) of ``disparity`` in the lower ``lower_rows_fraction``
    of the rows, then again over those of them within ``share · tolerance_px`` ``(B,)`` of the last fit, once for
    each share of ``tolerance_shares`` (the last fit's is not used); ``coefficients`` ``(B, 3)`` kept where not
    ``found`` or where a fit is singular.

    Why: the plane that leaves the floor out holds, within its tolerance over the whole view, the foot of the
    obstacles standing on it and of the far wall, whose disparity the floor's reaches there; a least-squares fit
    over all of them tilts it (rendered walker scenes, ``experiments/floor_distance.py``: the camera's height off
    by 0.18 m and its pitch by 5° on average, up to 0.76 m and 19° under a camera pitched 10°). The lower rows are
    the floor in front of the feet, nearest and steepest in disparity, where few obstacles' feet lie.
    Not differentiable."""
    dims = check_shape(disparity, "disparity", ["B", 1, "H", "W"])
    check_dtype(disparity, "disparity", "float")
    check_shape(on_plane, "on_plane", list(disparity.shape))
    check_dtype(on_plane, "on_plane", "bool")
    check_rows(coefficients, "coefficients", dims["B"], 3, kinds="float")
    check_rows(found, "found", dims["B"], kinds="bool")
    check_rows(tolerance_px, "tolerance_px", dims["B"], kinds="float")
    check_real(lower_rows_fraction, "lower_rows_fraction", 0.0, 1.0, low_open=True)
    if not isinstance(tolerance_shares, tuple) or not tolerance_shares:
        raise InputError(f"tolerance_shares: expected a tuple of shares > 0, got {tolerance_shares!r}")
    for share in tolerance_shares:
        check_real(share, "tolerance_shares", 0.0, low_open=True)
    b, _, h, w = disparity.shape
    if not bool(found.any()):  # (most frames of a scene without a floor: nothing to refit)
        return coefficients
    # The lower rows only, on a grid about REFIT_GRID_COLUMNS wide: a plane needs no more (half the time).
    top, step = min(h - 1, max(0, math.ceil((1 - lower_rows_fraction) * h))), max(1, round(w / REFIT_GRID_COLUMNS))
    d = disparity.detach()[:, :, top::step, ::step].to(torch.float64)
    options = {"dtype": torch.float64, "device": d.device}
    # centred coordinates keep the normal equations well conditioned
    x = (torch.arange(0, w, step, **options) - (w - 1) / 2).view(1, 1, 1, -1)
    y = (torch.arange(top, h, step, **options) - (h - 1) / 2).view(1, 1, -1, 1)
    use = on_plane[:, :, top::step, ::step] & found.view(b, 1, 1, 1)
    plane = coefficients.detach().to(torch.float64)
    plane = torch.stack([plane[:, 0], plane[:, 1], plane[:, 2] + plane[:, 0] * (w - 1) / 2
                         + plane[:, 1] * (h - 1) / 2], 1)  # about the centre
    tolerance = tolerance_px.detach().to(torch.float64).view(b, 1, 1, 1)
    features = torch.stack(torch.broadcast_tensors(x, y, torch.ones_like(x)), -1).view(-1, 3)  # (N, 3)
    products = (features.unsqueeze(-1) * features.unsqueeze(-2)).view(-1, 9)  # each pixel's x·x, x·y, ...
    values = d.reshape(b, -1)
    for share in tolerance_shares:
        weight = use.reshape(b, -1).to(torch.float64)
        # the normal equations of d = a·x + b·y + c over the weighted pixels, as two matrix products
        solution, info = torch.linalg.solve_ex((weight @ products).view(b, 3, 3), (weight * values) @ features)
        ok = (info == 0) & (weight.sum(1) >= 3) & solution.isfinite().all(1)
        plane = torch.where(ok.view(b, 1), solution, plane)
        residual = (values - plane @ features.T).abs().view(use.shape)
        use = use & (residual <= share * tolerance)
    refit = torch.stack([plane[:, 0], plane[:, 1], plane[:, 2] - plane[:, 0] * (w - 1) / 2
                         - plane[:, 1] * (h - 1) / 2], 1).to(coefficients.dtype)
    return torch.where(found.view(b, 1), refit, coefficients)


def floor_geometry(coefficients: torch.Tensor, found: torch.Tensor, focal_px: torch.Tensor,
                   baseline_m: torch.Tensor, doffs_px: torch.Tensor, image_hw: tuple[int, int]) -> FloorGeometry:
    """The camera over the floor whose plane ``coefficients`` ``(B, 3)`` (``a, b, c`` of ``d = a·x + b·y + c`` in
    the pixels of ``image_hw``'s views, :class:`~svs_torch.segmentation.ground_plane.GroundPlane`) was ``found``
    ``(B,)``; the rigs' ``focal_px``, ``baseline_m`` and ``doffs_px`` ``(B,)`` at that size (module docstring)."""
    b = check_rows(found, "found", "B", kinds="bool").shape[0]
    check_rows(coefficients, "coefficients", b, 3, kinds="float")
    _check_rig(focal_px, baseline_m, doffs_px, b)
    if (not isinstance(image_hw, (tuple, list)) or len(image_hw) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in image_hw)):
        raise InputError(f"image_hw: expected (height, width) in pixels, two positive ints, got {image_hw!r}")
    h, w = image_hw
    plane = coefficients.detach().to(torch.float64)
    focal, baseline = focal_px.detach().to(plane).view(b), baseline_m.detach().to(plane).view(b)
    a, slope_y, c = plane.unbind(1)
    at_centre = a * (w - 1) / 2 + slope_y * (h - 1) / 2 + c + doffs_px.detach().to(plane).view(b)
    normal = torch.stack([a, slope_y, at_centre / focal.clamp_min(1e-12)], 1)
    length = normal.norm(dim=1)
    ok = found & (length > 0) & length.isfinite() & (baseline > 0) & (focal > 0)
    normal = torch.where(ok.view(b, 1), normal / length.clamp_min(1e-300).view(b, 1), normal.new_tensor([0, 1, 0.]))
    axis = normal.new_tensor([0.0, 0.0, 1.0]).expand(b, 3)
    ahead = axis - normal[:, 2:] * normal
    ahead_length = ahead.norm(dim=1)
    ok &= ahead_length > 1e-6  # a camera looking straight down has no way ahead
    ahead = torch.where(ok.view(b, 1), ahead / ahead_length.clamp_min(1e-12).view(b, 1), torch.zeros_like(ahead))
    height = torch.where(ok, baseline / length.clamp_min(1e-300), 0.0)
    pitch = torch.where(ok, torch.rad2deg(torch.asin(normal[:, 2].clamp(-1, 1))), 0.0)
    dtype = coefficients.dtype if coefficients.is_floating_point() else torch.float32
    return FloorGeometry(ok, height.to(dtype), pitch.to(dtype), ahead.to(dtype))


def describe_floor(camera_height_m: float, pitch_deg: float, obstacle: str, ahead_m: float, surface_m: float) -> str:
    """How the reports say a floor's pose and an ``obstacle``'s distance ahead along it (``estimate``'s text and
    figure title), e.g. "along the floor (the camera 1.30 m over it, pitched 19.9° down): nearest obstacle 1.15 m
    ahead, its nearest part 1.06 m"."""
    return (f"along the floor (the camera {camera_height_m:.2f} m over it, pitched {pitch_deg:.1f}° down): {obstacle} "
            f"{ahead_m:.2f} m ahead, its nearest part {surface_m:.2f} m")


def pitched_camera(pitch_deg: float, batch_size: int, device: torch.device | str = "cpu") -> FloorGeometry:
    """The pose of a camera pitched ``pitch_deg`` below the horizontal (positive: down; unrolled) over a level
    floor, for ``batch_size`` pairs: the way ahead ``(0, −sin θ, cos θ)``. Its height is unknown (0), which the
    distances ahead do not need (``guide --camera-pitch-deg``: a rig's pitch as worn, where no floor is seen)."""
    check_real(pitch_deg, "pitch_deg", -90.0, 90.0, low_open=True, high_open=True)
    check_count(batch_size, "batch_size")
    try:
        device = torch.device(device)
    except (RuntimeError, TypeError) as error:
        raise InputError(f"device: expected a torch device such as 'cpu', got {device!r} ({error})") from None
    theta = math.radians(pitch_deg)
    ahead = torch.tensor([0.0, -math.sin(theta), math.cos(theta)], device=device).expand(batch_size, 3)
    return FloorGeometry(torch.ones(batch_size, dtype=torch.bool, device=device),
                         torch.zeros(batch_size, device=device), torch.full((batch_size,), float(pitch_deg),
                                                                            device=device), ahead.contiguous())


def _ahead_per_depth(floor: FloorGeometry, focal_px: torch.Tensor, size_hw: tuple[int, int],
                     rectified: torch.Tensor, H_left: torch.Tensor) -> torch.Tensor:
    """``(B, 1, H, W)``: each map pixel's distance ahead per metre of depth, ``r · u`` (module docstring); the
    pixels of a ``rectified`` pair taken back through ``H_left`` first."""
    b = floor.found.shape[0]
    h, w = size_hw
    u = floor.ahead.to(torch.float64).view(b, 1, 1, 3)
    focal = focal_px.detach().to(torch.float64).view(b, 1, 1).clamp_min(1e-12)
    options = {"dtype": torch.float64, "device": u.device}
    xs, ys = torch.arange(w, **options).view(1, 1, w), torch.arange(h, **options).view(1, h, 1)
    if bool(rectified.any()):
        grid = torch.stack(torch.broadcast_tensors(xs, ys), -1).view(1, h * w, 2).expand(b, -1, -1)
        # inv_ex: a rectified pair's homography is invertible; a hostile one must not stop the batch here.
        back = apply_homography(torch.linalg.inv_ex(H_left.detach().to(torch.float64)).inverse, grid)
        grid = torch.where(rectified.view(b, 1, 1) & back.valid.unsqueeze(-1), back.xy.to(grid), grid)
        xs, ys = grid[..., 0].view(b, h, w), grid[..., 1].view(b, h, w)
    # r · u, affine in the pixel: (B, H, W), or a row term plus a column term where no pair is rectified
    per_depth = (u[..., 0] * (xs - (w - 1) / 2) + u[..., 1] * (ys - (h - 1) / 2)) / focal + u[..., 2]
    return per_depth.float().clamp_min(_MIN_AHEAD_PER_DEPTH).view(b, 1, h, w)


def floor_distances(floor: FloorGeometry, dense: DenseDisparity, map_labels: torch.Tensor, objects: ObjectDepths,
                    focal_px: torch.Tensor, baseline_m: torch.Tensor, doffs_px: torch.Tensor, rectified: torch.Tensor,
                    H_left: torch.Tensor, percentiles: tuple[float, float] = (10.0, 90.0),
                    fill_invalid: bool = True, surface_within_in_view_top: bool = True) -> FloorDistances:
    """The distances ahead along the ``floor`` (:func:`floor_geometry`) of ``objects`` (the pipeline's, measured
    on the ``dense`` map over ``map_labels`` ``(B, 1, H, W)`` in its pixels), for the rigs' ``focal_px``,
    ``baseline_m``, ``doffs_px`` ``(B,)``; ``rectified`` ``(B,)`` and ``H_left`` ``(B, 3, 3)``: the pairs measured
    in rectified pixels and their left homography. ``percentiles``, ``fill_invalid`` and
    ``surface_within_in_view_top``: as the depth's (``DepthConfig.object_percentiles``, ``DenseConfig.fill_invalid``,
    ``DepthConfig.surface_within_in_view_top``: the low percentile over the pixels of
    :func:`~svs_torch.depth.dense_objects.surface_pixels`, chosen on the map's own disparities). Not
    differentiable."""
    b = _check_floor(floor)
    check_instance(dense, "dense", DenseDisparity)
    check_instance(objects, "objects", ObjectDepths)
    check_shape(dense.disparity_px, "dense.disparity_px", [b, 1, "H", "W"])
    check_shape(objects.label, "objects.label", [b, "N"])
    _check_rig(focal_px, baseline_m, doffs_px, b)
    check_rows(rectified, "rectified", b, kinds="bool")
    check_shape(H_left, "H_left", [b, 3, 3])
    disparity = dense.disparity_px.detach()
    slots = torch.where(objects.valid & floor.found.view(b, 1), objects.label, torch.full_like(objects.label, -1))
    ahead = objects  # no floor, or no object ranged on it: nothing to measure (all left not valid below)
    if bool((slots > 0).any()):
        per_depth = _ahead_per_depth(floor, focal_px, tuple(disparity.shape[-2:]), rectified, H_left)
        doffs = doffs_px.detach().to(disparity.dtype).view(b, 1, 1, 1)
        # f·B / (d' + doffs) = Z · (r · u): d' + doffs = (d + doffs) / (r · u).
        ahead_disparity = (disparity + doffs) / per_depth.to(disparity.dtype) - doffs
        ahead_map = dataclasses.replace(dense, disparity_px=torch.where(dense.valid, ahead_disparity,
                                                                        torch.zeros_like(disparity)))
        surface = surface_pixels(dense) if surface_within_in_view_top else None
        with torch.no_grad():
            ahead = dense_object_depths(ahead_map, map_labels, dataclasses.replace(objects, label=slots), focal_px,
                                        baseline_m, doffs_px, percentiles, min_valid_px=1, fill_invalid=fill_invalid,
                                        surface_valid=surface)
    valid_ahead = ahead.valid & (slots > 0)

    def kept(values: torch.Tensor) -> torch.Tensor:
        return torch.where(valid_ahead, values, torch.zeros_like(values))

    ahead = dataclasses.replace(objects, depth_median_m=kept(ahead.depth_median_m), depth_low_m=kept(ahead.depth_low_m),
                                depth_high_m=kept(ahead.depth_high_m), valid=valid_ahead)
    # copies, not views of the caller's rig (a caller in inference mode gets inference tensors throughout)
    rig = [value.detach().to(disparity.dtype).reshape(b).clone() for value in (focal_px, baseline_m, doffs_px)]
    return FloorDistances(floor, ahead, nearest_obstacle(ahead), *rig)
