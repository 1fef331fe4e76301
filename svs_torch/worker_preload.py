"""Imported once by the 'forkserver' that :func:`svs_torch.workers.worker_pool` forks its workers from: torch and
the pipeline, with the cyclic garbage collector off and the result frozen
(:func:`svs_torch.workers.imports_without_collection`), and glibc told to keep freed memory
(:func:`svs_torch.workers.keep_freed_memory`). Every worker forked from the server starts with all of it (its
memory shared with the server until written), so no worker imports torch itself.

numpy's OpenBLAS is held to one thread first: its threads would not survive the fork (only the forking thread
does), and the pipeline never calls it. The server runs no torch op, so no thread pool of torch or OpenMP exists
to be copied half-way.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from .workers import imports_without_collection, keep_freed_memory  # noqa: E402  (after the environment)

keep_freed_memory()
with imports_without_collection():
    import torch  # noqa: E402,F401
    import svs_torch.pipeline  # noqa: E402,F401
