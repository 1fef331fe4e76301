/* Row fill of invalid dense disparities, for svs_torch.depth.block_matching.fill_invalid_rows (the no-gradient
 * path).
 *
 * The torch path finds each pixel's nearest valid neighbours by a cumulative max and a flipped cumulative min
 * of indices, gathers both and selects: about fifteen passes over the (rows, W) crop. Here each row is read
 * twice (fill_row.h), with the same float32 operations as the torch path, so the same values bit for bit.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp. Loaded through ctypes by
 * svs_torch/depth/kernels/__init__.py; rows are shared among num_threads OpenMP threads.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "common.h"
#include "fill_row.h"

/* Returns 0, or -1 when memory could not be had (the caller then runs the torch path). */
int fill_invalid_rows(const float *disparity, const uint8_t *valid, int64_t rows, int64_t W, float *filled,
                      uint8_t *reachable, int64_t num_threads) {
    const int threads = thread_count(num_threads, rows);
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        int64_t *next = scratch(W, sizeof(int64_t));
        const int ready = scratch_ready(next != NULL, &failed);
#pragma omp for schedule(static)
        for (int64_t r = 0; r < rows; ++r) {
            if (!ready) continue;
            fill_row(disparity + r * W, valid + r * W, W, next, filled + r * W, reachable + r * W);
        }
        free(next);
    }
    return failed ? -1 : 0;
}
