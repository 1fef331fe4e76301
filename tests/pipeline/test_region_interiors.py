"""Each kept region of the nearness segmenter is measured over its interior (``PipelineConfig.
region_interior_working_px``, ``PipelineResult.object_labels``): the segmentation, the dense search and the
verdicts stay those of the whole regions; the objects' depths, areas and truths are over the interiors."""

from __future__ import annotations

import dataclasses
import sys

import pytest
import torch
from conftest import REPO_ROOT

from svs_torch.evaluation import evaluate_result, measured_regions, object_truth
from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth

sys.path.insert(0, str(REPO_ROOT / "experiments"))

import real_rig  # noqa: E402


@pytest.fixture(scope="module")
def pipes(data_dir):
    return real_rig.resample(real_rig.load_scene(data_dir / "middlebury_eval3_Q" / "Pipes"), "320x240")


def test_objects_are_measured_over_the_interiors_of_the_same_regions(pipes):
    """Tuned Pipes at 320×240: thin pipes whose regions the block matcher fattens onto the wall behind them."""
    inner = estimate_obstacle_depth(pipes)
    whole = estimate_obstacle_depth(pipes, dataclasses.replace(PipelineConfig(), region_interior_working_px=None))
    assert torch.equal(inner.segmentation.left.labels, whole.segmentation.left.labels)
    assert torch.equal(inner.dense.crop_xywh, whole.dense.crop_xywh) and bool(inner.verified[0] == whole.verified[0])
    assert torch.equal(whole.object_labels, whole.segmentation.left.labels)
    objects, seg = inner.depth.objects, inner.segmentation.left
    for slot, label in enumerate(seg.kept_labels[0].tolist()):
        if label <= 0:
            continue
        region, interior = seg.labels[0, 0] == label, inner.object_labels[0, 0] == label
        assert bool((interior <= region).all()) and int(interior.sum()) < int(region.sum())
        assert int(objects.area_px[0, slot]) == int(interior.sum())
        assert int(whole.depth.objects.area_px[0, slot]) == int(region.sum())
    # Every object's truth is the median ground truth over the pixels its estimate is the median of.
    truth = object_truth(pipes, measured_regions(inner))
    assert torch.equal(truth.depth_m, object_truth(pipes, dataclasses.replace(seg, labels=inner.object_labels)).depth_m)
    assert not torch.equal(truth.depth_m, object_truth(pipes, seg).depth_m)
    # measured 97.89 % over the whole regions, 98.46 % over their interiors (each of its two objects gains 0.5-0.6)
    acc_inner, acc_whole = (evaluate_result(pipes, r)[0].acc_objects_pct for r in (inner, whole))
    assert acc_whole < 98.1 < 98.3 < acc_inner


def test_the_paper_preset_and_otsu_pairs_measure_the_whole_regions(pipes):
    paper = estimate_obstacle_depth(pipes, PipelineConfig.paper())
    assert torch.equal(paper.object_labels, paper.segmentation.left.labels)
    assert paper.segmentation.from_disparity is None
