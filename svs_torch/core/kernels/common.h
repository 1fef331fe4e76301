/* What every kernel of svs_torch/<stage>/kernels shares: its vector width, its OpenMP thread count and its scratch
 * allocations (and their failure). Each source includes it; svs_torch/core/kernels/loader.py hashes it into every
 * library's cache key, so a change here rebuilds them all. */
#ifndef SVS_TORCH_KERNELS_COMMON_H
#define SVS_TORCH_KERNELS_COMMON_H

#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>

/* The bytes of one vector register of the widest instruction set compiled for, the size of the kernels' vector
 * types (GCC / Clang vector extensions). A wider type is lowered by the compiler, and GCC 12 lowers a 512-bit
 * type's comparisons on AVX2 one lane at a time, moving each in and out of the registers: on an AVX2 machine
 * without AVX-512 (an AMD EPYC VM, one thread) the block matcher then took 53 ms for a 320x240 frame's 48
 * disparities instead of 6.4, and the 7x7 median 72 ms instead of 9. */
#if defined(__AVX512BW__)
#define VECTOR_BYTES 64
#elif defined(__AVX2__)
#define VECTOR_BYTES 32
#else
#define VECTOR_BYTES 16
#endif

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
