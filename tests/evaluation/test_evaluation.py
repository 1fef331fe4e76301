"""svs_torch.evaluation: Eq. (9) scores and disparity errors against hand-computed values and against
experiments/paper_table1.py; configuration overrides; pair lists; the eval command."""

from __future__ import annotations

import dataclasses
import json
import shutil
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from conftest import REPO_ROOT

from svs_torch.cli import main
from svs_torch.core.checks import InputError
from svs_torch.core.types import StereoBatch
from svs_torch.data import load_pair_source, load_stereo_pair, read_pair_list, read_pair_sources
from svs_torch.data.pair_list import PairSource
from svs_torch.evaluation import (EvalSetup, PairEstimate, accuracy_pct, dense_disparity_errors, disparity_map_errors,
                                  evaluate_block, evaluate_pairs, object_truth, score_pair, sparse_disparity_errors,
                                  summarize, with_nominal_calibration)
from svs_torch.evaluation.overrides import apply_overrides, config_to_dict, parse_assignment, resolve_config
from svs_torch.geometry.lk_refinement import MatchRefinementConfig
from svs_torch.pipeline import PipelineConfig

sys.path.insert(0, str(REPO_ROOT / "experiments"))
import paper_table1  # noqa: E402

#: True R_min / R_max printed by experiments/paper_table1.py before its scoring moved into svs_torch.evaluation
#: (commit b75b511, width 320, default segmentation). Cones has no calibration: nominal f·B, the same for both.
RECORDED_TRUTH = {"middlebury_eval3_Q/ArtL": (1.4997491836547852, 1.7548385858535767),
                  "middlebury_2003_quarter/Cones": (4.050084114074707, 9.498412132263184)}


def test_accuracy_is_equation_9_floored_at_zero():
    assert accuracy_pct(2.0, 1.9) == pytest.approx(95.0)
    assert accuracy_pct(2.0, 2.1) == pytest.approx(95.0)
    assert accuracy_pct(2.0, 2.0) == 100.0
    assert accuracy_pct(2.0, None) == 0.0  # a failed estimate counts 0 %, never hidden
    assert accuracy_pct(1.0, 3.5) == 0.0  # worse than 0 % is 0 %


def test_accuracy_takes_numbers_and_names_what_is_not_one():
    """Found by an audit: a real distance float() reads ('2.0', which the check took) failed in the arithmetic with a
    TypeError, as did a string estimate, and a bool estimate scored as 1 m."""
    assert accuracy_pct("2.0", 1.9) == pytest.approx(95.0)
    assert accuracy_pct(torch.tensor(2.0), np.float64(1.9)) == pytest.approx(95.0)
    for estimated in ("1.9", True, [1.9]):
        with pytest.raises(InputError, match="^estimated: expected None or a distance, got "):
            accuracy_pct(2.0, estimated)


def test_score_pair_by_hand():
    # Truth: slot 0 at 2.0 m, slot 1 at 1.0 m; the estimate misses slot 1 and puts R_min at 1.1 m.
    score = score_pair([(0, 2.0), (1, 1.0)], PairEstimate("OK", 1.1, 2.0, [1.9, None]))
    assert (score.real_r_min_m, score.real_r_max_m) == (1.0, 2.0)
    assert score.acc_r_min_pct == pytest.approx(90.0) and score.acc_r_max_pct == pytest.approx(100.0)
    assert score.acc_objects_pct == pytest.approx((95.0 + 0.0) / 2)
    assert [o["acc_pct"] for o in score.objects] == pytest.approx([95.0, 0.0]) and score.num_objects == 2
    empty = score_pair([], PairEstimate("NO_OBJECTS", None, None, []))
    assert empty.acc_r_min_pct is None and empty.num_objects == 0


@pytest.mark.parametrize("truth", [[(0, 2.0)], []])
def test_score_pair_names_an_estimate_that_is_not_one(truth):
    """Found by a library user's audit: score_pair(truth, None) failed with "AttributeError: 'NoneType' object has
    no attribute 'objects_m'", and with no truth returned an empty score for it in silence."""
    with pytest.raises(InputError, match="^estimate: expected a PairEstimate, got NoneType$"):
        score_pair(truth, None)
    with pytest.raises(InputError, match="^estimate: expected a PairEstimate, got tuple$"):
        score_pair(truth, ("OK", 1.1, 2.0, [1.9]))


def _handmade_batch() -> tuple[StereoBatch, SimpleNamespace]:
    """Two 4×6 pairs, f·B = 10 m·px, doffs 0; label 1 covers columns 0–2, label 2 columns 3–5."""
    disparity = torch.tensor([[1.0, 2.0, 4.0, 5.0, 5.0, 5.0]] * 4).expand(2, 1, 4, 6).clone()
    disparity[1] *= 2
    valid = torch.ones_like(disparity, dtype=torch.bool)
    valid[0, 0, :, 2] = False  # pair 0: region 1 keeps d = 1 and 2 only
    image = torch.rand(2, 1, 4, 6, generator=torch.Generator().manual_seed(0))
    batch = StereoBatch.from_images(image, image, 10.0, 1.0, 0.0, True, disparity, valid)
    labels = torch.tensor([[1, 1, 1, 2, 2, 2]] * 4).expand(2, 1, 4, 6).clone()
    # Pair 1 keeps only region 2 (slot 1 is padding, -1).
    segmentation = SimpleNamespace(labels=labels, kept_labels=torch.tensor([[1, 2], [2, -1]]),
                                   kept_mask=labels > 0)
    return batch, segmentation


def test_object_truth_is_the_lower_median_of_the_region_depth():
    batch, segmentation = _handmade_batch()
    truth = object_truth(batch, segmentation)
    # Pair 0, region 1: depths 10/1 and 10/2 on 4 rows each -> 8 values, lower median 5.0 (torch.median's);
    # region 2: d = 5 everywhere -> 2.0. Pair 1: region 2 at d = 10 -> 1.0; slot 1 empty.
    assert torch.allclose(truth.depth_m, torch.tensor([[5.0, 2.0], [1.0, 0.0]]))
    assert truth.num_px.tolist() == [[8, 12], [12, 0]] and truth.valid.tolist() == [[True, True], [True, False]]
    values = np.sort(np.r_[[10.0] * 4, [5.0] * 4])
    assert truth.depth_m[0, 0] == values[(len(values) - 1) // 2]  # numpy, independently
    single = object_truth(batch.select([1]), SimpleNamespace(labels=segmentation.labels[1:],
                                                             kept_labels=segmentation.kept_labels[1:]))
    assert torch.equal(single.depth_m, truth.depth_m[1:])  # batched equals per pair
    # A target carries no gradient (an audit: a training loss differentiated through the truth too, and the focal
    # length's gradient cancelled).
    focal = torch.full((2,), 10.0, requires_grad=True)
    graded = object_truth(dataclasses.replace(batch, focal_px=focal), segmentation)
    assert torch.equal(graded.depth_m, truth.depth_m) and not graded.depth_m.requires_grad


def test_disparity_errors_by_hand():
    batch, segmentation = _handmade_batch()
    dense_disparity = batch.disparity_px.clone()
    dense_disparity[0, 0, 0, :3] += torch.tensor([0.5, 2.0, 4.0])  # three wrong pixels in pair 0
    dense = SimpleNamespace(disparity_px=dense_disparity, valid=torch.ones_like(batch.disparity_valid))
    result = SimpleNamespace(dense=dense, rectified=torch.tensor([False, True]),
                             segmentation=SimpleNamespace(left=segmentation))
    errors = dense_disparity_errors(batch, result)
    # Pair 0: 24 pixels, 20 with known GT (column 2 unknown, so the +4 px pixel does not count): errors
    # 0.5, 2.0 and 18 zeros -> lower median 0, 19 of 20 within 1 px, all within 3 px. Pair 1 is rectified: none.
    assert errors.count.tolist() == [20, 0] and errors.valid.tolist() == [True, False]
    assert errors.median_px[0] == 0.0
    assert errors.within_1px[0] == pytest.approx(19 / 20) and errors.within_3px[0] == pytest.approx(1.0)
    assert errors.within_2px[0] == pytest.approx(1.0)  # the 2.0 px error is within 2 px (bad-2 counts > 2)
    # Any map against the GT (a rival's): the same statistics from disparity_map_errors, here over pair 0 only.
    rival = disparity_map_errors(dense_disparity, dense.valid, batch.disparity_px, batch.disparity_valid,
                                 segmentation.kept_mask & torch.tensor([True, False]).view(2, 1, 1, 1))
    for name in ("median_px", "within_1px", "within_2px", "within_3px", "count"):
        assert torch.equal(getattr(rival, name), getattr(errors, name)), name
    # Sparse: three inliers in pair 0 at (x, y) = (1, 0), (3, 1), (4, 2) with disparity errors 0.5, 2, 4 and
    # one of them 2 px off its row; a fourth match is no inlier.
    left = torch.tensor([[[1.0, 0.0], [3.0, 1.0], [4.0, 2.0], [5.0, 3.0]]]).expand(2, 4, 2).clone()
    right = left.clone()
    right[..., 0] -= torch.tensor([2.0 + 0.5, 5.0 + 2.0, 5.0 + 4.0, 5.0])
    right[0, 0, 1] += 2.0  # right disparity, wrong row: not a correct correspondence
    points = SimpleNamespace(left=left, right=right, valid=torch.ones(2, 4, dtype=torch.bool))
    inliers = torch.tensor([[True, True, True, False], [False] * 4])
    sparse = sparse_disparity_errors(batch, SimpleNamespace(points=points,
                                                            fundamental=SimpleNamespace(inliers=inliers)))
    assert sparse.count.tolist() == [3, 0]
    assert sparse.median_px[0] == pytest.approx(2.0)
    assert sparse.within_1px[0] == pytest.approx(1 / 3) and sparse.within_3px[0] == pytest.approx(2 / 3)
    assert sparse.precision[0] == pytest.approx(0.0)  # the one within 1 px is off its row



def test_disparity_map_errors_name_a_nan_where_both_maps_are_known():
    """Found by an audit: a NaN in the map where it and the GT are known gave a NaN median and counted as wrong at
    every threshold, in silence (19 of 20 pixels within 1 px said 0.95 of a map that is NaN there), where
    measure_stereo_metrics names it. A NaN where either map is unknown is never read, as there."""
    truth = torch.full((2, 1, 4, 5), 3.0)
    known = torch.ones(2, 1, 4, 5, dtype=torch.bool)
    estimate = truth.clone()
    estimate[1, 0, 2, 2] = torch.nan
    with pytest.raises(InputError, match=r"^disparity_px: expected finite values where valid holds, got NaN or inf "
                                         r"for pair\(s\) \[1\] of 2$"):
        disparity_map_errors(estimate, known, truth, known, known)
    with pytest.raises(InputError, match=r"^truth_px: expected finite values where truth_valid holds"):
        disparity_map_errors(truth, known, estimate, known, known)
    unread = known.clone()
    unread[1, 0, 2, 2] = False
    errors = disparity_map_errors(estimate, unread, truth, known, known)
    assert errors.count.tolist() == [20, 19] and errors.median_px.tolist() == [0.0, 0.0]


def test_disparity_map_errors_without_a_mask_compare_every_pixel_both_maps_know():
    """A library user's audit: mask=None, as measure_stereo_metrics takes it, passed the checks and then failed with
    "unsupported operand type(s) for &: 'NoneType' and 'Tensor'"; it now means every pixel, as there."""
    truth = torch.full((2, 1, 4, 5), 3.0)
    known = torch.ones(2, 1, 4, 5, dtype=torch.bool)
    estimate = truth + torch.linspace(0.0, 3.9, 20).view(1, 1, 4, 5)
    unread = known.clone()
    unread[1, 0, 0] = False
    everywhere = disparity_map_errors(estimate, unread, truth, known)
    masked = disparity_map_errors(estimate, unread, truth, known, known)
    for name in ("median_px", "within_1px", "within_2px", "within_3px", "count"):
        assert torch.equal(getattr(everywhere, name), getattr(masked, name)), name
    assert everywhere.count.tolist() == [20, 15]


def test_nominal_calibration_of_a_batch_without_names_or_pairs():
    """A library user's audit: a batch made by StereoBatch.from_images (no names, its default) failed with torch's
    "The size of tensor a (2) must match the size of tensor b (0)", and an empty one (batch.select([])) with
    '"bitwise_or_cpu" not implemented for 'Float''. Unnamed pairs are neither KITTI's nor Aloe's."""
    image = torch.rand(2, 1, 8, 8)
    batch = StereoBatch.from_images(image, image, 500.0, 0.1, calibrated=torch.tensor([True, False]))
    nominal = with_nominal_calibration(batch)
    assert nominal.focal_px.tolist() == pytest.approx([500.0, 3740 / 3])
    assert nominal.baseline_m.tolist() == pytest.approx([0.1, 0.16]) and nominal.calibrated.tolist() == [True, True]
    empty = with_nominal_calibration(batch.select([]))
    assert empty.batch_size == 0 and empty.calibrated.dtype == torch.bool


def test_nominal_calibration_only_for_pairs_without_one(data_dir):
    cones = load_stereo_pair(data_dir / "middlebury_2003_quarter" / "Cones")
    teddy = load_stereo_pair(data_dir / "middlebury_2003_quarter" / "Teddy")
    assert not bool(cones.calibrated[0]) and bool(teddy.calibrated[0])
    nominal = with_nominal_calibration(cones)
    assert nominal.focal_px.tolist() == pytest.approx([3740 / 3]) and nominal.baseline_m.tolist() == [
        pytest.approx(0.16)] and bool(nominal.calibrated[0])
    same = with_nominal_calibration(teddy)
    assert torch.equal(same.focal_px, teddy.focal_px) and torch.equal(same.doffs_px, teddy.doffs_px)
    # OpenCV's full-size Aloe keeps its loader's full-size nominal rig (f 3740 px): the third size's focal put it
    # three times nearer than estimate and the third-size Aloe (an audit: 1.8 against 5.4 m)
    aloe = with_nominal_calibration(load_stereo_pair(data_dir / "opencv_samples"))
    third = with_nominal_calibration(load_stereo_pair(data_dir / "middlebury_2005_2006_third" / "Aloe"))
    assert aloe.focal_px.tolist() == [3740.0] and bool(aloe.calibrated[0])
    # floats: pytest 9.2's approx iterates a 0-d tensor and fails (TypeError), as a fresh install met it
    full_focal_per_px, third_focal_per_px = (float(b.focal_px[0] / b.size_hw[1]) for b in (aloe, third))
    assert full_focal_per_px == pytest.approx(third_focal_per_px, rel=0.01)


@pytest.mark.parametrize("scene", sorted(RECORDED_TRUTH))
def test_eval_agrees_with_paper_table1(data_dir, scene):
    """The library's scores equal Table 1's rows for the same scene, size and configuration, and its truth
    equals the numbers paper_table1.py printed before it used the library."""
    path = data_dir / scene
    height, width = load_stereo_pair(path).size_hw
    size = (320, round(height * 320 / width))  # paper_table1's "320": width 320, aspect kept
    rows = {r["method"]: r for r in paper_table1.run({"tuned": [path]}, ["320"], progress=False)}
    # paper_table1 ranges every method over the same Otsu regions; the default pipeline keeps its own (nearness)
    # regions since issue 32, so only the paper preset is compared here.
    for method, config in (("paper (MATLAB defaults, Eq. 5-8)", PipelineConfig.paper()),):
        evaluation = evaluate_block(read_pair_sources([path]), EvalSetup(config, size))[0]
        row = rows[method]
        assert (evaluation.real_r_min_m, evaluation.real_r_max_m) == pytest.approx(RECORDED_TRUTH[scene], rel=1e-6)
        assert evaluation.real_r_min_m == row["real_r_min_m"] and evaluation.r_min_m == row["r_min_m"]
        for key, table_key in (("acc_r_min_pct", "acc_r_min"), ("acc_r_max_pct", "acc_r_max"),
                               ("acc_objects_pct", "acc_objects")):
            assert getattr(evaluation, key) == row[table_key], (method, key)
        expected = max(0.0, (1 - abs(evaluation.real_r_min_m - evaluation.r_min_m) / evaluation.real_r_min_m)) * 100
        assert evaluation.acc_r_min_pct == pytest.approx(expected)


def test_summary_counts_failures_at_zero_percent():
    from svs_torch.evaluation import PairEvaluation

    rows = [PairEvaluation("a", "OK", has_truth=True, acc_r_min_pct=90.0, acc_r_max_pct=80.0, acc_objects_pct=85.0,
                           time_s=0.2),
            PairEvaluation("b", "NO_OBJECTS", has_truth=True, time_s=0.2),
            PairEvaluation("c", "BAD_INPUT", reason="unreadable")]
    summary = summarize(rows, wall_s=1.5)
    assert (summary["pairs"], summary["failed"], summary["scored"]) == (3, 2, 2)
    assert summary["acc_r_min_pct"] == pytest.approx(45.0) and summary["acc_objects_pct"] == pytest.approx(42.5)
    assert summary["pairs_per_s"] == pytest.approx(2.0) and summary["pipeline_s_per_pair"] == pytest.approx(0.2)
    assert [f["name"] for f in summary["failures"]] == ["b", "c"]


def test_an_output_that_cannot_be_written_stops_the_run(data_dir):
    """Found by an audit of the outputs: a map export that failed (a full disk) made its pairs ERROR rows, scored
    0 %, so a disk problem read as a 33 % accuracy with exit 0. An output's failure is the run's, not the pair's:
    it stops the run with its error. (A pair whose own run raises is still an ERROR row scored 0 %, its truth and
    name kept: test_a_pair_the_pipeline_fails_on_counts_zero_percent.)"""
    from svs_torch.evaluation import evaluate_pairs

    scenes = [data_dir / "middlebury_eval3_Q" / name for name in ("Teddy", "ArtL")]
    sources = read_pair_sources([str(scene) for scene in scenes])

    def export(batch, result, seconds):
        raise OSError(28, "--disparity-out: cannot write maps/Teddy/disp0SVSTorch.pfm: No space left on device")

    with pytest.raises(OSError, match="No space left on device"):
        list(evaluate_pairs(sources, EvalSetup(size_wh=(160, 120)), batch_size=2, on_result=export))


def test_a_pair_the_pipeline_fails_on_counts_zero_percent(data_dir, monkeypatch):
    """Found by a review of the evaluation: a pair with truth whose run raised was an ERROR row without its truth,
    calibration or name, so the summary left it out of the accuracy means: the means were the other pairs' alone."""
    import svs_torch.evaluation.runner as runner
    from svs_torch.evaluation import evaluate_pairs

    scenes = [data_dir / "middlebury_eval3_Q" / name for name in ("Teddy", "ArtL")]
    sources = read_pair_sources([str(scene) for scene in scenes])
    estimate = runner.estimate_obstacle_depth

    def fails_on_teddy(batch, config):
        if any(name.endswith("Teddy") for name in batch.names):
            raise RuntimeError("a pipeline failure")
        return estimate(batch, config)

    monkeypatch.setattr(runner, "estimate_obstacle_depth", fails_on_teddy)
    rows = [row for _, row in evaluate_pairs(sources, EvalSetup(size_wh=(160, 120)), batch_size=2)]
    teddy, artl = rows
    assert teddy.status == "ERROR" and teddy.name == "eval3/Teddy" and teddy.has_truth and teddy.calibrated
    summary = summarize(rows)
    assert (summary["failed"], summary["scored"]) == (1, 2)
    assert summary["acc_objects_pct"] == pytest.approx(artl.acc_objects_pct / 2)


def test_a_process_runs_the_pipeline_once_untimed_before_its_first_timed_batch(data_dir, monkeypatch):
    """Found by an audit: a process's first run paid the kernels' loading and first calls' set-up in its seconds per
    pair, so whichever sweep configuration ran first looked slower (0.05 against 0.03 s a pair), and swapping the
    order swapped results' "best by" time. Once per process, on one pair, discarded: the rows do not change."""
    import dataclasses

    import svs_torch.evaluation.runner as runner
    from svs_torch.evaluation import evaluate_pairs

    sources = read_pair_sources([str(data_dir / "middlebury_eval3_Q" / name) for name in ("Teddy", "ArtL")])
    estimate, sizes = runner.estimate_obstacle_depth, []

    def counted(batch, config):
        sizes.append(batch.batch_size)
        return estimate(batch, config)

    monkeypatch.setattr(runner, "estimate_obstacle_depth", counted)
    monkeypatch.setattr(runner, "_WARMED_UP", False)
    first = [row for _, row in evaluate_pairs(sources, EvalSetup(size_wh=(160, 120)), batch_size=2)]
    second = [row for _, row in evaluate_pairs(sources, EvalSetup(size_wh=(160, 120)), batch_size=2)]
    assert sizes == [1, 2, 2]  # the warm-up's one pair, then each run's batch of two, untimed only once
    untimed = [dataclasses.replace(row, time_s=0.0) for row in first]
    assert untimed == [dataclasses.replace(row, time_s=0.0) for row in second]


# --- configuration overrides ---------------------------------------------------------------------------------

def test_overrides_set_nested_fields_with_their_types():
    base = PipelineConfig()
    config = apply_overrides(base, dict([parse_assignment("segmentation.kernel_size=7"),
                                         parse_assignment("max_ratio=0.7"), parse_assignment("mutual=true"),
                                         parse_assignment("rectify=off"), parse_assignment("epipolar_band_px=none"),
                                         parse_assignment("depth.object_percentiles=[5, 95]"),
                                         parse_assignment("surf.metric_threshold=300")]))
    assert config.segmentation.kernel_size == 7 and config.max_ratio == 0.7 and config.mutual is True
    assert config.rectify == "off" and config.epipolar_band_px is None
    assert config.depth.object_percentiles == (5.0, 95.0) and config.surf.metric_threshold == 300.0
    assert config.segmentation.num_keep == base.segmentation.num_keep and base.segmentation.kernel_size == 5
    assert apply_overrides(base, {"refine_matches": False}).refine_matches is None
    paper = apply_overrides(PipelineConfig.paper(), {"refine_matches.min_correlation": 0.5})
    assert paper.refine_matches == MatchRefinementConfig(min_correlation=0.5)  # turned on from its defaults
    assert apply_overrides(base, {}) == base


@pytest.mark.parametrize("overrides, message", [
    ({"segmentation.kernal_size": 7}, "unknown parameter 'segmentation.kernal_size' (did you mean "
                                      "segmentation.kernel_size"),
    ({"segmentation.kernel_size": "abc"}, "segmentation.kernel_size: expected an integer, got 'abc'"),
    ({"segmentation.kernel_size": 0}, "segmentation.kernel_size = 0: kernel_size: expected a positive integer"),
    ({"max_ratio": float("inf")}, "max_ratio: expected a finite number, got inf"),
    ({"max_ratio": True}, "max_ratio: expected a finite number, got True"),
    ({"rectify": "sometimes"}, "rectify: expected one of 'auto', 'required', 'off', got 'sometimes'"),
    ({"depth.object_percentiles": [5]}, "depth.object_percentiles: expected a list of 2 numbers"),
    ({"segmentation": 3}, "segmentation: expected its fields as dotted keys"),
    ({"refine_matches": 3}, "refine_matches: expected true or false"),
    # An audit of hostile values: these ran, or failed late inside a kernel or torch without naming the key.
    ({"row_alignment.min_gain": -1}, "row_alignment.min_gain = -1: min_gain: expected an int from 0"),
    ({"row_alignment.min_inliers": 2**63}, "row_alignment.min_inliers = 9223372036854775808: min_inliers: expected"),
    ({"row_alignment.keystone_min_t": -1.0}, "row_alignment.keystone_min_t = -1.0: keystone_min_t: expected a finite"),
    ({"row_alignment.keystone_max_deg": 0}, "row_alignment.keystone_max_deg = 0: keystone_max_deg: expected"),
    ({"row_alignment.keystone_min_inliers": -1}, "keystone_min_inliers: expected an int from 0"),
    ({"row_alignment.min_gain_share": 1e9}, "min_gain_share: expected a finite number in [0, 1e+06]"),
    ({"segmentation.ground.hypotheses": 2**31}, "hypotheses: expected an int from 8 to 1048576, got 2147483648"),
    ({"segmentation.ground.seed": 10**30}, "segmentation.ground.seed = " + str(10**30) + ": seed: expected an int"),
    ({"segmentation.ground.min_span_px": -1.0}, "min_span_px: expected a finite number in [0, inf)"),
    ({"feature_smoothing_sigma_px": 1e9}, "feature_smoothing_sigma_px: expected a σ in (0, 1000] pixels or None"),
    ({"noisy_retry_sigma_px": 1e6}, "noisy_retry_sigma_px: expected a σ in (0, 1000] pixels or None"),
    ({"noisy_features_retry_sigma_px": 2**63}, "noisy_features_retry_sigma_px: expected a σ in (0, 1000]"),
    # Past float32's largest number (3.4e38): accepted, then every pair of an eval or a sweep an ERROR row, "value
    # cannot be converted to type float without overflow", naming no setting (an audit of sweeps and presets).
    ({"segmentation.ground.tolerance_px": 1e39}, "segmentation.ground.tolerance_px = 1e+39: tolerance_px, "
                                                 "noisy_tolerance_px, tolerance_fraction: expected each of the first "
                                                 "two in (0, 3.4e+38]"),
    ({"segmentation.ground.noisy_tolerance_px": 1e39}, "noisy_tolerance_px = 1e+39: tolerance_px, noisy_tolerance_px"),
    ({"refine_matches.max_radius_px": 1e39}, "refine_matches.max_radius_px = 1e+39: MatchRefinementConfig: expected "
                                             "max_shift_px >= 0, radius_scales > 0 and 0 < min_radius_px <= "
                                             "max_radius_px <= 3.4e+38"),
])
def test_bad_overrides_name_the_key(overrides, message):
    with pytest.raises(InputError) as error:
        apply_overrides(PipelineConfig(), overrides, "--set")
    assert message in str(error.value) and str(error.value).startswith("--set: ")


def test_config_file_then_set(tmp_path):
    path = tmp_path / "config.toml"
    path.write_text('preset = "paper"\nmax_ratio = 0.7\n"dense.window_size" = 7\n[segmentation]\nkernel_size = 3\n')
    with pytest.warns(UserWarning, match="dense.window_size: no effect under the paper range rule"):
        config, preset, overrides = resolve_config(config_file=path, assignments=["max_ratio=0.75"])
    assert preset == "paper" and config.depth.rule == "paper" and config.refine_matches is None
    assert config.max_ratio == 0.75 and config.dense.window_size == 7 and config.segmentation.kernel_size == 3
    assert overrides == {"max_ratio": 0.75, "dense.window_size": 7, "segmentation.kernel_size": 3}
    path.write_text("[segmentation]\nkernel = 3\n")
    with pytest.raises(InputError, match="unknown parameter 'segmentation.kernel'"):
        resolve_config(config_file=path)
    with pytest.raises(InputError, match="--set: expected KEY=VALUE"):
        parse_assignment("max_ratio")


def test_an_empty_config_file_name_is_refused_as_such():
    """An audit of careless arguments: eval --config "$CONFIG" with CONFIG unset said "--config: .: expected a TOML
    file, got a folder", naming a folder nobody gave."""
    with pytest.raises(InputError, match="^--config: expected a configuration file name, got ''$"):
        resolve_config(config_file="")


def test_a_later_assignment_wins_and_the_stored_overrides_replay_what_ran(tmp_path):
    """Found by a review of the evaluation: overrides were kept in a plain dict, so a key assigned again kept its
    first place. `--set a.b=0.5 --set a=none --set a.b=0.6` applied a.b before a (refinement off, not on at 0.6),
    and a config file's `a = "none"` then `a.b = 0.5` with `--set a=none` was stored as an order that replays into
    refinement on (eval --db then filed its rows under another configuration than ran)."""
    config, _, overrides = resolve_config(assignments=["refine_matches.min_correlation=0.5", "refine_matches=none",
                                                       "refine_matches.min_correlation=0.6"])
    assert config.refine_matches is not None and config.refine_matches.min_correlation == 0.6
    path = tmp_path / "config.toml"
    path.write_text('refine_matches = "none"\n"refine_matches.min_correlation" = 0.5\n')
    for sets in (["refine_matches=none"], ["refine_matches.min_correlation=0.7"], []):
        config, _, overrides = resolve_config(config_file=path, assignments=sets)
        assert apply_overrides(PipelineConfig(), overrides) == config, sets


def test_eval_db_refuses_a_calibration_given_as_an_option_for_file_pairs(data_dir, tmp_path, capsys):
    """Found by a review of the evaluation: a store keys a file pair by its files (and its list line's calibration),
    so a second `eval --db` with another --focal-px was filed under the first run's keys and silently dropped.
    Scenes, which carry their own calibration, are not concerned."""
    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    listing = tmp_path / "pairs.txt"
    listing.write_text(f"{teddy / 'im0.png'} {teddy / 'im1.png'}\n")
    store = tmp_path / "runs.sqlite"
    code = main(["eval", str(listing), "--size", "160x120", "--focal-px", "500", "--db", str(store)])
    err = capsys.readouterr().err
    assert code == 2 and "--focal-px, --db: a results store does not record a calibration given as an option" in err
    assert not store.exists()
    assert main(["eval", str(teddy), "--size", "160x120", "--db", str(store), "--json"]) == 0
    # A scene carries its own calibration: the option, which it would not take, is refused (it was ignored).
    assert main(["eval", str(teddy), "--size", "160x120", "--focal-px", "500", "--db", str(store), "--json"]) == 2


def test_an_empty_path_is_refused_not_read_as_the_current_folder(data_dir, tmp_path, monkeypatch, capsys):
    """An audit of careless arguments: 'svs-depth eval "$DATA"' with DATA unset evaluated every scene of the
    current folder (an empty path is '.'), where every other path option refuses an empty name."""
    shutil.copytree(data_dir / "middlebury_2001" / "Tsukuba", tmp_path / "Tsukuba")
    monkeypatch.chdir(tmp_path)
    assert main(["eval", "", "--size", "160x120", "--json"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.strip().splitlines() == ["svs-depth eval: error: path: expected a scene folder, a pair "
                                                      "list or index.jsonl, got ''"]


def test_eval_runs_a_pair_listed_twice_once(data_dir, capsys):
    """Found by a review of the evaluation: a scene listed twice (however spelled) weighed twice in eval's means,
    while its own --db store and a sweep count it once."""
    import json

    teddy, artl = (data_dir / "middlebury_eval3_Q" / name for name in ("Teddy", "ArtL"))
    assert main(["eval", str(teddy), str(artl), f"{teddy}/", "--size", "160x120", "--json"]) == 0
    out, err = capsys.readouterr()
    lines = [json.loads(line) for line in out.splitlines()]
    assert len(lines) == 3 and lines[-1]["pairs"] == 2 and lines[-1]["scored"] == 2
    assert "listed more than once, evaluated once: middlebury_eval3_Q/Teddy" in err


def test_eval_names_the_first_few_pairs_listed_twice(data_dir, tmp_path, capsys):
    """An audit of bulk runs: a list of 400 scenes given twice to eval said so in one 7 kB line naming all 400 (and
    not how many). It now counts them and names the first five, as the summary's pairs without truth."""
    scenes = [str(path) for path in sorted((data_dir / "middlebury_eval3_Q").iterdir())[:7]]
    listing = tmp_path / "pairs.txt"
    listing.write_text("\n".join(scenes * 2) + "\n")
    assert main(["eval", str(listing), "--size", "64x48", "--json"]) == 0
    err = capsys.readouterr().err
    names = ", ".join(f"middlebury_eval3_Q/{Path(scene).name}" for scene in scenes[:5])
    assert f"eval: 7 pairs listed more than once, evaluated once: {names} and 2 more\n" in err, err


def test_eval_runs_a_scene_reached_through_a_link_once(data_dir, tmp_path, capsys):
    """Was: a symbolic link to a scene listed beside the scene's own folder was evaluated twice, counted twice in
    every mean (its paths differ; its files are the same)."""
    import json

    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    link = tmp_path / "Teddy"
    link.symlink_to(teddy.resolve(), target_is_directory=True)
    assert main(["eval", str(teddy), str(link), "--size", "160x120", "--json"]) == 0
    out, err = capsys.readouterr()
    lines = [json.loads(line) for line in out.splitlines()]
    assert len(lines) == 2 and lines[-1]["pairs"] == 1
    assert "listed more than once, evaluated once" in err


def test_a_store_counts_a_scene_reached_through_a_link_once(data_dir, tmp_path, capsys):
    """Found by an audit of the bulk commands: the same scene stored by one run through its folder and by another
    through a link was two pairs in `results` (every mean counted it twice); a row a store already holds under
    the link's spelling (written before ids resolved links) counts once too."""
    import json
    import sqlite3

    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    link = tmp_path / "link_Teddy"
    link.symlink_to(teddy.resolve(), target_is_directory=True)
    db = tmp_path / "s.sqlite"
    for path in (teddy, link):
        assert main(["eval", str(path), "--size", "160x120", "--db", str(db)]) == 0
    connection = sqlite3.connect(db)
    with connection:  # an older store's id: the link's own absolute path
        connection.execute("INSERT INTO pairs(pair_id, left, right) VALUES (?, ?, NULL)", (str(link), str(link)))
        connection.execute("INSERT INTO results SELECT config_id, ?, run_id, " + ", ".join(
            f'"{d[1]}"' for d in connection.execute("PRAGMA table_info(results)").fetchall()[3:])
                           + " FROM results", (str(link),))
        assert connection.execute("SELECT count(*) FROM results").fetchone()[0] == 2
    connection.close()
    capsys.readouterr()
    assert main(["results", str(db), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["configs"][0]["pairs"] == 1


# --- pair lists ----------------------------------------------------------------------------------------------

def test_a_hash_inside_a_listed_path_is_part_of_it(data_dir, tmp_path):
    """Found by a review of the evaluation: a list line's '#' started a comment anywhere (shlex), so
    'take#2/left.png take#2/right.png' became one field; as in a shell, it starts one only at the start of a word."""
    import shutil

    from svs_torch.core.files import split_list_line

    assert split_list_line("take#2/l.png take#2/r.png  # a pair") == ["take#2/l.png", "take#2/r.png"]
    assert split_list_line("'a #b' c\\ #d e #f") == ["a #b", "c #d", "e"]
    assert split_list_line("   # a whole comment") == []
    with pytest.raises(ValueError):
        split_list_line('"unbalanced')
    folder = tmp_path / "take#2"
    folder.mkdir()
    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    shutil.copy(teddy / "im0.png", folder / "left.png")
    shutil.copy(teddy / "im1.png", folder / "right.png")
    listing = tmp_path / "pairs.txt"
    listing.write_text("take#2/left.png take#2/right.png  # Teddy, copied\n")
    (source,) = read_pair_list(listing)
    assert source.problem is None and source.left == str(folder / "left.png")


def test_a_windows_list_keeps_its_backslashes(tmp_path, monkeypatch):
    """A list written on Windows names its files with backslashes (``C:\\data\\left.png``): read as a POSIX shell's
    escapes they vanished, and every pair was a file not found (``C:dataleft.png``). On Windows they stay; quotes
    still group a path with spaces, and ``#`` still starts a comment."""
    from svs_torch.core.files import split_list_line

    monkeypatch.setattr(sys, "platform", "win32")
    assert split_list_line(r"C:\data\left.png C:\data\right.png  # a pair") == [r"C:\data\left.png",
                                                                                  r"C:\data\right.png"]
    assert split_list_line(r'"D:\my pairs\l.png" sub\r.png') == [r"D:\my pairs\l.png", r"sub\r.png"]
    listing = tmp_path / "pairs.txt"
    listing.write_bytes(b"take\\left.png take\\right.png\r\n")
    (source,) = read_pair_list(listing)
    assert source.left == str(tmp_path / "take\\left.png")


def test_a_kitti_download_lists_its_frames_with_truth_only(data_dir, tmp_path, capsys):
    """Found by a review of the evaluation: a KITTI training folder as downloaded holds frames _10 and _11, and only
    _10 has disparity truth; every _11 frame was listed and became a failed pair (BAD_INPUT, no disp_occ)."""
    import shutil

    shared = data_dir / "kitti" / "stereo2012_training"
    root = tmp_path / "training"
    for folder in ("colored_0", "colored_1", "disp_occ"):
        (root / folder).mkdir(parents=True)
        shutil.copy(shared / folder / "000000_10.png", root / folder / "000000_10.png")
        if folder != "disp_occ":
            shutil.copy(shared / folder / "000000_10.png", root / folder / "000000_11.png")
    sources = read_pair_sources([root])
    assert [Path(source.left).name for source in sources] == ["000000_10.png"]
    assert main(["eval", str(root), "--size", "160x48", "--json"]) == 0
    assert '"failed": 0' in capsys.readouterr().out


def test_pair_list_forms_each_keep_their_calibration(data_dir, tmp_path):
    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    listing = tmp_path / "pairs.txt"
    listing.write_text(f"# a comment\n{teddy}\n{teddy / 'im0.png'} {teddy / 'im1.png'}\n"
                       f"{teddy / 'im0.png'} {teddy / 'im1.png'} 1500 0.08 52\n"
                       f"a.png b.png 1500\n{teddy / 'im0.png'} {teddy / 'im1.png'} abc 0.08\n"
                       f"{teddy / 'im0.png'} {teddy / 'im1.png'} 1500 -1\n{data_dir / 'middlebury_2003_quarter'}\n")
    sources = read_pair_list(listing)
    assert [s.scene for s in sources] == [True, False, False, False, False, False, True, True]
    problems = [s.problem for s in sources]
    assert problems[:3] == [None] * 3 and problems[6:] == [None] * 2
    assert "line 5" in problems[3] and "got 3 fields" in problems[3]
    assert "line 6" in problems[4] and "FOCAL_PX: expected a focal length in pixels from 1 to 1,000,000, got 'abc'" \
        in problems[4]
    assert "BASELINE_M: expected a baseline in metres from 0.001 to 2 (millimetres / 1000), got '-1'" in problems[5]
    scene, plain, calibrated = (load_pair_source(s) for s in sources[:3])
    assert scene.focal_px.tolist() == pytest.approx([1500.0]) and scene.disparity_px is not None
    assert not bool(plain.calibrated[0]) and plain.focal_px.tolist() != pytest.approx([1500.0])  # the SVS model
    assert calibrated.focal_px.tolist() == pytest.approx([1500.0]) and calibrated.doffs_px.tolist() == [52.0]
    with pytest.raises(InputError, match="FOCAL_PX"):
        load_pair_source(sources[4])
    index = tmp_path / "index.jsonl"
    index.write_text('{"index": 0, "left": "l.jpg", "right": "r.jpg", "width": 320}\nnot json\n')
    entries = read_pair_list(index)
    assert entries[0].left == str(tmp_path / "l.jpg") and entries[0].problem is None
    assert "line 2" in entries[1].problem
    # Found by a review of the evaluation: a doffs_px alone was dropped without a word, and with focal_px alone it
    # was read in baseline_m's place ('BASELINE_M: expected a finite positive number, got -3').
    index.write_text('{"left": "l.jpg", "right": "r.jpg", "doffs_px": -3}\n'
                     '{"left": "l.jpg", "right": "r.jpg", "focal_px": 500, "doffs_px": -3}\n'
                     '{"left": "l.jpg", "right": "r.jpg", "focal_px": 500, "baseline_m": 0.1, "doffs_px": -3}\n')
    alone, no_baseline, whole = read_pair_list(index)
    assert alone.problem.endswith("expected both focal_px and baseline_m in a calibration, got doffs_px")
    assert no_baseline.problem.endswith("expected both focal_px and baseline_m in a calibration, got focal_px, "
                                        "doffs_px")
    assert (whole.focal_px, whole.baseline_m, whole.doffs_px) == (500.0, 0.1, -3.0)
    with pytest.raises(InputError, match="no such file or folder"):
        read_pair_sources([tmp_path / "missing"])
    assert [s.name for s in read_pair_sources([data_dir / "middlebury_2003_quarter"])] == [
        "middlebury_2003_quarter/Cones", "middlebury_2003_quarter/Teddy"]
    from svs_torch.data import list_shared_pairs

    # The shared data folder stands for all its pairs (not only the scene folders directly inside it).
    assert [s.left for s in read_pair_sources([data_dir])] == [str(p) for p in list_shared_pairs(data_dir)]


def test_estimate_pairs_reads_scenes_and_index(data_dir, tmp_path, capsys):
    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    listing = tmp_path / "pairs.txt"
    listing.write_text(f"{teddy}\nmissing.png other.png\n")
    code = main(["estimate", "--pairs", str(listing), "--size", "160x120", "--json"])
    out, err = capsys.readouterr()
    lines = [json.loads(line) for line in out.strip().splitlines()]
    assert code == 2 and "1 of 2 pairs are BAD_INPUT" in err  # the bad pair has its line; the scene ran
    assert lines[0]["status"] == "OK" and 1.2 < lines[0]["r_min_m"] < 1.6  # its own calibration, not the SVS's
    assert lines[1]["status"] == "BAD_INPUT" and "missing.png" in lines[1]["reason"]


# --- the eval command ----------------------------------------------------------------------------------------

def test_eval_command_json_summary_and_failures(data_dir, tmp_path, capsys):
    scenes = data_dir / "middlebury_eval3_Q"
    listing = tmp_path / "pairs.txt"
    listing.write_text(f"{scenes / 'Teddy'}\n{scenes / 'ArtL'}\nnot-a-pair.png\n")
    db = tmp_path / "eval.sqlite"
    code = main(["eval", str(listing), "--size", "160x120", "--json", "--db", str(db), "--set", "seed=1"])
    out, err = capsys.readouterr()
    lines = [json.loads(line) for line in out.strip().splitlines()]
    summary = lines[-1]
    assert code == 0 and "eval" in err and "3/3" in err  # the progress bar on stderr
    assert {"pairs", "failed", "acc_r_min_pct", "acc_r_max_pct", "acc_objects_pct", "pairs_per_s"} <= set(summary)
    assert (summary["pairs"], summary["failed"], summary["scored"]) == (3, 1, 2)
    assert summary["failures"][0]["status"] == "BAD_INPUT" and summary["pairs_per_s"] > 0
    assert [line["status"] for line in lines[:-1]] == ["OK", "OK", "BAD_INPUT"]
    assert all(80 < line["acc_objects_pct"] <= 100 for line in lines[:2])
    code = main(["results", str(db), "--csv"])
    header = capsys.readouterr().out.splitlines()[0].split(",")
    assert code == 0 and header[:8] == ["config", "left", "right", "status", "r_min_m", "r_max_m",
                                        "acc_r_min_pct", "acc_r_max_pct"]
    code = main(["eval", str(listing), "--set", "segmentation.kernal_size=3"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "unknown parameter 'segmentation.kernal_size'" in err[0]


def test_a_pair_without_truth_lists_its_ranged_objects_unscored(data_dir, tmp_path, capsys):
    """A JSON audit: a camera's pair (files, no ground truth) was an eval row with 'num_objects': 0 and no
    objects, though ranged, so a script counting obstacles from eval, sweep or results rows read none."""
    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    listing = tmp_path / "pairs.txt"
    listing.write_text(f"{teddy / 'im0.png'} {teddy / 'im1.png'}\n")
    assert main(["eval", str(listing), "--size", "160x120", "--json"]) == 0
    row = json.loads(capsys.readouterr().out.splitlines()[0])
    assert row["status"] == "OK" and not row["has_truth"] and row["acc_objects_pct"] is None
    assert row["num_objects"] == len(row["objects"]) >= 1
    assert all(o["real_m"] is None and o["acc_pct"] is None and 0.5 < o["estimated_m"] < 3 for o in row["objects"])
    assert min(o["estimated_m"] for o in row["objects"]) == pytest.approx(row["r_min_m"])


def test_a_pair_without_truth_has_the_same_row_whatever_scene_shares_its_batch(data_dir, tmp_path, capsys):
    """An audit of batch sizes: a file pair without ground truth had no metric_px_scale run alone (--batch-size 1)
    and 1.0 batched with a scene of the same size, so one pair's --json row and stored row changed with its batch."""
    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    listing = tmp_path / "pairs.txt"
    listing.write_text(f"{teddy}\n{teddy / 'im0.png'} {teddy / 'im1.png'}\n")
    rows = {}
    for batch_size in ("1", "2"):
        assert main(["eval", str(listing), "--size", "160x120", "--json", "--batch-size", batch_size]) == 0
        rows[batch_size] = [json.loads(line) for line in capsys.readouterr().out.splitlines()[:-1]]
        for row in rows[batch_size]:
            row.pop("time_s")
    assert not rows["1"][1]["has_truth"] and rows["1"][1]["metric_px_scale"] is None
    assert rows["1"] == rows["2"]


def test_a_pair_with_no_keypoint_at_all_is_scored_not_an_error(data_dir, capsys):
    """surf.max_keypoints=0 is a valid setting (the dense stage ranges without sparse inliers), yet scoring its
    empty inlier set failed in a median of nothing: every pair ERROR, and a sweep's resume re-ran them for ever."""
    code = main(["eval", str(data_dir / "middlebury_eval3_Q" / "Teddy"), "--size", "320x240", "--json",
                 "--set", "surf.max_keypoints=0"])
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert code == 0 and lines[0]["status"] == "OK" and lines[0]["acc_objects_pct"] > 90
    assert lines[0]["sparse_within_1px"] is None and lines[-1]["statuses"] == {"OK": 1}


def test_a_pair_unreadable_then_mended_is_run_again_into_the_store(data_dir, tmp_path, capsys):
    """Found by an audit of the bulk commands: a listed pair whose files were missing stayed BAD_INPUT in a store
    for ever; a later run found the files, printed the pair OK, and threw its row away (results: 'fail 1')."""
    import shutil
    import sqlite3

    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    listing = tmp_path / "list.txt"
    listing.write_text(f"{teddy / 'im0.png'} {teddy / 'im1.png'}\nlater_L.png later_R.png\n")
    db = tmp_path / "s.sqlite"
    args = ["eval", str(listing), "--size", "160x120", "--db", str(db)]

    def stored() -> list[str]:
        connection = sqlite3.connect(db)
        try:
            return sorted(status for (status,) in connection.execute("SELECT status FROM results"))
        finally:
            connection.close()

    assert main(args) == 0 and stored() == ["BAD_INPUT", "OK"]
    shutil.copy(teddy / "im0.png", tmp_path / "later_L.png")
    shutil.copy(teddy / "im1.png", tmp_path / "later_R.png")
    assert main(args) == 0 and stored() == ["OK", "OK"]
    capsys.readouterr()


def test_eval_into_a_store_that_keeps_earlier_rows_says_so_and_whether_they_differ(data_dir, tmp_path, capsys):
    """Found by an audit of the bulk commands: a second 'eval --db' after a view was changed printed the new result
    (92.3 %) and exited 0, while the store kept the first run's row (99.7 %), which 'results' reads, without a word.
    Now the run says how many rows the store kept and how many of them differ from what it printed (JSON:
    db_rows_kept, db_rows_kept_differing)."""
    import shutil
    import sqlite3

    import cv2

    scene = tmp_path / "Teddy"
    shutil.copytree(data_dir / "middlebury_eval3_Q" / "Teddy", scene)
    db = tmp_path / "s.sqlite"
    args = ["eval", str(scene), "--size", "160x120", "--db", str(db), "--json"]

    def run() -> tuple[dict, float, str]:  # the summary, the pair's objects Acc, stderr
        assert main(args) == 0
        out, err = capsys.readouterr()
        lines = [json.loads(line) for line in out.splitlines()]
        return lines[-1], lines[0]["acc_objects_pct"], err

    summary, first, err = run()
    assert "db_rows_kept" not in summary and "had rows in" not in err
    summary, _, err = run()  # the same pair, the same settings: the same row
    assert (summary["db_rows_kept"], summary["db_rows_kept_differing"]) == (1, 0)
    assert err.rstrip().endswith(f"1 of 1 pairs had rows in {db} for this configuration, the same as this run's: kept")
    right = cv2.imread(str(scene / "im1.png"))
    cv2.imwrite(str(scene / "im1.png"), np.roll(right, 12, axis=1))
    summary, now, err = run()
    assert (summary["db_rows_kept"], summary["db_rows_kept_differing"]) == (1, 1)
    assert abs(now - first) > 1
    assert f"the store keeps those, not this run's: 1 of them differs (first eval3/Teddy" in err
    with sqlite3.connect(db) as connection:
        assert connection.execute("SELECT acc_objects_pct FROM results").fetchall() == [(first,)]


def test_a_calibration_option_no_listed_pair_takes_is_refused(data_dir, tmp_path, capsys):
    """Found by an audit of the bulk commands: eval --focal-px / --baseline-m over scene folders (which carry their
    own calibration) ran as if not given, exit 0; estimate refused the same."""
    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    assert main(["eval", str(teddy), "--size", "160x120", "--focal-px", "300", "--baseline-m", "0.2"]) == 2
    assert "--focal-px, --baseline-m: every listed pair is a scene folder" in capsys.readouterr().err
    out_folder = tmp_path / "maps"
    assert main(["eval", str(teddy), "--size", "160x120", "--focal-px", "300", "--disparity-out", str(out_folder)]) == 2
    assert not out_folder.exists()  # refused before the output folder was made
    bad = tmp_path / "bad.txt"
    bad.write_text("a b c\n")  # a bad line is reported as such, not as a calibration the option would not change
    assert main(["eval", str(bad), "--size", "160x120", "--focal-px", "300", "--json"]) == 0
    assert '"status": "BAD_INPUT"' in capsys.readouterr().out
    listing = tmp_path / "list.txt"
    listing.write_text(f"{teddy / 'im0.png'} {teddy / 'im1.png'}\n")
    assert main(["eval", str(listing), "--size", "160x120", "--focal-px", "300", "--json"]) == 0  # a file pair takes it
    assert '"focal_px": 300.0' in capsys.readouterr().out


def test_a_list_line_mended_since_leaves_no_failed_pair_in_the_store(data_dir, tmp_path, capsys):
    """Found by an audit of the bulk commands: a line `L R 40O 0.16` (a letter O) was stored BAD_INPUT under an id
    naming the line; mended to 400, its pair ran OK under its own id and the old failure stayed: 'pairs 3, fail 1'
    for two listed pairs, in every mean. A line of another list is not touched."""
    import json

    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    listing, other = tmp_path / "list.txt", tmp_path / "other.txt"
    db = tmp_path / "s.sqlite"
    other.write_text(f"{teddy / 'im0.png'} {teddy / 'im1.png'} x 0.16\n")
    assert main(["eval", str(other), "--size", "160x120", "--db", str(db)]) == 0
    for focal in ("40O", "400"):
        listing.write_text(f"{teddy}\n{teddy / 'im0.png'} {teddy / 'im1.png'} {focal} 0.16\n")
        assert main(["eval", str(listing), "--size", "160x120", "--db", str(db)]) == 0
    capsys.readouterr()
    assert main(["results", str(db), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)["configs"][0]
    assert (summary["pairs"], summary["failed"]) == (3, 1)  # the other list's bad line stays; the mended one went


def test_eval_table_keeps_its_columns_for_every_status():
    """Found by an audit: DEGENERATE_RECTIFICATION overflowed the 17-character status column and shifted every
    number after it."""
    from svs_torch.cli.evaluate import HEADER, STATUS_WIDTH, format_row
    from svs_torch.evaluation.metrics import UNRUN_STATUSES
    from svs_torch.pipeline import PipelineStatus

    statuses = [status.name for status in PipelineStatus] + list(UNRUN_STATUSES)
    assert STATUS_WIDTH == max(map(len, statuses))
    fields = {name: None for name in ("r_min_m", "real_r_min_m", "acc_r_min_pct", "r_max_m", "real_r_max_m",
                                      "acc_r_max_pct", "acc_objects_pct", "dense_within_1px", "inlier_precision",
                                      "kept_nocc_bad2_pct", "kept_all_bad2_pct", "kept_all_avgerr_px",
                                      "kept_all_d1_pct", "kept_all_density")}
    rows = [format_row(SimpleNamespace(name="eval3/Teddy", status=status, time_s=0.5, calibrated=True,
                                           calibration=None, **fields))
            for status in statuses]
    time_at = HEADER.index("time s")
    assert all(row[time_at:time_at + 6].strip() == "0.500" for row in rows)


def test_a_config_file_names_a_parameter_given_twice_or_an_empty_table(tmp_path):
    """An audit of hostile configuration files: `"segmentation.kernel_size" = 5` beside `[segmentation]
    kernel_size = 7` ran with one of them in silence, and `[exposure]` alone (the exposure map on, a user would read)
    ran with it off."""
    path = tmp_path / "config.toml"
    path.write_text('"segmentation.kernel_size" = 5\n[segmentation]\nkernel_size = 7\n')
    with pytest.raises(InputError, match=r"config\.toml: segmentation\.kernel_size: given twice"):
        resolve_config(config_file=path)
    path.write_text('max_ratio = 0.7\n[set]\nmax_ratio = 0.6\n')
    with pytest.raises(InputError, match=r"config\.toml: max_ratio: given both at the top level and in \[set\]"):
        resolve_config(config_file=path)
    path.write_text("[exposure]\n")
    with pytest.raises(InputError, match=r"config\.toml: exposure: expected true or false .*, got \{\}"):
        resolve_config(config_file=path)
    path.write_text("[exposure]\nmin_change = 0.2\n[segmentation]\nkernel_size = 3\n")  # tables with keys still work
    config, _, overrides = resolve_config(config_file=path)
    assert config.exposure.min_change == 0.2 and overrides == {"exposure.min_change": 0.2,
                                                               "segmentation.kernel_size": 3}


def test_the_json_summary_records_the_configuration_that_ran(data_dir, tmp_path, capsys):
    """An audit: eval --json's summary line named no preset, override, size or value, so a line kept from a run
    could not be reproduced; it now carries them, and the whole configuration in effect."""
    path = tmp_path / "config.toml"
    path.write_text('preset = "paper"\n[dense]\nwindow_size = 7\n')
    code = main(["eval", str(data_dir / "middlebury_eval3_Q" / "Teddy"), "--size", "160x120", "--json",
                 "--config", str(path), "--set", "max_ratio=0.7"])
    summary = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert code == 0 and summary["pairs"] == 1 and summary["preset"] == "paper" and summary["size"] == "160x120"
    assert summary["overrides"] == {"dense.window_size": 7, "max_ratio": 0.7}
    ran = apply_overrides(PipelineConfig.paper(), summary["overrides"])
    assert summary["config"] == json.loads(json.dumps(config_to_dict(ran)))


def test_each_section_is_checked_with_its_final_values_whatever_the_order_of_its_keys(tmp_path):
    """An audit: overrides were applied one at a time, each dataclass checked on the way, so `--set
    segmentation.ground.min_camera_height_m=4 --set segmentation.ground.max_camera_height_m=5` (and the same two keys
    in a file's [segmentation.ground]) failed as "expected 0 < min < max, got 4.0, 3.0", 3 the default maximum the
    second key replaced; only the reverse order ran. `--preset paper --set differentiable=true --set depth.rule=dense`
    likewise."""
    config, _, _ = resolve_config(assignments=["segmentation.ground.min_camera_height_m=4",
                                               "segmentation.ground.max_camera_height_m=5"])
    assert (config.segmentation.ground.min_camera_height_m, config.segmentation.ground.max_camera_height_m) == (4, 5)
    path = tmp_path / "config.toml"
    path.write_text("[segmentation.ground]\nmin_camera_height_m = 4.0\nmax_camera_height_m = 5.0\n")
    assert resolve_config(config_file=path)[0] == config
    config, _, _ = resolve_config("paper", assignments=["differentiable=true", "depth.rule=dense"])
    assert config.differentiable and config.depth.rule == "dense"
    with pytest.raises(InputError, match=r"^--set: segmentation\.ground\.min_camera_height_m = 4, segmentation\.ground"
                                         r"\.max_camera_height_m = 2: min_camera_height_m, .* got 4\.0, 2\.0$"):
        resolve_config(assignments=["segmentation.ground.min_camera_height_m=4",
                                    "segmentation.ground.max_camera_height_m=2"])
    with pytest.raises(InputError, match=r"^--set: differentiable = True, depth\.rule = 'paper': differentiable: "):
        resolve_config("paper", assignments=["depth.rule=dense", "differentiable=true", "depth.rule=paper"])


def test_a_refused_combination_names_the_keys_its_message_is_about():
    """A refusal by the whole configuration names the keys its check names, not every key set at its level: on a
    differentiable configuration, max_ratio=0.7 with depth.rule=paper is refused for depth.rule."""
    differentiable = dataclasses.replace(PipelineConfig(), differentiable=True)
    with pytest.raises(InputError, match=r"^--set: depth\.rule = 'paper': differentiable: needs depth\.rule"):
        apply_overrides(differentiable, {"max_ratio": 0.7, "depth.rule": "paper"}, "--set")
    with pytest.raises(InputError, match=r"^grid: max_ratio = 2: max_ratio: expected a ratio in \(0, 1\]"):
        apply_overrides(PipelineConfig(), {"dense.window_size": 9, "max_ratio": 2}, "grid")


def test_a_scene_that_cannot_be_loaded_is_named_as_a_loaded_one(data_dir, tmp_path, capsys):
    """Found by an audit of eval on one's own data: a scene folder whose truth file was cut short was reported as
    ``tmp/Teddy`` (its folders), the same scene loaded as ``eval3/Teddy`` (its loader's name), so one pair had two
    names across runs; a KITTI frame alike (``stereo2015_training/...`` against ``kitti2015/...``). Each failed
    row is named as the pair would be loaded, as ``estimate --pairs`` names its exported map."""
    import json
    import shutil

    broken, whole = tmp_path / "broken" / "Teddy", tmp_path / "whole" / "ArtL"
    shutil.copytree(data_dir / "middlebury_eval3_Q" / "Teddy", broken)
    shutil.copytree(data_dir / "middlebury_eval3_Q" / "ArtL", whole)
    kitti = tmp_path / "stereo2015_training"
    shutil.copytree(data_dir / "kitti" / "stereo2015_training", kitti)
    for truth in (broken / "disp0GT.pfm", kitti / "disp_occ_0" / "000000_10.png"):
        truth.write_bytes(truth.read_bytes()[:200])
    assert main(["eval", str(broken), str(whole), str(kitti / "image_2" / "000000_10.png"), "--size", "160x120",
                 "--json"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()][:-1]
    assert [(row["name"], row["status"]) for row in rows] == [
        ("eval3/Teddy", "BAD_INPUT"), ("eval3/ArtL", "OK"), ("kitti2015/000000_10", "BAD_INPUT")]


@pytest.mark.parametrize("call, message", [
    (lambda sources: evaluate_block(str(sources[0].left), EvalSetup()), "sources: expected a list of PairSource"),
    (lambda sources: evaluate_block(sources[0], EvalSetup()), "sources: expected a list of PairSource"),
    (lambda sources: evaluate_block(sources, None), "setup: expected an EvalSetup, got NoneType"),
    (lambda sources: evaluate_block(sources, EvalSetup(config={})),
     "setup.config: expected a PipelineConfig, got dict"),
    (lambda sources: evaluate_block(sources, EvalSetup(max_pixels="9")),
     "setup.max_pixels: expected an integer of at least 1, got '9'"),
    (lambda sources: evaluate_block(sources, EvalSetup(doffs_px=None)), "setup.doffs_px: expected a number, got None"),
    (lambda sources: evaluate_block(sources, EvalSetup(focal_px=-5)), "setup.focal_px: expected a focal length"),
    (lambda sources: evaluate_block(sources, EvalSetup(calibration="rig.json")),
     "setup.calibration: expected a StereoCalibration, got str"),
    (lambda sources: list(evaluate_pairs(sources, EvalSetup(), batch_size=-1)),
     "batch_size: expected an integer of at least 1, got -1"),
    (lambda sources: list(evaluate_pairs(sources, EvalSetup(), batch_size=0)),
     "batch_size: expected an integer of at least 1, got 0"),
])
def test_a_bad_argument_of_the_evaluation_api_is_refused_by_name_before_any_pair_runs(data_dir, call, message):
    """Found by an audit of the Python API: a folder's name for the pairs was an AttributeError from the loader, a
    dict for the configuration made every pair ERROR, a batch_size of -1 evaluated nothing without a word (0 failed
    in range()), a max_pixels or doffs_px of another type was a TypeError from deep inside, and a negative focal_px
    made every listed pair BAD_INPUT where the command line refuses the option."""
    folder = data_dir / "opencv_samples"
    sources = [PairSource(str(folder / "left01.jpg"), str(folder / "right01.jpg"))]
    with pytest.raises(InputError) as error:
        call(sources)
    assert str(error.value).startswith(message)


def test_the_summary_gathered_pair_by_pair_is_the_lists_to_the_bit():
    """An audit of bulk runs: eval held every row to its end for its summary; it now gathers the summary pair by pair
    (RunningSummary) and lets the rows go. Its means are still statistics.fmean of the list's values, to the bit, where
    a running float sum is not (1e16, 1.0 and -1e16 among them), its lists the list's, and its summary of the pairs
    so far (an interrupted run's) that of those pairs."""
    import random
    import statistics

    from svs_torch.evaluation import PairEvaluation
    from svs_torch.evaluation.running_summary import MEANS, RunningSummary

    rng = random.Random(5)
    awkward = (1e16, 1.0, -1e16, 0.1, 0.2, 0.3, 99.97, 1e-9, 3.3333333333333335)

    def value():
        return rng.choice(awkward) if rng.random() < 0.5 else (None if rng.random() < 0.2 else rng.uniform(0, 100))

    rows = []
    for _ in range(300):
        status = rng.choice(["OK"] * 6 + ["NO_OBJECTS", "BAD_INPUT"])
        rows.append(PairEvaluation(
            f"p{rng.randrange(1000):03d}", status, reason=None if status == "OK" else "why",
            calibrated=rng.choice([True, False, None]), has_truth=rng.random() < 0.8,
            acc_r_min_pct=value() if status == "OK" else None, acc_r_max_pct=value(), acc_objects_pct=value(),
            **{key: value() for key in MEANS}, time_s=rng.random()))

    def mean(values):
        return statistics.fmean(values) if values else None

    summary, running = summarize(rows, wall_s=2.0), RunningSummary()
    with_truth = [e for e in rows if e.acc_r_min_pct is not None or (e.has_truth and not e.ok)]
    for key in ("acc_r_min_pct", "acc_r_max_pct", "acc_objects_pct"):
        assert summary[key] == mean([getattr(e, key) or 0.0 for e in with_truth if e.calibrated is not False])
        assert summary["nominal_calibration"][key] == mean([getattr(e, key) or 0.0 for e in with_truth
                                                            if e.calibrated is False])
    naive = 0
    for key in MEANS:
        values = [getattr(e, key) for e in rows if getattr(e, key) is not None]
        assert summary[key] == mean(values), key
        naive += sum(values) / len(values) != summary[key]
    assert naive  # (the check has teeth: a plain running sum gives other means)
    assert summary["unscored"]["names"] == sorted(e.name for e in rows if e.ok and e.acc_r_min_pct is None)[:100]
    assert summary["nominal_calibration"]["names"] == sorted(e.name for e in with_truth if e.calibrated is False)
    assert [f["name"] for f in summary["failures"]] == sorted(e.name for e in rows if not e.ok)
    for number, row in enumerate(rows, start=1):
        running.add(row)
        if number in (1, 7, 150, 300):
            assert running.summary(2.0) == summarize(rows[:number], wall_s=2.0)


def test_a_summary_names_at_most_the_first_hundred_pairs_scored_with_a_nominal_calibration():
    """Found by a look at a long run's output: eval --json's summary listed every pair scored with a nominal
    calibration by name (2 288 KITTI pairs were 95 % of a 63 kB summary line, in every row of a sweep's store too),
    while its ``unscored`` lists the first 100. It now lists the first 100 names in sorted order, as ``unscored``
    does, beside their count, gathered pair by pair in constant memory."""
    from svs_torch.evaluation import PairEvaluation
    from svs_torch.evaluation.running_summary import UNSCORED_NAMES, RunningSummary

    rows = [PairEvaluation(f"kitti/{(37 * i) % 250:06d}_10", "OK", calibrated=False, has_truth=True, acc_r_min_pct=90.0,
                           acc_r_max_pct=80.0, acc_objects_pct=85.0, time_s=0.1) for i in range(250)]
    rows.append(PairEvaluation("Teddy", "OK", calibrated=True, has_truth=True, acc_r_min_pct=99.0, acc_r_max_pct=98.0,
                               acc_objects_pct=97.0, time_s=0.1))
    summary = summarize(rows)
    nominal = summary["nominal_calibration"]
    assert nominal["scored"] == 250 and summary["scored"] == 1
    assert nominal["names"] == sorted(e.name for e in rows[:250])[:UNSCORED_NAMES] and UNSCORED_NAMES == 100
    assert nominal["acc_objects_pct"] == 85.0
    running = RunningSummary()
    for row in rows:
        running.add(row)
    assert len(running.nominal_first) == UNSCORED_NAMES and running.summary() == summary


@pytest.mark.skipif(not (sys.platform.startswith("linux")), reason="needs open-file-description locks (Linux)")
def test_eval_db_holds_its_configuration_while_it_runs_so_results_says_the_rest_is_not_run_yet(data_dir, tmp_path,
                                                                                                 capsys, monkeypatch):
    """Found by an audit of results on a store still being written: an eval --db held no claim, so results read
    while it ran could not tell it from a stopped one ("not run yet by a run still going, or a run stopped before
    it"), and a sweep of the same configuration on the store ran its pairs a second time beside it. eval now holds
    its configuration as a sweep does, while it runs: another process sees the store written, and a second eval of
    that configuration is refused naming --db, nothing recorded by it; once eval ends, nothing is held."""
    import contextlib
    import subprocess

    from svs_torch.evaluation.store import ResultStore

    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    db = tmp_path / "runs.sqlite"
    seen = []
    probe = [sys.executable, "-c", "import sys; from svs_torch.evaluation.store_access import sweep_is_writing; "
             "print(sweep_is_writing(sys.argv[1]))", str(db)]
    real = ResultStore.write_task

    def write_task(store, *args, **kwargs):  # while eval runs: another process reads the store, a second eval starts
        seen.append(subprocess.run(probe, capture_output=True, text=True, check=True).stdout.strip())
        seen.append(main(["eval", str(teddy), "--size", "160x120", "--db", str(db), "--json"]))
        return real(store, *args, **kwargs)

    monkeypatch.setattr(ResultStore, "write_task", write_task)
    assert main(["eval", str(teddy), "--size", "160x120", "--db", str(db), "--json"]) == 0
    err = capsys.readouterr().err
    assert seen == ["True", 2], seen
    assert f"--db: another run (a sweep or an eval --db) is writing {db}" in err, err
    assert subprocess.run(probe, capture_output=True, text=True, check=True).stdout.strip() == "False"
    import sqlite3

    with contextlib.closing(sqlite3.connect(db)) as connection:  # the refused eval recorded no run
        assert connection.execute("SELECT count(*) FROM runs").fetchone() == (1,)
