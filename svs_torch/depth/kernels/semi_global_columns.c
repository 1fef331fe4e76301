/* Semi-global aggregation of a SAD cost volume along its columns, for svs_torch.depth.semi_global (the hard path's
 * smoothing of noisy pairs; Hirschmueller 2008, Eq. (13)).
 *
 * The torch path scans the volume a row at a time, a dozen passes over each (B, D, W) slice, about 1 s a pair
 * at 300 x 200 x 48 on two cores. Here each task holds a strip of columns of one pair and keeps the previous
 * row's path costs of every disparity in cache:
 *   L(y, x, d) = C(y, x, d) + min(L(y-1, x, d), min(L(y-1, x, d-1), L(y-1, x, d+1)) + P1, m + P2) - m
 *   m = min_d L(y-1, x, d);  where m = +inf (the previous row wholly +inf: outside the pair's region) the path
 *   starts again: L(y, x, d) = C(y, x, d)
 * down the rows, then up them; out = L_down + L_up. The row paths are semi_global_rows.c's (without it, the torch
 * path runs this scan over the transposed volume). The float32 operations are the torch path's, in its order, so
 * the values are the same bit for bit: adds of the same operands and minima, which do no arithmetic.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp (no -ffast-math: the +inf costs mark
 * disparities outside the image and pixels outside the pair's region). Loaded through ctypes by
 * svs_torch/depth/kernels/__init__.py, which falls back to the torch path without a compiler.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "common.h"
#include "path_step.h"

/* Columns per task: 16 floats of a row are one cache line's worth of each of the D rows the scan keeps. */
#define STRIP 64

/* One disparity of a step (out of line, restrict arguments, no branches: gcc vectorises it over x): path_step.h's
 * step in each column, the path started again where ``restart`` is 1. */
__attribute__((noinline)) static void step_row(int64_t n, const float *restrict c, const float *restrict here,
                                               const float *restrict lo, const float *restrict hi,
                                               const float *restrict low, const float *restrict restart,
                                               float p1, float p2, float *restrict o) {
    for (int64_t x = 0; x < n; ++x)
        o[x] = path_step(c[x], here[x], lo[x], hi[x], low[x], restart[x] == 0.0f ? 0xffffffffu : 0u, p1, p2);
}

/* One step of the path: the row ``cost`` (D rows of ``stride`` floats, n columns used) after ``prev`` (the path's
 * previous row, same layout, or NULL for the first row), into ``cur``; ``work`` is 3 STRIP floats of scratch. */
static void step(const float *cost, int64_t stride, const float *prev, int64_t prev_stride, float *cur,
                 int64_t cur_stride, int64_t D, int64_t n, float p1, float p2, float *work) {
    if (prev == NULL) {
        for (int64_t d = 0; d < D; ++d)
            for (int64_t x = 0; x < n; ++x) cur[d * cur_stride + x] = cost[d * stride + x];
        return;
    }
    float *low = work, *restart = work + STRIP, *none = work + 2 * STRIP;
    for (int64_t x = 0; x < n; ++x) low[x] = prev[x];
    for (int64_t d = 1; d < D; ++d)
        for (int64_t x = 0; x < n; ++x) low[x] = min2(low[x], prev[d * prev_stride + x]);
    for (int64_t x = 0; x < n; ++x) {
        restart[x] = isfinite(low[x]) ? 0.0f : 1.0f;
        none[x] = INFINITY;
    }
    for (int64_t d = 0; d < D; ++d) {
        const float *here = prev + d * prev_stride;
        step_row(n, cost + d * stride, here, d > 0 ? here - prev_stride : none,
                 d + 1 < D ? here + prev_stride : none, low, restart, p1, p2, cur + d * cur_stride);
    }
}

/* costs, out: (B, D, H, W) float32; p1, p2: (B,). Returns 0, or -1 when memory could not be had (the caller then
 * runs the torch path). */
int semi_global_columns(const float *costs, int64_t B, int64_t D, int64_t H, int64_t W, const float *p1,
                        const float *p2, float *out, int64_t num_threads) {
    const int64_t strips = (W + STRIP - 1) / STRIP, tasks = B * strips;
    const int threads = thread_count(num_threads, tasks);
    const int64_t plane = H * W;
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        float *rows = scratch(2 * D * STRIP + 3 * STRIP, sizeof(float));
        const int ready = scratch_ready(rows != NULL, &failed);
#pragma omp for schedule(dynamic, 1)
        for (int64_t task = 0; task < tasks; ++task) {
            if (!ready) continue;
            const int64_t b = task / strips, x0 = (task % strips) * STRIP;
            const int64_t n = W - x0 < STRIP ? W - x0 : STRIP;
            const float *volume = costs + b * D * plane + x0;
            float *result = out + b * D * plane + x0;
            float *low = rows + 2 * D * STRIP;
            /* down the rows: the path costs go straight into out, the previous row read back from it */
            for (int64_t y = 0; y < H; ++y)
                step(volume + y * W, plane, y ? result + (y - 1) * W : NULL, plane, result + y * W, plane, D, n,
                     p1[b], p2[b], low);
            /* up the rows: two rows of scratch by turns, each added to out */
            float *previous = NULL;
            for (int64_t y = H - 1; y >= 0; --y) {
                float *current = rows + ((H - 1 - y) % 2) * D * STRIP;
                step(volume + y * W, plane, previous, STRIP, current, STRIP, D, n, p1[b], p2[b], low);
                for (int64_t d = 0; d < D; ++d) {
                    float *o = result + d * plane + y * W;
                    const float *u = current + d * STRIP;
                    for (int64_t x = 0; x < n; ++x) o[x] = o[x] + u[x];
                }
                previous = current;
            }
        }
        free(rows);
    }
    return failed ? -1 : 0;
}
