"""Figures that read well, written whole: real renders (matplotlib Agg) checked for text inside the page, white
labels on dark boxes, legends, a depth colour bar, ground truth beside the estimate; files written through a
temporary file with the permissions the umask gives."""

from __future__ import annotations

import contextlib
import dataclasses
import os
import stat
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from svs_torch import StereoBatch, estimate_obstacle_depth
from svs_torch.cli import main
from svs_torch.core.errors import InputError
from svs_torch.core.files import atomic_output, path_kind, write_bytes_atomic
from svs_torch.data.synthetic import random_obstacle_scenes
from svs_torch.pipeline import PipelineConfig
from svs_torch.plotting.figures import (AREA_LABEL_ROWS, LABEL_PAD_POINTS, depth_label_y, labels_image,
                                        objects_panel, write_image_atomic)
from svs_torch.plotting.plots import matches_figure, pipeline_figure, render


@contextlib.contextmanager
def umask(mask: int):
    old = os.umask(mask)
    try:
        yield
    finally:
        os.umask(old)


@pytest.fixture(scope="module")
def scene():
    """A synthetic SVS pair with exact ground truth, and the pipeline's result on it."""
    scenes = random_obstacle_scenes(1, 2, size_wh=(96, 72), generator=torch.Generator().manual_seed(3))
    return scenes.batch, estimate_obstacle_depth(scenes.batch)


def drawn_texts(figure) -> list:
    """Every text the figure draws: the title, axes titles, texts on images, legends, and the tick and axis labels
    of the axes that show them (colour bars)."""
    texts = [figure._suptitle] if figure._suptitle is not None else []
    for ax in figure.axes:
        texts += [ax.title, *ax.texts]
        if ax.get_legend() is not None:
            texts += ax.get_legend().get_texts()
        if ax.axison:
            texts += [*ax.get_xticklabels(), *ax.get_yticklabels(), ax.xaxis.label, ax.yaxis.label]
    return [t for t in texts if t.get_visible() and t.get_text().strip()]


def assert_every_text_inside(figure) -> None:
    render(figure)
    renderer = figure.canvas.get_renderer()
    page = figure.bbox
    for text in drawn_texts(figure):
        box = text.get_window_extent(renderer)
        assert (box.x0 >= page.x0 - 1 and box.y0 >= page.y0 - 1 and box.x1 <= page.x1 + 1
                and box.y1 <= page.y1 + 1), f"clipped: {text.get_text()!r} at {box.bounds} in {page.bounds}"


def test_pipeline_figure_shows_ground_truth_beside_the_estimate(scene):
    batch, result = scene
    figure = pipeline_figure(batch, result, 0)
    titles = [ax.get_title() for ax in figure.axes]
    assert any("dense depth estimate" in t for t in titles) and any("ground-truth depth" in t for t in titles)
    colour_bars = [ax for ax in figure.axes if ax.get_ylabel() == "depth (m)"]
    assert len(colour_bars) == 1  # one scale for the estimate and the truth
    labels = [t for ax in figure.axes for t in ax.texts]
    assert labels and all("true" in t.get_text() for t in labels)
    # Each object's true depth is the median ground-truth depth over its region (synthetic truth, exact).
    truth, valid = batch.ground_truth_depth_m()
    region = result.segmentation.left.labels[0, 0] == result.segmentation.left.kept_labels[0, 0]
    expected = float(truth[0, 0][region & valid[0, 0]].median())
    assert f"true {expected:.2f} m" in labels[0].get_text() or f"true {expected:.2f} m" in labels[1].get_text()
    assert "true" in figure._suptitle.get_text()  # the nearest obstacle's true depth in the title
    assert_every_text_inside(figure)


def test_pipeline_figure_names_a_batch_and_a_result_given_swapped_or_missing(scene):
    """Found by a library user's audit: estimate_figure(result, batch, 0) failed with "AttributeError:
    'PipelineResult' object has no attribute 'disparity_px'" from deep inside, and a result of None likewise."""
    from svs_torch.plotting.plots import estimate_figure

    batch, result = scene
    with pytest.raises(InputError, match="^batch: expected a StereoBatch, got PipelineResult$"):
        estimate_figure(result, batch, 0)
    with pytest.raises(InputError, match="^result: expected a PipelineResult, got NoneType$"):
        pipeline_figure(batch, None, 0)


def test_pipeline_figure_says_an_unranged_object_repeats(scene):
    """Was: a fence whose alias the views could not tell (the rendered 8 px bars at 1.5 m of
    experiments/repeated_patterns.py as a loose rig's frames) was labelled "no depth", like a region nothing could be
    measured on, where estimate's text says it repeats. Now its label says so; a ranged object's is as before."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "experiments"))
    import repeated_patterns as rp

    lefts, rights, _, _ = rp.render_pairs(periods=(8,))
    bars = rp.condition_batch(lefts, rights, rp.LOOSE_RIG, 4, 4.0).select([rp.cases((8,)).index(("bars", 8, 1.5))])
    with torch.inference_mode():
        result = estimate_obstacle_depth(bars, PipelineConfig())
    assert bool(result.unranged_repeated[0].all())
    labels = sorted(t.get_text() for ax in pipeline_figure(bars, result, 0).axes for t in ax.texts)
    assert labels == ["#1: no depth: it repeats", "#2: no depth: it repeats"]
    assert not any("repeats" in t.get_text() for ax in pipeline_figure(*scene, 0).axes for t in ax.texts)


def test_pipeline_figure_labels_are_white_on_dark_boxes_and_lines_have_a_legend(scene):
    batch, result = scene
    figure = pipeline_figure(batch, result, 0)
    for label in (t for ax in figure.axes for t in ax.texts):
        assert label.get_color() == "white"
        face = label.get_bbox_patch().get_facecolor()
        assert sum(face[:3]) / 3 < 0.2 and face[3] >= 0.7
    legend = [t.get_text() for ax in figure.axes if ax.get_legend() for t in ax.get_legend().get_texts()]
    assert any(t.startswith("RANSAC inlier (") for t in legend) and any(t.startswith("outlier (") for t in legend)


def test_pipeline_figure_draws_the_matches_on_the_views_they_were_found_on(scene):
    """Was: the matches were drawn on the masked images, black outside the kept regions, while the default finds
    its features on the whole views (``features_on="image"``): keypoints floated on black. Now the whole views,
    dimmed outside the kept regions: each side's panel is the view times 0.35 there and the view inside."""
    batch, result = scene
    figure = pipeline_figure(batch, result, 0)
    ax = next(ax for ax in figure.axes if ax.get_title().startswith("matches (the kept regions bright)"))
    canvas = ax.get_images()[0].get_array()
    height, width = batch.size_hw
    for side, (view, seg) in enumerate(((batch.left, result.segmentation.left),
                                        (batch.right, result.segmentation.right))):
        offset = side * (width + max(4, width // 50))
        drawn = np.asarray(canvas[:, offset:offset + width])
        image, kept = view[0, 0].numpy(), seg.kept_mask[0, 0].numpy()
        np.testing.assert_allclose(drawn, np.where(kept, image, 0.35 * image), atol=1e-6)
    keypoints = result.features_left.keypoints
    xy = keypoints.xy[0][keypoints.valid[0]].round().long()
    outside = ~result.segmentation.left.kept_mask[0, 0][xy[:, 1].clamp(0, height - 1), xy[:, 0].clamp(0, width - 1)]
    assert bool(outside.any())  # the default's keypoints lie outside the regions too, on a visible background


def test_a_depth_label_leaves_the_area_label_of_a_short_region_readable():
    """Was: the depth label sat on the region's centroid, which for a short region (held-out Laundry's window at
    320 px, a box 20 rows tall) covered the ``#1 928px`` label at the top of its box. Now it sits below that
    label where it would cover it, and stays inside the image."""
    size_hw, width_in = (240, 320), 4.2
    assert depth_label_y(120.0, 40.0, 2, size_hw, width_in) == 120.0  # a tall region: on its centroid
    moved = depth_label_y(95.0, 88.0, 2, size_hw, width_in)
    one_line = depth_label_y(95.0, 88.0, 1, size_hw, width_in)
    assert moved > one_line > 88.0 + AREA_LABEL_ROWS  # the label's upper half clears the area label's rows
    half = moved - (88.0 + AREA_LABEL_ROWS)
    assert 5.0 < half < 20.0  # two lines of 9 pt, about 27 px on a 320 px panel 4.2 in wide
    assert depth_label_y(235.0, 230.0, 2, size_hw, width_in) == pytest.approx(240 - half)  # kept inside


def test_depth_labels_are_kept_apart_and_inside_the_panel():
    """Found by an audit of the figures: two objects' labels at nearly one place covered each other (PianoL), and
    a label at the left edge was cut ('e 2.60 m'). Boxes estimated as place_depth_labels does: none overlaps, each
    inside the panel."""
    from svs_torch.plotting.figures import place_depth_labels

    size_hw, width_in = (240, 320), 4.2
    labels = [(160.0, 120.0, 60.0, "#1: 1.94 m\ntrue 1.96 m"), (165.0, 125.0, 70.0, "#2: 1.89 m\ntrue 1.96 m"),
              (2.0, 200.0, 190.0, "#3: no depth\ntrue 2.60 m"), (170.0, 118.0, 60.0, "#4: 3.10 m")]
    centres = place_depth_labels(labels, size_hw, width_in)
    points_to_px = 320 / (72 * width_in)
    boxes = []
    for (x, y), (*_, text) in zip(centres, labels):
        rows = text.split("\n")
        half_w = (max(map(len, rows)) * 9 * 0.6 + 2 * LABEL_PAD_POINTS) * points_to_px / 2
        half_h = (len(rows) * 9 * 1.25 + 2 * LABEL_PAD_POINTS) * points_to_px / 2
        assert half_w <= x <= 320 - half_w and half_h <= y <= 240 - half_h, text
        boxes.append((x - half_w, y - half_h, x + half_w, y + half_h))
    for i, a in enumerate(boxes):
        for b in boxes[i + 1:]:
            assert not (a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]), (a, b)
    assert centres[0] == (160.0, 120.0)  # the first stays on its centroid


def test_pipeline_figure_without_ground_truth_has_no_truth_panel():
    images = torch.rand(1, 1, 40, 56, generator=torch.Generator().manual_seed(0))
    batch = StereoBatch.from_images(images, images.roll(-2, -1), 100.0, 0.1)
    figure = pipeline_figure(batch, estimate_obstacle_depth(batch), 0)
    assert not any("ground-truth" in ax.get_title() for ax in figure.axes)
    assert "true" not in figure._suptitle.get_text()
    assert_every_text_inside(figure)



def test_depth_colour_bar_of_a_lone_wall_spans_10_cm_around_it():
    # An audit: `demo --objects 0 --preset paper` (a wall at 4 m, nothing else, no dense map) drew a bar from 4.000
    # to 4.001 m, read as "+4" over ticks 0.0000-0.0008, with the wall at the bar's very end.
    scenes = random_obstacle_scenes(1, 0, size_wh=(64, 48), generator=torch.Generator().manual_seed(0))
    figure = pipeline_figure(scenes.batch, estimate_obstacle_depth(scenes.batch, PipelineConfig.paper()), 0)
    bar = next(ax for ax in figure.axes if ax.get_ylabel() == "depth (m)")
    low, high = sorted(bar.get_ylim())
    assert high - low >= 0.1 - 1e-9 and low < 4.0 < high

@pytest.mark.parametrize("size_hw", [(1, 1), (5, 5), (6, 64), (64, 6), (200, 20)])
def test_pipeline_figure_titles_fit_at_any_aspect(size_hw):
    images = torch.rand(1, 1, *size_hw, generator=torch.Generator().manual_seed(1))
    batch = StereoBatch.from_images(images, images, 100.0, 0.1, names=("a-rather-long-pair-name_" * 3,))
    figure = pipeline_figure(batch, estimate_obstacle_depth(batch), 0)
    assert_every_text_inside(figure)
    assert max(render(figure).shape[:2]) <= 2000  # a tall or wide pair does not make a huge page


def test_demo_figure_at_a_tiny_size_is_not_a_column_of_title_letters(tmp_path, capsys):
    """Found by an audit: `demo --size 16x12` wrote a 1380x10473 figure, its top row's titles wrapped a letter a
    line at the 16 px panels and then scaled up 15 times with them. The panels are enlarged before their titles."""
    assert main(["demo", "--size", "16x12", "--seed", "14", "--figure", str(tmp_path / "tiny.png")]) == 0
    capsys.readouterr()
    height, width = cv2.imread(str(tmp_path / "tiny.png")).shape[:2]
    assert height < 1.5 * width  # (was 7.6 times its width)


@pytest.mark.parametrize("width", [24, 60, 320])
def test_a_title_wider_than_a_tiny_panel_is_wrapped_and_broken_never_clipped(width):
    """Found by an audit of the figures: at `demo --size 24x18` one-word lines were clipped mid-word ('imag',
    'binar'). Every line of the strip now fits the panel, and the words read back whole in order."""
    import svs_torch.plotting.figures as figures

    title = "left binary (nearness segmenter, p > 0.50) + opening"
    scale = 0.45 if width >= 160 else 0.35
    lines = figures._wrap(title, width - 8, scale)
    assert all(cv2.getTextSize(line, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][0] <= width - 8 for line in lines)
    assert "".join(lines).replace(" ", "") == title.replace(" ", "")
    assert figures.titled_panel(np.zeros((18, width, 3), np.uint8), title).shape[1] == width


def test_matches_figure_has_a_legend_for_inliers_and_outliers(scene):
    batch, result = scene
    keypoints = result.features_left.keypoints
    both = type(keypoints)(*(torch.cat([getattr(keypoints, f), getattr(result.features_right.keypoints, f)])
                             for f in ("xy", "scale", "score", "laplacian_sign", "orientation", "valid")))
    pairs = [[i, j] for i, j in enumerate(result.matches.idx[0].tolist()) if j >= 0]
    inlier = [bool(result.fundamental.inliers[0, i]) for i, _ in pairs]
    image = matches_figure(batch.left[0, 0], batch.right[0, 0], both, pairs, inlier)
    assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3
    plain = matches_figure(batch.left[0, 0], batch.right[0, 0], both, pairs)
    assert plain.shape[0] > 0 and not np.array_equal(image, plain)  # inlier colours differ from plain matches


def test_matches_beyond_the_most_drawn_are_thinned_and_counted(scene, monkeypatch):
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure

    from svs_torch.plotting import plots

    batch, result = scene
    idx = result.matches.idx[0].tolist()
    total = sum(j >= 0 for j in idx)
    assert total > 8

    def drawn(most: int) -> tuple[int, list[str]]:
        monkeypatch.setattr(plots, "MAX_DRAWN_MATCHES", most)
        ax = Figure().add_subplot()
        plots._matches_axis(ax, batch.left[0, 0].numpy(), batch.right[0, 0].numpy(), result.features_left.keypoints,
                            result.features_right.keypoints, idx, None, 0, "matches", 4.0)
        lines = sum(len(c.get_segments()) for c in ax.collections if isinstance(c, LineCollection))
        return lines, [t.get_text() for t in ax.get_legend().get_texts()]

    assert drawn(1000) == (total, [f"SAD match ({total})", "SURF keypoint"])
    lines, legend = drawn(4)
    assert lines <= 4 and legend[0] == f"SAD match ({total}, {lines} drawn)"


def test_objects_panel_labels_are_white(scene):
    batch, result = scene
    panel = objects_panel(batch.left, result.segmentation.left, 0)
    near_white = (panel.min(axis=2) > 230).sum()
    assert near_white > 10  # the white label text (the image itself is dimmed below 0.6 gray)


def test_objects_panel_labels_grow_with_the_image(scene):
    """A figure draws the panel at one size whatever the image's: at 1282 px wide a 1-pixel box and a 0.4 label
    were a hairline and an unreadable speck. The same objects in an image 4x the size, 384 px wide, have labels
    384 / 320 = 1.2x as large (the panel's base size holds up to 320 px)."""
    batch, result = scene
    seg = result.segmentation.left
    one = dataclasses.replace(seg, kept_labels=torch.tensor([[int(seg.kept_labels[0, 0]), -1]]))  # one label
    big = dataclasses.replace(one, labels=one.labels.repeat_interleave(4, -1).repeat_interleave(4, -2),
                              regions=dataclasses.replace(one.regions, bbox_xyxy=one.regions.bbox_xyxy * 4))
    image = batch.left.repeat_interleave(4, -1).repeat_interleave(4, -2)
    assert image.shape[-1] == 384

    def text_pixels(panel: np.ndarray) -> int:  # the white label text (the image is dimmed or tinted below it)
        return int((panel.min(axis=2) > 230).sum())

    small, large = text_pixels(objects_panel(batch.left, one, 0)), text_pixels(objects_panel(image, big, 0))
    assert small > 20 and 1.3 * small < large < 2.5 * small  # the same label at 1.2x: 56 and 101 pixels


def test_figure_file_is_a_png_with_the_umask_mode(scene, tmp_path):
    batch, result = scene
    target = tmp_path / "figure.png"
    with umask(0o027):
        write_image_atomic(target, render(pipeline_figure(batch, result, 0)))
    assert stat.S_IMODE(target.stat().st_mode) == 0o640
    decoded = cv2.imread(str(target))
    assert decoded is not None and decoded.shape[0] > 100
    assert [p.name for p in tmp_path.iterdir()] == ["figure.png"]  # no temporary file left


@pytest.mark.parametrize("mask", [0o022, 0o077, 0o002])
def test_cli_figures_follow_the_umask(tmp_path, mask):
    left = tmp_path / "left.png"
    scenes = random_obstacle_scenes(1, 2, size_wh=(64, 48), generator=torch.Generator().manual_seed(4))
    cv2.imwrite(str(left), (scenes.batch.left[0, 0] * 255).round().byte().numpy())
    cv2.imwrite(str(tmp_path / "right.png"), (scenes.batch.right[0, 0] * 255).round().byte().numpy())
    with umask(mask):
        assert main(["estimate", str(left), str(tmp_path / "right.png"), "--figure", str(tmp_path / "e.png"),
                     "--masks-out", str(tmp_path / "m.png")]) == 0
        assert main(["segment", str(left), str(tmp_path / "right.png"), "--figure", str(tmp_path / "s.png")]) == 0
    for name in ("e.png", "m.png", "s.png"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o666 & ~mask
        assert cv2.imread(str(tmp_path / name)) is not None


def test_a_file_name_with_dollars_is_drawn_as_written(tmp_path, capsys):
    """Found by an audit: a pair named l$bad\\frac$.png ended estimate --figure in "internal error: ValueError"
    (matplotlib read the name in the title as a formula) after its report, and l$x_1$.png was drawn as x₁."""
    left = tmp_path / "l$bad\\frac$.png"
    scenes = random_obstacle_scenes(1, 2, size_wh=(64, 48), generator=torch.Generator().manual_seed(4))
    cv2.imwrite(str(left), (scenes.batch.left[0, 0] * 255).round().byte().numpy())
    cv2.imwrite(str(tmp_path / "right.png"), (scenes.batch.right[0, 0] * 255).round().byte().numpy())
    assert main(["estimate", str(left), str(tmp_path / "right.png"), "--figure", str(tmp_path / "e.png")]) == 0
    assert cv2.imread(str(tmp_path / "e.png")) is not None and "internal error" not in capsys.readouterr().err


def test_atomic_output_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.bin"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError):
        with atomic_output(target) as stream:
            stream.write(b"half")
            raise RuntimeError("interrupted")
    assert target.read_bytes() == b"old" and [p.name for p in tmp_path.iterdir()] == ["out.bin"]
    write_bytes_atomic(target, b"new")
    assert target.read_bytes() == b"new" and [p.name for p in tmp_path.iterdir()] == ["out.bin"]


def test_path_kind_names_unusable_paths(tmp_path):
    assert path_kind(tmp_path, "out") == "folder" and path_kind(tmp_path / "x", "out") == "missing"
    with pytest.raises(InputError, match=r"^out: not a usable path \(File name too long\)"):
        path_kind(tmp_path / ("x" * 5000), "out")
    with pytest.raises(InputError, match=r"^out: not a usable path"):
        path_kind("a\0b", "out")


def test_labels_image_round_trips_lossless(scene, tmp_path):
    _, result = scene
    labels = labels_image(result.segmentation.left, 0)
    target = tmp_path / "labels.png"
    write_image_atomic(target, labels, "--masks-out", lossless=True)
    assert np.array_equal(cv2.imread(str(target), cv2.IMREAD_UNCHANGED), labels)
    with pytest.raises(InputError, match="--masks-out: expected a lossless"):
        write_image_atomic(tmp_path / "labels.jpg", labels, "--masks-out", lossless=True)


def test_estimate_on_a_scene_folder_draws_its_ground_truth(data_dir, tmp_path, capsys):
    """A scene folder alone is a pair with its own calibration and truth: the figure shows the true depth."""
    scene = data_dir / "middlebury_eval3_Q" / "Teddy"
    figure = tmp_path / "teddy.png"
    assert main(["estimate", str(scene), "--size", "160x134", "--figure", str(figure), "--json"]) == 0
    assert cv2.imread(str(figure)) is not None
    assert main(["estimate", str(scene), "--focal-px", "300"]) == 2
    assert capsys.readouterr().err.endswith("--focal-px, --baseline-m, --doffs-px, --calibration: a scene folder "
                                            "brings its own calibration\n")


def test_a_pair_left_unverified_says_so_and_labels_each_kept_object():
    """Found by an audit of the figures: on mismatched views (RANSAC found no geometry) the title gave only the
    status while the text said 'geometry not verified', and kept objects with neither a depth nor a truth were
    left without a label. Now the title says it and each kept object reads '#k: no depth'."""
    generator = torch.Generator().manual_seed(4)
    first, second = (random_obstacle_scenes(1, n, size_wh=(320, 240), generator=generator).batch for n in (4, 2))
    mismatched = dataclasses.replace(first, right=second.right, disparity_px=None, disparity_valid=None)
    from svs_torch import PipelineConfig, SegmentationConfig

    config = PipelineConfig(segmentation=SegmentationConfig(segmenter="otsu"))
    result = estimate_obstacle_depth(mismatched, config)
    assert not bool(result.verified[0]) and bool((result.segmentation.left.kept_labels[0] > 0).any())
    figure = pipeline_figure(mismatched, result, 0)
    assert "geometry not verified" in figure._suptitle.get_text().replace("\n", " ")
    texts = [t.get_text() for t in figure.axes[0].texts]
    kept = int((result.segmentation.left.kept_labels[0] > 0).sum())
    assert len(texts) == kept and all(t.startswith(f"#{k + 1}: ") for k, t in enumerate(texts))


def test_pipeline_figure_says_the_distance_ahead_along_the_floor_where_one_was_found():
    """``estimate --floor on --figure`` (a guide record drawn): the depths drawn are along the camera's axis, and the
    title says the nearest obstacle's distance ahead along the floor too, what guide said; without the floor rule,
    nothing about a floor."""
    from svs_torch.data.synthetic import render_obstacle_scenes
    from svs_torch.pipeline import PipelineConfig

    scenes = render_obstacle_scenes(torch.zeros(1, 0), torch.zeros(1, 0, 2), torch.zeros(1, 0, 2),
                                    generator=torch.Generator().manual_seed(3), floor_height_m=1.3,
                                    camera_pitch_deg=20.0, heaps=torch.tensor([[0.0, 1.2, 0.45, 0.35]]))
    result = estimate_obstacle_depth(scenes.batch, PipelineConfig().for_guide())
    title = pipeline_figure(scenes.batch, result, 0, true_nearest=1.0)._suptitle.get_text().replace("\n", " ")
    nearest = result.floor.nearest
    assert (f"#{int(nearest.slot[0]) + 1} {float(nearest.depth_m[0]):.2f} m ahead, its nearest part "
            f"{float(nearest.surface_m[0]):.2f} m") in title
    assert f"pitched {float(result.floor.floor.pitch_deg[0]):.1f}° down" in title and "along the floor" in title
    title = pipeline_figure(scenes.batch, estimate_obstacle_depth(scenes.batch), 0)._suptitle.get_text()
    assert "floor" not in title


def test_objects_panel_says_areas_in_input_pixels_and_leaves_a_tiny_view_unlabelled(scene, monkeypatch):
    """Found by an audit of the figures: the panel said the areas at the working size (Teddy reduced to 320x240:
    "#1 42200px") beside the report's input count (92725 px); and in a 64x48 view the enlarged label hid a third
    of it."""
    import svs_torch.plotting.figures as figures

    batch, result = scene
    seg = result.segmentation.left
    texts = []
    monkeypatch.setattr(figures, "_label", lambda panel, text, *args: texts.append(text))
    objects_panel(batch.left, seg, 0, area_scale=4.0)
    label = int(seg.kept_labels[0, 0])
    assert texts[0] == f"#1 {4 * int(seg.regions.area_px[0, label - 1])}px"
    texts.clear()
    tiny = dataclasses.replace(seg, labels=seg.labels[..., :12, :16])
    objects_panel(batch.left[..., :12, :16], tiny, 0)
    assert texts == []


@pytest.mark.parametrize("mode, data", [("wb", b"\x89PNG\r\n\x1a\n"), ("w", "a,b\n")])
def test_an_output_without_o_tmpfile_is_opened_binary(tmp_path, monkeypatch, mode, data):
    """Off Linux (no O_TMPFILE) the output's temporary file was opened by ``os.open`` without ``O_BINARY``: on
    Windows such a descriptor is in text mode, each \\n written as \\r\\n (a PNG broken from its signature on, a
    CSV's lines ended \\r\\r\\n). Now it is opened binary wherever the flag exists (here a stand-in flag, recorded)."""
    from svs_torch.core.files import atomic_output

    monkeypatch.delattr(os, "O_TMPFILE", raising=False)
    monkeypatch.setattr(os, "O_BINARY", 1 << 29, raising=False)
    real_open, flags = os.open, []

    def recording_open(path, flag, *args, **kwargs):
        flags.append(flag)
        return real_open(path, flag & ~(1 << 29), *args, **kwargs)

    monkeypatch.setattr(os, "open", recording_open)
    with atomic_output(tmp_path / "out", mode) as stream:
        stream.write(data)
    assert flags and all(flag & (1 << 29) for flag in flags)
    assert (tmp_path / "out").read_bytes() == (data if mode == "wb" else data.encode())


KILLED_WRITER = """\
import sys
from svs_torch.core.files import atomic_output
with atomic_output(sys.argv[1]) as stream:
    stream.write(b"half of a new file")
    stream.flush()
    print("writing", flush=True)
    sys.stdin.read()
"""


@pytest.mark.skipif(not hasattr(os, "O_TMPFILE") or not os.path.isdir("/proc/self/fd"),
                    reason="needs O_TMPFILE and /proc (Linux)")
def test_a_writer_killed_mid_write_leaves_the_old_file_and_nothing_else(tmp_path):
    """Found by an audit of two processes at once: a command killed with SIGKILL while writing a file (results
    --figure renders into it for 0.4 s) left a hidden half file beside it ('.f.png.c20bc52e.tmp')."""
    import signal
    import subprocess
    import sys

    import svs_torch

    target = tmp_path / "out.png"
    target.write_bytes(b"old")
    writer = subprocess.Popen([sys.executable, "-c", KILLED_WRITER, str(target)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True,
                              env={**os.environ, "PYTHONPATH": str(Path(svs_torch.__file__).parents[1])})
    try:
        assert writer.stdout.readline() == "writing\n"
    finally:
        os.kill(writer.pid, signal.SIGKILL)
        writer.wait()
    assert [p.name for p in tmp_path.iterdir()] == ["out.png"] and target.read_bytes() == b"old"


def test_an_image_written_after_a_block_takes_its_name_only_when_the_block_ends_normally(tmp_path):
    """:func:`image_written_after` (calibrate's figure beside its calibration): the image is complete before the
    block runs, takes its name at the block's normal end, and a block that raises leaves an earlier file as it was
    and its own error unchanged (an OSError of the block is not named as the figure's)."""
    from svs_torch.plotting.figures import image_written_after

    image = np.full((8, 8, 3), 200, np.uint8)
    path = tmp_path / "rig.png"
    path.write_bytes(b"an earlier figure")
    for error in (OSError(28, "No space left on device"), KeyboardInterrupt()):
        with pytest.raises(type(error)) as raised:
            with image_written_after(path, image, "--figure") as target:
                assert target == path and path.read_bytes() == b"an earlier figure"
                raise error
        assert raised.value is error and "--figure" not in str(raised.value)
        assert path.read_bytes() == b"an earlier figure" and sorted(tmp_path.iterdir()) == [path]
    with image_written_after(path, image, "--figure"):
        pass
    assert cv2.imread(str(path)).tolist() == image.tolist() and sorted(tmp_path.iterdir()) == [path]
