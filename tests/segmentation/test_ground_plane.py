"""The ground plane of the nearness map (svs_torch.segmentation.ground_plane): a floor is found where a walker's
camera would see one, and only there."""

import math

import numpy as np
import pytest
import torch

from svs_torch.core.errors import InputError
from svs_torch.segmentation.ground_plane import GroundPlaneConfig, _least_squares, fit_ground_plane
from svs_torch.segmentation.nearness_split import nearness_split

H, W = 240, 320
FOCAL_PX, BASELINE_M = 283.0, 0.1075
CY = 119.5


def floor_scene(height_m=1.3, pitch_deg=15.0, roll_deg=0.0, boxes=((60, 140, 1.5), (200, 260, 1.2)),
                wall_m=4.0, noise_px=0.0, seed=0):
    """A disparity map ``(1, 1, H, W)``: a floor under a camera ``height_m`` high pitched down ``pitch_deg``, a wall
    at ``wall_m`` and boxes (columns x0, x1 and depth) standing on the floor; the floor's mask."""
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64),
                            indexing="ij")
    theta, phi = math.radians(pitch_deg), math.radians(roll_deg)
    # A rolled camera: image axes turned by phi about the optical axis.
    u, v = (xs - 159.5) / FOCAL_PX, (ys - CY) / FOCAL_PX
    down_along_rows = v * math.cos(phi) - u * math.sin(phi)
    floor_d = BASELINE_M * FOCAL_PX * (down_along_rows * math.cos(theta) + math.sin(theta)) / height_m
    depth = torch.full((H, W), wall_m, dtype=torch.float64)
    floor = floor_d > FOCAL_PX * BASELINE_M / wall_m
    depth = torch.where(floor, FOCAL_PX * BASELINE_M / floor_d.clamp_min(1e-9), depth)
    for x0, x1, z in boxes:
        # A box stands on the floor: it hides the floor above the row where the floor is at its depth.
        on = (xs >= x0) & (xs < x1) & (floor_d < FOCAL_PX * BASELINE_M / z) & (ys > 30)
        depth = torch.where(on, torch.full_like(depth, z), depth)
    disparity = FOCAL_PX * BASELINE_M / depth
    if noise_px:
        disparity = disparity + noise_px * torch.randn(H, W, generator=torch.Generator().manual_seed(seed),
                                                       dtype=torch.float64)
    is_floor = (depth != wall_m) & ~torch.isin(depth, torch.tensor([z for *_, z in boxes], dtype=torch.float64))
    return disparity.float().view(1, 1, H, W), is_floor.view(1, 1, H, W)


def fit(disparity, measured=None, baseline_m=BASELINE_M, **settings):
    measured = torch.ones_like(disparity, dtype=torch.bool) if measured is None else measured
    baseline = torch.full((disparity.shape[0],), baseline_m)
    return fit_ground_plane(disparity, measured, baseline, GroundPlaneConfig(**settings))


@pytest.mark.parametrize("height_m,pitch_deg,roll_deg", [(1.3, 15.0, 0.0), (1.6, 30.0, 5.0), (1.0, 5.0, -8.0)])
def test_a_walkers_floor_is_found_with_its_height(height_m, pitch_deg, roll_deg):
    disparity, is_floor = floor_scene(height_m, pitch_deg, roll_deg, noise_px=0.2)
    plane = fit(disparity)
    assert bool(plane.found[0])
    # B / hypot(a, b) is the height over the cosine of the pitch (module docstring).
    expected = height_m / math.cos(math.radians(pitch_deg))
    # Within 5 %: a band of the wall and the boxes' feet lie within the tolerance, all in front (refit comment).
    assert float(plane.camera_height_m[0]) == pytest.approx(expected, rel=0.05)
    a, b = plane.coefficients[0, :2].tolist()
    assert math.degrees(math.atan2(-a, b)) == pytest.approx(roll_deg, abs=1.0)
    mask = plane.mask[0, 0]
    assert float((mask & is_floor[0, 0]).sum() / is_floor.sum()) > 0.95  # the floor is taken out...
    boxes = ~is_floor[0, 0] & (disparity[0, 0] > 20)
    assert float((mask & boxes).sum() / boxes.sum()) < 0.15  # ...and the boxes standing on it stay


def test_the_refit_is_numpys_least_squares_and_lies_on_the_floor():
    generator = torch.Generator().manual_seed(1)
    x, y = torch.rand(500, generator=generator) * W, torch.rand(500, generator=generator) * H
    d = (0.002 * x + 0.08 * y - 3 + 0.1 * torch.randn(2, 500, generator=generator))
    weight = torch.rand(2, 500, generator=generator) > 0.3
    plane = _least_squares(x, y, d, weight)
    for i in range(2):
        pick = weight[i].numpy()
        design = np.stack([x.numpy()[pick], y.numpy()[pick], np.ones(pick.sum())], 1).astype(np.float64)
        reference = np.linalg.lstsq(design, d[i].numpy()[pick].astype(np.float64), rcond=None)[0]
        np.testing.assert_allclose(plane[i].double().numpy(), reference, rtol=1e-4, atol=1e-4)
    # The fitted floor of a noisy map lies on the true floor: its residual there is well under the noise.
    disparity, is_floor = floor_scene(noise_px=0.3, seed=2)
    clean, _ = floor_scene()
    a, b, c = fit(disparity).coefficients[0].tolist()
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32),
                            indexing="ij")
    residual = (a * xs + b * ys + c - clean[0, 0])[is_floor[0, 0]].abs()
    assert float(residual.median()) < 0.15


def test_a_noisy_maps_grid_points_are_its_cells_medians():
    """cell_medians against a loop over the cells in numpy: each grid pixel the lower median of its cell's measured
    pixels (0 and not drawn with fewer than the least count, or with a median not positive); and a noisy pair's
    plane, its samples drawn from them, does not depend on the plain pair beside it in a batch."""
    from svs_torch.segmentation.ground_plane_grid import cell_medians

    generator = torch.Generator().manual_seed(3)
    disparity = torch.rand(2, 1, 37, 45, generator=generator) * 30 - 2
    measured = torch.rand(disparity.shape, generator=generator) < 0.3
    stride, least = 6, 4
    median, drawable = cell_medians(disparity, measured, stride, least)
    for pair in range(2):
        d, m = disparity[pair, 0].numpy(), measured[pair, 0].numpy()
        rows, columns = range(stride // 2, 37, stride), range(stride // 2, 45, stride)
        expected_d = np.zeros((len(rows), len(columns)), np.float32)
        expected_ok = np.zeros_like(expected_d, bool)
        for i, y in enumerate(rows):
            for j, x in enumerate(columns):
                cell = (slice(y - y % stride, y - y % stride + stride), slice(x - x % stride, x - x % stride + stride))
                values = np.sort(d[cell][m[cell]])
                if len(values) >= least:
                    expected_d[i, j] = values[(len(values) - 1) // 2]
                    expected_ok[i, j] = expected_d[i, j] > 0
        assert np.array_equal(median[pair].numpy(), expected_d) and np.array_equal(drawable[pair].numpy(), expected_ok)
    maps = torch.cat([floor_scene(1.3, 20.0, noise_px=0.6, seed=1)[0], floor_scene(1.6, 25.0, noise_px=0.3)[0]])
    seen = torch.rand(maps.shape, generator=generator) < 0.25
    baseline = torch.full((2,), BASELINE_M)
    together = fit_ground_plane(maps, seen, baseline, GroundPlaneConfig(), noisy=torch.tensor([True, False]))
    for i, noisy in enumerate((True, False)):
        alone = fit_ground_plane(maps[i:i + 1], seen[i:i + 1], baseline[:1], GroundPlaneConfig(),
                                 noisy=torch.tensor([noisy]))
        for name in ("coefficients", "found", "mask"):
            assert torch.equal(getattr(together, name)[i:i + 1], getattr(alone, name)), (i, name)


@pytest.mark.parametrize("seed", range(4))
def test_a_noisy_sparsely_measured_floor_is_found_on_its_cells_medians(seed):
    """A camera frame's floor: a quarter of its pixels measured, each off by noise of 0.6 px (the noisy tolerance
    is 1.5). Three nearby grid pixels seldom make a walker's slope (samples drawn from the pixels themselves find
    no floor in any of these seeds); samples drawn from the cells' medians do. A noisy map of upright surfaces
    still has none."""
    disparity, is_floor = floor_scene(1.3, 20.0, noise_px=0.6, seed=seed)
    measured = torch.rand(disparity.shape, generator=torch.Generator().manual_seed(100 + seed)) < 0.25
    noisy = torch.tensor([True])
    plane = fit_ground_plane(disparity, measured, torch.tensor([BASELINE_M]), GroundPlaneConfig(), noisy=noisy)
    assert bool(plane.found[0])
    expected = 1.3 / math.cos(math.radians(20.0))
    # the plane refitted for the pose (the map's own pixels near it) within 5 %; the one the rule tests within 10
    assert BASELINE_M / float(plane.refitted[0, :2].norm()) == pytest.approx(expected, rel=0.05)
    assert float(plane.camera_height_m[0]) == pytest.approx(expected, rel=0.1)
    assert float((plane.mask & is_floor).sum() / is_floor.sum()) > 0.85  # the map's own pixels, noise and all
    raw = fit_ground_plane(disparity, measured, torch.tensor([BASELINE_M]),
                           GroundPlaneConfig(noisy_cell_min_share=None), noisy=noisy)
    assert not bool(raw.found[0])
    upright = torch.full((1, 1, H, W), 8.0)
    upright[..., 40:200, 40:140] = 20.0
    upright = upright + 0.6 * torch.randn(upright.shape, generator=torch.Generator().manual_seed(seed))
    assert not bool(fit_ground_plane(upright, measured, torch.tensor([BASELINE_M]), GroundPlaneConfig(),
                                     noisy=noisy).found[0])


def test_fronto_parallel_scenes_have_no_floor():
    ys, xs = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    disparity = torch.full((1, 1, H, W), 8.0)
    disparity[..., 40:200, 40:140] = 20.0
    disparity[..., 60:240, 180:300] = 25.0
    assert not bool(fit(disparity).found[0])


def test_a_slanted_backdrop_with_the_scene_behind_it_is_not_a_floor():
    """A plane whose disparity grows down the image but with much of the scene behind it (a tilted table top with
    the room beyond its edge, a leaning board) is not a floor: nothing is seen under a floor."""
    disparity, _ = floor_scene(boxes=())
    behind = disparity.clone()
    behind[..., 150:, :160] = 3.0  # a far room seen below the plane's edge
    assert bool(fit(disparity).found[0])
    assert not bool(fit(behind).found[0])


def test_the_height_range_is_in_metres_of_the_rig():
    disparity, _ = floor_scene(height_m=1.3, pitch_deg=15.0)
    assert bool(fit(disparity).found[0])
    # The same map from a rig of a third of the baseline is a floor 0.45 m down: a table top, not a walker's floor.
    assert not bool(fit(disparity, baseline_m=BASELINE_M / 3).found[0])
    assert not bool(fit(disparity, baseline_m=math.nan).found[0])
    assert bool(fit(disparity, baseline_m=BASELINE_M / 3, min_camera_height_m=0.3).found[0])


def test_a_wall_facing_the_camera_is_not_a_shallow_floor():
    """Within the tolerance a shallow plane runs along a wall over a band of rows; its inliers all lie at one
    disparity, so it is not taken for a floor (here with a rig whose baseline would make that band's slope a
    walker's floor), and a level camera's floor, seen only beyond 3 m (a span of 2.3 px), is not looked for
    either."""
    level, _ = floor_scene(height_m=1.3, pitch_deg=0.0)
    assert not bool(fit(level, baseline_m=BASELINE_M / 3).found[0])
    assert not bool(fit(level).found[0])


def test_a_pairs_plane_does_not_depend_on_its_batch():
    maps = [floor_scene(1.3, 15.0)[0], floor_scene(1.6, 25.0, 4.0, noise_px=0.3)[0], torch.full((1, 1, H, W), 9.0)]
    together = fit(torch.cat(maps))
    for i, single in enumerate(maps):
        alone = fit(single)
        assert torch.equal(together.found[i:i + 1], alone.found)
        torch.testing.assert_close(together.coefficients[i:i + 1], alone.coefficients)
        assert torch.equal(together.mask[i:i + 1], alone.mask)
    assert together.found.tolist() == [True, True, False]


def test_a_map_without_a_floor_gives_what_the_whole_fit_gives():
    """The fit stops early where no pair can have a floor (no sample passes the rig's tests, or no plane survives
    the scoring); its answer for such a pair is the whole fit's, which runs when a floor is beside it in a batch."""
    upright = torch.full((1, 1, H, W), 8.0)
    upright[..., 40:200, 40:140] = 20.0
    backdrop, _ = floor_scene(boxes=())
    backdrop[..., 150:, :160] = 3.0  # plausible samples, but a far room seen below the plane's edge
    floor = floor_scene(1.3, 15.0)[0]
    for pair in (upright, backdrop):
        alone, whole = fit(pair), fit(torch.cat([floor, pair]))
        assert whole.found.tolist() == [True, False] and alone.found.tolist() == [False]
        for name in ("coefficients", "found", "camera_height_m", "mask"):
            expected, got = getattr(whole, name)[1:], getattr(alone, name)
            assert got.dtype == expected.dtype and torch.equal(got.nan_to_num(-1.0), expected.nan_to_num(-1.0))


@pytest.mark.parametrize("threads", [1, 3])
def test_the_kernel_gives_the_torch_paths_plane(monkeypatch, threads):
    """The C kernel (each pair's whole fit in one pass) against the torch path, bit for bit: floors under level,
    pitched and rolled cameras with noise, a fronto-parallel scene, a slanted backdrop, unmeasured pixels, the
    noisy tolerance, a working factor, a seeded generator, a rig without a baseline and no pitch limit."""
    from svs_torch.segmentation import kernels

    if not kernels.available("ground_plane_fit"):
        pytest.skip("no C compiler")
    backdrop, _ = floor_scene(boxes=())
    backdrop[..., 150:, :160] = 3.0
    maps = torch.cat([floor_scene(1.3, 15.0)[0], floor_scene(1.6, 25.0, 4.0, noise_px=0.3)[0],
                      floor_scene(1.0, 5.0, -8.0, noise_px=0.6, seed=2)[0], torch.full((1, 1, H, W), 9.0), backdrop,
                      floor_scene(2.0, 30.0, noise_px=1.0, seed=3)[0]])
    measured = torch.rand(maps.shape, generator=torch.Generator().manual_seed(5)) < 0.8
    baseline = torch.tensor([BASELINE_M] * 5 + [math.nan])
    calls = [dict(), dict(noisy=torch.tensor([True, False] * 3), working_factor=2.0),
             dict(focal_px=torch.full((6,), FOCAL_PX)), dict(generator=torch.Generator().manual_seed(9))]
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for options in calls:
            generator = options.pop("generator", None)
            fused = fit_ground_plane(maps, measured, baseline, GroundPlaneConfig(), generator=generator, **options)
            if generator is not None:
                generator.manual_seed(9)
            monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
            eager = fit_ground_plane(maps, measured, baseline, GroundPlaneConfig(), generator=generator, **options)
            monkeypatch.delenv("SVS_TORCH_KERNELS")
            assert fused.found[:3].any() and not fused.found[3:].any()  # floors found and not, both paths alike
            for name in ("coefficients", "found", "camera_height_m", "mask"):
                expected, got = getattr(eager, name), getattr(fused, name)
                assert got.dtype == expected.dtype and torch.equal(got.nan_to_num(-1.0), expected.nan_to_num(-1.0))
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize("noise_px", [0.0, 0.6])
def test_the_kernels_cell_medians_are_the_torch_paths_at_any_cell_size(monkeypatch, noise_px):
    """A noisy pair's samples from its cells' medians, kernel against torch path bit for bit, on cells of 64 pixels
    (320 px wide: ranks) and of 256 (640 px: quickselect, select_rank.h), with ties (a noiseless map's equal values)."""
    from svs_torch.segmentation import kernels

    if not kernels.available("ground_plane_fit"):
        pytest.skip("no C compiler")
    small, _ = floor_scene(1.3, 20.0, noise_px=noise_px, seed=1)
    large = small.repeat_interleave(2, -1).repeat_interleave(2, -2)
    for disparity in (small, large):
        measured = torch.rand(disparity.shape, generator=torch.Generator().manual_seed(7)) < 0.3
        options = dict(noisy=torch.tensor([True]), focal_px=torch.tensor([FOCAL_PX * disparity.shape[-1] / W]))
        fused = fit_ground_plane(disparity, measured, torch.tensor([BASELINE_M]), GroundPlaneConfig(), **options)
        monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
        eager = fit_ground_plane(disparity, measured, torch.tensor([BASELINE_M]), GroundPlaneConfig(), **options)
        monkeypatch.delenv("SVS_TORCH_KERNELS")
        assert bool(fused.found[0])
        for name in ("coefficients", "found", "camera_height_m", "mask", "refitted"):
            assert torch.equal(getattr(fused, name).nan_to_num(-1.0), getattr(eager, name).nan_to_num(-1.0)), name


@pytest.mark.parametrize("kernels_off", [False, True])
def test_a_map_without_grid_points_has_no_plane(monkeypatch, kernels_off):
    """An empty map, or one no taller than half the grid's stride, has no plane (the torch path had indexed an
    empty grid: a RuntimeError)."""
    if kernels_off:
        monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
    for h, w in ((0, 320), (3, 320), (240, 0)):
        plane = fit(torch.full((2, 1, h, w), 5.0))
        assert plane.found.tolist() == [False, False] and plane.mask.shape == (2, 1, h, w) and not plane.mask.any()


def test_unmeasured_pixels_are_not_fitted_but_are_masked():
    disparity, is_floor = floor_scene()
    # Half the pixels unmeasured (filled), at random.
    measured = torch.rand(is_floor.shape, generator=torch.Generator().manual_seed(4)) < 0.5
    plane = fit(disparity, measured)
    assert bool(plane.found[0])
    assert float((plane.mask & is_floor).sum() / is_floor.sum()) > 0.95


def test_bad_arguments_name_themselves():
    disparity, _ = floor_scene()
    with pytest.raises(InputError, match="measured"):
        fit_ground_plane(disparity, torch.ones(1, 1, 5, 5, dtype=torch.bool), torch.tensor([0.1]))
    with pytest.raises(InputError, match="baseline_m"):
        fit_ground_plane(disparity, torch.ones_like(disparity, dtype=torch.bool), None)
    with pytest.raises(InputError, match="min_camera_height_m"):
        GroundPlaneConfig(min_camera_height_m=2.0, max_camera_height_m=1.0)
    with pytest.raises(InputError, match="max_roll_deg"):
        GroundPlaneConfig(max_roll_deg=95.0)
    with pytest.raises(InputError, match="hypotheses"):
        GroundPlaneConfig(hypotheses=2)
    with pytest.raises(InputError, match="max_behind_share"):
        GroundPlaneConfig(max_behind_share=0.0)
    with pytest.raises(InputError, match="noisy_cell_min_share"):
        GroundPlaneConfig(noisy_cell_min_share=0.0)


def test_a_setting_or_map_of_another_kind_is_named():
    """Found by an audit of the library called by hand: a DenseConfig given as the fit's config (or as
    obstacle_truth's floor) failed on its first field (AttributeError: grid_columns), a map without its channel
    axis in the unpacking of its shape."""
    from svs_torch.depth.dense_config import DenseConfig
    disparity, _ = floor_scene()
    measured = torch.ones_like(disparity, dtype=torch.bool)
    with pytest.raises(InputError, match="^config: expected a GroundPlaneConfig, got DenseConfig$"):
        fit_ground_plane(disparity, measured, torch.tensor([0.1]), DenseConfig())
    with pytest.raises(InputError, match=r"^disparity: expected \(B, 1, H, W\), got \(1, "):
        fit_ground_plane(disparity[:, 0], measured, torch.tensor([0.1]))


def test_the_split_leaves_the_floor_out():
    """The split over the map without the floor is the split of the other pixels alone."""
    disparity, is_floor = floor_scene(pitch_deg=25.0)
    rest = disparity[~is_floor].view(1, 1, 1, -1)
    split, spread, _ = nearness_split(disparity, 0.1, is_floor)
    split_rest, spread_rest, _ = nearness_split(rest, 0.1)
    torch.testing.assert_close(split, split_rest)
    torch.testing.assert_close(spread, spread_rest)
    # Excluding nothing is the plain split; excluding every pixel keeps them all.
    torch.testing.assert_close(nearness_split(disparity, 0.1, torch.zeros_like(is_floor))[0],
                               nearness_split(disparity, 0.1)[0])
    torch.testing.assert_close(nearness_split(disparity, 0.1, torch.ones_like(is_floor))[0],
                               nearness_split(disparity, 0.1)[0])


def test_the_default_samples_are_kept_for_a_few_settings_only():
    """Found by an audit of the API's effect on its caller: the default samples' table was kept for every (seed,
    hypotheses) a process ever fitted with, 40 MB each at the most hypotheses: twelve seeds in a sweep or a notebook
    grew it by 480 MB for good. Now a few are kept, and a setting fitted again gets the same samples."""
    from svs_torch.segmentation import ground_plane

    disparity = torch.rand(1, 1, 24, 32, generator=torch.Generator().manual_seed(0)) * 10
    measured = torch.ones(1, 1, 24, 32, dtype=torch.bool)
    baseline_m = torch.tensor([0.1])
    first = fit_ground_plane(disparity, measured, baseline_m, GroundPlaneConfig(seed=12345))
    for seed in range(40):
        fit_ground_plane(disparity, measured, baseline_m, GroundPlaneConfig(seed=seed))
    assert len(ground_plane._DRAWS) <= 8
    again = fit_ground_plane(disparity, measured, baseline_m, GroundPlaneConfig(seed=12345))
    assert torch.equal(first.coefficients, again.coefficients) and torch.equal(first.mask, again.mask)



@pytest.mark.parametrize("draw, setting, message", [
    (math.nan, {}, r"^draws: expected uniforms in \[0, 1\]"),
    (1e300, {}, r"^draws: expected uniforms in \[0, 1\]"),
    (0.5, {"lower_row": 1e300}, r"^settings\['lower_row'\]: expected a value within ±2\^53, got 1e\+300$"),
    (0.5, {"lower_row": -2.0**60}, r"^settings\['lower_row'\]: expected a value within ±2\^53"),
    (0.5, {"stride": 2**40}, r"^settings\['stride'\]: expected a value within ±2\^31, got 1099511627776$"),
])
def test_the_kernel_wrapper_refuses_draws_and_settings_its_c_code_cannot_cast(draw, setting, message):
    """Found by an audit under UBSan: the C code cast a draw times the candidates' count, and the lower row, to
    integers, undefined for NaN or past 2^63 ("nan is outside the range of representable values of type 'long
    int'"), and squared the stride in int64 (a signed overflow at 2^40); the wrapper took any float64 draws and any
    finite setting."""
    from svs_torch.segmentation import kernels

    settings = dict(zip(kernels.GROUND_PLANE_SETTINGS, [4, 4, 0.05, 10, 0.3, 0.5, 3.0, 0.5, 0.1, 0.3, 10, 10]))
    draws = torch.rand(8, 5, dtype=torch.float64)
    draws[3, 0] = draw
    with pytest.raises(InputError, match=message):
        kernels.ground_plane_fit(torch.rand(1, 1, 40, 40) * 20, torch.ones(1, 1, 40, 40, dtype=torch.bool),
                                 torch.ones(1), torch.ones(1), torch.full((1,), 300.0), draws, settings | setting,
                                 torch.ones(1, dtype=torch.bool), 1)
