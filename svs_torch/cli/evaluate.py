"""``svs-depth eval``: run the pipeline over many pairs and score it against their ground truth."""

from __future__ import annotations

import argparse
import sys
import time
import warnings

from .capture_marks import capture_fields, warn_capture_marks
from .eval_store import (KeptRows, check_no_option_calibration_in_store, rows_stored_before, say_saved,
                         store_beside_export)
from .common import (Terminated, add_disparity_export_options, dumps_strict, options_named, output_file,
                     positive_int, resolve_export_options)
from .features import MAX_PIXELS, checked_size
from .progress import Progress
from .rig import (add_calibration_option, baseline_m_value, check_no_manual_calibration, doffs_px_value,
                  eval_rig_calibration, focal_px_value, rig_provenance, with_calibrated_rectification)

HELP = "score the pipeline against ground truth over many pairs (scene folders, lists)"

DESCRIPTION = """\
Run the pipeline over every pair of PATH... in batches and score it against each pair's ground truth:
Eq. (9) accuracy of R_min, R_max and each object (an object's true distance is the median GT depth over the
pixels it is measured over, its kept region's interior; true R_min / R_max are the nearest / farthest object),
the dense disparity error over the kept regions and the RANSAC inliers' disparity error (median, within 1 px,
within 3 px), inlier precision, counts, status and time. A failed pair counts 0 % and is listed; nothing is hidden.

The standard stereo metrics of the dense disparity map follow (Middlebury SDK: bad-0.5/1/2/4 %, avgerr, rms,
A50/A90/A95/A99; KITTI: D1 %, error > 3 px and > 5 % of the true disparity), each with the density it was
measured at (the share of the GT pixels the map covers; unknown pixels are not filled), over the kept regions
and over the whole frame, on all GT pixels and on the non-occluded ones where the data has a mask (MiddEval3
mask0nocc.png, KITTI disp_noc). Errors are in the data's native pixels, so the thresholds are the published
ones even with --size (an error measured at 320 px wide is scaled by native width / 320). The table shows
bad2n / bad2 (bad-2 % over the kept regions, non-occluded / all GT), avgerr (px), D1 % and dens; --json rows
carry every metric (map_*/kept_* keys, and per object); rectified pairs and the paper's range rule
(--preset paper, --set depth.rule=paper) have none.

PATH is a scene folder of any shared format (MiddEval3, Middlebury 2001-2006, KITTI, OpenCV aloe), a folder of
scene folders (or the shared data folder), a pair list ('LEFT RIGHT', 'LEFT RIGHT FOCAL_PX BASELINE_M
[DOFFS_PX]' or a scene folder per line; # comments; paths relative to the list's folder) or svs-depth capture's
index.jsonl. Every pair keeps its own calibration; a scene without a measured one is scored with a nominal one
for truth and estimate alike (its metres nominal): it is marked NOMINAL in the calib column and its accuracy
reported apart from the headline means. A listed pair without ground truth is ranged in the metres estimate
gives it (the SVS model, or --focal-px / --baseline-m, either alone). A KITTI training folder stands for each of
its frames. Every row names its calibration and source ("calibration" in the JSON; a list after the table).

Configuration: --preset default|paper, or --config FILE.toml, then any --set KEY=VALUE with a dotted field of
the pipeline configuration: segmentation.kernel_size, segmentation.num_keep, surf.metric_threshold,
surf.max_keypoints, max_ratio, mutual, refine_matches (true/false), ransac_threshold_px, rectify,
depth.rule (dense/paper), dense.window_size, dense.uniqueness_ratio, seed, ... (the same keys as sweep files).
"""

EPILOG = """\
examples:
  svs-depth eval ../shared/data/middlebury_eval3_Q --size 320x240
  svs-depth eval ../shared/data/middlebury_eval3_Q --preset paper --json | tail -1
  svs-depth eval scenes.txt --set segmentation.kernel_size=7 --set max_ratio=0.7 --db results.sqlite
  svs-depth eval ../shared/data/middlebury_eval3_Q --disparity-out maps/   (maps/Teddy/disp0SVSTorch.pfm, ...)

--json: one JSON object per pair, then one summary object as the last line, with pairs, failed,
acc_r_min_pct, acc_r_max_pct, acc_objects_pct (over the pairs with their own calibration), nominal_calibration
(the others, apart: their count, means and first 100 names), pairs_per_s (loading included), the mean disparity
errors, the mean stereo metrics (over every pair that has them: they are disparities, whatever the calibration),
the failures, and what ran: preset, overrides, size and config (every setting in effect). Pixels: the
dense_* and sparse_* errors are in the pixels the pipeline ran at (--size), the map_* and kept_* metrics in
the data's native pixels, at the published thresholds. --db adds the
rows to a results store (as svs-depth sweep does; a pair already stored for the same configuration keeps its
row, but an ERROR, BAD_INPUT or TOO_SMALL row, which is replaced: said at the end, with how many of the rows kept
differ from this run's, and in JSON as db_rows_kept, db_rows_kept_differing), for svs-depth results.
exit status: 0 done (failed pairs are counted in the output); 2 bad arguments, a missing PATH, or a bad --set;
1 an output that cannot be written (--disparity-out or --db on a full disk, or --db kept locked over 60 s by
another program: the option and the file named; the rows a --db store committed are kept), or a --disparity-out
map left unwritten rather than write over a ground truth, an input image or another pair's map (each warned;
every pair is still evaluated, exit 1 at the end).
Ctrl-C or SIGTERM: exit 130 / 143, after the summary of the pairs done (in JSON with "interrupted": true and
pairs_listed).
"""


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("eval", help=HELP, description=DESCRIPTION, epilog=EPILOG,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("paths", nargs="+", metavar="PATH", help="scene folder, folder of scenes, list, index.jsonl")
    parser.add_argument("--size", metavar="WxH", help="resample every pair to this size first (e.g. 320x240; at most "
                                                      "16 megapixels, and a pair over 16 megapixels needs it)")
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--preset", choices=("default", "paper"), default="default",
                       help="'default': the best measured settings; 'paper': the paper's MATLAB defaults")
    group.add_argument("--config", metavar="FILE.toml", help="a configuration file: preset = ... and dotted keys")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="sets",
                        help="override one setting, e.g. segmentation.kernel_size=7 (repeatable)")
    parser.add_argument("--batch-size", type=positive_int, default=8,
                        help="pairs read at a time, run at most 32 pairs of 320x240 (2.5 megapixels) at a time "
                             "(default: 8, the fastest measured, see estimate; a larger batch, and the next one "
                             "read meanwhile, hold more pairs in memory)")
    parser.add_argument("--focal-px", type=focal_px_value,
                        help="focal length of listed file pairs without one, pixels (default: the SVS model)")
    parser.add_argument("--baseline-m", type=baseline_m_value, help="baseline of those pairs, metres (default: SVS)")
    parser.add_argument("--doffs-px", type=doffs_px_value, default=0.0,
                        help="doffs of those pairs, pixels (default: 0)")
    add_calibration_option(parser, "listed file pairs (one with its own FOCAL_PX BASELINE_M is BAD_INPUT)",
                           kept_beside=True)
    parser.add_argument("--db", metavar="FILE.sqlite", type=output_file,
                        help="also store every row in this results file")
    parser.add_argument("--json", action="store_true", help="JSON lines: one per pair, the summary last")
    add_disparity_export_options(parser)
    parser.set_defaults(func=run)


def _number(value, digits: int = 1, scale: float = 1.0) -> str:
    return "-" if value is None else f"{value * scale:.{digits}f}"


def format_row(e) -> str:
    numbers = [(e.r_min_m, 3, 7), (e.real_r_min_m, 3, 7), (e.acc_r_min_pct, 1, 6), (e.r_max_m, 3, 7),
               (e.real_r_max_m, 3, 7), (e.acc_r_max_pct, 1, 6), (e.acc_objects_pct, 1, 6), (e.dense_within_1px, 2, 6),
               (e.inlier_precision, 2, 6), (e.kept_nocc_bad2_pct, 1, 6), (e.kept_all_bad2_pct, 1, 6),
               (e.kept_all_avgerr_px, 2, 6), (e.kept_all_d1_pct, 1, 5), (e.kept_all_density, 2, 5)]
    return (f"{e.name[:28]:<28} {e.status:<{STATUS_WIDTH}} "
            + " ".join(f"{_number(value, digits):>{width}}" for value, digits, width in numbers)
            + f" {e.time_s:6.3f} {_calibration_mark(e):<7}")


def _calibration_mark(e) -> str:
    """The table's calib column: ``own`` (the data's or the user's calibration), ``NOMINAL`` (none shipped:
    scored with a nominal one, apart from the headline means), ``model`` (the SVS model assumed, for some or all
    of it, as ``estimate`` ranges such a pair) or ``-`` (not loaded)."""
    if e.calibrated is None:
        return "-"
    nominal = e.calibration is not None and e.calibration["source"].startswith("nominal")
    return "own" if e.calibrated else "NOMINAL" if nominal else "model"


def format_calibrations(groups: dict[str, list]) -> list[str]:
    """Which calibration the metres use, one line per distinct one (with the pairs that use it): ``groups`` maps
    each one's text to its first pair's name and its count of pairs (:class:`Tally`)."""
    lines = []
    for line, (first, count) in groups.items():
        who = first if count == 1 else f"{count} pairs ({first}, ...)"
        lines.append(f"{who}: {line}")
    return lines


class Tally:
    """What eval's summary, its calibration lines and its note of the kept rows need of the rows, gathered as each
    row comes (:meth:`add`): a row is dropped once printed and stored. Why: every row of a run was held to its end
    for them (an audit of bulk runs: about 4.4 kB a pair, a store's rows held again for its note of kept rows)."""

    def __init__(self, before: dict[str, tuple]) -> None:
        from ..evaluation.running_summary import RunningSummary

        self.count, self.summary, self.kept = 0, RunningSummary(), KeptRows(before)
        self.calibrations: dict[str, list] = {}  # its text: [the first pair's name, how many pairs]

    def add(self, pair_id: str, evaluation) -> None:
        from ..data import format_calibration

        self.count += 1
        self.summary.add(evaluation)
        self.kept.add(pair_id, evaluation)
        if evaluation.calibration is not None:
            self.calibrations.setdefault(format_calibration(evaluation.calibration), [evaluation.name, 0])[1] += 1


#: The widest status (DEGENERATE_RECTIFICATION): a narrower column shifted every number after it (an audit).
STATUS_WIDTH = 24
HEADER = (f"{'pair':<28} {'status':<{STATUS_WIDTH}} {'R_min':>7} {'real':>7} {'Acc %':>6} {'R_max':>7} {'real':>7} "
          f"{'Acc %':>6} {'obj %':>6} {'d<=1':>6} {'prec':>6} {'bad2n':>6} {'bad2':>6} {'avgerr':>6} {'D1 %':>5} "
          f"{'dens':>5} {'time s':>6} {'calib':<7}")


def _stereo_lines(summary: dict) -> list[str]:
    """The summary's stereo metrics, one line per scope (kept regions or whole frame; all or non-occluded GT)."""
    lines = ["stereo metrics of the dense map (means over pairs, native px; bad-t and D1 in % of the pixels "
             "measured, at the density shown):"]
    for scope, label in (("kept_all", "kept regions, all GT"), ("kept_nocc", "kept regions, non-occluded"),
                         ("map_all", "whole frame, all GT"), ("map_nocc", "whole frame, non-occluded")):
        if summary.get(f"{scope}_density") is None:
            lines.append(f"  {label}: -")
            continue

        def value(metric: str, digits: int = 1) -> str:
            return _number(summary[f"{scope}_{metric}"], digits)

        count = summary[f"{scope}_pairs"]
        lines.append(f"  {label} ({count} pair{'' if count == 1 else 's'}): density {value('density', 3)}, "
                     f"bad-0.5/1/2/4 {value('bad0_5_pct')}/{value('bad1_pct')}/{value('bad2_pct')}/"
                     f"{value('bad4_pct')}, avgerr {value('avgerr_px', 2)}, rms {value('rms_px', 2)}, A50/90/95/99 "
                     f"{value('a50_px', 2)}/{value('a90_px', 2)}/{value('a95_px', 2)}/{value('a99_px', 2)}, "
                     f"D1 {value('d1_pct')}")
    return lines


def format_summary(summary: dict) -> list[str]:
    nominal = (summary.get("nominal_calibration") or {}).get("scored") or 0
    pairs = f"{summary['pairs']} pair{'' if summary['pairs'] == 1 else 's'}"
    lines = [f"{pairs}, {summary['failed']} failed, {summary['scored']} scored against ground "
             f"truth with their own calibration" + (f" and {nominal} with a NOMINAL one (apart, below)" if nominal
                                                    else "") + f"; {_number(summary['pairs_per_s'], 2)} pairs/s",
             f"mean Acc (Eq. 9) over {summary['scored']} pair{'' if summary['scored'] == 1 else 's'} with their own "
             "calibration: R_min "
             f"{_number(summary['acc_r_min_pct'])} %, R_max "
             f"{_number(summary['acc_r_max_pct'])} %, objects {_number(summary['acc_objects_pct'])} %",
             f"dense disparity: median error {_number(summary['dense_error_median_px'], 2)} px, within 1 px "
             f"{_number(summary['dense_within_1px'], 3)}, within 3 px {_number(summary['dense_within_3px'], 3)}; "
             f"inliers: median error {_number(summary['sparse_error_median_px'], 2)} px, precision "
             f"{_number(summary['inlier_precision'], 3)}",
             *_nominal_summary(summary.get("nominal_calibration")),
             *_no_truth_line(summary, nominal),
             *_stereo_lines(summary),
             "statuses: " + ", ".join(f"{k} {v}" for k, v in summary["statuses"].items())]
    for failure in summary["failures"]:
        lines.append(f"  failed: {failure['name']}: {failure['status']}"
                     + (f": {failure['reason']}" if failure["reason"] else ""))
    return lines


def _no_truth_line(summary: dict, nominal: int) -> list[str]:
    """Why nothing was scored, where pairs ran and none had ground truth (an audit: "0 scored", unexplained); which
    ranged pairs were not scored, where others were (a scene whose truth had gone missing read as an OK row)."""
    unscored = summary.get("unscored") or {"count": 0, "names": []}
    if (summary["scored"] or nominal) and unscored["count"]:
        count = unscored["count"]
        return [f"{count} ranged pair{'' if count == 1 else 's'} not scored (no ground truth, or none where "
                f"{'it was' if count == 1 else 'they were'} ranged; not in the means): "
                f"{_first_named(unscored['names'], count)}"]
    if summary["scored"] or nominal or summary["pairs"] <= summary["failed"]:
        return []
    return ["none of the ranged pairs has ground truth (listed file pairs and captured frames carry none; a scene "
            "folder's disparity map is its truth): their distances are in the rows above, as estimate gives them"]


def _nominal_summary(nominal: dict | None) -> list[str]:
    if not nominal or not nominal["scored"]:
        return []
    return [f"apart, {nominal['scored']} scored with a NOMINAL calibration (their data ship none; not in the means "
            f"above): R_min {_number(nominal['acc_r_min_pct'])} %, R_max {_number(nominal['acc_r_max_pct'])} %, "
            f"objects {_number(nominal['acc_objects_pct'])} %"]


def disparity_export(args: argparse.Namespace, config, sources=()):
    """The :class:`~svs_torch.evaluation.export.DisparityExport` of ``--disparity-out`` (its folder made, or
    the error raised, before any work), or None without the option. Its names are claimed from the whole list of
    ``sources`` first (:func:`~svs_torch.cli.estimate_report.claim_export_names`)."""
    if not args.disparity_out:
        return None
    from pathlib import Path

    from ..core.errors import InputError
    from ..evaluation.export import DisparityExport

    if config.depth.rule != "dense":
        raise InputError("--disparity-out: expected the dense range rule (the paper's rule measures no dense map), "
                         f"got depth.rule={config.depth.rule}")
    from .estimate_report import claim_export_names

    export = DisparityExport(Path(args.disparity_out), args.disparity_format, args.method_name)
    export.prepare()
    claim_export_names(args, sources, export)
    return export


#: The most names a line of eval's lists (the pairs listed twice, the pairs not scored): a list of 400 scenes given
#: twice was a 7 kB line of names.
NAMES_SHOWN = 5


def _first_named(names: list[str], count: int) -> str:
    """The first :data:`NAMES_SHOWN` of ``names`` and how many more of the ``count`` there are."""
    return ", ".join(names[:NAMES_SHOWN]) + (f" and {count - NAMES_SHOWN} more" if count > NAMES_SHOWN else "")


def run(args: argparse.Namespace) -> int:
    from ..core.workers import imports_without_collection

    with imports_without_collection():  # see there: the imports' objects are frozen
        from dataclasses import replace

        from ..data import read_pair_sources
        from ..data.pair_list import unique_sources
        from ..core.errors import InputError
        from ..evaluation import EvalSetup
        from ..evaluation.export import resized_maps_note
        from ..evaluation.overrides import config_to_dict, resolve_config

    resolve_export_options(args)
    size_wh = checked_size(args.size)  # over 16 megapixels refused, as estimate's (8192x8192 was taken: an audit)
    check_no_manual_calibration(args)
    if args.calibration and args.db:  # the store's pair and configuration ids do not record a rig yet
        raise InputError("--calibration, --db: a results store does not record the calibration; run without --db")
    config, preset, overrides = resolve_config(args.preset, args.config, args.sets)
    sources, repeated = unique_sources(read_pair_sources(args.paths, "path"))
    calibration = eval_rig_calibration(args, sources)
    calibrated = with_calibrated_rectification(config, args)  # a --set rectify=... still wins
    config = replace(calibrated, rectify=config.rectify) if "rectify" in overrides else calibrated
    if repeated:  # once each, as a sweep and a results store count them: a repeat would weigh twice in the means
        names = list(dict.fromkeys(source.name for source in repeated))  # the first few (a list given twice: 400)
        print(f"eval: {len(names)} pair{'s' * (len(names) != 1)} listed more than once, evaluated once: "
              f"{_first_named(names, len(names))}", file=sys.stderr)
    check_no_option_calibration_in_store(args, sources)
    export = disparity_export(args, config, sources)  # its folder made once the arguments are known to be good
    store, run_id, sweep_config = store_beside_export(export, args, preset, overrides, size_wh, sources)
    if export is not None and size_wh is not None:  # maps the official tools refuse, said (export.resized_maps_note)
        warnings.warn(resized_maps_note(size_wh), RuntimeWarning, stacklevel=1)
    if not args.json:
        print(HEADER)
    setup = EvalSetup(config, size_wh, args.focal_px, args.baseline_m, args.doffs_px, calibration,
                      rig_provenance(args.calibration or ""), max_pixels=MAX_PIXELS)
    # What ran, on the JSON summary: the summary line alone did not say (an audit of configuration values).
    ran = {"preset": preset, "overrides": overrides,
           "size": "native" if size_wh is None else f"{size_wh[0]}x{size_wh[1]}", "config": config_to_dict(config)}
    tally = Tally(rows_stored_before((store, run_id, sweep_config)))
    started = time.perf_counter()
    try:
        _evaluate_all(args, sources, setup, export, (store, run_id, sweep_config), tally)
    except (KeyboardInterrupt, Terminated):
        if tally.count:  # the pairs done are summarized, said to be a part: a long run stopped still tells its means
            _print_summary(args, tally, started, ran, len(sources))
        raise
    counts, note = tally.kept.note(args.db)
    _print_summary(args, tally, started, {**ran, **counts})
    if note:  # after the summary, where a user reads last
        print(note, file=sys.stderr)
    warn_capture_marks([capture_fields(source) for source in sources], len(sources))  # (as estimate --pairs)
    return 0


def _print_summary(args: argparse.Namespace, tally: Tally, started: float, ran: dict, listed: int | None = None
                   ) -> None:
    """The summary of the rows of ``tally`` (begun at ``started``, a perf_counter), last on stdout, in JSON with
    ``ran`` (preset, overrides, size, config). With ``listed`` (interrupted), of the pairs done, said so:
    ``interrupted`` and ``pairs_listed`` in JSON, a first line in text (an interrupted --json run ended on a pair's
    row)."""
    summary = tally.summary.summary(time.perf_counter() - started)
    if listed is not None:
        summary = {**summary, "interrupted": True, "pairs_listed": listed}
    if args.json:
        print(dumps_strict({**summary, **ran}), flush=True)
        return
    lines = format_calibrations(tally.calibrations) + format_summary(summary)
    if listed is not None:
        lines.insert(0, f"interrupted: the summary of the {tally.count} of {listed} pairs evaluated")
    print("\n".join(lines), flush=True)


def _evaluate_all(args: argparse.Namespace, sources: list, setup, export, stored_in: tuple, tally: Tally) -> None:
    """Evaluate ``sources`` batch by batch, each row printed as it comes, counted in ``tally`` and, with each batch's
    rows, committed to the ``--db`` store of ``stored_in`` (store, run id, sweep configuration), which is closed
    after; then dropped.
    Interrupted (Ctrl-C, SIGTERM), it says what was saved: it said only "interrupted", and a user could not tell
    whether the store kept the rows of the pairs done (an audit of interrupts)."""
    from dataclasses import asdict

    from ..evaluation import evaluate_pairs
    from ..evaluation.metrics import UNRUN_STATUSES
    from .estimate_report import forget_unrun_map

    store, run_id, sweep_config = stored_in
    block, rows = [], 0
    try:
        with Progress(len(sources), "eval") as bar:
            for source, evaluation in evaluate_pairs(sources, setup, args.batch_size, bar.update,
                                                     export.write if export is not None else None):
                tally.add(source.pair_id, evaluation)
                block.append((source.pair_id, evaluation))
                if export is not None and evaluation.status in UNRUN_STATUSES:
                    forget_unrun_map(args, source, evaluation.status, export)
                if len(block) == args.batch_size or tally.count == len(sources):
                    if store is not None:
                        with options_named(db="--db"):  # a disk that fills mid-run named "db:" (an audit)
                            store.write_task(sweep_config.config_id, run_id, block)
                        rows += len(block)
                    block = []
                line = (dumps_strict({"left": source.left, "right": source.right, **capture_fields(source),
                                      **asdict(evaluation)})
                        if args.json else format_row(evaluation))
                bar.write(line, file=sys.stdout)
    except (KeyboardInterrupt, Terminated):
        say_saved(args, rows, tally.count, len(sources))
        raise
    finally:
        if store is not None:
            store.close()
