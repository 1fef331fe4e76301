/* Hartley's uncalibrated rectification with the "parallel" x row, for svs_torch.geometry.rectification.
 * rectify_uncalibrated (the no-gradient path; its torch code stays the reference, the differentiable path and the
 * "hartley" mode's).
 *
 * Why: the torch path is about 180 small operations on 3 x 3 matrices (products, cross products, norms, a
 * determinant, an arctangent, the status tests), each paying torch's dispatch: about 2.5 ms for one pair, a
 * twentieth of guide's frame, for work of a few hundred flops. Here each pair is one pass in registers, the same
 * float64 steps in the same order as the torch code (matrix products summed over k in order, as torch's small
 * batched product does; no contraction to fused multiply-adds), except three that torch computes its own way:
 * the cross products of the adjugate, the norms and the determinant of the area test (here the rule of Sarrus).
 * Homographies and epipoles therefore agree with the torch path to the last bits, not bit for bit, and a status
 * can differ only where a test's value ties its threshold to those bits. The RMS row error over the inliers is
 * computed in the output's dtype from the homographies rounded to it, as the torch path does, summed in match
 * order (equal within that dtype's round-off).
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp (svs_torch/core/kernels/loader.py). Loaded
 * through ctypes by svs_torch/geometry/kernels/__init__.py; pairs are shared among num_threads OpenMP threads.
 */
#include <math.h>
#include <stdint.h>

#include "common.h"

/* 180 / pi, the constant torch.rad2deg multiplies by. */
#define DEGREES_PER_RADIAN 57.295779513082320876798154814105170332405472466564

/* RectificationStatus's values (svs_torch/geometry/rectification.py). */
enum { OK = 0, NOT_ENOUGH_INLIERS = 1, DEGENERATE = 2, EPIPOLE_IN_IMAGE = 3, DISTORTED = 4 };

/* c = a b for 3 x 3 row-major matrices, each entry summed over k in order from 0 (torch's small bmm). */
static void product(const double *a, const double *b, double *c) {
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) {
            double sum = 0.0;
            for (int k = 0; k < 3; ++k) sum += a[3 * i + k] * b[3 * k + j];
            c[3 * i + j] = sum;
        }
    }
}

static void cross(const double *a, const double *b, double *c) {
    c[0] = a[1] * b[2] - a[2] * b[1];
    c[1] = a[2] * b[0] - a[0] * b[2];
    c[2] = a[0] * b[1] - a[1] * b[0];
}

static double norm3(double x, double y, double z) { return sqrt(x * x + y * y + z * z); }

/* torch's argmax of three: the first of equal values, and the first NaN if any. */
static int argmax3(const double *v) {
    int best = 0;
    for (int i = 1; i < 3 && !isnan(v[best]); ++i)
        if (isnan(v[i]) || v[i] > v[best]) best = i;
    return best;
}

/* _epipoles: unit right and left epipoles of the centred F ``fn`` from its adjugate; returns rank >= 2. */
static int epipoles(const double *fn, double *right, double *left) {
    double col[3][3], adj[9];
    for (int c = 0; c < 3; ++c)
        for (int r = 0; r < 3; ++r) col[c][r] = fn[3 * r + c];
    cross(col[1], col[2], adj);
    cross(col[2], col[0], adj + 3);
    cross(col[0], col[1], adj + 6);
    double adj_sq = 0.0, f_sq = 0.0;
    for (int i = 0; i < 9; ++i) {
        adj_sq += adj[i] * adj[i];
        f_sq += fn[i] * fn[i];
    }
    const double f_norm = sqrt(f_sq);
    const int rank2 = sqrt(adj_sq) > 1e-9 * (f_norm * f_norm);  /* _RANK_TOLERANCE */
    if (!rank2)
        for (int i = 0; i < 9; ++i) adj[i] = (i % 4 == 0) ? 1.0 : 0.0;
    double row_norms[3], column_norms[3];
    for (int i = 0; i < 3; ++i) {
        row_norms[i] = norm3(adj[3 * i], adj[3 * i + 1], adj[3 * i + 2]);
        column_norms[i] = norm3(adj[i], adj[3 + i], adj[6 + i]);
    }
    const int row = argmax3(row_norms), column = argmax3(column_norms);
    const double rn = norm3(adj[3 * row], adj[3 * row + 1], adj[3 * row + 2]);
    const double cn = norm3(adj[column], adj[3 + column], adj[6 + column]);
    for (int i = 0; i < 3; ++i) {
        right[i] = adj[3 * row + i] / rn;
        left[i] = adj[3 * i + column] / cn;
    }
    return rank2;
}

/* _right_homography: H' = G R in the centred frame; returns whether the epipole is off the centre. */
static int right_homography(const double *e, double *h) {
    double norm = hypot(e[0], e[1]);
    const int off_centre = norm > 1e-12;
    if (!off_centre) norm = 1.0;
    const double side = e[0] >= 0 ? 1.0 : -1.0;
    const double cos_ = side * e[0] / norm, sin_ = side * e[1] / norm, u = side * norm;
    const double g = -e[2] / u;
    const double rows[9] = {cos_, sin_, 0.0, -sin_, cos_, 0.0, g * cos_, g * sin_, 1.0};
    for (int i = 0; i < 9; ++i) h[i] = rows[i];
    return off_centre;
}

/* _left_homography with the conformal ("parallel") x row; returns whether its line at infinity misses the
 * centre. */
static int left_homography(const double *fn, const double *e, const double *h_right, double *h) {
    const double minus_skew[9] = {-0.0, e[2], -e[1], -e[2], -0.0, e[0], e[1], -e[0], -0.0};
    double m[9], hm[9];
    product(minus_skew, fn, m);
    product(h_right, m, hm);
    const double centre_w = hm[8];
    const int finite = fabs(centre_w) > 1e-9 * norm3(hm[6], hm[7], hm[8]);
    const double divisor = finite ? centre_w : 1.0;
    for (int i = 3; i < 9; ++i) h[i] = hm[i] / divisor;
    /* The x row is the y row's gradient at the centre, h1[:2] - h1[2] h2[:2], turned by -90 degrees. */
    const double grad_u = h[3] - h[5] * h[6], grad_v = h[4] - h[5] * h[7];
    h[0] = grad_v;
    h[1] = -grad_u;
    h[2] = 0.0;
    return finite;
}

static double det3(const double *h) {
    return h[0] * (h[4] * h[8] - h[5] * h[7]) - h[1] * (h[3] * h[8] - h[5] * h[6]) + h[2] * (h[3] * h[7] - h[4] * h[6]);
}

/* _shape_status: *unsplit where w > 0 at every corner; returns the area and rotation test. */
static int shape_ok(const double *h, const double corners[4][3], double max_area_scale, double max_rotation_deg,
                    int *unsplit) {
    double w[5];
    int split = 0;
    for (int c = 0; c < 4; ++c) {
        double sum = 0.0;
        for (int k = 0; k < 3; ++k) sum += corners[c][k] * h[6 + k];
        split |= sum <= 0;  /* a NaN w does not split, and is taken as 1, as in torch */
        w[c] = sum > 0 ? sum : 1.0;
    }
    w[4] = 1.0;
    const double det = det3(h);
    int shaped = 1;
    for (int c = 0; c < 5; ++c) {
        const double area = det / (w[c] * w[c] * w[c]);
        shaped &= (area >= 1 / max_area_scale) & (area <= max_area_scale);
    }
    const double grad_u = h[3] - h[5] * h[6], grad_v = h[4] - h[5] * h[7];
    const double angle = fabs(atan2(grad_u, grad_v)) * DEGREES_PER_RADIAN;
    *unsplit = !split;
    return shaped && angle <= max_rotation_deg;
}

/* _rms_row_error: the RMS of the inliers' rectified row differences, over those in front of both cameras (w > 0),
 * in double for float64 outputs. */
static double rms_row_error(const double *h_left, const double *h_right, const double *left, const double *right,
                            const uint8_t *inliers, int64_t K) {
    double total = 0.0;
    int64_t used = 0;
    for (int64_t k = 0; k < K; ++k) {
        if (!inliers[k]) continue;
        const double xl = left[2 * k], yl = left[2 * k + 1], xr = right[2 * k], yr = right[2 * k + 1];
        const double wl = (xl * h_left[6] + yl * h_left[7]) + h_left[8];
        const double wr = (xr * h_right[6] + yr * h_right[7]) + h_right[8];
        if (!(wl > 0 && wr > 0)) continue;
        const double error = ((xl * h_left[3] + yl * h_left[4]) + h_left[5]) / wl
                             - ((xr * h_right[3] + yr * h_right[4]) + h_right[5]) / wr;
        total += error * error;
        ++used;
    }
    return sqrt(total / (double)(used > 0 ? used : 1));
}

/* The same in float for float32 outputs, as torch computes it (so that a huge row error overflows as there). */
static double rms_row_error_float(const double *h_left, const double *h_right, const double *left,
                                  const double *right, const uint8_t *inliers, int64_t K) {
    float hl[9], hr[9], total = 0.0f;
    for (int i = 0; i < 9; ++i) {
        hl[i] = (float)h_left[i];
        hr[i] = (float)h_right[i];
    }
    int64_t used = 0;
    for (int64_t k = 0; k < K; ++k) {
        if (!inliers[k]) continue;
        const float xl = (float)left[2 * k], yl = (float)left[2 * k + 1];
        const float xr = (float)right[2 * k], yr = (float)right[2 * k + 1];
        const float wl = (xl * hl[6] + yl * hl[7]) + hl[8], wr = (xr * hr[6] + yr * hr[7]) + hr[8];
        if (!(wl > 0 && wr > 0)) continue;
        const float error = ((xl * hl[3] + yl * hl[4]) + hl[5]) / wl - ((xr * hr[3] + yr * hr[4]) + hr[5]) / wr;
        total += error * error;
        ++used;
    }
    return sqrtf(total / (float)(used > 0 ? used : 1));
}

/* f (B, 3, 3) float64, pixel F; points_left, points_right (B, K, 2) float64 pixels; inliers (B, K) uint8;
 * image_hw (B, 2) int64, each >= 1. round_float: the outputs' dtype is float32 (the RMS row error then maps the
 * points by the homographies rounded to float). Writes h_left, h_right (B, 3, 3), epipole_left, epipole_right
 * (B, 3), rms (B,) float64; status, num_inliers (B,) int64 (RectificationStatus). */
void rectify_parallel(const double *f, const double *points_left, const double *points_right, const uint8_t *inliers,
                      const int64_t *image_hw, int64_t B, int64_t K, int64_t min_inliers, double max_area_scale,
                      double max_rotation_deg, int64_t round_float, double *h_left, double *h_right,
                      double *epipole_left, double *epipole_right, double *rms, int64_t *status,
                      int64_t *num_inliers, int64_t num_threads) {
#pragma omp parallel for num_threads(thread_count(num_threads, B)) schedule(static)
    for (int64_t p = 0; p < B; ++p) {
        /* _normalisers: the centred frame of scale 2 / (W + H). */
        const double height = (double)image_hw[2 * p], width = (double)image_hw[2 * p + 1];
        const double scale = 2.0 / (height + width), cx = (width - 1) / 2, cy = (height - 1) / 2;
        const double forward[9] = {scale, 0, -cx * scale, 0, scale, -cy * scale, 0, 0, 1};
        const double inverse[9] = {1 / scale, 0, cx, 0, 1 / scale, cy, 0, 0, 1};
        const double inverse_t[9] = {1 / scale, 0, 0, 0, 1 / scale, 0, cx, cy, 1};
        const double hx = cx * scale, hy = cy * scale;
        const double corners[4][3] = {{-hx, -hy, 1}, {hx, -hy, 1}, {-hx, hy, 1}, {hx, hy, 1}};
        double t[9], fn[9];
        product(inverse_t, f + 9 * p, t);
        product(t, inverse, fn);
        int finite = 1;
        for (int i = 0; i < 9; ++i) finite &= isfinite(fn[i]) != 0;
        if (!finite)
            for (int i = 0; i < 9; ++i) fn[i] = 0.0;  /* a failed RANSAC: DEGENERATE */
        double right_e[3], left_e[3], hr[9], hl[9];
        const int rank2 = epipoles(fn, right_e, left_e);
        const int off_centre = right_homography(right_e, hr);
        const int left_finite = left_homography(fn, right_e, hr, hl);
        int unsplit_left, unsplit_right;
        const int shaped_left = shape_ok(hl, corners, max_area_scale, max_rotation_deg, &unsplit_left);
        const int shaped_right = shape_ok(hr, corners, max_area_scale, max_rotation_deg, &unsplit_right);
        int64_t count = 0;
        for (int64_t k = 0; k < K; ++k) count += inliers[p * K + k] != 0;
        int64_t code = OK;  /* the last failed check wins, as in the torch path */
        if (!(shaped_left && shaped_right)) code = DISTORTED;
        if (!(unsplit_left && unsplit_right && left_finite && off_centre)) code = EPIPOLE_IN_IMAGE;
        if (!rank2) code = DEGENERATE;
        if (count < min_inliers) code = NOT_ENOUGH_INLIERS;
        status[p] = code;
        num_inliers[p] = count;
        double *out_left = h_left + 9 * p, *out_right = h_right + 9 * p;
        if (code == OK) {
            product(inverse, hl, t);
            product(t, forward, out_left);
            product(inverse, hr, t);
            product(t, forward, out_right);
        } else {
            for (int i = 0; i < 9; ++i) out_left[i] = out_right[i] = (i % 4 == 0) ? 1.0 : 0.0;
        }
        if (round_float)
            for (int i = 0; i < 9; ++i) {
                out_left[i] = (float)out_left[i];
                out_right[i] = (float)out_right[i];
            }
        const double *unit[2] = {left_e, right_e};
        double *pixel[2] = {epipole_left + 3 * p, epipole_right + 3 * p};
        for (int s = 0; s < 2; ++s) {
            double e[3];
            for (int i = 0; i < 3; ++i) e[i] = (inverse[3 * i] * unit[s][0] + inverse[3 * i + 1] * unit[s][1])
                                               + inverse[3 * i + 2] * unit[s][2];
            const double n = norm3(e[0], e[1], e[2]);
            for (int i = 0; i < 3; ++i) pixel[s][i] = rank2 ? e[i] / n : 0.0;
        }
        rms[p] = round_float ? rms_row_error_float(out_left, out_right, points_left + 2 * p * K,
                                                   points_right + 2 * p * K, inliers + p * K, K)
                             : rms_row_error(out_left, out_right, points_left + 2 * p * K, points_right + 2 * p * K,
                                             inliers + p * K, K);
    }
}
