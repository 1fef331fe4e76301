"""Imported once by the 'forkserver' that :func:`svs_torch.core.workers.worker_pool` forks its workers from: torch and
the pipeline, with the cyclic garbage collector off and the result frozen
(:func:`svs_torch.core.workers.imports_without_collection`), and glibc told to keep freed memory
(:func:`svs_torch.core.workers.keep_freed_memory`). Every worker forked from the server starts with all of it (its
memory shared with the server until written), so no worker imports torch itself.

numpy's OpenBLAS is held to one thread first: its threads would not survive the fork (only the forking thread
does), and the pipeline never calls it. The server runs no torch op, so no thread pool of torch or OpenMP exists
to be copied half-way.

When the server is told to stop (:func:`svs_torch.core.workers.stop_worker_server`, which waits for it), it ends at
once instead of tearing torch down module by module: that teardown took 0.14 s of the command line's wall time
after the last pair, and the server has nothing to flush or save. Only the forkserver gets this; a process that
imports this module for another reason exits as usual.
"""

from __future__ import annotations

import atexit
import os
import sys

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from ..core.workers import imports_without_collection, keep_freed_memory  # noqa: E402  (after the environment)


def _imported_by_forkserver() -> bool:
    """Whether this import runs inside ``multiprocessing.forkserver.main`` (the server's preload)."""
    from multiprocessing import forkserver

    frame = sys._getframe(1)
    while frame is not None:
        if frame.f_code is forkserver.main.__code__:
            return True
        frame = frame.f_back
    return False


def _end_now() -> None:
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


if _imported_by_forkserver():
    # Registered before torch's imports, so that the exit handlers torch registers still run first (they run in
    # reverse order). multiprocessing's own, registered earlier, is skipped: it would join the server's
    # children, and the pool has ended them all. The workers forked from the server inherit this handler but
    # never run it (a forked worker ends by os._exit).
    atexit.register(_end_now)

keep_freed_memory()
with imports_without_collection():
    import torch  # noqa: E402,F401
    import svs_torch.pipeline  # noqa: E402,F401
