"""The two views' exposures matched, the darker onto the brighter (svs_torch.pipeline.exposure, issue 33): the
affine map against numpy's quantiles, the dead band, gradients, refusals, and a brighter right camera ranged as the
pair was."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from svs_torch import InputError
from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth
from svs_torch.pipeline.exposure import ExposureConfig, exposures_differ, match_exposure

#: The one-sided clipping rule (``PipelineConfig.exposure_right_clipped``) at the share chosen on the tuning sets.
CLIPPED_RULE = ExposureConfig(min_right_clipped_share=0.05)


def _views(generator: torch.Generator, b: int = 3, h: int = 24, w: int = 32) -> torch.Tensor:
    return 0.1 + 0.7 * torch.rand(b, 1, h, w, generator=generator, dtype=torch.float64)


def test_the_darker_view_is_mapped_onto_the_brighter_ones_quartiles(generator):
    """Against numpy: the map is the affine one through both views' quartiles (np.quantile's linear rule), applied
    to the darker view (the lower upper quartile): the right view where it is darker, else the left by the
    inverse. Pairs: a right camera 30 % brighter, one darker with a raised black level, the same exposure, and one
    brighter by its black level alone."""
    left = _views(generator, b=4).float()
    right = (left * torch.tensor([1.3, 0.7, 1.0, 1.0]).view(-1, 1, 1, 1)
             + torch.tensor([0.0, 0.06, 0.0, 0.1]).view(-1, 1, 1, 1)).clamp(0, 1)
    hw = torch.tensor([[24, 32]] * 4)
    mapped_left, mapped_right, changed = match_exposure(left, right, hw)
    assert changed.tolist() == [True, True, False, True]
    for i in (0, 1, 3):
        ql, qr = (np.quantile(v[i].flatten().numpy().astype(np.float64), [0.25, 0.75]) for v in (left, right))
        scale = (ql[1] - ql[0]) / (qr[1] - qr[0])
        offset = ql[0] - scale * qr[0]
        if qr[1] <= ql[1]:  # pair 1: the right camera is the darker one
            assert i == 1 and torch.equal(mapped_left[i], left[i])
            np.testing.assert_allclose(mapped_right[i].numpy(), np.clip(scale * right[i].numpy() + offset, 0, 1),
                                       atol=2e-6)
            np.testing.assert_allclose(mapped_right[i].numpy(), left[i].numpy(), atol=2e-3)
        else:  # pairs 0 and 3: the right camera brighter (pair 0 clipped where left * 1.3 > 1)
            assert i in (0, 3) and torch.equal(mapped_right[i], right[i])
            np.testing.assert_allclose(mapped_left[i].numpy(), np.clip((left[i].numpy() - offset) / scale, 0, 1),
                                       atol=2e-6)
            # Both views now clip the same highlights: the point of mapping the darker view up.
            np.testing.assert_allclose(mapped_left[i].numpy(), right[i].numpy(), atol=2e-3)
            assert i == 3 or bool((mapped_left[i] == 1).any())
    assert torch.equal(mapped_left[2], left[2]) and torch.equal(mapped_right[2], right[2])  # untouched, bit for bit


def test_views_that_agree_or_a_flat_view_are_left_alone(generator):
    left = _views(generator).float()
    hw = torch.tensor([[24, 32]] * 3)
    right = left * 1.02  # within the dead band
    mapped_left, mapped_right, changed = match_exposure(left, right, hw)
    assert mapped_left is left and mapped_right is right and not bool(changed.any())
    flat = torch.full_like(left, 0.5)
    for one, other in ((left, flat), (flat, left)):  # nothing to stretch, or nothing to stretch onto
        mapped_left, mapped_right, changed = match_exposure(one, other, hw)
        assert mapped_left is one and mapped_right is other and not bool(changed.any())
    assert bool(match_exposure(left, left * 1.02, hw, ExposureConfig(min_change=0.0))[2].all())


def test_the_exposure_change_is_what_min_change_bounds(generator):
    """exposure_change against numpy's quartiles: |scale − 1| + |offset| of the map through both views' quartiles
    (a right camera 30 % darker: about 1 / 0.7 − 1), 0 for the same views and for a flat view; a pair is mapped
    exactly where it exceeds min_change; a wrong shape is refused by name."""
    from svs_torch.pipeline.exposure import exposure_change

    left = _views(generator, b=4).float()
    right = torch.cat([left[:1] * 0.7, left[1:2], left[2:3] * 1.1 + 0.02, torch.full_like(left[3:], 0.5)])
    hw = torch.tensor([[24, 32]] * 4)
    change = exposure_change(left, right, hw)
    for i in (0, 2):
        ql, qr = (np.quantile(v[i].flatten().numpy().astype(np.float64), [0.25, 0.75]) for v in (left, right))
        scale = (ql[1] - ql[0]) / (qr[1] - qr[0])
        assert change[i].item() == pytest.approx(abs(scale - 1) + abs(ql[0] - scale * qr[0]), abs=1e-5)
    assert change[0].item() == pytest.approx(1 / 0.7 - 1, abs=1e-4)
    assert change[1].item() == 0 and change[3].item() == 0
    for min_change in (0.05, 0.14, 0.5):
        expected = (change > min_change).tolist()
        assert exposures_differ(left, right, hw, ExposureConfig(min_change=min_change)).tolist() == expected
        assert match_exposure(left, right, hw, ExposureConfig(min_change=min_change))[2].tolist() == expected
    with pytest.raises(InputError, match=r"^right: expected \(4, 1, 24, 32\)"):
        exposure_change(left, right[:, :, :12], hw)


def test_gradients_flow_to_both_views(generator):
    hw = torch.tensor([[5, 6]] * 2)
    for gain in (0.6, 1.3):  # the right view mapped, then the left one
        left = _views(generator, b=2, h=5, w=6).mul(0.7).requires_grad_(True)
        right = (left.detach() * gain + 0.05).requires_grad_(True)
        which = 1 if gain < 1 else 0
        assert torch.autograd.gradcheck(lambda a, b: match_exposure(a, b, hw)[which], (left, right))


@pytest.mark.parametrize("min_right_clipped_share", [None, 0.01])
def test_a_pairs_gradients_are_the_same_alone_and_batched(min_right_clipped_share):
    """The gradient to a pair's map (scale, offset) sums over its pixels: batched, that sum was split among the
    threads by the batch's size, and pair 0's image gradients moved with the pairs beside it (5e-8 through the
    differentiable pipeline at 320x240, 2 threads; an audit). Now the same bit for bit, values too."""
    generator = torch.Generator().manual_seed(3)
    left = torch.rand(3, 1, 240, 320, generator=generator) * 0.8
    right = (left * 1.4 + 0.02).clamp(max=1.0)  # brighter and clipped: the left view is mapped up
    weights = torch.rand(1, 1, 240, 320, generator=generator)
    config = ExposureConfig(min_right_clipped_share=min_right_clipped_share)
    image_hw = torch.tensor([[240, 320]] * 3)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    found = []
    try:
        for count in (1, 3):
            views = (left[:count].clone().requires_grad_(), right[:count].clone().requires_grad_())
            mapped_left, mapped_right, changed = match_exposure(*views, image_hw[:count], config)
            assert bool(changed.all())
            loss = ((mapped_left[:1] + mapped_right[:1]) * weights).sum()
            found.append([mapped_left[0].detach(), *(g[0] for g in torch.autograd.grad(loss, views))])
    finally:
        torch.set_num_threads(before)
    assert all(torch.equal(alone, batched) for alone, batched in zip(*found))


def test_bad_input_is_refused_by_name():
    images = torch.rand(2, 1, 8, 8)
    with pytest.raises(InputError, match=r"^image_hw: expected every pair to fill"):
        match_exposure(images, images, torch.tensor([[8, 8], [6, 8]]))
    with pytest.raises(InputError, match=r"^right: expected"):
        match_exposure(images, torch.rand(2, 1, 8, 7), torch.tensor([[8, 8]] * 2))
    with pytest.raises(InputError, match=r"^quantiles"):
        ExposureConfig(quantiles=(0.75, 0.25))
    with pytest.raises(InputError, match=r"^min_change"):
        ExposureConfig(min_change=float("nan"))


def test_only_a_right_view_clipped_more_is_mapped_fitted_below_the_clip(generator):
    """``min_right_clipped_share``: of four pairs (a right camera 80 % brighter, 35 % of its view clipped; the same
    scene with the left camera brighter; a right camera 20 % brighter that clips nothing; the same exposure), only
    the first is mapped, against numpy: the affine map through both views' quantiles at (0.25, 0.75) × (1 − s), s
    the larger clipped share, so both lie below the plateau, where the quartiles would put the right's upper one
    on it and stretch the left view too little."""
    left = _views(generator, b=4).float()
    gain = torch.tensor([1.8, 1 / 1.8, 1.2, 1.0]).view(-1, 1, 1, 1)
    right = (left * gain).clamp(0, 1)
    left = torch.cat([left[:1], (left[1:2] * 1.8).clamp(0, 1), left[2:]])
    hw = torch.tensor([[24, 32]] * 4)
    config = ExposureConfig(min_right_clipped_share=0.05)
    shares = [float((v[0] == 1).float().mean()) for v in right]
    assert shares[0] > 0.3 and shares[2] == shares[3] == 0
    mapped_left, mapped_right, changed = match_exposure(left, right, hw, config)
    assert changed.tolist() == [True, False, False, False]
    assert exposures_differ(left, right, hw, config).tolist() == changed.tolist()  # the same selection, unmapped
    assert torch.equal(mapped_right, right) and torch.equal(mapped_left[1:], left[1:])
    unclipped = 1 - max(float((v[0] >= 254.5 / 255).float().mean()) for v in (left, right))
    ql, qr = (np.quantile(v[0].flatten().numpy().astype(np.float64), [0.25 * unclipped, 0.75 * unclipped])
              for v in (left, right))
    scale = (ql[1] - ql[0]) / (qr[1] - qr[0])
    offset = ql[0] - scale * qr[0]
    np.testing.assert_allclose(mapped_left[0].numpy(), np.clip((left[0].numpy() - offset) / scale, 0, 1), atol=2e-6)
    np.testing.assert_allclose(mapped_left[0].numpy(), right[0].numpy(), atol=2e-3)  # both clip the same pixels
    quartiles = match_exposure(left[:1], right[:1], hw[:1])[0]
    assert float((quartiles - right[:1]).abs().max()) > 0.05  # the quartile fit is off by more than noise
    # Nothing clipped more in the right view: the views as they were, and a share out of range is refused.
    same_left, same_right, none = match_exposure(left[2:], right[2:], hw[2:], config)
    assert not bool(none.any()) and torch.equal(same_left, left[2:]) and torch.equal(same_right, right[2:])
    for share in (0, 1.5, float("nan"), "0.1"):
        with pytest.raises(InputError, match=r"^min_right_clipped_share: expected a share in \(0, 1\]"):
            ExposureConfig(min_right_clipped_share=share)


def test_the_fit_below_the_clip_passes_gradients_to_both_views(generator):
    hw = torch.tensor([[5, 6]])
    left = _views(generator, b=1, h=5, w=6).requires_grad_(True)
    brighter = left.detach() * 1.6
    # Clipped pixels at 1 and the others 0.02 below theirs: no pixel near the clip level for gradcheck's steps.
    right = torch.where(brighter >= 1, 1.0, brighter - 0.02).requires_grad_(True)
    config = ExposureConfig(min_right_clipped_share=0.05)
    assert bool(match_exposure(left, right, hw, config)[2][0])
    assert torch.autograd.gradcheck(lambda a, b: match_exposure(a, b, hw, config)[0], (left, right))


def _real_rig():
    import sys

    from conftest import REPO_ROOT

    sys.path.insert(0, str(REPO_ROOT / "experiments"))
    import real_rig

    return real_rig


@pytest.mark.parametrize("exposure, retry, clipped, matched", [
    (None, None, None, False), (None, ExposureConfig(), None, True), (ExposureConfig(), None, None, True),
    (None, None, CLIPPED_RULE, True), (None, ExposureConfig(), CLIPPED_RULE, True)])
def test_a_brighter_right_camera_is_ranged_with_the_option(data_dir, exposure, retry, clipped, matched):
    """Middlebury Piano (a tuned scene) at 320×240 with its right view 30 % brighter (experiments/real_rig.py's
    "gain +30%"): ranged wrong without the exposure matched (89.3 %: the clipped patch's wrong matches made the
    nearness split be taken again, and the regions it kept were not the obstacles; before that rule, unranged),
    ranged to its clean accuracy with it: before every stage, in the second run of the pair whose split was taken
    again (the default; experiments/exposure.md), or before every stage because its right view clips 7 % of its
    pixels, the left none (``exposure_right_clipped``)."""
    from svs_torch.evaluation import evaluate_result

    real_rig = _real_rig()
    batch = real_rig.resample(real_rig.load_scene(data_dir / "middlebury_eval3_Q" / "Piano"), "320x240")
    bright = real_rig.stack_conditions(batch, [("gain +30%", batch.left, real_rig.misalign_right(
        batch.right, real_rig.Misalignment(gain=0.3), float(batch.focal_px[0])))])
    result = estimate_obstacle_depth(bright, PipelineConfig(exposure=exposure, exposure_retry=retry,
                                                            exposure_right_clipped=clipped))
    evaluation = evaluate_result(bright, result)[0]
    assert bool(result.exposure_matched[0]) == matched
    if matched:
        assert evaluation.status == "OK" and evaluation.acc_objects_pct > 97
        assert not bool(result.segmentation.split_retaken[0])
    else:
        assert evaluation.status != "OK" or evaluation.acc_objects_pct < 95
        assert bool(result.segmentation.split_retaken[0])


def test_a_right_camera_clipping_a_bright_scene_is_ranged_as_the_scene_is(data_dir):
    """Tuned Motorcycle and Playroom at 320×240 made bright (``real_rig.py --brightness 1.8``: 32 % and 34 % of
    the left view clipped), their right camera 30 % brighter still (45 % and 44 % clipped) or 30 % darker. The
    highlights clipped in the right view alone drew wrong matches that moved the medians (97.5 and 98.4 % per
    object); ``exposure_right_clipped`` maps the left view up first, fitted below the clip, and ranges them within
    0.6 points of the bright pair (99.4 and 99.9 %, against 100.0 and 99.6). The darker right views, whose left view
    clips more, are left as they are. (Off by default: the held-out corners with a gain fell, experiments/
    real_rig.md.)"""
    from svs_torch.evaluation import evaluate_result

    real_rig = _real_rig()
    for name in ("Motorcycle", "Playroom"):
        batch = real_rig.brightened(real_rig.resample(real_rig.load_scene(data_dir / "middlebury_eval3_Q" / name),
                                                      "320x240"), 1.8)
        views = [("clean", batch.left, batch.right)] + [
            (f"gain {gain:+}", batch.left, real_rig.misalign_right(batch.right, real_rig.Misalignment(gain=gain),
                                                                    float(batch.focal_px[0]))) for gain in (0.3, -0.3)]
        stacked = real_rig.stack_conditions(batch, views)
        clipped = estimate_obstacle_depth(stacked, PipelineConfig(exposure_right_clipped=CLIPPED_RULE))
        off = estimate_obstacle_depth(stacked, PipelineConfig())
        assert clipped.exposure_matched.tolist() == [False, True, False]
        (clean, brighter, darker), (_, brighter_off, darker_off) = (
            [e.acc_objects_pct for e in evaluate_result(stacked, r)] for r in (clipped, off))
        assert brighter > 99.3 and brighter > clean - 0.6 and brighter_off < 98.5
        assert darker == darker_off


def test_a_clipping_right_camera_is_matched_by_mapping_the_left_view_up(data_dir):
    """Piano at 320×240 behind a right camera 50 % brighter, 18 % of its view clipped at white. Mapped down, the
    clipped wall beside the lamp stayed a flat patch facing a textured one, the nearness segmenter kept it as a
    near region and the pair stayed unranged (0 %); mapping the darker left view up clips the same patch in both
    views, and the default retry ranges the pair (99.4 %)."""
    from svs_torch.evaluation import evaluate_result

    real_rig = _real_rig()
    batch = real_rig.resample(real_rig.load_scene(data_dir / "middlebury_eval3_Q" / "Piano"), "320x240")
    clipped = real_rig.misalign_right(batch.right, real_rig.Misalignment(gain=0.5), float(batch.focal_px[0]))
    assert float((clipped == 1).float().mean()) > 0.15
    bright = real_rig.stack_conditions(batch, [("gain +50%", batch.left, clipped)])
    result = estimate_obstacle_depth(bright, PipelineConfig())
    evaluation = evaluate_result(bright, result)[0]
    assert bool(result.exposure_matched[0]) and bool(result.verified[0])
    assert evaluation.status == "OK" and evaluation.acc_objects_pct > 97


def test_a_brighter_larger_right_view_with_white_patches_is_ranged(data_dir):
    """Tuned Pipes and Teddy at 320×240 behind a right camera 30 % brighter and 2 % larger (experiments/real_rig.py's
    gain and scale, both within issue 33's envelope), 6 % and 4 % of its view clipped at white, in one batch with
    the clean pairs. Each misaligned pair is row-aligned and rectified; warping its white patches blended 1.0s to
    one ulp above 1, which the row-aligned segmentation refused, and the whole batch stopped with an InputError.
    Now every pair is ranged about as the clean one is: 97.8 and 99.97 % against 98.5 and 99.7 % (Pipes 98.6 %
    with the 7×7 nearness map: the gain lifts the pair's matching residual past the gate of the wider window for
    noisy pairs, whose map cuts its regions differently, 0.7 points below the clean pair; issue 33 asks 0.5)."""
    from svs_torch.evaluation import evaluate_result

    real_rig = _real_rig()
    misaligned, clean = [], []
    for name in ("Pipes", "Teddy"):
        batch = real_rig.resample(real_rig.load_scene(data_dir / "middlebury_eval3_Q" / name), "320x240")
        right = real_rig.misalign_right(batch.right, real_rig.Misalignment(scale=0.02, gain=0.3),
                                        float(batch.focal_px[0]))
        assert float((right == 1).float().mean()) > 0.03
        stacked = real_rig.stack_conditions(batch, [("clean", batch.left, batch.right), ("loose", batch.left, right)])
        result = estimate_obstacle_depth(stacked, PipelineConfig())
        assert result.row_aligned.tolist() == [False, True]
        clean_eval, loose_eval = evaluate_result(stacked, result)
        assert clean_eval.status == loose_eval.status == "OK"
        misaligned.append(loose_eval.acc_objects_pct)
        clean.append(clean_eval.acc_objects_pct)
    assert min(misaligned) > 97.5 and all(m > c - 1.0 for m, c in zip(misaligned, clean))


@pytest.mark.parametrize("size", ["320x240", "native"])
def test_the_retry_keeps_a_pair_lit_by_two_lamps(data_dir, size):
    """MiddEval3 PianoL (Piano under a second lamp) in one batch with Piano behind a right camera 30 % brighter.
    Matching the exposure before every stage ranges the brighter pair but costs PianoL accuracy (99.2 -> 98.6 % at
    320×240; native 99.2 -> 98.6 % with the 7×7 nearness map, -> 99.3 % with the wider window for noisy pairs;
    before the nearness split was taken again, PianoL native was lost outright, experiments/exposure.md); the
    retry runs only the pairs the first run left unfinished or whose split was taken again, and keeps a second
    result only where it is verified (and, for a split taken again, where the matched views' split is the usual
    one, which PianoL's is not), so PianoL keeps its first result at both sizes and the brighter pair is ranged
    (99.6 % at 320×240, 99.7 % native). At native size the first run's coarse grid ranges two objects, one of them
    a clipped patch beyond the features' reach (70.9 px where the inliers reach 62.7): it does not count against
    the matched run's one object (a known loss, 80.1 %, from DenseConfig.in_view_detached_tail_share until then)."""
    from svs_torch.evaluation import evaluate_result

    real_rig = _real_rig()
    scenes = data_dir / "middlebury_eval3_Q"
    lit = real_rig.resample(real_rig.load_scene(scenes / "PianoL"), size)
    piano = real_rig.resample(real_rig.load_scene(scenes / "Piano"), size)
    bright = real_rig.misalign_right(piano.right, real_rig.Misalignment(gain=0.3), float(piano.focal_px[0]))
    # One scene under two lightings: PianoL's calibration and ground truth are Piano's.
    batch = real_rig.stack_conditions(lit, [("PianoL", lit.left, lit.right), ("Piano bright", piano.left, bright)])
    scores = {}
    # The default (the retry), off, always, and the one-sided clipping rule (which maps the brighter pair first).
    for name, config in (("retry", PipelineConfig()), ("off", PipelineConfig(exposure_retry=None)),
                         ("always", PipelineConfig(exposure=ExposureConfig(), exposure_retry=None)),
                         ("clipped", PipelineConfig(exposure_right_clipped=CLIPPED_RULE))):
        result = estimate_obstacle_depth(batch, config)
        scores[name] = [(e.status, e.acc_objects_pct) for e in evaluate_result(batch, result)]
        if name in ("retry", "clipped"):
            assert result.exposure_matched.tolist() == [False, True]
    assert scores["retry"][0] == scores["off"][0] == scores["clipped"][0]
    assert scores["clipped"][1][0] == "OK" and scores["clipped"][1][1] > 97
    # Without the retry the brighter pair is ranged wrong: on its split taken again at 320×240 (89.3 %), at native
    # size on the dense stage's coarse grid (a clipped patch: 31.7 %); the retry replaces either.
    assert scores["off"][1][0] != "OK" or scores["off"][1][1] < 95
    assert scores["retry"][1][0] == "OK" and scores["retry"][1][1] > 97
    assert scores["retry"][0][0] == "OK" and scores["retry"][0][1] > 98
    if size == "320x240":  # native, with the wider window for noisy pairs: matched 99.3 %, unmatched 99.2
        assert scores["always"][0][1] < scores["retry"][0][1]


def test_a_split_taken_again_is_retried_but_kept_where_the_matched_views_need_it_too(data_dir):
    """PianoL at 320×240 as a camera frame (JPEG digit 1, noise σ 2): its split is taken again, so the retry runs
    it on matched views; there the split is taken again too and a second, wrong region is ranged (90.3 %), so the
    first result (one object, 97.7 %) stays although the second ranges more objects. (Where the split is taken
    again only on the unmatched views, the matched run replaces it: test_a_brighter_right_camera_is_ranged_...)
    With the 7×7 nearness map, whose regions this frame was chosen for (with the default's wider window for noisy
    pairs the first result measures 99.7 %)."""
    from conftest import seven_by_seven_nearness
    from svs_torch.evaluation import evaluate_result

    real_rig = _real_rig()
    scenes = data_dir / "middlebury_eval3_Q"
    lit = real_rig.resample(real_rig.load_scene(scenes / "PianoL"), "320x240")
    # 5: PianoL's index in real_rig.py's tuned split, which seeds the scene's noise (its rows' frame).
    frame = next(view for view in real_rig.conditions(lit, 5) if view[0] == "jpeg q1 + noise s2")
    batch = real_rig.stack_conditions(lit, [frame])
    narrow = seven_by_seven_nearness()
    retried = estimate_obstacle_depth(batch, PipelineConfig(), network=narrow)
    matched = estimate_obstacle_depth(batch, PipelineConfig(exposure=ExposureConfig(), exposure_retry=None),
                                      network=narrow)
    assert bool(retried.segmentation.split_retaken[0]) and bool(matched.segmentation.split_retaken[0])
    assert not bool(retried.exposure_matched[0])
    assert int(matched.depth.objects.valid[0].sum()) > int(retried.depth.objects.valid[0].sum())
    kept, other = evaluate_result(batch, retried)[0], evaluate_result(batch, matched)[0]
    assert kept.acc_objects_pct > 97 and other.acc_objects_pct < kept.acc_objects_pct


def test_a_camera_frame_whose_views_differ_only_by_content_is_not_run_again(data_dir):
    """Pipes (a tuned scene) at 320×240 as a camera frame (JPEG digit 6, noise σ 6), without any gain: its views'
    quartiles differ by 0.064 (what each view alone sees, not an exposure). The first run leaves it unfinished, so
    a retry at the old min_change 0.05 ran the whole pipeline again on mapped views and kept that run; by default
    (``RETRY_MIN_CHANGE``, under the 0.143 of the smallest tuned ±30 % gain) it is run once and its result is the
    one without a retry. The Piano +30 % pairs above are still retried by default
    (test_the_retry_keeps_a_pair_lit_by_two_lamps). At 0.05 the map's test at the matched points
    (``PipelineConfig.exposure_retry_max_residual_ratio``) does not run it again either."""
    from svs_torch.pipeline.exposure import RETRY_MIN_CHANGE

    real_rig = _real_rig()
    pipes = real_rig.resample(real_rig.load_scene(data_dir / "middlebury_eval3_Q" / "Pipes"), "320x240")
    # 6: Pipes's index in real_rig.py's tuned split, which seeds the scene's noise (its rows' frame).
    frame = next(view for view in real_rig.conditions(pipes, 6) if view[0] == "jpeg q6 + noise s6")
    batch = real_rig.stack_conditions(pipes, [frame])
    differs = [bool(exposures_differ(batch.left, batch.right, batch.image_hw, ExposureConfig(min_change=change))[0])
               for change in (0.05, RETRY_MIN_CHANGE)]
    assert differs == [True, False]
    default = estimate_obstacle_depth(batch, PipelineConfig())
    eager = estimate_obstacle_depth(batch, PipelineConfig(exposure_retry=ExposureConfig(min_change=0.05),
                                                          exposure_retry_max_residual_ratio=None))
    # The map's test at the matched points (exposure_retry_max_residual_ratio) tells the content from a gain too.
    eager_tested = estimate_obstacle_depth(batch, PipelineConfig(exposure_retry=ExposureConfig(min_change=0.05)))
    without = estimate_obstacle_depth(batch, PipelineConfig(exposure_retry=None))
    assert bool(eager.exposure_matched[0]) and not bool(default.exposure_matched[0])
    for result in (default, eager_tested):
        assert torch.equal(result.depth.objects.depth_median_m, without.depth.objects.depth_median_m)
        assert torch.equal(result.depth.objects.valid, without.depth.objects.valid)


def test_the_retry_is_differentiable_and_refuses_a_wrong_setting(data_dir):
    """Under differentiable=True the retried pair's depths carry gradients to both views through the exposure map
    (and equal the hard ones within 0.5 %), as do those of a pair mapped by the one-sided clipping rule; a setting
    that is not an ExposureConfig, or a clipping rule without its share, is refused by name."""
    from dataclasses import replace

    from conftest import assert_differentiable_depths_are_the_hard_ones

    real_rig = _real_rig()
    piano = real_rig.resample(real_rig.load_scene(data_dir / "middlebury_eval3_Q" / "Piano"), "320x240")
    bright = real_rig.misalign_right(piano.right, real_rig.Misalignment(gain=0.3), float(piano.focal_px[0]))
    pair = replace(piano, left=piano.left.clone().requires_grad_(), right=bright.clone().requires_grad_())
    for config in (PipelineConfig(differentiable=True),
                   PipelineConfig(differentiable=True, exposure_retry=None, exposure_right_clipped=CLIPPED_RULE)):
        result = estimate_obstacle_depth(pair, config)
        assert bool(result.exposure_matched[0])
        assert_differentiable_depths_are_the_hard_ones(result, pair.left, pair.right)
    with pytest.raises(InputError, match=r"^exposure_retry: expected an ExposureConfig or None"):
        PipelineConfig(exposure_retry=True)
    with pytest.raises(InputError, match=r"^exposure_right_clipped: expected an ExposureConfig with min_right_"):
        PipelineConfig(exposure_right_clipped=ExposureConfig())


def test_a_complete_first_result_gives_way_only_to_objects_the_features_reach(data_dir):
    """A loose rig's camera frames (``real_rig.py --loose-rig-digit``) with the right camera 30 % brighter, each
    verified with every kept object ranged on the dense stage's coarse grid, so retried on matched views, which
    are measured there too. Tuned PianoL at 320×240, digit 4: the matched run keeps a second object at 63 px, where
    the inliers reach 19.6 px (past two wrong ones, 133.5 and 30.9), so the first result stays (99.5 % per object;
    the matched run's 69.7). Rendered scene 1 at digit 8, noise draw 1: the matched run ranges the scene's second
    box, within the inliers' reach, and replaces the first (99.2 %; the first's 75.0). Both with the coarse retry's
    x-Sobel costs alone (``DenseConfig.smoothing_intensity_weight`` 0), the frames this rule was chosen on: with the
    intensities' cost, PianoL's matched run is measured at the working width, so the rule is not reached (and it
    replaces the first, 80.0 %: a loss of that default, experiments/real_rig.md, "Featureless obstacles"), and with
    every region a candidate (``SegmentationConfig.max_clipped_share`` None): the matched views clip PianoL's lamp
    wall, which that rule leaves out, and its matched run is then measured at the working width too."""
    from svs_torch.evaluation import evaluate_result

    real_rig = _real_rig()
    base = PipelineConfig()
    base = dataclasses.replace(base, dense=dataclasses.replace(base.dense, smoothing_intensity_weight=0.0),
                               segmentation=dataclasses.replace(base.segmentation, max_clipped_share=None))
    lit = real_rig.resample(real_rig.load_scene(data_dir / "middlebury_eval3_Q" / "PianoL"), "320x240")
    rendered = real_rig.synthetic_scenes()[1]
    # 5: PianoL's index in real_rig.py's tuned split, which seeds the scene's noise (its rows' frames).
    cases = [(lit, 5, 4, 0, False), (rendered, 1, 8, 1, True)]
    for scene, index, digit, draw, replaced in cases:
        frames = real_rig.loose_rig_conditions(scene, index, digit, draw)
        batch = real_rig.stack_conditions(scene, [next(v for v in frames if v[0].startswith("gain +30%"))])
        first = estimate_obstacle_depth(batch, dataclasses.replace(base, exposure_retry=None))
        matched = estimate_obstacle_depth(batch, dataclasses.replace(base, exposure=base.exposure_retry,
                                                                     exposure_retry=None))
        retried = estimate_obstacle_depth(batch, base)
        assert bool(first.verified[0]) and bool(first.coarse[0]) and bool(matched.coarse[0])
        assert int(matched.depth.objects.valid[0].sum()) > int(first.depth.objects.valid[0].sum())
        assert bool(retried.exposure_matched[0]) == replaced
        scores = [evaluate_result(batch, r)[0].acc_objects_pct for r in (first, matched, retried)]
        assert scores[2] == (scores[1] if replaced else scores[0]) and scores[2] > 99
        assert min(scores[:2]) < 80


def test_objects_beyond_the_features_reach_are_those_past_the_third_largest_inlier(data_dir):
    """``exposure_retry._beyond_inliers`` against the reach computed here from its docstring: an object whose
    disparity (from its median depth) exceeds 1.25 times the third largest RANSAC inlier disparity plus 2 px is
    beyond; one just inside is not; an object not ranged never is; a pair without an inlier has every ranged object
    beyond and no object within reach."""
    from svs_torch.pipeline.exposure_retry import _beyond_inliers, _objects_within_inliers

    real_rig = _real_rig()
    scene = real_rig.resample(real_rig.load_scene(data_dir / "middlebury_eval3_Q" / "Piano"), "320x240")
    batch = real_rig.stack_conditions(scene, [("a", scene.left, scene.right), ("b", scene.left, scene.right)])
    result = estimate_obstacle_depth(batch, PipelineConfig())
    sparse = result.depth.disparities
    known = result.fundamental.inliers & sparse.valid
    third = sorted(sparse.disparity_px[0][known[0]].tolist(), reverse=True)[2]
    reach = 1.25 * third + 2.0
    scale = float(batch.focal_px[0] * batch.baseline_m[0])
    doffs = float(batch.doffs_px[0])
    objects = result.depth.objects
    n = objects.valid.shape[1]
    assert n >= 1
    depth = torch.full((2, n), scale / (reach - 5.0 + doffs), dtype=objects.depth_median_m.dtype)
    depth[0, 0] = scale / (reach + 0.5 + doffs)
    valid = torch.zeros(2, n, dtype=torch.bool)
    valid[:, 0] = True
    objects = dataclasses.replace(objects, depth_median_m=depth, valid=valid)
    # Pair "b" keeps its inliers out: none is known there.
    fundamental = dataclasses.replace(result.fundamental, inliers=torch.stack([result.fundamental.inliers[0],
                                                                              torch.zeros_like(known[1])]))
    tweaked = dataclasses.replace(result, depth=dataclasses.replace(result.depth, objects=objects),
                                  fundamental=fundamental)
    beyond, has_inliers = _beyond_inliers(tweaked, batch)
    assert has_inliers.tolist() == [True, False]
    assert beyond[0].tolist() == [True] + [False] * (n - 1) and beyond[1].tolist() == valid[1].tolist()
    assert _objects_within_inliers(tweaked, batch).tolist() == [False, False]
    inside = dataclasses.replace(objects, depth_median_m=torch.full_like(depth, scale / (reach - 0.5 + doffs)))
    tweaked = dataclasses.replace(tweaked, depth=dataclasses.replace(result.depth, objects=inside))
    assert _beyond_inliers(tweaked, batch)[0][0].tolist() == [False] * n
    assert _objects_within_inliers(tweaked, batch).tolist() == [True, False]


def _reference_residual_ratio(left: np.ndarray, right: np.ndarray, left_xy: np.ndarray, right_xy: np.ndarray,
                              valid: np.ndarray, min_change: float) -> float:
    """``matched_residual_ratio`` of one pair written from its docstring and ``match_exposure``'s, in numpy: the
    quartile map applied to the darker view, 5×5 patch means cut by the border, medians over the valid matches (the
    lower middle value of an even count, as ``torch.median`` takes)."""
    low_left, high_left = np.quantile(left, [0.25, 0.75])
    low_right, high_right = np.quantile(right, [0.25, 0.75])
    scale = (high_left - low_left) / (high_right - low_right)
    offset = low_left - scale * low_right
    changed = abs(scale - 1) + abs(offset) > min_change

    def patch_mean(image, x, y):
        x, y = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
        return image[max(y - 2, 0):y + 3, max(x - 2, 0):x + 3].mean()

    before, after = [], []
    for (xl, yl), (xr, yr), keep in zip(left_xy, right_xy, valid):
        if not keep:
            continue
        a, b = patch_mean(left, xl, yl), patch_mean(right, xr, yr)
        before.append(abs(a - b))
        if changed and high_right <= high_left:
            b = np.clip(scale * b + offset, 0, 1)
        elif changed:
            a = np.clip((a - offset) / scale, 0, 1)
        after.append(abs(a - b))
    if len(before) < 5:
        return float("nan")
    lower_median = lambda values: sorted(values)[(len(values) - 1) // 2]  # noqa: E731 (torch.median's, the lower)
    return float(lower_median(after) / lower_median(before))


def _gain_and_two_lamps(generator: torch.Generator) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """One textured scene ``(1, 1, 50, 74)`` (smooth enough for patch means) as the left view and right views seen
    8 px apart (a point at x in the left view is at x + 8 in the right): behind a camera 30 % darker ("gain"), lit
    by a lamp whose light falls off across the view, 0.55 to 1.45 of the left's ("two lamps"), and as it is
    ("same")."""
    scene = torch.nn.functional.avg_pool2d(torch.rand(1, 1, 52, 76, generator=generator, dtype=torch.float64), 3,
                                           stride=1)
    scene = 0.15 + 0.6 * (scene - scene.min()) / (scene.max() - scene.min())
    left, seen = scene[..., 8:], scene[..., :-8]
    falloff = torch.linspace(0.55, 1.45, seen.shape[-1], dtype=torch.float64)
    return left, {"gain": (0.7 * seen).clamp(0, 1), "two lamps": (seen * falloff).clamp(0, 1), "same": seen}


def test_the_map_brings_the_matched_points_of_a_gain_together_not_of_two_lamps(generator):
    """``matched_residual_ratio`` (the exposure retry's test of whether a second run can help) against the numpy
    reference above. One textured scene seen 8 px apart: behind a right camera 30 % darker the quartile map makes
    the matched points agree (ratio near 0); lit by a lamp whose light falls off across the right view (0.55 to
    1.45 of the left's), the views' quartiles differ as much, but no one map makes the points agree (ratio near 1).
    Fewer than 5 matches give NaN; a wrong shape is refused by name."""
    from svs_torch.pipeline.exposure import matched_residual_ratio

    left, rights = _gain_and_two_lamps(generator)
    ys, xs = torch.meshgrid(torch.arange(2, 48, 5.0), torch.arange(1, 58, 6.0), indexing="ij")
    left_xy = torch.stack([xs.flatten() + 0.3, ys.flatten() - 0.2], 1).to(torch.float64)
    right_xy = left_xy + torch.tensor([8.0, 0.0], dtype=torch.float64)
    valid = torch.rand(len(left_xy), generator=generator) < 0.8
    valid[:4] = True
    config = ExposureConfig()
    image_hw = torch.tensor([list(left.shape[-2:])] * 3)
    few = valid & (torch.arange(len(valid)) < 4)
    ratio = matched_residual_ratio(left.expand(3, -1, -1, -1), torch.cat([rights["gain"], rights["two lamps"],
                                                                          rights["gain"]]),
                                   image_hw, left_xy.expand(3, -1, -1), right_xy.expand(3, -1, -1),
                                   torch.stack([valid, valid, few]), config)
    assert ratio.shape == (3,) and bool(ratio[2].isnan())
    for i, name in enumerate(("gain", "two lamps")):
        expected = _reference_residual_ratio(left[0, 0].numpy(), rights[name][0, 0].numpy(), left_xy.numpy(),
                                             right_xy.numpy(), valid.numpy(), config.min_change)
        assert float(ratio[i]) == pytest.approx(expected, rel=1e-9, abs=1e-12)
    assert float(ratio[0]) < 0.1 and float(ratio[1]) > 0.8
    with pytest.raises(InputError, match=r"^right_xy: expected"):
        matched_residual_ratio(left, rights["gain"], image_hw[:1], left_xy[None], right_xy[None, :3], valid[None])
    # An audit: no match at all (eval --set surf.max_keypoints=0 on views the exposure retry reaches) failed in a
    # median of nothing, every such pair an ERROR row; too few matches to tell is NaN.
    none = matched_residual_ratio(left, rights["gain"], image_hw[:1], left_xy[None, :0], right_xy[None, :0],
                                  valid[None, :0])
    assert none.shape == (1,) and bool(none.isnan().all())


def test_the_pairs_to_match_are_those_that_differ_and_whose_map_brings_their_matches_together(generator):
    """``pairs_to_match`` (the retry's one call, one fit) is ``exposures_differ`` and-ed with
    ``matched_residual_ratio`` at most the bound, NaN counting as True; pairs whose views agree are never named.
    Under ``min_right_clipped_share`` the ratio measures the map ``match_exposure`` applies: a pair it leaves alone
    (its right view not clipped more) keeps ratio 1, not the whole views' map."""
    from svs_torch.pipeline.exposure import exposures_differ, match_exposure, matched_residual_ratio, pairs_to_match

    left, views = _gain_and_two_lamps(generator)
    rights = torch.cat([views["gain"], views["two lamps"], views["gain"], views["same"]])
    lefts = left.expand(4, -1, -1, -1)
    ys, xs = torch.meshgrid(torch.arange(2, 48, 5.0), torch.arange(1, 58, 6.0), indexing="ij")
    left_xy = torch.stack([xs.flatten(), ys.flatten()], 1).to(torch.float64).expand(4, -1, -1)
    right_xy = left_xy + torch.tensor([8.0, 0.0], dtype=torch.float64)
    valid = torch.ones(4, left_xy.shape[1], dtype=torch.bool)
    valid[2, 4:] = False  # the second gain pair: too few matches to tell
    image_hw = torch.tensor([list(left.shape[-2:])] * 4)
    config = ExposureConfig()
    differ = exposures_differ(lefts, rights, image_hw, config)
    ratio = matched_residual_ratio(lefts, rights, image_hw, left_xy, right_xy, valid, config)
    assert differ.tolist() == [True, True, True, False]
    for bound in (0.8, 0.05):
        picked = pairs_to_match(lefts, rights, image_hw, left_xy, right_xy, valid, config, bound)
        assert picked.tolist() == (differ & ~(ratio > bound)).tolist()
    assert pairs_to_match(lefts, rights, image_hw, left_xy, right_xy, valid, config, 0.8).tolist() == [
        True, False, True, False]
    assert pairs_to_match(lefts, rights, image_hw, left_xy, right_xy, valid, config).tolist() == differ.tolist()
    clipped = ExposureConfig(min_right_clipped_share=0.05)  # no right view here is clipped at white
    assert not bool(match_exposure(lefts, rights, image_hw, clipped)[2].any())
    unmapped = matched_residual_ratio(lefts[:2], rights[:2], image_hw[:2], left_xy[:2], right_xy[:2], valid[:2],
                                      clipped)
    assert unmapped.tolist() == [1.0, 1.0]
    assert not bool(pairs_to_match(lefts, rights, image_hw, left_xy, right_xy, valid, clipped, 0.8).any())


def test_a_pair_lit_by_two_lamps_is_not_run_again_where_the_map_cannot_bring_it_together(data_dir):
    """PianoL at 320×240 as the board's default camera frame (JPEG digit 4, noise σ 4): its first result is
    complete but measured on the dense stage's coarse grid with its split taken again, so the retry's rule names
    it, and a second run on matched views was guide's one frame over 50 ms (experiments/guide_second_passes.md),
    whose result was never kept. At its RANSAC inliers the map leaves the views as far apart (ratio 0.99), so it is
    no longer run again; Piano behind a right camera 30 % brighter, in the same batch, still is (0.25) and is
    ranged. Without the test (``exposure_retry_max_residual_ratio=None``) both are run again, to the same end."""
    from svs_torch.evaluation import evaluate_result
    from svs_torch.pipeline.exposure_retry import retry_with_exposure

    real_rig = _real_rig()
    scenes = data_dir / "middlebury_eval3_Q"
    lit = real_rig.resample(real_rig.load_scene(scenes / "PianoL"), "320x240")
    piano = real_rig.resample(real_rig.load_scene(scenes / "Piano"), "320x240")
    # 5: PianoL's index in real_rig.py's tuned split, which seeds the scene's noise (its rows' frame).
    frame = next(view for view in real_rig.conditions(lit, 5) if view[0] == "jpeg q4 + noise s4")
    bright = real_rig.misalign_right(piano.right, real_rig.Misalignment(gain=0.3), float(piano.focal_px[0]))
    batch = real_rig.stack_conditions(lit, [frame, ("Piano bright", piano.left, bright)])
    first = estimate_obstacle_depth(batch, PipelineConfig(exposure_retry=None))
    assert bool(first.coarse[0]) and bool(first.segmentation.split_retaken[0])
    scores = {}
    for ratio in (0.8, None):
        config = PipelineConfig(exposure_retry_max_residual_ratio=ratio)
        second_runs = []

        def run(pairs, settings):
            second_runs.append(list(pairs.names))
            return estimate_obstacle_depth(pairs, settings)

        result = retry_with_exposure(batch, first, config, run)
        assert second_runs == ([["Piano bright"]] if ratio else [[frame[0], "Piano bright"]])
        assert result.exposure_matched.tolist() == [False, True]
        scores[ratio] = [(e.status, round(e.acc_objects_pct, 6)) for e in evaluate_result(batch, result)]
        assert scores[ratio] == [(e.status, round(e.acc_objects_pct, 6))
                                 for e in evaluate_result(batch, estimate_obstacle_depth(batch, config))]
    assert scores[0.8] == scores[None] and scores[0.8][1][0] == "OK" and scores[0.8][1][1] > 97
    with pytest.raises(InputError, match=r"^exposure_retry_max_residual_ratio: expected a ratio > 0 or None"):
        PipelineConfig(exposure_retry_max_residual_ratio=0)
