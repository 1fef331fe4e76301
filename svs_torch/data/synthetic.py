"""Synthetic stereo scenes with exact ground truth: textured box fronts in front of a textured wall.

The rig is the SVS model of paper Sec. 3.1: an ideal rectified parallel pair, left optical centre at X = 0,
right at X = +baseline, pinhole focal ``f = camera.focal_px(W)``, principal point at the image centre, world
axes x right, y down, z forward. A point at depth Z seen at left column x is at right column ``x − f·B/Z`` on
the same row. Obstacles are fronto-parallel rectangles (box fronts; the paper's obstacles are 1–2 m away)
in front of a background plane. Each camera is ray cast on its own with a z-buffer: occlusions are exact
in both views.

Texture lives on the surfaces in world coordinates, so a surface point has the same intensity in both views:
``L(x) ≈ R(x − d)`` up to sampling. Obstacles are bright, the wall dark, with no overlap of the two intensity
ranges, so Otsu's threshold (Sec. 3.2) separates them; the speckle and blob texture gives SURF its features.

Not meant to be differentiated: the outputs are ground-truth data, not a model, and the z-buffer and the slot
lookup are hard selections (parameters that require grad still pass a graph through the projections, piecewise).
Every random draw goes through the ``generator`` argument.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..core.camera import SVS_CAMERA, SVSCamera
from ..core.checks import InputError, check_dtype, check_float_dtype, check_generator, check_shape
from ..core.types import StereoBatch
from .heap_rendering import draw, make_heap_field
from .scene_rendering import _check_scene_size, _Scene, _cast_rays, _render_view, _surface_tiles, _visible_bboxes

__all__ = ["CAMERA_PITCH_RANGE_DEG", "WALL_DEPTH_M", "SyntheticScenes", "random_obstacle_scenes",
           "render_obstacle_scenes"]


# random_obstacle_scenes layout, as fractions of the image size: a border kept free of obstacles and a gap
# between neighbouring obstacles' sectors, so the obstacles stay separate regions in both views.
_BORDER_FRACTION = 0.03
_GAP_FRACTION = 0.02
_MIN_SECTOR_WIDTH_M = 0.1  # narrowest obstacle random_obstacle_scenes accepts to fit into a sector
#: The camera pitches (degrees down, negative: up) :func:`render_obstacle_scenes` renders; the SVS emulator's
#: ``--camera-pitch-deg`` is held to them (outside, its render thread died and the floor was never drawn).
CAMERA_PITCH_RANGE_DEG = (-30.0, 60.0)
#: The wall behind the obstacles, metres ahead: :func:`render_obstacle_scenes`' default ``background_depth_m``, which
#: the SVS emulator's frames keep (its fast renderer and its floor-height bounds read it from here).
WALL_DEPTH_M = 4.0


@dataclass(frozen=True)
class SyntheticScenes:
    """A batch of rendered stereo scenes and their exact ground truth (K object slots per scene).

    Attributes:
        batch: the pairs: left/right ``(B, 1, H, W)`` in [0, 1]; ``disparity_px`` ``(B, 1, H, W)`` of the left
            view with ``disparity_valid`` all True; ``focal_px = camera.focal_px(W)``, ``baseline_m``,
            ``doffs_px = 0``, ``calibrated`` True, names ``"synthetic-<i>"``.
        depth_m: left-view depth in metres ``(B, 1, H, W)``, at the left pixel centres.
        object_ids: ``(B, 1, H, W)`` int64, 0 for the background, k for object slot k (1-based) at that pixel.
        object_depth_m: ``(B, K)`` depth of each object's front (at its centre for a turned one), metres; 0 in padding
            slots.
        object_valid: ``(B, K)`` bool, False in padding slots (a valid object may still be fully hidden).
        object_bbox_xyxy: ``(B, K, 4)`` int64 ``x0, y0, x1, y1`` (x1, y1 exclusive) of each object's visible
            left-image pixels; zeros where none is visible.
        object_center_xy_m: ``(B, K, 2)`` centre (X, Y) in metres in the left camera frame; 0 in padding slots.
        object_size_m: ``(B, K, 2)`` width, height in metres; 0 in padding slots.
        floor_mask: ``(B, 1, H, W)`` bool, the left view's floor pixels (their ``object_ids`` are 0: the floor
            is not an obstacle); None for a scene rendered without a floor.
        heap_mask: ``(B, 1, H, W)`` bool, the left view's pixels of the heap on the floor (an obstacle outside the
            K slots: their ``object_ids`` are 0); None for scenes rendered without heaps.
    """

    batch: StereoBatch
    depth_m: torch.Tensor
    object_ids: torch.Tensor
    object_depth_m: torch.Tensor
    object_valid: torch.Tensor
    object_bbox_xyxy: torch.Tensor
    object_center_xy_m: torch.Tensor | None = None
    object_size_m: torch.Tensor | None = None
    floor_mask: torch.Tensor | None = None
    heap_mask: torch.Tensor | None = None


def _resolve_generator(generator: torch.Generator | None, device: torch.device) -> torch.Generator:
    """The caller's generator, or a fresh one with a nondeterministic seed: the global RNG is never used."""
    check_generator(generator)
    if generator is not None:
        return generator
    fresh = torch.Generator(device=device)
    fresh.seed()
    return fresh


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise InputError(message)


def _check_look_args(texture_contrast: float, floor_height_m: float | None, camera_pitch_deg: float,
                     wall_texture_contrast: float | None = None) -> None:
    """Validate :func:`render_obstacle_scenes`'s texture contrasts and floor."""
    real = (lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v))
    _require(real(texture_contrast) and texture_contrast >= 0,
             f"texture_contrast: expected a finite number >= 0, got {texture_contrast!r}")
    _require(wall_texture_contrast is None or (real(wall_texture_contrast) and wall_texture_contrast >= 0),
             f"wall_texture_contrast: expected None or a finite number >= 0, got {wall_texture_contrast!r}")
    _require(floor_height_m is None or (real(floor_height_m) and floor_height_m > 0),
             f"floor_height_m: expected None or a positive finite height in metres, got {floor_height_m!r}")
    low, high = CAMERA_PITCH_RANGE_DEG
    _require(real(camera_pitch_deg) and low <= camera_pitch_deg <= high,
             f"camera_pitch_deg: expected degrees in [{low:g}, {high:g}], got {camera_pitch_deg!r}")


def _check_heaps(heaps: torch.Tensor | None, batch_size: int, floor_height_m: float | None, roughness_m: float) -> None:
    """Validate :func:`render_obstacle_scenes`'s heaps (None: none)."""
    if heaps is None:
        return
    _require(floor_height_m is not None, "heaps: expected a floor to stand on (give floor_height_m)")
    _require(isinstance(heaps, torch.Tensor) and heaps.shape == (batch_size, 4) and heaps.is_floating_point()
             and bool(torch.isfinite(heaps).all()),
             f"heaps: expected a finite float tensor of shape ({batch_size}, 4) (x, ahead, radius, height in "
             f"metres), got {heaps.dtype if isinstance(heaps, torch.Tensor) else type(heaps).__name__} "
             f"{tuple(heaps.shape) if isinstance(heaps, torch.Tensor) else ''}")
    _require(bool((heaps[:, 2:] >= 0).all()), "heaps: expected radii and heights >= 0 metres")
    _require(isinstance(roughness_m, (int, float)) and not isinstance(roughness_m, bool) and math.isfinite(roughness_m)
             and roughness_m >= 0, f"heap_roughness_m: expected a finite height >= 0 in metres, got {roughness_m!r}")


def _check_render_args(object_depth_m: torch.Tensor, object_center_xy_m: torch.Tensor,
                       object_size_m: torch.Tensor, object_valid: torch.Tensor | None,
                       size_wh: tuple[int, int], background_depth_m: float, supersample: int,
                       noise_std: float) -> torch.Tensor:
    """Validate :func:`render_obstacle_scenes`'s arguments; returns ``object_valid`` ``(B, K)`` bool."""
    dims = check_shape(object_depth_m, "object_depth_m", ["B", "K"])
    check_dtype(object_depth_m, "object_depth_m", "float")
    for name, value in (("object_center_xy_m", object_center_xy_m), ("object_size_m", object_size_m)):
        check_shape(value, name, [dims["B"], dims["K"], 2])
        check_dtype(value, name, "float")
    if object_valid is None:
        object_valid = torch.ones_like(object_depth_m, dtype=torch.bool)
    check_shape(object_valid, "object_valid", [dims["B"], dims["K"]])
    check_dtype(object_valid, "object_valid", "bool")
    _check_scene_size(size_wh, supersample, dims["B"])
    _require(math.isfinite(background_depth_m) and background_depth_m > 0,
             f"background_depth_m: expected a positive finite depth, got {background_depth_m}")
    _require(isinstance(supersample, int) and supersample >= 1,
             f"supersample: expected an integer >= 1, got {supersample!r}")
    _require(math.isfinite(noise_std) and noise_std >= 0, f"noise_std: expected a finite value >= 0, got {noise_std}")
    # One host sync per check, once per call at the public entry (checks.py's convention).
    depth, size = object_depth_m[object_valid], object_size_m[object_valid]
    _require(bool(torch.isfinite(depth).all() & (depth > 0).all()),
             "object_depth_m: expected positive finite depths in the valid slots")
    _require(not bool((depth >= background_depth_m).any()),
             f"object_depth_m: expected depths below background_depth_m={background_depth_m}")
    _require(bool(torch.isfinite(size).all() & (size > 0).all()),
             "object_size_m: expected positive finite widths and heights in the valid slots")
    _require(bool(torch.isfinite(object_center_xy_m[object_valid]).all()),
             "object_center_xy_m: expected finite centres in the valid slots")
    return object_valid


def render_obstacle_scenes(
    object_depth_m: torch.Tensor,
    object_center_xy_m: torch.Tensor,
    object_size_m: torch.Tensor,
    object_valid: torch.Tensor | None = None,
    *,
    size_wh: tuple[int, int] = (320, 240),
    camera: SVSCamera = SVS_CAMERA,
    background_depth_m: float = WALL_DEPTH_M,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
    supersample: int = 2,
    noise_std: float = 0.0,
    texture_contrast: float = 1.0,
    wall_texture_contrast: float | None = None,
    floor_height_m: float | None = None,
    camera_pitch_deg: float = 0.0,
    heaps: torch.Tensor | None = None,
    heap_roughness_m: float = 0.05,
    object_yaw_deg: torch.Tensor | None = None,
) -> SyntheticScenes:
    """Render B stereo pairs of K bright textured rectangles in front of a dark textured wall, optionally over a
    textured floor with heaps on it.

    Args:
        object_depth_m: ``(B, K)`` depth of each rectangle, metres, below ``background_depth_m``.
        object_center_xy_m: ``(B, K, 2)`` centre (X right, Y down) in metres in the left camera frame.
        object_size_m: ``(B, K, 2)`` width and height, metres.
        object_valid: ``(B, K)`` bool, False for padding slots (not rendered); default all valid.
        size_wh: output (width, height) in pixels.
        camera: the rig (focal length in pixels, baseline).
        background_depth_m: depth of the wall, metres.
        generator: source of the textures and the noise; None draws a fresh nondeterministic seed.
        dtype: ``torch.float32`` or ``torch.float64``, the outputs' (the geometry is computed in it too).
        supersample: images shaded on a finer grid by this factor and area-averaged (truth at pixel centres).
        noise_std: standard deviation of additive gaussian sensor noise on [0, 1] intensities.
        texture_contrast: the texture amplitude as a multiple of the default (0.14 on objects, 0.10 on the wall);
            e.g. 0.3 for weakly textured real fronts (painted boards, cloth), which JPEG and noise wipe out.
        wall_texture_contrast: the wall's texture amplitude as a multiple of its default instead (None: as
            ``texture_contrast``); e.g. 0.1 for a plain painted wall, about one 8-bit level, which a camera's noise
            hides (the same random draws at any value).
        floor_height_m: the cameras' height over a textured floor, metres (None: none): a walker's view, whose
            floor ahead is the nearest surface in view and not an obstacle.
        camera_pitch_deg: the cameras pitched down by this many degrees, in [−30, 60]; it moves only the floor
            (``P · (0, cos θ, sin θ) = floor_height_m`` in the camera's frame) and the heaps.
        heaps: ``(B, 4)`` a heap on each floor: centre X, distance ahead, radius, height, metres (radius 0: none);
            a dome with rocks of ``heap_roughness_m`` on it, textured as an obstacle (:mod:`.heap_rendering`).
        heap_roughness_m: the largest height of the heaps' rocks, metres (each rock's drawn between half that and
            that), ≥ 0; 0: smooth domes.
        object_yaw_deg: ``(B, K)`` each rectangle turned about its vertical axis through its centre by this many
            degrees in [−60, 60] (positive: its right side farther), so that its depth and disparity change across
            it as a real surface's do; its width is then measured along X (as seen from above) and
            ``object_depth_m`` is its depth at its centre. None: every front faces the cameras.

    Returns:
        :class:`SyntheticScenes` on ``object_depth_m``'s device. Not meant to be differentiated (module docstring).
    """
    check_float_dtype(dtype)  # float16 failed deep in the renderer, int64 gave float32 images, a string 'no device'
    object_valid = _check_render_args(object_depth_m, object_center_xy_m, object_size_m, object_valid,
                                      tuple(size_wh), background_depth_m, supersample, noise_std)
    _check_look_args(texture_contrast, floor_height_m, camera_pitch_deg, wall_texture_contrast)
    _check_heaps(heaps, object_depth_m.shape[0], floor_height_m, heap_roughness_m)
    (width, height), device = size_wh, object_depth_m.device
    generator = _resolve_generator(generator, device)
    scene = _make_scene(object_depth_m, object_center_xy_m, object_size_m, object_valid.to(device), camera,
                        (width, height), dtype, background_depth_m, floor_height_m, camera_pitch_deg)
    if object_yaw_deg is not None:
        scene = scene._replace(slope=_front_slopes(object_yaw_deg, scene, background_depth_m))
    if heaps is not None:  # drawn before the tiles: scenes without heaps draw what they drew before
        scene = scene._replace(heap=make_heap_field(heaps.to(device, dtype), float(heap_roughness_m), generator))
    tiles = _surface_tiles(scene, camera.baseline_m, (width, height), generator, float(texture_contrast),
                           None if wall_texture_contrast is None else float(wall_texture_contrast))
    left, right = (_with_noise(_render_view(camera_x, scene, (width, height), supersample, *tiles), noise_std,
                               generator) for camera_x in (0.0, camera.baseline_m))
    return _with_ground_truth(scene, left, right, camera.baseline_m)


def _front_slopes(yaw_deg: torch.Tensor, scene: _Scene, background_depth_m: float) -> torch.Tensor:
    """``dZ/dX`` ``(B, K)`` of fronts turned by ``yaw_deg`` (0 in padding slots), after checking that each turned
    front stays between the cameras and the wall and is seen from the front by every ray of the view."""
    check_shape(yaw_deg, "object_yaw_deg", list(scene.depth_m.shape))
    check_dtype(yaw_deg, "object_yaw_deg", "float")
    yaw = yaw_deg.to(scene.depth_m.device, scene.depth_m.dtype)
    _require(bool(torch.isfinite(yaw).all()) and bool((yaw.abs() <= 60).all()),
             "object_yaw_deg: expected finite angles in [-60, 60] degrees")
    slope = torch.where(scene.valid, torch.tan(torch.deg2rad(yaw)), 0.0)
    reach = slope.abs() * scene.size_m[..., 0] / 2  # the depth change from the centre to either side
    between = (scene.depth_m - reach > 0.05) & (scene.depth_m + reach < background_depth_m)
    _require(bool((between | ~scene.valid).all()),
             f"object_yaw_deg: a turned front must stay between 0.05 m and background_depth_m={background_depth_m}")
    # The widest ray of the view, |x - cx| / f, must meet every front from its side facing the cameras.
    widest = (scene.principal_xy[0] + 1) / scene.focal_px
    _require(bool((slope.abs() * widest < 0.9).all()),
             "object_yaw_deg: a front turned this far is seen edge-on at the image border")
    return slope


def _with_noise(view: torch.Tensor, noise_std: float, generator: torch.Generator) -> torch.Tensor:
    """``view`` with additive Gaussian sensor noise of ``noise_std`` (drawn from ``generator``), held to [0, 1]."""
    if noise_std > 0:
        view = view + noise_std * draw("randn", tuple(view.shape), generator, view.dtype, view.device)
    return view.clamp(0.0, 1.0)


def _make_scene(depth_m: torch.Tensor, center_xy_m: torch.Tensor, size_m: torch.Tensor, valid: torch.Tensor,
                camera: SVSCamera, size_wh: tuple[int, int], dtype: torch.dtype, background_depth_m: float,
                floor_height_m: float | None, camera_pitch_deg: float) -> _Scene:
    """The geometry :func:`render_obstacle_scenes` casts its rays against."""
    # Padding slots get harmless geometry (never hit, but their tiles are still drawn, keeping draws fixed).
    depth = torch.where(valid, depth_m.to(dtype), 1.0)
    center = torch.where(valid.unsqueeze(-1), center_xy_m.to(valid.device, dtype), 0.0)
    size = torch.where(valid.unsqueeze(-1), size_m.to(valid.device, dtype), 1.0)
    floor = None if floor_height_m is None else float(floor_height_m)
    return _Scene(camera.focal_px(size_wh[0]), camera.principal_point_px(*size_wh), depth, center, size, valid,
                  float(background_depth_m), floor, math.radians(camera_pitch_deg))


def _with_ground_truth(scene: _Scene, left: torch.Tensor, right: torch.Tensor,
                       baseline_m: float) -> SyntheticScenes:
    """Package rendered ``left``/``right`` ``(B, 1, H, W)`` with ground truth at the left pixel centres."""
    (b, _, height, width), options = left.shape, {"dtype": left.dtype, "device": left.device}
    x_px = torch.arange(width, **options).view(1, 1, 1, -1)
    y_px = torch.arange(height, **options).view(1, 1, -1, 1)
    depth_m, object_ids = _cast_rays(x_px, y_px, 0.0, scene)
    floor_mask = heap_mask = None
    if scene.floor_height_m is not None:  # the floor is not an obstacle: id 0, as the wall
        floor_mask = object_ids == scene.floor_slot
        object_ids = object_ids.masked_fill(floor_mask, 0)
    if scene.heap is not None:  # an obstacle outside the K slots: its own mask
        heap_mask = object_ids == scene.heap_slot
        object_ids = object_ids.masked_fill(heap_mask, 0)
    focal_px = torch.full((b,), scene.focal_px, **options)
    baseline = torch.full((b,), baseline_m, **options)
    disparity = (focal_px * baseline).view(b, 1, 1, 1) / depth_m
    batch = StereoBatch.from_images(left, right, focal_px, baseline, 0.0, True, disparity,
                                    torch.ones_like(disparity, dtype=torch.bool),
                                    names=tuple(f"synthetic-{i}" for i in range(b)))
    valid, zero = scene.valid, torch.zeros((), **options)
    return SyntheticScenes(batch=batch, depth_m=depth_m, object_ids=object_ids,
                           object_depth_m=torch.where(valid, scene.depth_m, zero), object_valid=valid,
                           object_bbox_xyxy=_visible_bboxes(object_ids, valid.shape[1]),
                           object_center_xy_m=torch.where(valid.unsqueeze(-1), scene.center_xy_m, zero),
                           object_size_m=torch.where(valid.unsqueeze(-1), scene.size_m, zero), floor_mask=floor_mask,
                           heap_mask=heap_mask)


def _check_random_args(batch_size: int, num_objects: int, size_wh: tuple[int, int],
                       depth_range_m: tuple[float, float], background_depth_m: float, camera: SVSCamera,
                       supersample: object) -> None:
    """Validate :func:`random_obstacle_scenes`'s own arguments (the renderer checks the rest)."""
    _require(isinstance(batch_size, int) and batch_size >= 1,
             f"batch_size: expected an integer >= 1, got {batch_size!r}")
    _require(isinstance(num_objects, int) and num_objects >= 0,
             f"num_objects: expected an integer >= 0, got {num_objects!r}")
    _check_scene_size(size_wh, supersample, batch_size)  # before the obstacles are drawn, B of them
    _require(len(depth_range_m) == 2 and all(math.isfinite(z) for z in depth_range_m),
             f"depth_range_m: expected (near, far) in metres, got {depth_range_m!r}")
    near, far = depth_range_m
    _require(0 < near <= far, f"depth_range_m: expected 0 < near <= far, got {depth_range_m!r}")
    _require(far < background_depth_m,
             f"depth_range_m: expected far < background_depth_m={background_depth_m}, got {depth_range_m!r}")
    # The narrowest sector room is at the near depth, where the disparity is largest (_place_obstacles).
    focal = camera.focal_px(size_wh[0])
    sector = size_wh[0] * (1 - 2 * _BORDER_FRACTION) / max(num_objects, 1)
    room_m = (sector - _GAP_FRACTION * size_wh[0] - focal * camera.baseline_m / near) * near / focal
    if num_objects > 0 and room_m < _MIN_SECTOR_WIDTH_M:
        # The most that fit: each sector holds the gap, the obstacle's disparity and the narrowest obstacle.
        needed_px = _GAP_FRACTION * size_wh[0] + focal * (camera.baseline_m + _MIN_SECTOR_WIDTH_M) / near
        fit = int(size_wh[0] * (1 - 2 * _BORDER_FRACTION) // needed_px)
        raise InputError(f"num_objects: {num_objects} obstacles do not fit side by side in both views at {near} m "
                         f"and {size_wh[0]}x{size_wh[1]} (each needs {_MIN_SECTOR_WIDTH_M} m); at most {fit} fit")


def _place_obstacles(batch_size: int, num_objects: int, size_wh: tuple[int, int],
                     depth_range_m: tuple[float, float], camera: SVSCamera, generator: torch.Generator,
                     dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Random depths ``(B, K)``, centres ``(B, K, 2)`` and sizes ``(B, K, 2)`` in metres, one obstacle per sector.

    The usable width of the left image is cut into K equal sectors, left to right; obstacle k lies inside
    sector k in BOTH views (its right-view image is its left one shifted by the disparity), so obstacles
    never overlap and are fully in view. Widths are drawn in [0.3, 0.6] m and heights in [0.4, 1.0] m, then
    capped to what fits the sector and the image height at the drawn depth.
    """
    width, height = size_wh
    focal = camera.focal_px(width)
    cx, cy = camera.principal_point_px(width, height)
    near, far = depth_range_m
    u = draw("rand", (batch_size, num_objects, 5), generator, dtype)
    depth = near + (far - near) * u[..., 0]
    border_x, gap = _BORDER_FRACTION * width, _GAP_FRACTION * width
    sector = (width - 2 * border_x) / max(num_objects, 1)  # K = 0: no sectors, nothing drawn
    sector_start = -0.5 + border_x + sector * torch.arange(num_objects, dtype=dtype)  # (K,) pixel edge
    disparity = focal * camera.baseline_m / depth
    room_x = sector - gap - disparity  # (B, K) pixels the left view can use so both views fit the sector
    size_x = torch.minimum(0.3 + 0.3 * u[..., 1], room_x * depth / focal)
    start_x = sector_start + gap / 2 + disparity + (room_x - focal * size_x / depth) * u[..., 3]
    room_y = height * (1 - 2 * _BORDER_FRACTION)
    size_y = torch.minimum(0.4 + 0.6 * u[..., 2], room_y * depth / focal)
    start_y = -0.5 + _BORDER_FRACTION * height + (room_y - focal * size_y / depth) * u[..., 4]
    center_x = (start_x + focal * size_x / depth / 2 - cx) * depth / focal
    center_y = (start_y + focal * size_y / depth / 2 - cy) * depth / focal
    return depth, torch.stack([center_x, center_y], dim=-1), torch.stack([size_x, size_y], dim=-1)


def random_obstacle_scenes(
    batch_size: int,
    num_objects: int = 2,
    *,
    size_wh: tuple[int, int] = (320, 240),
    depth_range_m: tuple[float, float] = (1.0, 2.0),
    camera: SVSCamera = SVS_CAMERA,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
    **render_kwargs,
) -> SyntheticScenes:
    """B random scenes of K obstacles side by side (left to right) at depths uniform in ``depth_range_m``.

    Obstacles 1–2 m away by default, as in the paper; widths 0.3–0.6 m and heights 0.4–1.0 m (box-sized;
    capped so each obstacle fits its sector of the view, see :func:`_place_obstacles`). ``render_kwargs`` go to
    :func:`render_obstacle_scenes` (``background_depth_m``, ``supersample``, ``noise_std``, ``floor_height_m``,
    ``camera_pitch_deg``, ``object_yaw_deg``). The same generator state gives identical scenes, in float32 and float64
    alike (to float32 precision). Not differentiable.

    Raises:
        InputError: naming ``batch_size``, ``num_objects`` (too many to fit side by side at ``near``),
            ``size_wh``, ``depth_range_m`` (not ``0 < near <= far < background_depth_m``) or ``dtype``.
    """
    size_wh = tuple(size_wh)
    check_float_dtype(dtype)
    background_depth_m = render_kwargs.get("background_depth_m", WALL_DEPTH_M)
    _check_random_args(batch_size, num_objects, size_wh, tuple(depth_range_m), background_depth_m, camera,
                       render_kwargs.get("supersample", 2))
    generator = _resolve_generator(generator, torch.device("cpu"))
    depth, center, size = _place_obstacles(batch_size, num_objects, size_wh, tuple(depth_range_m), camera,
                                           generator, dtype)
    return render_obstacle_scenes(depth, center, size, size_wh=size_wh, camera=camera, generator=generator,
                                  dtype=dtype, **render_kwargs)
