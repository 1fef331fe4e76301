"""What a newcomer tripped on (issue 29 part 5): figure titles and layouts, help texts that disagree with the
configuration, option aliases, one TOML format, normalised paths, an old results store."""

from __future__ import annotations

import json
import math

import sqlite3
import warnings
from pathlib import Path

import pytest
import torch

from svs_torch.cli import main
from svs_torch.core.checks import InputError
from svs_torch.data import PairSource
from svs_torch.data.datasets import pair_name
from svs_torch.data.synthetic import random_obstacle_scenes
from svs_torch.evaluation import PairEvaluation
from svs_torch.evaluation.overrides import resolve_config
from svs_torch.evaluation.report import csv_table, results_figure
from svs_torch.evaluation.store import SCHEMA_VERSION, ResultStore
from svs_torch.evaluation.sweep import load_sweep, make_sweep_config
from svs_torch.features.detector import MAX_KEYPOINTS
from svs_torch.pipeline import PipelineConfig, segment_pair
from svs_torch.plotting.figures import binary_title
from svs_torch.segmentation.segment import SegmentationConfig

REPO = Path(__file__).resolve().parent.parent


def test_help_texts_take_their_values_from_the_configuration(capsys):
    def _help(command: str) -> str:
        with pytest.raises(SystemExit):
            main([command, "--help"])
        return capsys.readouterr().out

    text = " ".join(_help("features").split())
    default, paper = PipelineConfig(), PipelineConfig.paper()
    assert f"(default: {default.max_ratio}; --preset paper: {paper.max_ratio}, MATLAB's MaxRatio)" in text
    # features keeps every keypoint by default (its own default, issue 33 item 4); the pipeline's commands the cap.
    assert (f"strongest keypoints kept per image (default: {MAX_KEYPOINTS}, every keypoint found; --preset paper: "
            f"{paper.surf.max_keypoints})") in text
    assert (f"strongest keypoints kept per image (default: {default.surf.max_keypoints})"
            in " ".join(_help("estimate").split()))
    sweep_help = _help("sweep")
    assert "--plot" not in sweep_help and "--figure" in sweep_help
    assert "--plot" not in (REPO / "experiments" / "sweep_defaults.toml").read_text()
    assert "exit status is 2 if any listed pair is BAD_INPUT" in " ".join(_help("estimate").split())


@pytest.mark.parametrize("segmenter, method, words", [("otsu", "otsu", "binary (Otsu "),
                                                       ("learned", "otsu", "binary (learned segmenter, p > 0.50)"),
                                                       ("nearness", "otsu", "binary (nearness segmenter, p > 0.50)"),
                                                       ("otsu", "canny", "Canny edges + closing")])
def test_the_binary_panel_names_what_made_it(segmenter, method, words):
    batch = random_obstacle_scenes(1, 2, size_wh=(160, 120), generator=torch.Generator().manual_seed(3)).batch
    seg = segment_pair(batch, SegmentationConfig(segmenter=segmenter, method=method)).left
    title = binary_title(seg, 0, segmenter, method)
    assert title.startswith(words) and ("Otsu" in title) == (segmenter == "otsu" and method == "otsu")


@pytest.mark.parametrize("segmenter", ["nearness", "otsu"])
def test_the_right_binary_panel_of_the_nearness_segmenter_says_it_is_the_lefts_regions_moved(monkeypatch, segmenter):
    """Found by an audit of the figures: the right view's mask, the left's kept regions shifted by their disparity,
    was titled as a threshold of the right image ("binary (nearness segmenter, p > 0.50) + opening")."""
    import svs_torch.plotting.figures as figures

    titles = []
    monkeypatch.setattr(figures, "titled_panel", lambda panel, title: titles.append(title) or panel)
    batch = random_obstacle_scenes(1, 2, size_wh=(160, 120), generator=torch.Generator().manual_seed(3)).batch
    stereo = segment_pair(batch, SegmentationConfig(segmenter=segmenter))
    figures.segmentation_panels(batch.left, stereo.left, 0, "left", segmenter)
    figures.segmentation_panels(batch.right, stereo.right, 0, "right", segmenter)
    moved = "right mask: the left's regions moved by disparity"
    assert titles[1].startswith("left binary (") and (titles[4] == moved) == (segmenter == "nearness")


def test_a_pair_named_only_by_its_view_takes_the_scene_folder_name():
    assert pair_name("/data/middlebury_eval3_Q/Teddy/im0.png") == "Teddy"
    assert pair_name("/data/middlebury_2003_quarter/Cones/imL.png") == "Cones"
    assert pair_name("/data/rig/left.png") == "rig"
    assert pair_name("/data/opencv_samples/left01.jpg") == "left01"  # a name of its own stays
    assert pair_name("/data/captures/pair0007_left.png") == "pair0007_left"


def _store(path: Path, values_by_config: dict[str, list[float]], left: str = "scenes/x/../Teddy") -> ResultStore:
    store = ResultStore(path)
    store.add_pairs([PairSource(left=f"{left}{i}", scene=True)
                     for i in range(max(3, *map(len, values_by_config.values())))])
    run = store.start_run("test", "v", {}, "")
    for number, (label, values) in enumerate(values_by_config.items()):
        config = make_sweep_config("default", {"segmentation.kernel_size": 3 + 2 * number}, None, label)
        store.add_configs([config.record()])
        rows = [(PairSource(left=f"{left}{i}", scene=True).pair_id,
                 PairEvaluation(name=f"scene{i}", status="OK", calibrated=True, has_truth=True, acc_r_min_pct=v,
                                acc_r_max_pct=v - 1, acc_objects_pct=v - 0.5)) for i, v in enumerate(values)]
        store.write_task(config.config_id, run, rows)
    return store


def test_results_figure_leaves_the_callers_matplotlib_as_it_was(tmp_path):
    """Found by an audit of the API's effect on its caller: results_figure ran ``matplotlib.use("Agg")`` and drew
    through pyplot, so a notebook's inline backend was switched off for the rest of its session and every call left
    one more figure open in pyplot. Now the backend and pyplot's figures are as they were, and the figure still
    draws and saves (its own Agg canvas)."""
    import matplotlib
    import matplotlib.pyplot as plt

    previous = matplotlib.get_backend()
    matplotlib.use("svg")  # a backend of the caller's that is not Agg
    try:
        figures = plt.get_fignums()
        with _store(tmp_path / "one.sqlite", {"a": [96.0, 98.5, 99.0]}) as store:
            figure = results_figure(store)
        figure.canvas.draw()
        assert (matplotlib.get_backend(), plt.get_fignums()) == ("svg", figures)
    finally:
        matplotlib.use(previous)


def test_results_figure_zooms_keeps_the_legend_off_the_bars_and_leaves_no_empty_panel(tmp_path):
    import matplotlib.pyplot as plt

    with _store(tmp_path / "one.sqlite", {"a": [96.0, 98.5, 99.0]}) as store:
        figure = results_figure(store)
    try:
        assert figure._suptitle.get_text() == "one.sqlite: 1 configuration"
        (bars,) = figure.axes
        low, high = bars.get_ylim()
        assert 90 < low < 95 and 99 < high <= 101  # zoomed to 95-99 %, not 0-100
        figure.canvas.draw()
        renderer = figure.canvas.get_renderer()
        legend = bars.get_legend().get_window_extent(renderer)
        assert legend.y0 >= bars.get_window_extent(renderer).y1 - 1  # above the bars, not over them
    finally:
        plt.close(figure)
    with _store(tmp_path / "two.sqlite", {"a": [96.0, 98.5, 99.0], "b": [97.0, 98.0, 99.5]}) as store:
        figure = results_figure(store)
    try:
        params, bars = figure.axes
        assert figure._suptitle.get_text().endswith("2 configurations")
        # One swept parameter and the bars: one row of two panels side by side, no third (blank) one.
        assert len(figure.axes) == 2 and bars.get_position().x0 > params.get_position().x1
        assert bars.get_position().y0 == pytest.approx(params.get_position().y0, abs=0.05)
    finally:
        plt.close(figure)


def test_results_counts_one_configuration_in_the_singular(tmp_path, capsys):
    with _store(tmp_path / "one.sqlite", {"a": [96.0, 98.5, 99.0]}):
        pass
    assert main(["results", str(tmp_path / "one.sqlite")]) == 0
    assert capsys.readouterr().out.startswith("1 configuration; ranked by ")


def test_results_of_a_store_without_rows_says_so(tmp_path, capsys):
    """Found by an audit: a sweep stopped before its first task left configurations and no rows; results printed
    an empty table ("0 configurations") while results --figure said "holds no results yet"."""
    store = ResultStore(tmp_path / "empty.sqlite")
    store.add_configs([make_sweep_config("default", {"segmentation.kernel_size": k}, None, f"k{k}").record()
                       for k in (3, 5)])
    store.close()
    assert main(["results", str(tmp_path / "empty.sqlite")]) == 0
    assert capsys.readouterr().out == (f"{tmp_path / 'empty.sqlite'}: no results yet (2 configurations recorded, no "
                                       "pair run); the run going on, or the same command run again, fills it\n")
    assert main(["results", str(tmp_path / "empty.sqlite"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["configs"] == []
    # An audit of sweeps: with --figure too the --csv was written (a header alone) before the figure said so, exit 2.
    rows, figure = tmp_path / "rows.csv", tmp_path / "figure.png"
    assert main(["results", str(tmp_path / "empty.sqlite"), "--csv", str(rows), "--figure", str(figure)]) == 2
    assert "holds no results yet" in capsys.readouterr().err and not rows.exists() and not figure.exists()


@pytest.mark.parametrize("swept", [1, 2])
def test_results_figure_shows_the_best_configurations_whole_name(tmp_path, swept):
    """Found by an audit: the per-scene title was wrapped at 90 characters, wider than its panel (the third, beside
    two swept parameters' panels), and a long configuration name ran off the figure's edge ("... kernel_size=5 see")."""
    import matplotlib.pyplot as plt

    long = " ".join(f"key{i}={i}" for i in range(40))  # short words: lines fill to the wrap width
    store = ResultStore(tmp_path / "long.sqlite")
    store.add_pairs([PairSource(left=f"scenes/Teddy{i}", scene=True) for i in range(3)])
    run = store.start_run("test", "v", {}, "")
    for number in range(3):
        overrides = {"segmentation.kernel_size": 3 + 2 * number, "seed": number % swept}
        config = make_sweep_config("default", overrides, None, f"{long} | variant {number}")
        store.add_configs([config.record()])
        rows = [(PairSource(left=f"scenes/Teddy{i}", scene=True).pair_id,
                 PairEvaluation(name=f"scene{i}", status="OK", calibrated=True, has_truth=True, acc_r_min_pct=v,
                                acc_r_max_pct=v - 1, acc_objects_pct=v - 0.5))
                for i, v in enumerate([96.0 + number, 98.5, 99.0])]
        store.write_task(config.config_id, run, rows)
    with store:
        figure = results_figure(store)
    try:
        assert len(figure.axes) == swept + 1
        figure.canvas.draw()
        bars = figure.axes[-1]
        title = bars.title.get_window_extent(figure.canvas.get_renderer())
        assert title.x0 >= 0 and title.x1 <= figure.bbox.x1
        assert bars.get_title().replace("\n", " ").endswith(f"{long} | variant 2")
    finally:
        plt.close(figure)


def test_results_bars_of_many_scenes_take_a_row_as_wide_as_their_names_need(tmp_path):
    """Found by an audit of the figures: a sweep over 40 scenes drew their 40 names over each other in a 5.2 in
    panel beside the parameter's. Now the bars take a row of their own, at least 0.22 in a scene, and no two tick
    labels overlap."""
    import matplotlib.pyplot as plt

    values = [90.0 + (i % 9) for i in range(40)]
    with _store(tmp_path / "many.sqlite", {"a": values, "b": values[::-1]}) as store:
        figure = results_figure(store)
    try:
        params, bars = figure.axes
        assert bars.get_position().y1 < params.get_position().y0  # a row of its own, under the parameter's
        assert bars.get_position().width * figure.get_figwidth() >= 0.22 * 40 - 0.5
        figure.canvas.draw()
        renderer = figure.canvas.get_renderer()
        boxes = [label.get_window_extent(renderer) for label in bars.get_xticklabels()]
        assert len(boxes) == 40
        # 7 pt names turned 60° clear each other where their ends lie a text height / sin 60° apart along x
        apart_px = 7 * figure.dpi / 72 / math.sin(math.radians(60))
        assert all(b.x1 - a.x1 >= apart_px for a, b in zip(boxes, boxes[1:]))
    finally:
        plt.close(figure)


def test_results_bars_span_the_rest_of_their_row(tmp_path):
    import matplotlib.pyplot as plt

    store = ResultStore(tmp_path / "grid.sqlite")
    store.add_pairs([PairSource(left="Teddy", scene=True)])
    run = store.start_run("test", "v", {}, "")
    for kernel in (3, 5):
        for window in (7, 9):
            for ratio in (0.1, 0.2):
                overrides = {"segmentation.kernel_size": kernel, "dense.window_size": window,
                             "dense.uniqueness_ratio": ratio}
                config = make_sweep_config("default", overrides, None)
                store.add_configs([config.record()])
                store.write_task(config.config_id, run, [(PairSource(left="Teddy", scene=True).pair_id,
                                                          PairEvaluation(name="Teddy", status="OK", calibrated=True,
                                                                         has_truth=True, acc_r_min_pct=90 + kernel,
                                                                         acc_r_max_pct=95.0, acc_objects_pct=96.0))])
    figure = results_figure(store)
    store.close()
    try:
        *params, bars = figure.axes
        assert len(params) == 3  # three swept parameters in the first row, the bars under them, full width
        assert bars.get_position().x0 == pytest.approx(params[0].get_position().x0)
        assert bars.get_position().x1 == pytest.approx(params[2].get_position().x1)
    finally:
        plt.close(figure)


def test_results_accepts_out_and_csv_paths_are_normalised(tmp_path, capsys):
    with _store(tmp_path / "one.sqlite", {"a": [96.0, 98.5, 99.0]}) as store:
        header, rows = csv_table(store)
    lefts = [row[header.index("left")] for row in rows]
    assert lefts == ["scenes/Teddy0", "scenes/Teddy1", "scenes/Teddy2"]
    assert main(["results", str(tmp_path / "one.sqlite"), "--out", str(tmp_path / "fig.png")]) == 0
    assert (tmp_path / "fig.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_one_toml_format_for_config_and_sweep_files(data_dir, tmp_path):
    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    sweep_file = tmp_path / "sweep.toml"
    sweep_file.write_text(f'paths = ["{teddy}"]\nsize = "160x120"\nmax_ratio = 0.7\n'
                          f'[set]\n"dense.window_size" = 7\n')
    with pytest.warns(UserWarning, match="the sweep's paths, size not used"):
        config, preset, overrides = resolve_config("default", sweep_file)
    assert (config.dense.window_size, config.max_ratio, preset) == (7, 0.7, "default")
    assert overrides == {"max_ratio": 0.7, "dense.window_size": 7}
    (sweep,) = load_sweep(sweep_file).configs  # and the same file is a sweep of one configuration
    assert sweep.record()["config"]["max_ratio"] == 0.7 and sweep.record()["config"]["dense"]["window_size"] == 7
    sweep_file.write_text(f'paths = ["{teddy}"]\n[grid]\n"dense.window_size" = [7, 9]\n')
    with pytest.raises(InputError, match="grid: a sweep's grid makes several configurations"):
        resolve_config("default", sweep_file)
    plain = tmp_path / "config.toml"
    plain.write_text('preset = "paper"\n[segmentation]\nkernel_size = 7\n')
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a plain configuration file: nothing to say
        config, preset, _ = resolve_config("default", plain)
    assert (config.segmentation.kernel_size, preset) == (7, "paper")


def test_a_version_1_store_is_read_as_it_is_and_upgraded_when_written(tmp_path):
    path = tmp_path / "old.sqlite"
    _store(path, {"a": [96.0, 98.0]}).close()
    connection = sqlite3.connect(path)
    connection.execute('ALTER TABLE results DROP COLUMN "calibration"')  # as version 1 wrote it
    connection.execute("UPDATE meta SET value = '1' WHERE key = 'schema_version'")
    connection.commit()
    connection.close()
    with ResultStore(path, create=False) as store:
        assert [row["calibration"] for row in store.results()] == [None, None]
    with ResultStore(path) as store:
        assert store.connection.execute("SELECT value FROM meta").fetchone() == (str(SCHEMA_VERSION),)
        columns = [row[1] for row in store.connection.execute("PRAGMA table_info(results)")]
        assert "calibration" in columns
