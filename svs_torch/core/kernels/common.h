/* What every kernel of svs_torch/<stage>/kernels shares: its OpenMP thread count and its scratch allocations (and
 * their failure). Each source includes it; svs_torch/core/kernels/loader.py hashes it into every library's cache
 * key, so a change here rebuilds them all. */
#ifndef SVS_TORCH_KERNELS_COMMON_H
#define SVS_TORCH_KERNELS_COMMON_H

#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>

/* Threads for ``tasks`` independent pieces of work: the caller's count (torch.get_num_threads()), at most one
 * per task, and at least one (OpenMP's num_threads must be positive, even for an empty batch). No kernel's
 * result depends on it. */
static inline int thread_count(int64_t requested, int64_t tasks) {
    const int64_t threads = requested < tasks ? requested : tasks;
    return threads < 1 ? 1 : (int)threads;
}

/* malloc of ``count`` elements of ``size`` bytes, never of 0 bytes: malloc(0) may return NULL, which the
 * kernels would take for a failed allocation. */
static inline void *scratch(int64_t count, size_t size) { return malloc(size * (size_t)(count > 0 ? count : 1)); }

/* ``ok``: whether this thread's scratch allocations all succeeded. When not, marks the call failed (``*failed``,
 * shared by the threads of the parallel region: the kernel returns -1 and its caller runs the torch path). */
static inline int scratch_ready(int ok, int *failed) {
    if (!ok) {
#pragma omp atomic write
        *failed = 1;
    }
    return ok;
}

#endif
