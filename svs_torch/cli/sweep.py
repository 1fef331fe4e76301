"""``svs-depth sweep``: run a grid (or a list) of configurations over many pairs into a resumable SQLite file."""

from __future__ import annotations

import argparse
import sys

from .common import Terminated, dumps_strict, non_negative_int, options_named, output_file, positive_int
from .progress import Progress

HELP = "run a parameter sweep over many pairs into a resumable SQLite results file"

DESCRIPTION = """\
Evaluate every configuration of a sweep file on every pair it lists (the metrics of svs-depth eval) and store
one row per (configuration, pair) in a SQLite file. The work is split into tasks of one configuration and a
block of pairs, run by a local process pool (each worker's torch threads pinned to cores / workers) or, with
--scheduler, a Dask cluster. Each task's rows are committed at once: kill the sweep at any moment (Ctrl-C, or
even kill -9) and run the same command again, and it runs only what is missing (a warning counts the rows
it keeps that an older code version computed, or whose pair's files changed since: a new --db runs them).
Sweeps of different configurations (other grids, a job array's parts) may write one --db at once; a sweep
any of whose configurations another running sweep holds is refused at once (run it after: it resumes).

sweep file (TOML; paths relative to the file):
  paths = ["../shared/data/middlebury_eval3_Q"]   scene folders, folders of scenes, pair lists, index.jsonl
  size = "320x240"                                 or "native" (default); at most 16 megapixels, as eval
  preset = "default"                               or "paper"
  batch_size = 8                                   pairs per task
  [set]                                            fixed settings for every configuration
  "dense.window_size" = 9
  [grid]                                           every combination of these values (at most 10 000)
  "segmentation.kernel_size" = [3, 5, 7]
  "max_ratio" = [0.6, 0.8]
  [[configs]]                                      optional: a list of configurations (x the grid)
  preset = "paper"
Keys are the dotted fields of the pipeline configuration, as in svs-depth eval --set. A bad file (unknown key
or parameter, wrong value, missing path) fails before any work with one line.
"""

EPILOG = """\
examples:
  svs-depth sweep experiments/sweep_defaults.toml --db sweep.sqlite
  svs-depth sweep sweep.toml --db sweep.sqlite --workers 2
  svs-depth sweep sweep.toml --db sweep.sqlite --scheduler tcp://10.0.0.5:8786   (pip install -e ".[dask]")
  svs-depth results sweep.sqlite --summary --figure sweep.png

Dask workers: start them with one thread each and without the nanny's MALLOC_TRIM_THRESHOLD_ (about 1.5x
slower torch), e.g.  DASK_CONFIG=experiments/dask_workers.yaml dask worker tcp://HOST:8786 --nthreads 1
exit status: 0 done (failed pairs are rows with their status); 2 bad arguments or sweep file, or another running
sweep holds some of its configurations; 1 the store cannot be written (a full disk, or another program kept it
locked over 60 s) or a worker process died; 130 interrupted, 143 terminated (SIGTERM) (in every case what
was committed stays; run again to resume: the rows missing and the ERROR, BAD_INPUT and TOO_SMALL rows are run
again).
"""


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("sweep", help=HELP, description=DESCRIPTION, epilog=EPILOG,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sweep_file", metavar="SWEEP.toml", help="the sweep file")
    parser.add_argument("--db", required=True, metavar="FILE.sqlite", type=output_file,
                        help="results file, created or resumed")
    parser.add_argument("--workers", type=non_negative_int, metavar="N",
                        help="local worker processes (default: one per core, or per OMP_NUM_THREADS if that is "
                             "fewer; 0: in this process)")
    parser.add_argument("--threads", type=positive_int, metavar="T",
                        help="torch threads per worker (default: cores, or OMP_NUM_THREADS if fewer, / workers; 1 "
                             "on Dask)")
    parser.add_argument("--scheduler", metavar="ADDRESS", help="run on the Dask cluster at this address")
    parser.add_argument("--json", action="store_true",
                        help='print one JSON summary line at the end (stopped by Ctrl-C or SIGTERM too: the rows this '
                             'run wrote, "interrupted": true)')
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..core.workers import imports_without_collection

    with imports_without_collection():  # see there: the imports' objects are frozen
        from ..core.files import check_path_given
        from ..evaluation.sweep import load_sweep, run_sweep
        from .capture_marks import capture_fields, warn_capture_marks

    check_path_given(args.sweep_file, "SWEEP.toml", "a sweep file name")  # ('' is '.': ".: expected a TOML file")
    sweep = _within_pixel_limit(load_sweep(args.sweep_file), args.sweep_file)
    _check_no_kept_calibration(sweep, args.sweep_file)
    bar, written = None, 0  # written: the rows this run's finished tasks wrote (said, and in JSON, when interrupted)

    def stored(result) -> None:
        nonlocal written
        written += len(result.rows)
        bar.update(len(result.rows))

    def start(total: int, done: int) -> None:
        nonlocal bar
        configs, pairs = len(sweep.configs), len(sweep.sources)
        print(f"svs-depth sweep: {configs} configuration{'s' * (configs != 1)} x {pairs} pair{'s' * (pairs != 1)}; "
              f"{done} row{'s' * (done != 1)} already in {args.db}, {total} to run", file=sys.stderr, flush=True)
        bar = Progress(total, "sweep", unit="row")  # (configuration, pair) rows: "20/20 pairs" for 10 pairs read odd

    def warn(message: str) -> None:
        if bar is not None:
            bar.warn(f"svs-depth sweep: warning: {message}")
        else:
            print(f"svs-depth sweep: warning: {message}", file=sys.stderr)

    try:
        with options_named(db="--db"):  # the store's errors named its argument, "db:", not the option (an audit)
            outcome = run_sweep(sweep, args.db, workers=args.workers, scheduler=args.scheduler,
                                threads=args.threads, on_task=stored, warn=warn, on_start=start)
    except (KeyboardInterrupt, Terminated):  # SIGTERM too: it said only "terminated" (an audit of interrupts)
        print(f"svs-depth sweep: every finished task is stored in {args.db} ({written} row"
              f"{'s' * (written != 1)} written by this run); run the same command again to resume", file=sys.stderr)
        if args.json:  # a script read nothing on stdout (an audit of interrupts); eval --json says "interrupted" so
            print(dumps_strict({"configs": len(sweep.configs), "pairs": len(sweep.sources), "rows_written": written,
                                "rows_total": len(sweep.configs) * len(sweep.sources), "interrupted": True}),
                  flush=True)
        raise
    finally:
        if bar is not None:
            bar.close()
    # as estimate --pairs and eval: the pairs a capture's index marks as no stereo moment, counted (an audit)
    warn_capture_marks([capture_fields(source) for source in sweep.sources], len(sweep.sources))
    total = len(sweep.configs) * len(sweep.sources)
    rows, tasks = outcome.rows_written, outcome.tasks
    print(f"svs-depth sweep: {rows} row{'s' * (rows != 1)} written by {tasks} task{'s' * (tasks != 1)}, "
          f"{outcome.rows_stored} of {total} stored in {args.db}"
          + (f" ({outcome.rows_to_retry} more failed there: BAD_INPUT, TOO_SMALL or ERROR rows, run again when the "
             f"same command is run again)" if outcome.rows_to_retry else ""), file=sys.stderr)
    if args.json:
        print(dumps_strict({"configs": len(sweep.configs), "pairs": len(sweep.sources), "tasks": outcome.tasks,
                            "rows_written": outcome.rows_written, "rows_stored": outcome.rows_stored,
                            "rows_to_retry": outcome.rows_to_retry,
                            "rows_total": total, "run_id": outcome.run_id}))
    return 0


def _check_no_kept_calibration(sweep, sweep_file: str) -> None:
    """Refuse a capture folder's ``index.jsonl`` listed with the rig calibration that ``capture --calibration`` and
    ``guide --record`` keep beside it, as ``eval --db`` refuses it. Why: a sweep applies no rig calibration, so its
    pairs were stored ranged unrectified in the SVS model's metres without a word (an audit), where eval and
    estimate --pairs rectify them with that copy."""
    from ..core.errors import InputError
    from .rig import kept_calibration_gone, kept_calibrations, rig_list_files

    kept_by_list = kept_calibrations(rig_list_files(sweep.sources))
    # one whose copy is gone too: it was stored in the SVS model's metres as a folder without one (an audit)
    if gone := kept_calibration_gone([listed for listed, kept in kept_by_list.items() if kept is None]):
        raise InputError(f"{sweep_file}: paths: {gone} lists pairs captured with a rig calibration, which is no "
                         "longer beside it and which a sweep does not apply; range those pairs with svs-depth eval or "
                         "estimate --pairs and the rig's file")
    for listed, kept in kept_by_list.items():
        if kept is not None:
            raise InputError(f"{sweep_file}: paths: {listed} was captured with a rig calibration ({kept}), which a "
                             "sweep does not apply and a results store does not record yet; range those pairs with "
                             "svs-depth eval or estimate --pairs, which rectify them with it")


def _within_pixel_limit(sweep, sweep_file: str):
    """``sweep`` held to eval's pixel limit (:data:`~svs_torch.cli.features.MAX_PIXELS`): its size over it refused,
    and at the native size a pair over it BAD_INPUT. Why: a sweep took size = "8192x8192" and ran a 6000x4000 pair
    at 3.9 GB in every worker, where eval refuses both (an audit)."""
    import dataclasses

    from ..core.errors import InputError
    from . import features

    if sweep.size_wh is not None and sweep.size_wh[0] * sweep.size_wh[1] > features.MAX_PIXELS:
        raise InputError(f"{sweep_file}: size: expected at most {features.MAX_PIXELS // 10**6} megapixels, got "
                         f"'{sweep.size_wh[0]}x{sweep.size_wh[1]}'")
    return dataclasses.replace(sweep, max_pixels=features.MAX_PIXELS)
