"""How ``svs-depth guide`` meets the end of the terminal it runs in (SIGHUP: an ssh session that dropped, a terminal
window closed): as a service's stop (SIGTERM) is met, the walker told "Guide stopped. No more warnings.", the record
closed whole, exit 129 (128 + SIGHUP). Python's default ended guide at once and in silence (an audit), and the
walker heard the silence as a clear way. Imports no torch (the command line's ``--help`` answers at once)."""

from __future__ import annotations

import contextlib
import os
import signal

from ..core.files import null_device_on
from .common import Terminated

__all__ = ["HungUp", "hung_up_on_sighup"]


class HungUp(Terminated):
    """SIGHUP arrived, raised in the main thread by :func:`hung_up_on_sighup`; a :class:`Terminated` (every place
    that ends a command whole on SIGTERM ends it so), with its own exit status."""

    status = 129


def _is_terminal(fd: int) -> bool:
    try:
        return os.isatty(fd)
    except OSError:
        return False


@contextlib.contextmanager
def hung_up_on_sighup():
    """SIGHUP raises :class:`HungUp` in the main thread meanwhile; the previous handler is put back after. A SIGHUP
    ignored when the program started (``nohup``) stays ignored: that guide was asked to outlive its terminal. Before
    raising, standard output and error, where they were a terminal that is now gone, are made the null device: each
    write to a hung-up terminal fails (EIO), and the words, the summary and the interpreter's last flush would have
    ended in errors and a traceback rather than in the walker hearing that guide stopped. A terminal still there (a
    ``kill -HUP``) keeps its lines."""
    sighup = getattr(signal, "SIGHUP", None)  # (none on Windows)
    if sighup is None or signal.getsignal(sighup) != signal.SIG_DFL:
        yield
        return
    from ..core.workers import signal_handler

    terminals = [fd for fd in (1, 2) if _is_terminal(fd)]

    def hang_up(signum, frame):
        for fd in terminals:
            if not _is_terminal(fd):  # hung up: isatty fails (EIO) on it now
                with contextlib.suppress(OSError):
                    null_device_on(fd)
        raise HungUp()

    with signal_handler(sighup, hang_up):
        yield
