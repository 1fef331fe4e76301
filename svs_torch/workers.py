"""Worker processes without torch in the parent: the core count, the worker start-up (torch's threads pinned)
and the watch that ends a worker whose parent is gone. Imports nothing heavy, so that the command line can
start its workers before it imports torch itself (or without ever importing it)."""

from __future__ import annotations

import os
import threading
import time

__all__ = ["available_cores", "start_worker", "thread_budget"]


def available_cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def thread_budget() -> int:
    """The threads this process may use in all: the cores it may run on, or fewer when ``OMP_NUM_THREADS``
    asks for fewer (a user limiting a job's share of the machine)."""
    cores = available_cores()
    try:
        asked = int(os.environ.get("OMP_NUM_THREADS", ""))
    except ValueError:
        return cores
    return max(1, min(cores, asked))


def _watch_parent(parent: int) -> None:
    while os.getppid() == parent:
        time.sleep(0.5)
    os._exit(1)  # the parent was killed (even with SIGKILL): no orphan keeps computing or holding memory


def start_worker(threads: int, warm_modules: tuple[str, ...] = ()) -> None:
    """Worker initializer: pin torch's threads, import ``warm_modules`` (so that the first task does not pay
    for them), leave Ctrl-C to the parent (which stops the pool; a worker would only print a traceback), and
    end the worker when its parent process is gone."""
    import importlib
    import signal

    import torch

    signal.signal(signal.SIGINT, signal.SIG_IGN)

    torch.set_num_threads(threads)
    for name in warm_modules:
        importlib.import_module(name)
    threading.Thread(target=_watch_parent, args=(os.getppid(),), daemon=True, name="watch-parent").start()
