"""The differentiable segmentation: gradients reach the image and the threshold, and T -> 0 gives the hard stage."""

from __future__ import annotations

import pytest
import torch

from svs_torch import InputError
from svs_torch.segmentation.morphology import dilate, erode, open_binary, structuring_element
from svs_torch.segmentation.segment import SegmentationConfig, segment_images
from svs_torch.segmentation.soft import soft_dilate, soft_erode, soft_open, soft_segment_images, soft_threshold


def blobs(batch: int, size: int, seed: int, dtype=torch.float64) -> torch.Tensor:
    noise = torch.rand(batch, 1, size, size, generator=torch.Generator().manual_seed(seed), dtype=dtype)
    smooth = torch.nn.functional.avg_pool2d(noise, 3, 1, 1)
    # Inside [0.05, 0.95], so gradcheck's perturbations stay within the valid [0, 1] range.
    return 0.05 + 0.9 * (smooth - smooth.amin()) / (smooth.amax() - smooth.amin())


def test_gradcheck_threshold_and_opening_reach_image_and_threshold():
    image = blobs(2, 7, 0).requires_grad_()
    threshold = torch.tensor([0.45, 0.55], dtype=torch.float64, requires_grad=True)
    element = structuring_element("cross", 3)

    def forward(image, threshold):
        return soft_open(soft_threshold(image, threshold, 0.1), element, 0.1)

    assert torch.autograd.gradcheck(forward, (image, threshold))
    assert torch.autograd.gradgradcheck(forward, (image, threshold))


@pytest.mark.parametrize("op", [soft_dilate, soft_erode])
def test_gradcheck_morphology_with_asymmetric_element(op):
    x = blobs(1, 6, 1).requires_grad_()
    element = torch.tensor([[True, False], [True, True]])
    assert torch.autograd.gradcheck(lambda x: op(x, element, 0.07), (x,))


def test_gradcheck_soft_segmentation_through_kept_regions():
    # 12 x 12, not 16 x 16: gradcheck runs the whole segmentation twice per input pixel (7.5 s at 16 x 16); the
    # square is kept and the rest left out as before.
    image = blobs(2, 12, 2)
    image[:, :, 3:9, 3:9] += 0.5  # a bright square that the hard stage keeps
    image = (0.95 * image / image.amax()).requires_grad_()
    threshold = torch.tensor([0.5, 0.5], dtype=torch.float64, requires_grad=True)
    config = SegmentationConfig(kernel_size=3)

    def forward(image, threshold):
        return soft_segment_images(image, threshold, config, 0.1, 0.1).masked

    assert torch.autograd.gradcheck(forward, (image, threshold))
    result = soft_segment_images(image, threshold, config, 0.1, 0.1)
    result.masked.sum().backward()
    assert image.grad.abs().sum() > 0 and threshold.grad.abs().sum() > 0
    assert torch.all(result.soft_mask[~result.hard.kept_mask] == 0)
    assert result.hard.kept_mask[:, :, 3:9, 3:9].all() and result.hard.kept_mask.sum() == 2 * 6 * 6


def test_small_temperature_gives_the_hard_stage():
    mask = torch.rand(3, 1, 24, 24, generator=torch.Generator().manual_seed(3)) > 0.45
    for shape, size in (("square", 3), ("cross", 5), ("ellipse", 5)):
        element = structuring_element(shape, size)
        x = mask.to(torch.float64)
        assert torch.equal(soft_dilate(x, element, 0.003) > 0.5, dilate(mask, element))
        assert torch.equal(soft_erode(x, element, 0.003) > 0.5, erode(mask, element))
        assert torch.equal(soft_open(x, element, 0.003) > 0.5, open_binary(mask, element))


def test_soft_segmentation_tends_to_hard_segmentation():
    image = blobs(2, 32, 4, torch.float32)
    hard = segment_images(image)
    soft = soft_segment_images(image, threshold_temperature=1e-4, morphology_temperature=2e-3)
    assert torch.equal(soft.soft_mask > 0.5, hard.kept_mask)


def test_constant_windows_are_unchanged():
    x = torch.full((1, 1, 5, 5), 0.3, dtype=torch.float64)
    element = structuring_element("square", 3)
    torch.testing.assert_close(soft_open(x, element, 0.05), x)


def test_errors_name_the_argument():
    image = torch.rand(2, 1, 8, 8)
    with pytest.raises(InputError, match=r"threshold: expected \(2\), got \(3\)"):
        soft_threshold(image, torch.zeros(3), 0.1)
    with pytest.raises(InputError, match="temperature: expected a positive temperature, got 0"):
        soft_threshold(image, torch.zeros(2), 0)
    with pytest.raises(InputError, match="element: expected at least one True offset"):
        soft_dilate(image, torch.zeros(3, 3, dtype=torch.bool))
    with pytest.raises(InputError, match="x: expected a float tensor"):
        soft_erode(image > 0.5, structuring_element("square", 3))


def test_a_soft_mask_alone_is_its_mask_in_a_batch(generator):
    """torch.sigmoid computes each vectorised run and the scalar tail of a tensor differently (3-4 % of values
    an ulp apart), and the tail falls on other pixels in a batch than alone: an image's soft binary moved with
    the images batched with it (an audit). Now each image's sigmoid is its own call."""
    image = torch.rand(8, 1, 37, 41, generator=generator)
    threshold = torch.rand(8, generator=generator)
    batched = soft_threshold(image, threshold, 0.05)
    for index in range(8):
        assert torch.equal(soft_threshold(image[index:index + 1], threshold[index:index + 1], 0.05),
                           batched[index:index + 1])


def test_empty_batches_calibration_of_another_batch_and_nan_logits_are_named():
    """Found by an audit of the differentiable side: an empty batch failed in a reshape deep in the histogram, a
    calibration of 3 for 2 pairs in a broadcast, and NaN logits left every object invalid without a word."""
    from svs_torch.segmentation import segment_images
    from svs_torch.segmentation.learned import soft_object_depths

    images = torch.rand(2, 1, 24, 32, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    for run in (segment_images, soft_segment_images):
        with pytest.raises(InputError, match="^image: expected at least one image, got an empty batch$"):
            run(images[:0])
    hard = segment_images(images)
    ones, zeros = torch.ones(2, dtype=torch.float64), torch.zeros(2, dtype=torch.float64)
    with pytest.raises(InputError, match=r"^focal_px: expected \(2\), got \(3\)$"):
        soft_object_depths(images, hard, images, torch.ones(3), ones, zeros)
    with pytest.raises(InputError, match="^logits: expected numbers, got NaN$"):
        soft_object_depths(images * float("nan"), hard, images, ones, ones, zeros)
    assert soft_object_depths(images, hard, images, ones, ones, zeros).depth_m.shape[0] == 2
    # A second audit: integer logits were taken, and one NaN disparity outside every kept region made the pair's
    # objects invalid and the logits' gradient NaN (0 · NaN). Outside the regions it is now ignored, inside refused.
    with pytest.raises(InputError, match="^logits: expected a float tensor"):
        soft_object_depths(images.long(), hard, images, ones, ones, zeros)
    images = blobs(2, 32, 4, torch.float64)
    hard = segment_images(images)
    assert hard.kept_mask.any() and not hard.kept_mask.all()
    logits = images.clone().requires_grad_()
    disparity = images + 1
    clean = soft_object_depths(logits, hard, disparity, ones, ones, zeros)
    outside = hard.kept_mask.logical_not().nonzero()[0].tolist()
    disparity[tuple(outside)] = float("nan")
    spoiled = soft_object_depths(logits, hard, disparity, ones, ones, zeros)
    assert torch.equal(spoiled.depth_m, clean.depth_m) and torch.equal(spoiled.valid, clean.valid)
    (grad,) = torch.autograd.grad(spoiled.depth_m.sum(), logits)
    assert torch.isfinite(grad).all()
    disparity[tuple(hard.kept_mask.nonzero()[0].tolist())] = float("inf")
    with pytest.raises(InputError, match="^disparity_px: expected finite values over the kept regions, got NaN or inf$"):
        soft_object_depths(logits, hard, disparity, ones, ones, zeros)


def test_an_element_off_to_one_side_gives_the_hard_filters_value_where_it_sees_nothing():
    """Found by an audit: where no offset of the element lands in the image (its only offset two columns left of
    the anchor, at the first two columns) the soft filters gave NaN, log(0 / 0); the hard ones give the max and
    min of nothing, 0 and 1. Now the same, with finite gradients."""
    x = torch.rand(1, 1, 8, 10, dtype=torch.float64, generator=torch.Generator().manual_seed(1), requires_grad=True)
    element = torch.zeros(1, 5, dtype=torch.bool)
    element[0, 0] = True
    mask = x.detach() > 0.5
    for soft, hard in ((soft_dilate, dilate), (soft_erode, erode), (soft_open, open_binary)):
        y = soft(x, element, 0.003)
        assert torch.isfinite(y).all() and torch.equal(y > 0.5, hard(mask, element)), soft.__name__
        (grad,) = torch.autograd.grad(y.sum(), x)
        assert torch.isfinite(grad).all()
    assert torch.autograd.gradcheck(lambda v: soft_open(v, element, 0.05), (x,))


def test_a_temperature_of_one_per_pair_and_a_float64_threshold_are_handled():
    """Found by an audit: a (B,) temperature failed in a bool() deep inside (a RuntimeError, not the argument
    named), and a float64 threshold made a float32 image's soft mask float64."""
    from svs_torch.depth.soft_dense import soft_block_match

    image = torch.rand(2, 1, 8, 12)
    with pytest.raises(InputError, match=r"^temperature: expected one positive number, got a tensor of shape \(2,\)$"):
        soft_threshold(image, torch.zeros(2), torch.tensor([0.1, 0.2]))
    with pytest.raises(InputError, match=r"^temperature: expected one positive number, got a tensor of shape \(2,\)$"):
        soft_block_match(image, image, 0, 4, torch.tensor([0.1, 0.2]))
    assert soft_threshold(image, torch.full((2,), 0.5, dtype=torch.float64), torch.tensor(0.1)).dtype == torch.float32


def test_gradcheck_temperatures_given_as_tensors():
    """Found by an audit: a morphology temperature given as a tensor that requires grad (a user learning it) got a
    NaN gradient (0 · inf from the border's −inf padding in exp(−inf / T)); the values were right. The threshold's
    temperature was fine."""
    image = blobs(2, 7, 2)
    threshold = torch.tensor([0.45, 0.55], dtype=torch.float64)
    element = structuring_element("square", 3)
    threshold_t = torch.tensor(0.1, dtype=torch.float64, requires_grad=True)
    morphology_t = torch.tensor(0.05, dtype=torch.float64, requires_grad=True)

    def forward(threshold_t, morphology_t):
        return soft_open(soft_threshold(image, threshold, threshold_t), element, morphology_t)

    assert torch.autograd.gradcheck(forward, (threshold_t, morphology_t))
    for op in (soft_dilate, soft_erode):
        gradient, = torch.autograd.grad(op(image, element, morphology_t).sum(), morphology_t)
        assert bool(torch.isfinite(gradient))
    with torch.no_grad():  # the same values as a plain number's
        assert torch.equal(forward(threshold_t, morphology_t), forward(0.1, 0.05))


@pytest.mark.parametrize("temperature, message", [
    (torch.tensor([1.0, 2.0]), r"^mask_temperature: expected one positive number, got a tensor of shape \(2,\)$"),
    ("1", r"^mask_temperature: expected a positive number, got '1'$"),
    (0.0, r"^mask_temperature: expected a positive number, got 0.0$"),
    (torch.tensor(0.5, device="meta"), r"^mask_temperature: expected a positive number, got tensor\(\.\.\., device='meta'")])
def test_a_mask_temperature_that_is_not_one_positive_number_is_named(temperature, message):
    """Found by an audit: soft_object_depths' mask_temperature of one per pair raised "Boolean value of Tensor with
    more than one value is ambiguous" and a string a TypeError, neither naming it (soft_threshold's and
    soft_block_match's temperatures were already checked so); a 0-d tensor that requires grad is taken. A second
    audit: a meta-device one raised a RuntimeError from its bool()."""
    from svs_torch.segmentation import segment_images
    from svs_torch.segmentation.learned import soft_object_depths

    images = blobs(2, 16, 5)
    hard, ones, zeros = segment_images(images), torch.ones(2, dtype=torch.float64), torch.zeros(2, dtype=torch.float64)
    with pytest.raises(InputError, match=message):
        soft_object_depths(images, hard, images + 1, ones, ones, zeros, temperature)
    learned = torch.tensor(0.5, dtype=torch.float64, requires_grad=True)
    depths = soft_object_depths(images, hard, images + 1, ones, ones, zeros, learned)
    assert bool(torch.isfinite(torch.autograd.grad(depths.depth_m.sum(), learned)[0]))


@pytest.mark.parametrize("foreground", ["bright", "dark"])
def test_an_8_bit_image_tends_to_the_hard_masks_at_otsus_level_too(foreground):
    """Found by an audit: the default threshold was Otsu's level / 255, where the hard stage keeps round(255 · x) >
    level; a pixel of an 8-bit image at that level stayed at 0.5 at any temperature, and with a dark foreground
    the kept mask held 0.5 there, not 1. Now the threshold sits halfway to the next level."""
    image = torch.round(blobs(2, 48, 2) * 255) / 255  # on the 1/255 grid, as a loaded image is
    config = SegmentationConfig(foreground=foreground)
    hard = segment_images(image, config)
    at_level = torch.round(image * 255) == hard.threshold_level.view(-1, 1, 1, 1)
    assert int(at_level.sum()) > 0 and bool((at_level & hard.kept_mask).any()) == (foreground == "dark")
    soft = soft_segment_images(image, config=config, threshold_temperature=1e-4, morphology_temperature=1e-4)
    torch.testing.assert_close(soft.soft_binary, hard.binary.to(image.dtype), atol=1e-3, rtol=0)
    torch.testing.assert_close(soft.soft_mask, hard.kept_mask.to(image.dtype), atol=1e-3, rtol=0)


@pytest.mark.parametrize("temperature", ["0.1", None, True, torch.tensor(0.1, device="meta")],
                         ids=["string", "None", "bool", "meta"])
def test_a_temperature_that_is_not_a_number_is_named(temperature):
    """Found by an audit: a string or None temperature raised a TypeError from a comparison, and a meta tensor a
    RuntimeError from its bool(), neither naming the argument (soft_object_depths' mask_temperature was already
    checked so); True was taken as 1. soft_segment_images' temperatures are named as it names them."""
    from svs_torch.depth.soft_dense import soft_block_match

    image, element = torch.rand(2, 1, 8, 12), structuring_element("square", 3)
    for call in (lambda: soft_threshold(image, torch.full((2,), 0.5), temperature),
                 lambda: soft_dilate(image, element, temperature), lambda: soft_open(image, element, temperature)):
        with pytest.raises(InputError, match=r"^temperature: expected a positive temperature, got "):
            call()
    for name in ("threshold_temperature", "morphology_temperature"):
        with pytest.raises(InputError, match=rf"^{name}: expected a positive temperature, got "):
            soft_segment_images(image, **{name: temperature})
    with pytest.raises(InputError, match=r"^temperature: expected a positive number, got "):
        soft_block_match(image, image, 0, 4, temperature)


@pytest.mark.parametrize("temperature", [float("inf"), torch.tensor(float("inf")), 1e39], ids=["inf", "tensor", "1e39"])
def test_a_morphology_temperature_past_the_dtypes_range_is_named(temperature):
    """Found by an audit: an inf temperature, or one past float32's largest number, gave NaN at every pixel of the
    smooth filters (inf · log 1) in silence, where soft_threshold takes the sigmoid's limit, 0.5."""
    image, element = torch.rand(2, 1, 8, 12), structuring_element("square", 3)
    for op in (soft_dilate, soft_erode, soft_open):
        with pytest.raises(InputError, match=r"^temperature: expected a finite positive temperature \(at most 3.4e\+38"):
            op(image, element, temperature)
    with pytest.raises(InputError, match=r"^morphology_temperature: expected a finite positive temperature"):
        soft_segment_images(image, morphology_temperature=temperature)
    assert bool(torch.isfinite(soft_dilate(image.double(), element, 1e39)).all())  # within float64's range
    assert torch.equal(soft_threshold(image, torch.full((2,), 0.5), temperature), torch.full_like(image, 0.5))


def test_a_threshold_or_element_on_another_device_is_named():
    """Found by an audit: a threshold on the meta device failed in a bool() deep in the finiteness check (and one on
    another device than the image's in the sum), a meta element in a bool() of its offsets, neither naming it."""
    image = torch.rand(2, 1, 8, 12)
    with pytest.raises(InputError, match=r"^threshold: expected a tensor with values, got one on the meta device$"):
        soft_threshold(image, torch.full((2,), 0.5, device="meta"))
    with pytest.raises(InputError, match=r"^threshold: expected a tensor with values, got one on the meta device$"):
        soft_segment_images(image, torch.full((2,), 0.5, device="meta"))
    for op in (soft_dilate, soft_erode, soft_open):
        with pytest.raises(InputError, match=r"^element: expected a tensor with values, got one on the meta device$"):
            op(image, structuring_element("square", 3).to("meta"))


@pytest.mark.parametrize("segmenter", ["nearness", "learned"])
def test_a_network_segmenter_is_refused_as_the_soft_segmentation_names_it(segmenter):
    """Found by an audit: the pipeline's own segmentation settings (segmenter 'nearness') were refused by
    segment_images' words, 'use segment_stereo', a hard function with no soft counterpart."""
    import dataclasses

    config = dataclasses.replace(SegmentationConfig(), segmenter=segmenter)
    with pytest.raises(InputError, match=rf"^config.segmenter: the soft segmentation relaxes the Otsu segmenter "
                                         rf"\('otsu'\), got '{segmenter}' \(its soft path: estimate_obstacle_depth"):
        soft_segment_images(torch.rand(1, 1, 16, 16), config=config)
