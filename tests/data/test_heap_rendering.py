"""Heaps on the rendered floor (svs_torch.data.heap_rendering): where the rays meet them, their truth and texture."""

from __future__ import annotations

import math

import pytest
import torch

from svs_torch import SVS_CAMERA, InputError
from svs_torch.data.heap_rendering import _field_at, make_heap_field
from svs_torch.data.synthetic import render_obstacle_scenes

SMALL = (160, 120)
HEIGHT_M, PITCH_DEG = 1.3, 25.0
HEAP = (0.1, 1.6, 0.5, 0.35)  # lateral X, ahead, radius, height (m)
ROCKS_M = 0.05


def heap_scene(seed: int = 4, heap=HEAP):
    """A box 2.6 m ahead and a heap 1.6 m ahead on the floor, a walker's camera pitched down."""
    return render_obstacle_scenes(torch.tensor([[2.6]]), torch.tensor([[[0.7, 0.0]]]), torch.tensor([[[0.6, 0.6]]]),
                                  size_wh=SMALL, floor_height_m=HEIGHT_M, camera_pitch_deg=PITCH_DEG,
                                  heaps=torch.tensor([heap]), heap_roughness_m=ROCKS_M,
                                  generator=torch.Generator().manual_seed(seed))


def floor_coordinates(scenes):
    """Every left pixel's surface point as (lateral X, distance ahead along the floor, height over it), metres,
    from the truth depth alone."""
    (w, h), theta = SMALL, math.radians(PITCH_DEG)
    f, (cx, cy) = SVS_CAMERA.focal_px(w), SVS_CAMERA.principal_point_px(w, h)
    x = torch.arange(w, dtype=torch.float32).view(1, 1, 1, w)
    y = torch.arange(h, dtype=torch.float32).view(1, 1, h, 1)
    z = scenes.depth_m
    down = (y - cy) / f
    return (z * (x - cx) / f, z * (math.cos(theta) - math.sin(theta) * down),
            HEIGHT_M - z * (down * math.cos(theta) + math.sin(theta)))


def test_the_heap_stands_on_the_floor_within_its_disc_at_its_fields_height():
    scenes = heap_scene()
    heap = scenes.heap_mask
    assert 0.05 < float(heap.float().mean()) < 0.5
    lateral, ahead, height = floor_coordinates(scenes)
    x0, f0, radius, top = HEAP
    reach = torch.hypot(lateral - x0, ahead - f0)[heap]
    assert float(reach.max()) <= radius * 1.02
    # The height over the floor at each heap pixel is the field's there (the ray stopped on the surface), a dome of
    # the heap's height with rocks on it.
    field = make_heap_field(torch.tensor([HEAP]), ROCKS_M, torch.Generator().manual_seed(4))
    assert top <= float(field.heights_m.max()) <= top + 4 * ROCKS_M
    assert float(height[heap].min()) > 0 and float(height[heap].max()) <= float(field.heights_m.max()) + 0.01
    on_field = _field_at(field, lateral, ahead)
    assert float((on_field - height)[heap].abs().max()) < 0.01
    # The floor's pixels lie on the floor, the heap hides some of it, and the heap is not a box slot.
    assert float(height[scenes.floor_mask].abs().max()) < 1e-3
    assert not bool((heap & scenes.floor_mask).any()) and not bool((scenes.object_ids[heap] != 0).any())


def test_the_heaps_texture_is_on_the_heap():
    """Both views see the same texture at the same heap point: L(x) ≈ R(x − d) over the heap."""
    scenes = heap_scene()
    right, (b, _, h, w) = scenes.batch.right, scenes.batch.right.shape
    x = torch.arange(w, dtype=right.dtype).view(1, 1, 1, w) - scenes.batch.disparity_px
    y = torch.arange(h, dtype=right.dtype).view(1, 1, h, 1).expand_as(x)
    grid = torch.stack([2 * x / (w - 1) - 1, 2 * y / (h - 1) - 1], dim=-1).squeeze(1)
    warped = torch.nn.functional.grid_sample(right, grid, mode="bilinear", align_corners=True)
    error = (scenes.batch.left - warped).abs()[scenes.heap_mask]
    unwarped = (scenes.batch.left - right).abs()[scenes.heap_mask]
    assert float(error.median()) < 0.02 and float(unwarped.median()) > 3 * float(error.median())


def test_same_seed_same_heap_and_none_without_heaps():
    first, again = heap_scene(), heap_scene()
    assert torch.equal(first.batch.left, again.batch.left) and torch.equal(first.heap_mask, again.heap_mask)
    flat = heap_scene(heap=(0.1, 1.6, 0.0, 0.35))  # radius 0: no heap
    assert not bool(flat.heap_mask.any())
    plain = render_obstacle_scenes(torch.tensor([[2.6]]), torch.tensor([[[0.7, 0.0]]]), torch.tensor([[[0.6, 0.6]]]),
                                   size_wh=SMALL, floor_height_m=HEIGHT_M, camera_pitch_deg=PITCH_DEG)
    assert plain.heap_mask is None


@pytest.mark.parametrize("kwargs,message", [
    ({"heaps": torch.tensor([list(HEAP)])}, "floor_height_m"),
    ({"floor_height_m": 1.3, "heaps": torch.tensor([[0.0, 1.0, 0.5]])}, r"heaps: expected .* shape \(1, 4\)"),
    ({"floor_height_m": 1.3, "heaps": torch.tensor([[0.0, 1.0, -0.5, 0.3]])}, "radii and heights"),
    ({"floor_height_m": 1.3, "heaps": torch.tensor([[0.0, math.nan, 0.5, 0.3]])}, "finite"),
    ({"floor_height_m": 1.3, "heaps": torch.tensor([list(HEAP)]), "heap_roughness_m": -0.1}, "heap_roughness_m"),
])
def test_heap_argument_errors(kwargs: dict, message: str) -> None:
    with pytest.raises(InputError, match=message):
        render_obstacle_scenes(torch.tensor([[2.0]]), torch.tensor([[[0.0, 0.0]]]), torch.tensor([[[0.5, 0.5]]]),
                               size_wh=SMALL, **kwargs)


@pytest.mark.parametrize("seed", range(6))
def test_marching_only_the_rays_that_can_meet_the_heap_gives_every_rays_depth(seed):
    """``heap_hits`` marches only the rows and columns where a ray can meet the heap (all of a 1280x1024 view took
    12 s); over random heaps, pitches, camera heights and an empty scene it gives exactly what marching every ray
    (``_march`` over the whole view) gives, and for the walker's heap it marches under three quarters of the view."""
    from svs_torch.data import heap_rendering

    g = torch.Generator().manual_seed(seed)
    heaps = torch.stack([torch.rand(2, generator=g) * 2 - 1, torch.rand(2, generator=g) * 3 - 0.3,
                         torch.rand(2, generator=g) * 0.6, torch.rand(2, generator=g) * 0.6], 1)
    heaps[1] *= seed % 2  # odd seeds: one scene without a heap
    field = make_heap_field(heaps, ROCKS_M, torch.Generator().manual_seed(seed))
    (w, h), f, (cx, cy) = SMALL, 150.0, (80.0, 60.0)
    x = torch.arange(w, dtype=torch.float32).view(1, 1, 1, w) + 0.25
    y = torch.arange(h, dtype=torch.float32).view(1, 1, h, 1) + 0.25
    pitch, height, camera_x = math.radians(-5 + 70 * float(torch.rand(1, generator=g))), 0.2 + 1.5 * float(
        torch.rand(1, generator=g)), 0.1075 * (seed % 2)
    marched = []
    real_march = heap_rendering._march

    def counting_march(across, *args):
        marched.append(across.numel())
        return real_march(across, *args)

    hits = heap_rendering.heap_hits(x, y, camera_x, f, (cx, cy), height, pitch, field)
    across, down = ((x - cx) / f).expand(2, 1, h, w), ((y - cy) / f).expand(2, 1, h, w)
    toward, forward = down * math.cos(pitch) + math.sin(pitch), math.cos(pitch) - math.sin(pitch) * down
    ahead0, side = field.origin_m[:, 1].view(-1, 1, 1, 1), field.side_m.view(-1, 1, 1, 1)
    reachable = forward > 1e-6
    near = torch.where(reachable, ahead0.clamp_min(0) / forward.clamp_min(1e-6), 0.0)
    far = torch.where(reachable, (ahead0 + side).clamp_min(0) / forward.clamp_min(1e-6), 0.0)
    every_ray = heap_rendering._march(across, toward, forward, near, far, reachable, camera_x, height, field)
    assert torch.equal(hits.nan_to_num(posinf=-1), every_ray.nan_to_num(posinf=-1))

    monkeypatched = pytest.MonkeyPatch()
    monkeypatched.setattr(heap_rendering, "_march", counting_march)
    try:
        walker = make_heap_field(torch.tensor([HEAP]), ROCKS_M, torch.Generator().manual_seed(seed))
        assert torch.isfinite(heap_rendering.heap_hits(x, y, 0.0, f, (cx, cy), HEIGHT_M, math.radians(PITCH_DEG),
                                                       walker)).any()
    finally:
        monkeypatched.undo()
    assert 0 < marched[0] < w * h * 3 / 4
