"""Tests for synthetic stereo scenes: shapes, determinism, exact geometry, photometric consistency, Otsu.

The geometric references here are written independently of the renderer (closed-form projections of the
rectangles and an explicit occlusion test along the right camera's ray); Otsu's threshold is OpenCV's.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from svs_torch import SVS_CAMERA, InputError, StereoBatch
from svs_torch.data.scene_rendering import _cast_rays, _Scene
from svs_torch.data.synthetic import SyntheticScenes, random_obstacle_scenes, render_obstacle_scenes

SMALL = (160, 120)


def seeded(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def scene_tensors(scenes: SyntheticScenes) -> dict[str, torch.Tensor]:
    """Every tensor of a result, by name, for equality checks."""
    batch = scenes.batch
    return {
        "left": batch.left, "right": batch.right, "disparity": batch.disparity_px, "depth": scenes.depth_m,
        "ids": scenes.object_ids, "object_depth": scenes.object_depth_m, "bbox": scenes.object_bbox_xyxy,
        "center": scenes.object_center_xy_m, "size": scenes.object_size_m,
    }


def pixel_world_points(scenes: SyntheticScenes) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """World X, Y, Z ``(B, 1, H, W)`` of the surface seen at each left pixel centre."""
    _, _, h, w = scenes.depth_m.shape
    f = scenes.batch.focal_px.view(-1, 1, 1, 1)
    x = torch.arange(w, dtype=f.dtype).view(1, 1, 1, w)
    y = torch.arange(h, dtype=f.dtype).view(1, 1, h, 1)
    z = scenes.depth_m
    return z * (x - (w - 1) / 2) / f, z * (y - (h - 1) / 2) / f, z


def occluded_in_right(scenes: SyntheticScenes) -> tuple[torch.Tensor, torch.Tensor]:
    """Independent occlusion test: is the left pixel's surface point hidden from the right camera?

    The right ray from (B, 0, 0) to the point P meets the plane Z = Z_j at X = B + (P_x − B)·Z_j/P_z,
    Y = P_y·Z_j/P_z; P is hidden if a nearer valid rectangle contains that point. Returns the mask
    ``(B, 1, H, W)`` and the nearest occluder's 1-based id (0 if none).
    """
    px, py, pz = pixel_world_points(scenes)
    baseline = scenes.batch.baseline_m.view(-1, 1, 1, 1)
    occluder = torch.zeros_like(scenes.object_ids)
    nearest = pz.clone()
    for j in range(scenes.object_depth_m.shape[1]):
        zj = scenes.object_depth_m[:, j].view(-1, 1, 1, 1)
        cx, cy = (scenes.object_center_xy_m[:, j, i].view(-1, 1, 1, 1) for i in range(2))
        w, h = (scenes.object_size_m[:, j, i].view(-1, 1, 1, 1) for i in range(2))
        xj = baseline + (px - baseline) * zj / pz
        yj = py * zj / pz
        hit = ((xj - cx).abs() < w / 2) & ((yj - cy).abs() < h / 2) & scenes.object_valid[:, j].view(-1, 1, 1, 1)
        hit = hit & (zj < nearest)
        nearest = torch.where(hit, zj, nearest)
        occluder = torch.where(hit, j + 1, occluder)
    return occluder > 0, occluder


def sample_right_at(scenes: SyntheticScenes, disparity: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """R(x − d) sampled bilinearly with grid_sample, and where x − d is inside the right image."""
    right = scenes.batch.right
    b, _, h, w = right.shape
    x = torch.arange(w, dtype=right.dtype).view(1, 1, 1, w) - disparity
    y = torch.arange(h, dtype=right.dtype).view(1, 1, h, 1).expand_as(x)
    grid = torch.stack([2 * x / (w - 1) - 1, 2 * y / (h - 1) - 1], dim=-1).squeeze(1)  # (B, H, W, 2)
    sampled = F.grid_sample(right, grid, mode="bilinear", align_corners=True)
    return sampled, (x >= 0) & (x <= w - 1)


@pytest.fixture(scope="module")
def scenes64() -> SyntheticScenes:
    return random_obstacle_scenes(4, size_wh=(320, 240), generator=seeded(7), dtype=torch.float64)


@pytest.mark.parametrize("batch_size", [1, 4])
def test_shapes_and_dtypes(batch_size: int, dtype: torch.dtype) -> None:
    scenes = random_obstacle_scenes(batch_size, 2, size_wh=SMALL, generator=seeded(0), dtype=dtype)
    batch = scenes.batch
    assert isinstance(batch, StereoBatch)
    for image in (batch.left, batch.right, batch.disparity_px, scenes.depth_m):
        assert image.shape == (batch_size, 1, 120, 160) and image.dtype == dtype
    assert batch.left.min() >= 0 and batch.left.max() <= 1 and batch.right.min() >= 0 and batch.right.max() <= 1
    assert batch.disparity_valid.dtype == torch.bool and bool(batch.disparity_valid.all())
    assert scenes.object_ids.shape == (batch_size, 1, 120, 160) and scenes.object_ids.dtype == torch.int64
    assert scenes.object_depth_m.shape == (batch_size, 2) and scenes.object_depth_m.dtype == dtype
    assert scenes.object_valid.shape == (batch_size, 2) and scenes.object_valid.dtype == torch.bool
    assert scenes.object_bbox_xyxy.shape == (batch_size, 2, 4) and scenes.object_bbox_xyxy.dtype == torch.int64
    assert torch.equal(batch.focal_px, torch.full((batch_size,), SVS_CAMERA.focal_px(160), dtype=dtype))
    assert torch.equal(batch.baseline_m, torch.full((batch_size,), SVS_CAMERA.baseline_m, dtype=dtype))
    assert bool((batch.doffs_px == 0).all()) and bool(batch.calibrated.all())
    assert batch.image_hw.tolist() == [[120, 160]] * batch_size
    assert batch.names == tuple(f"synthetic-{i}" for i in range(batch_size))
    assert bool(((scenes.object_depth_m >= 1.0) & (scenes.object_depth_m <= 2.0)).all())


def test_no_objects_is_all_background() -> None:
    scenes = random_obstacle_scenes(2, 0, size_wh=SMALL, generator=seeded(0), background_depth_m=3.0)
    assert scenes.object_depth_m.shape == (2, 0) and scenes.object_bbox_xyxy.shape == (2, 0, 4)
    assert bool((scenes.object_ids == 0).all()) and bool((scenes.depth_m == 3.0).all())


def test_same_seed_same_scenes_and_global_rng_untouched() -> None:
    state = torch.get_rng_state()
    first = scene_tensors(random_obstacle_scenes(3, size_wh=SMALL, generator=seeded(5), noise_std=0.01))
    second = scene_tensors(random_obstacle_scenes(3, size_wh=SMALL, generator=seeded(5), noise_std=0.01))
    other = scene_tensors(random_obstacle_scenes(3, size_wh=SMALL, generator=seeded(6), noise_std=0.01))
    random_obstacle_scenes(1, size_wh=SMALL)  # generator=None draws its own seed, not the global RNG
    assert torch.equal(torch.get_rng_state(), state)
    for name in first:
        assert torch.equal(first[name], second[name]), name
    assert not torch.equal(first["left"], other["left"]) and not torch.equal(first["depth"], other["depth"])


def test_the_same_seed_gives_the_same_scene_in_float64() -> None:
    """A float64 scene (a gradcheck's) is the float32 one at more precision, not another scene: the draws were
    taken in the output dtype, which reads other bits of the generator (1.034 and 1.608 m against 1.004 and
    1.060 m for one seed)."""
    kwargs = {"size_wh": SMALL, "noise_std": 0.01, "floor_height_m": 1.2,
              "heaps": torch.tensor([[0.0, 1.5, 0.3, 0.2], [0.0, 0.0, 0.0, 0.0]]), "heap_roughness_m": 0.02}
    single = scene_tensors(random_obstacle_scenes(2, generator=seeded(3), **kwargs))
    double = scene_tensors(random_obstacle_scenes(2, generator=seeded(3), dtype=torch.float64, **kwargs))
    for name, value in single.items():
        assert double[name].dtype == (torch.float64 if value.is_floating_point() else value.dtype), name
        if value.is_floating_point():
            assert torch.allclose(double[name].float(), value, rtol=0, atol=1e-5), name
        else:
            assert torch.equal(double[name], value), name


def test_disparity_is_focal_times_baseline_over_depth(dtype: torch.dtype) -> None:
    scenes = random_obstacle_scenes(2, size_wh=SMALL, generator=seeded(1), dtype=dtype)
    batch = scenes.batch
    expected = (batch.focal_px * batch.baseline_m).view(-1, 1, 1, 1) / scenes.depth_m
    assert torch.equal(batch.disparity_px, expected)
    depth, valid = batch.ground_truth_depth_m()
    assert bool(valid.all())
    torch.testing.assert_close(depth, scenes.depth_m)


def test_object_ids_agree_with_depths(scenes64: SyntheticScenes) -> None:
    depth, ids = scenes64.depth_m, scenes64.object_ids
    assert bool((depth[ids == 0] == 4.0).all())
    for b in range(ids.shape[0]):
        for k in range(scenes64.object_depth_m.shape[1]):
            mask = ids[b] == k + 1
            assert mask.sum() > 100  # random obstacles are side by side, each fully in view
            assert bool((depth[b][mask] == scenes64.object_depth_m[b, k]).all())


def test_bboxes_agree_with_object_ids(scenes64: SyntheticScenes) -> None:
    ids = scenes64.object_ids
    for b in range(ids.shape[0]):
        for k in range(scenes64.object_depth_m.shape[1]):
            rows, cols = (ids[b, 0] == k + 1).nonzero(as_tuple=True)
            expected = [cols.min(), rows.min(), cols.max() + 1, rows.max() + 1]
            assert scenes64.object_bbox_xyxy[b, k].tolist() == [int(v) for v in expected]


def test_explicit_scene_projection_and_occlusion() -> None:
    """A far box half hidden by a near one; boxes' pixel spans from the pinhole projection in closed form."""
    w, h = 320, 240
    f = SVS_CAMERA.focal_px(w)
    depth = torch.tensor([[1.8, 1.2, 1.5]], dtype=torch.float64)
    center = torch.tensor([[[0.0, 0.0], [-0.2, 0.05], [0.3, 0.0]]], dtype=torch.float64)
    size = torch.tensor([[[0.6, 0.5], [0.3, 0.3], [0.2, 0.2]]], dtype=torch.float64)
    valid = torch.tensor([[True, True, False]])  # slot 3 is padding: never drawn
    scenes = render_obstacle_scenes(depth, center, size, valid, size_wh=(w, h), generator=seeded(0),
                                    dtype=torch.float64)

    def span(c: float, half: float, z: float, centre_px: float) -> tuple[int, int]:
        # Pixel i is inside where |z·(i − centre_px)/f − c| < half: i in the open interval below.
        low, high = centre_px + f * (c - half) / z, centre_px + f * (c + half) / z
        return int(np.floor(low)) + 1, int(np.ceil(high))

    x0, x1 = span(-0.2, 0.15, 1.2, (w - 1) / 2)
    y0, y1 = span(0.05, 0.15, 1.2, (h - 1) / 2)
    assert scenes.object_bbox_xyxy[0, 1].tolist() == [x0, y0, x1, y1]
    assert bool((scenes.object_ids[0, 0, y0:y1, x0:x1] == 2).all())  # the near box wins the z-buffer
    far_x0, far_x1 = span(0.0, 0.3, 1.8, (w - 1) / 2)
    far_y0, far_y1 = span(0.0, 0.25, 1.8, (h - 1) / 2)
    assert scenes.object_bbox_xyxy[0, 0].tolist() == [far_x0, far_y0, far_x1, far_y1]
    assert int((scenes.object_ids == 1).sum()) < (far_x1 - far_x0) * (far_y1 - far_y0)  # partly hidden
    assert scenes.object_bbox_xyxy[0, 2].tolist() == [0, 0, 0, 0] and int((scenes.object_ids == 3).sum()) == 0
    assert scenes.object_valid.tolist() == [[True, True, False]] and float(scenes.object_depth_m[0, 2]) == 0.0


def test_batched_geometry_equals_per_scene(scenes64: SyntheticScenes) -> None:
    """Ground truth of one scene does not depend on the others in the batch (textures differ: own draws)."""
    for b in range(scenes64.depth_m.shape[0]):
        alone = render_obstacle_scenes(scenes64.object_depth_m[b:b + 1], scenes64.object_center_xy_m[b:b + 1],
                                       scenes64.object_size_m[b:b + 1], size_wh=(320, 240), generator=seeded(0),
                                       dtype=torch.float64, supersample=1)
        assert torch.equal(alone.depth_m[0], scenes64.depth_m[b])
        assert torch.equal(alone.object_ids[0], scenes64.object_ids[b])
        assert torch.equal(alone.object_bbox_xyxy[0], scenes64.object_bbox_xyxy[b])


def test_right_view_shows_the_same_object_unless_occluded(scenes64: SyntheticScenes) -> None:
    batch = scenes64.batch
    w, h = 320, 240
    scene = _Scene(float(batch.focal_px[0]), SVS_CAMERA.principal_point_px(w, h), scenes64.object_depth_m,
                   scenes64.object_center_xy_m, scenes64.object_size_m, scenes64.object_valid, 4.0)
    x_right = torch.arange(w, dtype=torch.float64).view(1, 1, 1, w) - batch.disparity_px
    y = torch.arange(h, dtype=torch.float64).view(1, 1, h, 1)
    right_depth, right_ids = _cast_rays(x_right, y, SVS_CAMERA.baseline_m, scene)
    occluded, occluder = occluded_in_right(scenes64)
    assert bool(occluded.any())  # the background behind each box is partly hidden from the right camera
    assert torch.equal(right_ids[~occluded], scenes64.object_ids[~occluded])
    assert torch.equal(right_depth[~occluded], scenes64.depth_m[~occluded])
    assert torch.equal(right_ids[occluded], occluder[occluded])


def test_photometric_consistency(scenes64: SyntheticScenes) -> None:
    """Texture is fixed to the surfaces: L(x) ≈ R(x − d) wherever the right camera sees the same point."""
    left = scenes64.batch.left
    occluded, _ = occluded_in_right(scenes64)
    warped, inside = sample_right_at(scenes64, scenes64.batch.disparity_px)
    keep = inside & ~occluded
    error = (left - warped).abs()[keep].median()
    unwarped, _ = sample_right_at(scenes64, torch.zeros_like(left))
    baseline_error = (left - unwarped).abs()[keep].median()
    assert error < 0.02
    assert baseline_error > 5 * error


def test_intensity_classes_and_otsu_separability() -> None:
    """OpenCV's Otsu threshold on the 8-bit left and right images recovers the obstacles (IoU > 0.9)."""
    scenes = random_obstacle_scenes(6, size_wh=(320, 240), generator=seeded(3), noise_std=0.01)
    ids = scenes.object_ids
    left = scenes.batch.left
    assert 0.65 <= float(left[ids > 0].mean()) <= 0.8 and 0.2 <= float(left[ids == 0].mean()) <= 0.3
    images = (scenes.batch.left * 255).round().to(torch.uint8).numpy()
    for b in range(images.shape[0]):
        _, binary = cv2.threshold(images[b, 0], 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
        truth = ids[b, 0].numpy() > 0
        found = binary > 0
        iou = (found & truth).sum() / (found | truth).sum()
        assert iou > 0.9, (b, iou)


def test_supersample_one_and_noise_keep_ground_truth() -> None:
    clean = random_obstacle_scenes(2, size_wh=SMALL, generator=seeded(4), supersample=1)
    noisy = random_obstacle_scenes(2, size_wh=SMALL, generator=seeded(4), supersample=1, noise_std=0.05)
    assert torch.equal(clean.depth_m, noisy.depth_m) and torch.equal(clean.object_ids, noisy.object_ids)
    assert not torch.equal(clean.batch.left, noisy.batch.left)
    assert noisy.batch.left.min() >= 0 and noisy.batch.left.max() <= 1


def test_texture_contrast_scales_the_texture_only() -> None:
    """The same scene at a lower texture contrast: the geometry and truth unchanged, each surface's intensities
    spread about the same mean by that factor (the low-texture tuning scenes of
    experiments/select_nearness_denoise.py)."""
    default = random_obstacle_scenes(3, size_wh=(160, 120), generator=seeded(8), supersample=1)
    same = random_obstacle_scenes(3, size_wh=(160, 120), generator=seeded(8), supersample=1, texture_contrast=1.0)
    weak = random_obstacle_scenes(3, size_wh=(160, 120), generator=seeded(8), supersample=1, texture_contrast=0.3)
    assert torch.equal(default.batch.left, same.batch.left) and torch.equal(default.batch.right, same.batch.right)
    assert torch.equal(default.depth_m, weak.depth_m) and torch.equal(default.object_ids, weak.object_ids)
    assert torch.equal(default.batch.disparity_px, weak.batch.disparity_px)
    for scene in range(3):
        for ident in range(3):  # 0 the wall, then each object
            region = default.object_ids[scene] == ident
            if int(region.sum()) < 50:
                continue
            strong_values, weak_values = default.batch.left[scene][region], weak.batch.left[scene][region]
            assert float(weak_values.std() / strong_values.std()) == pytest.approx(0.3, abs=0.02)
            assert float(weak_values.mean()) == pytest.approx(float(strong_values.mean()), abs=0.01)
    flat = random_obstacle_scenes(1, size_wh=(160, 120), generator=seeded(8), supersample=1, texture_contrast=0)
    assert float(flat.batch.left[flat.object_ids == 0].std()) < 1e-6


def test_wall_texture_contrast_scales_the_wall_only() -> None:
    """A plain wall (``wall_texture_contrast``) behind the same objects: the geometry, truth and objects' pixels
    unchanged, the wall's intensities spread about the same mean by that factor instead of ``texture_contrast``
    (experiments/real_rig.py ``--splits synthetic-wall``)."""
    default = random_obstacle_scenes(3, size_wh=(160, 120), generator=seeded(8), supersample=1)
    plain = random_obstacle_scenes(3, size_wh=(160, 120), generator=seeded(8), supersample=1,
                                   wall_texture_contrast=0.1)
    assert torch.equal(default.batch.disparity_px, plain.batch.disparity_px)
    objects, wall = default.object_ids > 0, default.object_ids == 0
    assert torch.equal(default.batch.left[objects], plain.batch.left[objects])
    for scene in range(3):
        strong, weak = default.batch.left[scene][wall[scene]], plain.batch.left[scene][wall[scene]]
        assert float(weak.std() / strong.std()) == pytest.approx(0.1, abs=0.01)
        assert float(weak.mean()) == pytest.approx(float(strong.mean()), abs=0.01)
    with pytest.raises(InputError, match="wall_texture_contrast: expected None or a finite number >= 0"):
        random_obstacle_scenes(1, size_wh=(160, 120), generator=seeded(8), wall_texture_contrast=-1.0)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"batch_size": 0}, "batch_size: expected an integer >= 1"),
        ({"num_objects": -1}, "num_objects: expected an integer >= 0"),
        ({"num_objects": 12}, "num_objects: 12 obstacles do not fit"),
        ({"depth_range_m": (0.0, 2.0)}, r"depth_range_m: expected 0 < near <= far"),
        ({"depth_range_m": (2.0, 1.0)}, r"depth_range_m: expected 0 < near <= far"),
        ({"depth_range_m": (1.0, 5.0)}, r"depth_range_m: expected far < background_depth_m=4.0"),
        ({"size_wh": (0, 120)}, r"size_wh: expected a \(width, height\) in pixels from 1 to 8192"),
        # Found by an audit: these raised torch's "can't allocate memory" from deep inside (40 GB, 16 TB), and a
        # request within what the kernel over-commits could have the process killed.
        ({"size_wh": (10**6, 10**6)}, r"size_wh: expected a \(width, height\) in pixels from 1 to 8192"),
        ({"batch_size": 10**9}, r"batch_size, size_wh, supersample: 1000000000 views of 160x120 shaded 2x finer"),
        ({"supersample": 10**5}, r"batch_size, size_wh, supersample: 2 views of 160x120 shaded 100000x finer"),
        ({"supersample": 0}, "supersample: expected an integer >= 1"),
        ({"noise_std": -0.1}, "noise_std: expected a finite value >= 0"),
        ({"texture_contrast": -0.5}, "texture_contrast: expected a finite number >= 0"),
        ({"texture_contrast": float("nan")}, "texture_contrast: expected a finite number >= 0"),
        # The most that fit is said, not a negative room (demo --objects 20: "room for -0.0762 m each").
        ({"num_objects": 20, "size_wh": (320, 240)}, r"num_objects: 20 obstacles do not fit .* at most 4 fit"),
    ],
)
def test_random_scene_errors(kwargs: dict, message: str) -> None:
    args = {"batch_size": 2, "size_wh": SMALL, "generator": seeded(0)} | kwargs
    with pytest.raises(InputError, match=message):
        random_obstacle_scenes(**args)


@pytest.mark.parametrize("dtype", [torch.float16, torch.int64, torch.bool, "float64"])
def test_a_dtype_the_pipeline_does_not_compute_in_is_named(dtype) -> None:
    """A library user's audit: float16 failed deep in the renderer (torch's "Unsupported dtype Half", naming
    ``object_depth_m`` from random_obstacle_scenes, which the caller never gave), int64 gave float32 scenes in silence
    and the string "float64" raised torch's "Invalid device string"."""
    message = r"^dtype: expected torch.float32 or torch.float64, got "
    with pytest.raises(InputError, match=message):
        random_obstacle_scenes(1, size_wh=SMALL, generator=seeded(0), dtype=dtype)
    with pytest.raises(InputError, match=message):
        render_obstacle_scenes(torch.tensor([[1.5]]), torch.zeros(1, 1, 2), torch.full((1, 1, 2), 0.5), size_wh=SMALL,
                               dtype=dtype)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("depth", torch.tensor([[1.0, 4.5]]), "object_depth_m: expected depths below background_depth_m=4.0"),
        ("depth", torch.tensor([[1.0, -1.0]]), "object_depth_m: expected positive finite depths"),
        ("size", torch.tensor([[[0.5, 0.5], [0.0, 0.5]]]), "object_size_m: expected positive finite"),
        ("center", torch.zeros(1, 2, 3), r"object_center_xy_m: expected \(1, 2, 2\), got \(1, 2, 3\)"),
        ("valid", torch.ones(1, 2), "object_valid: expected a bool tensor"),
        ("depth", torch.ones(10**5, 2), "batch_size, size_wh, supersample: 100000 views of 160x120 shaded 2x finer"),
    ],
)
def test_render_errors(field: str, value: torch.Tensor, message: str) -> None:
    b = value.shape[0] if field == "depth" else 1
    args = {"depth": torch.tensor([[1.0, 1.5]]), "center": torch.zeros(b, 2, 2),
            "size": torch.full((b, 2, 2), 0.5), "valid": None} | {field: value}
    with pytest.raises(InputError, match=message):
        render_obstacle_scenes(args["depth"], args["center"], args["size"], args["valid"], size_wh=SMALL)


def floor_scenes(height_m: float = 1.3, pitch_deg: float = 20.0, seed: int = 7) -> SyntheticScenes:
    """Two boxes 1.5 and 2.2 m ahead over a floor, as a walker's camera pitched down sees them."""
    depth = torch.tensor([[1.5, 2.2]])
    centre = torch.tensor([[[-0.4, 0.3], [0.5, 0.2]]])
    size = torch.tensor([[[0.4, 0.6], [0.5, 0.6]]])
    return render_obstacle_scenes(depth, centre, size, floor_height_m=height_m, camera_pitch_deg=pitch_deg,
                                  size_wh=SMALL, generator=torch.Generator().manual_seed(seed))


def test_without_a_floor_the_scenes_are_unchanged() -> None:
    args = (torch.tensor([[1.5]]), torch.tensor([[[0.0, 0.1]]]), torch.tensor([[[0.5, 0.5]]]))
    plain = render_obstacle_scenes(*args, size_wh=SMALL, generator=torch.Generator().manual_seed(3))
    named = render_obstacle_scenes(*args, size_wh=SMALL, generator=torch.Generator().manual_seed(3),
                                   floor_height_m=None, camera_pitch_deg=25.0)
    assert torch.equal(plain.batch.left, named.batch.left) and torch.equal(plain.batch.right, named.batch.right)
    assert plain.floor_mask is None and named.floor_mask is None


@pytest.mark.parametrize("pitch_deg", [0.0, 20.0])
def test_the_floors_disparity_is_the_planes(pitch_deg: float) -> None:
    """A floor h below a camera pitched down by θ has d = B·((y − cy)·cos θ + f·sin θ) / h, affine in the row;
    it is seen only below the horizon, and it is not an obstacle (id 0)."""
    scenes = floor_scenes(pitch_deg=pitch_deg)
    floor = scenes.floor_mask[0, 0]
    (w, h), theta = SMALL, np.radians(pitch_deg)
    f, (_, cy) = SVS_CAMERA.focal_px(w), SVS_CAMERA.principal_point_px(w, h)
    rows = torch.arange(h, dtype=torch.float32).view(-1, 1).expand(h, w)
    expected = SVS_CAMERA.baseline_m * ((rows - cy) * np.cos(theta) + f * np.sin(theta)) / 1.3
    torch.testing.assert_close(scenes.batch.disparity_px[0, 0][floor], expected[floor].float(), rtol=1e-4, atol=1e-4)
    assert bool(floor.any()) and not bool(floor[(expected <= 0)].any())
    assert not bool((scenes.object_ids[0, 0][floor] != 0).any())
    # The boxes stand in front of the floor and hide it; the far wall is behind it.
    assert bool((scenes.object_ids[0, 0] == 1).any()) and bool((scenes.object_ids[0, 0] == 2).any())


def test_a_pitched_camera_sees_the_floor_nearer() -> None:
    level, pitched = floor_scenes(pitch_deg=0.0), floor_scenes(pitch_deg=25.0)
    nearest = [float(s.depth_m[s.floor_mask].min()) for s in (level, pitched)]
    assert nearest[0] > 3.0 > 1.8 > nearest[1]  # beyond 3 m level; under 2 m pitched 25°: in the warning band
    assert float(pitched.batch.disparity_px[pitched.floor_mask].max()) > float(
        level.batch.disparity_px[level.floor_mask].max())
    # The pitched floor's disparity is a plane over the image: a least-squares fit in (x, y, 1) leaves nothing.
    rows, cols = torch.nonzero(pitched.floor_mask[0, 0], as_tuple=True)
    design = torch.stack([cols, rows, torch.ones_like(rows)], dim=1).double()
    disparity = pitched.batch.disparity_px[0, 0][rows, cols].double().unsqueeze(1)
    residual = design @ torch.linalg.lstsq(design, disparity).solution - disparity
    assert float(residual.abs().max()) < 1e-4


def test_the_floors_texture_is_on_the_floor() -> None:
    """Both views see the same texture at the same floor point: L(x) ≈ R(x − d) on the floor."""
    scenes = floor_scenes()
    warped, inside = sample_right_at(scenes, scenes.batch.disparity_px)
    occluded, _ = occluded_in_right(scenes)
    keep = inside & scenes.floor_mask & ~occluded
    error = (scenes.batch.left - warped).abs()[keep].median()
    unwarped, _ = sample_right_at(scenes, torch.zeros_like(scenes.batch.left))
    assert error < 0.02 and (scenes.batch.left - unwarped).abs()[keep].median() > 3 * error
    # Between the obstacles' gray and the wall's: neither Otsu's bright class nor the background's darkest.
    level = scenes.batch.left[scenes.floor_mask].mean()
    assert 0.3 < float(level) < 0.6


@pytest.mark.parametrize("kwargs,message", [({"floor_height_m": -1.0}, "floor_height_m"),
                                            ({"floor_height_m": float("nan")}, "floor_height_m"),
                                            ({"floor_height_m": 1.3, "camera_pitch_deg": 75.0}, "camera_pitch_deg"),
                                            ({"camera_pitch_deg": True}, "camera_pitch_deg")])
def test_floor_argument_errors(kwargs: dict, message: str) -> None:
    with pytest.raises(InputError, match=message):
        render_obstacle_scenes(torch.tensor([[1.5]]), torch.tensor([[[0.0, 0.0]]]), torch.tensor([[[0.5, 0.5]]]),
                               **kwargs)


def test_a_floor_keeps_its_fine_texture_in_front_of_a_far_wall():
    """The floor's texture tile spans the floor up to 4 m and wraps: spread over a 20 m corridor its 256 texels
    lost the fine speckle near the camera (x-gradients 3 times weaker), a floor no camera frame could match and
    that a real floor never is. Now the near floor looks the same in front of any wall."""
    from svs_torch.data.synthetic import render_obstacle_scenes

    gradients = []
    for wall_m in (4.0, 8.0, 20.0):
        scene = render_obstacle_scenes(torch.full((1, 1), 2.0), torch.zeros(1, 1, 2), torch.full((1, 1, 2), 0.5),
                                       torch.zeros(1, 1, dtype=torch.bool), floor_height_m=1.3,
                                       camera_pitch_deg=20.0, background_depth_m=wall_m,
                                       generator=torch.Generator().manual_seed(0), texture_contrast=0.5)
        lower = scene.batch.left[0, 0, 144:]  # the floor 1.4-2.6 m ahead
        gradients.append(float((lower[:, 2:] - lower[:, :-2]).abs().mean()))
    assert max(gradients) < 1.1 * min(gradients), gradients


def test_a_turned_front_has_the_planes_disparity_in_both_views() -> None:
    """object_yaw_deg: a front turned about its vertical axis, Z = Z_c + tan(yaw) (X − X_c); at each of its pixels the
    truth is f·B / Z of the ray's hit, written here independently of the renderer, the right view shows the same
    texture at x − d, and a turn of 0 renders the fronto-parallel scene bit for bit."""
    depth, centre = torch.tensor([[1.5, 2.5]]), torch.tensor([[[-0.2, 0.0], [0.4, 0.05]]])
    size = torch.tensor([[[0.5, 0.6], [0.6, 0.8]]])
    flat = render_obstacle_scenes(depth, centre, size, generator=seeded(3))
    same = render_obstacle_scenes(depth, centre, size, generator=seeded(3), object_yaw_deg=torch.zeros(1, 2))
    assert all(torch.equal(a, b) for a, b in zip(scene_tensors(flat).values(), scene_tensors(same).values()))
    yaw = torch.tensor([[30.0, -40.0]])
    turned = render_obstacle_scenes(depth, centre, size, generator=seeded(3), object_yaw_deg=yaw)
    f, b = SVS_CAMERA.focal_px(320), SVS_CAMERA.baseline_m
    cx = SVS_CAMERA.principal_point_px(320, 240)[0]
    disparity, ids = turned.batch.disparity_px[0, 0].double(), turned.object_ids[0, 0]
    columns = torch.arange(320, dtype=torch.float64).expand(240, 320)
    for k in (1, 2):
        slope = np.tan(np.radians(float(yaw[0, k - 1])))
        mine = ids == k
        z = (float(depth[0, k - 1]) - slope * float(centre[0, k - 1, 0])) / (1 - slope * (columns[mine] - cx) / f)
        assert torch.allclose(disparity[mine], f * b / z, rtol=1e-5)
        assert float(disparity[mine].max() - disparity[mine].min()) > 2  # the turn shows across the front
    warped, inside = sample_right_at(turned, turned.batch.disparity_px)
    on_fronts = inside & (turned.object_ids > 0)
    assert (turned.batch.left - warped).abs()[on_fronts].median() < 0.02


@pytest.mark.parametrize("yaw, message", [
    (torch.tensor([[70.0, 0.0]]), r"\[-60, 60\]"),
    (torch.tensor([[float("nan"), 0.0]]), r"\[-60, 60\]"),
    (torch.zeros(1, 3), "object_yaw_deg"),
])
def test_a_turn_out_of_range_is_refused(yaw: torch.Tensor, message: str) -> None:
    with pytest.raises(InputError, match=message):
        render_obstacle_scenes(torch.tensor([[1.5, 2.5]]), torch.zeros(1, 2, 2), torch.full((1, 2, 2), 0.5),
                               object_yaw_deg=yaw, generator=seeded(0))


def test_a_turned_front_must_stay_in_front_of_the_wall() -> None:
    with pytest.raises(InputError, match="background_depth_m"):  # 3.8 m ± tan(45°) · 0.5 m reaches past the wall
        render_obstacle_scenes(torch.tensor([[3.8]]), torch.zeros(1, 1, 2), torch.full((1, 1, 2), 1.0),
                               object_yaw_deg=torch.tensor([[45.0]]), generator=seeded(0))
