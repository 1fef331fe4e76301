"""The ``svs-depth`` command line.

Each subcommand lives in its own module with ``add_parser(subparsers)`` and a ``run(args) -> int``; heavy
imports (torch, OpenCV) happen inside ``run`` so that ``svs-depth --help`` answers at once.

May import: every package of ``svs_torch``, and ``hw`` for ``--emulator`` (the device emulator beside the
package). Nothing imports the CLI.
"""

from __future__ import annotations

from .starting import end_quietly_while_loading, interrupts_to_the_command

end_quietly_while_loading()  # before the other imports: a Ctrl-C among them gave a traceback (cli.starting)

import argparse  # noqa: E402 (after the handler, on purpose)
import os
import sys
import warnings

from ..core.files import PROGRESS_HELP, error_text, null_device_on
from . import bench, calibrate, capture, demo, estimate, evaluate, features, fundamental, guide, results, segment, sweep
from .common import STANDARD_OUTPUT, Terminated, stdout_errors_named, terminated_on_sigterm
from .interrupts import StderrAfterDecoders, end_interrupted
from .progress import print_above_bar

__all__ = ["main", "build_parser", "CliError"]

DESCRIPTION = """\
Range obstacles 1–2 m ahead with a Surveyor SVS stereo camera, batched in PyTorch.

The pipeline of the paper, stage by stage: segment the obstacles, find SURF features, match them by SAD,
estimate the fundamental matrix by RANSAC, rectify, and range the obstacles from disparity (R = f·B/d). By
default the obstacles are what is near in the pair's own disparity, the nearest region first, and each is
ranged by its median over a dense disparity map; --preset paper runs the paper's exact steps (Otsu threshold,
erosion + dilation, the two largest regions, SURF on the masked images, depth from the matched points).
"""

EPILOG = """\
examples:
  svs-depth demo                          a synthetic SVS scene ranged (no camera needed); writes svs_demo.png
  svs-depth estimate left.png right.png   distance to the obstacles of a stereo pair
  svs-depth segment left.png right.png    the obstacles estimate keeps (--preset paper: Otsu's)
  svs-depth segment L.png R.png --json    the same as JSON, for scripts
  svs-depth segment L.png R.png --figure seg.png --kernel-size 7 --keep 3
  svs-depth features L.png R.png --size 320x240 --figure matches.png  SURF keypoints and SAD matches
  svs-depth fundamental L.png R.png --json                           F by batched 7-point RANSAC
  svs-depth calibrate 'calib/left*.jpg' --square-m 0.025 --out rig.json   a rig's calibration (chessboards)
  svs-depth capture --emulator --count 5 --out-dir pairs/    grab pairs from a built-in SVS emulator
  svs-depth guide --emulator              live warnings when an obstacle is 1-2 m ahead
  svs-depth eval ../shared/data/middlebury_eval3_Q --size 320x240    accuracy against ground truth
  svs-depth sweep sweep.toml --db sweep.sqlite      a resumable parameter sweep; then: svs-depth results

Real data: any left/right image files work (gray or color; 8 or 16 bit; a JPEG, PNG or WebP turned by its EXIF
orientation, as a viewer shows it; not a phone's HEIC, which OpenCV does not decode). Without calibration the SVS
model is assumed: 3.6 mm lens, 4.17 mm sensor, 10.75 cm baseline (focal 276 px at 320x240).
""" + PROGRESS_HELP + """
Run 'svs-depth COMMAND --help' for each command's options.
"""


class CliError(Exception):
    """A user-facing failure: printed as one line, exit status 2."""


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line on stderr (exit 2), naming the option and what it
    expected, e.g. ``svs-depth estimate: error: argument --batch-size: expected a positive integer, got '0'``."""

    _arguments: list[str] = []

    def parse_known_args(self, args=None, namespace=None):  # type: ignore[override]
        # Kept for error(): a subcommand's parser is called with the rest of the command line.
        self._arguments = list(sys.argv[1:] if args is None else args)
        return super().parse_known_args(args, namespace)

    def error(self, message: str) -> None:  # type: ignore[override]
        message = " ".join(message.split())
        if message.endswith(": expected one argument"):
            message += self._value_read_as_option(message)
        if message.startswith("argument COMMAND: invalid choice: "):
            message += self._option_before_command()
        if message.startswith("the following arguments are required: "):
            # 'segment -left.png right.png': the file read as an option, and the error named the right image missing
            # (an audit); the same hint as for an unrecognized one (_refuse_extras).
            files = [token for token in self._arguments if token.startswith("-") and os.path.isfile(token)]
            message += f" ({files[0]} reads as an option: write ./{files[0]})" if files else ""
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")

    def _value_read_as_option(self, message: str) -> str:
        """`` , got '-5x10', read as an option (write --size=-5x10)``: argparse takes a value that starts with '-'
        and is not a number for the next option, and said only "expected one argument" (an audit's find)."""
        options = message.removeprefix("argument ").removesuffix(": expected one argument").split("/")
        for option, value in zip(self._arguments, self._arguments[1:]):
            name = value.split("=")[0]
            known = any(o.startswith(name) for o in self._option_string_actions) if name.startswith("--") else (
                name in self._option_string_actions)  # a value forgotten before the next option: said as it was
            if option in options and value.startswith("-") and not known:
                typed = value if value.isprintable() else repr(value)  # a control character kept the error one line
                return f", got {value!r}, read as an option (write {option}={typed} for a value that starts with '-')"
        return ""

    def commands(self) -> dict[str, argparse.ArgumentParser]:
        """The parsers of this parser's commands by name ({} for a parser without commands)."""
        actions = [a for a in self._actions if isinstance(a, argparse._SubParsersAction)]
        return dict(actions[0].choices) if actions else {}

    def _option_before_command(self) -> str:
        """`` (--size: give a command's options after its name: svs-depth estimate ... --size 320x240)``: in
        'svs-depth --size 320x240 estimate L R' argparse took the option's value for the command and said only
        "invalid choice: '320x240'" (an audit)."""
        commands = self.commands()
        first = next((i for i, token in enumerate(self._arguments) if token in commands), None)
        early = [i for i, token in enumerate(self._arguments[:first]) if token.startswith("-")]
        if first is None or not early:
            return ""
        given = " ".join(self._arguments[early[0]:first])
        return (f" ({self._arguments[early[0]].split('=')[0]}: give a command's options after its name: svs-depth "
                f"{self._arguments[first]} ... {given})")


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("svs-torch")
    except PackageNotFoundError:
        return "unknown (not installed)"


class _VersionAction(argparse.Action):
    """``--version``: prints ``svs-depth <version>`` and exits. The version is looked up only when asked: reading
    the installed package's metadata took 3 ms, a fifth of building the whole parser, on every command run."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                 help="show program's version number and exit"):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        parser._print_message(f"{parser.prog} {_version()}\n", sys.stdout)
        parser.exit()


def build_parser() -> OneLineParser:
    """The ``svs-depth`` argument parser with every subcommand (each parsed namespace's ``func`` runs it); for
    scripts and tests that parse a command line without running it."""
    parser = OneLineParser(
        prog="svs-depth",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action=_VersionAction)
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module in (demo, estimate, segment, features, fundamental, calibrate, capture, guide, bench, evaluate,
                   sweep, results):
        module.add_parser(subparsers)
    return parser


def _silence_stdout() -> None:
    """After a closed pipe (``svs-depth ... | head``): send further output to /dev/null so that the interpreter's
    final flush does not raise again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass


def _warning_printer(prog: str):
    """``warnings.showwarning`` for the command line: one line, ``svs-depth estimate: warning: ...``, with no
    source file or code line (they mean nothing to a user)."""

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        text = " ".join(str(message).split())
        if text.startswith("--disparity-out: ") and " not written: " in text:  # (a worker's, too: forwarded as text)
            show.maps_not_written += 1
        try:
            # A line of its own, not on a bar, under STDERR_LOCK (not into a decoder's window of another thread)
            print_above_bar(f"{prog}: warning: {text}", file or sys.stderr)
        except (OSError, ValueError):
            pass

    show.maps_not_written = 0  # type: ignore[attr-defined]
    return show


def _maps_not_written(prog: str, count: int) -> int:
    """Exit 1 after a run whose ``--disparity-out`` left maps unwritten rather than write over an input, a ground
    truth or another pair's map (each warned as it happened): it said exit 0, so a script took every map as
    written (an audit)."""
    print(f"{prog}: error: --disparity-out: {count} map{'' if count == 1 else 's'} not written (warned above); "
          f"every pair's results stand", file=sys.stderr)
    return 1


def _refuse_extras(parser: OneLineParser, args: argparse.Namespace, extras: list[str]) -> None:
    """Exit 2 on arguments no parser took, naming the command, as its own options' errors do ("svs-depth segment:
    error: ..."). A file whose name starts with '-' reads as an option (an audit): say how to write it. A command's
    option given before the command's name ('svs-depth --json estimate L R') was called unrecognized by the very
    command whose --help lists it (an audit): say to give it after the name."""
    command, argv = getattr(args, "command", None), parser._arguments  # (the whole command line)
    subparser = parser.commands().get(command, parser)
    before = argv[:argv.index(command)] if command in argv else []
    early = [extra for extra in extras if extra in before and extra.split("=")[0] in subparser._option_string_actions]
    if early:
        subparser.error(f"{early[0]}: an option of 'svs-depth {command}': give it after the command's name "
                        f"(svs-depth {command} ... {early[0]})")
    files = [extra for extra in extras if extra.startswith("-") and os.path.isfile(extra)]
    hint = f" ({files[0]} reads as an option: write ./{files[0]})" if files else ""
    subparser.error(f"unrecognized arguments: {' '.join(extras)}{hint}")


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``svs-depth`` console script; returns the exit status (see :func:`_main`).

    As the program (no ``argv``), a Ctrl-C once the command is over ends the process as the shell's Ctrl-C does
    (status 130 to the shell, nothing printed): one while the interpreter shut down (torch's exit handlers take a
    while) printed a KeyboardInterrupt traceback after the command's own last line (an audit of interrupts)."""
    if argv is None:
        _closed_streams_on_the_null_device()
        _unencodable_escaped()
        sys.stderr = StderrAfterDecoders(sys.stderr)
    try:
        status = _main(argv)
    finally:
        if argv is None:
            import signal

            try:
                signal.signal(signal.SIGINT, signal.SIG_DFL)
            except ValueError:  # not the main thread: Python's handler stays
                pass
    if argv is None and status in (129, 130, 143):  # (129: guide's terminal closed, cli.hangup)
        end_interrupted(status)
    return status


def _closed_streams_on_the_null_device() -> None:
    """A standard stream the shell closed (``>&-``, ``2>&-``, ``<&-``: Python then has ``sys.stdout`` None) opened
    on the null device, its descriptor taken: every command but ``--help`` ended in "internal error:
    AttributeError: 'NoneType' object has no attribute 'write'" (an audit of guide), and a file opened later (a
    record's JPEG, an exported map) would have been given descriptor 1 or 2, where OpenCV's and torch's own messages
    then land. What was to be written there goes nowhere, as the closing asked; a guide started so still speaks."""
    for fd, name in ((0, "stdin"), (1, "stdout"), (2, "stderr")):
        if getattr(sys, name) is not None:
            continue
        null_device_on(fd)
        setattr(sys, name, open(fd, "r" if fd == 0 else "w", encoding="utf-8", errors="backslashreplace",
                                closefd=False))


def _unencodable_escaped() -> None:
    """Characters standard output's encoding lacks written as escapes (``\\u2013``), as Python writes them on
    stderr; a file name's undecodable bytes (``surrogateescape``) still written as they were. Under ``LC_ALL=C``
    with UTF-8 mode off (``PYTHONUTF8=0``), or ``PYTHONIOENCODING=ascii``, ``svs-depth --help`` ended in a
    UnicodeEncodeError traceback on the '–' of its first line (an audit)."""
    if getattr(sys.stdout, "errors", None) in ("strict", "surrogateescape") and hasattr(sys.stdout, "reconfigure"):
        import codecs

        codecs.register_error("svs_torch.escape", _escape)
        try:
            sys.stdout.reconfigure(errors="svs_torch.escape")
        except (ValueError, OSError):  # a stream that cannot change now: left as it is
            pass


def _escape(error: UnicodeError) -> tuple[str | bytes, int]:
    """The encode error handler of :func:`_unencodable_escaped`."""
    import codecs

    chunk = error.object[error.start:error.end]
    if isinstance(error, UnicodeEncodeError) and all(0xDC80 <= ord(char) <= 0xDCFF for char in chunk):
        return bytes(ord(char) - 0xDC00 for char in chunk), error.end
    return codecs.backslashreplace_errors(error)


def _main(argv: list[str] | None) -> int:
    """Run the command of ``argv`` (default: ``sys.argv``); returns the exit status.

    Exit status: 0 done (a pair that cannot be ranged is a status in the output, not an error); 1 a capture or
    file error while running, or an unexpected internal error; 2 bad arguments or input (one line on stderr
    naming the argument); 130 interrupted (Ctrl-C); 141 the reader of the output went away (e.g. ``| head``);
    143 terminated (SIGTERM: what was being written is removed, as on Ctrl-C); 129 guide's terminal closed (SIGHUP,
    ``cli.hangup``: the other commands die of it, Python's default).
    """
    parser = build_parser()
    args, extras = parser.parse_known_args(argv)
    if extras:
        _refuse_extras(parser, args, extras)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    # numpy's OpenBLAS starts a thread per core when OpenCV first imports numpy, and they spin before they sleep;
    # no command calls it (torch has its own BLAS), so the command's own process keeps it to one thread, as its
    # workers do (core.workers.start_worker). A user's own setting stands.
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from ..core.errors import InputError
    from ..core.workers import keep_freed_memory

    keep_freed_memory()  # the commands run batch after batch (see there why)
    prog = f"svs-depth {args.command}"
    try:
        interrupts_to_the_command()  # (the handler of cli.starting until here, where KeyboardInterrupt is caught)
        with warnings.catch_warnings(), terminated_on_sigterm(), stdout_errors_named():
            warnings.showwarning = show = _warning_printer(prog)
            code = int(args.func(args) or 0)
            sys.stdout.flush()  # a closed pipe or a full disk shows here, inside the handler, not at interpreter exit
        return _maps_not_written(prog, show.maps_not_written) if code == 0 and show.maps_not_written else code
    except Terminated as stop:
        print(f"{prog}: terminated", file=sys.stderr)
        return stop.status  # 143; 129 for guide's SIGHUP (cli.hangup) taken as it closed its speaker
    except (InputError, CliError) as error:
        print(f"{prog}: error: {' '.join(str(error).split())}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        _silence_stdout()
        return 141
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except (FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError) as error:
        print(f"{prog}: error: {error_text(error)}", file=sys.stderr)
        return 2
    except OSError as error:
        if error.filename == STANDARD_OUTPUT:
            _silence_stdout()  # nothing more to say there, and the interpreter's last flush would fail again
        print(f"{prog}: error: {error_text(error)}", file=sys.stderr)
        return 1
    except Exception as error:  # noqa: BLE001 -- the last line of defence: one line, never a traceback
        return _unexpected(prog, error)


def _unexpected(prog: str, error: Exception) -> int:
    """Say in one line what :func:`main` did not expect; exit status 1."""
    # (concurrent.futures' BrokenProcessPool by name: importing it would slow every command's start.)
    if type(error).__name__ == "BrokenProcessPool":  # a worker killed from outside (OOM killer): not a bug
        print(f"{prog}: error: a worker process died (killed, or out of memory: try fewer --workers or a "
              "smaller batch); rows a --db store committed are kept, and the same command runs only what is "
              "missing", file=sys.stderr)
        return 1
    print(f"{prog}: internal error: {type(error).__name__}: {' '.join(str(error).split())[:300]} "
          "(please report it)", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())
