"""Where a sweep's tasks run: a local process pool, or a Dask ``distributed`` cluster. Each executor maps a
top-level function over picklable items and yields the results as they finish (in any order); the caller
stores them, so only one process ever writes the results file.

Local pool: :func:`svs_torch.core.workers.worker_pool` (workers forked from a server that imported torch once, or
spawned; never forked from this process, whose torch thread pools may have started), each pinned to ``threads``
torch threads so that workers × threads does not oversubscribe the cores; a worker ends itself when the sweep's
process is gone (a sweep killed with SIGKILL leaves no orphan computing).

Dask (imported only here, only when asked for; ``pip install -e ".[dask]"``): ``client.map(..., pure=False)`` so
that every call runs; the workers are checked for the pitfalls of ``../shared/REFERENCE.md`` (a nanny's
``MALLOC_TRIM_THRESHOLD_``, about 1.5× slower torch here: reported as a warning; torch threads are pinned by the
task itself).
"""

from __future__ import annotations

import concurrent.futures
import os
from collections.abc import Callable, Iterable, Iterator
from typing import Any

from ..core.checks import InputError
from ..core.workers import abandon_pool, available_cores, stop_worker_server, worker_pool

__all__ = ["available_cores", "connect_dask", "map_dask", "map_process_pool"]


def map_process_pool(function: Callable[[Any], Any], items: Iterable[Any], workers: int, threads: int
                     ) -> Iterator[Any]:
    """``function(item)`` for every item in ``workers`` processes of ``threads`` torch threads each
    (:func:`svs_torch.core.workers.worker_pool`), yielded as each finishes. Leaving the loop early cancels what has
    not started."""
    executor = worker_pool(workers, threads)
    try:
        # No name for the list: as_completed lets go of each future it yields, so a finished task's rows are
        # freed once handled, not held to the end of the sweep (an audit of long runs found estimate --pairs'
        # parent growing so, 3–4 kB a pair).
        for future in concurrent.futures.as_completed([executor.submit(function, item) for item in items]):
            yield future.result()
    except BaseException:  # Ctrl-C, SIGTERM, an error, the loop left early: nothing more is wanted, wait for none
        abandon_pool(executor)
        raise
    executor.shutdown(wait=True)
    stop_worker_server()


def _worker_state() -> dict:
    return {"MALLOC_TRIM_THRESHOLD_": os.environ.get("MALLOC_TRIM_THRESHOLD_")}


def connect_dask(address: str, warn: Callable[[str], None]):
    """A ``distributed.Client`` of the cluster at ``address``, its workers checked; an InputError (one line)
    when Dask is not installed, the scheduler cannot be reached or has no workers."""
    try:
        from distributed import Client
    except ImportError:
        raise InputError("--scheduler: Dask distributed is not installed (pip install -e \".[dask]\")") from None
    try:
        client = Client(address, timeout="20s")
    except (OSError, TimeoutError, ValueError) as error:
        raise InputError(f"--scheduler: cannot reach a Dask scheduler at {address!r} "
                         f"({' '.join(str(error).split())})") from None
    states = client.run(_worker_state)
    if not states:
        client.close()
        raise InputError(f"--scheduler: the Dask cluster at {address!r} has no workers")
    trimmed = [worker for worker, state in states.items() if state["MALLOC_TRIM_THRESHOLD_"] is not None]
    if trimmed:
        warn(f"{len(trimmed)} of {len(states)} Dask workers run with MALLOC_TRIM_THRESHOLD_ set by their nanny, "
             "which slows torch about 1.5x: start them with DASK_CONFIG=experiments/dask_workers.yaml")
    return client


def map_dask(client, function: Callable[[Any], Any], items: Iterable[Any]) -> Iterator[Any]:
    """``function(item)`` for every item on the cluster, yielded as each finishes; closes the client at the
    end (and cancels what is left if the loop stops early)."""
    from distributed import as_completed

    try:
        # pure=False: every call runs, even two with equal arguments (Dask would otherwise reuse one result).
        futures = client.map(function, list(items), pure=False)
        try:
            for future in as_completed(futures):
                yield future.result()
        finally:
            client.cancel(futures)
    finally:
        client.close()
