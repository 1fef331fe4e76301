"""``svs-depth bench``: svs_torch against OpenCV and kornia doing the same work, whole process and in-process."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .common import positive_int

HELP = "benchmark: svs_torch vs OpenCV SIFT/ORB loops and kornia, from the command line and in-process"

DESCRIPTION = """\
Time svs_torch as a user meets it against rivals doing the same work, in one run on this machine:

- whole process: 'svs-depth estimate --pairs LIST --json' against OpenCV loops (decode, Otsu + opening + two
  largest regions, SIFT or ORB, ratio matching, findFundamentalMat RANSAC, StereoBM median over the regions),
  interleaved, the median of --repeats runs, on synthetic SVS pairs and (with the shared data) real pairs at
  320x240 and 640x480;
- in-process: stage times at B = 32, per-pair time from B = 1 to 128, peak memory per pair, one-pair latency
  (with the shared data also guide's, frame by frame on the real pairs as camera frames: median, 90th
  percentile, max), kornia's SIFTFeature + match_snn + RANSAC; and 'svs-depth --help' start-up.

Each rival's keypoints, matches, inliers and median R_min are printed beside its speed, so a win by doing less
shows. Takes a few minutes at the defaults.
"""

EPILOG = """\
examples:
  svs-depth bench                                  # synthetic pairs only
  svs-depth bench --data ../shared/data --json bench.json
  svs-depth bench --pairs 32 --repeats 1 --no-memory   # a quicker look (the in-process part as always)
"""


#: The most pairs an input set takes (--pairs): 8x the README's 512-pair run, about 0.6 MB of temporary PNG files a
#: pair with the shared data and hours of runs. 10^9 was taken and failed after the imports, an internal error
#: trying to allocate 40 GB for the synthetic scenes at once (an audit).
MAX_BENCH_PAIRS = 4096
# Each repeat runs every rival over every input set as whole processes (minutes at the default --pairs): a mistyped
# --repeats 300 was taken, 300 rounds of them.
MAX_BENCH_REPEATS = 100


def bench_pairs(text: str) -> int:
    """argparse type of ``--pairs``: 1 to :data:`MAX_BENCH_PAIRS`."""
    value = positive_int(text)
    if value > MAX_BENCH_PAIRS:
        raise argparse.ArgumentTypeError(f"expected 1 to {MAX_BENCH_PAIRS} pairs, got {text!r}")
    return value


def bench_repeats(text: str) -> int:
    """argparse type of ``--repeats``: 1 to :data:`MAX_BENCH_REPEATS`."""
    value = positive_int(text)
    if value > MAX_BENCH_REPEATS:
        raise argparse.ArgumentTypeError(f"expected 1 to {MAX_BENCH_REPEATS} runs, got {text!r}")
    return value


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("bench", help=HELP, description=DESCRIPTION, epilog=EPILOG,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", metavar="DIR", help="the shared data folder for real pairs (default: none, "
                                                      "synthetic pairs only)")
    parser.add_argument("--pairs", type=bench_pairs, default=64, metavar="N",
                        help=f"pairs per input set of the whole-process runs, 1 to {MAX_BENCH_PAIRS} (default: 64); "
                             "the in-process part "
                             "always runs its 128 synthetic pairs, B = 1 to 128 (about 4 GB at its peak)")
    parser.add_argument("--repeats", type=bench_repeats, default=3, metavar="N",
                        help=f"runs per rival, 1 to {MAX_BENCH_REPEATS}; the median is reported (default: 3)")
    parser.add_argument("--threads", type=positive_int, help="threads for every rival, at most the cores this "
                                                             "process may run on (default: 2, or those cores if "
                                                             "fewer)")
    parser.add_argument("--no-memory", action="store_true", help="skip the peak-memory child processes")
    parser.add_argument("--json", metavar="FILE", help="also write the full report with its metadata as JSON")
    parser.set_defaults(func=run)


def checked_threads(threads: int | None) -> int:
    """``--threads``, or its default of 2 (fewer on a machine with fewer cores), refused above the cores this process
    may run on. Why: ``svs-depth estimate`` takes no more threads than those cores, while the OpenCV loop took
    ``cv2.setNumThreads(999)``, its pool spawned up to 999 processes, the in-process part ran 999 torch threads on 2
    cores, and the report recorded 'threads 999' for all of them (an audit)."""
    from ..core.checks import InputError
    from ..core.workers import available_cores

    cores = available_cores()
    if threads is None:
        return min(2, cores)
    if threads > cores:
        raise InputError(f"--threads: expected 1 to {cores} (the cores this process may run on), got {threads}")
    return threads


def run(args: argparse.Namespace) -> int:
    from ..core.workers import imports_without_collection

    with imports_without_collection():  # see there: the imports' objects are frozen
        from ..evaluation.benchmark import format_tables, run_benchmark
        from ..core.checks import InputError
        from ..core.files import atomic_output, check_output_file, path_kind, write_errors_named
        from ..data import list_shared_pairs
        from .common import dumps_strict

    args.threads = checked_threads(args.threads)
    if args.data is not None and not args.data.strip():  # '' ran the synthetic set alone, unsaid (an audit)
        raise InputError(f"--data: expected a folder name, got {args.data!r}")
    data_dir = Path(args.data) if args.data is not None else None
    kind = path_kind(data_dir, "--data") if data_dir is not None else "folder"
    if kind != "folder":
        said = {"missing": "which does not exist", "file": "which is a file"}.get(kind, "a device or special file")
        raise InputError(f"--data: expected a folder, got {args.data!r}, {said}")
    if data_dir is not None and not list_shared_pairs(data_dir):  # else only the synthetic set ran, unsaid
        raise InputError(f"--data: no shared pair with ground truth in {args.data!r} (expected the shared data "
                         f"folder: middlebury_eval3_Q/, middlebury_2005_2006_third/, kitti/, ...)")
    if args.json is not None:  # '' too: an empty name was skipped in silence (an audit)
        check_output_file(args.json, "--json", (".json",), "a .json")  # before minutes of work, not after
    report = run_benchmark(args.pairs, args.repeats, args.threads, data_dir,
                           progress=lambda text: print(text, file=sys.stderr, flush=True),
                           memory=not args.no_memory)
    print(format_tables(report))  # first: a report that cannot be saved is still seen
    if args.json:
        # A full disk named the option and the file, not a temporary file or neither (an audit).
        with write_errors_named("--json", args.json), atomic_output(args.json, "w", encoding="utf-8") as stream:
            stream.write(dumps_strict(report) + "\n")
    return 0
