"""``svs-depth results``: summaries, CSV and plots of a results file written by ``sweep`` or ``eval --db``."""

from __future__ import annotations

import argparse
import csv
import sys
from collections.abc import Sequence

from .common import add_figure_option, check_outputs_apart, dumps_strict, non_negative_int, options_named, output_file

HELP = "summarise, export (CSV) or plot a sweep's results file"

DESCRIPTION = """\
Read a results file of svs-depth sweep (or eval --db).

--summary (the default without --csv or --figure): each configuration's mean Eq. (9) accuracy of R_min, R_max and
the objects (a failed pair counts 0 %) over the pairs scored with their own calibration, or, where more pairs were
scored with a nominal one (data that ship none, as most Middlebury 2005/2006 scenes), over those (the 'scored'
column says which, and how many); dense and inlier disparity quality (means over the pairs that have them: a note
says where that is fewer for some configuration), failures and time, best first (pairs_per_s here is over the
pairs' summed pipeline time: a store keeps no wall time, so it reads higher than eval's, which counts loading
too); configurations of the same results on every pair (a swept setting that changed nothing) are named together;
then the best configuration by each metric. --csv: one row per (configuration, pair), columns config, left, right,
status, r_min_m, r_max_m, acc_r_min_pct, acc_r_max_pct (config is the configuration's id), then its label, size,
the swept parameters (param:KEY) and every other column, among them the stereo metrics of the dense map
(<scope>_<metric>: scope map_all, map_nocc, kept_all or kept_nocc; metric density, bad0_5_pct ... bad4_pct,
avgerr_px, rms_px, a50_px ... a99_px, d1_pct, num_px; empty where a pair has none, as in rows stored before they
existed); paths are shown normalised (no inner '..'; a leading one, relative to the folder it was run in, stays).
--figure: mean accuracy against each swept parameter and per-scene bars of the best configuration.
"""

EPILOG = """\
examples:
  svs-depth results sweep.sqlite
  svs-depth results sweep.sqlite --csv > rows.csv
  svs-depth results sweep.sqlite --summary --top 5 --figure sweep.png
"""


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("results", help=HELP, description=DESCRIPTION, epilog=EPILOG,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("db", metavar="FILE.sqlite", help="results file of svs-depth sweep or eval --db")
    parser.add_argument("--summary", action="store_true", help="best configurations by each metric (the default "
                        "without --csv or --figure)")
    parser.add_argument("--csv", nargs="?", const="-", metavar="FILE.csv", type=output_file,
                        help="one row per (configuration, pair), to FILE.csv or standard output")
    add_figure_option(parser, "figure: metrics against each swept parameter, scenes", "--plot", "--out",
                      kinds=".png, .pdf or .svg")
    parser.add_argument("--top", type=non_negative_int,
                        help="configurations listed in the summary, best first (0: all; default: 10, and all with "
                             "--json)")
    parser.add_argument("--sort", default="acc_objects_pct",
                        choices=("acc_r_min_pct", "acc_r_max_pct", "acc_objects_pct", "dense_within_1px",
                                 "inlier_precision"), help="metric the summary ranks by (default: acc_objects_pct)")
    parser.add_argument("--json", action="store_true",
                        help="the summary as one JSON object: configs (best first by --sort, --top of them), "
                             "sort, best (each metric's best configuration id over every stored configuration, "
                             "listed or not), same_results (groups of configuration ids whose rows are the same on "
                             "every pair, times aside), configs_without_rows and pairs_without_rows (recorded, no "
                             "row yet: a run still going has not reached them, or one stopped before them) and "
                             "writing (whether a sweep or an eval --db is writing the store now)")
    parser.set_defaults(func=run)


def _number(value, digits: int = 1) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _print_summary(summaries: list[dict], best, args: argparse.Namespace, same: list[list[str]],
                   unrun: tuple[int, int, bool] = (0, 0, False), changed: Sequence[str] = ()) -> None:
    from ..evaluation.report import ranked_group, ranked_value

    shown = ranked_summaries(summaries, args)
    print(f"{len(summaries)} configuration{'s' * (len(summaries) != 1)}; ranked by {args.sort}"
          + (f", the best {len(shown)}" if len(shown) < len(summaries) else ""))
    for note in _unrun_notes(*unrun, args.db, len(summaries)):
        print(note)
    common = _common_settings(summaries)
    if common:
        print(f"every configuration also ran with (not in its label): {common}")
    print(f"{'config':<16} {'pairs':>5} {'fail':>4} {'scored':>6} {'R_min %':>7} {'R_max %':>7} {'obj %':>6} "
          f"{'d<=1':>5} {'prec':>5} {'s/pair':>6}  label")
    for s in shown:
        group, count = ranked_group(s)
        scored = f"{count}{' n' if group == 'nominal' else ''}"
        print(f"{s['config_id']:<16} {s['pairs']:>5} {s['failed']:>4} {scored:>6} "
              f"{_number(ranked_value(s, 'acc_r_min_pct')):>7} {_number(ranked_value(s, 'acc_r_max_pct')):>7} "
              f"{_number(ranked_value(s, 'acc_objects_pct')):>6} {_number(s['dense_within_1px'], 2):>5} "
              f"{_number(s['inlier_precision'], 2):>5} {_number(s['pipeline_s_per_pair'], 3):>6}  {s['label']} "
              f"({s['preset']}, {s['size']})")
    if any(ranked_group(s)[0] == "nominal" for s in shown):
        print("note: 'scored' is the pairs the accuracies are over; 'n': scored with a nominal calibration (their "
              "data ship none), more than those with their own (svs-depth eval shows both groups)")
    else:
        _print_nominal_apart(shown)
    missing = [s for s in summaries if s.get("pairs_missing")]
    if missing:
        print("note: the configurations were not all measured on the same pairs ("
              + ", ".join(f"{s['config_id']} lacks {s['pairs_missing']}" for s in missing)
              + "): their means are over different pairs; resume the sweep (or rerun) to compare like with like")
    uneven = _uneven_counts_note(summaries)
    if uneven:
        print(uneven)
    labels = {s["config_id"]: s["label"] for s in summaries}
    for group in same:
        print(f"note: {' = '.join(f'{c} ({labels[c]})' for c in group)}: the same results on every pair, times "
              f"aside: what differs between them changed nothing here (as a setting that the configuration in use "
              f"never reads does, e.g. one of another segmenter)")
    for note in [*_code_version_notes(summaries), *changed]:
        print(note)
    print("best by each metric:")
    for key, label, s in best:
        digits = 3 if key in ("dense_within_1px", "inlier_precision", "pipeline_s_per_pair") else 1
        # An exact tie is said, as the figure's (an audit: the first stored of two equal configurations was named
        # best alone, the other's equal value hidden by the rounding).
        tied = sum(ranked_value(other, key) == ranked_value(s, key) for other in summaries) - 1
        print(f"  {label:<18} {_number(ranked_value(s, key), digits):>7}  {s['config_id']}  {s['label']}"
              + (f"  (tied with {tied} other{'s' * (tied > 1)})" if tied else ""))


def _unrun_notes(configs: int, pairs: int, writing: bool, db: str, run: int) -> list[str]:
    """Notes of the ``configs`` configurations and the ``pairs`` pairs recorded in ``db`` that have no row: an
    interrupted run's table read as a finished one (an audit: a sweep's 40 configurations of 1000 run, "best" of
    the 40; and an eval --db stopped after 8 of its 45 pairs, summarised over the 8 without a word). ``writing``: a
    sweep or an eval --db is writing the store now (its claims,
    :func:`~svs_torch.evaluation.store_access.sweep_is_writing`), so they are not run yet; else a run stopped before
    them, or one still running that the store cannot tell (where the system has no such locks): the notes said
    "stopped" of the pairs an eval was still running."""
    from ..evaluation.store_access import WRITERS

    notes = []
    for count, noun, where, read in ((configs, "configuration", "", f"the ranking and the best are of the {run} run"),
                                     (pairs, "pair", " in any configuration", "the means are over the pairs run")):
        if not count:
            continue
        if writing:
            why, fill = f"not run yet: {WRITERS} is writing the store now", "the run writing it fills those it covers"
        else:
            why = f"not run yet by a run still going, or a run stopped before {'them' if count > 1 else 'it'}"
            fill = "the run going on, or the same command run again, fills the rest"
        notes.append(f"note: {count} more {noun}{'s' * (count != 1)} recorded in {db} "
                     f"{'have' if count != 1 else 'has'} no row{where} yet ({why}): {read} so far; {fill}")
    return notes


def _code_version_notes(summaries: list[dict]) -> list[str]:
    """A note of each configuration whose rows come from several code versions, and one where the configurations,
    each of one version, are of different ones: a sweep resumed after a code change ranked the new configurations
    against the old ones without a word (an audit), the difference between them perhaps the code's."""
    from ..evaluation.kept_rows import named

    notes = [f"note: {s['config_id']}'s rows come from {len(s['code_versions'])} code versions "
             f"({', '.join(map(str, s['code_versions']))}): rerun into a new --db to compare like with like"
             for s in summaries if len(s["code_versions"]) > 1]
    by_version: dict[str, list[str]] = {}
    for s in summaries:
        if len(s["code_versions"]) == 1:
            by_version.setdefault(str(s["code_versions"][0]), []).append(s["config_id"])
    if not notes and len(by_version) > 1:
        listed = "; ".join(f"{version}: {named(ids)}" for version, ids in by_version.items())
        notes.append(f"note: the configurations were measured by {len(by_version)} code versions ({listed}): what "
                     f"differs between them may be the code's; rerun into a new --db to compare like with like")
    return notes


def _changed_files_notes(store, db: str) -> list[str]:
    """A note of the rows whose pair's files changed after they were stored (:mod:`~svs_torch.evaluation.kept_rows`):
    an eval --db after a mended image kept the old row, and the table read it without a word (an audit)."""
    from ..evaluation.kept_rows import named, rows_of_changed_files

    changed, seen, names = rows_of_changed_files(store)
    return [f"note: {changed} of the {seen} rows in {db} are of pairs whose files changed since the row was stored "
            f"({named(names)}): rerun into a new --db to measure them as they are now"] if changed else []


def _common_settings(summaries: list[dict]) -> str:
    """The overrides every configuration ran with, at one value, that some label leaves out: a sweep's [set] (its
    labels name the grid alone), so a sweep whose only setting was [set] read as "(preset)" and two stores of
    sweeps differing in [set] alone read the same (an audit)."""
    first = summaries[0]["overrides"] if summaries else {}
    common = {key: value for key, value in first.items()
              if all(key in s["overrides"] and s["overrides"][key] == value for s in summaries)}
    unnamed = [key for key in common
               if any(not any(part.startswith(f"{key}=") for part in s["label"].split()) for s in summaries)]
    return " ".join(f"{key}={common[key]}" for key in unnamed)


def _print_nominal_apart(shown: list[dict]) -> None:
    """A note of the pairs scored with a nominal calibration where the accuracies are over those with their own:
    left out of the means without a word, they were the one pair of five 'scored' left unexplained (an audit; eval
    says "apart, below")."""
    apart = {s["config_id"]: (s.get("nominal_calibration") or {}).get("scored") or 0 for s in shown}
    if any(apart.values()):
        most = f"{'' if len(set(apart.values())) == 1 else 'up to '}{max(apart.values())}"
        print(f"note: 'scored' is the pairs with their own calibration the accuracies are over; {most} more per "
              f"configuration were scored with a nominal one (their data ship none), apart and not in these means: "
              f"their means are --json's nominal_calibration")


#: ``(column, count key)`` of the table's means over only the pairs that have them (a failed pair has none).
_MEASURED_COUNTS = (("d<=1", "dense_pairs"), ("prec", "inlier_pairs"), ("bad-2/D1", "kept_all_pairs"))


def _uneven_counts_note(summaries: list[dict]) -> str | None:
    """A note where a configuration's disparity means are over fewer pairs than another's (an audit: one that failed
    on the hard pairs ranked best by d<=1 or bad-2 over the easy ones it kept, unsaid), or None; a mean over none
    shows '-' already."""
    most = {key: max((s[key] for s in summaries if s.get(key) is not None), default=None)
            for _, key in _MEASURED_COUNTS}
    fewer = [(s, [(column, key) for column, key in _MEASURED_COUNTS if 0 < (s.get(key) or 0) < most[key]])
             for s in summaries]
    fewer = [(s, short) for s, short in fewer if short]
    if not fewer:
        return None
    listed = "; ".join(f"{s['config_id']} " + ", ".join(f"{column} over {s[key]} of {most[key]}"
                                                        for column, key in short) for s, short in fewer[:5])
    return (f"note: d<=1, prec, bad-2 and D1 are means over the pairs that have them (a failed pair has none; the "
            f"accuracies count it 0 %), not over the same number for every configuration ({listed}"
            f"{f'; and {len(fewer) - 5} more' if len(fewer) > 5 else ''}): compare them with care")


def ranked_summaries(summaries: list[dict], args: argparse.Namespace) -> list[dict]:
    """The summaries best first by ``--sort`` (as ranked_value reads it), the first ``--top`` of them (all with
    --top 0; without --top, 10 in the table and all in JSON)."""
    from ..evaluation.report import ranked_value

    ranked = sorted(summaries, key=lambda s: -(v if (v := ranked_value(s, args.sort)) is not None else -1e9))
    top = args.top if args.top is not None else (0 if args.json else 10)
    return ranked[:top] if top else ranked


def _unrun(store, summaries: list[dict], writing: bool) -> tuple[set[str], tuple[int, int, bool]]:
    """The configurations recorded in ``store``, and how many of them and of its pairs have no row, and ``writing``
    (a sweep or an eval --db is writing the store now)."""
    from ..evaluation.report import pairs_without_rows

    recorded = {c["config_id"] for c in store.configs()}
    return recorded, (len(recorded - {s["config_id"] for s in summaries}), pairs_without_rows(store), writing)


def run(args: argparse.Namespace) -> int:
    # The store's errors named the library's argument, "db: ...", where the usage line shows FILE.sqlite (an audit).
    with options_named(db="FILE.sqlite", store="FILE.sqlite"):
        return _run(args)


#: What fills a store that has no row yet, where no run is writing it and where one is. Where none is, as the notes
#: of a store with rows say (_unrun_notes): an eval --db records its configuration and pairs before its first row,
#: and its store, read while it ran, was to be filled by "running the sweep's command again".
_FILLS_AN_EMPTY_STORE = ("the run going on, or the same command run again,", "the run writing it now")


def _run(args: argparse.Namespace) -> int:
    from ..core.workers import imports_without_collection
    from ..evaluation.store_access import check_store_path

    check_store_path(args.db, create=False)  # first: a mistyped name was said after torch's import (2 s)
    with imports_without_collection():  # see there: a Ctrl-C meanwhile is raised once they are done
        from ..evaluation.report import best_by_metric, config_summaries, csv_table, plot_results, same_results
        from ..evaluation.store import ResultStore
        from ..evaluation.store_access import WRITERS, sweep_is_writing
        from ..core.files import atomic_output, check_output_file, write_errors_named

    # Output files are checked before any work: a bad name fails at once, and nothing is half-written.
    if args.csv == "-" and (args.json or args.summary):  # the summary's JSON was the table's last line, or lost
        from ..core.checks import InputError

        raise InputError(f"--csv: the table and {'--json' if args.json else '--summary'} would both go to standard "
                         f"output; give --csv a FILE.csv")
    if args.figure:
        check_output_file(args.figure, args.figure_option, (".png", ".pdf", ".svg"), "a .png, .pdf or .svg")
    if args.csv and args.csv != "-":
        check_output_file(args.csv, "--csv")
    # `results DB --csv DB` wrote the table over the store
    check_outputs_apart([("--csv", None if args.csv == "-" else args.csv), (args.figure_option, args.figure)],
                        [("results file itself", args.db)])
    if writing := sweep_is_writing(args.db):  # (before the store is opened: see there) the table read as finished
        print(f"svs-depth results: note: {WRITERS} is writing {args.db} now; these are the rows stored so far",
              file=sys.stderr)
    with ResultStore(args.db, create=False) as store:
        if args.figure:  # first: a store without rows has no figure, and its --csv was written before it said so
            with write_errors_named(args.figure_option, args.figure):
                plot_results(store, args.figure, writing)
            print(f"figure written to {args.figure}", file=sys.stderr)
        if args.csv:
            header, rows = csv_table(store)
            if args.csv == "-":
                csv.writer(sys.stdout).writerows([header, *rows])
            else:  # never half a table; a full disk named with the option and the file
                with write_errors_named("--csv", args.csv), \
                        atomic_output(args.csv, "w", newline="", encoding="utf-8") as stream:
                    csv.writer(stream).writerows([header, *rows])
        if args.summary or args.json or not (args.csv or args.figure):
            rows = store.results()  # read once, for both
            summaries = config_summaries(store, rows)
            best = best_by_metric(summaries)
            recorded, unrun = _unrun(store, summaries, writing)
            if args.json:
                # "best" over every configuration, as the text's: over the --top listed it named another (the best
                # of two listed by R_min 99.408 % where a configuration left out read 99.411), and broke ties in
                # the listing's order, not the text's.
                print(dumps_strict({"configs": ranked_summaries(summaries, args), "sort": args.sort,
                                    "best": {key: s["config_id"] for key, _, s in best},
                                    "same_results": same_results(store, rows), "configs_without_rows": unrun[0],
                                    "pairs_without_rows": unrun[1], "writing": writing}))
            elif not summaries:  # an empty table read as a result (an audit: the figure said "no results yet")
                print(f"{args.db}: no results yet ({len(recorded)} configuration{'s' * (len(recorded) != 1)} recorded, "
                      f"no pair run); {_FILLS_AN_EMPTY_STORE[writing]} fills it")
            else:
                _print_summary(summaries, best, args, same_results(store, rows), unrun,
                               _changed_files_notes(store, args.db))
    return 0
