/* Row fill of invalid dense disparities, for svs_torch.dense.fill_invalid_rows (the no-gradient path).
 *
 * The torch path finds each pixel's nearest valid neighbours by a cumulative max and a flipped cumulative min
 * of indices, gathers both and selects: about fifteen passes over the (rows, W) crop. Here each row is read
 * twice, right to left (the next valid column) and left to right (the last valid one, and the output):
 *   valid pixel:                   d
 *   valid neighbours on both sides: (dl + dr) / 2 where |dl - dr| <= 1, else min(dl, dr)
 *   one side only:                 that side's value;   none: 0, not reachable
 * The same float32 operations as the torch path, so the same values bit for bit.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp. Loaded through ctypes by
 * svs_torch/kernels/__init__.py; rows are shared among num_threads OpenMP threads.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "common.h"

/* Returns 0, or -1 when memory could not be had (the caller then runs the torch path). */
int fill_invalid_rows(const float *disparity, const uint8_t *valid, int64_t rows, int64_t W, float *filled,
                      uint8_t *reachable, int64_t num_threads) {
    const int threads = thread_count(num_threads, rows);
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        int64_t *next = scratch(W, sizeof(int64_t));
        if (!next) {
#pragma omp atomic write
            failed = 1;
        }
#pragma omp for schedule(static)
        for (int64_t r = 0; r < rows; ++r) {
            if (!next) continue;
            const float *d = disparity + r * W;
            const uint8_t *ok = valid + r * W;
            float *out = filled + r * W;
            uint8_t *reach = reachable + r * W;
            int64_t upcoming = W; /* the first valid column at or right of x; W: none */
            for (int64_t x = W - 1; x >= 0; --x) {
                if (ok[x]) upcoming = x;
                next[x] = upcoming;
            }
            int64_t last = -1; /* the last valid column at or left of x; -1: none */
            for (int64_t x = 0; x < W; ++x) {
                if (ok[x]) {
                    last = x;
                    out[x] = d[x];
                    reach[x] = 1;
                    continue;
                }
                const int has_left = last >= 0, has_right = next[x] < W;
                if (has_left && has_right) {
                    const float from_left = d[last], from_right = d[next[x]];
                    const float smaller = from_left < from_right ? from_left : from_right;
                    out[x] = fabsf(from_left - from_right) <= 1.0f ? (from_left + from_right) / 2.0f : smaller;
                } else if (has_left) {
                    out[x] = d[last];
                } else if (has_right) {
                    out[x] = d[next[x]];
                } else {
                    out[x] = 0.0f;
                }
                reach[x] = (uint8_t)(has_left || has_right);
            }
        }
        free(next);
    }
    return failed ? -1 : 0;
}
