"""Worker processes without torch in the parent: the core count, the worker start-up (torch's threads pinned,
the allocator told to keep freed memory) and the watch that ends a worker whose parent is gone. Imports
nothing heavy, so that the command line can start its workers before it imports torch itself (or without
ever importing it)."""

from __future__ import annotations

import contextlib
import ctypes
import gc
import os
import platform
import select
import sys
import threading
import time
from collections.abc import Iterator
from typing import TYPE_CHECKING

__all__ = ["abandon_pool", "available_cores", "imports_without_collection", "keep_freed_memory", "signal_handler",
           "signals_held", "start_worker", "stop_worker_server", "thread_budget", "worker_pool"]

if TYPE_CHECKING:  # for the annotations only: the pool imports it when it is made
    import concurrent.futures

#: glibc ``mallopt`` parameters (``malloc.h``) and the values :func:`keep_freed_memory` sets.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024  # glibc's largest on 64-bit
TRIM_THRESHOLD_BYTES = 1024 * 1024 * 1024  # keep_freed_memory: a B = 128 batch's chunks (about 1 GB at 320x240)


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


def keep_freed_memory() -> bool:
    """Tell glibc's allocator to keep the memory a batch frees for the next batch: blocks up to 32 MB come
    from the heap instead of fresh ``mmap`` pages, and up to 1 GB of freed heap stays mapped.

    Why: a pipeline batch allocates and frees hundreds of tensors of 0.1–10 MB. By default glibc serves each
    from new pages (its threshold only adapts upwards as blocks are freed) and hands them back, so the kernel
    zeroes every page again on first touch: about a fifth of a worker's time went to page faults and
    ``munmap`` (``perf``). Interleaved on 64 real 320×240 pairs, one thread, the default configuration:
    43.8 → 34.5 ms a pair. Setting only the trim threshold is worse than nothing (it freezes the mmap
    threshold at 128 KB: 77 ms). The cost: the process keeps up to its peak after a batch, and that peak is
    a little higher (one synthetic pair at B = 1: 11.4 → 13.4 MB above the loaded state).

    Why 1 GB of freed heap, not 256 MB: a batch over ``svs_torch.pipeline.run.CHUNK_PIXELS`` holds each chunk's
    result (about 3.5 MB a 320×240 pair) until they are merged. Under 256 MB, freeing them after the merge gave
    part of the heap back, and every chunk of the next batch of 128 paid 40 000–60 000 page faults: 13.0–13.2 ms a
    pair against 11.7–11.9 for the same pairs as batches of 32. With 1 GB: no fault, 11.4–12.2 ms (synthetic pairs,
    2 threads). A process that never runs such a batch never holds that much.

    Called by the command line and its workers (a process that runs batches back to back), never on import:
    a library should not retune its host's allocator. Returns whether both settings took (False off glibc)."""
    if not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc":
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    # Both: setting either one stops glibc adapting the mmap threshold.
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) & bool(mallopt(_M_TRIM_THRESHOLD,
                                                                                TRIM_THRESHOLD_BYTES))


@contextlib.contextmanager
def imports_without_collection() -> Iterator[None]:
    """Run the imports of a command or worker with the cyclic garbage collector off, then freeze what they
    made: they build about 250 000 objects (torch and the pipeline's modules) that live as long as the
    process, and the collector walked them again and again while they grew and then at every full pass.
    Measured: ``import torch, svs_torch.pipeline`` 1.69 → 1.49 s; a worker of ``svs-depth estimate --pairs``
    spent 0.19 s in the collector, now 0.004 s (512 real 320×240 pairs, whole process: 0.93 of the time).

    Only around imports: later objects are collected as usual (a long ``guide`` or ``sweep`` run never grows
    from a switched-off collector).

    In the main thread, Ctrl-C is also held back until the imports are done, then raised as usual: a
    KeyboardInterrupt inside numpy's or torch's import left them half made, and what followed varied (an audit of
    interrupts, about 100 tries in the first second: "internal error: AttributeError: module 'numpy' has no
    attribute 'lib'", an abort from pybind11 with exit 134, or the interrupt lost and the command run to the end).
    """
    import signal

    enabled = gc.isenabled()
    gc.disable()
    try:
        with signals_held(signal.SIGINT):
            yield
    finally:
        gc.freeze()
        if enabled:
            gc.enable()


@contextlib.contextmanager
def signal_handler(signum: int, handler) -> Iterator[object]:
    """``handler`` for signal ``signum`` in the block, the previous one put back after (Python's default where
    the previous was not set from Python, which Python cannot put back); yields the previous handler. Off the main
    thread nothing changes and None is yielded: Python takes signals in the main thread only."""
    import signal

    if threading.current_thread() is not threading.main_thread():
        yield None
        return
    previous = signal.signal(signum, handler)
    try:
        yield previous
    finally:
        if previous is not None:
            signal.signal(signum, previous)
        else:
            signal.signal(signum, signal.default_int_handler if signum == signal.SIGINT else signal.SIG_DFL)


@contextlib.contextmanager
def signals_held(*signums: int) -> Iterator[None]:
    """Hold ``signums`` (default: Ctrl-C's SIGINT, SIGTERM and SIGHUP) back in the block, then deliver them as their
    handlers would, even when the block raised: for a step that must not be cut in two, such as a command's imports
    (:func:`imports_without_collection`) or writing a pair's images and then listing them (an audit of the device
    side: a SIGTERM between the two left a recorded pair's images unlisted in ``index.jsonl``, 1 run in 4). A
    handler that only notes the signal, not a blocked mask: any other thread may take a process's signal. Off the
    main thread nothing is held (Python takes signals in the main thread only)."""
    import signal

    caught: list[int] = []
    previous: dict[int, object] = {}

    def note(number: int, frame) -> None:
        caught.append(number)

    try:
        with contextlib.ExitStack() as stack:
            # SIGHUP too where there is one: guide ends on it as on SIGTERM (cli.hangup), and capture, which dies
            # of it, then dies after the pair is whole, not between its images and its index line
            held = (signal.SIGINT, signal.SIGTERM) + ((signal.SIGHUP,) if hasattr(signal, "SIGHUP") else ())
            for signum in signums or held:
                previous[signum] = stack.enter_context(signal_handler(signum, note))
            yield
    finally:
        for signum in dict.fromkeys(caught):
            handler = previous[signum]
            if callable(handler):  # the handler in place before: KeyboardInterrupt, Terminated, ...
                handler(signum, None)
            elif handler == signal.SIG_DFL or handler is None:
                os.kill(os.getpid(), signum)  # the default action, now that it is back in place


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, PermissionError):  # gone, or someone else's process took the number
        return False
    return True


def _watch_parent(parent: int) -> None:
    """End this worker when the process ``parent`` ends (even by SIGKILL): no orphan keeps computing or holding
    memory. ``parent`` is the process that made the pool, not necessarily this one's direct parent (a forkserver
    outlives it while its workers hold its 'alive' pipe). A pidfd (Linux ≥ 5.3) wakes at the parent's exit and
    cannot be fooled by a reused process number; on Windows the spawned worker waits on its handle of the parent;
    elsewhere the number is polled."""
    try:
        handle = os.pidfd_open(parent)
    except (AttributeError, OSError):  # no pidfd here, or the parent is already gone
        handle = None
    if handle is not None:
        select.select([handle], [], [])
    elif sys.platform == "win32":  # there os.kill(pid, 0) asks nothing: it ends the parent (TerminateProcess)
        import multiprocessing

        known = multiprocessing.parent_process()  # spawned: its sentinel is a handle on the parent process
        if known is None or known.pid != parent:
            return
        known.join()
    else:
        while _alive(parent):
            time.sleep(0.5)
    os._exit(1)


def worker_pool(workers: int, threads: int, warm_modules: tuple[str, ...] = ()
                ) -> concurrent.futures.ProcessPoolExecutor:
    """A ``ProcessPoolExecutor`` of ``workers`` processes, each started by :func:`start_worker` with ``threads``
    torch threads. Where the platform has the 'forkserver' start method (Linux, macOS), the workers are forked
    from a server that imported torch and the pipeline once (:mod:`svs_torch.pipeline.preload`) and
    ``warm_modules``: a worker is ready in milliseconds instead of spending 1.0–1.5 CPU-seconds importing torch
    itself. Elsewhere they are spawned (never plainly forked: this process may have started torch's thread
    pools). The server keeps the environment this process had when it started it, and it counts its workers'
    CPU time: end it with :func:`stop_worker_server` once the pool has shut down."""
    import concurrent.futures  # here, not at the top: the command line imports this module for --help too
    import multiprocessing
    import signal

    if "forkserver" in multiprocessing.get_all_start_methods():
        from multiprocessing import forkserver

        context = multiprocessing.get_context("forkserver")
        callers = getattr(forkserver._forkserver, "_preload_modules", None)  # no public getter
        context.set_forkserver_preload(["svs_torch.pipeline.preload", *warm_modules])
        # Started here and now (its imports go on in the background): it inherits this process's descriptors as
        # they are at this moment, before the command line's decoding redirects descriptor 2 for a few ms at a
        # time (image_files collects decoder messages that way), which a later start could catch.
        # SIGINT ignored meanwhile, so that the server ignores it from its first instruction (an ignored signal
        # stays ignored across exec, and Python then installs no handler of its own). Why: the terminal sends
        # Ctrl-C to the whole process group, and the forkserver, importing the pipeline for a second or two before
        # it ignores SIGINT itself, printed a 27–35 line KeyboardInterrupt traceback above this process's one-line
        # 'interrupted' (an audit of interrupts). A Ctrl-C in these few milliseconds is lost.
        with signal_handler(signal.SIGINT, signal.SIG_IGN):
            forkserver.ensure_running()
        # The server has its list (it is read only at its start): the caller's own is put back. Left set, a caller's
        # own forkserver pool, later in the process, started from a server that imported torch and the pipeline,
        # and every worker of it ran numpy on one OpenBLAS thread (an audit of the API's effect on its caller).
        if callers is not None:
            context.set_forkserver_preload(callers)
    else:
        context = multiprocessing.get_context("spawn")
    return concurrent.futures.ProcessPoolExecutor(workers, mp_context=context, initializer=start_worker,
                                                  initargs=(threads, warm_modules, os.getpid()))


def stop_worker_server() -> None:
    """End the forkserver of :func:`worker_pool` (if one runs) and wait for it, after the pool has shut down:
    its workers' CPU time then counts among this process's children (as ``time`` or a benchmark measures it;
    an unwaited server's is lost), and a later pool starts a server with the environment of that moment.
    Python has no public call for it: without ``ForkServer._stop`` (3.8–3.13 have it) the server ends with
    this process, as before."""
    from multiprocessing import forkserver

    stop = getattr(getattr(forkserver, "_forkserver", None), "_stop", None)
    if stop is not None:
        stop()


def abandon_pool(executor: concurrent.futures.ProcessPoolExecutor) -> None:
    """Stop a :func:`worker_pool` at once, waiting for nothing: cancel what has not started, kill its workers and
    its forkserver. For Ctrl-C, SIGTERM or an error, when the running tasks' results are not wanted (a sweep keeps
    what it committed). Why: the orderly shutdown waited for the workers and the server, and a first Ctrl-C or
    SIGTERM that came while the pool was starting left ``sweep`` hung until a second one (an audit: 10 of 14
    signals; the server never saw its end of the pipe, a worker waited for a task that never came)."""
    import signal

    from multiprocessing import forkserver

    processes = list((getattr(executor, "_processes", None) or {}).values())
    executor.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        with contextlib.suppress(Exception):
            process.kill()
    server = getattr(forkserver, "_forkserver", None)
    pid = getattr(server, "_forkserver_pid", None)
    if pid is not None:
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGKILL)
        with contextlib.suppress(Exception):
            stop_worker_server()  # reaps the killed server (its waitpid returns at once)
    for process in processes:
        with contextlib.suppress(Exception):
            process.join(timeout=1.0)


def start_worker(threads: int, warm_modules: tuple[str, ...] = (), parent: int | None = None) -> None:
    """Worker initializer: pin torch's (and numpy's OpenBLAS) threads, keep freed memory
    (:func:`keep_freed_memory`), import ``warm_modules`` (so that the first task does not pay for them), leave
    Ctrl-C to the parent (which stops the pool; a worker would only print a traceback), and end the worker when
    the process ``parent`` (default: its direct parent) is gone."""
    import importlib
    import signal

    keep_freed_memory()
    # numpy's OpenBLAS starts a thread per core when it is imported, and they spin for a while before they
    # sleep: about 0.12 CPU-seconds a worker taken from the other workers (the pipeline never calls it).
    os.environ.setdefault("OPENBLAS_NUM_THREADS", str(threads))
    with imports_without_collection():
        import torch

        for name in warm_modules:
            importlib.import_module(name)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    torch.set_num_threads(threads)
    threading.Thread(target=_watch_parent, args=(os.getppid() if parent is None else parent,), daemon=True,
                     name="watch-parent").start()
