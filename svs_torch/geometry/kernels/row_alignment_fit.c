/* The row alignment's whole similarity fit, one pair at a time, for svs_torch.geometry.row_alignment.
 * fit_row_alignment (the no-gradient path; its torch code stays the reference and the differentiable refit's).
 *
 * Why: the torch path draws 256 three-match samples, solves them, scores them, refits the best by least squares,
 * tests the limits and reads whether the rig's rows show a keystone in about 130 small torch operations: about
 * 2.5 ms a pair at B = 1, a twentieth of guide's frame, for a few thousand flops. Here, per pair:
 *
 * 1. the samples are draw_minimal_samples's ranks among the valid matches, exactly (minimal_samples.h);
 * 2. each sample's system (y_r, x_r, 1) (a, b, t_y) = y_l is dropped where the determinant of the system divided by
 *    its largest |x| or |y| (at least 1) is at most 1e-6, else solved by LU with partial pivoting;
 * 3. its MSAC cost sums min(|b x_r + a y_r + t_y - y_l|, threshold)^2 over the valid matches in index order;
 * 4. the cheapest (the first of equal costs, as torch's argmin) gives the inliers, the least-squares refit over
 *    them (normal equations plus 1e-9 I) the final inliers, and the acceptance tests are _accept's;
 * 5. where a focal length is given, the refit of the keystone model over those inliers (_keystone_refit) says
 *    whether some turn term is significant; only then does the caller run the torch keystone fit.
 *
 * The float64 expressions are the torch code's, in the same order and without contraction to fused multiply-adds,
 * but its LU solves are not LAPACK's and its sums run in match order: parameters agree with the torch path to
 * about 1e-15 relative, so an inlier or a test can differ only where a residual or a limit ties to those bits.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp (svs_torch/core/kernels/loader.py). Loaded
 * through ctypes by svs_torch/geometry/kernels/__init__.py; pairs are shared among num_threads OpenMP threads.
 */
#include <float.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "common.h"
#include "minimal_samples.h"
#include "small_lu.h"

/* 180 / pi, the constant torch.rad2deg multiplies by. */
#define DEGREES_PER_RADIAN 57.295779513082320876798154814105170332405472466564

#define SAMPLE 3

/* The settings, in the order of svs_torch.geometry.kernels.ROW_ALIGNMENT_SETTINGS. */
enum {
    THRESHOLD, NUM_HYPOTHESES, MIN_INLIERS, MIN_INLIER_SHARE, MIN_GAIN, MIN_GAIN_SHARE, MAX_ROLL_RAD, MAX_SCALE_CHANGE,
    MAX_SHIFT_FRACTION, KEYSTONE_MIN_DEG, KEYSTONE_MIN_T, NUM_SETTINGS
};

/* |b x_r + a y_r + t_y - y_l| of match k (_row_residuals). */
static inline double row_residual(const double *h, const double *left, const double *right, int64_t k) {
    return fabs(((h[1] * right[2 * k] + h[0] * right[2 * k + 1]) + h[2]) - left[2 * k + 1]);
}

/* Steps 2-3 for the hypotheses of one pair: the cheapest sample's (a, b, t_y), NaN-free as torch's nan_to_num. */
static void best_hypothesis(const double *left, const double *right, const int64_t *rows, int64_t n, uint64_t seed,
                            int64_t hypotheses, double threshold, double *best) {
    double best_cost = INFINITY;
    best[0] = best[1] = best[2] = NAN;
    for (int64_t h = 0; h < hypotheses; ++h) {
        double params[3] = {NAN, NAN, NAN}, cost = INFINITY;
        if (n >= SAMPLE) {
            int64_t ranks[SAMPLE];
            draw_minimal_sample(seed, h, n, SAMPLE, ranks);
            double system[9], scaled[9], largest = 1.0;
            int pivot[3], singular;
            for (int s = 0; s < SAMPLE; ++s) {
                const int64_t k = rows[ranks[s]];
                system[3 * s] = right[2 * k + 1];
                system[3 * s + 1] = right[2 * k];
                system[3 * s + 2] = 1.0;
                params[s] = left[2 * k + 1];
                largest = fmax(largest, fmax(fabs(system[3 * s]), fabs(system[3 * s + 1])));
            }
            for (int i = 0; i < 9; ++i) scaled[i] = system[i] / largest;
            /* |det| of the scaled system at most 1e-6: a collinear or repeated sample, dropped */
            if (fabs(lu_factor(scaled, 3, pivot, &singular)) > 1e-6) {
                lu_factor(system, 3, pivot, &singular);
                lu_solve(system, 3, pivot, params);
                cost = 0.0;
                for (int64_t i = 0; i < n; ++i) {
                    double r = row_residual(params, left, right, rows[i]);
                    r = r > threshold ? threshold : r;
                    cost += r * r;
                }
            } else {
                params[0] = params[1] = params[2] = NAN;
            }
        }
        /* argmin: the first of equal costs, and the first NaN if any (torch propagates NaN). */
        if (h == 0 || (!isnan(best_cost) && (isnan(cost) || cost < best_cost))) {
            best_cost = cost;
            for (int i = 0; i < 3; ++i) best[i] = params[i];
        }
    }
    for (int i = 0; i < 3; ++i)
        best[i] = isnan(best[i]) ? 0.0 : (isinf(best[i]) ? copysign(DBL_MAX, best[i]) : best[i]);
}

/* _refit: least-squares (a, b, t_y) over the marked matches. */
static void refit(const double *left, const double *right, const uint8_t *inliers, int64_t K, double *params) {
    double normal[9] = {0}, rhs[3] = {0};
    for (int64_t k = 0; k < K; ++k) {
        if (!inliers[k]) continue;
        const double d[3] = {right[2 * k + 1], right[2 * k], 1.0};
        for (int i = 0; i < 3; ++i) {
            for (int j = 0; j < 3; ++j) normal[3 * i + j] += d[i] * d[j];
            rhs[i] += d[i] * left[2 * k + 1];
        }
    }
    for (int i = 0; i < 3; ++i) normal[4 * i] += 1e-9;
    int pivot[3], singular;
    lu_factor(normal, 3, pivot, &singular);
    for (int i = 0; i < 3; ++i) params[i] = rhs[i];
    lu_solve(normal, 3, pivot, params);
}

/* Step 5 (_keystone_refit with both turn terms, then _fit_keystone's significance test): whether a turn reads. */
static int reads_turn(const double *left, const double *right, const uint8_t *inliers, int64_t K, double height,
                      double width, double focal, const double *settings) {
    const double cy = (height - 1) / 2, cx = (width - 1) / 2;
    double normal[25] = {0}, rhs[5] = {0}, weight = 0.0;
    for (int64_t k = 0; k < K; ++k) {
        if (!inliers[k]) continue;
        const double u = right[2 * k] - cx, v = right[2 * k + 1] - cy;
        const double d[5] = {v, u, 1.0, u * v / focal, v * v / focal}, target = left[2 * k + 1] - cy;
        for (int i = 0; i < 5; ++i) {
            for (int j = 0; j < 5; ++j) normal[5 * i + j] += d[i] * d[j];
            rhs[i] += d[i] * target;
        }
        weight += 1.0;
    }
    for (int i = 0; i < 5; ++i) normal[6 * i] += 1e-9;
    int pivot[5], singular;
    lu_factor(normal, 5, pivot, &singular);
    double params[5];
    for (int i = 0; i < 5; ++i) params[i] = rhs[i];
    lu_solve(normal, 5, pivot, params);
    double squares = 0.0;
    for (int64_t k = 0; k < K; ++k) {
        if (!inliers[k]) continue;
        const double u = right[2 * k] - cx, v = right[2 * k + 1] - cy;
        const double d[5] = {v, u, 1.0, u * v / focal, v * v / focal};
        double fitted = 0.0;
        for (int i = 0; i < 5; ++i) fitted += d[i] * params[i];
        const double residual = fitted - (left[2 * k + 1] - cy);
        squares += residual * residual;
    }
    const double variance = squares / fmax(weight - 5, 1.0);
    int reads = 0;
    for (int term = 3; term < 5; ++term) {
        double unit[5] = {0};
        unit[term] = 1.0;
        lu_solve(normal, 5, pivot, unit);  /* column `term` of the inverse: its diagonal entry */
        const double error = sqrt(fmax(unit[term] * variance, 0.0));
        const double degrees = fabs(atan(params[term] / params[0]) * DEGREES_PER_RADIAN);
        reads |= (degrees >= settings[KEYSTONE_MIN_DEG]) & (fabs(params[term]) >= settings[KEYSTONE_MIN_T] * error);
    }
    return reads;
}

/* left, right (B, K, 2) float64 pixels; valid (B, K) uint8; image_hw (B, 2) int64, each >= 1; seeds (B,) int64;
 * focal (B,) float64 or NULL (no keystone reading); settings (NUM_SETTINGS,) float64. Writes homography (B, 3, 3),
 * inliers (B, K) uint8 (the refit's, before the acceptance), accepted (B,) uint8, count (B,) int64 (of inliers),
 * correction (B,) float64 (0 where not accepted), reads_turn (B,) uint8. Returns -1 when memory could not be had. */
int row_alignment_fit(const double *left, const double *right, const uint8_t *valid, const int64_t *image_hw,
                      const int64_t *seeds, const double *focal, const double *settings, int64_t B, int64_t K,
                      double *homography, uint8_t *inliers, uint8_t *accepted, int64_t *count, double *correction,
                      uint8_t *turn, int64_t num_threads) {
    const double threshold = settings[THRESHOLD];
    int failed = 0;
#pragma omp parallel num_threads(thread_count(num_threads, B))
    {
        int64_t *rows = scratch(K, sizeof(int64_t));
        const int ready = scratch_ready(rows != NULL, &failed);
#pragma omp for schedule(dynamic, 1)
        for (int64_t p = 0; p < B; ++p) {
            if (!ready) continue;
            const double *pl = left + 2 * p * K, *pr = right + 2 * p * K;
            const uint8_t *pv = valid + p * K;
            uint8_t *pin = inliers + p * K;
            int64_t n = 0, raw = 0;
            for (int64_t k = 0; k < K; ++k) {
                if (!pv[k]) continue;
                rows[n++] = k;
                raw += fabs(pl[2 * k + 1] - pr[2 * k + 1]) < threshold;
            }
            /* torch's normal equations multiply every row, padding too, by its 0 / 1 weight: a non-finite
             * coordinate anywhere makes them NaN (0 * inf), so the pair is left unaligned, as there. */
            int finite = 1;
            for (int64_t k = 0; k < K; ++k)
                finite &= isfinite(pr[2 * k]) && isfinite(pr[2 * k + 1]) && isfinite(pl[2 * k + 1]);
            double best[3], params[3] = {NAN, NAN, NAN};
            best_hypothesis(pl, pr, rows, n, (uint64_t)seeds[p], (int64_t)settings[NUM_HYPOTHESES], threshold, best);
            for (int64_t k = 0; k < K; ++k) pin[k] = pv[k] && row_residual(best, pl, pr, k) < threshold;
            if (finite) refit(pl, pr, pin, K, params);
            int64_t c = 0;
            for (int64_t k = 0; k < K; ++k) c += (pin[k] = pv[k] && row_residual(params, pl, pr, k) < threshold);
            count[p] = c;
            /* _accept */
            const double a = params[0], b = params[1], t_y = params[2];
            const double height = (double)image_hw[2 * p], width = (double)image_hw[2 * p + 1];
            const double cy = (height - 1) / 2, cx = (width - 1) / 2;
            double *h = homography + 9 * p;
            const double similarity[9] = {a, -b, cx - (a * cx - b * cy), b, a, t_y, 0.0, 0.0, 1.0};
            const double centre_shift = (t_y + b * (width - 1) / 2) + (a - 1) * (height - 1) / 2;
            /* torch computes the share tests in float32: an int64 count times a Python float */
            const int64_t share_gain = (int64_t)ceilf((float)settings[MIN_GAIN_SHARE] * (float)raw);
            const int64_t gain = share_gain > (int64_t)settings[MIN_GAIN] ? share_gain : (int64_t)settings[MIN_GAIN];
            const double scale = 1 / fmax(hypot(a, b), 1e-12);
            const int ok = c >= (int64_t)settings[MIN_INLIERS]
                           && (float)c >= (float)settings[MIN_INLIER_SHARE] * (float)n
                           && fabs(atan2(b, a)) <= settings[MAX_ROLL_RAD]
                           && fabs(scale - 1) <= settings[MAX_SCALE_CHANGE]
                           && fabs(centre_shift) <= settings[MAX_SHIFT_FRACTION] * height
                           && c >= raw + gain && isfinite(a) && isfinite(b) && isfinite(t_y);
            accepted[p] = (uint8_t)ok;
            double move = 0.0;
            for (int i = 0; i < 9; ++i) h[i] = ok ? similarity[i] : (i % 4 == 0 ? 1.0 : 0.0);
            if (ok) {  /* _corner_row_move: the largest row move of the four corners */
                const double xs[4] = {0.0, width - 1, 0.0, width - 1}, ys[4] = {0.0, 0.0, height - 1, height - 1};
                for (int corner = 0; corner < 4; ++corner) {
                    const double row = (xs[corner] * h[3] + ys[corner] * h[4]) + h[5];
                    const double w = (xs[corner] * h[6] + ys[corner] * h[7]) + h[8];
                    const double moved = fabs(row / w - ys[corner]);
                    move = (moved > move || isnan(moved)) && !isnan(move) ? moved : move;
                }
            }
            correction[p] = move;
            turn[p] = focal != NULL && finite && reads_turn(pl, pr, pin, K, height, width, focal[p], settings);
        }
        free(rows);
    }
    return failed ? -1 : 0;
}
