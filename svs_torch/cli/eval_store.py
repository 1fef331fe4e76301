"""``svs-depth eval --db``: the results store an eval writes its rows to, and what it tells of them: the rows an
interrupted run kept, and the rows stored before for the same configuration, which the store keeps rather than this
run's."""

from __future__ import annotations

import argparse
import sys

from .common import options_named

__all__ = ["COMPARED_FIELDS", "KeptRows", "check_no_option_calibration_in_store", "rows_stored_before",
           "say_saved", "store_beside_export"]

#: The result fields whose stored value, where it differs from this run's, tells that a kept row is not what this run
#: measured (the pipeline is deterministic: the same pair, settings and code give the same values, all but the time).
COMPARED_FIELDS = ("status", "r_min_m", "r_max_m", "acc_objects_pct")


def store_beside_export(export, *args):
    """:func:`_open_store` of ``args``; a refused ``--db`` leaves no ``--disparity-out`` folder that ``export`` made,
    empty, behind."""
    try:
        return _open_store(*args)
    except BaseException:
        if export is not None:
            export.remove_if_unused()
        raise


def say_saved(args: argparse.Namespace, rows: int, done: int, total: int) -> None:
    """What an interrupted eval kept: the rows its ``--db`` store committed, the maps of ``--disparity-out``."""
    if args.db:
        print(f"svs-depth eval: {rows} of {total} pairs' rows are stored in {args.db}; the same command run again "
              "keeps them and stores the rest", file=sys.stderr)
    if args.disparity_out:
        print(f"svs-depth eval: the maps written in {args.disparity_out} are whole ({done} of {total} pairs "
              "evaluated)", file=sys.stderr)


def rows_stored_before(stored_in: tuple) -> dict[str, tuple]:
    """``{pair_id: values of COMPARED_FIELDS}`` of the rows the ``--db`` store of ``stored_in`` (store, run id,
    sweep configuration) held for this run's configuration before it ran, those it keeps whatever this run measures
    (a row of a retried status, which a new result replaces, is not among them); {} without a store."""
    from ..evaluation.store import RETRIED_STATUSES

    store, _, sweep_config = stored_in
    if store is None:
        return {}
    values = store.stored_values(sweep_config.config_id, COMPARED_FIELDS)  # (status first)
    return {pair_id: row for pair_id, row in values.items() if row[0] not in RETRIED_STATUSES}


class KeptRows:
    """Of the pairs an eval evaluated (:meth:`add`, each as it comes: only its compared values are kept, not the row),
    those whose rows the ``--db`` store held before (``before``: :func:`rows_stored_before`) and keeps instead of
    this run's, and how many of them differ from what this run printed. Why: a second 'eval --db' after an image, a
    ground truth or the code changed printed the new numbers and exited 0, while the store kept the first run's rows
    and 'results' showed them (an audit: 92.3 % printed, 99.7 % stored), without a word."""

    def __init__(self, before: dict[str, tuple]) -> None:
        self.before, self.evaluated, self.kept, self.differing = before, 0, 0, 0
        self.first: tuple | None = None  # the first differing row: (name, status, objects %, the stored values)

    def add(self, pair_id: str, evaluation) -> None:
        self.evaluated += 1
        if pair_id not in self.before:
            return
        self.kept += 1
        stored = self.before[pair_id]
        if tuple(getattr(evaluation, name) for name in COMPARED_FIELDS) != stored:
            self.differing += 1
            if self.first is None:
                self.first = (evaluation.name, evaluation.status, evaluation.acc_objects_pct, stored)

    def note(self, db: str) -> tuple[dict, str | None]:
        """The counts for the JSON summary (``db_rows_kept``, ``db_rows_kept_differing``; {} where none was kept)
        and the line that says so (None where none was), of the store ``db``."""
        if not self.kept:
            return {}, None
        counts = {"db_rows_kept": self.kept, "db_rows_kept_differing": self.differing}
        said = f"svs-depth eval: {self.kept} of {self.evaluated} pairs had rows in {db} for this configuration"
        if not self.differing:
            return counts, f"{said}, the same as this run's: kept"
        name, status, new, stored = self.first
        old = stored[COMPARED_FIELDS.index("acc_objects_pct")]
        return counts, (f"{said} before this run, and the store keeps those, not this run's: {self.differing} of them "
                        f"differ{'s' if self.differing == 1 else ''} (first {name}: {stored[0]}, objects "
                        f"{_percent(old)} stored, {status}, {_percent(new)} now); svs-depth results reads the "
                        f"stored rows: give another --db file to store this run's")


def _percent(value) -> str:
    return "-" if value is None else f"{value:.1f} %"


def check_no_option_calibration_in_store(args: argparse.Namespace, sources) -> None:
    """A results store keys a file pair by its files and the calibration its list line gives: rows ranged with
    --focal-px, --baseline-m or --doffs-px would be filed under the same keys as the SVS model's (and a later run
    with other values silently kept the first's rows)."""
    from ..core.errors import InputError

    options = [name for name, value, default in (("--focal-px", args.focal_px, None), ("--baseline-m",
               args.baseline_m, None), ("--doffs-px", args.doffs_px, 0.0)) if value != default]
    takers = [source for source in sources if not source.scene and source.focal_px is None and not source.problem]
    if options and sources and not takers and not any(source.problem for source in sources):  # it ran as if not given
        raise InputError(f"{', '.join(options)}: every listed pair is a scene folder (its data's calibration, or a "
                         f"nominal one for scoring where it ships none) or a list line that gives one, which the "
                         f"option does not change; drop it")
    if args.db and options and takers:
        raise InputError(f"{', '.join(options)}, --db: a results store does not record a calibration given as an "
                         f"option; give it on the pairs' list lines ('LEFT RIGHT FOCAL_PX BASELINE_M [DOFFS_PX]') or "
                         f"run without --db")


def _open_store(args: argparse.Namespace, preset, overrides, size_wh, sources) -> tuple:
    """With ``--db``: the results store, opened with this run's configuration and pairs recorded, the run's id
    and its sweep configuration; (None, None, None) without."""
    if not args.db:
        return None, None, None
    from ..evaluation.store import ResultStore, check_storable
    from ..core.checkout import code_version
    from ..evaluation.sweep import environment, make_sweep_config

    sweep_config = make_sweep_config(preset, overrides, size_wh)
    with options_named(db="--db"):  # the store's errors named its argument, "db:", not the option (an audit)
        store = ResultStore(check_storable(args.db, sources))  # paths a store cannot keep refused before it is made
        try:
            # Held as a sweep holds its configurations, so that results reading the store while this runs says the
            # pairs not reached are not run yet (it said "stopped before them"), and a sweep or another eval of the
            # same configuration on it waits for this one, nothing recorded.
            store.claim_for_a_sweep([sweep_config.config_id])
        except BaseException:
            store.close()
            raise
    store.add_configs([sweep_config.record()])
    store.add_pairs(sources)
    run_id = store.start_run("eval", code_version(), environment("in-process", 0, None), " ".join(sys.argv[1:]))
    return store, run_id, sweep_config
