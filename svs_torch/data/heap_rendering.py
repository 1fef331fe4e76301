"""Heaps on the rendered floor: continuous rough surfaces (a pile of rocks, a heap of cloth or rubble) that rise from
the floor a walker's camera sees, drawn by marching each pixel's ray through a height field.

Why: the floor rule (:mod:`svs_torch.segmentation.ground_plane`) fits a plane to the nearness map and leaves out
what lies on it. The renderer's boxes face the camera, so a heap of them is a staircase of fronts that no plane
holds; a rock pile or draped cloth is one continuous surface, rough at the scale of its rocks, and a plane fitted to
its upper side holds much of it within a pixel of disparity (experiments/walker_floor.md). These heaps are tuning
data for that case.

The height field is a dome of the heap's height over its radius, plus rocks (Gaussian bumps of a few centimetres at
random places on it), sampled on a square grid over the floor (its lateral X and its distance ahead along the
floor, both in metres) and read bilinearly. A ray meets it where its height over the floor first falls below the
field's: found by stepping through the heap's extent ahead and refining by bisection. Not differentiable.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F

__all__ = ["WALKER_HEAP_HEIGHT_M", "WALKER_HEAP_RADIUS_M"]

#: A heap of rocks beside a walker's path, radius and height in metres: the "walker" heaps of
#: experiments/walker_heaps.py and the one the device emulator draws on its floor (``hw.frames.ObstacleTrack``).
WALKER_HEAP_RADIUS_M, WALKER_HEAP_HEIGHT_M = 0.45, 0.35

#: Height-field samples per side, ray steps through the heap's extent ahead, and bisection refinements.
_GRID, _STEPS, _BISECTIONS = 128, 64, 8
#: Rocks per heap, and their radii as shares of the heap's radius.
_ROCKS, _ROCK_RADIUS_SHARE = 48, (0.06, 0.16)
#: A ray's hit counts as the heap's where the field stands at least this high (metres); lower, it is the floor.
_MIN_HEIGHT_M = 0.003


def draw(kind: str, shape: tuple[int, ...], generator: torch.Generator, dtype: torch.dtype,
         device: torch.device | None = None) -> torch.Tensor:
    """Uniform [0, 1) (``kind="rand"``) or standard normal (``"randn"``) numbers drawn in float32 and returned in
    ``dtype``: a float64 draw reads other bits of the generator, so the same seed gave another scene in float64 (a
    gradcheck's) than in float32. Every random draw of the rendered scenes goes through it."""
    sample = torch.rand if kind == "rand" else torch.randn
    return sample(shape, generator=generator, dtype=torch.float32, device=device).to(dtype)


class HeapField(NamedTuple):
    """Each scene's height field (B heaps, at most one a scene).

    Attributes:
        heights_m: ``(B, 1, G, G)`` the height over the floor, metres; rows run ahead, columns lateral.
        origin_m: ``(B, 2)`` the grid's corner: lateral X and distance ahead, metres.
        side_m: ``(B,)`` the grid's side, metres (0: no heap in that scene).
    """

    heights_m: torch.Tensor
    origin_m: torch.Tensor
    side_m: torch.Tensor


def make_heap_field(heaps: torch.Tensor, roughness_m: float, generator: torch.Generator) -> HeapField:
    """The height fields of ``heaps`` ``(B, 4)``: centre X, centre distance ahead, radius and height, metres (a
    radius of 0: none), with rocks of ``roughness_m`` high drawn from ``generator``."""
    b = heaps.shape[0]
    options = {"dtype": heaps.dtype, "device": heaps.device}
    centre, radius, height = heaps[:, :2], heaps[:, 2], heaps[:, 3]
    side = 2.2 * radius
    cells = (torch.arange(_GRID, **options) + 0.5) / _GRID - 0.5  # grid cell centres in units of the side
    lateral = cells.view(1, 1, -1) * side.view(b, 1, 1)
    ahead = cells.view(1, -1, 1) * side.view(b, 1, 1)
    share = (lateral ** 2 + ahead ** 2) / radius.clamp_min(1e-9).view(b, 1, 1) ** 2
    dome = height.view(b, 1, 1) * (1 - share).clamp_min(0) ** 0.75
    # Rocks: uniform over the heap's disc, their radii and heights drawn, each a Gaussian bump.
    angle = draw("rand", (b, _ROCKS), generator, **options) * (2 * math.pi)
    reach = draw("rand", (b, _ROCKS), generator, **options).sqrt() * radius.view(b, 1)
    low, high = _ROCK_RADIUS_SHARE
    size = (low + (high - low) * draw("rand", (b, _ROCKS), generator, **options)) * radius.view(b, 1)
    rise = roughness_m * (0.5 + 0.5 * draw("rand", (b, _ROCKS), generator, **options))
    dx = lateral.unsqueeze(-1) - (reach * angle.cos()).view(b, 1, 1, -1)
    dy = ahead.unsqueeze(-1) - (reach * angle.sin()).view(b, 1, 1, -1)
    rocks = (rise.view(b, 1, 1, -1) * torch.exp(-(dx ** 2 + dy ** 2) / (2 * size.view(b, 1, 1, -1) ** 2))).sum(-1)
    field = torch.where(share < 1, dome + rocks, torch.zeros_like(dome))
    origin = centre - side.unsqueeze(-1) / 2
    return HeapField(field.unsqueeze(1), origin, torch.where(radius > 0, side, torch.zeros_like(side)))


def _field_at(heap: HeapField, lateral_m: torch.Tensor, ahead_m: torch.Tensor) -> torch.Tensor:
    """The field's height ``(B, 1, h, w)`` at floor points ``(B, 1, h, w)`` (0 outside the grid)."""
    side = heap.side_m.clamp_min(1e-9).view(-1, 1, 1, 1)
    u = (lateral_m - heap.origin_m[:, 0].view(-1, 1, 1, 1)) / side * 2 - 1
    v = (ahead_m - heap.origin_m[:, 1].view(-1, 1, 1, 1)) / side * 2 - 1
    grid = torch.stack([u[:, 0], v[:, 0]], -1)  # (B, h, w, 2): x along the columns (lateral), y along the rows
    return F.grid_sample(heap.heights_m, grid, mode="bilinear", padding_mode="zeros", align_corners=False)


def rays_shape(batch_size: int, x_px: torch.Tensor, y_px: torch.Tensor) -> tuple[int, int, int, int]:
    """``(B, 1, h, w)``: the rays of pixel columns ``x_px`` and rows ``y_px`` broadcast together.

    By ``torch.broadcast_tensors`` (views, no copy), not ``torch.broadcast_shapes``: in torch 2.13 that imports
    ``torch._refs`` and with it sympy on its first call, 0.6–1.2 s of the demo's whole process."""
    return (batch_size, 1, *torch.broadcast_tensors(x_px, y_px)[0].shape[-2:])


def heap_hits(x_px: torch.Tensor, y_px: torch.Tensor, camera_x_m: float, focal_px: float,
              principal_xy: tuple[float, float], floor_height_m: float, pitch_rad: float,
              heap: HeapField) -> torch.Tensor:
    """The depth ``(B, 1, h, w)`` (metres, along the optical axis) where each pixel's ray first meets the heap, +inf
    where it does not, for a camera at ``(camera_x_m, 0, 0)`` ``floor_height_m`` over the floor, pitched down by
    ``pitch_rad`` (:func:`svs_torch.data.scene_rendering._cast_rays`' conventions).

    Only the rows and columns holding a ray that can meet the heap are marched: a ray whose stretch over the heap's
    extent ahead passes beside its grid, stays above its highest point or is under the floor already cannot. The
    heap is a small part of the view, and marching every ray of a 1280x1024 frame took 12 s a view; the rays
    marched give the same depths."""
    cx, cy = principal_xy
    b = heap.side_m.shape[0]
    shape = rays_shape(b, x_px, y_px)
    across, down = ((x_px - cx) / focal_px).expand(shape), ((y_px - cy) / focal_px).expand(shape)
    toward = down * math.cos(pitch_rad) + math.sin(pitch_rad)  # the ray's fall towards the floor per metre of depth
    forward = math.cos(pitch_rad) - math.sin(pitch_rad) * down  # its distance ahead along the floor per metre
    ahead0, side = heap.origin_m[:, 1].view(-1, 1, 1, 1), heap.side_m.view(-1, 1, 1, 1)
    reachable = forward > 1e-6
    near = torch.where(reachable, ahead0.clamp_min(0) / forward.clamp_min(1e-6), 0.0)
    far = torch.where(reachable, (ahead0 + side).clamp_min(0) / forward.clamp_min(1e-6), 0.0)
    # Where a ray can meet the heap: its lateral reach over [near, far] overlaps the grid (a cell's margin for the
    # bilinear read), and its lowest point there is no higher than the field's highest.
    margin, x0 = side / _GRID, heap.origin_m[:, 0].view(-1, 1, 1, 1)
    lateral_near, lateral_far = camera_x_m + near * across, camera_x_m + far * across
    beside = (torch.maximum(lateral_near, lateral_far) < x0 - margin) | \
        (torch.minimum(lateral_near, lateral_far) > x0 + side + margin)
    # A ray already under the floor where it enters the extent (the heap wholly ahead of the camera) crosses the
    # field at the first step and is refined to within 1/63 of the side from the grid's edge, where the field is 0
    # (the heap's disc keeps 0.1 radius, 4.5 % of the side, from it): no hit either.
    entering, leaving = floor_height_m - near * toward, floor_height_m - far * toward
    above = torch.minimum(entering, leaving) > heap.heights_m.amax(dim=(1, 2, 3)).view(-1, 1, 1, 1)
    under = (entering <= 0) & (ahead0 > 0)
    can_meet = (reachable & (side > 0) & ~beside & ~above & ~under).flatten(0, 1).any(0)  # (h, w)
    hits = torch.full(shape, math.inf, dtype=near.dtype, device=near.device)
    rows, columns = can_meet.any(1).nonzero().flatten(), can_meet.any(0).nonzero().flatten()
    if rows.numel():
        window = (..., slice(int(rows[0]), int(rows[-1]) + 1), slice(int(columns[0]), int(columns[-1]) + 1))
        hits[window] = _march(across[window], toward[window], forward[window], near[window], far[window],
                              reachable[window], camera_x_m, floor_height_m, heap)
    return hits


def _march(across: torch.Tensor, toward: torch.Tensor, forward: torch.Tensor, near: torch.Tensor, far: torch.Tensor,
           reachable: torch.Tensor, camera_x_m: float, floor_height_m: float, heap: HeapField) -> torch.Tensor:
    """:func:`heap_hits` for the rays ``(B, 1, h, w)`` of a window: each one's lateral and downward slope
    (``across``, ``toward``), its distance ahead per metre of depth (``forward``) and the depths where it enters and
    leaves the heap's extent ahead (``near``, ``far``), stepped through and refined by bisection."""
    side = heap.side_m.view(-1, 1, 1, 1)

    def gap(depth: torch.Tensor) -> torch.Tensor:  # the ray's height over the floor minus the field's
        return (floor_height_m - depth * toward) - _field_at(heap, camera_x_m + depth * across, depth * forward)

    found = torch.zeros(near.shape, dtype=torch.bool, device=near.device)
    before, after = near.clone(), far.clone()
    previous = near
    for step in range(1, _STEPS):
        depth = near + (far - near) * (step / (_STEPS - 1))
        crossed = ~found & (gap(depth) <= 0)
        before, after = torch.where(crossed, previous, before), torch.where(crossed, depth, after)
        found |= crossed
        previous = depth
    for _ in range(_BISECTIONS):
        middle = (before + after) / 2
        below = gap(middle) <= 0
        before, after = torch.where(below, before, middle), torch.where(below, middle, after)
    height = _field_at(heap, camera_x_m + after * across, after * forward)
    hit = found & reachable & (side > 0) & (height >= _MIN_HEIGHT_M)
    return torch.where(hit, after, torch.full_like(after, math.inf))
