"""Settings only the dense range rule reads are said to have no effect under the paper's rule (eval's --set and
--config, a sweep), and they do have none: the paper preset gives the same results, bit for bit, with every one
of them changed."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
import torch

from svs_torch.cli import main
from svs_torch.data import load_stereo_pair, resize_stereo_batch
from svs_torch.evaluation.inert_settings import DENSE_RULE_ONLY, NEARNESS_SEGMENTER_ONLY, inert_overrides
from svs_torch.evaluation.overrides import apply_overrides
from svs_torch.evaluation.sweep import load_sweep
from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth

#: Each key of DENSE_RULE_ONLY set away from the paper preset's value, and some of the dense stage's.
CHANGED = {
    "dense.window_size": 5, "dense.working_width_px": 200, "dense.uniqueness_ratio": 0.3, "dense.fill_invalid": False,
    "verify_min_inliers": 50, "verify_min_inlier_share": 0.9, "verify_min_agreeing_inliers": 30,
    "verify_many_inliers": "none", "verify_many_inliers_min_agreeing": 9, "verify_unanimous_min_inliers": "none",
    "verify_unanimous_min_agreeing": 9, "verify_whole_view": False, "noisy_retry_sigma_px": 1.0,
    "noisy_features_retry_sigma_px": 1.5, "coarse_retry_below_share": 0.45, "drop_unmeasured_below_share": 0.3,
    "drop_unmeasured_nearer_below_share": 0.1, "region_interior_working_px": 2.0, "measure_near_surface": True,
    "exposure_retry": True, "exposure_retry_max_residual_ratio": 0.1,
    # the dense map's object checks: these ran in silence under --preset paper (an audit of sweeps and presets)
    "depth.surface_within_in_view_top": False, "depth.min_object_pixels": 500, "depth.min_object_valid_fraction": 0.9,
    "depth.min_object_valid_fraction_unverified": 0.95, "depth.min_object_pixels_in_view": 500,
    "depth.coarse_retry_max_period_peak": "none", "depth.alias_check_min_period_peak": 0.1,
    "depth.coarse_retry_max_period_px": 8, "depth.alias_check_max_period_px": 8,
}


def _pairs(data_dir):
    """Teddy at 160x120 as it is, and with its right view 30 % brighter and noisy: the pairs the second passes
    and the exposure retry run on under the dense rule."""
    batch = resize_stereo_batch(load_stereo_pair(data_dir / "middlebury_eval3_Q" / "Teddy"), (160, 120))
    noise = torch.randn(batch.right.shape, generator=torch.Generator().manual_seed(0)) * (6 / 255)
    bright = dataclasses.replace(batch, right=(batch.right * 1.3 + noise).clamp(0, 1))
    return [batch, bright]


def _outcome(result) -> list[np.ndarray]:
    depth = result.depth
    return [t.numpy() for t in (result.status, result.fundamental.inliers, result.segmentation.left.kept_labels,
                                depth.range.r_min_m, depth.range.r_max_m, depth.objects.depth_median_m,
                                depth.objects.valid)]


def test_every_dense_rule_setting_changes_nothing_under_the_paper_rule(data_dir):
    assert {key if key.startswith("depth.") else key.split(".")[0] for key in CHANGED} == set(DENSE_RULE_ONLY)
    paper = PipelineConfig.paper()
    changed = apply_overrides(paper, CHANGED)
    assert list(inert_overrides(changed, CHANGED)) == list(CHANGED)
    assert inert_overrides(apply_overrides(PipelineConfig(), CHANGED), CHANGED) == {}  # the dense rule reads them
    for batch in _pairs(data_dir):
        before, after = (_outcome(estimate_obstacle_depth(batch, config)) for config in (paper, changed))
        for one, other in zip(before, after):
            np.testing.assert_array_equal(one, other)


#: Each field of NEARNESS_SEGMENTER_ONLY set away from the default (the floor turned on, with a setting of its own).
NEARNESS_CHANGED = {"segmentation.ground.min_camera_height_m": 0.5, "segmentation.min_measured_share": 0.9,
                    "segmentation.max_clipped_share": 0.01, "segmentation.keep": "nearest_first",
                    "segmentation.min_area_fraction": 0.2, "segmentation.near_min_area_fraction": 0.1}


@pytest.mark.parametrize("segmenter", ["otsu", "learned"])
def test_the_nearness_segmenters_settings_change_nothing_under_another(data_dir, segmenter):
    """The floor, the share of the view measured, the clipped regions and the keep rule with its least areas are the
    nearness segmenter's alone: under Otsu (the paper preset's) and the learned segmenter (both keep="largest" here,
    changed to "nearest_first") the results are the same, bit for bit; under the nearness segmenter (the default)
    they are read."""
    assert {".".join(key.split(".")[:2]) for key in NEARNESS_CHANGED} == set(NEARNESS_SEGMENTER_ONLY)
    base = PipelineConfig.paper() if segmenter == "otsu" else apply_overrides(
        PipelineConfig(), {"segmentation.segmenter": "learned", "segmentation.keep": "largest"})
    changed = apply_overrides(base, NEARNESS_CHANGED)
    assert list(inert_overrides(changed, NEARNESS_CHANGED)) == list(NEARNESS_CHANGED)
    assert inert_overrides(apply_overrides(PipelineConfig(), NEARNESS_CHANGED), NEARNESS_CHANGED) == {}
    for batch in _pairs(data_dir):
        before, after = (_outcome(estimate_obstacle_depth(batch, config)) for config in (base, changed))
        for one, other in zip(before, after):
            np.testing.assert_array_equal(one, other)


def test_eval_says_which_settings_do_nothing(data_dir, tmp_path, capsys):
    """Found by an audit of --set: 'eval --preset paper --set dense.window_size=9' ran, said nothing, and gave the
    results without it (the dense stage does not run under the paper rule)."""
    teddy = str(data_dir / "middlebury_eval3_Q" / "Teddy")
    config = tmp_path / "c.toml"
    config.write_text('preset = "paper"\n"verify_min_inliers" = 9\nmax_ratio = 0.7\n')
    runs = [(["--preset", "paper", "--set", "dense.window_size=7", "--set", "max_ratio=0.7"],
             "--set: dense.window_size: no effect under the paper range rule (depth.rule = 'paper'): only the dense "
             "rule reads it"),
            (["--config", str(config)], f"--config: {config}: verify_min_inliers: no effect under the paper range"),
            (["--set", "dense.window_size=7", "--set", "depth.rule=paper", "--set", "measure_near_surface=true"],
             "--set: dense.window_size, measure_near_surface: no effect"),
            (["--config", str(config), "--set", "depth.rule=dense"], None),
            (["--preset", "paper", "--set", "segmentation.max_clipped_share=0.2"],
             "--set: segmentation.max_clipped_share: no effect under the otsu segmenter (segmentation.segmenter): only "
             "the nearness segmenter reads it"),
            (["--set", "segmentation.max_clipped_share=0.2"], None),
            # was silent (an audit): Otsu keeps the largest regions whatever the keep rule says
            (["--preset", "paper", "--set", "segmentation.keep=nearest_first"],
             "--set: segmentation.keep: no effect under the otsu segmenter (segmentation.segmenter): only the nearness "
             "segmenter reads it"),
            (["--set", "segmentation.keep=largest"], None)]
    for options, warned in runs:
        assert main(["eval", teddy, "--size", "160x120", "--json", *options]) == 0
        err = capsys.readouterr().err
        assert err.count("no effect under the") == (warned is not None), (options, err)
        assert warned is None or warned in err, err


def test_a_sweep_says_once_which_settings_do_nothing(data_dir, tmp_path):
    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    sweep_file = tmp_path / "sweep.toml"
    sweep_file.write_text(f'paths = ["{teddy}"]\n[grid]\n"dense.window_size" = [7, 9]\n'
                          '[[configs]]\npreset = "paper"\n[[configs]]\npreset = "default"\n')
    with pytest.warns(UserWarning) as caught:
        assert len(load_sweep(sweep_file).configs) == 4
    said = [str(w.message) for w in caught if "no effect" in str(w.message)]
    assert said == [f"{sweep_file}: dense.window_size: no effect under the paper range rule (depth.rule = 'paper') "
                    "in 2 of 4 configurations: only the dense rule reads it"], said
    sweep_file.write_text(f'paths = ["{teddy}"]\n[grid]\n"dense.window_size" = [7, 9]\n')
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_sweep(sweep_file)
