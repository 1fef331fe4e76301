"""Work run beside the main thread that a Ctrl-C never waits for: :class:`DaemonTask`, one call in its own
daemon thread, used where a thread pool was (eval's decode-ahead, a stereo camera's two boards).

Why not ``concurrent.futures.ThreadPoolExecutor``: Python cannot release a lock whose ``__enter__`` a signal
interrupted after it took the lock (``threading.Condition.__enter__`` is Python code around a lock's ``acquire``).
A Ctrl-C that landed there, in ``submit`` or ``Future.result``, left the executor's semaphore or the future's
condition held by the main thread for good; the worker then waited on it, and the executor's exit (and Python's
own, which joins every pool worker) waited on the worker: ``svs-depth eval`` hung after Ctrl-C (once in CI; the
threads' stacks showed ``_idle_semaphore.release`` and ``shutdown``; ``tests/core/test_daemon_task.py`` makes the
interrupt land there on purpose). A daemon thread is joined by nothing but :meth:`DaemonTask.result`, whose wait
(``Thread.join``) releases what an interrupt leaves behind, and by Python's exit for a bounded time only
(:data:`AT_EXIT_WAIT_S`).
"""

from __future__ import annotations

import atexit
import threading
import time
from collections.abc import Callable
from typing import Generic, TypeVar

__all__ = ["AT_EXIT_WAIT_S", "BEGIN_WAIT_S", "DaemonTask"]

T = TypeVar("T")

#: How long Python's exit waits, in all, for the calls still running. Why wait: Python ends a daemon thread that
#: comes back from C code once the exit has begun by unwinding its stack, and unwinding OpenCV's C++ frames so
#: aborts the process ("terminate called without an active exception": eval stopped by Ctrl-C while it decoded
#: the next block ended in SIGABRT, 6 runs in 6). Why a bound: a call that cannot end must not hold the exit.
AT_EXIT_WAIT_S = 10.0

#: How long the exit waits for a counted call's thread to begin it, seconds (:func:`_let_running_calls_end`).
BEGIN_WAIT_S = 1.0

#: The calls Python's exit waits for: each counted before its thread starts, let go as its call ends.
_RUNNING: set[DaemonTask] = set()


@atexit.register
def _let_running_calls_end() -> None:
    deadline = time.monotonic() + AT_EXIT_WAIT_S
    for task in list(_RUNNING):
        # A thread whose start() a Ctrl-C cut short may never begin (a lock the interrupt left held): that one is
        # waited for BEGIN_WAIT_S only
        if task._began.wait(max(0.0, min(BEGIN_WAIT_S, deadline - time.monotonic()))):
            task._thread.join(max(0.0, deadline - time.monotonic()))


class DaemonTask(Generic[T]):
    """``function(*args)`` started at once in a daemon thread named ``name``. :meth:`result` waits for it and
    returns its value or raises what it raised (:meth:`exception` returns it). Nothing else waits for it: a caller
    interrupted (Ctrl-C) before calling :meth:`result` leaves it to finish on its own, and Python's exit waits for
    it at most :data:`AT_EXIT_WAIT_S` seconds; with ``wait_at_exit=False`` not at all, for a call that runs no
    C++ (whose thread Python may end as it exits) and may take long, such as opening a link.

    Example:
        >>> DaemonTask(sum, [1, 2, 3]).result()
        6
    """

    def __init__(self, function: Callable[..., T], *args: object, name: str = "svs-daemon-task",
                 wait_at_exit: bool = True) -> None:
        self._value: T | None = None
        self._error: BaseException | None = None
        self._began = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(function, args), name=name, daemon=True)
        # Counted before start(), not after it, nor by the thread: a Ctrl-C in start() (which waits for the thread
        # to begin) skipped a count after it, and one by the thread came after the exit had looked (eval's SIGABRT
        # after Ctrl-C, 1 run in 20: the exit began while the next block's thread had not yet got the GIL)
        if wait_at_exit:
            _RUNNING.add(self)
        self._thread.start()

    def _run(self, function: Callable[..., T], args: tuple) -> None:
        self._began.set()
        try:
            self._value = function(*args)
        except BaseException as error:  # handed to result(), in the caller's thread
            self._error = error
        finally:
            _RUNNING.discard(self)

    def done(self) -> bool:
        """Whether the call has returned or raised."""
        return not self._thread.is_alive()

    def exception(self) -> BaseException | None:
        """What the call raised once it ends, or None when it returned."""
        self._thread.join()
        return self._error

    def result(self) -> T:
        """The call's value once it returns; what it raised, raised here."""
        if self.exception() is not None:
            raise self._error
        return self._value  # type: ignore[return-value]
