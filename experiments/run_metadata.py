"""What every experiment records beside its numbers: code version, library versions, machine and threads."""

from __future__ import annotations

import os
import platform
import sys
from pathlib import Path


def default_data_dir() -> str:
    """The shared data: ``$SVS_TORCH_DATA``, else ``../shared/data`` beside the repository (as the tests)."""
    return os.environ.get("SVS_TORCH_DATA", str(Path(__file__).resolve().parents[1].parent / "shared" / "data"))


def shared_data_folder(text: str) -> str:
    """An ``argparse`` type for ``--data``: a folder holding one of the shared data sets or more
    (:data:`svs_torch.data.datasets.SHARED_DATA_FOLDERS`, MANIFEST §1). An empty folder, or one data set's own
    folder (``shared/data/kitti``), ran to empty or partial tables, written, exit 0, and some scripts to a traceback
    (an audit)."""
    import argparse

    from svs_torch.data.datasets import SHARED_DATA_FOLDERS

    path = Path(text)
    if not path.is_dir():
        if text == default_data_dir():  # the default, not there: a run that reads no data runs, one that does says so
            return text
        raise argparse.ArgumentTypeError(f"expected the shared data folder, got {text!r}: no such folder")
    if not any((path / name).is_dir() for name in SHARED_DATA_FOLDERS):
        raise argparse.ArgumentTypeError(f"expected the shared data folder (holding {', '.join(SHARED_DATA_FOLDERS)}, "
                                         f"or some of them), got {text!r}, which holds none")
    return text


def shared_data_path(text: str) -> Path:
    """:func:`shared_data_folder`, as a :class:`Path`."""
    return Path(shared_data_folder(text))


def add_data_option(parser, kind=str) -> None:
    """``--data``, the shared data folder (:func:`default_data_dir`), checked when parsed (:func:`shared_data_folder`),
    as ``kind`` (``str`` or ``Path``)."""
    parser.add_argument("--data", type=shared_data_path if kind is Path else shared_data_folder,
                        default=default_data_dir(), help="the shared data folder (default: %(default)s)")


def output_path(text: str) -> Path:
    """An ``argparse`` type for a report file (``--json``, ``--markdown``): the checks every svs-depth output gets
    (:func:`svs_torch.core.files.check_output_file`: a file name, not a folder or device, in an existing folder a
    file can be written to), made when parsed, before any work (a 3-minute run once ended in a
    FileNotFoundError, its markdown unwritten)."""
    import argparse

    from svs_torch.core.errors import InputError
    from svs_torch.core.files import check_output_file

    try:
        return check_output_file(text, "file")
    except InputError as error:
        raise argparse.ArgumentTypeError(str(error).removeprefix("file: ")) from None


def use_two_threads() -> int:
    """Run torch on two threads, or fewer where ``OMP_NUM_THREADS`` asks (``svs_torch.core.workers.thread_budget``),
    for the scripts without ``--threads``; returns the count (an audit: they took two whatever the job was limited
    to)."""
    import torch

    from svs_torch.core.workers import thread_budget

    torch.set_num_threads(min(2, thread_budget()))
    return torch.get_num_threads()


def scene_limit(text: str) -> int | None:
    """An ``argparse`` type for ``--limit``: a count of scenes (or pairs) of at least 1, or 0 for all (None).
    Found by an audit: ``--limit -1`` ran all but the last scene in silence, and ``--limit 0`` meant "all" in some
    experiments and an empty table, exit 0, in others."""
    import argparse

    from svs_torch.cli.common import non_negative_int

    try:
        return non_negative_int(text) or None
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected a count of at least 1, or 0 for all, got {text!r}") from None


def size_list(form: str):
    """An ``argparse`` type for ``--sizes``: comma-separated sizes, each ``native`` or, for ``form`` "wxh", WxH
    (``320x240``), for "width", a width in pixels (``320``); the text is returned as given. Scripts differ (a size
    in the other form once ended in a ValueError traceback), so the message says which this one takes."""
    import argparse
    import re

    from svs_torch.core.camera import MAX_SIZE_PX

    pattern = r"\d+x\d+" if form == "wxh" else r"\d+"
    example = "320x240,native" if form == "wxh" else "320,native"

    def fits(part: str) -> bool:  # no side of 0 (a traceback or a refusal after the run began: an audit) or huge
        return bool(re.fullmatch(pattern, part)) and all(0 < int(side) <= MAX_SIZE_PX for side in part.split("x"))

    def parse(text: str) -> str:
        bad = [part for part in text.split(",") if part != "native" and not fits(part)]
        if bad or not text:
            raise argparse.ArgumentTypeError(f"expected comma-separated {'WxH sizes' if form == 'wxh' else 'widths'}"
                                             f" or native (e.g. {example}; sides 1 to {MAX_SIZE_PX}), got {text!r}")
        return text

    return parse


def comma_list(item, what: str):
    """An ``argparse`` type for comma-separated values (``--contrasts 1,0.5``), each checked by the ``argparse``
    type ``item`` and named ``what`` in the message; the text is returned as given. An audit: a bad value was a
    ValueError or KeyError traceback after minutes of work, or (NaN) a run that went on."""
    import argparse

    def parse(text: str) -> str:
        try:
            for part in text.split(","):
                item(part)
        except argparse.ArgumentTypeError as error:
            raise argparse.ArgumentTypeError(f"expected comma-separated {what}: {error}") from None
        return text

    return parse


def check_reports_apart(parser, args, inputs: tuple[tuple[str, str], ...] = ()) -> None:
    """Refuse, as ``parser``'s error, ``--json`` and ``--markdown`` at one file, or either at one of the files
    ``inputs`` (``(option, path)``) the run reads: the table was written over the report (or the report over the
    table, or over the weights evaluated) after the whole run, exit 0 (an audit)."""
    json_path, markdown_path = getattr(args, "json", None), getattr(args, "markdown", None)
    if json_path and markdown_path and Path(json_path).resolve() == Path(markdown_path).resolve():
        parser.error(f"argument --markdown: the file of --json, {str(markdown_path)!r}; the one would be written "
                     "over the other")
    for report_option, report in (("--json", json_path), ("--markdown", markdown_path)):
        for option, path in inputs:
            if report and path and Path(report).resolve() == Path(path).resolve():
                parser.error(f"argument {report_option}: the file {option} reads, {str(report)!r}")


def refuse_unread_options(parser, args, dests: list[str], when: str) -> None:
    """Refuse, as ``parser``'s error, the options of ``dests`` given a value other than their default in a run that
    does not read them (``when``: the runs that do). An audit: 'train_segmentation.py --pairs mine.txt' trained from
    scratch on the shared scenes, and 'train_nearness.py --num-synthetic 9' (no --steps) wrote the rule's weights,
    each recording the option as if it had been used."""
    given = ["--" + dest.replace("_", "-") for dest in dests if getattr(args, dest) != parser.get_default(dest)]
    if given:
        parser.error(f"{', '.join(given)}: only {when}; this run would not read {'them' if given[1:] else 'it'}")


def add_common_options(parser, *, data_type=str, threads: int | None = None, repeats: int | None = None,
                       sizes: str | None = None, sizes_form: str = "wxh", json: bool = False) -> None:
    """The options many experiments share, each with its help: ``--data`` (as ``data_type``), and where given
    ``--threads`` / ``--repeats`` (their defaults), ``--sizes`` (its default, in ``sizes_form``: :func:`size_list`)
    and ``--json``."""
    from svs_torch.cli.common import positive_int  # (--threads 0 was a RuntimeError traceback, --repeats 0 one after
    # the run's loading: an audit)

    add_data_option(parser, data_type)
    if threads is not None:
        parser.add_argument("--threads", type=positive_int, default=threads,
                            help="torch threads (default: %(default)s)")
    if repeats is not None:
        parser.add_argument("--repeats", type=positive_int, default=repeats,
                            help="timed runs of each; the median is reported (default: %(default)s)")
    if sizes is not None:
        kind = "WxH sizes" if sizes_form == "wxh" else "widths in pixels"
        parser.add_argument("--sizes", default=sizes, type=size_list(sizes_form),
                            help=f"comma-separated {kind} or native (default: %(default)s)")
    if json:
        parser.add_argument("--json", type=output_path, metavar="FILE", help="write the report as JSON to FILE")


def run_script(main) -> None:
    """Run an experiment's ``main()`` as a command: a refused input (``InputError``: a bad ``--set``, data folder,
    option value) is one line on stderr and exit status 2, not a traceback; Ctrl-C one line and exit status 130,
    as the command line's (a traceback from wherever the run was, an audit; each experiment writes its outputs
    whole or not at all)."""
    from svs_torch.core.errors import InputError

    try:
        main()
    except InputError as error:
        print(f"{Path(sys.argv[0]).name}: error: {error}", file=sys.stderr)
        raise SystemExit(2) from None
    except KeyboardInterrupt:
        print(f"{Path(sys.argv[0]).name}: interrupted", file=sys.stderr)
        raise SystemExit(130) from None


def write_text_whole(path: str | Path, text: str) -> None:
    """Write an experiment's report file (``--json``, ``--markdown``) whole, in UTF-8, or not at all, as
    :func:`write_report` writes both: ``Path.write_text`` emptied an earlier report of that name first, a full disk
    or a Ctrl-C while writing left it cut short, and it wrote "×" and "±" in the locale's encoding (an audit)."""
    from svs_torch.core.files import write_bytes_atomic

    write_bytes_atomic(path, text.encode("utf-8"))


def run_metadata(threads: int, **extra) -> dict:
    """Commit, versions (torch, kornia, OpenCV, numpy, Python), machine, CPU count and vector instructions (torch's
    CPU capability), thread count, OpenMP wait policy and load average at the time of the call, the ``command``
    (given, else :func:`script_command`), plus the experiment's own ``extra`` settings."""
    import cv2
    import kornia
    import numpy
    import torch

    from svs_torch.core.checkout import code_version, short_commit
    from svs_torch.core.workers import available_cores

    # The library's checkout as a sweep's store and the benchmark record it, "-dirty" where its files differ from
    # the commit: a table made on edited code read as one made at the commit (an audit).
    return {"commit": short_commit(), "code_version": code_version(), "torch": torch.__version__,
            "kornia": kornia.__version__, "opencv": cv2.__version__, "numpy": numpy.__version__,
            "python": sys.version.split()[0],
            "machine": platform.machine(), "cpus": os.cpu_count(), "cores_available": available_cores(),
            "threads": threads,
            # The vector instructions torch's CPU kernels use: a training run is bit for bit only on the same ones
            # (ATEN_CPU_CAPABILITY=avx2 on an AVX-512 machine moved train_segmentation.py's weights by 7.7e-4 in
            # 40 steps); the shipped obstacle_net.pt, which did not record them, is not reproduced here (an audit).
            "cpu_capability": torch.backends.cpu.get_cpu_capability(),
            "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"), "load_average": os.getloadavg(),
            "command": extra.pop("command", None) or script_command(), **extra}


def script_command() -> str | None:
    """How this process was started, where it is an experiment run as a script (``python experiments/NAME.py
    ...``), quoted for a shell; None where it is not (an experiment's ``main(argv)`` called in-process, whose
    arguments are not this process's). An audit found 12 experiments whose JSON said neither what was run nor
    with which options, a table that could not be made again from its own record."""
    script = Path(sys.argv[0]) if sys.argv and sys.argv[0] else None
    if script is None or script.suffix != ".py" or script.resolve().parent != Path(__file__).resolve().parent:
        return None
    return command_line(f"experiments/{script.name}", None)


def write_report(report: dict, table: str, json_path: Path | None, markdown_path: Path | None) -> None:
    """``report`` as JSON to ``json_path`` and ``table`` to ``markdown_path``, each where given, each written whole
    or not at all."""
    import json

    if json_path:
        write_text_whole(json_path, json.dumps(report, indent=1))
    if markdown_path:
        write_text_whole(markdown_path, table)


def command_line(script: str, argv: list[str] | None) -> str:
    """How ``script`` (``experiments/NAME.py``) was run: with ``argv``, or this process's arguments, quoted for a
    shell (``--conditions "jpeg q4"`` written unquoted failed when run again)."""
    import shlex
    import sys

    return shlex.join(["python", script, *(argv if argv is not None else sys.argv[1:])])


def report_rows(table: str, rows: list[dict], command: str, overrides: list[str], started_s: float,
                json_path: Path | None, markdown_path: Path | None) -> dict:
    """Print ``table``, and write it and the ``rows`` with the run's metadata (``command``, ``--set``'s
    ``overrides``, the time since ``started_s`` on ``time.perf_counter``) where asked; returns the report."""
    import time

    import torch

    print(table)
    report = {"metadata": run_metadata(torch.get_num_threads(), command=command, overrides=overrides,
                                        time_s=time.perf_counter() - started_s), "rows": rows}
    write_report(report, table, json_path, markdown_path)
    return report


def add_rendered_experiment_options(parser) -> None:
    """The options of the rendered-scene experiments (thin_obstacles.py, walker_floor.py, walker_heaps.py): ``--set``
    (repeatable), ``--no-rival``, ``--json`` and ``--markdown``."""
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="pipeline override")
    parser.add_argument("--no-rival", action="store_true", help="skip StereoSGBM")
    # Checked before the run, as every other experiment's (a 3-minute run ended in a FileNotFoundError: an audit)
    parser.add_argument("--json", type=output_path, metavar="FILE",
                        help="write the rows and the run's metadata as JSON")
    parser.add_argument("--markdown", type=output_path, metavar="FILE", help="write the table as markdown")


def rendered_experiment_setup(doc: str, argv: list[str] | None, extra_options=None):
    """A rendered-scene experiment's start (walker_floor.py, walker_heaps.py): its options parsed from ``argv``
    (:func:`add_rendered_experiment_options`, then ``extra_options(parser)`` where given; ``doc``'s first
    paragraph the description), the pipeline's
    configuration with ``--set``'s overrides (a bad one is the parser's error), the setting's name for the table,
    and the start time on ``time.perf_counter``."""
    import argparse
    import time

    from svs_torch.core.errors import InputError
    from svs_torch.evaluation.overrides import apply_overrides, parse_assignment
    from svs_torch.pipeline import PipelineConfig

    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    add_rendered_experiment_options(parser)
    if extra_options is not None:
        extra_options(parser)
    args = parser.parse_args(argv)
    check_reports_apart(parser, args)
    try:
        config = apply_overrides(PipelineConfig(), dict(parse_assignment(text) for text in args.set))
    except InputError as error:
        parser.error(str(error))
    return args, config, "default" + "".join(f", {text}" for text in args.set), time.perf_counter()
