"""Stage containers, input checks and the SVS camera model."""

from __future__ import annotations

import dataclasses
import re
import warnings

import pytest
import torch

from svs_torch import SVS_CAMERA, InputError, StereoBatch, SVSCamera
from svs_torch.core.camera import parse_size
from svs_torch.core.checks import (all_finite, check_dtype, check_finite, check_finite_where, check_image, check_instance,
                                   check_shape, checked_images)
from svs_torch.depth import ObjectDepths, estimate_range, labelled_quantile, masked_quantile, point_depths
from svs_torch.features import extract_surf_features
from svs_torch.geometry.matching import match_sad
from svs_torch.geometry.ransac import estimate_fundamental_ransac


@pytest.mark.parametrize("width, expected", [(160, 138), (320, 276), (640, 553), (1280, 1105)])
def test_svs_focal_in_pixels_matches_the_protocol_table(width, expected):
    # SVS_PROTOCOL.md §5: f_px ≈ 3.60 / 4.17 × width.
    assert round(SVS_CAMERA.focal_px(width)) == expected


def test_depth_and_disparity_are_inverse_and_paper_baseline():
    assert SVS_CAMERA.baseline_m == pytest.approx(0.1075)  # paper; the firmware says 0.107
    d = SVS_CAMERA.disparity_px(1.5, 320)
    assert d == pytest.approx(276.26 * 0.1075 / 1.5, rel=1e-3)
    assert SVS_CAMERA.depth_m(d, 320) == pytest.approx(1.5)
    assert SVS_CAMERA.depth_m(0.0, 320) == float("inf")
    assert SVSCamera(baseline_m=0.107).depth_m(d, 320) < 1.5


def test_parse_size():
    assert parse_size("320x240") == (320, 240) and parse_size("640X480") == (640, 480)
    with pytest.raises(InputError, match="size: expected WIDTHxHEIGHT such as 320x240, got '320'"):
        parse_size("320")
    with pytest.raises(InputError, match="expected a positive width and height"):
        parse_size("0x240")
    # An audit: --size 100000x100000 ended a whole eval (or sweep) run in a failed 40 GB allocation.
    assert parse_size("8192x6144") == (8192, 6144)
    with pytest.raises(InputError, match="--size: expected a width and height of at most 8192 px, got '100000x100000'"):
        parse_size("100000x100000", "--size")


def test_check_shape_binds_letters_and_names_the_argument():
    assert check_shape(torch.zeros(2, 3, 3), "x", ["B", "N", "N"]) == {"B": 2, "N": 3}
    with pytest.raises(InputError, match=r"points1: expected \(B, K, 2\), got \(4, 10, 3\)"):
        check_shape(torch.zeros(4, 10, 3), "points1", ["B", "K", 2])
    with pytest.raises(InputError, match=r"x: expected \(B, N, N\), got \(2, 3, 4\)"):
        check_shape(torch.zeros(2, 3, 4), "x", ["B", "N", "N"])
    with pytest.raises(InputError, match="x: expected a torch.Tensor"):
        check_shape([1, 2], "x", ["N"])


def make_batch(b=3, h=4, w=5, **kwargs) -> StereoBatch:
    return StereoBatch.from_images(torch.rand(b, 1, h, w), torch.rand(b, 1, h, w), 276.0, 0.1075, **kwargs)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64, torch.complex64])
def test_all_finite_agrees_with_isfinite_all_for_every_kind_of_bad_value(dtype):
    """all_finite (one aminmax pass; found profiling estimate --pairs, where isfinite(x).all() of the images and
    descriptors took 4 % of the time) says what isfinite(x).all() says: NaN, +inf and -inf anywhere, alone or
    together, in a strided view or a tensor needing gradients."""
    base = torch.rand(3, 1, 7, 9).to(dtype)
    for value in (float("nan"), float("inf"), -float("inf")):
        for where in ((0, 0, 0, 0), (2, 0, 6, 8), (1, 0, 3, 4)):
            bad = base.clone()
            bad[where] = value
            assert all_finite(bad) is bool(torch.isfinite(bad).all()) is False
            assert all_finite(bad.transpose(-1, -2)) is False and all_finite(bad[:, :, ::2]) is bool(
                torch.isfinite(bad[:, :, ::2]).all())
    both = base.clone()
    both[0, 0, 0, 0], both[1, 0, 1, 1] = float("inf"), -float("inf")
    assert all_finite(both) is False and all_finite(base) is True
    if dtype.is_floating_point:
        assert all_finite(base.clone().requires_grad_()) is True
    assert all_finite(torch.empty(0, 3, dtype=dtype)) is True


def test_all_finite_takes_integers_and_bools_and_the_checks_still_name_the_bad_values():
    assert all_finite(torch.tensor([True, False])) and all_finite(torch.arange(5)) and all_finite(torch.tensor(3.0))
    assert not all_finite(torch.tensor(float("nan")))
    with pytest.raises(InputError, match="focal_px: expected finite values, got inf"):
        check_finite(torch.tensor([1.0, float("inf")]), "focal_px")
    check_finite(torch.tensor([1.0, 2.0]), "focal_px")
    with pytest.raises(InputError, match="expected finite positive values, got 0"):
        check_finite(torch.tensor([1.0, 0.0]), "focal_px", positive=True)
    truth = torch.tensor([[1.0, float("nan")], [2.0, 3.0]])
    check_finite_where(truth, "depth", torch.tensor([[True, False], [True, True]]), "valid")
    with pytest.raises(InputError, match=r"pair\(s\) \[0\] of 2"):
        check_finite_where(truth, "depth", torch.ones(2, 2, dtype=torch.bool), "valid")


def test_checked_images_are_not_ranged_again_in_the_block_and_nothing_else_is_spared():
    views = torch.rand(2, 1, 6, 8)
    bad = views.clone()
    bad[1, 0, 2, 3] = float("nan")  # what a check would refuse: a skipped check lets it through
    with checked_images(bad):
        check_image(bad, "left")
        check_image(bad.detach(), "left")  # the same memory and layout
        assert all_finite(bad)
        for other in (bad.clone(), bad[1:], bad.transpose(-1, -2)):  # other memory or layout: checked as ever
            with pytest.raises(InputError, match="left: expected values in"):
                check_image(other, "left")
        with checked_images(views):  # nested: both named
            check_image(bad, "left")
            check_image(views, "right")
    with pytest.raises(InputError, match=r"left: expected values in \[0, 1\], got NaN \(image 1 of 2\)"):
        check_image(bad, "left")  # after the block
    assert not all_finite(bad)


def test_the_pipeline_ranges_each_view_once(monkeypatch):
    """Its stages each ranged the same two views (17 full-image scans a batch of 8 at 320x240 before, 8 now)."""
    from conftest import render_border_strip_scene
    from svs_torch.pipeline import estimate_obstacle_depth

    batch = render_border_strip_scene().batch
    scans = {"left": 0, "right": 0}
    aminmax = torch.aminmax

    def counted(tensor, *args, **kwargs):
        for name in scans:
            scans[name] += tensor.data_ptr() == getattr(batch, name).data_ptr() and tensor.shape == batch.left.shape
        return aminmax(tensor, *args, **kwargs)

    monkeypatch.setattr(torch, "aminmax", counted)
    result = estimate_obstacle_depth(batch)
    assert scans == {"left": 1, "right": 1}
    assert result.status.tolist() == [0]
    bad = dataclasses.replace(batch)
    bad.left[0, 0, 5, 5] = float("nan")  # written after the batch was made: the pipeline's own check finds it
    with pytest.raises(InputError, match="left: expected values in"):
        estimate_obstacle_depth(bad)


def test_collated_views_are_not_ranged_again_and_the_pipeline_still_refuses_a_part_written_into(monkeypatch):
    """Batches made (and ranged) one by one, then collated as ``estimate --pairs`` collates them: the
    concatenated views are not scanned again (16 scans of 8 pairs' views at 320x240 before), and a part written
    into after it was made is still refused by name where the pipeline takes the batch."""
    from svs_torch.data import collate_stereo_batches
    from svs_torch.pipeline import estimate_obstacle_depth

    parts = [make_batch(), make_batch()]
    scanned = []
    aminmax = torch.aminmax
    monkeypatch.setattr(torch, "aminmax", lambda tensor, *args, **kwargs: scanned.append(tensor.shape)
                        or aminmax(tensor, *args, **kwargs))
    collated = collate_stereo_batches(parts, mode="pad")  # as estimate --pairs collates a size group
    assert collated.batch_size == 6 and (6, 1, 4, 5) not in scanned
    assert torch.equal(collated.left, torch.cat([p.left for p in parts]))
    parts[1].right[2, 0, 1, 1] = 2.0  # out of range, after that part was made
    written = collate_stereo_batches(parts, mode="pad")
    with pytest.raises(InputError, match=r"right: expected values in \[0, 1\], got min .*, max 2 \(image 5 of 6\)"):
        estimate_obstacle_depth(written)


def test_stereo_batch_from_images_broadcasts_calibration():
    batch = make_batch()
    assert batch.focal_px.shape == (3,) and batch.image_hw.tolist() == [[4, 5]] * 3
    assert batch.calibrated.dtype == torch.bool and not batch.calibrated.any()
    assert batch.batch_size == 3 and batch.size_hw == (4, 5)


def test_stereo_batch_checks_its_fields():
    with pytest.raises(InputError, match=r"right: expected the shape of left \(2, 1, 4, 5\), got \(2, 1, 4, 6\)"):
        StereoBatch.from_images(torch.rand(2, 1, 4, 5), torch.rand(2, 1, 4, 6), 276.0, 0.1)
    with pytest.raises(InputError, match=r"left: expected \(B, 1, H, W\), got \(2, 3, 4, 5\)"):
        StereoBatch.from_images(torch.rand(2, 3, 4, 5), torch.rand(2, 3, 4, 5), 276.0, 0.1)
    with pytest.raises(InputError, match=r"right: expected values in \[0, 1\]"):
        StereoBatch.from_images(torch.rand(1, 1, 4, 5), torch.rand(1, 1, 4, 5) + 1, 276.0, 0.1)
    with pytest.raises(InputError, match="disparity_valid: expected it together with disparity_px"):
        make_batch(disparity_px=torch.zeros(3, 1, 4, 5))
    with pytest.raises(InputError, match="names: expected 3 names, one per pair, got 1"):
        make_batch(names=("a",))
    # Found by an audit: one string was read as a sequence of names, its letters ("expected 1 names, got 5" for
    # "Teddy"), and a one-letter one for one pair, or a three-letter one for three, was kept as if it were one.
    with pytest.raises(InputError, match=r"^names: expected a sequence of 1 name, one per pair, got one string "
                                         r"'Teddy' \(for one pair: \('Teddy',\)\)$"):
        make_batch(1, names="Teddy")
    with pytest.raises(InputError, match="^names: expected a sequence of 3 names, one per pair, got one string 'abc'$"):
        make_batch(names="abc")
    with pytest.raises(InputError, match="names: expected a sequence of 1 name, one per pair, got one string 'T'"):
        dataclasses.replace(make_batch(1), names="T")
    # Found by an audit: a float64 right view beside a float32 left made the differentiable depth float64, its
    # values other than the float32 pair's, while the hard result stayed float32.
    with pytest.raises(InputError, match="^right: expected the left view's dtype torch.float32, got torch.float64$"):
        StereoBatch.from_images(torch.rand(1, 1, 4, 5), torch.rand(1, 1, 4, 5, dtype=torch.float64), 276.0, 0.1)
    meta = torch.zeros(1, 1, 4, 5, device="meta")  # was: RuntimeError 'Tensor.item() cannot be called on meta tensors'
    with pytest.raises(InputError, match="^left: expected an image with values, got a tensor on the meta device$"):
        StereoBatch.from_images(meta, meta, 276.0, 0.1)


def test_ground_truth_depth_masks_unknown_and_non_positive_disparity():
    disparity = torch.tensor([[[[10.0, 0.0, -5.0, 20.0]]]])
    valid = torch.tensor([[[[True, True, True, False]]]])
    batch = StereoBatch.from_images(torch.rand(1, 1, 1, 4), torch.rand(1, 1, 1, 4), 100.0, 0.5, doffs_px=2.0,
                                    calibrated=True, disparity_px=disparity, disparity_valid=valid)
    depth, ok = batch.ground_truth_depth_m()
    assert ok.tolist() == [[[[True, True, False, False]]]]
    torch.testing.assert_close(depth[ok], torch.tensor([50.0 / 12.0, 25.0]))
    uncalibrated = StereoBatch.from_images(batch.left, batch.right, 100.0, 0.5, disparity_px=disparity,
                                           disparity_valid=valid)
    assert not uncalibrated.ground_truth_depth_m()[1].any()


def test_select_and_to():
    batch = make_batch(names=("a", "b", "c"))
    sub = batch.select([2, 0])
    assert sub.names == ("c", "a") and torch.equal(sub.left, batch.left[[2, 0]])
    assert batch.select(slice(1, None)).names == ("b", "c")
    assert batch.select(torch.tensor([False, True, False])).names == ("b",)
    double = batch.to(dtype=torch.float64)
    assert double.left.dtype == torch.float64 and double.image_hw.dtype == torch.int64
    # Nothing to move or cast: the batch itself, not a validated copy (collating a list pays for that per pair).
    assert batch.to(dtype=torch.float32) is batch and batch.to("cpu") is batch and double.to() is double
    assert batch.to("cpu", torch.float64).left.dtype == torch.float64


def _meta(*shape, dtype=torch.float32):
    return torch.ones(*shape, dtype=dtype, device="meta")


@pytest.mark.parametrize("call, name", [
    (lambda: match_sad(_meta(1, 5, 64), _meta(1, 5, 64), torch.ones(1, 5, dtype=torch.bool),
                       torch.ones(1, 5, dtype=torch.bool)), "desc_left"),
    (lambda: estimate_fundamental_ransac(_meta(1, 20, 2), _meta(1, 20, 2), torch.ones(1, 20, dtype=torch.bool)),
     "points_left"),
    (lambda: estimate_fundamental_ransac(torch.rand(1, 20, 2), torch.rand(1, 20, 2), _meta(1, 20, dtype=torch.bool)),
     "valid"),
    (lambda: estimate_range(_meta(1, 5), _meta(1, 5, dtype=torch.bool), 276.0, 0.1), "disparity_px"),
    (lambda: point_depths(_meta(1, 5), _meta(1, 5, dtype=torch.bool), 276.0, 0.1), "disparity_px"),
    (lambda: masked_quantile(_meta(2, 5), _meta(2, 5, dtype=torch.bool), [0.5]), "values"),
    (lambda: labelled_quantile(_meta(1, 6), _meta(1, 6, dtype=torch.int64), _meta(1, 2, dtype=torch.int64), [0.5]),
     "values"),
    (lambda: extract_surf_features(torch.rand(1, 1, 40, 40), mask=_meta(1, 1, 40, 40, dtype=torch.bool)), "mask"),
])
def test_a_meta_device_tensor_is_named_by_every_stage(call, name):
    """Found by an audit: a meta-device tensor (shapes without values) given to a stage failed deep in torch, at
    the first check that read a value ("Tensor.item() cannot be called on meta tensors", "Tensor on device meta is
    not on the expected device cpu!"), naming no argument; check_dtype now refuses it by name."""
    with pytest.raises(InputError, match=f"^{name}: expected a tensor with values, got one on the meta device$"):
        call()


def _sparse(*shape, dtype=torch.float32):
    return torch.ones(*shape, dtype=dtype).to_sparse()


def _quantized(*shape):
    with warnings.catch_warnings():  # torch 2.13 deprecates quantized tensors; a caller may still hold one
        warnings.simplefilter("ignore", UserWarning)
        return torch.quantize_per_tensor(torch.ones(*shape), 1.0, 0, torch.qint8)


_LABELS = torch.ones(2, 6, dtype=torch.int64)


@pytest.mark.parametrize("call, message", [
    (lambda: labelled_quantile(torch.rand(2, 6), _sparse(2, 6, dtype=torch.int64), _LABELS[:, :1], [0.5]),
     "labels: expected a dense tensor, got layout torch.sparse_coo"),
    (lambda: labelled_quantile(_sparse(2, 6), _LABELS, _LABELS[:, :1], [0.5]),
     "values: expected a dense tensor, got layout torch.sparse_coo"),
    (lambda: extract_surf_features(torch.rand(1, 1, 40, 40), mask=_sparse(1, 1, 40, 40, dtype=torch.bool)),
     "mask: expected a dense tensor, got layout torch.sparse_coo"),
    (lambda: match_sad(_sparse(1, 5, 64), torch.rand(1, 5, 64), torch.ones(1, 5, dtype=torch.bool),
                       torch.ones(1, 5, dtype=torch.bool)), "desc_left: expected a dense tensor"),
    (lambda: estimate_fundamental_ransac(torch.rand(1, 20, 2), torch.rand(1, 20, 2), torch.ones(1, 20, dtype=torch.bool),
                                         pair_seeds=_quantized(1)),
     "pair_seeds: expected an int tensor (int8, int16, int32, int64 or uint8), got torch.qint8"),
    (lambda: labelled_quantile(torch.rand(2, 6), _LABELS.to(torch.uint64), _LABELS[:, :1], [0.5]),
     "labels: expected an int tensor (int8, int16, int32, int64 or uint8), got torch.uint64"),
    (lambda: StereoBatch(*[torch.rand(1, 1, 8, 8)] * 2, torch.ones(1), torch.ones(1), torch.zeros(1),
                         torch.zeros(1, dtype=torch.bool), torch.tensor([[8, 8]], dtype=torch.uint16)),
     "image_hw: expected an int tensor (int8, int16, int32, int64 or uint8), got torch.uint16"),
])
def test_sparse_quantized_and_wide_unsigned_tensors_are_named(call, message):
    """Found by an audit of hostile calls into the stages: a sparse labels tensor reached the quantile kernel's
    wrapper and failed in its .contiguous() ("unsupported memory format option Contiguous"), a sparse mask in
    SURF's; a qint8 or uint16 / uint64 tensor passed as "int" and failed in torch ('"gt_cpu" not implemented for
    'UInt64'', "load_scalar: invalid type"). check_dtype now names the argument."""
    with pytest.raises(InputError, match=f"^{re.escape(message)}"):
        call()


def test_an_error_takes_the_article_its_expectation_needs():
    """A library user's audit: match_sad's Laplacian signs as floats said "expected a int tensor", and a wrong
    container "expected a ObjectDepths"."""
    from svs_torch.core.checks import check_dtype, check_instance
    from svs_torch.depth import ObjectDepths

    with pytest.raises(InputError, match=r"^labels: expected an int tensor, got torch.float32$"):
        check_dtype(torch.zeros(1), "labels", "int")
    with pytest.raises(InputError, match=r"^x: expected an int or bool tensor, got torch.float32$"):
        check_dtype(torch.zeros(1), "x", "int|bool")
    with pytest.raises(InputError, match=r"^mask: expected a bool tensor, got torch.float32$"):
        check_dtype(torch.zeros(1), "mask", "bool")
    with pytest.raises(InputError, match=r"^objects: expected an ObjectDepths, got int$"):
        check_instance(1, "objects", ObjectDepths)
    # A list or a number where a tensor belongs failed on .is_meta inside the check (AttributeError; an audit of the
    # library called by hand: svs_torch.pipeline.soft.quantize_straight_through([0.5])).
    with pytest.raises(InputError, match=r"^image: expected a float32 or float64 tensor, got list$"):
        check_dtype([0.5], "image", "float")
    with pytest.raises(InputError, match=r"^labels: expected an int tensor, got int$"):
        check_dtype(1, "labels", "int")
    with pytest.raises(InputError, match=r"^batch: expected a StereoBatch, got int$"):
        check_instance(1, "batch", StereoBatch)
