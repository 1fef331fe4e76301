"""Parameter sweeps: configurations × pairs, as tasks of one configuration and a block of pairs, run by a local
process pool or a Dask cluster, with every result in a SQLite store (:mod:`.store`).

Sweep file (TOML; relative paths are relative to the file)::

    paths = ["../shared/data/middlebury_eval3_Q"]   # scene folders, folders of scenes, lists, index.jsonl
    size = "320x240"                                 # resample every pair first ("native": as loaded)
    preset = "default"                               # or "paper": what the overrides apply to
    batch_size = 8                                   # pairs per task (one batched pipeline run)
    [set]                                            # fixed overrides for every configuration
    "dense.window_size" = 9
    [grid]                                           # every combination, the first key varying slowest
    "segmentation.kernel_size" = [3, 5, 7]
    "max_ratio" = [0.6, 0.8]
    [[configs]]                                      # and/or a list of configurations (crossed with the grid)
    preset = "paper"

Everything is checked before any work starts: unknown keys and parameters, values of the wrong type, missing
paths; the error is one line naming the file and the key.

A configuration's id is a hash of everything that can change a result: the whole resolved
:class:`~svs_torch.pipeline.PipelineConfig`, the size and, for a learned segmenter, the content of its weights file
(retrained in place, it is another configuration); the same configuration from another sweep file reuses its rows.
The batch size is not in it: a pair's result does not depend on its batch (pairs of different sizes run as groups
of one size, :mod:`svs_torch.core.size_groups`; RANSAC is seeded per pair;
``tests/pipeline/test_batch_independence.py``). The code version is recorded per run: a store whose rows come from
several versions says so when a sweep adds to it (or keeps rows of another version, or of files changed since:
:mod:`.kept_rows`) and in every ``svs-depth results`` summary. Tasks are blocks of
the pairs a configuration still lacks (stored pairs are never run again, whatever batch they ran in: a result
does not depend on its batch), and a task's rows are written in one transaction with ``INSERT OR IGNORE``. So a
sweep killed at any moment, or given a longer pair list, and started again runs only what is missing and ends
with the rows an uninterrupted run would have (``time_s`` and ``run_id`` aside).

Executors (:mod:`.executors`): in the calling process (``workers=0``); a local process pool whose workers each
run ``torch.set_num_threads(max(1, cores // workers))`` (``OMP_NUM_THREADS`` in place of the cores where fewer)
so that they do not oversubscribe the cores; or a Dask
``distributed`` cluster (``scheduler="tcp://HOST:PORT"``, ``pip install -e ".[dask]"``), where each task pins
torch to one thread. Only this process writes the store: workers return rows.
"""

from __future__ import annotations

import dataclasses
import difflib
import hashlib
import json
import platform
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..core.camera import MAX_SIZE_PX, parse_size
from ..core.checkout import code_version
from ..core.checks import InputError
from ..core.files import tidy_path
from ..core.workers import thread_budget
from ..data.pair_list import PairSource, read_pair_sources, unique_sources
from ..pipeline import PipelineConfig
from ..segmentation.network_files import weights_path
from .executors import available_cores, connect_dask, map_dask, map_process_pool
from .inert_settings import warn_inert_overrides
from .metrics import PairEvaluation
from .kept_rows import kept_rows_notices
from .overrides import (MAX_GRID_POINTS, PRESETS, apply_overrides, config_to_dict, describe_overrides, expand_grid,
                        flatten_table, merge_fixed, merge_labels, merge_overrides, parameter_types, preset_config,
                        read_toml)
from .runner import EvalSetup, _check_list, _expect, evaluate_block
from .store import ResultStore, check_storable

__all__ = ["Sweep", "SweepConfig", "SweepOutcome", "Task", "TaskResult", "code_version", "load_sweep",
           "make_sweep", "make_sweep_config", "plan_tasks", "run_sweep", "run_task"]

SWEEP_KEYS = ("paths", "size", "preset", "batch_size", "set", "grid", "configs")
DEFAULT_BATCH_SIZE = 8
#: What a pair over the pixel limit is told to resample it with in a sweep: its file's key, not eval's --size, an
#: option sweep does not take (an audit).
SWEEP_RESIZE_WITH = 'the sweep file\'s size = "WxH"'


@dataclass(frozen=True)
class SweepConfig:
    """One configuration of a sweep: its id, label, preset, overrides, size and resolved configuration."""

    config_id: str
    label: str
    preset: str
    overrides: dict[str, Any]
    size: str
    config: PipelineConfig

    def record(self) -> dict:
        """The row of the ``configs`` table."""
        return {"config_id": self.config_id, "label": self.label, "preset": self.preset,
                "overrides": self.overrides, "size": self.size, "config": config_to_dict(self.config)}


@dataclass(frozen=True)
class Sweep:
    """A checked sweep: pairs (deduplicated, in order), configurations, size, pairs per task, and its text;
    ``max_pixels``: a pair of more pixels run at its native size is ``BAD_INPUT`` (:class:`.runner.EvalSetup`)."""

    sources: tuple[PairSource, ...]
    configs: tuple[SweepConfig, ...]
    size_wh: tuple[int, int] | None
    batch_size: int = DEFAULT_BATCH_SIZE
    text: str = ""
    max_pixels: int | None = None


def _size_text(size_wh: tuple[int, int] | None) -> str:
    return "native" if size_wh is None else f"{size_wh[0]}x{size_wh[1]}"


def make_sweep_config(preset: str, overrides: dict[str, Any], size_wh: tuple[int, int] | None,
                      label: str | None = None, source: str = "sweep") -> SweepConfig:
    """Resolve and check one configuration (an InputError naming ``source`` and the key if it is bad)."""
    config = apply_overrides(preset_config(preset, f"{source}: preset"), overrides, source)
    size = _size_text(size_wh)
    identity = {"config": config_to_dict(config), "size": size}
    if config.segmentation.segmenter != "otsu":
        # The weights file can be retrained in place: its content, not its name, is the setting.
        identity["weights_sha256"] = _file_sha256(weights_path(config.segmentation.segmenter))
    digest = hashlib.sha256(json.dumps(identity, sort_keys=True).encode())
    return SweepConfig(digest.hexdigest()[:16], label if label is not None else describe_overrides(overrides),
                       preset, dict(overrides), size, config)


def _file_sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _dedupe(sources: Sequence[PairSource]) -> tuple[PairSource, ...]:
    return tuple(unique_sources(sources)[0])


def make_sweep(sources: Sequence[PairSource], configs: Sequence[SweepConfig], size_wh: tuple[int, int] | None,
               batch_size: int = DEFAULT_BATCH_SIZE, text: str = "") -> Sweep:
    """A sweep from pairs and configurations made in code (the same configuration twice counts once, labelled by
    every description that reached it: :func:`~.overrides.merge_labels`)."""
    _check_list(sources, PairSource, "sweep: sources", "PairSource (read_pair_sources)")
    _check_list(configs, SweepConfig, "sweep: configs", "SweepConfig (make_sweep_config)")
    unique: dict[str, SweepConfig] = {}
    for c in configs:
        first = unique.setdefault(c.config_id, c)
        if first is not c:
            unique[c.config_id] = dataclasses.replace(first, label=merge_labels(first.label, c.label))
    return Sweep(_dedupe(sources), tuple(unique.values()), size_wh, batch_size, text)


def _check_run(sweep: Any, workers: Any = None, threads: Any = None) -> None:
    """Refuse a sweep built by hand with odd values, or odd ``workers``/``threads``, by name before a store is made
    (an audit: a batch_size of 0 failed in range() and one of -1 ran nothing and said it was done, a size of
    (0, 120) failed in the resampler, workers=-1 in the process pool, each after the store held the run)."""
    _expect(isinstance(sweep, Sweep), f"sweep: expected a Sweep (load_sweep, make_sweep), got {type(sweep).__name__}")
    _check_list(sweep.sources, PairSource, "sweep: sources", "PairSource (read_pair_sources)")
    _check_list(sweep.configs, SweepConfig, "sweep: configs", "SweepConfig (make_sweep_config)")
    count = lambda value, least: type(value) is int and value >= least  # noqa: E731 -- (True is no count)
    size, side = sweep.size_wh, lambda n: count(n, 1) and n <= MAX_SIZE_PX  # noqa: E731 -- (a file's size's bound)
    _expect(size is None or (isinstance(size, (tuple, list)) and len(size) == 2 and all(side(n) for n in size)),
            f"sweep: size_wh: expected None or (width, height), two ints from 1 to {MAX_SIZE_PX}, got {size!r}")
    for config in sweep.configs:  # its rows would be stored under the id of a configuration of another size
        _expect(config.size == _size_text(size), f"sweep: configs: {config.label!r} was made for the size "
                                                 f"{config.size}, the sweep's is {_size_text(size)}")
    for name, value, least in (("batch_size", sweep.batch_size, 1), ("max_pixels", sweep.max_pixels, 1),
                               ("workers", workers, 0), ("threads", threads, 1)):
        _expect((value is None and name != "batch_size") or count(value, least),
                f"sweep: {name}: expected an integer of at least {least}, got {value!r}")


def _check_preset(preset: Any, source: str) -> None:
    _expect(isinstance(preset, str) and preset in PRESETS,  # a list here failed as "unhashable type"
            f"{source}: preset: expected one of {', '.join(map(repr, PRESETS))}, got {preset!r}")


def _too_many(name: str, entries: int, points: int) -> str:
    """The error of a sweep whose [[configs]] entries, each run over the whole grid, make too many configurations
    (the grid's own limit let 3 entries x 10 000 points through)."""
    return (f"{name}: configs: {entries} [[configs]] x {points} grid points = {entries * points} configurations, at "
            f"most {MAX_GRID_POINTS}; list fewer, or split them into several sweeps")


def _warn_repeated(configs: Sequence[SweepConfig], name: str) -> None:
    """Warn where a sweep file's configurations are one (``[5, 5]``): each runs once, said "1 configuration"."""
    firsts: dict[str, str] = {}  # each configuration's first label (setdefault records it, and is never None)
    repeats = [(firsts[c.config_id], c.label) for c in configs if c.config_id in firsts
               or firsts.setdefault(c.config_id, c.label) is None]
    if repeats:
        (first, again), count = repeats[0], len(configs)
        example = f"{again!r} twice" if again == first else f"{again!r} is {first!r}"
        warnings.warn(f"{name}: {count} configurations listed, {count - len(repeats)} distinct: {len(repeats)} repeat"
                      f"{'s' * (len(repeats) == 1)} one listed before ({example}); each runs once", stacklevel=3)


def load_sweep(path: str | Path) -> Sweep:
    """Read and check a sweep file (module docstring); every error is one InputError naming the file."""
    path = Path(path)
    name = str(path)
    table = read_toml(path, name)
    # Other top-level keys are parameters, fixed for every configuration, as in a --config file (one format).
    top_level = flatten_table({key: value for key, value in table.items() if key not in SWEEP_KEYS}, source=name)
    known = parameter_types()
    for key in top_level:  # the near names first, as --set and --config give them ('prest': did you mean preset?)
        close = difflib.get_close_matches(key, [*SWEEP_KEYS, *known], n=3, cutoff=0.6)
        _expect(key in known, f"{name}: unknown key {key!r} (" + (f"did you mean {', '.join(close)}? " if close else "")
                + f"expected {', '.join(SWEEP_KEYS)}, or a parameter such as segmentation.kernel_size)")
    paths = table.get("paths")
    paths = [paths] if isinstance(paths, str) else paths
    _expect(isinstance(paths, list) and paths and all(isinstance(p, str) and p.strip() for p in paths),  # ('': '.')
            f"{name}: paths: expected a list of scene folders or pair lists, got {table.get('paths')!r}")
    resolved = [p if Path(p).is_absolute() else tidy_path(path.parent / p) for p in paths]  # (see there: links)
    size = table.get("size", "native")
    _expect(isinstance(size, str), f"{name}: size: expected 'WxH' such as '320x240', or 'native', got {size!r}")
    size_wh = None if size == "native" else parse_size(size, f"{name}: size")
    batch_size = table.get("batch_size", DEFAULT_BATCH_SIZE)
    _expect(isinstance(batch_size, int) and not isinstance(batch_size, bool) and batch_size >= 1,
            f"{name}: batch_size: expected a positive integer, got {batch_size!r}")
    preset = table.get("preset", "default")
    _check_preset(preset, name)
    fixed = table.get("set", {})
    _expect(isinstance(fixed, dict), f"{name}: set: expected a table of parameters, got {fixed!r}")
    grid = table.get("grid", {})
    _expect(isinstance(grid, dict), f"{name}: grid: expected a table of parameter lists, got {grid!r}")
    entries = table.get("configs", [{}])
    _expect(isinstance(entries, list) and entries and all(isinstance(e, dict) for e in entries),
            f"{name}: configs: expected [[configs]] tables, got {entries!r}")
    fixed = merge_fixed(top_level, flatten_table(fixed, source=f"{name}: set"), name)
    make_sweep_config(preset, fixed, size_wh, source=f"{name}: set")  # its errors name [set], not the grid
    grid = flatten_table(grid, source=f"{name}: grid")
    points = expand_grid(grid, f"{name}: grid")
    _expect(len(entries) * len(points) <= MAX_GRID_POINTS, _too_many(name, len(entries), len(points)))
    both = sorted(set(fixed) & set(grid))  # the grid's won in silence: the fixed value never ran
    _expect(not both, f"{name}: {', '.join(both)}: set both as fixed for every configuration and in [grid]; expected "
                      f"each in one of them")
    configs = []
    for number, entry in enumerate(entries, start=1):
        source = f"{name}: configs[{number}]"
        entry = dict(entry)
        entry_preset = entry.pop("preset", preset)  # before flattening: a table here is a bad preset, not keys
        _check_preset(entry_preset, source)
        entry = flatten_table(entry, source=source)
        make_sweep_config(entry_preset, merge_overrides(fixed, entry), size_wh, source=source)
        for point in points:
            varying = merge_overrides(entry, point)
            label = describe_overrides(varying)
            if entry_preset != preset:  # "preset=paper", not "preset=paper (preset)"
                label = f"preset={entry_preset}" if not varying else f"preset={entry_preset} {label}"
            configs.append(make_sweep_config(entry_preset, merge_overrides(fixed, varying), size_wh, label,
                                             f"{name}: grid"))
    warn_inert_overrides([(c.config, c.overrides) for c in configs], name)  # one line, not one a configuration
    _warn_repeated(configs, name)
    sources = read_pair_sources(resolved, f"{name}: paths")
    return make_sweep(sources, configs, size_wh, batch_size, path.read_text(encoding="utf-8"))


@dataclass(frozen=True)
class Task:
    """One unit of work: a configuration and a block of pairs, run as one batch.

    ``threads``: torch threads in the worker (None: leave the process's setting); ``max_pixels``: the sweep's."""

    config_id: str
    config: PipelineConfig
    size_wh: tuple[int, int] | None
    sources: tuple[PairSource, ...]
    threads: int | None = None
    max_pixels: int | None = None


@dataclass(frozen=True)
class TaskResult:
    """A task's ``(pair_id, evaluation)`` rows and its wall time in the worker."""

    config_id: str
    rows: list[tuple[str, PairEvaluation]] = field(default_factory=list)
    seconds: float = 0.0


def run_task(task: Task) -> TaskResult:
    """Run one task (in a worker, or in this process): load, run and score its block of pairs, on ``task.threads``
    torch threads. The caller's thread count is put back after: run in this process (``run_sweep(workers=0,
    threads=T)``), a task left a notebook's torch on T threads (an audit of the API's effect on its caller)."""
    import torch

    previous = torch.get_num_threads()
    if task.threads is not None and previous != task.threads:
        torch.set_num_threads(task.threads)
    try:
        started = time.perf_counter()
        evaluations = evaluate_block(task.sources, EvalSetup(task.config, task.size_wh, max_pixels=task.max_pixels,
                                                                 resize_with=SWEEP_RESIZE_WITH))
        return TaskResult(task.config_id, [(s.pair_id, e) for s, e in zip(task.sources, evaluations)],
                          time.perf_counter() - started)
    finally:
        if torch.get_num_threads() != previous:
            torch.set_num_threads(previous)


def plan_tasks(sweep: Sweep, done: set[tuple[str, str]]) -> list[Task]:
    """The tasks still to run: for every configuration, the pairs whose (configuration, pair) row is missing from
    ``done``, in the sweep's order, in blocks of ``batch_size``. Blocks of the whole list ran its stored pairs
    again: a pair list grown by one scene, or one ERROR row, made a block of eight pairs run for one."""
    tasks = []
    for config in sweep.configs:
        missing = tuple(s for s in sweep.sources if (config.config_id, s.pair_id) not in done)
        for start in range(0, len(missing), sweep.batch_size):
            tasks.append(Task(config.config_id, config.config, sweep.size_wh, missing[start:start + sweep.batch_size],
                              max_pixels=sweep.max_pixels))
    return tasks


def environment(executor: str, workers: int, threads: int | None) -> dict:
    """What the results were computed with: versions, machine, executor."""
    import cv2
    import numpy
    import torch

    return {"python": platform.python_version(), "platform": platform.platform(), "machine": platform.machine(),
            "cpus": available_cores(), "torch": torch.__version__, "numpy": numpy.__version__,
            "opencv": cv2.__version__,
            "executor": executor, "workers": workers, "threads_per_worker": threads}


@dataclass(frozen=True)
class SweepOutcome:
    """What a run did: tasks run, rows written, rows of this sweep that were already stored, the run's id, and the
    rows of this sweep stored at its end (rows of a RETRIED_STATUSES status not counted: a resume runs them again),
    counted in the store: a sweep running beside it on the same store may have written some; and the rows of this
    sweep stored with such a status (an audit read "2 of 4 stored" of a file holding 4 rows)."""

    tasks: int
    rows_written: int
    rows_already_done: int
    run_id: int
    rows_stored: int = 0
    rows_to_retry: int = 0


def run_sweep(sweep: Sweep, db: str | Path, workers: int | None = None, scheduler: str | None = None,
              on_task: Callable[[TaskResult], None] | None = None, warn: Callable[[str], None] | None = None,
              command: str = "sweep", threads: int | None = None,
              on_start: Callable[[int, int], None] | None = None) -> SweepOutcome:
    """Run the missing part of ``sweep`` into the store ``db`` (created if needed), as a run named ``command``.

    Args:
        workers: local worker processes (default: one per core, or per ``OMP_NUM_THREADS`` if that is fewer, at
            most one per task); 0 runs the tasks in this process. Ignored with ``scheduler``.
        scheduler: a Dask scheduler address: run the tasks on that cluster.
        on_task: called with each finished task's result after its rows are committed (progress).
        warn: receives one-line warnings (default: stderr).
        threads: torch threads per worker (default: the cores, or OMP_NUM_THREADS if fewer, // workers; Dask: 1).
        on_start: called once with (rows to run, rows already stored) before any task runs.
    """
    warn = warn or (lambda message: print(f"warning: {message}", file=sys.stderr))
    _check_run(sweep, workers, threads)
    if scheduler:  # reached (with workers) before the store is made: else a bad address left a store without rows
        connect_dask(scheduler, lambda message: None).close()
    with ResultStore(check_storable(db, sweep.sources)) as store:
        store.claim_for_a_sweep(c.config_id for c in sweep.configs)
        store.add_configs(c.record() for c in sweep.configs)
        store.add_pairs(sweep.sources)
        config_ids = [c.config_id for c in sweep.configs]
        # This sweep's rows only: the store may hold the same configurations on other pairs ("3 of 1 stored").
        keys = {(c.config_id, s.pair_id) for c in sweep.configs for s in sweep.sources}
        done = store.done(config_ids) & keys
        if scheduler:
            executor, count, threads = "dask", 0, threads or 1
        else:
            count = thread_budget() if workers is None else workers  # not the cores: OMP_NUM_THREADS was ignored
            executor = "in-process" if count == 0 else "local-processes"
        tasks = plan_tasks(sweep, done)
        if not scheduler and count:
            count = min(count, max(1, len(tasks)))
            threads = threads or max(1, thread_budget() // count)
        tasks = [dataclasses.replace(task, threads=threads) for task in tasks]
        client = connect_dask(scheduler, warn) if scheduler and tasks else None
        version = code_version()
        for notice in kept_rows_notices(store, db, done, version, adding=bool(tasks)):
            warn(notice)
        run_id = store.start_run(command, version, environment(executor, count, threads), sweep.text)
        if on_start is not None:
            on_start(sum(len(t.sources) for t in tasks), len(done))
        if not tasks:
            return SweepOutcome(0, 0, len(done), run_id, len(done))
        if client is not None:
            results = map_dask(client, run_task, tasks)
        elif count == 0:
            results = map(run_task, tasks)
        else:
            results = map_process_pool(run_task, tasks, count, threads)
        written = 0
        for result in results:
            written += store.write_task(result.config_id, run_id, result.rows)
            if on_task is not None:
                on_task(result)
        return SweepOutcome(len(tasks), written, len(done), run_id, len(store.done(config_ids) & keys),
                            len(store.done(config_ids, retried=True) & keys))
