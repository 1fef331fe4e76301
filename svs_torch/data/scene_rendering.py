"""The ray caster of the synthetic scenes: each pixel's ray against the scene's boxes, the back wall and, optionally,
the floor under a pitched camera (what a walker's camera sees below the horizon), the surfaces' textures (seeded
tiles of smoothed noise fixed to the surface, so both views see the same texture at the same point), the shading,
and each object's visible box.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F

from ..core.camera import MAX_SIZE_PX
from ..core.errors import InputError
from .heap_rendering import HeapField, draw, heap_hits, rays_shape

__all__ = []


# Each surface carries a periodic noise tile of G × G texels spanning a square of side max(width, height)
# (the background: its visible extent), so the texture is fixed to the surface and wraps seamlessly.
_TILE_TEXELS = 256
# Texture scales as gaussian sigmas in OUTPUT pixels at the surface's depth: a fine speckle that the
# smallest SURF scale (sigma 1.2) responds to, and coarser blobs. Fixing them in pixels keeps every surface
# equally rich in features at any depth and resolution; they are still world-fixed, since both views see a
# surface at the same depth.
_TEXTURE_SIGMA_PX = (1.2, 4.0)
_TEXTURE_GAIN = 1.5  # tanh gain on the unit-variance noise: sharpens blob edges into corners
# Intensity = mean + amplitude · tanh(...): obstacles in [0.52, 0.92], wall in [0.10, 0.40]. The gap between
# the two ranges is what makes Otsu's two classes separable, with room for some sensor noise.
_OBJECT_MEAN = (0.66, 0.78)
_OBJECT_AMPLITUDE = 0.14
_BACKGROUND_MEAN = (0.20, 0.30)
_BACKGROUND_AMPLITUDE = 0.10
# The floor: between the two, neither the brightest obstacle nor the dark wall (a grey carpet, a pavement).
_FLOOR_MEAN = (0.35, 0.55)
_FLOOR_AMPLITUDE = 0.10
# The floor's texture scale is set at this distance ahead (it recedes: finer far off, coarser near).
_FLOOR_TEXTURE_DEPTH_M = 2.0
# The floor's tile spans the floor up to a wall at most this far ahead, and wraps beyond it: its 256 texels
# spread over a deeper floor lost the fine speckle (a wall at 20 m: the near floor's x-gradients 3 times weaker
# than with one at 4 m, a floor no camera frame could match), which a real floor keeps at any depth.
_FLOOR_TILE_MAX_DEPTH_M = 4.0


class _Scene(NamedTuple):
    """Geometry shared by the ray casts of one render call (all tensors in the render dtype)."""

    focal_px: float
    principal_xy: tuple[float, float]
    depth_m: torch.Tensor  # (B, K), padding slots made harmless (depth 1, never hit)
    center_xy_m: torch.Tensor  # (B, K, 2)
    size_m: torch.Tensor  # (B, K, 2)
    valid: torch.Tensor  # (B, K) bool
    background_depth_m: float
    floor_height_m: float | None = None  # the camera's height over the floor; None: no floor
    pitch_rad: float = 0.0  # the camera pitched down by this much (the floor's plane only)
    heap: HeapField | None = None  # a heap on the floor (:mod:`.heap_rendering`); None: none
    slope: torch.Tensor | None = None  # (B, K) dZ/dX of each box front turned about its vertical axis; None: all 0

    @property
    def floor_slot(self) -> int:
        """The floor's slot in the z-buffer and the tiles: after the wall (0) and the K objects."""
        return self.depth_m.shape[1] + 1

    @property
    def heap_slot(self) -> int:
        """The heap's slot: after the floor's."""
        return self.floor_slot + 1

    def along_floor(self, depth: torch.Tensor, y_px: torch.Tensor) -> torch.Tensor:
        """The forward coordinate along the floor, metres, of the points at ``depth`` seen at rows ``y_px``."""
        cy = self.principal_xy[1]
        return depth * (math.cos(self.pitch_rad) - math.sin(self.pitch_rad) * (y_px - cy) / self.focal_px)


def _cast_rays(x_px: torch.Tensor, y_px: torch.Tensor, camera_x_m: float,
               scene: _Scene) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest surface along the ray of each pixel of a camera at ``(camera_x_m, 0, 0)`` looking down +Z.

    Args:
        x_px: pixel columns (sub-pixel allowed), broadcastable to ``(B, 1, h, w)``.
        y_px: pixel rows, broadcastable to ``(B, 1, h, w)``.
        camera_x_m: the optical centre's X in metres (0 for the left camera, the baseline for the right).
        scene: the object and background geometry.

    Returns:
        depth ``(B, 1, h, w)`` in metres of the nearest surface (exactly an object's depth or the background's)
        and its slot ``(B, 1, h, w)`` int64, 0 for the background, k for object slot k. Edges are open
        (a ray exactly on an edge misses); equal depths overlapping resolve to the lower slot.
    """
    b, k = scene.depth_m.shape
    cx, cy = scene.principal_xy
    depth = scene.depth_m.view(b, k, 1, 1)
    center = scene.center_xy_m.view(b, k, 1, 1, 2)
    if scene.slope is not None:
        # A front turned about its vertical axis: Z = Z_k + s (X − X_k). The ray X = camera_x + Z u meets it at
        # Z = (Z_k + s (camera_x − X_k)) / (1 − s u), a depth per column (B, K, 1, w).
        slope, ray_x = scene.slope.view(b, k, 1, 1), (x_px - cx) / scene.focal_px
        depth = (depth + slope * (camera_x_m - center[..., 0])) / (1 - slope * ray_x)
    # Where each ray meets object k's plane, in world metres. Rectangles are axis-aligned (a turned one as seen
    # from above), so the column test and the row test are separate: (B, K, h|1, w) and (B, K, h, w|1).
    hit_x = camera_x_m + depth * ((x_px - cx) / scene.focal_px)
    hit_y = depth * ((y_px - cy) / scene.focal_px)
    half = scene.size_m.view(b, k, 1, 1, 2) / 2
    inside_x = ((hit_x - center[..., 0]).abs() < half[..., 0]) & scene.valid.view(b, k, 1, 1)
    inside_y = (hit_y - center[..., 1]).abs() < half[..., 1]
    shape = rays_shape(b, x_px, y_px)  # (B, 1, h, w), also for K = 0
    nearest = torch.full(shape, scene.background_depth_m, dtype=depth.dtype, device=depth.device)
    slot = torch.zeros(shape, dtype=torch.int64, device=depth.device)
    # A z-buffer over the K slots (K is small; a running minimum is faster and lighter than an argmin over
    # a (B, K + 1, h, w) stack). Strict "<": on equal depths the lower slot wins.
    for i in range(k):
        closer = inside_x[:, i:i + 1] & inside_y[:, i:i + 1] & (depth[:, i:i + 1] < nearest)
        nearest = torch.where(closer, depth[:, i:i + 1], nearest)
        slot = torch.where(closer, i + 1, slot)
    if scene.floor_height_m is not None:
        # The floor: the points P with P · down = h, down = (0, cos θ, sin θ) in the camera's frame (pitched down
        # by θ). The ray (x − cx, y − cy, f) / f meets it at Z = h / (r · down) where r · down > 0 (below the
        # horizon); it shows where nearer than every box and the wall.
        toward = (y_px - cy) / scene.focal_px * math.cos(scene.pitch_rad) + math.sin(scene.pitch_rad)
        floor = scene.floor_height_m / toward.clamp_min(1e-12)
        closer = (toward > 0) & (floor < nearest)
        nearest = torch.where(closer, floor.to(nearest.dtype), nearest)
        slot = torch.where(closer, scene.floor_slot, slot)
    if scene.heap is not None:
        heap = heap_hits(x_px, y_px, camera_x_m, scene.focal_px, scene.principal_xy, scene.floor_height_m,
                         scene.pitch_rad, scene.heap)
        closer = heap < nearest
        nearest = torch.where(closer, heap.to(nearest.dtype), nearest)
        slot = torch.where(closer, scene.heap_slot, slot)
    return nearest, slot


def _make_tiles(tile_depth_m: torch.Tensor, tile_side_m: torch.Tensor, focal_px: float,
                generator: torch.Generator, contrast: float = 1.0, floor: bool = False,
                heap: bool = False, wall_contrast: float | None = None) -> torch.Tensor:
    """Periodic texture tiles ``(B, S, G, G)`` in [0, 1], slot 0 the wall, from the depth ``(B, S)`` of each
    surface (it sets the texture scale, see the module constants) and the side ``(B, S)`` in metres of the
    square each tile spans; ``contrast`` scales the texture amplitudes (the same random draws at any value), and
    ``wall_contrast`` the wall's instead where given. ``floor``: every slot is a floor's (its intensities); ``heap``:
    every slot is an obstacle's."""
    b, s = tile_depth_m.shape
    g = _TILE_TEXELS
    dtype, device = tile_depth_m.dtype, tile_depth_m.device
    noise = draw("randn", (b, s, 2, g, g), generator, dtype, device)
    level = draw("rand", (b, s), generator, dtype, device)
    sigma_px = torch.tensor(_TEXTURE_SIGMA_PX, dtype=dtype, device=device)
    texel_m = tile_side_m / g
    # Sigma in texels; capped at G/4 so the lowest frequency survives and the normalisation below is sound.
    sigma = (sigma_px * (tile_depth_m / focal_px).unsqueeze(-1) / texel_m.unsqueeze(-1)).clamp(max=g / 4)
    freq_y = torch.fft.fftfreq(g, dtype=dtype, device=device).view(g, 1)
    freq_x = torch.fft.rfftfreq(g, dtype=dtype, device=device).view(1, g // 2 + 1)
    # Gaussian blur as a product in frequency: batched over surfaces with a different sigma each.
    response = torch.exp(-2 * math.pi ** 2 * sigma.view(b, s, 2, 1, 1) ** 2 * (freq_y ** 2 + freq_x ** 2))
    field = torch.fft.irfft2(torch.fft.rfft2(noise) * response, s=(g, g))
    field = field - field.mean(dim=(-2, -1), keepdim=True)
    field = field / field.std(dim=(-2, -1), keepdim=True)
    texture = torch.tanh(_TEXTURE_GAIN * field.sum(dim=2) / math.sqrt(2))  # (B, S, G, G) in (-1, 1)
    is_object = (torch.arange(s, device=device).view(1, s) > 0) | heap
    low = torch.where(is_object, _OBJECT_MEAN[0], _BACKGROUND_MEAN[0])
    high = torch.where(is_object, _OBJECT_MEAN[1], _BACKGROUND_MEAN[1])
    wall = contrast if wall_contrast is None else wall_contrast
    amplitude = torch.where(is_object, _OBJECT_AMPLITUDE * contrast, _BACKGROUND_AMPLITUDE * wall)
    if floor:
        low, high = torch.full_like(low, _FLOOR_MEAN[0]), torch.full_like(high, _FLOOR_MEAN[1])
        amplitude = torch.full_like(amplitude, _FLOOR_AMPLITUDE * contrast)
    mean = low + (high - low) * level  # (B, S)
    return mean.view(b, s, 1, 1) + amplitude.view(1, s, 1, 1) * texture


def _surface_tiles(scene: _Scene, baseline_m: float, size_wh: tuple[int, int], generator: torch.Generator,
                   contrast: float = 1.0, wall_contrast: float | None = None
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Texture tiles ``(B, K + 1, G, G)`` of the wall (slot 0) and the objects, their centres ``(B, K + 1, 2)``
    and sides ``(B, K + 1)`` in metres. An object's tile spans max(width, height) around its centre; the wall's
    spans what either camera sees of it (the left view's extent plus the baseline).
    """
    b = scene.depth_m.shape[0]
    options = {"dtype": scene.depth_m.dtype, "device": scene.depth_m.device}
    wall_side = scene.background_depth_m * max(size_wh) / scene.focal_px + baseline_m
    wall_center = torch.tensor([baseline_m / 2, 0.0], **options).expand(b, 1, 2)
    tile_center = torch.cat([wall_center, scene.center_xy_m], dim=1)
    tile_side = torch.cat([torch.full((b, 1), wall_side, **options), scene.size_m.amax(dim=-1)], dim=1)
    tile_depth = torch.cat([torch.full((b, 1), scene.background_depth_m, **options), scene.depth_m], dim=1)
    tiles = _make_tiles(tile_depth, tile_side, scene.focal_px, generator, contrast, wall_contrast=wall_contrast)
    if scene.floor_height_m is None:
        return tiles, tile_center, tile_side
    # The floor's tile, drawn after the others (a scene's boxes and wall look the same with or without it),
    # spans the floor the cameras see up to the wall: X and the distance ahead along the floor.
    floor_depth_m = min(scene.background_depth_m, _FLOOR_TILE_MAX_DEPTH_M)
    floor_side = torch.full((b, 1), 2 * floor_depth_m + baseline_m, **options)
    floor_tile = _make_tiles(torch.full((b, 1), _FLOOR_TEXTURE_DEPTH_M, **options), floor_side, scene.focal_px,
                             generator, contrast, floor=True)
    floor_center = torch.tensor([baseline_m / 2, scene.background_depth_m], **options).expand(b, 1, 2)
    tiles, tile_center = torch.cat([tiles, floor_tile], 1), torch.cat([tile_center, floor_center], 1)
    tile_side = torch.cat([tile_side, floor_side], 1)
    if scene.heap is None:
        return tiles, tile_center, tile_side
    # The heap's tile, after the floor's: an obstacle's intensities, fixed to the floor coordinates under it (its
    # lateral X and its distance ahead), at the texture scale of its depth.
    heap_side = scene.heap.side_m.clamp_min(1e-3).view(b, 1)
    heap_center = scene.heap.origin_m.view(b, 1, 2) + heap_side.unsqueeze(-1) / 2
    heap_tile = _make_tiles(heap_center[..., 1].clamp_min(0.5), heap_side, scene.focal_px, generator, contrast,
                            heap=True)
    return (torch.cat([tiles, heap_tile], 1), torch.cat([tile_center, heap_center], 1),
            torch.cat([tile_side, heap_side], 1))


def _shade(depth: torch.Tensor, slot: torch.Tensor, x_px: torch.Tensor, y_px: torch.Tensor,
           camera_x_m: float, scene: _Scene, tiles: torch.Tensor, tile_center_xy_m: torch.Tensor,
           tile_side_m: torch.Tensor) -> torch.Tensor:
    """Intensity ``(B, 1, h, w)`` of the surfaces hit (``depth``, ``slot`` from :func:`_cast_rays`).

    The world hit point is mapped into its surface's tile (``tiles`` ``(B, S, G, G)``, centres
    ``(B, S, 2)``, sides ``(B, S)``) and sampled bilinearly with wrap-around; one gather per corner, so
    only the visible surface is sampled.
    """
    b, s, g, _ = tiles.shape
    cx, cy = scene.principal_xy
    row = g + 1
    # Per-slot affine map from (depth · ray direction) to texel-centre coordinates (texel i covers [i, i + 1)
    # of the tile scaled to G): u = Z·(x − cx)/f · G/side + ((camera_x − centre_x)·G/side + G/2 − 1/2).
    # Gathering these (B, S) tables per pixel costs fewer full-image passes than mapping world points.
    scale = g / tile_side_m
    offset = (torch.tensor([camera_x_m, 0.0], dtype=scale.dtype, device=scale.device) - tile_center_xy_m)
    offset = offset * scale.unsqueeze(-1) + (g / 2 - 0.5)  # (B, S, 2)
    first = (torch.arange(b * s, device=slot.device).view(b, s) * (row * row))  # flat index of each tile
    flat_slot = slot.flatten(1)

    def per_pixel(table: torch.Tensor) -> torch.Tensor:
        return table.gather(1, flat_slot).view_as(slot)

    scale = per_pixel(scale)
    # Wrapped into [0, G): the tiles are periodic, so surfaces larger than their tile stay seamless.
    u = torch.addcmul(per_pixel(offset[..., 0]), depth * ((x_px - cx) / scene.focal_px), scale).remainder(g)
    down = depth * ((y_px - cy) / scene.focal_px)
    if scene.floor_height_m is not None:  # the floor's (and a heap's) second coordinate: the distance ahead along it
        down = torch.where(slot >= scene.floor_slot, scene.along_floor(depth, y_px), down)
    v = torch.addcmul(per_pixel(offset[..., 1]), down, scale).remainder(g)
    # Rounding can give exactly G; the clamp keeps the corner inside. The tiles get a wrapped extra row and
    # column so the +1 neighbours need no integer modulo (which is slow on CPU).
    u0, v0 = u.floor().clamp(max=g - 1), v.floor().clamp(max=g - 1)
    fu, fv = u - u0, v - v0
    padded = torch.cat([tiles, tiles[..., :1, :]], dim=-2)
    padded = torch.cat([padded, padded[..., :1]], dim=-1).reshape(-1)  # (B·S·(G+1)²,)
    corner = per_pixel(first) + (v0 * row + u0).long()  # exact: below 2^24 even in float32
    # The other corners via shifted views of the flat tiles rather than three more index tensors.
    top = torch.lerp(padded.take(corner), padded[1:].take(corner), fu)
    bottom = torch.lerp(padded[row:].take(corner), padded[row + 1:].take(corner), fu)
    return torch.lerp(top, bottom, fv)


#: The most samples a batch's view is shaded at (B · W·s · H·s): 2^30, 4 GiB a float32 buffer, of which the ray caster
#: holds several at once. 3,495 pairs of 320x240 at the default supersample 2; one pair of 8192x8192 (--size's
#: largest side) at 2. Past it a request is refused by name, not an allocation failing deep in torch or, within what
#: the kernel over-commits, a process the OOM killer ends.
MAX_SHADED_SAMPLES = 2**30


def _check_scene_size(size_wh: tuple, supersample: object, batch_size: int) -> None:
    """InputError naming ``size_wh`` (sides from 1 to ``MAX_SIZE_PX``) or the request (``batch_size`` views of
    ``size_wh`` shaded ``supersample`` times finer) past :data:`MAX_SHADED_SAMPLES`."""
    if not (len(size_wh) == 2 and all(isinstance(n, int) and 0 < n <= MAX_SIZE_PX for n in size_wh)):
        raise InputError(f"size_wh: expected a (width, height) in pixels from 1 to {MAX_SIZE_PX}, got {size_wh!r}")
    if isinstance(supersample, int) and batch_size * size_wh[0] * size_wh[1] * supersample**2 > MAX_SHADED_SAMPLES:
        raise InputError(f"batch_size, size_wh, supersample: {batch_size} views of {size_wh[0]}x{size_wh[1]} shaded "
                         f"{supersample}x finer is more than the {MAX_SHADED_SAMPLES} samples rendered at once; "
                         "render fewer scenes a call")


def _render_view(camera_x_m: float, scene: _Scene, size_wh: tuple[int, int], supersample: int,
                 tiles: torch.Tensor, tile_center_xy_m: torch.Tensor, tile_side_m: torch.Tensor) -> torch.Tensor:
    """One camera's image ``(B, 1, H, W)``: shade an s× finer grid, then average each s × s block."""
    width, height = size_wh
    dtype, device = scene.depth_m.dtype, scene.depth_m.device
    # Sub-pixel sample centres of output pixel i: (j + 0.5) / s − 0.5 for the s samples j inside it.
    x_px = ((torch.arange(width * supersample, dtype=dtype, device=device) + 0.5) / supersample - 0.5)
    y_px = ((torch.arange(height * supersample, dtype=dtype, device=device) + 0.5) / supersample - 0.5)
    x_px, y_px = x_px.view(1, 1, 1, -1), y_px.view(1, 1, -1, 1)
    depth, slot = _cast_rays(x_px, y_px, camera_x_m, scene)
    image = _shade(depth, slot, x_px, y_px, camera_x_m, scene, tiles, tile_center_xy_m, tile_side_m)
    return F.avg_pool2d(image, supersample) if supersample > 1 else image


def _visible_bboxes(object_ids: torch.Tensor, num_objects: int) -> torch.Tensor:
    """``(B, K, 4)`` int64 ``x0, y0, x1, y1`` (exclusive ends) of labels 1..K in ``object_ids``; 0 if absent."""
    b, _, h, w = object_ids.shape
    labels = torch.arange(1, num_objects + 1, device=object_ids.device).view(1, num_objects, 1, 1)
    mask = object_ids == labels  # (B, K, H, W)

    def span(present: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        index = torch.arange(n, device=present.device)
        first = torch.where(present, index, n).amin(dim=-1)
        last = torch.where(present, index, -1).amax(dim=-1) + 1
        seen = present.any(dim=-1)
        return torch.where(seen, first, 0), torch.where(seen, last, 0)

    x0, x1 = span(mask.any(dim=2), w)
    y0, y1 = span(mask.any(dim=3), h)
    return torch.stack([x0, y0, x1, y1], dim=-1)
