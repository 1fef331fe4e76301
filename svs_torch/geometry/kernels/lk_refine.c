/* Sub-pixel refinement of matched points by translational Lucas-Kanade, for svs_torch.geometry.lk_refinement (the
 * no-gradient path of refine_matches_lk; the torch path _refine_lk stays the reference).
 *
 * The torch path samples every patch of the batch with grid_sample and reduces it with a dozen elementwise
 * passes per Gauss-Newton step: 14 samplings of B x K x 169 points and about 100 passes in all. Here each
 * match is refined start to finish while its 169 samples sit in L1, LANES matches per OpenMP iteration (torch's
 * own pool, see svs_torch/core/kernels/loader.py). The arithmetic is the torch path's step for step (bilinear
 * samples with the border repeated, Gaussian weights, zero-mean unit-RMS patches, the Jacobian with its mean
 * and its component along the template removed, H^-1 applied once, steps clamped to 1 px), but the weighted
 * sums run in double and in their own order, so positions agree with the torch path to about 1e-4 px, not bit
 * for bit (tests/core/test_kernels.py).
 *
 * Why LANES matches at once: each sum over a patch is a chain of dependent double adds, in a fixed order so that
 * results do not depend on the compiler; its latency, not the arithmetic, bounded the loop. The LANES matches'
 * chains are independent and run interleaved (lane fastest in memory, so they share vector registers), each in
 * its own order: the same bits as one match at a time (tests/core/test_kernels.py), 17-19 % less time on the
 * 2 791 matches of 8 synthetic pairs at one thread.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp (see svs_torch/core/kernels/loader.py).
 */
#include <math.h>
#include <stdint.h>

#include "common.h"

#define HALF 6
#define SIDE (2 * HALF + 1)
#define SAMPLES (SIDE * SIDE)
#define LANES 8

/* Bilinear samples of a (H, W) image at (cx + ox[p], cy + oy[p]), pixel-centre coordinates, the border pixel
 * repeated outside (grid_sample, align_corners=True, padding_mode="border"). The offsets are a SIDE x SIDE grid
 * (ox depends on the column of the patch only, oy on its row), so each column's taps and weight and each row's
 * are made once (the same float operations as per sample). Where the columns' left taps are consecutive and
 * each right tap is the next pixel (a grid spacing of 1 px inside the image: 8 patches in 10 on the shared
 * scenes) every patch row reads two runs of the image rows and vectorises with plain loads; otherwise the taps
 * are looked up. The same values either way. */
static void sample_patch(const float *restrict image, int32_t H, int32_t W, float cx, float cy,
                         const float *restrict ox, const float *restrict oy, float *restrict out, int stride) {
    const float right_edge = (float)(W - 1), bottom_edge = (float)(H - 1);
    int32_t x0[SIDE], x1[SIDE], top[SIDE], bottom[SIDE];
    float fx[SIDE], gx[SIDE], fy[SIDE];
    int consecutive = 1;
    for (int i = 0; i < SIDE; ++i) {
        float x = cx + ox[i], y = cy + oy[i * SIDE];
        x = x > 0.0f ? x : 0.0f;
        x = x < right_edge ? x : right_edge;
        y = y > 0.0f ? y : 0.0f;
        y = y < bottom_edge ? y : bottom_edge;
        x0[i] = (int32_t)x; /* x, y >= 0: truncation is the floor */
        const int32_t row = (int32_t)y;
        fx[i] = x - (float)x0[i];
        gx[i] = 1.0f - fx[i];
        fy[i] = y - (float)row;
        x1[i] = x0[i] + (x0[i] < W - 1);
        top[i] = row * W;
        bottom[i] = (row + (row < H - 1)) * W;
        consecutive &= (x1[i] == x0[i] + 1) & (x0[i] == x0[0] + i);
    }
    for (int j = 0; j < SIDE; ++j) {
        const float *restrict above = image + top[j], *restrict below = image + bottom[j];
        const float wy = fy[j], vy = 1.0f - wy;
        float *restrict o = out + j * SIDE * stride;
        if (consecutive) {
            const float *restrict a = above + x0[0], *restrict b = below + x0[0];
            for (int i = 0; i < SIDE; ++i)
                o[i * stride] = vy * (gx[i] * a[i] + fx[i] * a[i + 1]) + wy * (gx[i] * b[i] + fx[i] * b[i + 1]);
        } else {
            for (int i = 0; i < SIDE; ++i)
                o[i * stride] = vy * (gx[i] * above[x0[i]] + fx[i] * above[x1[i]])
                       + wy * (gx[i] * below[x0[i]] + fx[i] * below[x1[i]]);
        }
    }
}

/* Zero-mean, unit weighted RMS of n samples in place; returns the RMS (clamped to 1e-6, as _centre). */
static float standardise(float *values, const double *weight, int n) {
    double mean = 0.0, power = 0.0;
    for (int p = 0; p < n; ++p) mean += weight[p] * values[p];
    for (int p = 0; p < n; ++p) {
        values[p] = (float)(values[p] - mean);
        power += weight[p] * (double)values[p] * values[p];
    }
    float rms = (float)sqrt(power);
    return rms > 1e-6f ? rms : 1e-6f;
}

/* One match's fixed part: the patch grid (ox, oy), its weights w, the standardised template t and the descent
 * images dx, dy (H^-1 applied to w g). Returns whether the Gauss-Newton system is solvable. */
static int prepare_match(const float *restrict L, int32_t h32, int32_t w32, float lx, float ly, float r,
                         float *restrict ox, float *restrict oy, double *restrict w, float *restrict t,
                         float *restrict dx, float *restrict dy) {
    float spacing = r / HALF;
    if (spacing < 1.0f) spacing = 1.0f;
    double total = 0.0;
    const float sigma = r / 2.0f, reach = (r + 0.5f) * (r + 0.5f);
    /* The weights depend on |column offset| and |row offset| only, symmetrically: 28 distinct values of the
     * 169, each computed once (the same float d2 and double exp as per sample). */
    double unique[HALF + 1][HALF + 1];
    for (int i = 0; i <= HALF; ++i)
        for (int j = 0; j <= i; ++j) {
            const float a = (float)i * spacing, c = (float)j * spacing;
            const float d2 = a * a + c * c;
            unique[i][j] = unique[j][i] = d2 <= reach ? exp(-(double)d2 / (2.0 * sigma * sigma)) : 0.0;
        }
    for (int p = 0; p < SAMPLES; ++p) {
        const int ci = p % SIDE - HALF, ri = p / SIDE - HALF;
        ox[p] = (float)ci * spacing;
        oy[p] = (float)ri * spacing;
        w[p] = unique[ci < 0 ? -ci : ci][ri < 0 ? -ri : ri];
        total += w[p];
    }
    for (int p = 0; p < SAMPLES; ++p) w[p] /= total;
    sample_patch(L, h32, w32, lx, ly, ox, oy, t, 1);
    const float rms = standardise(t, w, SAMPLES);
    for (int p = 0; p < SAMPLES; ++p) t[p] /= rms;
    /* The template's gradient: central differences of the bilinear image half a pixel either side. */
    float gx[SAMPLES], gy[SAMPLES], ahead[SAMPLES], behind[SAMPLES];
    sample_patch(L, h32, w32, lx + 0.5f, ly, ox, oy, ahead, 1);
    sample_patch(L, h32, w32, lx - 0.5f, ly, ox, oy, behind, 1);
    for (int p = 0; p < SAMPLES; ++p) gx[p] = (ahead[p] - behind[p]) / rms;
    sample_patch(L, h32, w32, lx, ly + 0.5f, ox, oy, ahead, 1);
    sample_patch(L, h32, w32, lx, ly - 0.5f, ox, oy, behind, 1);
    for (int p = 0; p < SAMPLES; ++p) gy[p] = (ahead[p] - behind[p]) / rms;
    /* The Jacobian of the standardised patch: without its weighted mean and its part along the template. */
    double mx = 0.0, my = 0.0;
    for (int p = 0; p < SAMPLES; ++p) {
        mx += w[p] * gx[p];
        my += w[p] * gy[p];
    }
    double px = 0.0, py = 0.0;
    for (int p = 0; p < SAMPLES; ++p) {
        gx[p] = (float)(gx[p] - mx);
        gy[p] = (float)(gy[p] - my);
        px += w[p] * t[p] * gx[p];
        py += w[p] * t[p] * gy[p];
    }
    double hxx = 0.0, hxy = 0.0, hyy = 0.0;
    for (int p = 0; p < SAMPLES; ++p) {
        gx[p] = (float)(gx[p] - t[p] * px);
        gy[p] = (float)(gy[p] - t[p] * py);
        hxx += w[p] * gx[p] * gx[p];
        hxy += w[p] * gx[p] * gy[p];
        hyy += w[p] * gy[p] * gy[p];
    }
    const double det = hxx * hyy - hxy * hxy;
    const int solvable = det != 0.0 && isfinite(det) && isfinite(1.0 / det);
    /* descent_p = H^-1 (w_p g_p): the step is -sum_p residual_p descent_p. */
    for (int p = 0; p < SAMPLES; ++p) {
        double ax = w[p] * gx[p], ay = w[p] * gy[p];
        dx[p] = solvable ? (float)((hyy * ax - hxy * ay) / det) : 0.0f;
        dy[p] = solvable ? (float)((hxx * ay - hxy * ax) / det) : 0.0f;
    }
    return solvable;
}

/* standardise() of LANES patches at once: each lane's sums in the same order as alone (the same values), but the
 * lanes' independent sums interleaved, so the adds of one lane wait on their own previous result while the other
 * lanes' go on (a single lane's chain of dependent double adds is what bounds the loop). */
static void standardise_lanes(float (*restrict values)[LANES], const double (*restrict weight)[LANES],
                              float *restrict rms) {
    double mean[LANES] = {0.0}, power[LANES] = {0.0};
    for (int p = 0; p < SAMPLES; ++p)
        for (int g = 0; g < LANES; ++g) mean[g] += weight[p][g] * values[p][g];
    for (int p = 0; p < SAMPLES; ++p)
        for (int g = 0; g < LANES; ++g) {
            values[p][g] = (float)(values[p][g] - mean[g]);
            power[g] += weight[p][g] * (double)values[p][g] * values[p][g];
        }
    for (int g = 0; g < LANES; ++g) {
        rms[g] = (float)sqrt(power[g]);
        rms[g] = rms[g] > 1e-6f ? rms[g] : 1e-6f;
    }
}

/* left, right: (B, H, W) float32. Per row of the (B, K) matches: left_xy, right_xy (B, K, 2) float32, radius
 * (B, K) float32 (the patch radius, already clamped), active (B, K) uint8 (rows to refine). Writes refined
 * (B, K, 2) (the right point, moved when the refinement converged within max_shift), correlation (B, K)
 * (weighted NCC at the returned position; 0 for inactive rows). Matches are taken LANES at a time (an inactive
 * or missing row's lane runs on zeros and is not written). */
void lk_refine(const float *left, const float *right, int64_t B, int64_t H, int64_t W, int64_t K,
               const float *left_xy, const float *right_xy, const float *radius, const uint8_t *active,
               int64_t iterations, float max_shift, float *refined, float *correlation, int64_t num_threads) {
    const int64_t rows = B * K, groups = (rows + LANES - 1) / LANES;
    const int threads = thread_count(num_threads, groups);
    const int32_t h32 = (int32_t)H, w32 = (int32_t)W;
#pragma omp parallel for schedule(dynamic, 4) num_threads(threads)
    for (int64_t group = 0; group < groups; ++group) {
        /* Per lane: the grid offsets; per sample and lane (the lane fastest, so the lanes' sums vectorise): the
         * weights, template, descent images and warped patch. */
        float ox[LANES][SAMPLES], oy[LANES][SAMPLES], t[SAMPLES][LANES], dx[SAMPLES][LANES], dy[SAMPLES][LANES];
        float warped[SAMPLES][LANES], rx[LANES], ry[LANES], sx[LANES], sy[LANES], warped_rms[LANES];
        double w[SAMPLES][LANES];
        const float *R[LANES];
        int live[LANES], solvable[LANES];
        for (int g = 0; g < LANES; ++g) {
            const int64_t row = group * LANES + g;
            live[g] = row < rows && active[row];
            solvable[g] = 0;
            sx[g] = sy[g] = 0.0f;
            R[g] = right;
            if (row < rows) {
                rx[g] = refined[2 * row] = right_xy[2 * row];
                ry[g] = refined[2 * row + 1] = right_xy[2 * row + 1];
                correlation[row] = 0.0f;
            }
            if (!live[g]) {
                for (int p = 0; p < SAMPLES; ++p) {
                    w[p][g] = 0.0;
                    t[p][g] = dx[p][g] = dy[p][g] = warped[p][g] = 0.0f;
                }
                continue;
            }
            const int64_t b = row / K;
            R[g] = right + b * H * W;
            float lane_t[SAMPLES], lane_dx[SAMPLES], lane_dy[SAMPLES];
            double lane_w[SAMPLES];
            solvable[g] = prepare_match(left + b * H * W, h32, w32, left_xy[2 * row], left_xy[2 * row + 1],
                                        radius[row], ox[g], oy[g], lane_w, lane_t, lane_dx, lane_dy);
            for (int p = 0; p < SAMPLES; ++p) {
                w[p][g] = lane_w[p];
                t[p][g] = lane_t[p];
                dx[p][g] = lane_dx[p];
                dy[p][g] = lane_dy[p];
            }
        }
        for (int64_t it = 0; it < iterations; ++it) {
            for (int g = 0; g < LANES; ++g)
                if (live[g])
                    sample_patch(R[g], h32, w32, rx[g] + sx[g], ry[g] + sy[g], ox[g], oy[g], &warped[0][g], LANES);
            standardise_lanes(warped, (const double (*)[LANES])w, warped_rms);
            double step_x[LANES] = {0.0}, step_y[LANES] = {0.0};
            for (int p = 0; p < SAMPLES; ++p)
                for (int g = 0; g < LANES; ++g) {
                    double residual = warped[p][g] / warped_rms[g] - t[p][g];
                    step_x[g] -= residual * dx[p][g];
                    step_y[g] -= residual * dy[p][g];
                }
            for (int g = 0; g < LANES; ++g) {
                sx[g] += (float)(step_x[g] < -1.0 ? -1.0 : (step_x[g] > 1.0 ? 1.0 : step_x[g]));
                sy[g] += (float)(step_y[g] < -1.0 ? -1.0 : (step_y[g] > 1.0 ? 1.0 : step_y[g]));
            }
        }
        for (int g = 0; g < LANES; ++g) {
            if (!live[g]) continue;
            const int moved = solvable[g] && isfinite(sx[g]) && isfinite(sy[g])
                              && sqrtf(sx[g] * sx[g] + sy[g] * sy[g]) <= max_shift;
            if (moved) {
                rx[g] += sx[g];
                ry[g] += sy[g];
            }
            const int64_t row = group * LANES + g;
            refined[2 * row] = rx[g];
            refined[2 * row + 1] = ry[g];
            sample_patch(R[g], h32, w32, rx[g], ry[g], ox[g], oy[g], &warped[0][g], LANES);
        }
        standardise_lanes(warped, (const double (*)[LANES])w, warped_rms);
        double ncc[LANES] = {0.0};
        for (int p = 0; p < SAMPLES; ++p)
            for (int g = 0; g < LANES; ++g) ncc[g] += (double)warped[p][g] / warped_rms[g] * t[p][g] * w[p][g];
        for (int g = 0; g < LANES; ++g)
            if (live[g]) correlation[group * LANES + g] = (float)ncc[g];
    }
}
