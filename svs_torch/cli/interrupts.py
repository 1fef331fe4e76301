"""How the ``svs-depth`` program meets a Ctrl-C (or SIGTERM) that lands while another thread works: its lines on
standard error are not lost in a decoder's window, and its end does not wait for a thread the signal left stuck.
Imports no torch (the command line's ``--help`` answers at once)."""

from __future__ import annotations

import os
import sys

from ..core.files import STDERR_LOCK

__all__ = ["INTERRUPTED_THREADS_WAIT_S", "StderrAfterDecoders", "end_interrupted"]

#: How long an interrupted program waits for its threads before it ends without them (:func:`end_interrupted`).
INTERRUPTED_THREADS_WAIT_S = 3.0


class StderrAfterDecoders:
    """The program's ``sys.stderr``: each write under :data:`~svs_torch.core.files.STDERR_LOCK`, so that no line of
    any thread goes into the window in which another thread lends descriptor 2 to a C decoder (``core.image_files``)
    and is lost. Progress and warnings took the lock already; the rest did not: eval stopped by Ctrl-C while it
    decoded its next block lost "interrupted" and what its store kept (an audit of the interrupt)."""

    def __init__(self, stream) -> None:
        self._stream = stream
        #: The stream itself, for tqdm: :class:`~svs_torch.cli.progress.Progress` takes the lock around its bar's
        #: writes, and tqdm's monitor thread writes holding tqdm's lock, so taking ours there too would deadlock.
        self.unlocked = stream

    def write(self, text: str) -> int:
        with STDERR_LOCK:
            return self._stream.write(text)

    def writelines(self, lines) -> None:
        with STDERR_LOCK:
            self._stream.writelines(lines)

    def flush(self) -> None:
        with STDERR_LOCK:
            self._stream.flush()

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


def end_interrupted(status: int) -> None:
    """After Ctrl-C (130) or SIGTERM (143): give the threads Python's exit would wait for (non-daemon) up to
    :data:`INTERRUPTED_THREADS_WAIT_S` to end, then end the program at once, its output flushed, if one has not.
    Why: a signal can land as the main thread takes a lock that another thread needs (Python cannot release a lock
    whose ``__enter__`` it cut short), and Python's exit then waited for that thread for good: a process pool's
    manager thread, after a Ctrl-C in ``estimate --pairs --workers 2`` at 5 of its 12 such places and in ``sweep``
    at 1 of 7 (an audit that interrupted each place in turn: ``tests/interrupt_places.py``). Only then: the usual
    exit also runs multiprocessing's clean-up, without which its resource tracker warns of leaked semaphores. What
    the commands keep is written and closed before they return (stores, maps, records)."""
    import threading
    import time

    deadline = time.monotonic() + INTERRUPTED_THREADS_WAIT_S
    waited_for = [thread for thread in threading.enumerate()
                  if not thread.daemon and thread is not threading.current_thread()]
    # concurrent.futures joins its process pools' manager threads at exit too, daemon or not (one started by a
    # daemon thread is: estimate --pairs starts its pool so); no public list of them
    pools = sys.modules.get("concurrent.futures.process")
    waited_for += [thread for thread in list(getattr(pools, "_threads_wakeups", {})) if thread not in waited_for]
    for thread in waited_for:
        try:
            thread.join(max(0.0, deadline - time.monotonic()))
        except RuntimeError:  # a start() the signal cut short: the thread never began, and never ends
            pass
    if not any(thread in threading.enumerate() for thread in waited_for):
        return
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe or stream: nothing more can be said there
            pass
    os._exit(status)
