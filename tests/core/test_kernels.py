"""The fused C kernels (svs_torch.core.kernels) against the torch paths they replace: the same values bit for bit,
the fallback without a compiler, the on-disk cache. The dense-stage kernel's own tests are in test_dense.py."""

from __future__ import annotations

import dataclasses
import math
import platform
import shutil

import pytest
import torch

from svs_torch.core import kernels
from svs_torch.core.errors import InputError
from svs_torch.data import load_middlebury_eval3, resize_stereo_batch
from svs_torch.depth import kernels as depth_kernels
from svs_torch.features import kernels as features_kernels
from svs_torch.features.hessian import _interior_maxima, hessian_octaves, maxima_support
from svs_torch.features.surf import SurfConfig, extract_surf_features
from svs_torch.geometry import kernels as geometry_kernels
from svs_torch.segmentation import kernels as segmentation_kernels

needs_kernel = pytest.mark.skipif(not kernels.available("hessian_octave"), reason="no C compiler")


def _with_threads(threads: int, function, *args, **kwargs):
    """``function(*args, **kwargs)`` with torch (and so the kernels' OpenMP loops) on ``threads`` threads."""
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        return function(*args, **kwargs)
    finally:
        torch.set_num_threads(before)


def _torch_path(monkeypatch, function, *args):
    """``function(*args)`` with every kernel off (``SVS_TORCH_KERNELS=torch``): the torch path's result."""
    monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
    try:
        return function(*args)
    finally:
        monkeypatch.delenv("SVS_TORCH_KERNELS")


@pytest.fixture(scope="module")
def images(data_dir):
    pair = resize_stereo_batch(load_middlebury_eval3(data_dir / "middlebury_eval3_Q" / "Teddy"), (320, 267))
    return torch.cat([pair.left, pair.right, torch.flip(pair.left, (-1,))])


@needs_kernel
def test_hessian_kernel_is_bit_identical_to_torch(images, monkeypatch):
    """Every octave's det(H) and trace from the C kernel equal the torch path's (same float32 operations in
    the same order, no FMA contraction), on real images with an odd size."""
    images = images[..., :263, :317]
    fused = hessian_octaves(images, num_octaves=4)
    monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
    eager = hessian_octaves(images, num_octaves=4)
    for a, b in zip(fused, eager):
        assert torch.equal(a.det, b.det) and torch.equal(a.trace, b.trace)
    assert any(bool((a.det > 1e-4).any()) for a in fused)


@needs_kernel
def test_surf_features_unchanged_by_the_kernel(images, monkeypatch):
    """The detector's kernels give the same keypoints bit for bit; the descriptor kernel (double arithmetic)
    the same descriptors to the float32 torch path's round-off."""
    fused = extract_surf_features(images, config=SurfConfig())
    monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
    eager = extract_surf_features(images, config=SurfConfig())
    assert torch.equal(fused.keypoints.xy, eager.keypoints.xy)
    assert float((fused.descriptors - eager.descriptors).abs().max()) < 5e-4


@needs_kernel
def test_padded_integral_kernel_is_bit_identical_to_torch(images):
    """The mean-removed, padded integral table in one pass equals integral_image + pad_integral bit for bit
    (float32 values, cumulative sums carried in double as torch's), on real images, odd sizes and a 1-pixel
    image; other dtypes are left to torch."""
    from svs_torch.features.integral import image_means, integral_image, pad_integral

    for batch in (images[..., :263, :317], images[:1, :, :1, :1]):
        table = features_kernels.padded_integral(batch, image_means(batch), 23)
        assert torch.equal(table, pad_integral(integral_image(batch, subtract_mean=True), 23))
        assert torch.equal(features_kernels.padded_integral(batch, None, 23), table)  # the kernel's own means
    # Its means are image_means' (a double sum in pixel order, as torch's cumsum carries it): on a native-size
    # image too, and with values whose float32 running sums would drift.
    large = torch.rand(2, 1, 2000, 2900, generator=torch.Generator().manual_seed(5)) * 1e3 - 400
    assert torch.equal(features_kernels.padded_integral(large, None, 2),
                       features_kernels.padded_integral(large, image_means(large), 2))
    assert features_kernels.padded_integral(images.double(), images.double().mean(dim=(-2, -1)).flatten(), 23) is None


def test_hessian_gradients_and_float64_take_the_torch_path(images):
    """The kernel is the no-gradient float32 path: a float64 image, or one that needs gradients, still gets
    the differentiable torch responses."""
    image = images[:1, :, :60, :80].double().requires_grad_()
    octaves = hessian_octaves(image, num_octaves=1)
    octaves[0].det.sum().backward()
    assert image.grad is not None and image.grad.abs().sum() > 0


def test_hessian_kernel_refuses_tables_it_cannot_read():
    """A float64 table, outputs that are not contiguous or a pad too small for the largest box are left to
    torch (returns False, writes nothing)."""
    if not kernels.available("hessian_octave"):
        pytest.skip("no C compiler")
    padded = torch.rand(2, 1, 40, 44)
    det, trace = torch.zeros(2, 3, 8, 10), torch.zeros(2, 3, 8, 10)
    sizes, areas = [9, 15, 21], [1.0, 1.0, 1.0]
    assert not features_kernels.hessian_octave(padded.double(), 12, 1, sizes, areas, areas, 0.9, det, trace)
    assert not features_kernels.hessian_octave(padded, 12, 1, sizes, areas, areas, 0.9, det, trace.transpose(-1, -2)
                                               .contiguous().transpose(-1, -2))
    assert not features_kernels.hessian_octave(padded, 8, 1, sizes, areas, areas, 0.9, det, trace)  # 21 // 2 + 1 > 8
    assert not det.any() and not trace.any()
    assert features_kernels.hessian_octave(padded, 12, 1, sizes, areas, areas, 0.9, det, trace) and det.any()


@needs_kernel
@pytest.mark.parametrize("threads", [1, 3])
def test_hessian_kernel_same_for_any_thread_count(images, threads):
    """The rows are split across threads; each point's arithmetic does not depend on the split."""
    reference = hessian_octaves(images, num_octaves=2)
    split = _with_threads(threads, hessian_octaves, images, num_octaves=2)
    for a, b in zip(split, reference):
        assert torch.equal(a.det, b.det) and torch.equal(a.trace, b.trace)


@needs_kernel
def test_local_maxima_kernel_equals_torch(images):
    """The scale-space maxima from the C kernel equal ``_interior_maxima``'s on real octaves, with the shared
    support and with a per-image mask, at two thresholds."""
    mask = torch.rand(images.shape[0], 1, *images.shape[-2:], generator=torch.Generator().manual_seed(0)) > 0.3
    found = 0
    for octave in hessian_octaves(images, num_octaves=3):
        for support in (maxima_support(octave), maxima_support(octave, mask)):
            for threshold in (0.0, 1000 / 255**2):
                fused = features_kernels.local_maxima(octave.det, support, threshold)
                assert torch.equal(fused, _interior_maxima(octave.det, support, threshold))
                found += int(torch.isfinite(fused).sum())
    assert found > 100


@needs_kernel
def test_local_maxima_kernel_ties_and_nan():
    """A tie with a neighbour counts as a maximum (as ``centre == peak`` does); a NaN neighbour rejects the
    point (torch's running maximum turns NaN); a NaN centre is never kept."""
    from svs_torch.features.hessian import _interior_maxima

    det = torch.zeros(1, 3, 7, 7)
    det[0, 1, 1, 1] = det[0, 1, 1, 2] = 2.0  # a tie
    det[0, 1, 5, 5] = 3.0
    det[0, 2, 5, 4] = float("nan")  # beside (1, 5, 5)
    det[0, 1, 3, 5] = float("nan")
    support = torch.ones(1, 1, 5, 5, dtype=torch.bool)
    fused = features_kernels.local_maxima(det, support, 0.5)
    assert torch.equal(fused, _interior_maxima(det, support, 0.5))
    assert fused[0, 0, 0, 0] == 2.0 and fused[0, 0, 0, 1] == 2.0
    assert torch.isfinite(fused).sum() == 2  # not (5, 5) beside the NaN, not the NaN centre


def test_local_maxima_kernel_refuses_other_inputs():
    """float64 maps and a grid without interior are left to torch (None); a support of another shape is an
    error (the kernel would read past it)."""
    if not kernels.available("local_maxima"):
        pytest.skip("no C compiler")
    support = torch.ones(1, 1, 3, 3, dtype=torch.bool)
    assert features_kernels.local_maxima(torch.zeros(1, 3, 5, 5, dtype=torch.float64), support, 0.0) is None
    with pytest.raises(InputError, match=r"^support: expected \(1, 1, 3, 4\), got \(1, 1, 3, 3\)"):
        features_kernels.local_maxima(torch.zeros(1, 3, 5, 6), support, 0.0)
    assert features_kernels.local_maxima(torch.zeros(1, 3, 2, 5), torch.ones(1, 1, 0, 3, dtype=torch.bool), 0.0) is None


def _dense_top(dets, supports, threshold, k):
    """The torch path: each octave's dense map of maxima, concatenated, torch.topk."""
    maps = [_interior_maxima(det, support, threshold).flatten(1) for det, support in zip(dets, supports)]
    return torch.topk(torch.cat(maps, dim=1), k, dim=1)


@pytest.mark.skipif(not kernels.available("strongest_maxima"), reason="no C compiler")
@pytest.mark.parametrize("threads", [1, 3])
def test_strongest_maxima_kernel_gives_the_dense_paths_topk(images, threads):
    """On real octaves, with the shared support and a per-image mask, k under and over the number of maxima:
    torch.topk's values and indices over the concatenated dense maps; past the last maximum, −inf at index 0."""
    octaves = hessian_octaves(images, num_octaves=3)
    mask = torch.rand(images.shape[0], 1, *images.shape[-2:], generator=torch.Generator().manual_seed(0)) > 0.3
    dets = [octave.det for octave in octaves]
    for supports in ([maxima_support(o) for o in octaves], [maxima_support(o, mask) for o in octaves]):
        for k in (64, 5000):
            values, index = _with_threads(threads, features_kernels.strongest_maxima, dets, supports, 1000 / 255**2, k)
            expected_values, expected_index = _dense_top(dets, supports, 1000 / 255**2, k)
            found = torch.isfinite(expected_values)
            assert torch.equal(values, expected_values)
            assert torch.equal(index, torch.where(found, expected_index, 0))
    assert 64 < int(found.sum(dim=1).min()) < 5000


@pytest.mark.skipif(not kernels.available("strongest_maxima"), reason="no C compiler")
def test_strongest_maxima_kernel_ties_and_small_octaves():
    """Equal maxima come in index order (octave by octave); an octave without interior points adds nothing to
    the index; float64 maps are left to torch (None), k past the interior points is an error (as topk's)."""
    dets = [torch.zeros(1, 3, 9, 9), torch.zeros(1, 3, 2, 2), torch.zeros(1, 3, 5, 5)]
    for det, places in ((dets[0], [(1, 6, 2), (1, 2, 6), (1, 2, 2)]), (dets[2], [(1, 2, 2)])):
        for s, y, x in places:
            det[0, s, y, x] = 1.0
    dets[0][0, 1, 4, 4] = 2.0
    supports = [torch.ones(1, 1, 7, 7, dtype=torch.bool), None, torch.ones(1, 1, 3, 3, dtype=torch.bool)]
    values, index = features_kernels.strongest_maxima(dets, supports, 0.5, 8)
    assert values[0, :5].tolist() == [2.0, 1.0, 1.0, 1.0, 1.0] and torch.isinf(values[0, 5:]).all()
    assert index[0, :5].tolist() == [3 * 7 + 3, 1 * 7 + 1, 1 * 7 + 5, 5 * 7 + 1, 49 + 1 * 3 + 1]
    assert features_kernels.strongest_maxima([d.double() for d in dets], supports, 0.5, 8) is None
    with pytest.raises(InputError, match=r"^k: expected an int in \[0, 58\]"):
        features_kernels.strongest_maxima(dets, supports, 0.5, 59)


@pytest.mark.skipif(not kernels.available("strongest_maxima"), reason="no C compiler")
def test_maxima_supports_of_any_bytes_keep_their_nonzero_points():
    """A support viewed from bytes other than 0 / 1 (uint8 2 as bool) compares equal to all True, yet
    strongest_maxima's C code anded each byte with the threshold's 1 and kept no maximum (all -inf, in silence);
    local_maxima's reads it as a truth value. Both now answer as for the all-True support (an audit of hostile
    calls)."""
    det = torch.rand(2, 4, 12, 12, generator=torch.Generator().manual_seed(0))
    ones = torch.ones(2, 2, 10, 10, dtype=torch.bool)
    odd = torch.full((2, 2, 10, 10), 2, dtype=torch.uint8).view(torch.bool)
    values, index = features_kernels.strongest_maxima([det], [ones], 0.0, 5)
    assert torch.isfinite(values).all()
    found = features_kernels.strongest_maxima([det], [odd], 0.0, 5)
    assert torch.equal(found[0], values) and torch.equal(found[1], index)
    assert torch.equal(features_kernels.local_maxima(det, odd, 0.0), features_kernels.local_maxima(det, ones, 0.0))


@pytest.mark.skipif(not kernels.available("find_runs"), reason="no C compiler")
@pytest.mark.parametrize("threads", [1, 3])
@pytest.mark.parametrize("width", [1, 7, 8, 9, 67])
def test_find_runs_kernel_equals_torch(generator, monkeypatch, threads, width):
    """The runs of sparse, dense and blocky masks (rows all set, all clear, runs across the eight-pixel words and
    up to the row's end), with and without a value that splits them: the torch path's starts and ends."""
    from svs_torch.segmentation.components import _find_runs

    masks = [torch.rand(3, 5, width, generator=generator) > p for p in (0.9, 0.5, 0.05)]
    blocky = torch.rand(3, 5, 1, generator=generator).expand(3, 5, width) > 0.5  # whole rows set or clear
    blocky = blocky.clone()
    blocky[0, 0, width // 2:] = False
    masks.append(blocky)
    for mask in masks:
        value = torch.randint(1, 3, mask.shape, generator=generator)
        for given in (None, value):
            assert segmentation_kernels.find_runs(mask, given) is not None
            fused = _with_threads(threads, _find_runs, mask, given)
            reference = _torch_path(monkeypatch, _find_runs, mask, given)
            assert torch.equal(fused.start, reference.start) and torch.equal(fused.end, reference.end)
    # int64 values only
    assert segmentation_kernels.find_runs(masks[0], torch.zeros(masks[0].shape, dtype=torch.int32)) is None


@pytest.mark.skipif(not kernels.available("label_runs"), reason="no C compiler")
@pytest.mark.parametrize("threads", [1, 3])
@pytest.mark.parametrize("connectivity", [4, 8])
def test_label_runs_kernel_equals_torch(generator, monkeypatch, threads, connectivity):
    """Labels, label counts and region properties of sparse, dense, diagonal and empty masks (components that
    touch only at a corner, that meet late through a U shape, a blank image amid others): the torch path's."""
    from svs_torch.segmentation.components import connected_components_with_stats

    masks = [torch.rand(4, 1, 9, 13, generator=generator) > p for p in (0.8, 0.5, 0.2)]
    shapes = torch.zeros(4, 1, 9, 13, dtype=torch.bool)
    shapes[0, 0, range(9), range(9)] = True  # a diagonal: one region at 8-connectivity, nine at 4
    shapes[1, 0, 1:8, 1] = shapes[1, 0, 1:8, 11] = shapes[1, 0, 7, 1:12] = True  # a U: its arms meet at the bottom
    shapes[3, 0, -1, :] = True  # the last row of an image never joins the next image's first
    masks.append(shapes)
    for mask in masks:
        fused = _with_threads(threads, connected_components_with_stats, mask, connectivity)
        reference = _torch_path(monkeypatch, connected_components_with_stats, mask, connectivity)
        assert torch.equal(fused[0], reference[0]) and torch.equal(fused[1], reference[1])
        for field in ("area_px", "bbox_xyxy", "centroid_xy", "valid"):
            assert torch.equal(getattr(fused[2], field), getattr(reference[2], field))
    assert int(connected_components_with_stats(shapes, connectivity)[1][0]) == (1 if connectivity == 8 else 9)
    assert int(connected_components_with_stats(shapes, connectivity)[1][1]) == 1
    int32 = torch.zeros(2, dtype=torch.int32)
    assert segmentation_kernels.label_runs(int32, int32, 1, 1, 2, 8) is None


@pytest.mark.skipif(not kernels.available("gray_levels"), reason="no C compiler")
@pytest.mark.parametrize("threads", [1, 3])
def test_gray_levels_kernel_equals_torch(generator, threads):
    """Levels and histograms of random images, of the levels' exact half-way points (round half to even), of
    the range's ends and of sizes that are no multiple of the kernel's chunks: the torch path's."""
    from svs_torch.segmentation.threshold import gray_histogram, gray_levels

    halves = (torch.arange(0, 255, dtype=torch.float32) + 0.5) / 255
    images = [torch.rand(3, 1, 67, 71, generator=generator), halves.view(1, 1, 5, 51).repeat(2, 1, 1, 1),
              torch.tensor([0.0, 1.0, 1e-9, 1 - 1e-7]).view(1, 1, 2, 2), torch.rand(2, 1, 1, 9000, generator=generator)]
    for image in images:
        levels, histogram = _with_threads(threads, segmentation_kernels.gray_levels, image)
        assert torch.equal(levels, gray_levels(image)) and torch.equal(histogram, gray_histogram(gray_levels(image)))
    assert segmentation_kernels.gray_levels(images[0].double()) is None


@pytest.mark.skipif(not kernels.available("nearness_split"), reason="no C compiler")
@pytest.mark.parametrize("threads", [1, 3])
def test_nearness_split_kernel_equals_torch(generator, monkeypatch, threads):
    """The nearness split's kernel gives the torch path's splits and retakings bit for bit: a scene's map with
    a few wrong matches far above it (the split taken again under the 90th percentile), maps of a few levels (ties
    at the split), a flat map, with and without a floor left out (one pair leaving out every pixel, which then
    counts them all), at any share; a map with NaN or an infinity, and float64, are left to the torch path."""
    from svs_torch.segmentation.nearness_split import nearness_split

    scene = torch.rand(3, 1, 48, 64, generator=generator) * 12
    scene[:, :, 10:30, 20:40] += 20  # a near box
    outliers = torch.rand(3, 1, 48, 64, generator=generator) < 0.03
    maps = [scene, torch.where(outliers, 95.0, scene), (scene / 8).round() * 8, torch.full((2, 1, 5, 7), 3.5)]
    for disparity in maps:
        floor = torch.zeros_like(disparity, dtype=torch.bool)
        floor[:, :, -12:] = True
        floor[0] = True
        for exclude in (None, floor):
            for share, most, gap in ((0.0, 1.0, 0.0), (0.1, 1.0, 0.0), (0.45, 1.0, 0.0), (0.1, 0.9, 0.1),
                                     (0.45, 0.3, 0.5)):
                fast = _with_threads(threads, nearness_split, disparity, share, exclude, most, gap)
                assert all(torch.equal(a, b) for a, b in zip(
                    fast, _torch_path(monkeypatch, nearness_split, disparity, share, exclude, most, gap)))
    assert bool(nearness_split(maps[1], 0.1)[2].any())  # the taken-again path ran
    flat = maps[0].flatten(1)
    clip = flat.amax(1)
    assert segmentation_kernels.nearness_split(flat, None, clip, clip, 0.1) is not None
    for bad in (flat.index_fill(1, torch.tensor([5]), math.nan), flat.index_fill(1, torch.tensor([5]), math.inf)):
        assert segmentation_kernels.nearness_split(bad, None, clip, clip, 0.1) is None
    assert segmentation_kernels.nearness_split(flat.double(), None, clip.double(), clip.double(), 0.1) is None


@pytest.mark.skipif(not kernels.available("refine_maxima"), reason="no C compiler")
@pytest.mark.parametrize("upsample", [False, True])
def test_refine_maxima_kernel_equals_torch(images, monkeypatch, upsample):
    """The compiled fit of the strongest maxima gives the torch path's keypoints (positions, sizes, peaks, signs,
    validity) on a real scene, with the detector's upsampling and a blank image amid others; the 3 × 3 solve's
    rounding is the only difference allowed."""
    from svs_torch.features.detector import SurfConfig, detect_surf_keypoints

    batch = torch.cat([images, torch.zeros_like(images[:1])])
    config = SurfConfig(upsample=upsample, max_keypoints=300)
    fused = detect_surf_keypoints(batch, config)
    monkeypatch.setattr(features_kernels, "refine_maxima", lambda *args: None)
    reference = detect_surf_keypoints(batch, config)
    assert torch.equal(fused.valid, reference.valid) and int(fused.valid.sum()) > 500
    assert torch.equal(fused.laplacian_sign, reference.laplacian_sign) and not fused.valid[-1].any()
    for field in ("xy", "scale", "score"):
        torch.testing.assert_close(getattr(fused, field), getattr(reference, field), rtol=1e-6, atol=1e-6)


def test_kernels_build_without_openmp(images, monkeypatch, tmp_path):
    """A compiler that refuses -fopenmp still gets the kernels, built serially, with the same values."""
    compiler = shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        pytest.skip("no C compiler")
    wrapper = tmp_path / "cc-without-openmp"
    wrapper.write_text(f'#!/bin/sh\nfor a in "$@"; do [ "$a" = -fopenmp ] && exit 1; done\nexec {compiler} "$@"\n')
    wrapper.chmod(0o755)
    reference = hessian_octaves(images, num_octaves=2)
    monkeypatch.setenv("CC", str(wrapper))
    monkeypatch.setenv("SVS_TORCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(kernels, "_LIBRARIES", {})
    assert kernels.available("hessian_octave")
    serial = hessian_octaves(images, num_octaves=2)
    for a, b in zip(serial, reference):
        assert torch.equal(a.det, b.det) and torch.equal(a.trace, b.trace)


@pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64"), reason="x86 instruction sets")
@pytest.mark.parametrize("march", ["x86-64", "x86-64-v3"], ids=["sse2", "avx2"])
def test_vector_kernels_same_on_smaller_instruction_sets(march, monkeypatch, tmp_path, generator):
    """The kernels written with vector types size them to one register of the instruction set built for
    (``VECTOR_BYTES`` in common.h: 16 bytes for SSE2, 32 for AVX2), and the semi-global column and row steps are
    written so that AVX2 vectorises them. Built for those instruction sets, whatever this machine has, the 16-bit
    block matcher, the median filter's network and the semi-global passes still equal their torch paths, on widths
    that leave a partial vector, ranges of more than one vector of columns and heights that leave a partial block
    of rows."""
    from svs_torch.depth.block_matching import block_match_sad
    from svs_torch.depth.dense_config import DenseConfig
    from svs_torch.depth.semi_global import _scan_columns_torch
    from svs_torch.segmentation.nearness_denoise import _median_filter

    compiler = shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        pytest.skip("no C compiler")
    wrapper = tmp_path / "cc-other-march"
    wrapper.write_text(f'#!/bin/sh\nfor a in "$@"; do shift; [ "$a" = -march=native ] && a=-march={march}; '
                       f'set -- "$@" "$a"; done\nexec {compiler} "$@"\n')
    wrapper.chmod(0o755)
    base = torch.rand(3, 1, 41, 77, generator=generator)
    right = 0.9 * torch.roll(base, shifts=-6, dims=-1) + 0.1 * torch.rand(3, 1, 41, 77, generator=generator)
    minimum, image_hw = torch.tensor([0, 2, 1]), torch.tensor([[41, 77], [35, 70], [41, 77]])
    expected = [block_match_sad(base, right, minimum, n, DenseConfig(kernel="torch"), image_hw) for n in (12, 45)]
    maps = _nearness_maps(generator)
    medians = [_torch_path(monkeypatch, _median_filter, image, 7) for image in maps]
    costs = (torch.rand(2, 9, 13, 37, generator=generator) * 300).round()
    costs[0, :, :, :5] = torch.inf  # outside the pair's region: the path starts again after it
    costs[1, :4] = torch.inf
    p1, p2 = torch.tensor([3.0, 8.0]), torch.tensor([12.0, 30.0])
    aggregated = _scan_columns_torch(costs, p1, p2)
    with_rows = aggregated + _scan_columns_torch(costs.transpose(-1, -2).contiguous(), p1, p2).transpose(-1, -2)
    monkeypatch.setenv("CC", str(wrapper))
    monkeypatch.setenv("SVS_TORCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(kernels, "_LIBRARIES", {})
    assert kernels.available("block_match")
    for n, reference in zip((12, 45), expected):
        found = block_match_sad(base, right, minimum, n, DenseConfig(kernel="c"), image_hw)
        assert torch.equal(found.disparity_px, reference.disparity_px) and torch.equal(found.valid, reference.valid)
        assert found.valid.sum() > 1000
    for image, reference in zip(maps, medians):
        torch.testing.assert_close(segmentation_kernels.median_filter(image, 7), reference, rtol=0, atol=0)
    assert torch.equal(depth_kernels.semi_global_columns(costs, p1, p2), aggregated)
    rows, (low, index) = depth_kernels.semi_global_rows(costs, p1, p2, aggregated)
    assert torch.equal(rows, with_rows) and torch.equal(index, with_rows.min(dim=1).indices)


def test_vector_types_are_sized_by_the_register_width():
    """Every kernel's GCC vector type takes its size from ``VECTOR_BYTES`` (common.h), never a fixed byte count:
    a type wider than the machine's registers is compiled one lane at a time without AVX-512 (the block matcher
    and the median were 8x slower on an AVX2 machine that way)."""
    from svs_torch.core.kernels.loader import SOURCES

    texts = {name: path.read_text() for name, path in SOURCES.items()}
    sizes = [(name, part.split(")", 1)[0]) for name, text in texts.items() for part in text.split("vector_size(")[1:]]
    for name, size in sizes:
        assert "LANES" in size, f"{name}: vector_size({size}) is not sized by VECTOR_BYTES"
    assert len(sizes) >= 4 and "".join(texts.values()).count("VECTOR_BYTES /") == 2


def test_shared_headers_are_part_of_every_cache_key(monkeypatch, tmp_path):
    """A change to any shared header (common.h: thread count, scratch allocation; fill_row.h, select_rank.h)
    names a new library for every kernel, so no process loads one built from the old header."""
    before = {name: kernels.loader._library_path(name) for name in kernels.SOURCES}
    assert {header.name for header in kernels.HEADERS} >= {"common.h", "fill_row.h", "select_rank.h"}
    for index, original in enumerate(kernels.HEADERS):
        header = tmp_path / original.name
        header.write_bytes(original.read_bytes() + b"\n/* changed */\n")
        changed = (*kernels.HEADERS[:index], header, *kernels.HEADERS[index + 1:])
        with monkeypatch.context() as patch:
            patch.setattr(kernels.loader, "HEADERS", changed)
            after = {name: kernels.loader._library_path(name) for name in kernels.SOURCES}
        assert all(before[name] != after[name] for name in kernels.SOURCES), original.name


def test_kernels_take_an_empty_batch():
    """B = 0 reaches the kernels as an empty batch (OpenMP still gets one thread) and gives empty results."""
    if not kernels.available("sad_nearest"):
        pytest.skip("no C compiler")
    best, second, index, back = geometry_kernels.sad_nearest(torch.zeros(0, 4, 64), torch.zeros(0, 5, 64),
                                                             torch.ones(0, 4, dtype=torch.bool),
                                                             torch.ones(0, 5, dtype=torch.bool))
    assert best.shape == (0, 4) and back.shape == (0, 5)
    described = features_kernels.usurf_describe(torch.zeros(0, 1, 20, 20), 8, torch.zeros(0, 3, 2), torch.ones(0, 3),
                                                torch.ones(0, 3, dtype=torch.bool), False)
    assert described.shape == (0, 3, 64)
    table = features_kernels.padded_integral(torch.zeros(0, 1, 20, 20), torch.zeros(0), 8)
    assert table.shape == (0, 1, 37, 37)
    count, below, _ = depth_kernels.labelled_select(torch.zeros(0, 6), torch.zeros(0, 6, dtype=torch.int64),
                                                    torch.ones(0, 2, dtype=torch.int64), torch.tensor([0.5]))
    assert count.shape == (0, 2) and below.shape == (0, 2, 1)
    count, median = depth_kernels.region_medians(torch.zeros(0, 6), torch.zeros(0, 6, dtype=torch.int64), 3)
    assert count.shape == median.shape == (0, 3)
    values, index = features_kernels.strongest_maxima([torch.zeros(0, 3, 5, 5)],
                                                      [torch.ones(1, 1, 3, 3, dtype=torch.bool)], 0.5, 4)
    assert values.shape == index.shape == (0, 4)


def _block_match_inputs(seed: int) -> tuple:
    """Three pairs of whole-number images with their own boxes (one empty, one past the padded size) and
    ranges, for the dense kernel."""
    from svs_torch.depth.cost_volume import quantize_levels

    generator = torch.Generator().manual_seed(seed)
    left = quantize_levels(torch.rand(3, 130, 90, generator=generator) * 0.2 - 0.1)
    right = quantize_levels(torch.rand(3, 130, 90, generator=generator) * 0.2 - 0.1)
    texture = torch.rand(3, 130, 90, generator=generator) * 0.1
    boxes = torch.tensor([[0, 0, 90, 130], [10, 20, 50, 100], [0, 0, 0, 0]])
    return (left, right, texture, 7, boxes, torch.tensor([0, 2, 5]), torch.tensor([16, 9, 16]),
            torch.tensor([[130, 90], [120, 80], [130, 90]]), torch.tensor([True, False, True]))


@needs_kernel
@pytest.mark.parametrize("threads", [1, 3])
def test_dense_kernel_same_for_any_thread_count(threads):
    """Pairs and bands of rows are shared among OpenMP threads; no value depends on how."""
    inputs = _block_match_inputs(2)
    rules = (0.1, 1.0, 0.2, False)
    reference = depth_kernels.block_match(*inputs, *rules)
    split = _with_threads(threads, depth_kernels.block_match, *inputs, *rules)
    assert all(torch.equal(a, b) for a, b in zip(split, reference))
    assert reference[1][0].any() and reference[1][1].any() and not reference[1][2].any()  # the empty box


@needs_kernel
@pytest.mark.parametrize("rows", [1, 7, 40, 48, 500])
def test_dense_kernel_same_for_any_band_height(rows, monkeypatch):
    """A pair's rows are matched in bands (tasks for the threads); no value depends on their height, so the
    height can be chosen for balance alone."""
    inputs = _block_match_inputs(5)
    rules = (0.1, 1.0, 0.2, False)
    reference = depth_kernels.block_match(*inputs, *rules)
    monkeypatch.setattr(depth_kernels, "band_rows", lambda height, batch, threads: rows)
    found = _with_threads(2, depth_kernels.block_match, *inputs, *rules)
    assert all(torch.equal(a, b) for a, b in zip(found, reference))


def test_dense_kernel_bands_are_even_for_fewer_pairs_than_threads():
    """One pair on two threads: a 240-row view in 6 bands of 40 rows, not 5 of 48 (3 bands on one thread set the
    time); as many pairs as threads keep the usual height."""
    assert depth_kernels.band_rows(240, 1, 2) == 40
    assert depth_kernels.band_rows(188, 1, 2) == 47  # 4 bands already
    assert depth_kernels.band_rows(130, 1, 3) == 44
    assert depth_kernels.band_rows(10, 1, 2) == 5
    assert depth_kernels.band_rows(240, 2, 2) == depth_kernels.band_rows(240, 1, 1) == depth_kernels.BAND_ROWS
    assert depth_kernels.band_rows(0, 0, 2) == depth_kernels.BAND_ROWS


@needs_kernel
def test_dense_kernel_equals_the_torch_box_matcher():
    """Each pair at its own box and range equals the torch path's shared box (dense._match_box, which the
    kernel replaces) inside that box, its winning costs too, and nothing is written outside it."""
    from svs_torch.depth import block_matching as dense

    left, right, _, size, boxes, minimum, counts, image_hw, lower = _block_match_inputs(3)
    config = dense.DenseConfig(window_size=size, prefilter="none", texture_threshold=0.0, kernel="torch")
    search = dense.DisparityRange(minimum, 16, counts)
    found = depth_kernels.block_match(left, right, None, size, boxes, minimum, counts, image_hw, lower,
                                      config.uniqueness_ratio, config.lr_max_diff_px, 0.0, False, best_cost=True)
    expected, ok, cost = dense._match_box(left.unsqueeze(1) / 255, right.unsqueeze(1) / 255, boxes[:, 0],
                                          boxes[:, 1], 130, 90, search, image_hw, config, lower)
    for b, (x0, y0, w, h) in enumerate(boxes.tolist()):
        inside = torch.zeros(130, 90, dtype=torch.bool)
        inside[y0:y0 + h, x0:x0 + w] = True
        assert torch.equal(found[1][b][inside], ok[b][:h, :w].flatten()) and not found[1][b][~inside].any()
        assert torch.equal(found[0][b][inside], expected[b][:h, :w].flatten())
        assert torch.equal(found[2][b][inside], cost[b][:h, :w].flatten()) and found[2][b][~inside].isnan().all()
    assert found[1].sum() > 1000


@needs_kernel
@pytest.mark.parametrize("source", ["raw", "xsobel"])
def test_dense_kernel_prefilters_as_the_torch_path(source):
    """From the raw images the kernel pre-filters a crop row at a time (x-Sobel, clip, quantize_levels; the
    texture from the left image's clipped x-Sobel): the same maps as from whole pre-filtered images, with boxes
    at and past the frame's edges (replicate border) and a texture rule that rejects some pixels."""
    from svs_torch.depth.cost_volume import prefilter_xsobel, quantize_levels

    _, _, _, size, boxes, minimum, counts, image_hw, lower = _block_match_inputs(4)
    generator = torch.Generator().manual_seed(5)
    raw_left = torch.rand(3, 130, 90, generator=generator)
    raw_left[:, 50:90] = 0.5  # a flat band for the texture rule
    raw_right = torch.roll(raw_left, -3, dims=-1) * 0.8 + 0.2 * torch.rand(3, 130, 90, generator=generator)
    cap = 31 / 255
    sobel_left = prefilter_xsobel(raw_left.unsqueeze(1), cap)[:, 0]
    sobel_right = prefilter_xsobel(raw_right.unsqueeze(1), cap)[:, 0]
    levels = (quantize_levels(sobel_left), quantize_levels(sobel_right)) if source == "xsobel" else (
        quantize_levels(raw_left), quantize_levels(raw_right))
    rules = (0.1, 1.0, 2 / 255 * size ** 2, False)
    expected = depth_kernels.block_match(*levels, sobel_left.abs(), size, boxes, minimum, counts, image_hw, lower,
                                         *rules)
    found = depth_kernels.block_match(raw_left, raw_right, True, size, boxes, minimum, counts, image_hw, lower, *rules,
                                      source=source, prefilter_cap=cap)
    untextured = depth_kernels.block_match(*levels, None, size, boxes, minimum, counts, image_hw, lower, *rules)
    assert torch.equal(found[0], expected[0]) and torch.equal(found[1], expected[1])
    assert expected[1].sum() > 500 and untextured[1].sum() > expected[1].sum()  # the texture rule rejected some
    with pytest.raises(ValueError, match="texture"):
        depth_kernels.block_match(raw_left, raw_right, sobel_left, size, boxes, minimum, counts, image_hw, lower,
                                  *rules, source=source, prefilter_cap=cap)


@pytest.mark.skipif(not kernels.available("usurf_describe"), reason="no C compiler")
def test_usurf_kernel_agrees_with_the_torch_descriptor(images, monkeypatch):
    """The C descriptor does the torch path's arithmetic in double: on real images (keypoints near the border
    included) its 64-long descriptors equal the float64 torch path's to 1e-6 and the float32 one's to that
    path's own round-off (median 1e-5, at most 5e-4). The 128-long ones split each sum by the sign of the
    other response, so against the float32 path a response near zero may land in the other half; against the
    float64 one they agree to 1e-6 too, since a response 0 by definition (its cells in the replicate border) counts
    as not negative in both (before, its round-off sign split 99 of these 625 keypoints' sums differently, by up to
    0.015). Padding rows are zero, and with gradients the torch path runs (the kernel has none)."""
    import dataclasses

    from svs_torch.features.descriptor import describe_surf
    from svs_torch.features.detector import detect_surf_keypoints
    from svs_torch.core.types import Keypoints

    keypoints = detect_surf_keypoints(images)
    assert int(keypoints.valid.sum()) > 300 and not bool(keypoints.valid.all())
    for extended in (False, True):
        fused = describe_surf(images, keypoints, extended)
        with monkeypatch.context() as patch:
            patch.setenv("SVS_TORCH_KERNELS", "torch")
            patch.setattr(kernels, "_LIBRARIES", {})
            reference = describe_surf(images.double(), keypoints, extended)
            single = describe_surf(images, keypoints, extended)
        error = (fused.double() - reference).abs().amax(-1)[keypoints.valid]
        assert float(error.median()) < 1e-6 and float(error.max()) < 1e-6
        if not extended:
            error = (fused - single).abs().amax(-1)[keypoints.valid]
            assert float(error.median()) < 5e-5 and float(error.max()) < 5e-4
        assert torch.equal(fused[~keypoints.valid], torch.zeros_like(fused[~keypoints.valid]))
    image = images[:1].clone().requires_grad_(True)
    one = Keypoints(*(getattr(keypoints, f.name)[:1] for f in dataclasses.fields(Keypoints)))
    describe_surf(image, one).sum().backward()
    assert image.grad is not None and image.grad.abs().sum() > 0


@pytest.mark.skipif(not kernels.available("lk_refine"), reason="no C compiler")
def test_lk_kernel_agrees_with_the_torch_refinement(data_dir, monkeypatch):
    """The C refinement takes the torch path's steps with its sums in double and in its own order: on the
    matches of real pairs, the same rows pass the correlation gate (all but a rare one on the edge) and the
    points agree to 1e-3 px but for a rare ill-conditioned patch."""
    from svs_torch.pipeline import segment_pair
    from svs_torch.pipeline import stages as pipeline
    from svs_torch.data import collate_stereo_batches, list_shared_pairs, load_stereo_pair
    from svs_torch.geometry.lk_refinement import refine_matches_lk
    from svs_torch.geometry.matched_points import gather_matched_points

    pairs = [resize_stereo_batch(load_stereo_pair(path), (320, 240)) for path in list_shared_pairs(data_dir)[:6]]
    batch = collate_stereo_batches(pairs)
    config = pipeline.PipelineConfig()
    images, mask = pipeline._feature_images(batch, segment_pair(batch, config.segmentation), config)
    left, right = pipeline._features(images, mask, config)
    points = gather_matched_points(left.keypoints.xy, right.keypoints.xy, pipeline._match(left, right, config))
    b = batch.batch_size

    def refine():
        return refine_matches_lk(images[:b], images[b:], points, left.keypoints.scale, min_correlation=0.7)

    fused = refine()
    monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
    reference = refine()
    both = fused.valid & reference.valid
    assert int(points.valid.sum()) > 200 and int(both.sum()) > 100
    assert (fused.valid != reference.valid).float().sum() <= 0.01 * points.valid.sum()
    error = (fused.right - reference.right)[both].abs().amax(-1)
    assert float(error.median()) < 1e-4 and float((error < 1e-3).float().mean()) > 0.99


@pytest.mark.skipif(not kernels.available("lk_refine"), reason="no C compiler")
def test_lk_kernel_matches_are_independent_of_their_neighbours(generator):
    """The kernel refines several matches at once with their sums interleaved (see the C source); each match's
    result is bit for bit the one it gets alone, whichever rows share its task (inactive rows, the batch's other
    pair, a last task that is not full)."""
    import torch.nn.functional as F

    texture = F.avg_pool2d(torch.rand(2, 1, 90, 124, generator=generator), 3, 1)  # (2, 1, 88, 122), smooth
    left, right = texture[:, :, :, :120].contiguous(), texture[:, :, :, 2:].contiguous()
    k = 21
    left_xy = torch.rand(2, k, 2, generator=generator) * torch.tensor([110.0, 78.0]) + 5.0
    right_xy = left_xy + torch.rand(2, k, 2, generator=generator) * 2.0 - torch.tensor([3.0, 1.0])
    radius = torch.rand(2, k, generator=generator) * 9.0 + 3.0
    active = torch.rand(2, k, generator=generator) > 0.2
    refined, correlation = geometry_kernels.lk_refine(left, right, left_xy, right_xy, radius, active, 8, 2.0)
    assert bool((refined != right_xy)[active].any()) and bool((correlation[active] != 0).all())
    assert torch.equal(refined[~active], right_xy[~active]) and bool((correlation[~active] == 0).all())
    for b in range(2):
        for n in active[b].nonzero().flatten().tolist():
            alone, alone_correlation = geometry_kernels.lk_refine(
                left[b:b + 1], right[b:b + 1], left_xy[b:b + 1, n:n + 1], right_xy[b:b + 1, n:n + 1],
                radius[b:b + 1, n:n + 1], active[b:b + 1, n:n + 1], 8, 2.0)
            assert torch.equal(alone[0, 0], refined[b, n]) and torch.equal(alone_correlation[0, 0], correlation[b, n])


@pytest.mark.skipif(not kernels.available("lk_refine"), reason="no C compiler")
def test_lk_kernel_leaves_sides_past_float32_whole_numbers_to_torch():
    """The kernel clamps each sample at the float32 (W - 1, H - 1): past 2^24 that rounds up to W, and a match at
    the last column of a 2 x (2^25 + 4) pair read one float past the image (ASan: heap-buffer-overflow in
    sample_patch; an audit of hostile calls). Such sizes now take the torch path (None); 2^24 still runs. The
    images are expanded rows, so nothing that size is allocated unless the kernel runs."""
    one = torch.ones(1, 1, dtype=torch.bool)
    for width, runs in ((2**25 + 4, False), (2**24 + 1, False), (2**24, True)):
        image = torch.rand(1, 1, 2, 1).expand(1, 1, 2, width) if not runs else torch.rand(1, 1, 1, width)
        xy = torch.tensor([[[width - 1.0, 0.0]]])
        found = geometry_kernels.lk_refine(image, image, xy, xy.clone(), torch.full((1, 1), 3.0), one, 2, 1.0)
        assert (found is not None) == runs, width


@pytest.mark.skipif(not kernels.available("sad_nearest"), reason="no C compiler")
@pytest.mark.parametrize("mutual", [False, True])
@pytest.mark.parametrize("band_px", [None, 4.0])
def test_sad_matching_kernel_equals_cdist_path(images, monkeypatch, mutual, band_px):
    """SAD matching through the C kernel gives the torch path's matches (cdist, topk, argmin) on real SURF
    descriptors, with the Laplacian gate, the epipolar band, the ratio test and the mutual check; costs equal to
    float32 round-off."""
    from svs_torch.geometry.matching import match_sad

    features = extract_surf_features(images, config=SurfConfig(metric_threshold=100.0))
    left, right = (features.descriptors[i:i + 1].expand(2, -1, -1).clone() for i in (0, 1))
    left[1] = features.descriptors[2]
    valid_left = features.keypoints.valid[[0, 2]]
    valid_right = features.keypoints.valid[[1, 1]]
    signs = features.keypoints.laplacian_sign

    def match():
        return match_sad(left, right, valid_left, valid_right, max_ratio=0.8, mutual=mutual,
                         laplacian_left=signs[[0, 2]], laplacian_right=signs[[1, 1]],
                         xy_left=features.keypoints.xy[[0, 2]], xy_right=features.keypoints.xy[[1, 1]],
                         epipolar_band_px=band_px)

    fused = match()
    monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
    reference = match()
    assert int((reference.idx >= 0).sum()) > 50
    assert torch.equal(fused.idx, reference.idx)
    assert torch.allclose(fused.cost, reference.cost, rtol=1e-6, atol=0)


@pytest.mark.skipif(not kernels.available("sad_nearest"), reason="no C compiler")
@pytest.mark.parametrize("band_px", [None, 0.3])
def test_sad_nearest_splits_one_pairs_rows_among_threads_with_the_same_results(generator, band_px):
    """With fewer pairs than threads (guide's one pair) each pair's rows go to the threads in blocks, each with its
    own column minima merged in block order: best, second, index and back equal the one-thread path bit for bit,
    and a column nearest to two equal rows of different blocks names the first (as torch's argmin)."""
    b, k, k2, d = 1, 301, 257, 64
    left, right = torch.rand(b, k, d, generator=generator), torch.rand(b, k2, d, generator=generator)
    left[0, 250] = left[0, 3]
    right[0, 17] = left[0, 3]  # column 17 is at distance 0 from rows 3 and 250, one in each half
    valid_left, valid_right = torch.rand(b, k, generator=generator) > 0.1, torch.rand(b, k2, generator=generator) > 0.1
    valid_left[0, [3, 250]], valid_right[0, 17] = True, True
    sign_left = torch.randint(0, 2, (b, k), generator=generator) * 2 - 1
    sign_right = torch.randint(0, 2, (b, k2), generator=generator) * 2 - 1
    sign_left[0, [3, 250]], sign_right[0, 17] = 1, 1
    y_left, y_right = torch.rand(b, k, generator=generator), torch.rand(b, k2, generator=generator)
    y_left[0, [3, 250]], y_right[0, 17] = 0.5, 0.5
    args = (left, right, valid_left, valid_right, sign_left, sign_right, y_left, y_right, band_px)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = geometry_kernels.sad_nearest(*args)
        results = []
        for count in (2, 3):
            torch.set_num_threads(count)
            results.append(geometry_kernels.sad_nearest(*args))
    finally:
        torch.set_num_threads(threads)
    assert int(one[3][0, 17]) == 3 and float(one[0][0, 3]) == 0.0
    for split in results:
        for got, want in zip(split, one):
            assert torch.equal(got, want)


@pytest.mark.skipif(not kernels.available("sad_nearest"), reason="no C compiler")
@pytest.mark.parametrize("band_px", [None, 1.0])
def test_sad_matching_kernel_edge_rows(band_px):
    """An invalid row, rows whose sign or band leaves no candidate or a single one, two at the same distance, an
    invalid column, the signs out of order: the same best / second / back as the masked matrix gives."""
    from svs_torch.geometry.matching import _allowed

    left = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.0, 1.0], [2.0, 2.0]]])
    right = torch.tensor([[[0.0, 0.5], [3.0, 3.0], [0.0, 1.5], [5.0, 5.0], [0.0, 0.5]]])
    valid_left = torch.tensor([[False, True, True, True, True]])
    valid_right = torch.tensor([[True, True, True, False, True]])
    sign_left, sign_right = torch.tensor([[1, 1, 1, -1, 7]]), torch.tensor([[1, -1, 1, 1, 1]])
    y_left, y_right = torch.tensor([[0.0, 5.0, 0.0, 0.0, 0.0]]), torch.tensor([[0.0, 0.0, 0.5, 0.0, 9.0]])
    xy_left, xy_right = torch.stack([y_left, y_left], -1), torch.stack([y_right, y_right], -1)
    best, second, index, back = geometry_kernels.sad_nearest(left, right, valid_left, valid_right, sign_left,
                                                             sign_right, y_left, y_right, band_px)
    allowed = _allowed(valid_left, valid_right, sign_left, sign_right, xy_left, xy_right, band_px)
    distance = torch.where(allowed, torch.cdist(left, right, p=1), torch.inf)
    nearest = torch.topk(distance, 2, dim=-1, largest=False)
    assert torch.equal(best, nearest.values[..., 0]) and torch.equal(second, nearest.values[..., 1])
    assert torch.equal(index, torch.where(torch.isfinite(best), distance.argmin(dim=-1), 0))  # first on ties
    assert torch.equal(back, distance.argmin(dim=-2))
    # Row 2: columns 0, 2 and 4 at 0.5 (the band drops 4): a tie, the first.
    assert best[0, 2] == second[0, 2] == 0.5 and index[0, 2] == 0
    if band_px is None:  # row 1: columns 0 and 4 at 1.5
        assert best[0, 1] == second[0, 1] == 1.5 and index[0, 1] == 0
    else:  # the band leaves row 1 nothing
        assert torch.isinf(best[0, 1]) and int(allowed[0, 2].sum()) == 2
    assert best[0, 3] == 5.0 and torch.isinf(second[0, 3])  # its sign's single candidate
    assert torch.isinf(best[0, 0]) and torch.isinf(best[0, 4])  # invalid; no column of its sign


@pytest.mark.skipif(not kernels.available("labelled_select"), reason="no C compiler")
def test_labelled_select_kernel_gives_the_sorting_paths_quantiles(monkeypatch):
    """Quickselect per object gives the order statistics the sort gives, so the same quantiles bit for bit:
    negative values, ties, ±inf, labels of no slot, padded and repeated slots, empty slots, long rows."""
    from svs_torch.depth.quantiles import labelled_quantile

    generator = torch.Generator().manual_seed(4)
    cases = []
    for p in (0, 1, 7, 300, 20000):
        values = torch.randint(-9, 9, (3, p), generator=generator).float()
        values[1] += torch.randn(p, generator=generator) * 100
        if p > 2:
            values[2, :2] = torch.tensor([float("inf"), -float("inf")])
        cases.append((values, torch.randint(-1, 5, (3, p), generator=generator),
                      torch.tensor([[1, 2, -1], [3, 3, 4], [2, 9, 1]])))
    q = [0.5, 0.1, 0.9, 0.0, 1.0, 0.37]
    fused = [labelled_quantile(*case, q) for case in cases]
    monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
    for case, result in zip(cases, fused):
        reference = labelled_quantile(*case, q)
        assert torch.equal(result.valid, reference.valid)
        assert torch.equal(result.values.nan_to_num(), reference.values.nan_to_num())  # inf − inf interpolates to NaN
    assert fused[-1].valid.sum() == 7  # all but the padding slot and slot 9, which no label holds


@pytest.mark.skipif(not kernels.available("fill_invalid_rows"), reason="no C compiler")
def test_fill_rows_kernel_is_bit_identical_to_torch(monkeypatch):
    """Rows with no valid pixel, one, a few and nearly all; neighbours that agree (mean) and that do not
    (the smaller): the same fill and reachability as the torch path."""
    from svs_torch.depth.block_matching import fill_invalid_rows

    generator = torch.Generator().manual_seed(5)
    disparity = torch.rand(4, 9, 57, generator=generator) * torch.tensor([0.5, 2.0, 10.0, 40.0]).view(4, 1, 1)
    valid = torch.rand(4, 9, 57, generator=generator) < torch.tensor([0.02, 0.2, 0.6, 0.97]).view(4, 1, 1)
    valid[0, 0] = False
    fused = fill_invalid_rows(disparity, valid)
    monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
    reference = fill_invalid_rows(disparity, valid)
    assert torch.equal(fused[0], reference[0]) and torch.equal(fused[1], reference[1])
    assert not fused[1][0, 0].any() and fused[1][3].all()


def _object_depth_inputs(seed: int) -> tuple:
    """Four pairs of dense disparities with their own boxes (inside the frame, past its left and right edges,
    empty), label images, slots (repeated, padding, a label no pixel holds), and calibrations under which some
    denominators are not positive and some depths overflow."""
    from svs_torch.depth.dense_config import DenseDisparity
    from svs_torch.depth.depth_types import ObjectDepths

    generator = torch.Generator().manual_seed(seed)
    b, h, w = 4, 37, 53
    disparity = torch.rand(b, 1, h, w, generator=generator) * 40
    valid = torch.rand(b, 1, h, w, generator=generator) < torch.tensor([0.1, 0.5, 0.9, 0.5]).view(b, 1, 1, 1)
    disparity = torch.where(valid, disparity, torch.zeros_like(disparity))
    labels = torch.randint(0, 4, (b, 1, h, w), generator=generator)
    boxes = torch.tensor([[3, 2, 40, 30], [-6, -3, 30, 45], [40, 10, 25, 20], [5, 5, 0, 0]])
    slots = torch.tensor([[1, 2, -1], [2, 2, 3], [3, 1, 9], [1, 2, 3]])
    n = slots.shape[1]
    zeros = torch.zeros(b, n)
    objects = ObjectDepths(slots, torch.full((b, n), 50), zeros, torch.zeros(b, n, dtype=torch.int64),
                           torch.zeros(b, n, dtype=torch.int64), zeros, zeros, zeros,
                           torch.zeros(b, n, dtype=torch.bool), torch.zeros(b, 0, dtype=torch.int64))
    dense = DenseDisparity(disparity, valid, torch.zeros(b, dtype=torch.int64), 40, boxes, torch.full((b,), 40))
    focal, baseline = torch.tensor([100.0, 3e38, 100.0, 100.0]), torch.tensor([0.1, 10.0, 0.1, 0.1])
    doffs = torch.tensor([0.0, 0.0, -20.0, 0.0])  # pair 2: half its denominators are not positive
    return dense, labels, objects, focal, baseline, doffs


@pytest.mark.skipif(not kernels.available("object_depths"), reason="no C compiler")
@pytest.mark.parametrize("fill", [True, False])
@pytest.mark.parametrize("threads", [1, 3])
def test_object_depths_kernel_is_bit_identical_to_torch(monkeypatch, fill, threads):
    """Each pair read at its own box (clamped past the frame's edges) gives the torch path's statistics and
    counts bit for bit: with and without the row fill, repeated and padding slots, an empty box, non-positive
    denominators and overflowing depths, for any thread count."""
    from svs_torch.depth.dense_objects import dense_object_depths

    inputs = _object_depth_inputs(6)
    ran = []
    compiled = depth_kernels.object_depths
    monkeypatch.setattr(depth_kernels, "object_depths", lambda *args: ran.append(compiled(*args)) or ran[-1])
    fused = _with_threads(threads, dense_object_depths, *inputs, percentiles=(10.0, 90.0), min_valid_px=1,
                          fill_invalid=fill)
    assert len(ran) == 1 and ran[0] is not None  # the kernel, not the fallback, gave ``fused``
    monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
    reference = dense_object_depths(*inputs, percentiles=(10.0, 90.0), min_valid_px=1, fill_invalid=fill)
    for name in ("depth_median_m", "depth_low_m", "depth_high_m", "valid", "num_valid_px", "num_in_view_px"):
        assert torch.equal(getattr(fused, name), getattr(reference, name)), name
    assert fused.valid[0, :2].all() and not fused.valid[0, 2] and not fused.valid[3].any()
    assert torch.equal(fused.depth_median_m[1, 0], fused.depth_median_m[1, 1])  # a repeated slot
    assert not fused.valid[2, 2]  # label 9: no pixel


@pytest.mark.parametrize("path", ["auto", "torch"])
@pytest.mark.parametrize("own_tops", [False, True])
def test_objects_pixels_in_view_counted_by_hand(monkeypatch, path, own_tops):
    """``num_in_view_px`` counts, per slot, the measured pixels (each position of the searched box, clamped to
    the frame as ``num_valid_px`` counts them: valid, positive denominator, finite depth) at frame columns
    ``x ≥ min_disparity_px + pair_num_disparities − 1``, or from each object's own top below that where
    ``object_in_view_top_px`` gives one, as a loop over the box does, for ranges that start above and below 0, one
    wider than the frame and an empty one; ``min_in_view_px`` drops exactly the objects with fewer and changes no
    statistic."""
    from dataclasses import replace

    from svs_torch.depth.dense_objects import dense_object_depths

    if path == "torch":
        monkeypatch.setenv("SVS_TORCH_KERNELS", "torch")
    dense, labels, objects, focal, baseline, doffs = _object_depth_inputs(8)
    dense = replace(dense, min_disparity_px=torch.tensor([5, -3, 0, 2]),
                    pair_num_disparities=torch.tensor([10, 4, 80, 0]))
    if own_tops:  # below, at and above the pair's top; a repeated label (pair 1) counts from its first slot's
        dense = replace(dense, object_in_view_top_px=torch.tensor([[9, 30, 2], [0, 7, -4], [50, 90, 1], [3, 0, 1]]))
    result = dense_object_depths(dense, labels, objects, focal, baseline, doffs, min_valid_px=1)
    b, n = objects.label.shape
    expected = torch.zeros(b, n, dtype=torch.int64)
    for i in range(b):
        d_max = int(dense.min_disparity_px[i] + dense.pair_num_disparities[i]) - 1
        x0, y0, width, height = dense.crop_xywh[i].tolist()  # each position of the box, clamped to the frame
        for y in (min(max(y0 + j, 0), labels.shape[-2] - 1) for j in range(height)):
            for x in (min(max(x0 + k, 0), labels.shape[-1] - 1) for k in range(width)):
                denominator = dense.disparity_px[i, 0, y, x] + doffs[i]  # float32, as the statistics
                if not dense.valid[i, 0, y, x] or denominator <= 0:
                    continue
                if not 0 < float(focal[i] * baseline[i] / denominator) < float("inf"):
                    continue
                for k in range(n):
                    first = next(e for e in range(n) if objects.label[i, e] == objects.label[i, k])
                    top = d_max if not own_tops else min(d_max, int(dense.object_in_view_top_px[i, first]))
                    expected[i, k] += int(objects.label[i, k] > 0 and labels[i, 0, y, x] == objects.label[i, k]
                                          and x >= max(top, 0))
    assert torch.equal(result.num_in_view_px, expected)
    assert (result.num_in_view_px <= result.num_valid_px).all()
    # Pair 2's d_max lies past the frame: nothing in view, but where an object's own top lies inside it.
    assert result.num_in_view_px[2, 1:].eq(0).all() and (result.num_in_view_px[2, 0] > 0) == own_tops
    assert (result.num_in_view_px[0] > 0).any() and (result.num_in_view_px[0] < result.num_valid_px[0]).any()
    threshold = int(expected[result.valid].max())  # only the best-seen object keeps its depth
    checked = dense_object_depths(dense, labels, objects, focal, baseline, doffs, min_valid_px=1,
                                  min_in_view_px=threshold)
    assert torch.equal(checked.valid, result.valid & (expected >= threshold))
    assert result.valid.sum() > checked.valid.sum() > 0
    assert torch.equal(checked.depth_median_m[checked.valid], result.depth_median_m[checked.valid])


def test_object_depths_gradients_take_the_torch_path():
    """With gradients wanted the statistics come from the torch path, and they reach the disparities."""
    from svs_torch.depth.dense_objects import dense_object_depths

    dense, labels, objects, _, _, doffs = _object_depth_inputs(7)
    focal, baseline = torch.full((4,), 100.0), torch.full((4,), 0.1)  # no overflowing depth: finite gradients
    disparity = dense.disparity_px.clone().requires_grad_(True)
    dense = type(dense)(disparity, *(getattr(dense, f) for f in ("valid", "min_disparity_px", "num_disparities",
                                                                  "crop_xywh", "pair_num_disparities")))
    result = dense_object_depths(dense, labels, objects, focal, baseline, doffs, min_valid_px=1)
    result.depth_median_m[result.valid].sum().backward()
    assert disparity.grad is not None and torch.isfinite(disparity.grad).all() and disparity.grad.abs().sum() > 0


def _nearness_maps(generator: torch.Generator) -> list[torch.Tensor]:
    """Disparity-like maps for the nearness segmenter's statistics: uniform values, few levels (ties everywhere),
    ±inf among them, and odd and one-pixel sizes."""
    maps = []
    for shape in [(3, 1, 17, 23), (2, 1, 1, 9), (1, 1, 6, 1), (2, 1, 60, 80)]:
        values = torch.rand(shape, generator=generator) * 40
        maps += [values, values.round() / 4, torch.where(values > 36, torch.inf, torch.where(values < 2, -torch.inf,
                                                                                              values))]
    return maps


@pytest.mark.skipif(not kernels.available("median_filter"), reason="no C compiler")
@pytest.mark.parametrize("threads", [1, 3])
def test_median_filter_kernel_equals_the_sorting_path(generator, monkeypatch, threads):
    """The median kernel (segmentation/kernels/median_filter.c: a selection network up to 7×7, a register of
    pixels of a row at a time, 4 to 16, the tracked median above) against the torch path that sorts every window:
    the same values, for every window side up to the largest it takes, on rows shorter and longer than the
    network's lanes."""
    from svs_torch.segmentation.nearness_denoise import _median_filter

    for image in _nearness_maps(generator):
        for window in (1, 3, 5, 7, 9, 11, segmentation_kernels.MAX_MEDIAN_WINDOW):
            fused = _with_threads(threads, segmentation_kernels.median_filter, image, window)
            assert fused is not None
            torch.testing.assert_close(fused, _torch_path(monkeypatch, _median_filter, image, window), rtol=0, atol=0)
    image = _nearness_maps(generator)[0]
    assert segmentation_kernels.median_filter(image, segmentation_kernels.MAX_MEDIAN_WINDOW + 2) is None
    assert segmentation_kernels.median_filter(torch.where(image > 30, torch.nan, image), 7) is None
    assert segmentation_kernels.median_filter(image.double(), 7) is None


@pytest.mark.skipif(not kernels.available("region_medians"), reason="no C compiler")
@pytest.mark.parametrize("threads", [1, 3])
def test_region_medians_kernel_equals_the_sorting_path(generator, monkeypatch, threads):
    """Each region's lower median by selection (depth/kernels/region_medians.c) against the two sorts of the
    torch path, with empty labels among them and labels beyond the last region's."""
    from svs_torch.depth.quantiles import region_lower_median

    for image in _nearness_maps(generator):
        values = image.flatten(1)
        for num_labels in (0, 1, 5, 40):
            labels = torch.randint(0, num_labels + 1, values.shape, generator=generator)
            fused = _with_threads(threads, region_lower_median, values, labels, num_labels)
            eager = _torch_path(monkeypatch, region_lower_median, values, labels, num_labels)
            torch.testing.assert_close(fused, eager, rtol=0, atol=0)
            if num_labels:
                member = values[0][labels[0] == 1]
                if member.numel():
                    assert fused[0][0, 0] == member.sort().values[(member.numel() - 1) // 2]


@pytest.mark.skipif(not kernels.available("label_counts"), reason="no C compiler")
@pytest.mark.parametrize("threads", [1, 3])
def test_label_counts_kernel_equals_the_scatter_path(generator, monkeypatch, threads):
    """Each region's flagged pixels counted in one pass (segmentation/kernels/label_counts.c) against the torch path's
    scatter-add of the flags made int64, with empty batches, empty images, no region, labels no pixel holds and
    every flag set or none; a label outside [0, slots] is refused by name, as the scatter refused it."""
    from svs_torch.segmentation.nearness_regions import _label_counts

    for b, h, w in ((3, 24, 40), (1, 1, 1), (0, 5, 5), (2, 0, 7), (8, 60, 80)):
        for slots in (0, 1, 6, 300):
            labels = torch.randint(0, slots + 1, (b, 1, h, w), generator=generator)
            for flags in (torch.rand(b, 1, h, w, generator=generator) < 0.3, torch.ones(b, 1, h, w, dtype=torch.bool),
                          torch.zeros(b, 1, h, w, dtype=torch.bool)):
                fused = _with_threads(threads, _label_counts, labels, flags, slots)
                eager = _torch_path(monkeypatch, _label_counts, labels, flags, slots)
                assert fused.dtype == torch.int64 and fused.shape == (b, slots)
                assert torch.equal(fused, eager), (b, h, w, slots)
    labels = torch.randint(0, 4, (2, 1, 6, 6), generator=generator)
    flags = torch.ones(2, 1, 6, 6, dtype=torch.bool)
    for bad in (7, -1):
        labels[1, 0, 2, 3] = bad
        with pytest.raises(InputError, match=r"^labels: expected labels in \[0, 4\], got values from"):
            segmentation_kernels.label_counts(labels.flatten(1), flags.flatten(1), 4)
    assert segmentation_kernels.label_counts(labels.flatten(1).int(), flags.flatten(1), 4) is None


@pytest.mark.skipif(not kernels.available("labelled_select"), reason="no C compiler")
def test_row_quantile_equals_torch_quantile(generator):
    """The nearness rule's percentiles by selection: ``torch.quantile``'s numbers, to the bit."""
    from svs_torch.depth.quantiles import row_quantile

    for image in _nearness_maps(generator):
        for q in [(0.1, 0.9, 0.995), (0.0, 0.5, 1.0), (0.25,)]:
            torch.testing.assert_close(row_quantile(image.flatten(1), q),
                                       torch.quantile(image.flatten(1), torch.tensor(q), dim=1).T,
                                       rtol=0, atol=0, equal_nan=True)


# ---------------------------------------------------------------------------------------------------------------
# Found by an audit of the kernels' safety (hostile calls of the public and semi-public functions): two crashes,
# C integer overflows and sizes without a bound. Each call below crashed, ran undefined arithmetic, or wrapped a
# number silently before; each is now refused by name (or, for the semi-public wrapper, left to the torch path).

def _dense_objects_call(crop: list[int]):
    from svs_torch.depth.dense_config import DenseDisparity
    from svs_torch.depth.dense_objects import dense_object_depths
    from svs_torch.depth.depth_types import ObjectDepths

    dense = DenseDisparity(torch.rand(1, 1, 8, 16) * 5, torch.ones(1, 1, 8, 16, dtype=torch.bool),
                           torch.zeros(1, dtype=torch.int64), 8, torch.tensor([crop]), torch.full((1,), 8))
    zero, zero_int = torch.zeros(1, 1), torch.zeros(1, 1, dtype=torch.int64)
    objects = ObjectDepths(label=torch.tensor([[1]]), area_px=torch.full((1, 1), 5), centroid_x_px=zero,
                           side=zero_int, num_inliers=zero_int, depth_median_m=zero, depth_low_m=zero,
                           depth_high_m=zero, valid=zero_int.bool(), point_slot=torch.zeros(1, 0, dtype=torch.int64))
    return lambda: dense_object_depths(dense, torch.ones(1, 1, 8, 16, dtype=torch.int64), objects, 500.0, 0.1)


@pytest.mark.parametrize("crop", [[-2**63, 0, 4, 4], [0, 0, 40_000_000, 4], [-17, 0, 4, 4], [0, 20, 4, 4],
                                  [0, 0, 4, -1]])
def test_dense_object_depths_refuses_a_box_far_outside_its_map(crop):
    """x0 = -2^63 passed an abs() bound (abs(-2^63) is -2^63 in torch) and wrote out of bounds (SIGSEGV); a box
    4e7 wide on an 8x16 map counted 320 million valid pixels in 4.4 GB."""
    with pytest.raises(InputError, match=r"dense\.crop_xywh: expected boxes \(x0, y0, width, height\) within the "
                                         r"16x8 map widened by its size on each side"):
        _dense_objects_call(crop)()
    _dense_objects_call([-16, -8, 48, 24])()  # past the frame by its size: the border repeats there
    with pytest.raises(InputError, match=r"boxes: expected \(x0, y0, width, height\) within the 16x8 map widened"):
        depth_kernels._check_box_rows(torch.tensor([[-2**63, 0, 4, 4]]), "boxes", 1, 8, 16)


@pytest.mark.parametrize("box", [[0, 0, 100, 100], [-7, 0, 4, 4], [0, 0, 2**31 - 1, 2**31 - 1]])
def test_object_depths_kernel_refuses_a_box_far_outside_its_map(box):
    """Found by an audit: the wrapper itself bounded a box by ±2^31 only (dense_object_depths, its caller, by the
    map widened by its size): a 20000-px box on a 6 x 6 map counted 4e8 members in 8 s and 3 GB, and one of 60000
    would have asked for 36 GB."""
    args = (torch.ones(1, 6, 6, dtype=torch.bool), torch.ones(1, 6, 6, dtype=torch.int64))
    rest = (torch.ones(1, 1, dtype=torch.int64), torch.ones(1), torch.zeros(1), torch.zeros(1, 1, dtype=torch.int64),
            True, torch.tensor([0.5]))
    with pytest.raises(InputError, match=r"^boxes: expected \(x0, y0, width, height\) within the 6x6 map widened by "
                                         r"its size on each side"):
        depth_kernels.object_depths(torch.rand(1, 6, 6), *args, torch.tensor([box]), *rest)
    whole = depth_kernels.object_depths(torch.rand(1, 6, 6), *args, torch.tensor([[-6, -6, 18, 18]]), *rest)
    assert whole is None or whole[0].tolist() == [[18 * 18]]  # past the frame by its size: the border repeats


def test_semi_global_columns_leaves_no_disparity_to_the_torch_path():
    """D = 0 with H >= 2 read the empty output's null pointer (SIGSEGV)."""
    assert depth_kernels.semi_global_columns(torch.zeros(1, 0, 4, 3), torch.zeros(1), torch.zeros(1)) is None


def test_sizes_beyond_what_the_kernels_hold_are_refused():
    from svs_torch.depth.block_matching import block_match_sad
    from svs_torch.depth.dense_config import DenseConfig
    from svs_torch.depth.pooling import mean_pool
    from svs_torch.depth.search_range import disparity_search_range
    from svs_torch.geometry.lk_refinement import MatchRefinementConfig

    image = torch.rand(1, 1, 8, 16)
    with pytest.raises(InputError, match=r"min_disparity_px: expected values in \(-2\^31, 2\^31\)"):
        block_match_sad(image, image, torch.tensor([-2**63]), 8)  # the abs() bound again: C overflow
    for window in (513, 10_001, 2**64 + 1):  # 2^64 + 1 ran as a 1-pixel window through ctypes; 10 001: 1.8 GB
        with pytest.raises(InputError, match="window_size: expected an odd int from 1 to 511"):
            DenseConfig(window_size=window)
    with pytest.raises(InputError, match="texture_threshold: expected a value from 0 to 1e6"):
        DenseConfig(texture_threshold=1e308)
    with pytest.raises(InputError, match=r"margin_px: expected an int from 0 to 2\^31 - 1"):
        DenseConfig(margin_px=2**63 - 1)
    with pytest.raises(InputError, match="iterations: expected an integer from 0 to 1000"):
        MatchRefinementConfig(iterations=2**64 + 1)
    for factor in (0, 1000, -2):  # 1000 on a 4x4 image: 10 s and 820 MB of slices
        with pytest.raises(InputError, match="factor: expected an int from 1 to the images' smaller side 4"):
            mean_pool(torch.rand(1, 1, 4, 4), factor)
    # 65 534 disparities over a 64x48 pair: torch asked 68 GB, the fused kernel 34; 3 000 still run.
    from svs_torch.depth.cost_volume import _cost_volume
    from svs_torch.depth.soft_dense import soft_block_match
    small = torch.rand(1, 1, 48, 64)
    with pytest.raises(InputError, match=r"num_disparities: 65534 disparities ask for a 32 GB cost volume per image "
                                         r"row \(65534 x 131130 values"):
        block_match_sad(small, small, 0, 65534)
    zero = torch.zeros(1, dtype=torch.int64)
    with pytest.raises(InputError, match=r"ask for a 9 GB cost volume per pair \(40000 x 900 x 64 values"):
        _cost_volume(small, small, zero, zero, 900, 64, zero, 40000, torch.tensor([64]), DenseConfig())
    with pytest.raises(InputError, match=r"num_disparities: 40000 disparities ask for a 9 GB cost volume per pair"):
        soft_block_match(torch.rand(1, 1, 900, 64), torch.rand(1, 1, 900, 64), 0, 40000, 1.0)
    assert block_match_sad(small, small, 0, 3000).disparity_px.shape == small.shape
    with pytest.raises(InputError, match="disparity_px: expected finite values, got inf"):
        disparity_search_range(torch.tensor([[math.inf, 3.0]]), torch.ones(1, 2, dtype=torch.bool),
                               torch.tensor([16]), DenseConfig())
    left = image[:, 0]
    args = dict(texture=None, mask=None, boxes=torch.tensor([[0, 0, 16, 8]]), min_disparity=torch.zeros(1, dtype=torch.int64),
                counts=torch.full((1,), 4), image_hw=torch.tensor([[8, 16]]), lower_is_limit=torch.zeros(1, dtype=torch.bool),
                uniqueness_ratio=0.0, lr_max_diff_px=None, texture_min=0.0, prefilter_cap=31.0)
    with pytest.raises(InputError, match="window_size: expected an odd int from 1 to 511"):
        depth_kernels._check_block_match(left, left, window_size=3037000499, mask_margin_px=0, **args)
    with pytest.raises(InputError, match=r"mask_margin_px: expected an int from 0 to 2\^31 - 1"):
        depth_kernels._check_block_match(left, left, window_size=9, mask_margin_px=2**63 - 1, **args)


def test_label_slots_beyond_the_pixels_are_refused():
    """A label id sets the table sizes: one pixel labelled 2^24 in a 4x4 image took 2.6 GB in region_properties,
    and region_lower_median(num_labels=2**40) asked for 8.8 TB, each a RuntimeError from an allocation."""
    from svs_torch.depth.quantiles import region_lower_median
    from svs_torch.segmentation.components import region_properties

    labels = torch.zeros(1, 1, 4, 4, dtype=torch.int64)
    labels[0, 0, 1, 1] = 2**24
    with pytest.raises(InputError, match=r"labels: expected labels 1..n with n at most 65536 \(an image's pixels"):
        region_properties(labels)
    labels[0, 0, 1, 1] = 16
    assert region_properties(labels).area_px.shape == (1, 16)
    with pytest.raises(InputError, match=r"num_labels: expected at most 65536 \(the values per pair, or 65536\), "
                                         r"got 1099511627776"):
        region_lower_median(torch.rand(1, 16), torch.zeros(1, 16, dtype=torch.int64), 2**40)


def test_shapes_and_dtypes_the_kernel_audit_found_failing_deep():
    from svs_torch.depth.quantiles import labelled_quantile
    from svs_torch.depth.semi_global import semi_global_aggregate

    with pytest.raises(InputError, match="costs: expected a float tensor, got torch.int64"):
        semi_global_aggregate(torch.zeros(1, 2, 3, 3, dtype=torch.int64), torch.zeros(1), torch.zeros(1))
    with pytest.raises(InputError, match=r"values: expected \(B, P\), got \(5\)"):
        labelled_quantile(torch.rand(5), torch.zeros(5, dtype=torch.long), torch.zeros(1, 1, dtype=torch.long),
                          torch.tensor([0.5]))


def test_the_largest_window_a_configuration_takes_runs_at_every_size(data_dir):
    """A review: the dense stage widens a window by up to 1.5 for views 353-479 px wide (dense.working_window),
    and refused the 281 it made of a configured 201 (then the bound): every such pair ERROR."""
    from svs_torch.depth.dense import working_window
    from svs_torch.depth.dense_config import DenseConfig
    from svs_torch.pipeline import PipelineConfig, PipelineStatus, estimate_obstacle_depth

    assert max(working_window(width, DenseConfig(window_size=511)) for width in range(300, 700)) == (
        depth_kernels.MAX_WINDOW)
    batch = resize_stereo_batch(load_middlebury_eval3(data_dir / "middlebury_eval3_Q" / "Teddy"), (448, 336))
    result = estimate_obstacle_depth(batch, PipelineConfig(dense=DenseConfig(window_size=201)))
    assert int(result.status[0]) in (PipelineStatus.OK, PipelineStatus.NO_DENSE_DEPTH)



def _negative_view(values: torch.Tensor) -> torch.Tensor:
    """``values`` as a negative view (``z.conj().imag``): the same numbers, its memory holding their negation."""
    view = torch.complex(torch.zeros_like(values), -values).conj().imag
    assert view.is_neg() and torch.equal(view, values)
    return view


@needs_kernel
def test_negative_views_are_read_as_their_values(data_dir):
    """A one-element negative view is contiguous, so the wrappers' ``.contiguous()`` kept it and the kernels read
    its memory, the negated values: a quantile [0.5] was read as -0.5, a rank before the sorted members (memory
    outside them came back, -8.7e13), and Teddy's (1,) calibration as its negation ranged it at 0 m. Now such a
    tensor takes the torch path (found by an audit of hostile calls)."""
    from svs_torch import estimate_obstacle_depth
    from svs_torch.depth import labelled_quantile

    generator = torch.Generator().manual_seed(3)
    values = torch.rand(2, 50, generator=generator)
    labels, slots = torch.ones(2, 50, dtype=torch.int64), torch.ones(2, 1, dtype=torch.int64)
    for q in (0.5, 1.0):
        plain = labelled_quantile(values, labels, slots, [q])
        assert torch.equal(labelled_quantile(values, labels, slots, _negative_view(torch.tensor([q]))).values,
                           plain.values)
    assert not kernels.on_cpu(torch.float32, _negative_view(torch.ones(1)))
    pair = resize_stereo_batch(load_middlebury_eval3(data_dir / "middlebury_eval3_Q" / "Teddy"), (320, 267))
    viewed = dataclasses.replace(pair, **{name: _negative_view(getattr(pair, name))
                                          for name in ("focal_px", "baseline_m", "doffs_px")})
    expected, found = estimate_obstacle_depth(pair), estimate_obstacle_depth(viewed)
    assert float(expected.depth.range.r_min_m[0]) > 1.0
    assert torch.equal(found.depth.objects.depth_median_m, expected.depth.objects.depth_median_m)
    assert torch.equal(found.status, expected.status)
