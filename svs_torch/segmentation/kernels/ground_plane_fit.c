/* The ground plane's whole fit, one pair at a time, for svs_torch.segmentation.ground_plane.fit_ground_plane (its
 * torch code stays the reference and the fallback).
 *
 * Why: guide fits every frame. On the map's grid (about 40 x 30 points) the torch path draws 64 three-point planes
 * and scores them against every point in (B, 64, P) arrays, refits, scores twice more and masks the whole view:
 * about 150 small torch operations, 3-4 ms a frame at B = 1 where the floor is looked for in vain and 5-6 ms where
 * one is found, for work of a few hundred microseconds. Here each pair is one pass, in the torch code's order and
 * dtypes: the samples (the caller's uniform draws, the same for every pair), their planes solved in double by LU
 * with partial pivoting and rounded to float, the rig's tests, the inliers and the share behind each plane, the
 * span, the weighted count and its first maximum, the two least-squares refits in double, the last tests and the
 * mask of the view's pixels on the plane, all in float32 where torch computes in float32 (each Python constant
 * rounded to float first, as torch does with a scalar). The weighted counts and the least-squares sums are sums of
 * whole numbers and of products exact in double, so their order does not matter; the planes' solves are not
 * LAPACK's, so a plane can differ from the torch path's in its last float bit, and a test only where it ties.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp (svs_torch/core/kernels/loader.py). Loaded
 * through ctypes by svs_torch/segmentation/kernels/__init__.py; pairs are shared among num_threads OpenMP threads.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "common.h"
#include "select_rank.h"
#include "small_lu.h"

/* The settings, in the order of svs_torch.segmentation.kernels.GROUND_PLANE_SETTINGS. */
enum {
    STRIDE, MIN_SPAN, TOLERANCE_FRACTION, LOWER_ROW, TAN_ROLL, MIN_HEIGHT, MAX_HEIGHT, TAN_PITCH, MAX_BEHIND,
    MIN_SHARE, CENTRE_X, CENTRE_Y, NUM_SETTINGS
};

/* Solves a x = b (3 x 3) into x; returns 0 when a is exactly singular (x is then unset). */
static int solve3(double *a, const double *b, double *x, double *det) {
    int pivot[3], singular;
    *det = lu_factor(a, 3, pivot, &singular);
    if (singular) return 0;
    for (int i = 0; i < 3; ++i) x[i] = b[i];
    lu_solve(a, 3, pivot, x);
    return 1;
}

typedef struct {
    const float *d;      /* the grid's disparities (P,) */
    const uint8_t *ok;   /* measured and positive (P,) */
    const float *x, *y;  /* each grid point's pixel column and row (P,) */
    int64_t count;       /* P */
} Grid;

/* _inliers of one plane: marks inliers (P,), returns the share behind it. */
static float plane_inliers(const float *plane, const Grid *g, float tolerance, float fraction, uint8_t *inliers) {
    int64_t below = 0, behind = 0;
    for (int64_t p = 0; p < g->count; ++p) {
        const float predicted = (plane[0] * g->x[p] + plane[1] * g->y[p]) + plane[2];
        float limit = fraction * predicted;
        limit = limit < tolerance ? tolerance : limit;  /* clamp_min: a NaN limit stays NaN */
        const int under = g->ok[p] && predicted > 0;
        const float offset = g->d[p] - predicted;
        below += under;
        behind += under && offset < -limit;
        inliers[p] = (uint8_t)(under && fabsf(offset) <= limit);
    }
    return (float)behind / (float)(below > 0 ? below : 1);
}

/* _span: the range of the inliers' disparities (0 with none). */
static float span(const uint8_t *inliers, const Grid *g) {
    float top = -INFINITY, bottom = INFINITY;
    int any = 0;
    for (int64_t p = 0; p < g->count; ++p) {
        if (!inliers[p]) continue;
        any = 1;
        top = g->d[p] > top || isnan(g->d[p]) ? g->d[p] : top;
        bottom = g->d[p] < bottom || isnan(g->d[p]) ? g->d[p] : bottom;
    }
    return any ? top - bottom : 0.0f;
}

/* _plausible: a walker's floor for this rig (height, roll, and pitch where focal is not NaN). */
static int plausible(const float *plane, float baseline, float focal, const double *s) {
    const float a = plane[0], b = plane[1];
    const float height = baseline / hypotf(a, b);
    int ok = (b > 0) && fabsf(a) <= (float)s[TAN_ROLL] * b && height >= (float)s[MIN_HEIGHT]
             && height <= (float)s[MAX_HEIGHT];
    if (!isnan(focal)) {
        const float horizon = -(a * (float)s[CENTRE_X] + plane[2]) / (b > 1e-12f ? b : 1e-12f);
        ok = ok && horizon >= (float)s[CENTRE_Y] - focal * (float)s[TAN_PITCH];
    }
    return ok;
}

/* _least_squares over the marked points, in double (exact sums); NaN with fewer than three or a singular system. */
static void least_squares(const uint8_t *weight, const Grid *g, float *plane) {
    double normal[9] = {0}, rhs[3] = {0}, solution[3], det;
    int64_t used = 0;
    for (int64_t p = 0; p < g->count; ++p) {
        if (!weight[p]) continue;
        const double row[3] = {g->x[p], g->y[p], 1.0};
        for (int i = 0; i < 3; ++i) {
            for (int j = 0; j < 3; ++j) normal[3 * i + j] += row[i] * row[j];
            rhs[i] += row[i] * (double)g->d[p];
        }
        ++used;
    }
    if (used >= 3 && solve3(normal, rhs, solution, &det))
        for (int i = 0; i < 3; ++i) plane[i] = (float)solution[i];
    else
        plane[0] = plane[1] = plane[2] = NAN;
}

/* _sample_planes for hypothesis n of a pair: the plane through three grid points, NaN where one is off the grid
 * or unmeasured, or the sample nearly collinear. */
static void sample_plane(const double *draw, const uint8_t *candidate, int64_t candidates, const Grid *g,
                         int64_t gh, int64_t gw, float *plane) {
    plane[0] = plane[1] = plane[2] = NAN;
    const int64_t cells = gh * gw, rank = (int64_t)(draw[0] * (double)candidates);
    int64_t first = cells - 1, seen_count = 0;
    for (int64_t p = 0; p < cells; ++p) {  /* searchsorted(cumsum, rank + 1): the rank-th candidate */
        seen_count += candidate[p];
        if (seen_count >= rank + 1) {
            first = p;
            break;
        }
    }
    const double reach[2] = {(double)(gw / 8 > 1 ? gw / 8 : 1), (double)(gh / 6 > 1 ? gh / 6 : 1)};
    int64_t column[3] = {first % gw, 0, 0}, row[3] = {first / gw, 0, 0};
    for (int k = 1; k < 3; ++k) {
        column[k] = column[0] + (int64_t)nearbyint((draw[2 * k - 1] * 2 - 1) * reach[0]);  /* round half even */
        row[k] = row[0] + (int64_t)nearbyint((draw[2 * k] * 2 - 1) * reach[1]);
    }
    double matrix[9], values[3], solution[3], det;
    int usable = candidates >= 1;
    for (int k = 0; k < 3; ++k) {
        const int inside = column[k] >= 0 && column[k] < gw && row[k] >= 0 && row[k] < gh;
        const int64_t c = column[k] < 0 ? 0 : (column[k] >= gw ? gw - 1 : column[k]);
        const int64_t r = row[k] < 0 ? 0 : (row[k] >= gh ? gh - 1 : row[k]);
        const int64_t index = r * gw + c;
        usable &= inside && g->ok[index] != 0;
        matrix[3 * k] = g->x[c];
        matrix[3 * k + 1] = g->y[r * gw];
        matrix[3 * k + 2] = 1.0;
        values[k] = (double)g->d[index];
    }
    if (!usable || !solve3(matrix, values, solution, &det) || !(fabs(det) > 1.0)) return;
    const float result[3] = {(float)solution[0], (float)solution[1], (float)solution[2]};
    if (!(isfinite(result[0]) && isfinite(result[1]) && isfinite(result[2]))) return;
    for (int i = 0; i < 3; ++i) plane[i] = result[i];
}

/* The pair's fit (fit_ground_plane after its early exits): *found, plane (3,), its inlier scratch (3 P). The
 * three-point samples are drawn from ``samples`` (the grid itself, or a noisy pair's cells' medians), every test
 * and refit on ``g``. */
static int fit_pair(const Grid *g, const Grid *samples, int64_t gh, int64_t gw, const double *draws,
                    int64_t hypotheses, float baseline, float focal, float tolerance, const double *s,
                    uint8_t *scratch, float *plane) {
    const int64_t P = g->count;
    uint8_t *candidate = scratch, *inliers = scratch + P, *chosen = scratch + 2 * P;
    const float lower_row = (float)s[LOWER_ROW], fraction = (float)s[TOLERANCE_FRACTION];
    const float min_span = (float)s[MIN_SPAN], max_behind = (float)s[MAX_BEHIND];
    int64_t candidates = 0;
    for (int64_t p = 0; p < P; ++p)
        candidates += (candidate[p] = (uint8_t)(samples->ok[p] && samples->y[p] >= lower_row));
    float best_count = 0.0f, best_plane[3] = {NAN, NAN, NAN};
    int64_t best = -1;
    for (int64_t n = 0; n < hypotheses; ++n) {
        float sample[3];
        sample_plane(draws + 5 * n, candidate, candidates, samples, gh, gw, sample);
        float count = -1.0f;
        if (plausible(sample, baseline, focal, s)) {
            const float behind = plane_inliers(sample, g, tolerance, fraction, inliers);
            if (behind <= max_behind && span(inliers, g) >= min_span) {
                count = 0.0f;  /* each inlier weighs by how low it lies, none above the sampled rows */
                for (int64_t p = 0; p < P; ++p)
                    if (inliers[p]) count += g->y[p] - lower_row > 0 ? g->y[p] - lower_row : 0.0f;
            }
        }
        if (best < 0 || count > best_count) {  /* argmax: the first of equal counts */
            best = n;
            best_count = count;
            for (int i = 0; i < 3; ++i) best_plane[i] = sample[i];
        }
    }
    if (!(best_count > 0)) return 0;
    plane_inliers(best_plane, g, tolerance, fraction, chosen);
    least_squares(chosen, g, plane);
    /* Refitted on the points within half the tolerance (fit_ground_plane's comment says why). */
    plane_inliers(plane, g, tolerance / 2, (float)(s[TOLERANCE_FRACTION] / 2), inliers);
    int64_t close = 0;
    for (int64_t p = 0; p < P; ++p) close += inliers[p];
    if (close >= 3) least_squares(inliers, g, plane);
    const float behind = plane_inliers(plane, g, tolerance, fraction, inliers);
    int64_t on_plane = 0;
    for (int64_t p = 0; p < P; ++p) on_plane += inliers[p];
    const float share = (float)on_plane / (float)(P > 1 ? P : 1);
    return plausible(plane, baseline, focal, s) && share >= (float)s[MIN_SHARE] && behind <= max_behind
           && span(inliers, g) >= min_span;
}

/* The k-th least of values[0, n) (0 <= k < n, n <= 64, no NaN) by ranks: the first value with at most k below it
 * and more than k at most it. No branch on the data in the counting, which vectorises: on a 320-px map's cells of
 * 64 pixels, half the time of quickselect (select_rank.h), whose partitions mispredict. */
static float rank_kth(const float *values, int64_t n, int64_t k) {
    for (int64_t i = 0; i < n; ++i) {
        const float v = values[i];
        int32_t less = 0, at_most = 0;
        for (int64_t j = 0; j < n; ++j) {
            less += values[j] < v;
            at_most += values[j] <= v;
        }
        if (less <= k && k < at_most) return v;
    }
    return values[k];  /* not reached: some value is the k-th */
}

/* A noisy pair's sampled grid point (svs_torch/segmentation/ground_plane_grid.py, cell_medians): the lower median of the
 * measured pixels of its cell, rows [row0, row0 + stride) and columns [col0, col0 + stride) inside the view, NaN
 * ones left out of the median but counted (as torch's nanmedian over them); not measured (and 0) with fewer than
 * cell_min measured. ``buffer`` holds stride * stride floats. */
static void cell_median(const float *map, const uint8_t *seen, int64_t H, int64_t W, int64_t row0, int64_t col0,
                        int64_t stride, int64_t cell_min, float *buffer, float *d, int *measured) {
    int64_t count = 0, finite = 0;
    for (int64_t y = row0; y < row0 + stride && y < H; ++y)
        for (int64_t x = col0; x < col0 + stride && x < W; ++x)
            if (seen[y * W + x]) {
                ++count;
                if (!isnan(map[y * W + x])) buffer[finite++] = map[y * W + x];
            }
    *measured = count >= cell_min;
    const int64_t k = (finite - 1) / 2;
    if (!*measured || finite == 0) {
        *d = !*measured ? 0.0f : NAN;
    } else if (finite <= 64) {
        *d = rank_kth(buffer, finite, k);
    } else {
        select_rank(buffer, 0, finite, k);  /* the value of rank k, as a sort gives it (select_rank.h) */
        *d = buffer[k];
    }
}

/* disparity (B, H, W) float32, measured (B, H, W) uint8; baseline (B,), tolerance (B,) float32 (in the map's
 * pixels); focal (B,) float32, not NaN, or NULL (no pitch limit); draws (N, 5) float64, the samples' uniforms; settings
 * (NUM_SETTINGS,) float64; cells (B,) uint8 or NULL: the pairs whose samples are drawn from their cells' medians
 * over at least cell_min measured pixels (cell_median). Writes plane (B, 3) float32 (0 where not found), found (B,)
 * uint8, height (B,) float32 (NaN where not found) and mask (B, H, W) uint8. Returns -1 when memory could not be
 * had. */
int ground_plane_fit(const float *disparity, const uint8_t *measured, const float *baseline, const float *tolerance,
                     const float *focal, const double *draws, const double *settings, int64_t B, int64_t H, int64_t W,
                     int64_t hypotheses, float *plane, uint8_t *found, float *height, uint8_t *mask,
                     const uint8_t *cells, int64_t cell_min, int64_t num_threads) {
    const int64_t stride = (int64_t)settings[STRIDE], offset = stride / 2;
    const int64_t gh = H > offset ? (H - offset + stride - 1) / stride : 0;
    const int64_t gw = W > offset ? (W - offset + stride - 1) / stride : 0, P = gh * gw;
    int failed = 0;
#pragma omp parallel num_threads(thread_count(num_threads, B))
    {
        float *values = scratch(4 * P, sizeof(float));
        uint8_t *flags = scratch(5 * P, 1);
        float *cell = cells != NULL ? scratch(stride * stride, sizeof(float)) : NULL;
        const int ready = scratch_ready(values != NULL && flags != NULL && (cells == NULL || cell != NULL), &failed);
#pragma omp for schedule(dynamic, 1)
        for (int64_t b = 0; b < B; ++b) {
            if (!ready) continue;
            float *d = values, *xs = values + P, *ys = values + 2 * P, *medians = values + 3 * P;
            uint8_t *medians_ok = flags + 4 * P;
            const int medians_used = cells != NULL && cells[b];
            /* A sample's first point lies at or below the lower row, the other two at most gh / 6 rows above it
             * (sample_plane): the cells above are never drawn, and their medians not made. */
            const int64_t drawn_from = (int64_t)ceil((settings[LOWER_ROW] - (double)offset) / (double)stride)
                                       - (gh / 6 > 1 ? gh / 6 : 1);
            for (int64_t r = 0; r < gh; ++r) {  /* the grid: every stride-th pixel from stride // 2 */
                for (int64_t c = 0; c < gw; ++c) {
                    const int64_t pixel = (b * H + offset + r * stride) * W + offset + c * stride, p = r * gw + c;
                    d[p] = disparity[pixel];
                    flags[p] = measured[pixel] && d[p] > 0;
                    xs[p] = (float)(c * stride + offset);
                    ys[p] = (float)(r * stride + offset);
                    if (medians_used && r < drawn_from) {
                        medians[p] = 0.0f;
                        medians_ok[p] = 0;
                    } else if (medians_used) {
                        int seen;
                        cell_median(disparity + b * H * W, measured + b * H * W, H, W, r * stride, c * stride, stride,
                                    cell_min, cell, medians + p, &seen);
                        medians_ok[p] = seen && medians[p] > 0;
                    }
                }
            }
            const Grid grid = {d, flags, xs, ys, P}, cell_grid = {medians, medians_ok, xs, ys, P};
            float *out = plane + 3 * b;
            const float f = focal != NULL ? focal[b] : NAN;  /* NaN: no pitch limit */
            const int ok = P > 0 && fit_pair(&grid, medians_used ? &cell_grid : &grid, gh, gw, draws, hypotheses,
                                             baseline[b], f, tolerance[b], settings, flags + P, out);
            found[b] = (uint8_t)ok;
            height[b] = ok ? baseline[b] / fmaxf(hypotf(out[0], out[1]), 1e-12f) : NAN;
            if (!ok) out[0] = out[1] = out[2] = 0.0f;
            const float fraction = (float)settings[TOLERANCE_FRACTION];
            for (int64_t y = 0; y < H; ++y) {  /* _pixels_on: the view's pixels on the plane */
                const float *row = disparity + (b * H + y) * W;
                uint8_t *out_row = mask + (b * H + y) * W;
                for (int64_t x = 0; x < W; ++x) {
                    const float predicted = (out[0] * (float)x + out[1] * (float)y) + out[2];
                    float limit = fraction * predicted;
                    limit = limit < tolerance[b] ? tolerance[b] : limit;
                    out_row[x] = (uint8_t)(ok && predicted > 0 && fabsf(row[x] - predicted) <= limit);
                }
            }
        }
        free(values);
        free(flags);
        free(cell);
    }
    return failed ? -1 : 0;
}
