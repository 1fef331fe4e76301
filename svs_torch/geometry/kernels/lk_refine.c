/* Sub-pixel refinement of matched points by translational Lucas-Kanade, for svs_torch.geometry.lk_refinement (the
 * no-gradient path of refine_matches_lk; the torch path _refine_lk stays the reference).
 *
 * The torch path samples every patch of the batch with grid_sample and reduces it with a dozen elementwise
 * passes per Gauss-Newton step: 14 samplings of B x K x 169 points and about 100 passes in all. Here each
 * match is refined start to finish while its 169 samples sit in L1, one match per OpenMP iteration (torch's
 * own pool, see svs_torch/core/kernels/loader.py). The arithmetic is the torch path's step for step (bilinear
 * samples with the border repeated, Gaussian weights, zero-mean unit-RMS patches, the Jacobian with its mean
 * and its component along the template removed, H^-1 applied once, steps clamped to 1 px), but the weighted
 * sums run in double and in their own order, so positions agree with the torch path to about 1e-4 px, not bit
 * for bit (tests/core/test_kernels.py).
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp (see svs_torch/core/kernels/loader.py).
 */
#include <math.h>
#include <stdint.h>

#include "common.h"

#define HALF 6
#define SIDE (2 * HALF + 1)
#define SAMPLES (SIDE * SIDE)

/* Bilinear samples of a (H, W) image at (cx + ox[p], cy + oy[p]), pixel-centre coordinates, the border pixel
 * repeated outside (grid_sample, align_corners=True, padding_mode="border"). The offsets are a SIDE x SIDE grid
 * (ox depends on the column of the patch only, oy on its row), so each column's taps and weight and each row's
 * are made once (the same float operations as per sample). Where the columns' left taps are consecutive and
 * each right tap is the next pixel (a grid spacing of 1 px inside the image: 8 patches in 10 on the shared
 * scenes) every patch row reads two runs of the image rows and vectorises with plain loads; otherwise the taps
 * are looked up. The same values either way. */
static void sample_patch(const float *restrict image, int32_t H, int32_t W, float cx, float cy,
                         const float *restrict ox, const float *restrict oy, float *restrict out) {
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
        float *restrict o = out + j * SIDE;
        if (consecutive) {
            const float *restrict a = above + x0[0], *restrict b = below + x0[0];
            for (int i = 0; i < SIDE; ++i)
                o[i] = vy * (gx[i] * a[i] + fx[i] * a[i + 1]) + wy * (gx[i] * b[i] + fx[i] * b[i + 1]);
        } else {
            for (int i = 0; i < SIDE; ++i)
                o[i] = vy * (gx[i] * above[x0[i]] + fx[i] * above[x1[i]])
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

/* left, right: (B, H, W) float32. Per row of the (B, K) matches: left_xy, right_xy (B, K, 2) float32, radius
 * (B, K) float32 (the patch radius, already clamped), active (B, K) uint8 (rows to refine). Writes refined
 * (B, K, 2) (the right point, moved when the refinement converged within max_shift), correlation (B, K)
 * (weighted NCC at the returned position; 0 for inactive rows). */
void lk_refine(const float *left, const float *right, int64_t B, int64_t H, int64_t W, int64_t K,
               const float *left_xy, const float *right_xy, const float *radius, const uint8_t *active,
               int64_t iterations, float max_shift, float *refined, float *correlation, int64_t num_threads) {
    const int threads = thread_count(num_threads, B * K);
    const int32_t h32 = (int32_t)H, w32 = (int32_t)W;
#pragma omp parallel for schedule(dynamic, 16) num_threads(threads)
    for (int64_t row = 0; row < B * K; ++row) {
        const int64_t b = row / K;
        float rx = right_xy[2 * row], ry = right_xy[2 * row + 1];
        refined[2 * row] = rx;
        refined[2 * row + 1] = ry;
        correlation[row] = 0.0f;
        if (!active[row]) continue;
        const float *L = left + b * H * W, *R = right + b * H * W;
        const float lx = left_xy[2 * row], ly = left_xy[2 * row + 1], r = radius[row];
        float spacing = r / HALF;
        if (spacing < 1.0f) spacing = 1.0f;
        float ox[SAMPLES], oy[SAMPLES], t[SAMPLES], gx[SAMPLES], gy[SAMPLES], warped[SAMPLES];
        double w[SAMPLES], total = 0.0;
        const float sigma = r / 2.0f, reach = (r + 0.5f) * (r + 0.5f);
        for (int p = 0; p < SAMPLES; ++p) {
            ox[p] = (float)(p % SIDE - HALF) * spacing;
            oy[p] = (float)(p / SIDE - HALF) * spacing;
            float d2 = ox[p] * ox[p] + oy[p] * oy[p];
            w[p] = d2 <= reach ? exp(-(double)d2 / (2.0 * sigma * sigma)) : 0.0;
            total += w[p];
        }
        for (int p = 0; p < SAMPLES; ++p) w[p] /= total;
        sample_patch(L, h32, w32, lx, ly, ox, oy, t);
        const float rms = standardise(t, w, SAMPLES);
        for (int p = 0; p < SAMPLES; ++p) t[p] /= rms;
        /* The template's gradient: central differences of the bilinear image half a pixel either side. */
        float ahead[SAMPLES], behind[SAMPLES];
        sample_patch(L, h32, w32, lx + 0.5f, ly, ox, oy, ahead);
        sample_patch(L, h32, w32, lx - 0.5f, ly, ox, oy, behind);
        for (int p = 0; p < SAMPLES; ++p) gx[p] = (ahead[p] - behind[p]) / rms;
        sample_patch(L, h32, w32, lx, ly + 0.5f, ox, oy, ahead);
        sample_patch(L, h32, w32, lx, ly - 0.5f, ox, oy, behind);
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
        float dx[SAMPLES], dy[SAMPLES];
        for (int p = 0; p < SAMPLES; ++p) {
            double ax = w[p] * gx[p], ay = w[p] * gy[p];
            dx[p] = solvable ? (float)((hyy * ax - hxy * ay) / det) : 0.0f;
            dy[p] = solvable ? (float)((hxx * ay - hxy * ax) / det) : 0.0f;
        }
        float sx = 0.0f, sy = 0.0f;
        for (int64_t it = 0; it < iterations; ++it) {
            sample_patch(R, h32, w32, rx + sx, ry + sy, ox, oy, warped);
            const float warped_rms = standardise(warped, w, SAMPLES);
            double step_x = 0.0, step_y = 0.0;
            for (int p = 0; p < SAMPLES; ++p) {
                double residual = warped[p] / warped_rms - t[p];
                step_x -= residual * dx[p];
                step_y -= residual * dy[p];
            }
            sx += (float)(step_x < -1.0 ? -1.0 : (step_x > 1.0 ? 1.0 : step_x));
            sy += (float)(step_y < -1.0 ? -1.0 : (step_y > 1.0 ? 1.0 : step_y));
        }
        const int moved = solvable && isfinite(sx) && isfinite(sy) && sqrtf(sx * sx + sy * sy) <= max_shift;
        if (moved) {
            rx += sx;
            ry += sy;
        }
        refined[2 * row] = rx;
        refined[2 * row + 1] = ry;
        sample_patch(R, h32, w32, rx, ry, ox, oy, warped);
        const float warped_rms = standardise(warped, w, SAMPLES);
        double ncc = 0.0;
        for (int p = 0; p < SAMPLES; ++p) ncc += (double)warped[p] / warped_rms * t[p] * w[p];
        correlation[row] = (float)ncc;
    }
}
