"""Fuzz (hypothesis) of every public function that reaches a C kernel of a stage (its ``kernels/``): drawn shapes
(empty images, K = 0, B = 0, batch lengths that do not match), values (NaN, ±inf, huge, negative), bool masks
viewed from other bytes and out-of-range sizes, each run with the kernels and with ``SVS_TORCH_KERNELS=torch``.
Both must give the same values (bit for bit where the kernel promises it, else to its stated tolerance) or both
raise the same kind of error; never a crash. ``tests/sanitize/run.sh`` runs this file against kernels built with
AddressSanitizer and UBSan, where an out-of-bounds read that happens to return is a failure too.

Derandomized, so CI sees the same examples every run; the whole file takes about 25 s on two cores. More
examples for a bug hunt: ``SVS_FUZZ_SCALE=20 pytest tests/core/test_kernel_fuzz.py``.
"""

from __future__ import annotations

import contextlib
import math
import os
from dataclasses import fields, is_dataclass

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from svs_torch.core import kernels
from svs_torch.core.errors import InputError
from svs_torch.core.types import FundamentalStatus, Keypoints
from svs_torch.depth import kernels as depth_kernels
from svs_torch.depth.block_matching import block_match_sad, dense_disparity_over_regions, fill_invalid_rows
from svs_torch.depth.cost_volume import _costs_in_cache
from svs_torch.depth.semi_global import semi_global_aggregate, semi_global_aggregate_with_winner
from svs_torch.depth.winner import _winner_stats_torch
from svs_torch.depth.dense_config import DenseConfig, DenseDisparity, DisparityRange
from svs_torch.depth.dense_objects import dense_object_depths
from svs_torch.depth.depth_types import ObjectDepths
from svs_torch.depth.quantiles import labelled_quantile, region_lower_median, row_quantile
from svs_torch.depth.search_range import disparity_search_range
from svs_torch.features import kernels as features_kernels
from svs_torch.features.descriptor import describe_surf
from svs_torch.features.surf import SurfConfig, extract_surf_features
from svs_torch.geometry import kernels as geometry_kernels
from svs_torch.geometry.lk_refinement import refine_matches_lk
from svs_torch.geometry.matched_points import MatchedPoints
from svs_torch.geometry.matching import match_sad
from svs_torch.geometry.ransac import estimate_fundamental_ransac
from svs_torch.geometry.rectification import rectify_uncalibrated
from svs_torch.geometry.row_alignment import fit_row_alignment
from svs_torch.segmentation import kernels as segmentation_kernels
from svs_torch.segmentation.components import connected_components_with_stats, region_properties
from svs_torch.segmentation.ground_plane import GroundPlaneConfig, fit_ground_plane
from svs_torch.segmentation.interior import region_interiors
from svs_torch.segmentation.nearness_denoise import _median_filter
from svs_torch.segmentation.nearness_regions import shift_regions_to_right
from svs_torch.segmentation.nearness_split import nearness_split
from svs_torch.segmentation.threshold import gray_levels_and_histogram

pytestmark = pytest.mark.skipif(not kernels.available("find_runs"), reason="no C compiler")

#: Every stage's kernel wrappers.
STAGE_KERNELS = (segmentation_kernels, features_kernels, geometry_kernels, depth_kernels)
SCALE = max(int(os.environ.get("SVS_FUZZ_SCALE", "1")), 1)


def examples(count: int) -> settings:
    return settings(max_examples=count * SCALE, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@contextlib.contextmanager
def _torch_path():
    """Every kernel off (``SVS_TORCH_KERNELS=torch``, read at each call) for the block."""
    before = os.environ.get("SVS_TORCH_KERNELS")
    os.environ["SVS_TORCH_KERNELS"] = "torch"
    try:
        yield
    finally:
        if before is None:
            del os.environ["SVS_TORCH_KERNELS"]
        else:
            os.environ["SVS_TORCH_KERNELS"] = before


def _outcome(function, *args, **kwargs):
    """The result, or the kind of error: only InputError may come out of a public function."""
    try:
        return function(*args, **kwargs)
    except InputError as error:
        assert str(error).split(":")[0], error  # names its argument first
        return InputError


def _leaves(value) -> list:
    if is_dataclass(value):
        return [leaf for f in fields(value) for leaf in _leaves(getattr(value, f.name))]
    if isinstance(value, (tuple, list)):
        return [leaf for item in value for leaf in _leaves(item)]
    return [value]


def _assert_same(fused, eager, atol: float = 0.0) -> None:
    """Both raised InputError, or every tensor equal (NaN where NaN; within ``atol`` where the kernel's sums
    round differently)."""
    assert (fused is InputError) == (eager is InputError), (fused, eager)
    if fused is InputError:
        return
    for a, b in zip(_leaves(fused), _leaves(eager), strict=True):
        if isinstance(a, torch.Tensor):
            assert a.shape == b.shape and a.dtype == b.dtype, (a.shape, b.shape, a.dtype, b.dtype)
            torch.testing.assert_close(a, b, rtol=0, atol=atol, equal_nan=True)
        else:
            assert a == b or (isinstance(a, float) and math.isnan(a) and math.isnan(b)), (a, b)


def _both(function, *args, atol: float = 0.0, **kwargs):
    fused = _outcome(function, *args, **kwargs)
    with _torch_path():
        eager = _outcome(function, *args, **kwargs)
    _assert_same(fused, eager, atol)
    return fused


SPECIALS = (math.nan, math.inf, -math.inf, 1e30, -1e30)


@st.composite
def tensors(draw, shape, low=0.0, high=1.0, specials=0.1, dtype=torch.float32):
    """A float tensor of ``shape``: uniform in [low, high], a share ``specials`` of NaN / ±inf / huge values."""
    seed = draw(st.integers(0, 2**31 - 1))
    generator = torch.Generator().manual_seed(seed)
    values = low + (high - low) * torch.rand(shape, generator=generator, dtype=torch.float64)
    if specials and draw(st.booleans()):
        pick = torch.rand(shape, generator=generator) < specials
        choice = torch.tensor(SPECIALS, dtype=torch.float64)[torch.randint(len(SPECIALS), shape, generator=generator)]
        values = torch.where(pick, choice, values)
    return values.to(dtype)


@st.composite
def masks(draw, shape, odd_bytes=True):
    """A bool mask, sometimes viewed from bytes other than 0 / 1 (a uint8 mask's ``view(torch.bool)``)."""
    seed = draw(st.integers(0, 2**31 - 1))
    generator = torch.Generator().manual_seed(seed)
    density = draw(st.sampled_from([0.0, 0.3, 0.7, 1.0]))
    mask = torch.rand(shape, generator=generator) < density
    if odd_bytes and draw(st.booleans()):
        raw = mask.to(torch.uint8) * torch.randint(1, 256, shape, generator=generator, dtype=torch.uint8)
        mask = raw.view(torch.bool)
    return mask


#: B, H, W (0: empty images). B >= 1: several torch paths fail on an empty batch (a RuntimeError from
#: ``reshape(b, -1)``, not a crash) in code no kernel reaches; ``tests/core/test_kernels.py`` covers B = 0 for the
#: kernels.
sizes = st.tuples(st.integers(1, 3), st.integers(0, 20), st.integers(0, 24))


@st.composite
def image_hws(draw, b, h, w):
    """Each pair's size: usually valid, else too large, zero, or with the wrong number of rows."""
    kind = draw(st.sampled_from(["none", "valid", "valid", "large", "zero", "rows"]))
    if kind == "none":
        return None
    rows = b if kind != "rows" else draw(st.sampled_from([max(b - 1, 0), b + 1]))
    hh = [draw(st.integers(1, max(h, 1))) for _ in range(rows)]
    ww = [draw(st.integers(1, max(w, 1))) for _ in range(rows)]
    if kind == "large" and rows:
        hh[0], ww[0] = h + draw(st.integers(1, 300)), w + draw(st.integers(0, 300))
    if kind == "zero" and rows:
        hh[0] = 0
    return torch.tensor(list(zip(hh, ww)), dtype=torch.int64).view(rows, 2)


@given(size=sizes, data=st.data())
@examples(40)
def test_block_match_sad(size, data):
    b, h, w = size
    left = data.draw(tensors((b, 1, h, w), specials=0.05))
    right = data.draw(tensors((b, 1, h, w), specials=0.05))
    minimum = data.draw(st.integers(-4, 8))
    count = data.draw(st.integers(1, 16))
    config = DenseConfig(window_size=data.draw(st.sampled_from([3, 5])), prefilter=data.draw(
        st.sampled_from(["xsobel", "none"])), lr_max_diff_px=data.draw(st.sampled_from([None, 1.0])))
    _both(block_match_sad, left, right, minimum, count, config, data.draw(image_hws(b, h, w)))


@given(size=sizes, data=st.data())
@examples(40)
def test_dense_disparity_over_regions(size, data):
    b, h, w = size
    left, right = data.draw(tensors((b, 1, h, w), specials=0.0)), data.draw(tensors((b, 1, h, w), specials=0.0))
    mask = data.draw(masks((b, 1, h, w), odd_bytes=False))
    count = data.draw(st.integers(1, 12))
    own = data.draw(st.sampled_from(["none", "within", "above", "short"]))
    rows = max(b - 1, 0) if own == "short" else b
    pair = None if own == "none" else torch.tensor(
        [data.draw(st.integers(1, count + (20 if own == "above" else 0))) for _ in range(rows)], dtype=torch.int64)
    search = DisparityRange(torch.tensor([data.draw(st.integers(0, 6)) for _ in range(b)], dtype=torch.int64),
                            count, pair)
    smoothing = data.draw(st.sampled_from([None, (1.0, 4.0)]))
    config = DenseConfig(window_size=3, smoothing_penalties=smoothing, smoothing_min_residual_levels=0.0)
    _both(dense_disparity_over_regions, left, right, mask, search, config, data.draw(image_hws(b, h, w)))


@given(shape=st.tuples(st.integers(0, 3), st.integers(1, 6), st.integers(0, 9), st.integers(0, 70)), data=st.data())
@examples(40)
def test_semi_global_aggregate(shape, data):
    costs = data.draw(tensors(shape, low=0, high=300, specials=0.1)).abs()
    p1 = data.draw(tensors(shape[:1], low=0, high=50, specials=0.0))
    p2 = p1 * data.draw(st.sampled_from([1.0, 4.0]))
    _both(semi_global_aggregate, costs, p1, p2)
    _both(semi_global_aggregate_with_winner, costs, p1, p2)


@given(shape=st.tuples(st.integers(0, 3), st.integers(1, 6), st.integers(1, 9), st.integers(1, 20)),
       data=st.data())
@examples(40)
def test_sad_volume(shape, data):
    """The dense stage's cost volume (the semi-global path's): whole levels, which the kernel sums, or fractions,
    NaN, ±inf and huge values, which it leaves to the torch loop."""
    b, d, h, w = shape
    k = data.draw(st.sampled_from([1, 3, 5]))
    whole = data.draw(st.booleans())
    left = data.draw(tensors((b, 1, h + k - 1, w + k - 1), low=-255, high=255, specials=0.0 if whole else 0.1))
    right = data.draw(tensors((b, 1, h + k - 1, w + k - 1 + d - 1), low=-255, high=255,
                              specials=0.0 if whole else 0.1))
    if whole:
        left, right = left.round(), right.round()
    outside = data.draw(st.sampled_from([None, "mask"]))
    if outside is not None:
        outside = data.draw(masks((b, d, 1, w)))
    _both(_costs_in_cache, left, right, h, w, d, k, outside)


@given(shape=st.tuples(st.integers(0, 3), st.integers(1, 6), st.integers(0, 5), st.integers(0, 24)), data=st.data())
@examples(40)
def test_winner_statistics(shape, data):
    """The winner's statistics of a volume (the noisy pairs' aggregated one): NaN, ±inf and huge costs; the box is
    at least as wide as the range, as the dense stage's always is."""
    b, d, h, w = shape
    costs = data.draw(tensors((b, d, h, w + d), low=0, high=300, specials=0.1))
    minimum = costs.min(dim=1) if costs.numel() else (costs.new_empty(b, h, w + d),
                                                        torch.zeros(b, h, w + d, dtype=torch.int64))
    _both(_winner_stats_torch, costs, minimum, data.draw(st.booleans()), data.draw(st.booleans()))


@given(shape=st.tuples(st.integers(0, 3), st.integers(0, 5), st.integers(0, 30)), data=st.data())
@examples(40)
def test_fill_invalid_rows(shape, data):
    disparity = data.draw(tensors(shape, low=0, high=40))
    _both(fill_invalid_rows, disparity, data.draw(masks(shape)))


@given(shape=st.tuples(st.integers(1, 3), st.integers(0, 12), st.integers(0, 40)), connectivity=st.sampled_from(
    [4, 8]), data=st.data())
@examples(50)
def test_connected_components(shape, connectivity, data):
    b, h, w = shape
    mask = data.draw(masks((b, 1, h, w)))
    _both(connected_components_with_stats, mask, connectivity)
    labels = (data.draw(tensors((b, 1, h, w), low=-1, high=4, specials=0.0))).to(torch.int64)
    _both(region_properties, labels)


@given(size=sizes, data=st.data())
@examples(30)
def test_gray_levels(size, data):
    _both(gray_levels_and_histogram, data.draw(tensors((size[0], 1, size[1], size[2]), low=-0.2, high=1.2,
                                                       specials=0.0)))


@given(size=st.tuples(st.integers(1, 2), st.integers(0, 48), st.integers(0, 48)), data=st.data())
@examples(20)
def test_surf_features(size, data):
    b, h, w = size
    image = data.draw(tensors((b, 1, h, w), specials=0.0))
    config = SurfConfig(max_keypoints=data.draw(st.sampled_from([0, 1, 30])), upsample=data.draw(st.booleans()),
                        metric_threshold=data.draw(st.sampled_from([0.0, 10.0, 1000.0])))
    # The descriptor kernel sums in double, the torch path in float32: descriptors within its round-off.
    _both(extract_surf_features, image, config, atol=5e-4)


@st.composite
def keypoint_sets(draw, b, k, h, w):
    xy = draw(tensors((b, k, 2), low=-5, high=max(h, w) + 5))
    scale = draw(tensors((b, k), low=0.0, high=6.0))
    valid = draw(masks((b, k)))
    zeros = torch.zeros(b, k)
    return Keypoints(xy=xy, scale=scale, score=zeros, laplacian_sign=torch.zeros(b, k, dtype=torch.int64),
                     orientation=zeros, valid=valid)


def _waves(b: int, h: int, w: int, phase: torch.Tensor, shift_px: float = 0.0) -> torch.Tensor:
    """Smooth images with structure at every place ``(B, 1, H, W)``, one phase per image."""
    y, x = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    return 0.5 + 0.4 * torch.sin((x + shift_px) / 3 + phase) * torch.cos(y / 4 - phase)


@given(size=sizes, k=st.integers(0, 6), extended=st.booleans(), data=st.data())
@examples(40)
def test_describe_surf(size, k, extended, data):
    """Extreme positions and scales (NaN, ±inf, 1e30, outside the image) must not crash and give the same
    errors and zero rows; values are compared where a descriptor is defined by the image (a keypoint inside it,
    scale >= 1): elsewhere the patch is a constant border, and a unit vector of round-off noise is any vector."""
    b, h, w = size
    image = _waves(b, h, w, data.draw(tensors((b, 1, 1, 1), high=6.0, specials=0.0)))
    keypoints = data.draw(keypoint_sets(b, k, h, w))
    fused = _outcome(describe_surf, image, keypoints, extended)
    with _torch_path():
        eager = _outcome(describe_surf, image, keypoints, extended)
        # The kernel works in double: its reference is the torch path in float64 (the float32 path's round-off
        # flips the sign of near-zero responses, which moves the extended descriptor's halves by up to 0.08).
        exact = _outcome(describe_surf, image.double(), keypoints, extended)
    assert (fused is InputError) == (eager is InputError) == (exact is InputError), (fused, eager)
    if fused is InputError:
        return
    valid = keypoints.valid.view(torch.uint8) != 0
    assert not bool(fused[~valid].any()) and not bool(eager[~valid].any())
    x, y = keypoints.xy.unbind(-1)
    defined = valid & (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1) & (keypoints.scale >= 1) & (
        keypoints.scale <= 6) & (min(h, w) >= 8)
    torch.testing.assert_close(fused[defined], exact[defined].float(), rtol=0, atol=1e-5)


@given(b=st.integers(1, 2), k=st.integers(0, 6), k2=st.integers(0, 6), d=st.sampled_from([0, 4, 64]),
       mutual=st.booleans(), band=st.sampled_from([None, 0.0, 2.5]), data=st.data())
@examples(50)
def test_match_sad(b, k, k2, d, mutual, band, data):
    left, right = data.draw(tensors((b, k, d), low=-1, high=1)), data.draw(tensors((b, k2, d), low=-1, high=1))
    valid_left, valid_right = data.draw(masks((b, k))), data.draw(masks((b, k2)))
    signs = data.draw(st.booleans())
    gates = {}
    if signs:
        gates = {"laplacian_left": torch.randint(-1, 2, (b, k), generator=torch.Generator().manual_seed(k)),
                 "laplacian_right": torch.randint(-1, 2, (b, k2), generator=torch.Generator().manual_seed(k2))}
    if band is not None:
        gates.update(xy_left=data.draw(tensors((b, k, 2), high=20)), xy_right=data.draw(tensors((b, k2, 2), high=20)),
                     epipolar_band_px=band)
    _both(match_sad, left, right, valid_left, valid_right, mutual=mutual, **gates)


@given(size=st.tuples(st.integers(1, 2), st.integers(0, 30), st.integers(0, 30)), k=st.integers(0, 5),
       data=st.data())
@examples(30)
def test_refine_matches_lk(size, k, data):
    b, h, w = size
    # Smooth images (a few blobs): on noise the Gauss-Newton steps are ill-conditioned and the kernel's double
    # sums may take another branch of a clamp; on images with structure both paths land within 1e-3 px.
    phase = data.draw(tensors((b, 1, 1, 1), high=6.0, specials=0.0))
    left, right = _waves(b, h, w, phase), _waves(b, h, w, phase, shift_px=0.7)
    xy_left = data.draw(tensors((b, k, 2), low=-3, high=max(h, w) + 3, specials=0.05))
    xy_right = xy_left - 0.5
    points = MatchedPoints(xy_left, xy_right, data.draw(masks((b, k), odd_bytes=False)))
    scale = data.draw(st.sampled_from([None, "drawn"]))
    scale = None if scale is None else data.draw(tensors((b, k), high=5.0, specials=0.0))
    fused = _outcome(refine_matches_lk, left, right, points, scale, min_correlation=-1.0)
    with _torch_path():
        eager = _outcome(refine_matches_lk, left, right, points, scale, min_correlation=-1.0)
    assert (fused is InputError) == (eager is InputError)
    if fused is not InputError:
        assert torch.equal(fused.valid, eager.valid)
        finite = torch.isfinite(eager.right).all(-1) & torch.isfinite(eager.left).all(-1) & eager.valid
        torch.testing.assert_close(fused.right[finite], eager.right[finite], rtol=0, atol=1e-3)


@given(b=st.integers(0, 3), k=st.integers(0, 30), data=st.data())
@examples(40)
def test_row_alignment_costs(b, k, data):
    """The row alignment's hypotheses scored by the kernel or by the (B, M, K) torch expression: the same
    alignment, with padding rows, repeated points (degenerate samples) and NaN / infinite / huge coordinates."""
    left = data.draw(tensors((b, k, 2), high=300.0, specials=0.05))
    right = left + data.draw(tensors((b, k, 2), low=-2.0, high=2.0, specials=0.05))
    if data.draw(st.booleans()) and k > 3:
        right[:, 1:3] = right[:, :1]  # a repeated point: its samples are singular
    valid = data.draw(masks((b, k), odd_bytes=False))
    image_hw = torch.tensor([[240, 320]] * b, dtype=torch.int64).view(b, 2)
    # With focal lengths the kernel also reads the keystone (its LU is not LAPACK's: to 1e-9).
    focal_px = data.draw(st.sampled_from([None, torch.full((b,), 300.0, dtype=torch.float64)]))
    _both(fit_row_alignment, left, right, valid, image_hw, focal_px=focal_px, atol=1e-9)


@given(b=st.integers(0, 3), k=st.integers(0, 30), dtype=st.sampled_from([torch.float32, torch.float64]),
       data=st.data())
@examples(40)
def test_rectify_uncalibrated(b, k, dtype, data):
    """Hartley's rectification with the parallel x row by the kernel or the torch path: the same statuses and
    inlier counts, homographies and epipoles to their last bits, with near-rectified and arbitrary F (NaN,
    infinite, huge, zero), points of the same kinds, inliers viewed from odd bytes and per-pair image sizes."""
    near = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
    spread = data.draw(st.sampled_from([1e-3, 1.0]))
    F = near + data.draw(tensors((b, 3, 3), low=-spread, high=spread, specials=0.05, dtype=torch.float64))
    left = data.draw(tensors((b, k, 2), high=300.0, specials=0.05, dtype=dtype))
    right = left + data.draw(tensors((b, k, 2), low=-20.0, high=2.0, specials=0.05, dtype=dtype))
    inliers = data.draw(masks((b, k)))
    image_hw = torch.tensor([[data.draw(st.integers(1, 300)), data.draw(st.integers(1, 400))] for _ in range(b)],
                            dtype=torch.int64).view(b, 2)
    fused = _outcome(rectify_uncalibrated, F.to(dtype), left, right, inliers, image_hw)
    with _torch_path():
        eager = _outcome(rectify_uncalibrated, F.to(dtype), left, right, inliers, image_hw)
    assert fused is not InputError and eager is not InputError
    assert torch.equal(fused.status, eager.status) and torch.equal(fused.num_inliers, eager.num_inliers)
    close = 1e-9 if dtype == torch.float64 else 1e-5  # float32 outputs: a float64 ulp may round the other way
    for name in ("H_left", "H_right", "epipole_left", "epipole_right"):
        torch.testing.assert_close(getattr(fused, name), getattr(eager, name), rtol=close, atol=close,
                                   equal_nan=True)
    rms = eager.rms_row_error_px.to(torch.float64)  # float32 rows round to 1e-7 of the coordinates in torch's sums
    torch.testing.assert_close(fused.rms_row_error_px.to(torch.float64), rms, rtol=1e-4, atol=1e-4, equal_nan=True)


@given(b=st.integers(0, 3), k=st.integers(0, 40), scoring=st.sampled_from(["msac", "ransac"]), data=st.data())
@examples(40)
def test_ransac_fundamental(b, k, scoring, data):
    """RANSAC by the kernel or by the torch path: the same error or results of the same form, with padding rows,
    repeated points (degenerate samples), huge and NaN coordinates (NaN only in padding: valid rows must be finite),
    and chunks and limits of any size. The two agree on the inliers but for float32 ties
    (``tests/geometry/test_ransac_kernel.py``), so here only the form and the invariants are compared."""
    left = data.draw(tensors((b, k, 2), high=data.draw(st.sampled_from([1.0, 300.0, 1e30])), specials=0.0,
                             dtype=torch.float64))
    right = left + data.draw(tensors((b, k, 2), low=-3.0, high=3.0, specials=0.0, dtype=torch.float64))
    if data.draw(st.booleans()) and k > 3:
        right[:, 1:3] = right[:, :1]
        left[:, 1:3] = left[:, :1]
    valid = data.draw(masks((b, k), odd_bytes=False))
    if data.draw(st.booleans()):
        left = torch.where(valid.unsqueeze(-1), left, math.nan)  # padding may hold anything
    settings = {"max_iterations": data.draw(st.integers(1, 300)), "chunk_size": data.draw(st.integers(1, 200)),
                "threshold_px": data.draw(st.sampled_from([1e-6, 1.0, 1e6])), "scoring": scoring,
                "confidence": data.draw(st.sampled_from([0.5, 0.99, 1.0])), "pair_seeds": torch.arange(b)}
    fused = _outcome(estimate_fundamental_ransac, left, right, valid, **settings)
    with _torch_path():
        eager = _outcome(estimate_fundamental_ransac, left, right, valid, **settings)
    assert (fused is InputError) == (eager is InputError)
    if fused is not InputError:
        for a, b_ in zip(_leaves(fused), _leaves(eager), strict=True):
            assert a.shape == b_.shape and a.dtype == b_.dtype
        assert not (fused.inliers & ~valid).any() and bool(torch.isfinite(fused.F).all())
        short = FundamentalStatus.TOO_FEW_MATCHES  # decided by the counts alone
        assert torch.equal(fused.status == short, eager.status == short)


@given(size=sizes, n=st.integers(0, 3), data=st.data())
@examples(40)
def test_shift_regions_to_right(size, n, data):
    """The kept regions moved into the right view by the kernel or the torch path: the same labels, with shifts
    past either side, halves, huge, infinite and NaN shifts (the torch path's), and empty or dropped slots."""
    b, h, w = size
    generator = torch.Generator().manual_seed(b * 100 + h * 10 + w + n)
    labels = torch.randint(0, 4, (b, 1, h, w), generator=generator)
    kept = torch.randint(-1, 4, (b, n), generator=generator)
    shift = data.draw(tensors((b, n), low=-30.0, high=30.0, specials=0.2)).round() / data.draw(st.sampled_from([1, 2]))
    _both(shift_regions_to_right, labels, kept, shift)


@given(size=sizes, n=st.integers(0, 3), radius=st.integers(0, 30), data=st.data())
@examples(40)
def test_region_interiors(size, n, radius, data):
    """The kept regions cut to their interior by the kernel or the torch path: the same labels, with empty views,
    empty, repeated or absent slots, radii past the view, pairs viewed from odd bytes, and shares that are NaN,
    infinite or outside [0, 1]."""
    b, h, w = size
    generator = torch.Generator().manual_seed(b * 100 + h * 10 + w + n + radius)
    labels = torch.randint(0, 4, (b, 1, h, w), generator=generator)
    kept = torch.randint(-1, 5, (b, n), generator=generator)
    pairs = data.draw(masks((b,)))
    share = data.draw(st.sampled_from([0.5, 0.0, 1.0, 0.3, math.nan, math.inf, -math.inf, 2.0]))
    _both(region_interiors, labels, kept, radius, pairs, share)


@given(size=sizes, data=st.data())
@examples(40)
def test_fit_ground_plane(size, data):
    """The ground plane by the kernel or the torch path, bit for bit: maps smaller than the grid's stride, NaN,
    infinite and negative disparities, odd-byte masks, baselines that are NaN or 0, and with or without focal
    lengths (some NaN) and the noisy tolerance and cells' medians (some pairs or all)."""
    b, h, w = size
    disparity = data.draw(tensors((b, 1, h, w), low=-2.0, high=40.0, specials=0.05))
    ramp = torch.linspace(0, 30, h).view(1, 1, h, 1) if h else torch.zeros(1, 1, 0, 1)
    if data.draw(st.booleans()):  # a floor-like ramp down the rows, so that some samples pass the rig's tests
        disparity = disparity * 0.05 + ramp
    measured = data.draw(masks((b, 1, h, w)))
    baseline = data.draw(st.sampled_from([torch.full((b,), 0.1), torch.tensor([0.1, math.nan, 0.0])[:b]]))
    focal = data.draw(st.sampled_from([None, torch.full((b,), 200.0), torch.tensor([200.0, math.nan, -1.0])[:b]]))
    noisy = data.draw(st.sampled_from([None, torch.ones(b, dtype=torch.bool), torch.tensor([False, True, True])[:b]]))
    config = GroundPlaneConfig(grid_columns=data.draw(st.sampled_from([8, 40])))
    _both(fit_ground_plane, disparity, measured, baseline, config, focal_px=focal, noisy=noisy)


@given(size=sizes, data=st.data())
@examples(50)
def test_nearness_split(size, data):
    """The nearness split by the kernel or the torch path, bit for bit: maps with NaN, infinite, huge and negative
    disparities, a few levels (ties at the split), flat maps, odd-byte floors that leave out some, all or none of
    a pair's pixels, and minimum near shares that never, sometimes or always take the split again."""
    b, h, w = size
    disparity = data.draw(tensors((b, 1, h, w), low=-2.0, high=60.0, specials=0.05))
    if data.draw(st.booleans()):  # a few levels: ties with the split, and flat maps
        disparity = (disparity / 15).round() * 15
    exclude = data.draw(st.sampled_from([None, "mask"]))
    if exclude is not None:
        exclude = data.draw(masks((b, 1, h, w)))
    share = data.draw(st.sampled_from([0.0, 0.1, 0.5, 1.0, -1.0, 2.0]))
    _both(nearness_split, disparity, share, exclude)  # (an empty map: its quantiles refuse it on both paths)


@given(b=st.integers(1, 3), p=st.integers(0, 40), n=st.integers(0, 3), data=st.data())
@examples(50)
def test_labelled_quantile(b, p, n, data):
    values = data.draw(tensors((b, p), low=-5, high=5))
    labels = torch.randint(-1, 4, (b, p), generator=torch.Generator().manual_seed(p + n))
    slots = torch.randint(-1, 4, (b, n), generator=torch.Generator().manual_seed(p * n + 1))
    q = data.draw(st.lists(st.sampled_from([0.0, 0.1, 0.5, 0.9, 1.0, math.nan, -0.1, 1.5]), max_size=3))
    _both(labelled_quantile, values, labels, slots, q)
    valid = data.draw(masks((b, p), odd_bytes=False))
    _both(disparity_search_range, values, valid, torch.full((b,), 40), DenseConfig())


@given(size=sizes, window=st.sampled_from([1, 3, 7, 15, 17]), data=st.data())
@examples(40)
def test_nearness_map_statistics(size, window, data):
    """The nearness segmenter's median filter, region medians and percentiles (its three kernels)."""
    b, h, w = size
    image = data.draw(tensors((b, 1, h, w), low=-3, high=40))
    _both(_median_filter, image, window)
    num_labels = data.draw(st.integers(0, 4))
    labels = torch.randint(data.draw(st.sampled_from([0, -1])), num_labels + data.draw(st.sampled_from([1, 2])),
                           (b, h * w), generator=torch.Generator().manual_seed(h * w + num_labels))
    _both(region_lower_median, image.flatten(1), labels, num_labels)
    q = data.draw(st.lists(st.sampled_from([0.0, 0.1, 0.995, 1.0, math.nan, 1.5]), min_size=1, max_size=3))
    _both(row_quantile, image.flatten(1), q)


@given(size=st.tuples(st.integers(1, 3), st.integers(0, 12), st.integers(0, 16)), n=st.integers(0, 3),
       fill=st.booleans(), data=st.data())
@examples(40)
def test_dense_object_depths(size, n, fill, data):
    b, h, w = size
    disparity = data.draw(tensors((b, 1, h, w), low=0, high=12))
    valid = data.draw(masks((b, 1, h, w)))
    labels = torch.randint(0, 3, (b, 1, h, w), generator=torch.Generator().manual_seed(h * w + n))
    box = data.draw(st.sampled_from(["whole", "over", "short"]))
    rows = max(b - 1, 0) if box == "short" else b
    crop = torch.tensor([[0, 0, w + (5 if box == "over" else 0), h]] * rows, dtype=torch.int64).view(rows, 4)
    minimum = torch.zeros(b, dtype=torch.int64)
    dense = DenseDisparity(disparity, valid, minimum, 12, crop, torch.full((b,), data.draw(st.integers(1, 14))))
    slot_labels = torch.arange(1, n + 1).expand(b, n).clone()
    zeros = torch.zeros(b, n)
    objects = ObjectDepths(label=slot_labels, area_px=torch.full((b, n), 5), centroid_x_px=zeros,
                           side=torch.zeros(b, n, dtype=torch.int64), num_inliers=torch.zeros(b, n, dtype=torch.int64),
                           depth_median_m=zeros, depth_low_m=zeros, depth_high_m=zeros,
                           valid=torch.zeros(b, n, dtype=torch.bool), point_slot=torch.zeros(b, 0, dtype=torch.int64))
    _both(dense_object_depths, dense, labels, objects, 500.0, 0.1, fill_invalid=fill, min_valid_px=1)


@pytest.mark.parametrize("wrapper, args", [
    ("block_match", lambda: (torch.rand(1, 8, 8), torch.rand(1, 8, 8), None, 3, torch.tensor([[0, 0, 9, 8]]),
                             torch.zeros(1, dtype=torch.int64), torch.tensor([4]), torch.tensor([[8, 8]]),
                             torch.ones(1, dtype=torch.bool), 0.0, None, 0.0, False)),
    ("usurf_describe", lambda: (torch.rand(1, 1, 8, 8), -1, torch.zeros(1, 2, 2), torch.ones(1, 2),
                                torch.ones(1, 2, dtype=torch.bool), False)),
    # An infinite position at an infinite scale: a NaN cast to an index in C (UBSan: "-nan is outside the range of
    # representable values of type 'long int'", usurf_describe.c's locate); found by an audit
    ("usurf_describe", lambda: (torch.rand(1, 1, 8, 8), 4, torch.tensor([[[math.inf, 5.0]]]),
                                torch.tensor([[math.inf]]), torch.ones(1, 1, dtype=torch.bool), False)),
    ("sad_nearest", lambda: (torch.rand(1, 3, 8), torch.rand(1, 3, 4), torch.ones(1, 3, dtype=torch.bool),
                             torch.ones(1, 3, dtype=torch.bool))),
    ("labelled_select", lambda: (torch.rand(1, 9), torch.ones(1, 3, dtype=torch.int64),
                                 torch.ones(1, 1, dtype=torch.int64), torch.tensor([0.5]))),
    ("labelled_select", lambda: (torch.rand(1, 9), torch.ones(1, 9, dtype=torch.int64),
                                 torch.ones(1, 1, dtype=torch.int64), torch.tensor([math.nan]))),
    ("label_runs", lambda: (torch.tensor([0, 95]), torch.tensor([3, 120]), 1, 10, 10, 8)),
    ("median_filter", lambda: (torch.rand(1, 1, 8, 8), 4)),
    ("row_alignment_cost", lambda: (torch.rand(1, 4, 3, dtype=torch.float64), torch.rand(1, 5, dtype=torch.float64),
                                    torch.rand(1, 5, dtype=torch.float64), torch.rand(1, 6, dtype=torch.float64),
                                    torch.ones(1, 5, dtype=torch.bool), 1.0)),
    ("row_alignment_cost", lambda: (torch.rand(1, 4, 3, dtype=torch.float64), *(torch.rand(1, 5, dtype=torch.float64)
                                    for _ in range(3)), torch.ones(1, 5, dtype=torch.bool), math.nan)),
    ("rectify_parallel", lambda: (torch.rand(1, 3, 3), torch.rand(1, 5, 2), torch.rand(1, 4, 2),
                                  torch.ones(1, 5, dtype=torch.bool), torch.tensor([[4, 5]]), 7, 4.0, 45.0)),
    ("rectify_parallel", lambda: (torch.rand(2, 3, 3), torch.rand(2, 5, 2), torch.rand(2, 5, 2),
                                  torch.ones(2, 5, dtype=torch.bool), torch.tensor([[4, 5]]), 7, 4.0, 45.0)),
    ("row_alignment_fit", lambda: (torch.rand(1, 5, 2, dtype=torch.float64), torch.rand(1, 5, 2, dtype=torch.float64),
                                   torch.ones(1, 6, dtype=torch.bool), torch.tensor([[4, 5]]),
                                   torch.zeros(1, dtype=torch.int64), None, {})),
    ("row_alignment_fit", lambda: (torch.rand(1, 5, 2, dtype=torch.float64), torch.rand(1, 5, 2, dtype=torch.float64),
                                   torch.ones(1, 5, dtype=torch.bool), torch.tensor([[4, 5]]),
                                   torch.zeros(1, dtype=torch.int64), torch.ones(2, dtype=torch.float64), {})),
    ("ransac_fundamental", lambda: (torch.rand(1, 8, 2, dtype=torch.float64), torch.rand(1, 9, 2, dtype=torch.float64),
                                    torch.ones(1, 8, dtype=torch.bool), torch.zeros(1, dtype=torch.int64), {})),
    ("ransac_fundamental", lambda: (torch.rand(1, 8, 2, dtype=torch.float64), torch.rand(1, 8, 2, dtype=torch.float64),
                                    torch.ones(1, 8, dtype=torch.bool), torch.zeros(2, dtype=torch.int64), {})),
    ("shift_regions", lambda: (torch.zeros(1, 1, 4, 5, dtype=torch.int64), torch.ones(2, 1, dtype=torch.int64),
                               torch.zeros(2, 1))),
    ("shift_regions", lambda: (torch.zeros(1, 1, 4, 5, dtype=torch.int64), torch.ones(1, 2, dtype=torch.int64),
                               torch.zeros(1, 3))),
    ("region_medians", lambda: (torch.rand(1, 9), torch.full((1, 9), 3), 2)),
    ("label_counts", lambda: (torch.full((1, 9), 3), torch.ones(1, 9, dtype=torch.bool), 2)),
    ("label_counts", lambda: (torch.ones(2, 9, dtype=torch.int64), torch.ones(2, 8, dtype=torch.bool), 2)),
    ("label_counts", lambda: (torch.ones(2, 9, dtype=torch.int64), torch.ones(2, 9, dtype=torch.bool), -1)),
    ("region_interiors", lambda: (torch.zeros(1, 1, 4, 5, dtype=torch.int64), torch.ones(2, 1, dtype=torch.int64), 1,
                                  torch.ones(1, dtype=torch.bool), 0.5)),
    ("region_interiors", lambda: (torch.zeros(1, 1, 4, 5, dtype=torch.int64), torch.ones(1, 1, dtype=torch.int64), -1,
                                  torch.ones(1, dtype=torch.bool), 0.5)),
    ("ground_plane_fit", lambda: (torch.rand(1, 1, 4, 5), torch.ones(1, 1, 4, 4, dtype=torch.bool), torch.ones(1),
                                  torch.ones(1), None, torch.rand(8, 5, dtype=torch.float64), {})),
    ("ground_plane_fit", lambda: (torch.rand(1, 1, 4, 5), torch.ones(1, 1, 4, 5, dtype=torch.bool), torch.ones(1),
                                  torch.ones(1), None, torch.rand(8, 4, dtype=torch.float64), {})),
    ("nearness_split", lambda: (torch.rand(2, 9), None, torch.ones(2), torch.ones(1), 0.1)),
    ("nearness_split", lambda: (torch.rand(2, 9), torch.zeros(2, 8, dtype=torch.bool), torch.ones(2), torch.ones(2),
                                0.1)),
    ("nearness_split", lambda: (torch.rand(2, 9), None, torch.ones(2), torch.ones(2), math.nan)),
    ("semi_global_columns", lambda: (torch.rand(2, 3, 4, 5), torch.zeros(1), torch.zeros(2))),
    ("semi_global_columns", lambda: (torch.rand(3, 4, 5), torch.zeros(3), torch.zeros(3))),
    ("sad_volume", lambda: (torch.rand(1, 6, 6), torch.rand(1, 6, 5), 4, 4, 3, None)),
    ("semi_global_rows", lambda: (torch.rand(2, 3, 4, 5), torch.zeros(2), torch.zeros(2), torch.rand(2, 3, 5, 4))),
    ("semi_global_rows", lambda: (torch.rand(2, 3, 4, 5), torch.zeros(1), torch.zeros(2), torch.rand(2, 3, 4, 5))),
    ("winner_statistics", lambda: (torch.rand(1, 3, 4, 5), torch.full((1, 4, 5), 3), True, True)),
    ("winner_statistics", lambda: (torch.rand(1, 3, 4, 5), torch.zeros(1, 5, 4, dtype=torch.int64), True, True)),
    ("sad_volume", lambda: (torch.rand(2, 6, 6), torch.rand(1, 6, 8), 4, 4, 3, None)),
    ("region_medians", lambda: (torch.rand(1, 9), torch.full((1, 9), -1), 2)),
    ("lk_refine", lambda: (torch.rand(1, 1, 8, 8), torch.rand(1, 1, 4, 4), torch.zeros(1, 2, 2), torch.zeros(1, 2, 2),
                           torch.ones(1, 2), torch.ones(1, 2, dtype=torch.bool), 4, 2.0)),
    ("padded_integral", lambda: (torch.rand(2, 1, 4, 4), torch.rand(2), -1)),
    ("object_depths", lambda: (torch.rand(1, 4, 4), torch.ones(1, 4, 4, dtype=torch.bool),
                               torch.ones(1, 4, 4, dtype=torch.int64), torch.tensor([[2, 0, 4, 4]] * 2),
                               torch.ones(1, 1, dtype=torch.int64), torch.ones(1), torch.zeros(1),
                               torch.zeros(1, 1, dtype=torch.int64), True, torch.tensor([0.5]))),
    ("refine_maxima", lambda: ([torch.rand(1, 4, 6, 6)], [torch.rand(1, 4, 6, 6)], [1], [[9, 15, 21, 27]],
                               torch.ones(1, 1), torch.tensor([[500]]), 1.0, 0.5)),
    ("hessian_octave", lambda: (torch.zeros(1, 1, 30, 30), 10, 0, [9, 15, 21, 27], [1.0] * 4, [1.0] * 4, 0.9,
                                torch.empty(1, 4, 2, 2), torch.empty(1, 4, 2, 2))),
    ("strongest_maxima", lambda: ([torch.rand(1, 4, 5, 5)], [torch.ones(1, 2, 3, 3, dtype=torch.bool)], 0.0, 99)),
])
def test_wrappers_refuse_what_their_kernels_cannot_read(wrapper, args):
    """Each public wrapper of a stage's ``kernels`` checks what its C code assumes: a box past the frame (or a
    box per pair for another batch), a negative pad, descriptor or label lengths that differ, runs outside the
    grid, a NaN quantile, images of different sizes, indices past the maps, a zero grid step, more maxima than
    points. (Under the sanitizer build the first of these read or wrote out of bounds before the checks.)"""
    with pytest.raises(InputError, match=r"^[A-Za-z_][\w\[\]., ]*: "):
        stage = next(module for module in STAGE_KERNELS if hasattr(module, wrapper))
        getattr(stage, wrapper)(*args())


def _stereo(b: int, h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(b * 1000 + h * 10 + w)
    return torch.rand(b, 1, h, w, generator=generator), torch.rand(b, 1, h, w, generator=generator)


def _upright(xy: torch.Tensor) -> Keypoints:
    b, k = xy.shape[:2]
    zeros = torch.zeros(b, k)
    return Keypoints(xy=xy, scale=torch.full((b, k), 2.0), score=zeros, laplacian_sign=torch.zeros(b, k,
                     dtype=torch.int64), orientation=zeros, valid=torch.ones(b, k, dtype=torch.bool))


@pytest.mark.parametrize("call, message", [
    # image_hw larger than the tensors (was: heap writes past block_match.c's map, or rows wrapping)
    (lambda: block_match_sad(*_stereo(2, 40, 50), 0, 16, image_hw=torch.tensor([[400, 500], [400, 500]])),
     r"^image_hw: expected \(height, width\) rows with 1 <= height <= 40 and 1 <= width <= 50"),
    (lambda: block_match_sad(*_stereo(2, 40, 50), 0, 16, image_hw=torch.tensor([[40, 80], [40, 80]])),
     r"^image_hw: expected .* got \[40, 80\]"),
    # batch lengths: fewer rows than pairs, counts above num_disparities (was: out-of-bounds reads)
    (lambda: block_match_sad(*_stereo(4, 40, 50), 0, 16, image_hw=torch.tensor([[40, 50]])),
     r"^image_hw: expected \(4, 2\), got \(1, 2\)"),
    (lambda: dense_disparity_over_regions(*_stereo(2, 20, 30), torch.ones(2, 1, 20, 30, dtype=torch.bool),
                                          DisparityRange(torch.zeros(2, dtype=torch.int64), 16,
                                                         torch.tensor([16, 400]))),
     r"^search.pair_num_disparities: expected values in \[1, 16\], got 400"),
    # empty images (was: SIGSEGV in lk_refine.c, usurf_describe.c, object_depths.c)
    (lambda: refine_matches_lk(*_stereo(1, 0, 30), MatchedPoints(
        torch.full((1, 3, 2), 5.0), torch.full((1, 3, 2), 5.0), torch.ones(1, 3, dtype=torch.bool))),
     r"^left: expected images of at least 1 x 1 pixels, got \(1, 1, 0, 30\)"),
    (lambda: describe_surf(torch.rand(1, 1, 20, 0), _upright(torch.full((1, 3, 2), 5.0))),
     r"^image: expected images of at least 1 x 1 pixels"),
    # a NaN quantile (was: an undefined NaN -> int cast in select_rank.h)
    (lambda: labelled_quantile(torch.rand(2, 50), torch.ones(2, 50, dtype=torch.int64),
                               torch.ones(2, 1, dtype=torch.int64), [math.nan]),
     r"^q: expected quantiles in \[0, 1\], got \[nan\]"),
    # a keypoint whose patch would need a border no memory holds
    (lambda: describe_surf(torch.rand(1, 1, 20, 20), _upright(torch.tensor([[[1e30, 5.0]]]))),
     r"^keypoints: expected every valid keypoint's patch"),
    # images the dense kernel's exact sums cannot take
    (lambda: block_match_sad(torch.full((1, 1, 8, 8), math.inf), torch.rand(1, 1, 8, 8), 0, 4),
     r"^left: expected values in \[0, 1\]"),
])
def test_issue_30_inputs_raise_named_errors(call, message):
    """The inputs the sanitizer audit of issue 30 found crashing the process (or reading out of bounds) through
    public functions now raise InputError naming the argument, with the kernels and with the torch paths."""
    with pytest.raises(InputError, match=message):
        call()
    with _torch_path(), pytest.raises(InputError, match=message):
        call()


def test_bool_masks_of_any_bytes_label_as_their_nonzero_pixels():
    """A uint8 mask viewed as bool (bytes other than 0 / 1) overran find_runs.c's counted slots; now it labels as
    the mask of its nonzero bytes, with the kernels and with the torch path (measured against that mask)."""
    generator = torch.Generator().manual_seed(5)
    raw = (torch.rand(2, 1, 64, 64, generator=generator) > 0.5).to(torch.uint8) * torch.randint(
        1, 256, (2, 1, 64, 64), generator=generator, dtype=torch.uint8)
    reference = connected_components_with_stats(raw != 0)
    for outcome in (connected_components_with_stats(raw.view(torch.bool)), _both(
            connected_components_with_stats, raw.view(torch.bool))):
        assert torch.equal(outcome[0], reference[0]) and torch.equal(outcome[1], reference[1])
