"""Reading a results store back: per-configuration summaries, the best configuration by each metric, CSV rows,
and a figure (each metric against each swept parameter, and per-scene bars of the best configuration, or its
accuracies sorted over the pairs where a store holds more than :data:`~.pair_spread.MAX_SCENE_BARS`).

Summaries use :func:`~svs_torch.evaluation.runner.summarize`, the same rules as ``svs-depth eval``: a failed
pair with ground truth counts 0 %, failures are counted.
"""

from __future__ import annotations

import dataclasses
import json
import textwrap
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ..core.checks import InputError, check_instance
from ..core.files import atomic_output, check_output_file, tidy_path
from .metrics import UNRUN_STATUSES, PairEvaluation
from .pair_spread import MAX_SCENE_BARS, sorted_accuracies
from .runner import summarize
from .store import RESULT_COLUMNS, ResultStore
from .store_access import WRITERS

__all__ = ["METRICS", "best_by_metric", "config_summaries", "csv_table", "distinct_labels", "plot_results",
           "pairs_without_rows", "ranked_group", "ranked_value", "parameter_value", "results_figure", "same_results",
           "swept_parameters"]

#: ``(key, label, higher is better)`` of the metrics a configuration is ranked by.
METRICS: tuple[tuple[str, str, bool], ...] = (
    ("acc_r_min_pct", "Acc R_min %", True),
    ("acc_r_max_pct", "Acc R_max %", True),
    ("acc_objects_pct", "Acc objects %", True),
    ("dense_within_1px", "dense within 1 px", True),
    ("inlier_precision", "inlier precision", True),
    ("kept_all_bad2_pct", "bad-2 % (kept)", False),
    ("kept_all_d1_pct", "D1 % (kept)", False),
    ("pipeline_s_per_pair", "s per pair", False),
)
_BOOLEAN_COLUMNS = {name for name, _ in RESULT_COLUMNS
                    if str(next(f.type for f in dataclasses.fields(PairEvaluation) if f.name == name)).startswith(
                        "bool")}


def _evaluation(row: dict) -> PairEvaluation:
    values = {name: row[name] for name, _ in RESULT_COLUMNS}
    for name in _BOOLEAN_COLUMNS:
        values[name] = None if values[name] is None else bool(values[name])
    return PairEvaluation(**values)


def config_summaries(store: ResultStore, rows: list[dict] | None = None) -> list[dict]:
    """One summary per stored configuration (with its ``config_id``, ``label``, ``preset``, ``size``,
    ``overrides``, the ``code_versions`` its rows were computed by and ``pairs_missing``, how many of the pairs
    any configuration was measured on it lacks: an interrupted sweep's means are over different pairs; and
    ``dense_pairs`` / ``inlier_pairs``, the pairs its dense and inlier disparity means are over, as the stereo
    metrics' ``<scope>_pairs``: a failed pair has none), in the order the configurations were stored;
    configurations without rows are left out. ``rows``: ``store.results()``, where the caller read them already."""
    check_instance(store, "store", ResultStore)
    by_config: dict[str, list[PairEvaluation]] = {}
    versions: dict[str, list[str]] = {}
    pairs: dict[str, set[str]] = {}
    for row in store.results() if rows is None else rows:
        by_config.setdefault(row["config_id"], []).append(_evaluation(row))
        pairs.setdefault(row["config_id"], set()).add(row["pair_id"])
        seen = versions.setdefault(row["config_id"], [])
        if row["code_version"] not in seen:
            seen.append(row["code_version"])
    every_pair = set().union(*pairs.values())
    summaries = []
    configs = store.configs()
    labels = distinct_labels(configs)
    for config in configs:
        rows = by_config.get(config["config_id"])
        if rows:
            summary = summarize(rows)
            summaries.append({key: config[key] for key in ("config_id", "preset", "size", "overrides")}
                             | {"label": labels[config["config_id"]]}
                             | {"code_versions": versions[config["config_id"]],
                                "pairs_missing": len(every_pair - pairs[config["config_id"]])} | summary
                             | {"dense_pairs": sum(e.dense_within_1px is not None for e in rows),
                                "inlier_pairs": sum(e.inlier_precision is not None for e in rows)})
    # One group for every configuration (ranked_group): each choosing its own, a configuration measured on fewer
    # pairs was ranked by its own-calibration mean against the others' nominal ones, under one heading.
    own = sum(s.get("scored") or 0 for s in summaries)
    nominal = sum((s.get("nominal_calibration") or {}).get("scored") or 0 for s in summaries)
    for s in summaries:
        s["ranked_group"] = "nominal" if nominal > own else "own"
    return summaries


def distinct_labels(configs: Sequence[dict]) -> dict[str, str]:
    """Each stored configuration's label, made to tell it from others of the same label, preset and size: two
    sweeps into one store whose files differ only in their fixed ``[set]`` values label their configurations by the
    grid alone ("segmentation.kernel_size=3" twice, with different results). Those labels gain the parameters that
    differ within the group, as they ran (``"segmentation.kernel_size=3 max_ratio=0.7"``)."""
    groups: dict[tuple[str, str, str], list[dict]] = {}
    for config in configs:
        groups.setdefault((config["label"], config["preset"], config["size"]), []).append(config)
    labels = {config["config_id"]: config["label"] for config in configs}
    for (label, _, _), group in groups.items():
        keys: list[str] = []
        for config in group:
            keys += [key for key in config["overrides"] if key not in keys]
        differing = [key for key in keys if len({repr(_value_that_ran(c, key)) for c in group}) > 1]
        for config in group if differing else ():
            labels[config["config_id"]] = f"{label} " + " ".join(
                f"{key}={_value_that_ran(config, key)}" for key in differing)
    return labels


def ranked_group(summary: dict) -> tuple[str, int]:
    """Which pairs a summary's accuracies are ranked over, and how many of them it has: ``("own", n)``, the pairs
    scored with their own calibration (the headline means of ``eval``), or ``("nominal", n)``, those scored with a
    nominal one (their data ship none), where the store holds more of those (``config_summaries`` decides once for
    every configuration, its ``ranked_group``). A sweep over 26 Middlebury 2005/2006 scenes has one with a
    calibration of its own (Art): ranked on it alone, the window best by it was the worst over the other 25."""
    own, nominal = summary.get("scored") or 0, (summary.get("nominal_calibration") or {}).get("scored") or 0
    group = summary.get("ranked_group") or ("nominal" if nominal > own else "own")
    return group, nominal if group == "nominal" else own


def ranked_value(summary: dict, key: str) -> float | None:
    """The summary's ``key``; an accuracy is the mean over :func:`ranked_group`'s pairs (the same footing for every
    configuration of a sweep over the same pairs): what the results table shows and ranks by, and the figure
    plots."""
    if key.startswith("acc_") and ranked_group(summary)[0] == "nominal":
        return (summary.get("nominal_calibration") or {}).get(key)
    return summary.get(key)


def best_by_metric(summaries: Sequence[dict]) -> list[tuple[str, str, dict]]:
    """``(metric key, label, best summary)`` for each metric some configuration has (by :func:`ranked_value`)."""
    best = []
    for key, label, higher in METRICS:
        candidates = [s for s in summaries if ranked_value(s, key) is not None]
        if candidates:
            pick = (max if higher else min)(candidates, key=lambda s: ranked_value(s, key))
            best.append((key, label, pick))
    return best


#: A stored row's columns that say when, by which code and how fast it ran, not what it measured.
_NOT_MEASURED = frozenset({"config_id", "run_id", "code_version", "time_s"})


def same_results(store: ResultStore, rows: list[dict] | None = None) -> list[list[str]]:
    """The groups (of two or more, in the order stored) of configurations whose stored rows are the same on every
    pair, times aside, each group measured on the same pairs: what differs between them changed nothing there.

    Why: a sweep over a setting that the configuration in use never reads (``segmentation.foreground`` under the
    nearness segmenter, which takes no Otsu split of the intensities) ran its values as so many configurations,
    each ranked, one named best, and nothing said they were one (an audit of the results' numbers). ``rows``:
    ``store.results()``, where the caller read them already."""
    check_instance(store, "store", ResultStore)
    by_config: dict[str, list[dict]] = {}
    for row in store.results() if rows is None else rows:  # (ordered by configuration, then pair)
        by_config.setdefault(row["config_id"], []).append({k: v for k, v in row.items() if k not in _NOT_MEASURED})
    groups: dict[str, list[str]] = {}
    for config_id, measured in by_config.items():
        groups.setdefault(json.dumps(measured, sort_keys=True, default=str), []).append(config_id)
    order = {c["config_id"]: i for i, c in enumerate(store.configs())}
    return sorted((sorted(g, key=order.get) for g in groups.values() if len(g) > 1), key=lambda g: order[g[0]])


def swept_parameters(store: ResultStore) -> list[str]:
    """The override keys whose value differs between the stored configurations (plus ``preset`` and ``size`` if
    they do)."""
    check_instance(store, "store", ResultStore)
    configs = store.configs()
    keys: list[str] = []
    for config in configs:
        keys += [key for key in config["overrides"] if key not in keys]
    swept = [key for key in keys if len({repr(c["overrides"].get(key)) for c in configs}) > 1]
    if len({c["size"] for c in configs}) > 1:  # else a panel averaged 160x120 and 320x240 rows in silence
        swept.insert(0, "size")
    if len({c["preset"] for c in configs}) > 1:
        swept.insert(0, "preset")
    return swept


#: The first CSV columns, in this order (``config`` is the configuration's id).
CSV_FIRST = ("config", "left", "right", "status", "r_min_m", "r_max_m", "acc_r_min_pct", "acc_r_max_pct")


def csv_table(store: ResultStore) -> tuple[list[str], list[list[Any]]]:
    """Header and rows, one per (configuration, pair): :data:`CSV_FIRST`, then the configuration's ``label``,
    ``size`` and each swept parameter's value in the configuration that ran (``param:<key>``), then every other
    result column, then the ``code_version`` of the run that wrote the row."""
    check_instance(store, "store", ResultStore)
    configs = {c["config_id"]: c for c in store.configs()}
    labels = distinct_labels(list(configs.values()))
    swept = [key for key in swept_parameters(store) if key != "size"]  # the table has a size column of its own
    rest = [name for name, _ in RESULT_COLUMNS if name not in CSV_FIRST]
    header = [*CSV_FIRST, "label", "size", *(f"param:{key}" for key in swept), "pair_id", *rest, "code_version"]
    rows = []
    for row in store.results():
        config = configs[row["config_id"]]
        params = [parameter_value(config, key) for key in swept]
        # Paths as a person would write them: a sweep file's "../../shared/data" joined to its folder reads
        # "experiments/../../shared/..." until normalised (the same file; ids keep the absolute path). Not where a
        # link makes "link/.." another folder: that shows a file that is not the pair's (tidy_path).
        paths = {key: tidy_path(row[key]) if row[key] else row[key] for key in ("left", "right")}
        values = {**row, **paths, "config": row["config_id"], "objects": json.dumps(row["objects"]),
                  "calibration": json.dumps(row["calibration"]) if row["calibration"] else None}
        rows.append([values[c] for c in CSV_FIRST] + [labels[row["config_id"]], config["size"], *params,
                                                      row["pair_id"]] + [values[name] for name in rest]
                    + [row["code_version"]])
    return header, rows


def parameter_value(config: dict, key: str) -> Any:
    """A stored configuration's value of a swept parameter (:func:`swept_parameters`): its preset, its size, or
    the value the configuration ran with (:func:`_value_that_ran`)."""
    return config[key] if key in ("preset", "size") else _value_that_ran(config, key)


def _value_that_ran(config: dict, key: str) -> Any:
    """A swept parameter's value in the configuration that ran (its preset's where it was not overridden: an empty
    cell read as 'not set' hid the 0.8 a default configuration ran with), from the stored whole configuration."""
    value: Any = config.get("config")
    for part in key.split("."):
        if not isinstance(value, dict) or part not in value:
            return config["overrides"].get(key)  # a store that predates the whole configuration, or a None parent
        value = value[part]
    if isinstance(value, dict) or (value is None and key in config["overrides"]):
        # An optional sub-setting (refine_matches, row_alignment, exposure, ...): switched on, its whole settings
        # dict made an unreadable CSV cell and figure tick; it reads as the value it was swept with, or True where
        # its preset switched it on (it read "on", a tick apart from the same setting swept as true: an audit).
        override = config["overrides"].get(key)
        return override if override is not None and not isinstance(override, dict) else (
            True if isinstance(value, dict) else None)
    return value


def _scene_name(row: dict, counted: bool) -> str:
    """A per-scene bar's tick: the pair's name, marked where its bars are not a measured accuracy (failed: its
    status, 0 % bars where it has ground truth; without: no bars, "no truth") or not in the headline means (a
    nominal calibration: its data ship none)."""
    marks = [row["status"]] if row["status"] != "OK" else []
    marks += ["no truth"] if not counted and row["status"] not in UNRUN_STATUSES else []  # unread: truth unknown
    marks += ["nominal"] if counted and row["calibrated"] == 0 else []
    return row["name"] + (f" ({', '.join(marks)})" if marks else "")


def _scene_bars(axis, store: ResultStore, summary: dict, tied: int = 0) -> None:
    rows = [r for r in store.results() if r["config_id"] == summary["config_id"]]
    # The summary's rules (runner.summarize): a pair without ground truth has no accuracy, and no bar (its 0 % bars
    # read as a measured 0 and set the axis to 0-100, an audit); a failed pair with it counts 0 %, and says why.
    scored = [r["acc_r_min_pct"] is not None or (bool(r["has_truth"]) and r["status"] != "OK") for r in rows]
    names = [_scene_name(r, counted) for r, counted in zip(rows, scored)]
    if len(rows) > MAX_SCENE_BARS:  # a bar group a pair: 77 605 px wide at 3 200 pairs (pair_spread)
        everything = sorted_accuracies(axis, rows, scored, names) or [0.0]
    else:
        everything = _bars(axis, rows, scored, names)
    # Zoomed to the data: on a 0-100 scale, 96 % and 99 % look the same. The label says the axis is cut.
    low, high = min(everything), max(everything)
    margin = max(0.5, 0.15 * (high - low))
    # Never past 100 %, which no accuracy reaches (an axis to 104 % read as room above the best, an audit).
    axis.set_ylim(max(0.0, min(low - margin, 100.0 - 2 * margin)), min(100.0, high + margin))
    axis.set_ylabel("Eq. (9) accuracy, % (axis zoomed to the data)", fontsize=8)
    axis.grid(axis="y", alpha=0.3)
    # An exact tie is said (an audit: two configurations at 99.7 %, one named "best" alone).
    best = f"best by object accuracy (tied with {tied} other{'s' if tied > 1 else ''})" if tied else \
        "best by object accuracy"
    # Wrapped to the panel's width (8 pt text, at most 0.6 em a character): at 90 characters a third panel cut the
    # best configuration's name at the figure's edge (an audit).
    width_in = axis.get_position().width * axis.figure.get_figwidth()
    per = "per scene" if len(rows) <= MAX_SCENE_BARS else f"over {len(rows)} pairs"
    axis.set_title(textwrap.fill(f"{per}, {best}: {summary['label']}", max(30, int(width_in * 72 / 4.8))),
                   fontsize=8, pad=20)
    # Above the bars, never over them.
    axis.legend(fontsize=7, ncol=3, loc="lower center", bbox_to_anchor=(0.5, 1.0), frameon=False)


def _bars(axis, rows: list[dict], scored: list[bool], names: list[str]) -> list[float]:
    """A group of three bars a pair (R_min, R_max, objects), named below; returns the values drawn."""
    width, everything = 0.27, []
    for offset, (key, label) in enumerate((("acc_r_min_pct", "R_min"), ("acc_r_max_pct", "R_max"),
                                           ("acc_objects_pct", "objects"))):
        values = [(r[key] or 0.0) if counted else float("nan") for r, counted in zip(rows, scored)]
        everything += [v for v in values if v == v] or [0.0]
        axis.bar([i + (offset - 1) * width for i in range(len(rows))], values, width, label=label)
    axis.set_xticks(range(len(rows)), names, rotation=60, ha="right", fontsize=7)
    return everything


def _parameter_axis(axis, summaries: Sequence[dict], configs: dict[str, dict], key: str) -> None:
    def value(s: dict) -> Any:  # the value that ran, as the CSV's: an override left out read "None" before
        return parameter_value(configs[s["config_id"]], key)

    values = {repr(value(s)): value(s) for s in summaries}
    numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values.values())
    levels = sorted(values, key=lambda r: (values[r], r) if numeric else (len(r), r))
    for metric, label in (("acc_r_min_pct", "R_min"), ("acc_r_max_pct", "R_max"), ("acc_objects_pct", "objects")):
        means = []
        for level in levels:
            group = [v for s in summaries if repr(value(s)) == level and (v := ranked_value(s, metric)) is not None]
            means.append(sum(group) / len(group) if group else float("nan"))
        axis.plot(range(len(levels)), means, marker="o", label=label)
    # Never past 100 %, as the scene bars: equal means (a parameter without effect) were autoscaled to 94-105 %.
    low, high = axis.get_ylim()
    axis.set_ylim(low, min(high, 100.0))
    # The values as the CSV's cells (a repr's quotes and escapes stripped by hand left a path with an apostrophe
    # or a backslash quoted or doubled, an audit).
    axis.set_xticks(range(len(levels)), [str(values[level]) for level in levels], fontsize=8)
    axis.set_xlabel(key, fontsize=9)
    axis.set_ylabel("mean Acc %, over the other parameters (axis zoomed to the data)", fontsize=8)
    axis.grid(alpha=0.3)
    axis.legend(fontsize=7)


def plot_results(store: ResultStore, path: str | Path, writing: bool = False) -> Path:
    """Write :func:`results_figure` (``writing`` as there) to ``path`` (any image format matplotlib writes), under a
    temporary name and renamed, never half-written. A bad ``path`` is refused by name before the figure is drawn (an
    audit: a folder or a .txt was matplotlib's "Format '' is not supported", a missing folder a FileNotFoundError
    naming the temporary file, None a TypeError)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.text import Text

    check_instance(store, "store", ResultStore)
    suffixes = tuple(f".{kind}" for kind in sorted(FigureCanvasAgg.get_supported_filetypes()))
    path = check_output_file(path, "path", suffixes, f"an image ({', '.join(suffixes)})")
    figure = results_figure(store, writing)
    for text in figure.findobj(Text):  # a scene folder's name with '$' drawn as written, as plotting.plain_texts
        text.set_parse_math(False)
    with atomic_output(path) as stream:
        figure.savefig(stream, format=path.suffix.lstrip(".").lower(), dpi=110)
    return path


def results_figure(store: ResultStore, writing: bool = False):
    """The results figure (a matplotlib Figure): one panel per swept parameter (mean Eq. (9) accuracy of R_min,
    R_max and objects at each value, averaged over the other parameters) and, filling the rest of the last row (or a
    row of its own, as wide as its scenes need), per-scene bars of the best configuration by object accuracy, zoomed
    to the data, its legend above them; the title says where a configuration has no rows or lacks pairs the others
    have. An Agg canvas of its own, no pyplot: the caller's backend and pyplot's figures are left as they were (an
    audit of the API's effect on its caller: ``matplotlib.use("Agg")`` here turned a notebook's inline plots off for
    the rest of its session, and each call left one more figure open in pyplot). ``writing``: a sweep or an eval
    --db is writing the store now (:func:`~.store_access.sweep_is_writing`, read before the store is opened), which
    the title says."""
    check_instance(store, "store", ResultStore)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    summaries = config_summaries(store)
    if not summaries:
        raise InputError(f"store: {store.path} holds no results yet")
    swept = swept_parameters(store)
    # The table's ranking: nominal-calibration means where more pairs were scored with one (ranked_group).
    best = max(summaries, key=lambda s: v if (v := ranked_value(s, "acc_objects_pct")) is not None else -1.0)
    columns = min(3, len(swept) + 1)
    row, column = divmod(len(swept), columns)
    # Each scene's name wants about 0.22 in (7 pt, turned 60°): 40 scenes overlapped in one 5.2 in panel (an
    # audit's find). Where the rest of the row is too narrow, the bars take a row of their own, the figure wider.
    # Past MAX_SCENE_BARS the pairs' sorted accuracies want no more than a wide panel (pair_spread).
    scenes = sum(r["config_id"] == best["config_id"] for r in store.results())
    scenes_in = 0.22 * scenes + 1.5 if scenes <= MAX_SCENE_BARS else 8.0
    if column and 5.2 * (columns - column) < scenes_in:
        row, column = row + 1, 0
    figure = Figure(figsize=(max(5.2 * columns, scenes_in), 4.4 * (row + 1)))
    FigureCanvasAgg(figure)
    grid = figure.add_gridspec(row + 1, columns)
    configs = {c["config_id"]: c for c in store.configs()}
    for number, key in enumerate(swept):
        _parameter_axis(figure.add_subplot(grid[number // columns, number % columns]), summaries, configs, key)
    tied = sum(ranked_value(s, "acc_objects_pct") == ranked_value(best, "acc_objects_pct") for s in summaries) - 1
    _scene_bars(figure.add_subplot(grid[row, column:]), store, best, tied)  # the rest of its row: no empty panels
    # Wrapped to the figure (about 11 characters an inch at 11 pt): one swept parameter's is 10.4 in wide, none's 5.2.
    title = f"{store.path.name}: {_rows_in_title(summaries, len(configs), writing)}".split("\n")
    figure.suptitle("\n".join(textwrap.fill(line, int(figure.get_figwidth() * 11)) for line in title), fontsize=11)
    figure.tight_layout()
    return figure


def _rows_in_title(summaries: Sequence[dict], recorded: int, writing: bool) -> str:
    """The figure's title after the store's name: how many configurations have rows, and, as the summary's notes
    say, where that is fewer than the ``recorded`` ones or some lack pairs the others have, that each mean is over
    the rows there are (an audit: a stopped sweep's panels averaged over different parts of the grid, unsaid); not
    that a sweep stopped where one is ``writing`` the store, or an eval --db (no claim) may still be running."""
    count, short = len(summaries), sum(1 for s in summaries if s.get("pairs_missing"))
    if count >= recorded and not short:
        return f"{count} configuration{'' if count == 1 else 's'}"
    return (f"{count} of {recorded} configurations have rows"
            + (f", {short} of them not on every pair" if short else "")
            + "\neach mean is over the rows stored so far ("
            + (f"{WRITERS} is writing the store now" if writing else
               "a run still going, or one stopped before the rest: the same command run again fills it") + ")")


def pairs_without_rows(store) -> int:
    """How many pairs recorded in a :class:`~.store.ResultStore` (each run records its pairs before it runs them)
    have no row in any configuration: the pairs an interrupted run never reached."""
    return int(store.connection.execute("SELECT count(*) FROM pairs WHERE pair_id NOT IN (SELECT pair_id FROM "
                                        "results)").fetchone()[0])
