/* The statistics of each pixel's winner in a cost volume, for svs_torch.depth.winner._winner_stats_torch (the torch
 * path's volume: the noisy pairs' aggregated one, svs_torch.depth.semi_global).
 *
 * Given the winner-takes-all index ``best`` of every left pixel:
 *   before, after = the costs at best - 1 and best + 1, each clamped to [0, D - 1]
 *   rival         = the least cost at |d - best| > 1 (+inf if none), the uniqueness test's
 *   right_best    = the right view's own winner, C_R(j, d) = C_L(j + d, d), over d ascending (a strictly smaller
 *                   cost replaces it, as the torch path's running minimum), -1 where that minimum is not finite
 * The torch path gathers the neighbours, scatters +inf into the volume, takes a minimum over it and restores it,
 * then runs D small operations for the right winner: about 15 ms for one pair's 160 x 330 x 64 volume on two
 * threads. Here each task holds one row of one pair and reads the row's D lines once for each statistic (2 ms).
 * Minima do no arithmetic and the NaN rules are torch.minimum's (a NaN anywhere in a minimum makes it NaN), so the
 * values are the torch path's bit for bit.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp (no -ffast-math: +inf marks the costs
 * outside the image or the pair's range). Loaded through ctypes by svs_torch/depth/kernels/__init__.py, which falls
 * back to the torch path without a compiler.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "common.h"

/* torch.minimum of two floats: NaN if either is. */
static inline float nan_minimum(float a, float b) { return isnan(a) || isnan(b) ? NAN : (b < a ? b : a); }

/* costs: (B, D, H, W) float32; best: (B, H, W) int64 in [0, D); before, after: (B, H, W) float32; rival: (B, H, W)
 * float32 or NULL; right_best: (B, H, W) int64 or NULL; running: W floats of scratch per thread. Returns 0, or -1
 * when memory could not be had (the caller then runs the torch path). */
int winner_statistics(const float *costs, const int64_t *best, int64_t B, int64_t D, int64_t H, int64_t W,
                      float *before, float *after, float *rival, int64_t *right_best, int64_t num_threads) {
    const int64_t tasks = B * H, plane = H * W;
    const int threads = thread_count(num_threads, tasks);
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        float *running = scratch(W, sizeof(float));
        const int ready = scratch_ready(running != NULL, &failed);
#pragma omp for schedule(static)
        for (int64_t task = 0; task < tasks; ++task) {
            if (!ready) continue;
            const int64_t b = task / H, y = task % H, at = b * plane + y * W;
            const float *volume = costs + b * D * plane + y * W; /* disparity d's row: volume + d * plane */
            const int64_t *index = best + at;
            for (int64_t x = 0; x < W; ++x) {
                const int64_t k = index[x], lo = k > 0 ? k - 1 : 0, hi = k + 1 < D ? k + 1 : D - 1;
                before[at + x] = volume[lo * plane + x];
                after[at + x] = volume[hi * plane + x];
            }
            if (rival != NULL) {
                float *least = rival + at;
                for (int64_t x = 0; x < W; ++x) least[x] = INFINITY;
                for (int64_t d = 0; d < D; ++d) {
                    const float *c = volume + d * plane;
                    for (int64_t x = 0; x < W; ++x) {
                        const int64_t gap = d - index[x];
                        const float value = gap > 1 || gap < -1 ? c[x] : INFINITY;
                        least[x] = nan_minimum(least[x], value);
                    }
                }
            }
            if (right_best != NULL) {
                int64_t *winner = right_best + at;
                for (int64_t j = 0; j < W; ++j) {
                    running[j] = volume[j];
                    winner[j] = 0;
                }
                for (int64_t d = 1; d < D && d < W; ++d) {
                    const float *c = volume + d * plane + d; /* column j + d of disparity d */
                    for (int64_t j = 0; j < W - d; ++j) {
                        const int better = c[j] < running[j];
                        running[j] = nan_minimum(running[j], c[j]);
                        winner[j] = better ? d : winner[j];
                    }
                }
                for (int64_t j = 0; j < W; ++j)
                    if (!isfinite(running[j])) winner[j] = -1;
            }
        }
        free(running);
    }
    return failed ? -1 : 0;
}
