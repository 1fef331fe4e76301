/* RANSAC over 7-point samples for the fundamental matrix, one pair start to finish, for
 * svs_torch.geometry.ransac.estimate_fundamental_ransac (the no-gradient path it takes for MSAC and RANSAC scoring;
 * its torch path stays the reference, and the only path for LMedS).
 *
 * Why: the torch path batches pairs and hypotheses into tensors, which pays when a batch is large, but one pair's
 * estimate is still about 1 900 small torch operations (a chunk of 96 samples solved, scored twice, locally
 * optimised, the winner polished), and their dispatch is nearly all of its time: 4.2 ms for one pair of 340
 * matches, 1.0 ms a pair at B = 8 (one thread), against 0.07 ms for OpenCV's findFundamentalMat. Here each pair
 * runs the same algorithm step for step (see ransac.py's docstring): the same SplitMix64 samples and
 * pre-verification rows, Hartley normalisation with one shared scale, the 7-point null space by LU in mixed
 * unknowns (pivoted over all nine where that block is ill-conditioned), the cubic's closed-form roots with two
 * Newton steps, float32 Sampson scores with the same guard, pre-verification keeping the best eighth, LO-RANSAC's
 * Tukey-weighted 8-point refits, the adaptive stopping rule, the final polish, and the float64 inliers in pixels.
 *
 * Not bit for bit: the LU, the 9x9 symmetric eigenproblem (cyclic Jacobi here, LAPACK there), the rank-2 projection
 * (one-sided Jacobi SVD here) and the sums run in their own order, so a model agrees with the torch path's to
 * about 1e-12 and a score to float32 round-off; where two hypotheses' scores tie to those bits the other one may
 * win, and its refits then end at nearly the same F. tests/geometry/test_ransac_kernel.py states the agreement.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp (svs_torch/core/kernels/loader.py). Loaded
 * through ctypes by svs_torch/geometry/kernels/__init__.py; pairs are shared among num_threads OpenMP threads.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "common.h"
#include "minimal_samples.h"

#define SAMPLE 7

/* The settings array's entries (svs_torch.geometry.kernels.ransac_fundamental writes them in this order). */
enum {
    S_THRESHOLD_PX, S_CONFIDENCE, S_MAX_ITERATIONS, S_CHUNK_SIZE, S_SCORING, S_LOCAL_OPTIMIZATION, S_PREVERIFICATION,
    S_POLISH, S_LO_STEPS, S_LO_WINDOW, S_LO_TOLERANCE, S_POLISH_STEPS, S_POLISH_WINDOW, S_DEGENERATE_PIVOT,
    S_FAST_PIVOT, S_MAX_ROOT_DETERMINANT, S_GUARD, S_PREVERIFY_POINTS, S_PREVERIFY_KEEP_RATIO, S_SIGN_TIE, S_COUNT
};

typedef struct {
    double threshold_px, confidence, lo_window, lo_tolerance, polish_window, degenerate_pivot, fast_pivot,
        max_root_determinant, guard, sign_tie;
    int64_t max_iterations, chunk_size, lo_steps, polish_steps, preverify_points, keep_ratio;
    int ransac_scoring, local_optimization, preverification, polish;
} Settings;

/* One pair's prepared rows (the torch path's _Problem): n valid rows in index order. */
typedef struct {
    int64_t n, subset_size;
    double *design;  /* (n, 9) rows a with x'^T F x = a . f, normalised points */
    double *quadratic; /* (n, 12) Sampson-denominator monomials */
    float *design32, *quadratic32; /* the same in float32, for the scores */
    int64_t *subset; /* the pre-verification rows, by increasing key */
    double t_left[9], t_right[9]; /* x_normalised = T x_px */
    double threshold_sq; /* threshold^2 in normalised units */
    double guard; /* added to the float32 scores' Sampson denominator (ransac_scoring._DENOMINATOR_GUARD) */
    int64_t preverify_points;
} Problem;

/* ransac_sampling._preverification_rows: the rows of the smallest keys (signed, as torch's int64 topk). */
static void preverification_rows(uint64_t seed, Problem *pr, int64_t points, int64_t *keys) {
    const uint64_t subset_seed = splitmix64(seed + GAMMA);
    for (int64_t r = 0; r < pr->n; ++r) keys[r] = (int64_t)splitmix64(subset_seed + (uint64_t)(r + 1) * GAMMA);
    const int64_t size = pr->n < points ? pr->n : points;
    for (int64_t i = 0; i < size; ++i) { /* selection by repeated minimum: size is at most 32 */
        int64_t best = -1;
        for (int64_t r = 0; r < pr->n; ++r) {
            if (keys[r] == INT64_MAX) continue;
            if (best < 0 || keys[r] < keys[best]) best = r;
        }
        pr->subset[i] = best;
        keys[best] = INT64_MAX; /* a real key equal to INT64_MAX is not reachable in practice (one in 2^64) */
    }
    pr->subset_size = size;
}

/* epipolar_distance._sampson_coefficients: g with (Fx)_1^2 + (Fx)_2^2 + (F^T x')_1^2 + (F^T x')_2^2 + guard = g . m. */
static void sampson_coefficients(const double *f, double guard, double *g) {
    const double f00 = f[0], f01 = f[1], f02 = f[2], f10 = f[3], f11 = f[4], f12 = f[5], f20 = f[6], f21 = f[7];
    g[0] = f00 * f00 + f10 * f10;
    g[1] = 2 * (f00 * f01 + f10 * f11);
    g[2] = f01 * f01 + f11 * f11;
    g[3] = 2 * (f00 * f02 + f10 * f12);
    g[4] = 2 * (f01 * f02 + f11 * f12);
    g[5] = f00 * f00 + f01 * f01;
    g[6] = 2 * (f00 * f10 + f01 * f11);
    g[7] = f10 * f10 + f11 * f11;
    g[8] = 2 * (f00 * f20 + f01 * f21);
    g[9] = 2 * (f10 * f20 + f11 * f21);
    g[10] = f02 * f02 + f12 * f12 + f20 * f20 + f21 * f21 + guard;
    g[11] = 1.0;
}

/* Hartley normalisation of n points (point_pairs.normalize_points_hartley): centroid and scale sqrt(2) / mean
 * distance (1 where the points coincide). */
static void hartley(const double *xy, int64_t n, double *centroid, double *scale) {
    double sx = 0.0, sy = 0.0, total = (double)n;
    for (int64_t i = 0; i < n; ++i) {
        sx += xy[2 * i];
        sy += xy[2 * i + 1];
    }
    const double safe = total > 0 ? total : 1.0;
    centroid[0] = sx / safe;
    centroid[1] = sy / safe;
    double spread = 0.0;
    for (int64_t i = 0; i < n; ++i) {
        const double dx = xy[2 * i] - centroid[0], dy = xy[2 * i + 1] - centroid[1];
        const double d2 = dx * dx + dy * dy;
        spread += d2 > 0 ? sqrt(d2) : 0.0;
    }
    const double mean = spread / safe;
    *scale = mean > 0 ? sqrt(2.0) / mean : 1.0;
}

/* ransac_scoring._prepare for one pair: normalised points with one shared scale, design rows and monomials. */
static void prepare(const double *left, const double *right, int64_t n, double threshold_px, Problem *pr) {
    double c_left[2], c_right[2], s_left, s_right;
    hartley(left, n, c_left, &s_left);
    hartley(right, n, c_right, &s_right);
    const double scale = sqrt(s_left * s_right);
    double shift_left[2], shift_right[2];
    for (int j = 0; j < 2; ++j) { /* as the torch path: the image's own shift, rescaled to the shared scale */
        shift_left[j] = (-c_left[j] * s_left) / s_left * scale;
        shift_right[j] = (-c_right[j] * s_right) / s_right * scale;
    }
    const double tl[9] = {scale, 0, shift_left[0], 0, scale, shift_left[1], 0, 0, 1};
    const double tr[9] = {scale, 0, shift_right[0], 0, scale, shift_right[1], 0, 0, 1};
    memcpy(pr->t_left, tl, sizeof tl);
    memcpy(pr->t_right, tr, sizeof tr);
    for (int64_t i = 0; i < n; ++i) {
        const double x = left[2 * i] * scale + shift_left[0], y = left[2 * i + 1] * scale + shift_left[1];
        const double xr = right[2 * i] * scale + shift_right[0], yr = right[2 * i + 1] * scale + shift_right[1];
        const double rh[3] = {xr, yr, 1.0}, lh[3] = {x, y, 1.0};
        double *a = pr->design + 9 * i, *q = pr->quadratic + 12 * i;
        for (int u = 0; u < 3; ++u)
            for (int v = 0; v < 3; ++v) a[3 * u + v] = rh[u] * lh[v];
        const double m[12] = {x * x, x * y, y * y, x, y, xr * xr, xr * yr, yr * yr, xr, yr, 1.0, 0.0};
        memcpy(q, m, sizeof m);
        for (int j = 0; j < 9; ++j) pr->design32[9 * i + j] = (float)a[j];
        for (int j = 0; j < 12; ++j) pr->quadratic32[12 * i + j] = (float)q[j];
    }
    pr->n = n;
    pr->threshold_sq = (threshold_px * scale) * (threshold_px * scale);
}

/* ransac_scoring._score of one model over a set of rows (all n, or the subset): float32 squared Sampson distances;
 * MSAC sum of min(d^2, t^2), or RANSAC's -count plus the MSAC tie-break, both over the pair's own rows. */
static double score(const Problem *pr, const double *f, int use_subset, double threshold_sq, int ransac) {
    float fn[9], gd[12];
    double g[12];
    sampson_coefficients(f, pr->guard, g);
    for (int j = 0; j < 9; ++j) fn[j] = (float)f[j];
    for (int j = 0; j < 12; ++j) gd[j] = (float)g[j];
    const float t = (float)threshold_sq;
    const int64_t rows = use_subset ? pr->subset_size : pr->n;
    float total = 0.0f;
    int64_t count = 0;
    for (int64_t i = 0; i < rows; ++i) {
        const int64_t r = use_subset ? pr->subset[i] : i;
        const float *a = pr->design32 + 9 * r, *q = pr->quadratic32 + 12 * r;
        float num = 0.0f, den = 0.0f;
        for (int j = 0; j < 9; ++j) num += fn[j] * a[j];
        for (int j = 0; j < 12; ++j) den += gd[j] * q[j];
        float d = (num * num) / den;
        count += d <= t;
        d = d > t ? t : d; /* torch.minimum: a NaN stays NaN */
        total += d;
    }
    if (!ransac) return (double)total;
    return (double)(total / t) / (double)(rows + 1) - (double)count;
}

/* ransac_scoring._sampson_sq of one model at row i: the float64 squared Sampson distance (normalised units) and its
 * denominator (clamped at 0: the expansion may round a sum of squares to -1e-16). */
static double sampson_sq(const Problem *pr, const double *f, const double *g, int64_t i, double *denominator) {
    const double *a = pr->design + 9 * i, *q = pr->quadratic + 12 * i;
    double algebraic = 0.0, den = 0.0;
    for (int j = 0; j < 9; ++j) algebraic += a[j] * f[j];
    for (int j = 0; j < 12; ++j) den += q[j] * g[j];
    den = den > 0.0 ? den : 0.0;
    *denominator = den;
    const double num = algebraic * algebraic;
    return den > 0.0 ? num / den : (num == 0.0 ? 0.0 : INFINITY);
}

/* LU with partial pivoting of the m x n (m >= n) row-major matrix a, in place (LAPACK getrf's algorithm: the
 * largest pivot of each column, the first on ties); swaps[j] is the row exchanged with row j. Returns
 * min |u_jj| > ratio * max |u_jj| (False for NaN). */
static int lu_factor(double *a, int m, int n, int *swaps, double ratio) {
    for (int j = 0; j < n; ++j) {
        int p = j;
        for (int i = j + 1; i < m; ++i)
            if (fabs(a[i * n + j]) > fabs(a[p * n + j])) p = i;
        swaps[j] = p;
        if (p != j)
            for (int k = 0; k < n; ++k) {
                const double t = a[j * n + k];
                a[j * n + k] = a[p * n + k];
                a[p * n + k] = t;
            }
        const double pivot = a[j * n + j];
        if (pivot != 0.0)
            for (int i = j + 1; i < m; ++i) a[i * n + j] /= pivot;
        for (int i = j + 1; i < m; ++i)
            for (int k = j + 1; k < n; ++k) a[i * n + k] -= a[i * n + j] * a[j * n + k];
    }
    double smallest = INFINITY, largest = 0.0;
    for (int j = 0; j < n; ++j) {
        const double u = fabs(a[j * n + j]);
        smallest = u < smallest ? u : smallest;
        largest = u > largest ? u : largest;
    }
    return smallest > ratio * largest;
}

/* minimal_solvers._mixing_matrix: the reflection I - 2 v v^T with v along (1, -2, 3, 5, -7, 11, 13, -17, 19). */
static void mixing_matrix(double *q) {
    const double raw[9] = {1.0, -2.0, 3.0, 5.0, -7.0, 11.0, 13.0, -17.0, 19.0};
    double norm = 0.0, v[9];
    for (int i = 0; i < 9; ++i) norm += raw[i] * raw[i];
    norm = sqrt(norm);
    for (int i = 0; i < 9; ++i) v[i] = raw[i] / norm;
    for (int i = 0; i < 9; ++i)
        for (int j = 0; j < 9; ++j) q[i * 9 + j] = (i == j ? 1.0 : 0.0) - 2.0 * v[i] * v[j];
}

/* minimal_solvers._nullspace_pivoted: null(A) of a 7 x 9 sample from the LU of A^T (9 x 7), rows basis (2, 9). */
static int nullspace_pivoted(const double *design, double ratio, double *basis) {
    double lu[63];
    int swaps[7];
    for (int i = 0; i < 9; ++i)
        for (int j = 0; j < 7; ++j) lu[i * 7 + j] = design[j * 9 + i];
    const int full = lu_factor(lu, 9, 7, swaps, ratio);
    for (int c = 0; c < 2; ++c) { /* solve L1^T x = -L2^T[:, c] (unit upper), then f = P [x; e_c] */
        double y[9];
        for (int i = 6; i >= 0; --i) {
            double v = -lu[(7 + c) * 7 + i];
            for (int k = i + 1; k < 7; ++k) v -= lu[k * 7 + i] * y[k];
            y[i] = v;
        }
        y[7] = c == 0 ? 1.0 : 0.0;
        y[8] = c == 1 ? 1.0 : 0.0;
        for (int j = 6; j >= 0; --j) {
            const double t = y[j];
            y[j] = y[swaps[j]];
            y[swaps[j]] = t;
        }
        memcpy(basis + 9 * c, y, sizeof y);
    }
    return full;
}

/* minimal_solvers._nullspace_7 for one sample (7 design rows): two orthonormal rows spanning the null space, and
 * whether the sample has rank 7. */
static int nullspace_7(const double *design, const double *mixing, const Settings *st, double *basis) {
    double mixed[63], block[49], rhs[14];
    for (int i = 0; i < 7; ++i)
        for (int j = 0; j < 9; ++j) {
            double v = 0.0;
            for (int k = 0; k < 9; ++k) v += design[i * 9 + k] * mixing[k * 9 + j];
            mixed[i * 9 + j] = v;
        }
    for (int i = 0; i < 7; ++i) {
        for (int j = 0; j < 7; ++j) block[i * 7 + j] = mixed[i * 9 + j];
        rhs[i * 2] = -mixed[i * 9 + 7];
        rhs[i * 2 + 1] = -mixed[i * 9 + 8];
    }
    int swaps[7];
    int full = lu_factor(block, 7, 7, swaps, st->fast_pivot);
    if (full) {
        for (int j = 0; j < 7; ++j) /* the right-hand sides permuted as the rows were, then L y = b, U x = y */
            if (swaps[j] != j)
                for (int c = 0; c < 2; ++c) {
                    const double t = rhs[j * 2 + c];
                    rhs[j * 2 + c] = rhs[swaps[j] * 2 + c];
                    rhs[swaps[j] * 2 + c] = t;
                }
        for (int c = 0; c < 2; ++c) {
            double x[7];
            for (int i = 0; i < 7; ++i) {
                double v = rhs[i * 2 + c];
                for (int k = 0; k < i; ++k) v -= block[i * 7 + k] * x[k];
                x[i] = v;
            }
            for (int i = 6; i >= 0; --i) {
                double v = x[i];
                for (int k = i + 1; k < 7; ++k) v -= block[i * 7 + k] * x[k];
                x[i] = v / block[i * 7 + i];
            }
            double g[9];
            for (int i = 0; i < 7; ++i) g[i] = x[i];
            g[7] = c == 0 ? 1.0 : 0.0;
            g[8] = c == 1 ? 1.0 : 0.0;
            for (int i = 0; i < 9; ++i) { /* f = Q g */
                double v = 0.0;
                for (int k = 0; k < 9; ++k) v += g[k] * mixing[i * 9 + k];
                basis[9 * c + i] = v;
            }
        }
    } else {
        full = nullspace_pivoted(design, st->degenerate_pivot, basis);
    }
    double *first = basis, *second = basis + 9, dot = 0.0, norm = 0.0; /* Gram-Schmidt (_orthonormalize) */
    for (int i = 0; i < 9; ++i) norm += first[i] * first[i];
    norm = 1.0 / sqrt(norm);
    for (int i = 0; i < 9; ++i) first[i] *= norm;
    for (int i = 0; i < 9; ++i) dot += first[i] * second[i];
    norm = 0.0;
    for (int i = 0; i < 9; ++i) {
        second[i] -= dot * first[i];
        norm += second[i] * second[i];
    }
    norm = 1.0 / sqrt(norm);
    for (int i = 0; i < 9; ++i) second[i] *= norm;
    return full;
}

static double determinant3(const double *m) {
    return m[0] * (m[4] * m[8] - m[5] * m[7]) - m[1] * (m[3] * m[8] - m[5] * m[6]) + m[2] * (m[3] * m[7] - m[4] * m[6]);
}

/* minimal_solvers.real_cubic_roots of a t^3 + b t^2 + c t + d, step for step; returns how many leading roots are
 * valid (3 or 1; 0 where a = 0 or a root is not finite). */
static int real_cubic_roots(const double *coefficients, double *roots, int *valid) {
    double scale = 0.0;
    for (int i = 0; i < 4; ++i) scale = fabs(coefficients[i]) > scale ? fabs(coefficients[i]) : scale;
    const double s = scale > 0 ? scale : 1.0;
    const double a = coefficients[0] / s, b = coefficients[1] / s, c = coefficients[2] / s, d = coefficients[3] / s;
    const int has_cubic = a != 0.0;
    const double a_safe = has_cubic ? a : 1.0;
    const double p = b / a_safe, q = c / a_safe, r = d / a_safe;
    const double big_p = q - p * p / 3.0;
    const double big_q = 2.0 * (p * p * p) / 27.0 - p * q / 3.0 + r;
    const double discriminant = (big_q / 2.0) * (big_q / 2.0) + (big_p / 3.0) * (big_p / 3.0) * (big_p / 3.0);
    const int three = discriminant < 0;
    const double inside = -big_p / 3.0;
    const double m = 2.0 * sqrt(inside > 0.0 ? inside : 0.0);
    double cos_3theta = three ? 3.0 * big_q / (big_p * m) : 0.0;
    cos_3theta = cos_3theta < -1.0 ? -1.0 : (cos_3theta > 1.0 ? 1.0 : cos_3theta);
    const double theta = acos(cos_3theta) / 3.0;
    const double shifts[3] = {0.0, -2.0 * M_PI / 3.0, -4.0 * M_PI / 3.0};
    const double sqrt_disc = sqrt(discriminant > 0.0 ? discriminant : 0.0);
    const double w = -big_q / 2.0 - (big_q >= 0 ? sqrt_disc : -sqrt_disc);
    const double u = (w > 0 ? 1.0 : (w < 0 ? -1.0 : 0.0)) * pow(fabs(w), 1.0 / 3.0);
    const double single = u != 0.0 ? u - big_p / (3.0 * u) : 0.0;
    for (int k = 0; k < 3; ++k) {
        double root = (three ? m * cos(theta + shifts[k]) : single) - p / 3.0;
        for (int step = 0; step < 2; ++step) {
            const double value = ((a * root + b) * root + c) * root + d;
            const double slope = (3.0 * a * root + 2.0 * b) * root + c;
            if (slope != 0.0) root = root - value / slope;
        }
        valid[k] = (three || k == 0) && has_cubic && isfinite(root);
        roots[k] = valid[k] ? root : 0.0;
    }
    return 0;
}

/* minimal_solvers._seven_point_from_design for one sample: up to 3 unit-norm models (9 each) and their validity. */
static void seven_point(const double *design, const double *mixing, const Settings *st, double *models,
                        uint8_t *usable) {
    /* values at the nodes -1, 0, 1, 2 to (a, b, c, d): the inverse Vandermonde matrix, exactly */
    static const double TO_COEFFICIENTS[4][4] = {
        {-1.0 / 6.0, 0.5, -1.0 / 3.0, 0.0},
        {0.5, -1.0, -0.5, 1.0},
        {-0.5, 0.5, 1.0, 0.0},
        {1.0 / 6.0, 0.0, -1.0 / 6.0, 0.0}};
    static const double NODES[4] = {-1.0, 0.0, 1.0, 2.0};
    double basis[18];
    const int full = nullspace_7(design, mixing, st, basis);
    double x[9], d[9], values[4], forward[4], coefficients[4];
    for (int i = 0; i < 9; ++i) {
        x[i] = basis[9 + i];
        d[i] = basis[i] - x[i];
    }
    for (int k = 0; k < 4; ++k) {
        double m[9];
        for (int i = 0; i < 9; ++i) m[i] = x[i] + NODES[k] * d[i];
        values[k] = determinant3(m);
    }
    for (int j = 0; j < 4; ++j) {
        double v = 0.0;
        for (int k = 0; k < 4; ++k) v += values[k] * TO_COEFFICIENTS[k][j];
        forward[j] = v;
    }
    const int reverse = fabs(forward[0]) < fabs(forward[3]);
    for (int j = 0; j < 4; ++j) coefficients[j] = reverse ? forward[3 - j] : forward[j];
    double roots[3];
    int valid[3];
    real_cubic_roots(coefficients, roots, valid);
    const double *big = reverse ? d : x, *small = reverse ? x : d;
    for (int k = 0; k < 3; ++k) {
        double *f = models + 9 * k, norm = 0.0;
        for (int i = 0; i < 9; ++i) {
            f[i] = big[i] + roots[k] * small[i];
            norm += f[i] * f[i];
        }
        norm = sqrt(norm);
        if (norm > 0)
            for (int i = 0; i < 9; ++i) f[i] /= norm;
        usable[k] = valid[k] && full && fabs(determinant3(f)) <= st->max_root_determinant;
        if (!usable[k]) memset(f, 0, 9 * sizeof(double));
    }
}

/* The eigenvector of the smallest eigenvalue of a symmetric 9 x 9 matrix (torch.linalg.eigh's first column), by
 * cyclic Jacobi rotations until the off-diagonal part is negligible. */
static void smallest_eigenvector(double *a, double *vector) {
    double v[81];
    for (int i = 0; i < 81; ++i) v[i] = (i % 10 == 0) ? 1.0 : 0.0;
    for (int sweep = 0; sweep < 64; ++sweep) {
        double off = 0.0, diagonal = 0.0;
        for (int p = 0; p < 9; ++p) {
            diagonal += a[p * 9 + p] * a[p * 9 + p];
            for (int q = p + 1; q < 9; ++q) off += a[p * 9 + q] * a[p * 9 + q];
        }
        if (!(off > 1e-34 * diagonal)) break; /* also ends on NaN */
        for (int p = 0; p < 8; ++p)
            for (int q = p + 1; q < 9; ++q) {
                const double apq = a[p * 9 + q];
                if (apq == 0.0) continue;
                const double theta = (a[q * 9 + q] - a[p * 9 + p]) / (2.0 * apq);
                const double t = (theta >= 0 ? 1.0 : -1.0) / (fabs(theta) + sqrt(theta * theta + 1.0));
                const double c = 1.0 / sqrt(t * t + 1.0), s = t * c;
                for (int k = 0; k < 9; ++k) { /* A <- A J (columns p, q) */
                    const double akp = a[k * 9 + p], akq = a[k * 9 + q];
                    a[k * 9 + p] = c * akp - s * akq;
                    a[k * 9 + q] = s * akp + c * akq;
                }
                for (int k = 0; k < 9; ++k) { /* A <- J^T A (rows p, q) */
                    const double apk = a[p * 9 + k], aqk = a[q * 9 + k];
                    a[p * 9 + k] = c * apk - s * aqk;
                    a[q * 9 + k] = s * apk + c * aqk;
                }
                for (int k = 0; k < 9; ++k) {
                    const double vkp = v[k * 9 + p], vkq = v[k * 9 + q];
                    v[k * 9 + p] = c * vkp - s * vkq;
                    v[k * 9 + q] = s * vkp + c * vkq;
                }
            }
    }
    int smallest = 0;
    for (int i = 1; i < 9; ++i)
        if (a[i * 9 + i] < a[smallest * 9 + smallest]) smallest = i;
    for (int i = 0; i < 9; ++i) vector[i] = v[i * 9 + smallest];
}

/* minimal_solvers.enforce_rank2: F minus its component along the right singular vector of the smallest singular
 * value (one-sided Jacobi SVD of the 3 x 3 matrix): U diag(s1, s2, 0) V^T. */
static void enforce_rank2(double *f) {
    double u[9], v[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1};
    memcpy(u, f, sizeof u);
    for (int sweep = 0; sweep < 32; ++sweep) {
        int rotated = 0;
        for (int i = 0; i < 2; ++i)
            for (int j = i + 1; j < 3; ++j) {
                double alpha = 0.0, beta = 0.0, gamma = 0.0;
                for (int k = 0; k < 3; ++k) {
                    alpha += u[k * 3 + i] * u[k * 3 + i];
                    beta += u[k * 3 + j] * u[k * 3 + j];
                    gamma += u[k * 3 + i] * u[k * 3 + j];
                }
                if (!(fabs(gamma) > 1e-17 * sqrt(alpha * beta))) continue;
                rotated = 1;
                const double zeta = (beta - alpha) / (2.0 * gamma);
                const double t = (zeta >= 0 ? 1.0 : -1.0) / (fabs(zeta) + sqrt(1.0 + zeta * zeta));
                const double c = 1.0 / sqrt(1.0 + t * t), s = c * t;
                for (int k = 0; k < 3; ++k) {
                    const double ui = u[k * 3 + i], uj = u[k * 3 + j];
                    u[k * 3 + i] = c * ui - s * uj;
                    u[k * 3 + j] = s * ui + c * uj;
                    const double vi = v[k * 3 + i], vj = v[k * 3 + j];
                    v[k * 3 + i] = c * vi - s * vj;
                    v[k * 3 + j] = s * vi + c * vj;
                }
            }
        if (!rotated) break;
    }
    int smallest = 0;
    double least = INFINITY;
    for (int j = 0; j < 3; ++j) {
        const double norm = u[j] * u[j] + u[3 + j] * u[3 + j] + u[6 + j] * u[6 + j];
        if (norm < least) {
            least = norm;
            smallest = j;
        }
    }
    const double n0 = v[smallest], n1 = v[3 + smallest], n2 = v[6 + smallest];
    for (int r = 0; r < 3; ++r) {
        const double along = f[r * 3] * n0 + f[r * 3 + 1] * n1 + f[r * 3 + 2] * n2;
        f[r * 3] -= along * n0;
        f[r * 3 + 1] -= along * n1;
        f[r * 3 + 2] -= along * n2;
    }
}

/* ransac_refine._reweighted_refit: the Tukey-weighted 8-point refit of f within window x threshold; returns whether
 * the model had the 8 inliers a fit needs. */
static int reweighted_refit(const Problem *pr, const double *f, double window, double *refit) {
    double g[12], normal[81] = {0};
    sampson_coefficients(f, 0.0, g);
    const double threshold_sq = pr->threshold_sq, window_sq = window * window * threshold_sq;
    int64_t inliers = 0;
    for (int64_t i = 0; i < pr->n; ++i) {
        double den;
        const double d2 = sampson_sq(pr, f, g, i, &den);
        const int near = d2 <= window_sq && den > 0;
        if (!near) continue;
        inliers += d2 <= threshold_sq;
        double tukey = 1.0 - d2 / window_sq;
        tukey = tukey > 0.0 ? tukey : 0.0;
        const double w = tukey * tukey / den;
        const double *a = pr->design + 9 * i;
        for (int p = 0; p < 9; ++p) {
            const double wa = a[p] * w;
            for (int q = 0; q < 9; ++q) normal[p * 9 + q] += wa * a[q];
        }
    }
    smallest_eigenvector(normal, refit);
    enforce_rank2(refit);
    return inliers >= 8;
}

/* The refit loop shared by local optimisation (LOCAL_OPTIMIZATION_*) and the polish (POLISH_*): refits kept while
 * they lower the loss, stopped once one gains less than the tolerance. */
static double refine(const Problem *pr, const Settings *st, double *model, double loss, int64_t steps, double window,
                     double score_threshold_sq, int ransac, int running) {
    double refit[9];
    for (int64_t step = 0; step < steps; ++step) {
        const int enough = reweighted_refit(pr, model, window, refit);
        const double refit_loss = (enough && running) ? score(pr, refit, 0, score_threshold_sq, ransac) : INFINITY;
        const int better = refit_loss < loss;
        if (better) memcpy(model, refit, sizeof refit);
        running = better && refit_loss < loss - st->lo_tolerance * fabs(loss);
        if (better) loss = refit_loss;
        if (!running) break;
    }
    return loss;
}

/* ransac._required_iterations. */
static int64_t required_iterations(int64_t inliers, int64_t n, const Settings *st) {
    if (st->confidence >= 1.0) return st->max_iterations;
    const double ratio = (double)inliers / (double)(n > 1 ? n : 1);
    const double all_good = pow(ratio, SAMPLE);
    const double per_draw = log1p(-(all_good < 1.0 ? all_good : 1.0));
    double needed = all_good > 0 ? log1p(-st->confidence) / per_draw : INFINITY;
    if (isnan(needed)) return INT64_MIN; /* what torch's NaN.long() gives on x86: the pair stops */
    needed = needed < (double)st->max_iterations ? needed : (double)st->max_iterations;
    return (int64_t)ceil(needed);
}

/* Scratch of one thread: a pair's rows and a chunk's models. */
typedef struct {
    double *left, *right, *models, *rough;
    int64_t *keys, *kept;
    uint8_t *usable, *taken;
} Work;

/* a before b in torch.topk(largest=False)'s order: NaN after every number. */
static int ranks_lower(double a, double b) { return isnan(b) ? !isnan(a) : a < b; }

/* ransac._best_of_chunk: the chunk's best model (by the full score, the first on ties) among the best
 * ceil(S / PREVERIFY_KEEP_RATIO) on the pre-verification rows; returns its loss (inf: none usable). */
static double best_of_chunk(const Problem *pr, const Settings *st, Work *w, int64_t models, double *best) {
    const int64_t keep = (models + st->keep_ratio - 1) / st->keep_ratio;
    int64_t kept = models;
    for (int64_t s = 0; s < models; ++s) w->kept[s] = s;
    if (st->preverification && keep < models) {
        for (int64_t s = 0; s < models; ++s) {
            w->rough[s] = w->usable[s] ? score(pr, w->models + 9 * s, 1, pr->threshold_sq, st->ransac_scoring)
                                       : INFINITY;
            w->taken[s] = 0;
        }
        for (int64_t i = 0; i < keep; ++i) { /* the keep smallest, the earlier first on ties */
            int64_t pick = -1;
            for (int64_t s = 0; s < models; ++s)
                if (!w->taken[s] && (pick < 0 || ranks_lower(w->rough[s], w->rough[pick]))) pick = s;
            if (pick < 0) break; /* not reached: keep < models */
            w->taken[pick] = 1;
        }
        kept = 0;
        for (int64_t s = 0; s < models; ++s) /* in hypothesis order */
            if (w->taken[s]) w->kept[kept++] = s;
    }
    double best_loss = INFINITY;
    int64_t best_index = w->kept[0];
    for (int64_t i = 0; i < kept; ++i) {
        const int64_t s = w->kept[i];
        const double loss = w->usable[s] ? score(pr, w->models + 9 * s, 0, pr->threshold_sq, st->ransac_scoring)
                                         : INFINITY;
        if (loss < best_loss) {
            best_loss = loss;
            best_index = s;
        }
    }
    memcpy(best, w->models + 9 * best_index, 9 * sizeof(double));
    return best_loss;
}

/* ransac._search for one pair: the chunk loop with local optimisation and the stopping rule. Writes the best
 * model (normalised) and returns its loss; *iterations the hypotheses drawn. */
static double search(const Problem *pr, const Settings *st, Work *w, uint64_t seed, const double *mixing,
                     double *best, int64_t *iterations) {
    double best_loss = INFINITY, raw_loss = INFINITY, candidate[9], sample[63], g[12];
    memset(best, 0, 9 * sizeof(double));
    *iterations = 0;
    if (pr->n < SAMPLE) return best_loss;
    for (int64_t first = 0; first < st->max_iterations; first += st->chunk_size) {
        const int64_t count = st->chunk_size < st->max_iterations - first ? st->chunk_size
                                                                            : st->max_iterations - first;
        for (int64_t h = 0; h < count; ++h) {
            int64_t ranks[SAMPLE];
            draw_minimal_sample(seed, first + h, pr->n, SAMPLE, ranks);  /* draw_minimal_samples */
            for (int r = 0; r < SAMPLE; ++r) memcpy(sample + 9 * r, pr->design + 9 * ranks[r], 9 * sizeof(double));
            seven_point(sample, mixing, st, w->models + 27 * h, w->usable + 3 * h);
        }
        double loss = best_of_chunk(pr, st, w, 3 * count, candidate);
        const int new_raw = loss < raw_loss;
        if (new_raw) raw_loss = loss;
        if (st->local_optimization && new_raw)
            loss = refine(pr, st, candidate, loss, st->lo_steps, st->lo_window, pr->threshold_sq,
                          st->ransac_scoring, 1);
        if (loss < best_loss) {
            best_loss = loss;
            memcpy(best, candidate, sizeof candidate);
        }
        int64_t inliers = 0;
        if (isfinite(best_loss)) {
            sampson_coefficients(best, 0.0, g);
            for (int64_t i = 0; i < pr->n; ++i) {
                double den;
                inliers += sampson_sq(pr, best, g, i, &den) <= pr->threshold_sq;
            }
        }
        *iterations = first + count;
        if (required_iterations(inliers, pr->n, st) <= first + count) break;
    }
    return best_loss;
}

/* ransac._finish's model: F = T_right^T F_n T_left, unit Frobenius norm, its largest-magnitude entry positive: the
 * first, in row-major order, within sign_tie (minimal_solvers.SIGN_TIE_TOLERANCE) of the largest (a translation's
 * F is skew-symmetric, its largest entries tied in magnitude and opposite in sign). */
static void to_pixels(const Problem *pr, const double *fn, double sign_tie, double *f) {
    double tmp[9];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            double v = 0.0;
            for (int k = 0; k < 3; ++k) v += fn[i * 3 + k] * pr->t_left[k * 3 + j];
            tmp[i * 3 + j] = v;
        }
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            double v = 0.0;
            for (int k = 0; k < 3; ++k) v += pr->t_right[k * 3 + i] * tmp[k * 3 + j];
            f[i * 3 + j] = v;
        }
    double norm = 0.0, top = 0.0;
    for (int i = 0; i < 9; ++i) {
        norm += f[i] * f[i];
        top = fabs(f[i]) > top ? fabs(f[i]) : top;
    }
    int largest = 0;
    while (largest < 8 && !(fabs(f[largest]) >= top * (1.0 - sign_tie))) ++largest;
    norm = sqrt(norm);
    const double sign = f[largest] < 0 ? -1.0 : 1.0;
    for (int i = 0; i < 9; ++i) f[i] = norm > 0 ? f[i] * sign / norm : 0.0;
}

static void read_settings(const double *values, Settings *st) {
    st->threshold_px = values[S_THRESHOLD_PX];
    st->confidence = values[S_CONFIDENCE];
    st->max_iterations = (int64_t)values[S_MAX_ITERATIONS];
    st->chunk_size = (int64_t)values[S_CHUNK_SIZE];
    st->ransac_scoring = values[S_SCORING] != 0.0;
    st->local_optimization = values[S_LOCAL_OPTIMIZATION] != 0.0;
    st->preverification = values[S_PREVERIFICATION] != 0.0;
    st->polish = values[S_POLISH] != 0.0;
    st->lo_steps = (int64_t)values[S_LO_STEPS];
    st->lo_window = values[S_LO_WINDOW];
    st->lo_tolerance = values[S_LO_TOLERANCE];
    st->polish_steps = (int64_t)values[S_POLISH_STEPS];
    st->polish_window = values[S_POLISH_WINDOW];
    st->degenerate_pivot = values[S_DEGENERATE_PIVOT];
    st->fast_pivot = values[S_FAST_PIVOT];
    st->max_root_determinant = values[S_MAX_ROOT_DETERMINANT];
    st->guard = values[S_GUARD];
    st->preverify_points = (int64_t)values[S_PREVERIFY_POINTS];
    st->keep_ratio = (int64_t)values[S_PREVERIFY_KEEP_RATIO];
    st->sign_tie = values[S_SIGN_TIE];
}

/* One pair from its valid rows to F in pixels and its inliers (ransac.estimate_fundamental_ransac after the
 * arguments are checked). */
static void one_pair(const double *left, const double *right, const uint8_t *valid, int64_t K, uint64_t seed,
                     const Settings *st, const double *mixing, Work *w, Problem *pr, double *f, uint8_t *found,
                     int64_t *iterations, uint8_t *inliers) {
    int64_t n = 0;
    for (int64_t k = 0; k < K; ++k)
        if (valid[k]) {
            w->left[2 * n] = left[2 * k];
            w->left[2 * n + 1] = left[2 * k + 1];
            w->right[2 * n] = right[2 * k];
            w->right[2 * n + 1] = right[2 * k + 1];
            ++n;
        }
    pr->guard = st->guard;
    pr->preverify_points = st->preverify_points;
    prepare(w->left, w->right, n, st->threshold_px, pr);
    preverification_rows(seed, pr, st->preverify_points, w->keys);
    double best[9];
    double loss = search(pr, st, w, seed, mixing, best, iterations);
    if (st->polish && isfinite(loss)) {
        const double window_sq = st->polish_window * st->polish_window * pr->threshold_sq;
        refine(pr, st, best, score(pr, best, 0, window_sq, 0), st->polish_steps, st->polish_window, window_sq, 0, 1);
    }
    to_pixels(pr, best, st->sign_tie, f);
    *found = isfinite(loss);
    const double threshold_sq = st->threshold_px * st->threshold_px;
    for (int64_t k = 0; k < K; ++k) { /* the exact float64 Sampson distance in pixels (_finish) */
        const double x[3] = {left[2 * k], left[2 * k + 1], 1.0}, xr[3] = {right[2 * k], right[2 * k + 1], 1.0};
        double line_right[3], line_left[3];
        for (int i = 0; i < 3; ++i) {
            line_right[i] = f[i * 3] * x[0] + f[i * 3 + 1] * x[1] + f[i * 3 + 2] * x[2];
            line_left[i] = f[i] * xr[0] + f[3 + i] * xr[1] + f[6 + i] * xr[2];
        }
        const double algebraic = xr[0] * line_right[0] + xr[1] * line_right[1] + xr[2] * line_right[2];
        const double den = line_right[0] * line_right[0] + line_right[1] * line_right[1] +
                           line_left[0] * line_left[0] + line_left[1] * line_left[1];
        const double num = algebraic * algebraic;
        const double d2 = den > 0 ? num / den : (num == 0.0 ? 0.0 : INFINITY);
        inliers[k] = valid[k] && *found && d2 <= threshold_sq;
    }
}

/* points_left, points_right (B, K, 2) float64; valid (B, K) uint8; seeds (B,) int64; settings (S_COUNT,) float64.
 * Writes F (B, 3, 3) float64 in pixels (the zero matrix where no model was found), found (B,) uint8, iterations
 * (B,) int64 and inliers (B, K) uint8. Returns -1 when memory could not be had (the caller runs the torch path). */
int ransac_fundamental(const double *points_left, const double *points_right, const uint8_t *valid,
                       const int64_t *seeds, const double *settings, int64_t B, int64_t K, double *F, uint8_t *found,
                       int64_t *iterations, uint8_t *inliers, int64_t num_threads) {
    Settings st;
    read_settings(settings, &st);
    double mixing[81];
    mixing_matrix(mixing);
    const int64_t models = 3 * st.chunk_size;
    const int threads = thread_count(num_threads, B);
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        Work w = {scratch(2 * K, sizeof(double)), scratch(2 * K, sizeof(double)), scratch(9 * models, sizeof(double)),
                  scratch(models, sizeof(double)), scratch(K, sizeof(int64_t)), scratch(models, sizeof(int64_t)),
                  scratch(models, 1), scratch(models, 1)};
        Problem pr = {0};
        pr.design = scratch(9 * K, sizeof(double));
        pr.quadratic = scratch(12 * K, sizeof(double));
        pr.design32 = scratch(9 * K, sizeof(float));
        pr.quadratic32 = scratch(12 * K, sizeof(float));
        pr.subset = scratch(st.preverify_points, sizeof(int64_t));
        const int ready = scratch_ready(w.left && w.right && w.models && w.rough && w.keys && w.kept && w.usable &&
                                            w.taken && pr.design && pr.quadratic && pr.design32 && pr.quadratic32 &&
                                            pr.subset,
                                        &failed);
#pragma omp for schedule(dynamic, 1)
        for (int64_t p = 0; p < B; ++p) {
            if (!ready) continue;
            one_pair(points_left + p * K * 2, points_right + p * K * 2, valid + p * K, K, (uint64_t)seeds[p],
                     &st, mixing, &w, &pr, F + 9 * p, found + p, iterations + p, inliers + p * K);
        }
        free(w.left), free(w.right), free(w.models), free(w.rough), free(w.keys), free(w.kept), free(w.usable);
        free(w.taken), free(pr.design), free(pr.quadratic), free(pr.design32), free(pr.quadratic32), free(pr.subset);
    }
    return failed ? -1 : 0;
}
