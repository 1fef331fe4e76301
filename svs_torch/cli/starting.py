"""A Ctrl-C while ``svs-depth`` loads (its modules and its command line, before the command's own handling of
Ctrl-C begins: a tenth of a second, several on a busy machine) ends it as a later one does, ``svs-depth estimate:
interrupted`` and exit 130, where it printed a KeyboardInterrupt traceback from inside an import. The first module
``svs_torch.cli`` imports, so it imports only ``os``, ``signal`` and ``sys``."""

from __future__ import annotations

import os
import signal
import sys

__all__ = ["end_quietly_while_loading", "interrupts_to_the_command"]


def _the_program() -> bool:
    """Whether this process is ``svs-depth`` itself: its console script, or ``python -m svs_torch.cli`` (whose
    ``argv[0]`` is "-m" while the package loads). A script or test that imports the CLI keeps its own Ctrl-C."""
    first = os.path.basename(sys.argv[0]) if sys.argv else ""
    return first.split(".")[0] == "svs-depth" or (first == "-m" and "svs_torch.cli" in getattr(sys, "orig_argv", ()))


def _interrupted_while_loading(signum, frame) -> None:
    """The line the command's handling says (``svs_torch.cli._main``), then exit 130 at once: nothing has been
    written or opened yet, and an exception raised here would come out of an import as a traceback."""
    command = sys.argv[1] if len(sys.argv) > 1 and sys.argv[1].isalpha() else ""  # (not yet parsed)
    try:
        os.write(2, f"svs-depth{' ' if command else ''}{command}: interrupted\n".encode(errors="replace"))
    except OSError:  # a closed standard error: nothing can be said
        pass
    os._exit(130)


def end_quietly_while_loading() -> None:
    """As the program, until :func:`interrupts_to_the_command`: a Ctrl-C says its one line and exits 130."""
    if _the_program() and signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        try:
            signal.signal(signal.SIGINT, _interrupted_while_loading)
        except ValueError:  # not the main thread
            pass


def interrupts_to_the_command() -> None:
    """Python's KeyboardInterrupt back, which the command's handling turns into the same line (and its clean-up)."""
    if signal.getsignal(signal.SIGINT) is _interrupted_while_loading:
        signal.signal(signal.SIGINT, signal.default_int_handler)
