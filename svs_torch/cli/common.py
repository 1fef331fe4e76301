"""What every ``svs-depth`` command shares: option types that refuse bad values with one line, the figure option,
the smallest pair the pipeline can range, and strict JSON output.

Only the standard library is imported here, so that ``svs-depth --help`` stays fast.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
from typing import Any

__all__ = [
    "MAX_SEED", "MIN_SIDE_PX", "add_disparity_export_options", "add_figure_option", "check_outputs_apart",
    "dumps_strict", "finite_float", "non_negative_float", "non_negative_int", "options_named", "output_file",
    "output_folder", "positive_float", "positive_int", "resolve_export_options", "seed_int", "timeout_seconds",
    "too_small_reason", "unit_interval_float",
]

#: The smallest width and height the feature stage handles: SURF's first octave needs 5 pixels per side for its
#: 3 x 3 x 3 non-maximum suppression (smaller pairs get the status TOO_SMALL, never a crash).
MIN_SIDE_PX = 5


def _number(text: str, kind: type) -> Any:
    try:
        value = kind(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}, got {text!r}") \
            from None
    if kind is float and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def finite_float(text: str) -> float:
    """argparse type: a finite number (no ``nan``, ``inf``)."""
    return _number(text, float)


def positive_float(text: str) -> float:
    """argparse type: a finite number greater than zero."""
    value = _number(text, float)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a finite positive number, got {text!r}")
    return value


def timeout_seconds(text: str) -> float:
    """argparse type of a reply timeout: over 0 and at most a day (1e10 s failed deep inside: over the platform's
    longest wait, threading.TIMEOUT_MAX)."""
    value = positive_float(text)
    if value > 86400:
        raise argparse.ArgumentTypeError(f"expected seconds over 0 and at most 86400 (a day), got {text!r}")
    return value


def non_negative_float(text: str) -> float:
    """argparse type: a finite number, zero or more."""
    value = _number(text, float)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0, got {text!r}")
    return value


def unit_interval_float(text: str) -> float:
    """argparse type: a number in (0, 1]."""
    value = _number(text, float)
    if not 0 < value <= 1:
        raise argparse.ArgumentTypeError(f"expected a number in (0, 1], got {text!r}")
    return value


def positive_int(text: str) -> int:
    """argparse type: an integer of at least 1."""
    value = _number(text, int)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


#: The most pairs a capture or guide run takes (about 58 days at 20 pairs a second): a count of 10^20 was taken and
#: the progress line promised an ETA of 6e18 s (an audit).
MAX_PAIRS = 100_000_000


def pair_count(text: str, least: int = 1) -> int:
    """argparse type of ``--count``: a number of pairs, ``least`` to :data:`MAX_PAIRS`."""
    value = _number(text, int)
    if not least <= value <= MAX_PAIRS:
        raise argparse.ArgumentTypeError(f"expected a number of pairs from {least} to {MAX_PAIRS}, got {text!r}")
    return value


def pair_count_or_zero(text: str) -> int:
    """argparse type of guide's ``--count``: 0 (until interrupted) to :data:`MAX_PAIRS`."""
    return pair_count(text, least=0)


def noise_levels(text: str) -> float:
    """argparse type of ``--emulator-noise``: a sensor noise σ in 8-bit levels, 0 to 255 (1e6 was taken, an audit)."""
    value = _number(text, float)
    if not 0 <= value <= 255:
        raise argparse.ArgumentTypeError(f"expected a noise σ in 8-bit levels, 0 to 255, got {text!r}")
    return value


def non_negative_int(text: str) -> int:
    """argparse type: an integer of at least 0."""
    value = _number(text, int)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}")
    return value


#: The most re-sent ``I`` commands per frame (``--retries``): each waits up to a frame's whole timeout, so ten already
#: let a dead board hold a run for tens of seconds before it is named.
MAX_RETRIES = 10
DEFAULT_RETRIES = 2  # LinkConfig.max_retries; a literal so --help needs no capture import


def link_retries(text: str) -> int:
    """argparse type of ``--retries``: re-sent grabs per frame, 0 to :data:`MAX_RETRIES`."""
    value = _number(text, int)
    if not 0 <= value <= MAX_RETRIES:
        raise argparse.ArgumentTypeError(f"expected a number of retries from 0 to {MAX_RETRIES}, got {text!r}")
    return value


def quality_digit(text: str) -> int:
    """argparse type of ``--quality``: the boards' JPEG quality digit, 1 (best) to 8 (worst) (``int`` said only
    "invalid int value: '4.5'", not what was expected: an audit)."""
    value = int(text) if text.strip().lstrip("+").isdecimal() else 0
    if not 1 <= value <= 8:
        raise argparse.ArgumentTypeError(f"expected a JPEG quality digit, 1 (best) to 8 (worst), got {text!r}")
    return value


def add_retries_option(parser: argparse.ArgumentParser) -> None:
    """``--retries N``: how often a board's grab is sent again after a silent or broken reply
    (``LinkConfig.max_retries``)."""
    parser.add_argument("--retries", type=link_retries, default=DEFAULT_RETRIES, metavar="N",
                        help="times a board's grab is sent again after a silent or broken reply (no header, a frame "
                             "cut short or failing its checks), "
                             f"0 to {MAX_RETRIES}: more for a flaky radio link, 0 to hear of a lost frame at once "
                             f"(default: {DEFAULT_RETRIES})")


#: The largest seed: RANSAC seeds and torch generators are 64-bit signed integers.
MAX_SEED = 2**63 - 1


def seed_int(text: str) -> int:
    """argparse type: a seed, an integer from 0 to 2**63 - 1."""
    value = _number(text, int)
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"expected an integer from 0 to {MAX_SEED}, got {text!r}")
    return value


@contextlib.contextmanager
def options_named(**options: str):
    """Re-raise a library :class:`~svs_torch.core.errors.InputError` that names a configuration field
    (``kernel_size: expected ...``) as naming the option the user typed (``--kernel-size: expected ...``)."""
    from ..core.errors import InputError

    try:
        yield
    except InputError as error:
        field, colon, reason = str(error).partition(":")
        if colon and field in options:
            raise InputError(f"{options[field]}:{reason}") from None
        raise
    except OSError as error:  # a full disk under the store: "db: cannot write ..." named the argument too
        field, colon, reason = (error.strerror or "").partition(":")
        if colon and field in options and error.filename is None:
            raise OSError(error.errno, f"{options[field]}:{reason}") from None
        raise


def output_file(text: str) -> str:
    """argparse type: an output file name that is not empty. Why: ``--masks-out "$OUT"`` with OUT unset ran,
    wrote nothing and exited 0."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"expected a file name, got {text!r}")
    return text


def output_folder(text: str) -> str:
    """argparse type: an output folder name that is not empty (``--disparity-out "$OUT"`` with OUT unset)."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"expected a folder name, got {text!r}")
    return text


def check_outputs_apart(outputs: list[tuple[str, str | None]], inputs: list[tuple[str, str | None]]) -> None:
    """Refuse, before any work, two outputs ``(option, path)`` at one file and an output that is one of the
    ``inputs`` ``(name, path)`` (None paths are skipped). Why: ``segment L.png R.png --figure L.png`` wrote the
    figure over the left image (exit 0), ``calibrate --pairs list.txt --out list.txt`` the calibration over its
    list; the next run read the figure as the image."""
    import os

    from ..core.dataset_files import files_read_with
    from ..core.errors import InputError

    named = [(option, path) for option, path in outputs if path]
    read = [file for name, source in inputs for file in files_read_with(source, name)] if named else []
    for number, (option, path) in enumerate(named):
        for other_option, other in named[:number]:
            if os.path.realpath(path) == os.path.realpath(other):
                raise InputError(f"{option}: the same file as {other_option} ({path}): name two files")
        for file, what in read if os.path.exists(path) else ():
            if os.path.samefile(path, file):
                raise InputError(f"{option}: {path} is {what}: it would be written over")


class _FigureAction(argparse.Action):
    """Store the figure file and the option name the user typed, so that an error names it."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        if not values.strip():  # named as typed (argparse's type error would say "--figure/--plot/--out")
            parser.error(f"{option_string or '--figure'}: expected a file name, got {values!r}")
        setattr(namespace, self.dest, values)
        namespace.figure_option = option_string or "--figure"


def add_figure_option(parser: argparse.ArgumentParser, help_text: str, *aliases: str, default: str | None = None,
                      kinds: str = ".png, .jpg, .bmp or .tif"):
    """``--figure FIG.png`` (the one name for a figure file across commands) with the command's old names as
    aliases (``--plot``, ``--out``), all stored in ``args.figure``; ``args.figure_option`` is the name typed."""
    default_text = f" (default: {default})" if default else ""
    parser.set_defaults(figure_option="--figure")
    parser.add_argument("--figure", *aliases, dest="figure", metavar="FIG.png", default=default,
                        action=_FigureAction,
                        help=f"{help_text}{default_text}; {kinds}"
                             + (f" (also {', '.join(aliases)})" if aliases else ""))


def _method_name(text: str) -> str:
    """argparse type: a method name for Middlebury's file names (as ``evaluation.export.METHOD_NAME``)."""
    if not (1 <= len(text) <= 64 and all(c.isascii() and (c.isalnum() or c in "_-") for c in text)):
        raise argparse.ArgumentTypeError(f"expected 1-64 letters, digits, '_' or '-', got {text!r}")
    return text


def add_disparity_export_options(parser: argparse.ArgumentParser) -> None:
    """``--disparity-out DIR``, ``--disparity-format`` and ``--method-name`` of ``eval`` and ``estimate``."""
    group = parser.add_argument_group("disparity maps out (svs_torch/evaluation/export.py)")
    group.add_argument("--disparity-out", metavar="DIR", type=output_folder,
                       help="write each pair's dense disparity map into DIR (made if missing; its parent must "
                            "exist), at the size the pipeline ran on (with --size, a size the SDK and the KITTI "
                            "devkit do not score), unmeasured pixels unknown; a pair the pipeline rectified has its "
                            "map brought back to the left image's pixels (one --calibration rectified stays in "
                            "rectified pixels); needs the dense range rule")
    group.add_argument("--disparity-format", choices=("middlebury", "kitti"),
                       help="'middlebury': DIR/<scene>/disp0<NAME>.pfm (float32, +inf unknown) and "
                            "time<NAME>.txt (seconds), the MiddEval3 SDK's layout (default; the maps are sparse, "
                            "and Middlebury names a sparse result disp0<NAME>_s.pfm: --method-name SVSTorch_s); "
                            "'kitti': DIR/<pair>.png, uint16 = disparity x 256, 0 unknown, the KITTI devkit's")
    group.add_argument("--method-name", metavar="NAME", type=_method_name,
                       help="NAME in Middlebury's file names (letters, digits, _ and -; default: SVSTorch); "
                            "the KITTI layout's have none")


def resolve_export_options(args: argparse.Namespace) -> None:
    """``--disparity-format`` and ``--method-name`` given without ``--disparity-out`` are refused (they ran
    without effect, exit 0), and ``--method-name`` with the KITTI layout, whose names hold none; their defaults
    filled in where it is given."""
    from ..core.errors import InputError

    given = [name for name, value in (("--disparity-format", args.disparity_format),
                                      ("--method-name", args.method_name)) if value is not None]
    if given and not args.disparity_out:
        raise InputError(f"{given[0]}: given without --disparity-out, whose files it names")
    if args.method_name is not None and args.disparity_format == "kitti":  # DIR/<pair>.png: it ran without effect
        raise InputError("--method-name: given with --disparity-format kitti, whose file names (DIR/<pair>.png) "
                         "carry no method name; drop it, or write the Middlebury layout")
    args.disparity_format = args.disparity_format or "middlebury"
    args.method_name = args.method_name or "SVSTorch"


def too_small_reason(size_hw: tuple[int, int]) -> str | None:
    """Why a pair of this (H, W) cannot be ranged, or None when it is large enough."""
    height, width = size_hw
    if min(height, width) < MIN_SIDE_PX:
        return f"image {width}x{height} is smaller than {MIN_SIDE_PX}x{MIN_SIDE_PX} pixels"
    return None


def _finite_or_none(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: _finite_or_none(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_or_none(item) for item in value]
    return value


def dumps_strict(value: Any) -> str:
    """JSON that strict parsers accept: NaN and ±inf become ``null`` (``json.dumps`` would write ``NaN``)."""
    return json.dumps(_finite_or_none(value), allow_nan=False)


class Terminated(BaseException):  # not an Exception: no broad handler on the way swallows it
    """SIGTERM arrived (``kill``, a service manager's stop), raised in the main thread by
    :func:`terminated_on_sigterm`."""

    status = 143  # the exit status (128 + SIGTERM); a subclass for another signal has its own


@contextlib.contextmanager
def terminated_on_sigterm():
    """SIGTERM raises :class:`Terminated` in the main thread meanwhile, so that a command stops as Ctrl-C stops it:
    an output being written is removed (``core.files.atomic_output``), a compiler it waits for is stopped, and
    ``main`` says so in one line (exit 143). Found by audits: ``guide`` ended at once and said nothing; ``results
    --figure`` left its temporary ``.r.png.*.tmp`` behind, and a first run's kernel compile its ``.so``. The previous
    handler is restored after; off the main thread (where Python keeps signals to itself), nothing."""
    import signal

    from ..core.workers import signal_handler

    def terminate(signum, frame):
        raise Terminated()

    with signal_handler(signal.SIGTERM, terminate):
        yield


STANDARD_OUTPUT = "standard output"


class _StdoutNamingErrors:
    """``sys.stdout`` whose write and flush errors name it (``OSError.filename``), everything else passed through."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except OSError as error:
            raise _named_stdout(error) from None

    def flush(self) -> None:
        try:
            self._stream.flush()
        except OSError as error:
            raise _named_stdout(error) from None

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


def _named_stdout(error: OSError) -> OSError:
    if error.filename is None:
        error.filename = STANDARD_OUTPUT
    return error


@contextlib.contextmanager
def stdout_errors_named():
    """Meanwhile a failed write to standard output says so: ``svs-depth eval ... --json > rows.jsonl`` on a full
    disk ends ``error: No space left on device: standard output``, not a bare ``No space left on device`` that
    names nothing (an audit's find: the figure, CSV and calibration writers named their files, stdout did not).
    ``sys.stdout`` is restored after."""
    import sys

    stream = sys.stdout
    sys.stdout = _StdoutNamingErrors(stream)
    try:
        yield
    finally:
        sys.stdout = stream
