/* Semi-global aggregation of a SAD cost volume along its rows, added to the column paths, and the winner, for
 * svs_torch.depth.semi_global (the hard path's smoothing of noisy pairs; Hirschmueller 2008, Eq. (13)).
 *
 * The torch path runs the column scan (semi_global_columns.c) a second time on the transposed volume, adds the two
 * and takes the minimum over the disparities: two transposed copies of the volume, an add and a reduction. Here
 * each task takes a block of ROWS rows of one pair, transposed so that each column's D x ROWS costs are
 * contiguous, and walks along the rows with the block's rows as the vector lanes, as the column
 * kernel walks down the columns with the columns as its lanes:
 *   L(x, d) = C(x, d) + min(L(x-1, d), min(L(x-1, d-1), L(x-1, d+1)) + P1, m + P2) - m,  m = min_d L(x-1, d)
 *   (m = +inf: the previous pixel wholly +inf, outside the pair's region, and the path starts again: L = C + 0)
 * rightwards, then leftwards; out = columns + (L_right + L_left), and the minimum of out over d with its first
 * index. The float32 operations are the torch path's, in its order (a minimum does no arithmetic, so its order
 * is free), so the values are the same bit for bit. (Until 2026-11-29 the lanes were the disparities of one pixel,
 * a call a pixel with a scalar tail of D mod 8: on a noisy 320x240 frame's coarse retry, 33 x 120 x 224, 3.7 ms on
 * two threads where the column kernel takes 1.2.)
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

/* Rows a task walks at once: the lanes of every step (two AVX2 vectors, four SSE2 ones, one AVX-512 one). */
#define ROWS 16
/* Columns of a block transposed at once (transpose_in): 8, 16, 32 and 64 took 2.1, 1.9, 2.4 and 2.2 ms for the
 * kernel on a coarse retry's 52 x 115 x 262 volume at two threads. */
#define TILE 16

/* One step of the path at one column, every lane (path_step.h's): ``cost`` (D x ROWS), after ``prev`` (the path
 * at the previous column: (D + 2) x ROWS, +inf in the first and last ROWS so that d - 1 and d + 1 need no branch)
 * whose minima over d are ``low`` (ROWS), into ``here`` (the same layout as prev; its padding is the caller's);
 * ``keep`` holds all ones where the path goes on, 0 where it starts again (low = +inf). Writes the minima of
 * here's values over d to ``next`` (ROWS). Out of line, restrict arguments, no branches: gcc vectorises it over
 * the lanes. */
__attribute__((noinline)) static void step_lanes(int64_t D, const float *restrict cost, const float *restrict prev,
                                                 const float *restrict low, const uint32_t *restrict keep,
                                                 float p1, float p2, float *restrict here, float *restrict next) {
    for (int64_t r = 0; r < ROWS; ++r) next[r] = INFINITY;
    for (int64_t d = 0; d < D; ++d) {
        const float *lo = prev + d * ROWS, *mid = lo + ROWS, *hi = mid + ROWS;
        const float *c = cost + d * ROWS;
        float *o = here + (d + 1) * ROWS;
        for (int64_t r = 0; r < ROWS; ++r) {
            o[r] = path_step(c[r], mid[r], lo[r], hi[r], low[r], keep[r], p1, p2);
            next[r] = min2(next[r], o[r]);
        }
    }
}

/* The path's first column: L = C, and its minima over d. */
static void start_lanes(int64_t D, const float *cost, float *here, float *next) {
    for (int64_t r = 0; r < ROWS; ++r) next[r] = INFINITY;
    for (int64_t d = 0; d < D; ++d)
        for (int64_t r = 0; r < ROWS; ++r) {
            here[(d + 1) * ROWS + r] = cost[d * ROWS + r];
            next[r] = min2(next[r], cost[d * ROWS + r]);
        }
}

/* One step of a path into ``here`` (``first``: its first column, no ``prev``), the lanes' minima carried in ``low``. */
static void walk(int64_t D, const float *cost, const float *prev, float *here, float *low, uint32_t *keep,
                 float p1, float p2, int first) {
    float next[ROWS];
    for (int64_t r = 0; r < ROWS; ++r) here[r] = here[(D + 1) * ROWS + r] = INFINITY;
    if (first) {
        start_lanes(D, cost, here, next);
    } else {
        for (int64_t r = 0; r < ROWS; ++r) keep[r] = isfinite(low[r]) ? 0xffffffffu : 0u;
        step_lanes(D, cost, prev, low, keep, p1, p2, here, next);
    }
    for (int64_t r = 0; r < ROWS; ++r) low[r] = next[r];
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

/* The block's costs (rows y0 .. y0 + n - 1 of plane ``volume``, D planes of ``plane`` floats, rows of W) into
 * ``block`` (W x D x ROWS); lanes past n get 0 (their paths are made and never read). Each source row is read in
 * order, TILE columns at a time for the ROWS rows of one disparity, so that the TILE lines of the block they fill
 * are written whole while in the first-level cache. Two orders were slower: a tile of columns of all D x ROWS rows
 * at once missed the cache at nearly every read (more streams than the prefetchers follow); a disparity's whole
 * rows at once wrote W lines of the block D x ROWS x 4 bytes apart, which at 52 disparities (a coarse retry's
 * 52 x 115 x 262 volume) fall in 16 of the cache's 64 sets and were evicted before their ROWS rows were all
 * written: the transpose took 1.9 of the kernel's 3.3 ms there (two threads), 0.6 with tiles. Data moved, never
 * computed: the same values. */
static void transpose_in(const float *volume, int64_t D, int64_t W, int64_t plane, int64_t n, float *block) {
    for (int64_t d = 0; d < D; ++d)
        for (int64_t x0 = 0; x0 < W; x0 += TILE) {
            const int64_t x1 = x0 + TILE < W ? x0 + TILE : W;
            for (int64_t r = 0; r < ROWS; ++r) {
                float *to = block + d * ROWS + r;
                if (r < n) {
                    const float *src = volume + d * plane + r * W;
                    for (int64_t x = x0; x < x1; ++x) to[x * D * ROWS] = src[x];
                } else {
                    for (int64_t x = x0; x < x1; ++x) to[x * D * ROWS] = 0.0f;
                }
            }
        }
}

/* costs, columns, out: (B, D, H, W) float32; p1, p2: (B,); low: (B, H, W) float32 and best: (B, H, W) int64, the
 * minimum of out over d and its first index. Returns 0, or -1 when memory could not be had (the caller then runs
 * the torch path). */
int semi_global_rows(const float *costs, int64_t B, int64_t D, int64_t H, int64_t W, const float *p1, const float *p2,
                     const float *columns, float *out, float *low, int64_t *best, int64_t num_threads) {
    const int64_t blocks = (H + ROWS - 1) / ROWS, tasks = B * blocks, plane = H * W, lane = (D + 2) * ROWS;
    const int threads = thread_count(num_threads, tasks);
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        /* the block's costs (W, D, ROWS), its rightward path then both paths' sum (W, D + 2, ROWS), two leftward
         * steps, one disparity's sums back in rows (ROWS, W) */
        float *block = scratch(W * D * ROWS + W * lane + 2 * lane + ROWS * W, sizeof(float));
        const int ready = scratch_ready(block != NULL, &failed);
#pragma omp for schedule(dynamic, 1)
        for (int64_t task = 0; task < tasks; ++task) {
            if (!ready) continue;
            const int64_t b = task / blocks, y0 = (task % blocks) * ROWS;
            const int64_t n = H - y0 < ROWS ? H - y0 : ROWS, at = b * D * plane + y0 * W;
            float *path = block + W * D * ROWS, *left = path + W * lane, *rows = left + 2 * lane;
            float m[ROWS];
            uint32_t keep[ROWS];
            transpose_in(costs + at, D, W, plane, n, block);
            for (int64_t x = 0; x < W; ++x)
                walk(D, block + x * D * ROWS, x ? path + (x - 1) * lane : NULL, path + x * lane, m, keep, p1[b],
                     p2[b], x == 0);
            for (int64_t x = W - 1; x >= 0; --x) {
                float *current = left + ((W - 1 - x) % 2) * lane, *sum = path + x * lane + ROWS;
                walk(D, block + x * D * ROWS, left + ((W - x) % 2) * lane, current, m, keep, p1[b], p2[b],
                     x == W - 1);
                for (int64_t i = 0; i < D * ROWS; ++i) sum[i] = sum[i] + current[ROWS + i];
            }
            /* each disparity's sums back in rows, added to the columns' paths; each pixel's d ascending, so that a
             * strictly smaller total replaces the winner: the first index on ties, +inf and index 0 where every
             * total is +inf */
            float *lowest = low + b * plane + y0 * W;
            int64_t *index = best + b * plane + y0 * W;
            for (int64_t i = 0; i < n * W; ++i) {
                lowest[i] = INFINITY;
                index[i] = 0;
            }
            for (int64_t d = 0; d < D; ++d) {
                for (int64_t x = 0; x < W; ++x) {
                    const float *sum = path + x * lane + (d + 1) * ROWS;
                    for (int64_t r = 0; r < n; ++r) rows[r * W + x] = sum[r];
                }
                for (int64_t r = 0; r < n; ++r)
                    add_row(W, columns + at + d * plane + r * W, rows + r * W, d, out + at + d * plane + r * W,
                            lowest + r * W, index + r * W);
            }
        }
        free(block);
    }
    return failed ? -1 : 0;
}
