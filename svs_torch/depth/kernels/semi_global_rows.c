/* Semi-global aggregation of a SAD cost volume along its rows, added to the column paths, and the winner, for
 * svs_torch.depth.semi_global (the hard path's smoothing of noisy pairs; Hirschmueller 2008, Eq. (13)).
 *
 * The torch path runs the column scan (semi_global_columns.c) a second time on the transposed volume, adds the two
 * and takes the minimum over the disparities: two transposed copies of the volume, an add and a reduction. Here
 * each task transposes one row of the volume (in cache-sized blocks) so that each pixel's D costs are contiguous,
 * and walks along it with the disparities as the vector lanes:
 *   L(x, d) = C(x, d) + min(L(x-1, d), min(L(x-1, d-1), L(x-1, d+1)) + P1, m + P2) - m,  m = min_d L(x-1, d)
 *   (m = +inf: the previous pixel wholly +inf, outside the pair's region, and the path starts again: L = C)
 * rightwards, then leftwards; out = columns + (L_right + L_left), and the minimum of out over d with its first
 * index. The float32 operations are the torch path's, in its order (a minimum does no arithmetic, so its order
 * is free), so the values are the same bit for bit.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp (no -ffast-math: the +inf costs mark
 * disparities outside the image and pixels outside the pair's region). Loaded through ctypes by
 * svs_torch/depth/kernels/__init__.py, which falls back to the torch path without a compiler.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "common.h"

/* The side of the blocks a row is transposed in: 16 floats are a cache line, and a block's lines of both
 * layouts stay in the first-level cache. */
#define TILE 16
/* Partial minima of a pixel's D path costs, one vector of them (a minimum's order does not change its value). */
#define PARTS 8

static inline float min2(float a, float b) { return b < a ? b : a; }

/* m = the minimum of the D values at ``v``. */
static float smallest(const float *restrict v, int64_t D) {
    float part[PARTS];
    int64_t d = 0;
    for (int64_t k = 0; k < PARTS; ++k) part[k] = INFINITY;
    for (; d + PARTS <= D; d += PARTS)
        for (int64_t k = 0; k < PARTS; ++k) part[k] = min2(part[k], v[d + k]);
    for (int64_t k = 0; d + k < D; ++k) part[k] = min2(part[k], v[d + k]);
    float m = part[0];
    for (int64_t k = 1; k < PARTS; ++k) m = min2(m, part[k]);
    return m;
}

/* The step's D values (out of line, restrict arguments, no branches: gcc vectorises it over d); ``lo``, ``mid``
 * and ``hi`` are the previous pixel's path at d - 1, d and d + 1, ``m`` its minimum. Returns the minimum of the
 * values written, taken PARTS at a time as they are made (the next step's m). */
__attribute__((noinline)) static float step_pixel(int64_t D, const float *restrict cost, const float *restrict lo,
                                                  const float *restrict mid, const float *restrict hi, float m,
                                                  float p1, float p2, float *restrict here) {
    float part[PARTS];
    for (int64_t k = 0; k < PARTS; ++k) part[k] = INFINITY;
    int64_t d = 0;
    for (; d + PARTS <= D; d += PARTS)
        for (int64_t k = 0; k < PARTS; ++k) {
            const float best = min2(min2(mid[d + k], min2(hi[d + k], lo[d + k]) + p1), m + p2);
            here[d + k] = cost[d + k] + (best - m);
            part[k] = min2(part[k], here[d + k]);
        }
    for (int64_t k = 0; d + k < D; ++k) {
        const float best = min2(min2(mid[d + k], min2(hi[d + k], lo[d + k]) + p1), m + p2);
        here[d + k] = cost[d + k] + (best - m);
        part[k] = min2(part[k], here[d + k]);
    }
    float next = part[0];
    for (int64_t k = 1; k < PARTS; ++k) next = min2(next, part[k]);
    return next;
}

/* n pixels of one disparity d: out = columns + sum, and the running winner (no branches: gcc vectorises it over
 * the pixels). */
__attribute__((noinline)) static void add_row(int64_t n, const float *restrict columns, const float *restrict sum,
                                              int64_t d, float *restrict out, float *restrict lowest,
                                              int64_t *restrict index) {
    for (int64_t x = 0; x < n; ++x) {
        const float total = columns[x] + sum[x];
        const int smaller = total < lowest[x];
        out[x] = total;
        lowest[x] = smaller ? total : lowest[x];
        index[x] = smaller ? d : index[x];
    }
}

/* One step of a path at one pixel: ``cost`` (its D costs) after ``prev`` (the path at the previous pixel: D + 2
 * values, +inf at both ends so that d - 1 and d + 1 need no branch; NULL at the first pixel) whose minimum is
 * ``m``, into ``cur`` (the same layout). Returns the minimum of cur's D values. */
static float step(const float *cost, const float *prev, float m, float *cur, int64_t D, float p1, float p2) {
    cur[0] = INFINITY;
    cur[D + 1] = INFINITY;
    float *here = cur + 1;
    if (prev == NULL) {
        for (int64_t d = 0; d < D; ++d) here[d] = cost[d];
        return smallest(here, D);
    }
    if (!isfinite(m)) {
        for (int64_t d = 0; d < D; ++d) here[d] = cost[d] + 0.0f;
        return smallest(here, D);
    }
    return step_pixel(D, cost, prev, prev + 1, prev + 2, m, p1, p2, here);
}

/* costs, columns, out: (B, D, H, W) float32; p1, p2: (B,); low: (B, H, W) float32 and best: (B, H, W) int64, the
 * minimum of out over d and its first index. Returns 0, or -1 when memory could not be had (the caller then runs
 * the torch path). */
int semi_global_rows(const float *costs, int64_t B, int64_t D, int64_t H, int64_t W, const float *p1, const float *p2,
                     const float *columns, float *out, float *low, int64_t *best, int64_t num_threads) {
    const int64_t tasks = B * H, plane = H * W, lane = D + 2;
    const int threads = thread_count(num_threads, tasks);
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        /* the row's costs (W, D), its rightward path then both paths' sum (W, D + 2), two leftward steps */
        float *row = scratch(W * D + W * lane + 2 * lane, sizeof(float));
        const int ready = scratch_ready(row != NULL, &failed);
#pragma omp for schedule(static)
        for (int64_t task = 0; task < tasks; ++task) {
            if (!ready) continue;
            const int64_t b = task / H, y = task % H, at = b * D * plane + y * W;
            float *path = row + W * D, *left = path + W * lane;
            for (int64_t x0 = 0; x0 < W; x0 += TILE)
                for (int64_t d0 = 0; d0 < D; d0 += TILE)
                    for (int64_t d = d0; d < d0 + TILE && d < D; ++d)
                        for (int64_t x = x0; x < x0 + TILE && x < W; ++x) row[x * D + d] = costs[at + d * plane + x];
            float m = INFINITY;
            for (int64_t x = 0; x < W; ++x)
                m = step(row + x * D, x ? path + (x - 1) * lane : NULL, m, path + x * lane, D, p1[b], p2[b]);
            const float *previous = NULL;
            for (int64_t x = W - 1; x >= 0; --x) {
                float *current = left + ((W - 1 - x) % 2) * lane, *sum = path + x * lane + 1;
                m = step(row + x * D, previous, m, current, D, p1[b], p2[b]);
                for (int64_t d = 0; d < D; ++d) sum[d] = sum[d] + current[d + 1];
                previous = current;
            }
            /* back to (D, W), added to the columns' paths; each pixel's d ascending, so that a strictly smaller
             * total replaces the winner: the first index on ties, +inf and index 0 where every total is +inf */
            float *lowest = low + b * plane + y * W;
            int64_t *index = best + b * plane + y * W;
            for (int64_t x = 0; x < W; ++x) {
                lowest[x] = INFINITY;
                index[x] = 0;
            }
            for (int64_t x0 = 0; x0 < W; x0 += TILE) /* the sums transposed back into row, (D, W) */
                for (int64_t d0 = 0; d0 < D; d0 += TILE)
                    for (int64_t x = x0; x < x0 + TILE && x < W; ++x)
                        for (int64_t d = d0; d < d0 + TILE && d < D; ++d) row[d * W + x] = path[x * lane + 1 + d];
            for (int64_t d = 0; d < D; ++d)
                add_row(W, columns + at + d * plane, row + d * W, d, out + at + d * plane, lowest, index);
        }
        free(row);
    }
    return failed ? -1 : 0;
}
