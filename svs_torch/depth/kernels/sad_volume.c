/* The SAD cost volume of a box and its winner-takes-all, for svs_torch.depth.cost_volume._costs_in_cache (the hard
 * path's volume, which the semi-global aggregation of noisy pairs reads whole: svs_torch.depth.semi_global).
 *
 * The torch path takes each disparity's slab of absolute differences and its two box sums in about 2 K passes,
 * then masks and compares it: 60-odd small operations a disparity, about 20 ms for one pair's box at 320 x 240
 * and 64 disparities. Here each task holds a band of output rows of one pair and, disparity by disparity, keeps
 * the K-row column sums of its differences in cache, sliding them down the band (one row added, one taken
 * away) and the window along each row the same way.
 *
 *   costs[b, d, y, x] = the sum over i, j < K of |left[b, y + i, x + j] - right[b, y + i, x + j + D - 1 - d]|
 *                       (+inf where outside[b, d, x])
 *   best_cost, best   = the minimum over d and its first index (d ascending, strictly less replaces)
 *
 * The caller passes whole numbers whose window sums stay below 2^24 (the matched levels of
 * svs_torch.depth.dense.quantize_levels): every partial sum is then exact in float32, so sliding sums give the
 * torch path's values bit for bit whatever their order.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp. Loaded through ctypes by
 * svs_torch/depth/kernels/__init__.py, which falls back to the torch path without a compiler.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "common.h"

/* Output rows per task: a pair's box splits across threads (the B = 1 ``guide`` case), and the K - 1 rows a band
 * sums before its first output row are a small share of it. */
#define BAND 32

/* One row of |l - r| over n columns added to (sign 1) or taken from (sign -1) the column sums. */
static inline void accumulate(float *restrict sums, const float *restrict l, const float *restrict r, int64_t n,
                              float sign) {
    for (int64_t x = 0; x < n; ++x) sums[x] += sign * fabsf(l[x] - r[x]);
}

/* left: (B, height + K - 1, width + K - 1); right: (B, height + K - 1, width + K - 1 + D - 1); outside: (B, D, width)
 * bytes or NULL; costs: (B, D, height, width); best_cost, best: (B, height, width), written where outside is given.
 * Returns 0, or -1 when memory could not be had (the caller then runs the torch path). */
int sad_volume(const float *left, const float *right, int64_t B, int64_t D, int64_t height, int64_t width, int64_t K,
               const uint8_t *outside, float *costs, float *best_cost, int64_t *best, int64_t num_threads) {
    const int64_t hl = height + K - 1, wl = width + K - 1, wr = wl + D - 1;
    const int64_t bands = (height + BAND - 1) / BAND, tasks = B * bands, plane = height * width;
    const int threads = thread_count(num_threads, tasks);
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        float *sums = scratch(wl, sizeof(float));
        const int ready = scratch_ready(sums != NULL, &failed);
#pragma omp for schedule(dynamic, 1)
        for (int64_t task = 0; task < tasks; ++task) {
            if (!ready) continue;
            const int64_t b = task / bands, y0 = (task % bands) * BAND;
            const int64_t y1 = y0 + BAND < height ? y0 + BAND : height;
            const float *l = left + b * hl * wl, *r_pair = right + b * hl * wr;
            for (int64_t d = 0; d < D; ++d) {
                const float *r = r_pair + (D - 1 - d);
                const uint8_t *out_of_range = outside ? outside + (b * D + d) * width : NULL;
                float *plane_d = costs + (b * D + d) * plane;
                for (int64_t x = 0; x < wl; ++x) sums[x] = 0.0f;
                for (int64_t i = 0; i < K; ++i) accumulate(sums, l + (y0 + i) * wl, r + (y0 + i) * wr, wl, 1.0f);
                for (int64_t y = y0; y < y1; ++y) {
                    if (y > y0) {
                        accumulate(sums, l + (y + K - 1) * wl, r + (y + K - 1) * wr, wl, 1.0f);
                        accumulate(sums, l + (y - 1) * wl, r + (y - 1) * wr, wl, -1.0f);
                    }
                    float *row = plane_d + y * width;
                    float window = 0.0f;
                    for (int64_t j = 0; j < K; ++j) window += sums[j];
                    row[0] = window;
                    for (int64_t x = 1; x < width; ++x) {
                        window += sums[x + K - 1] - sums[x - 1];
                        row[x] = window;
                    }
                    if (out_of_range == NULL) continue;
                    float *low = best_cost + b * plane + y * width;
                    int64_t *index = best + b * plane + y * width;
                    for (int64_t x = 0; x < width; ++x) {
                        if (out_of_range[x]) row[x] = INFINITY;
                        if (d == 0) {
                            low[x] = row[x];
                            index[x] = 0;
                        } else if (row[x] < low[x]) {
                            low[x] = row[x];
                            index[x] = d;
                        }
                    }
                }
            }
        }
        free(sums);
    }
    return failed ? -1 : 0;
}
