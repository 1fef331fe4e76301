/* Upright SURF descriptors (U-SURF) straight from the image, for svs_torch.features.descriptor (the no-gradient
 * path of _describe_upright; the torch path stays the reference and the differentiable path).
 *
 * The torch path builds a float32 padded integral image, gathers the valid keypoints, reads a 22 x 22 lattice of
 * integral values per keypoint by bilinear gathers, turns it into 21 x 21 cell means, 20 x 20 Haar responses and
 * 4 x 4 sub-region sums in about 30 passes over B x K x 400 values, and scatters the rows back. Here each image's integral
 * is built once in double and each keypoint is described start to finish while its lattice sits in L1. The
 * arithmetic is the torch path's (bilinear reads of the table clamped to its extent, cell means over the cell areas,
 * 2 x 2-cell Haar differences, the sigma = 3.3 Gaussian centred between the middle samples, OpenCV's
 * sub-region-major layout, unit length), but in double and summed in its own order, so the descriptors agree with
 * the torch path's to its own float32 error (median 1e-5, at most a few 1e-4), not bit for bit
 * (tests/core/test_kernels.py).
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp (see svs_torch/core/kernels/loader.py).
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "common.h"

#define CELLS 21           /* cell means per side */
#define EDGES (CELLS + 1)  /* lattice points per side */
#define SAMPLES (CELLS - 1) /* Haar responses per side (Sec. 4.2: 20) */
#define SIGMA 3.3

/* Where a table coordinate falls: the two indices either side and the weight of the second, the coordinate
 * clamped to [0, size - 1] (grid_sample, align_corners=True, on coordinates that never leave the table). */
static void locate(double t, int64_t size, int64_t *first, int64_t *second, double *fraction) {
    t = t < 0 ? 0 : (t > (double)(size - 1) ? (double)(size - 1) : t);
    const int64_t i = (int64_t)t; /* t >= 0: truncation is the floor */
    *first = i;
    *second = i + (i < size - 1);
    *fraction = t - (double)i;
}

/* Whether the two cells [a, b] of a Haar response across an axis of ``size`` pixels lie within one pixel (no
 * boundary k + 0.5, 0 <= k <= size - 2, strictly inside): their means are then equal and the response is 0 by
 * definition, whatever sign round-off gives it (descriptor.py's _within_one_pixel, the same arithmetic). */
static int within_one_pixel(double a, double b, int64_t size) {
    return fmax(floor(a - 0.5) + 1, 0) > fmin(ceil(b - 0.5) - 1, (double)(size - 2));
}

static void describe_one(const double *table, int64_t H1, int64_t W1, int64_t pad, double x, double y, double s,
                         int extended, const double *weight, float *out) {
    double lattice[EDGES][EDGES], means[CELLS][CELLS], u[EDGES], v[EDGES];
    for (int n = 0; n < EDGES; ++n) {
        const double edge = (double)n - CELLS / 2.0; /* -10.5 ... 10.5 */
        u[n] = x + s * edge + 0.5 + (double)pad;
        v[n] = y + s * edge + 0.5 + (double)pad;
    }
    /* The lattice is upright, so its bilinear reads share their columns along a row and their rows along a
     * column: each table row is read at the 22 columns' two indices, then the rows are blended. */
    int64_t x0[EDGES], x1[EDGES];
    double fx[EDGES];
    for (int n = 0; n < EDGES; ++n) locate(u[n], W1, &x0[n], &x1[n], &fx[n]);
    for (int m = 0; m < EDGES; ++m) {
        int64_t y0, y1;
        double fy;
        locate(v[m], H1, &y0, &y1, &fy);
        const double *top = table + y0 * W1, *bottom = table + y1 * W1;
        for (int n = 0; n < EDGES; ++n)
            lattice[m][n] = (1 - fy) * ((1 - fx[n]) * top[x0[n]] + fx[n] * top[x1[n]])
                            + fy * ((1 - fx[n]) * bottom[x0[n]] + fx[n] * bottom[x1[n]]);
    }
    /* The cell's area from its unclamped edges, as the torch path (cells past the table's edge read less). */
    for (int m = 0; m < CELLS; ++m)
        for (int n = 0; n < CELLS; ++n)
            means[m][n] = (lattice[m + 1][n + 1] - lattice[m][n + 1] - lattice[m + 1][n] + lattice[m][n])
                          / ((u[n + 1] - u[n]) * (v[m + 1] - v[m]));
    const int parts = extended ? 8 : 4;
    double descriptor[128] = {0};
    /* The weighted Haar responses first (a loop gcc vectorises), then their sums per sub-region. Explicitly
     * aligned: without it gcc 12 (-O3 -march=native) stored to them with aligned vector moves at an address the
     * frame did not align, and the call faulted. */
    double dxs[SAMPLES][SAMPLES] __attribute__((aligned(64)));
    double dys[SAMPLES][SAMPLES] __attribute__((aligned(64)));
    for (int i = 0; i < SAMPLES; ++i)
        for (int j = 0; j < SAMPLES; ++j) {
            const double w = weight[i * SAMPLES + j];
            dxs[i][j] = w * (means[i][j + 1] - means[i][j] + means[i + 1][j + 1] - means[i + 1][j]) / 2;
            dys[i][j] = w * (means[i + 1][j] - means[i][j] + means[i + 1][j + 1] - means[i][j + 1]) / 2;
        }
    if (!extended) {
        /* A row of four sub-regions at a time, their sums in registers (each sub-region's samples added in the
         * raster order of the 20 x 20 samples, as before): accumulating into the descriptor in memory made each
         * add wait for the previous store. */
        for (int bi = 0; bi < 4; ++bi) {
            double sum[4][4] = {{0}};
            for (int i = 5 * bi; i < 5 * bi + 5; ++i)
                for (int bj = 0; bj < 4; ++bj)
                    for (int j = 5 * bj; j < 5 * bj + 5; ++j) {
                        sum[bj][0] += dxs[i][j];
                        sum[bj][1] += dys[i][j];
                        sum[bj][2] += fabs(dxs[i][j]);
                        sum[bj][3] += fabs(dys[i][j]);
                    }
            for (int bj = 0; bj < 4; ++bj)
                for (int d = 0; d < 4; ++d) descriptor[(bi * 4 + bj) * 4 + d] = sum[bj][d];
        }
    } else {
        /* A response that is 0 by definition (its two cells within one pixel, as in the replicate border) counts as
         * not negative: its round-off sign put the other response into either half (up to 0.05 from the torch
         * path's near the border). The edges again in image coordinates, as the torch path computes them. */
        const int64_t H = H1 - 2 * pad - 1, W = W1 - 2 * pad - 1;
        int steady_x[SAMPLES], steady_y[SAMPLES];
        for (int n = 0; n < SAMPLES; ++n) {
            const double first = (double)n - CELLS / 2.0, last = (double)(n + 2) - CELLS / 2.0;
            steady_x[n] = within_one_pixel(x + s * first, x + s * last, W);
            steady_y[n] = within_one_pixel(y + s * first, y + s * last, H);
        }
        for (int i = 0; i < SAMPLES; ++i)
            for (int j = 0; j < SAMPLES; ++j) {
                const double dx = dxs[i][j], dy = dys[i][j];
                double *block = descriptor + ((i / 5) * 4 + j / 5) * 8;
                const int a = dy < 0 && !steady_y[i] ? 0 : 2, b = dx < 0 && !steady_x[j] ? 4 : 6;
                block[a] += dx;
                block[a + 1] += fabs(dx);
                block[b] += dy;
                block[b + 1] += fabs(dy);
            }
    }
    const int length = 16 * parts;
    double norm = 0;
    for (int d = 0; d < length; ++d) norm += descriptor[d] * descriptor[d];
    norm = sqrt(norm);
    for (int d = 0; d < length; ++d) out[d] = norm > 0 ? (float)(descriptor[d] / norm) : 0.0f;
}

/* The integral image (H + 2 pad + 1, W + 2 pad + 1) of an (H, W) image extended by ``pad`` pixels of replicate
 * border (svs_torch.features.integral.padded_integral_image), in double: exact enough without removing the mean
 * first, which the float32 torch path needs (its sums reach 10^4 over a 320 x 240 image). Anchored at the image's
 * top-left corner (table index pad, pad): each value is the signed sum between that corner and its own, summed
 * outward from the corner, so it does not depend on ``pad``. Why: the border is the batch's (wide enough for the
 * batch's largest keypoint), and a table summed from its own corner gave an image's descriptors other float
 * roundings in another batch (issue 29). Box sums, differences of four values, are unchanged. */
static void row_prefix(const float *row, int64_t W, int64_t pad, double *out) {
    const int64_t W1 = W + 2 * pad + 1;
    out[pad] = 0;
    for (int64_t c = pad + 1; c < W1; ++c) { /* rightward from the corner: pixel j = c - 1 - pad */
        const int64_t j = c - 1 - pad;
        out[c] = out[c - 1] + row[j >= W ? W - 1 : j];
    }
    for (int64_t c = pad - 1; c >= 0; --c) out[c] = out[c + 1] - row[0]; /* leftward: the replicated first pixel */
}

static void padded_integral(const float *image, int64_t H, int64_t W, int64_t pad, double *table) {
    const int64_t H1 = H + 2 * pad + 1, W1 = W + 2 * pad + 1;
    for (int64_t c = 0; c < W1; ++c) table[pad * W1 + c] = 0;
    for (int64_t r = pad + 1; r < H1; ++r) { /* downward: image row i = r - 1 - pad */
        const int64_t i = r - 1 - pad;
        double *out = table + r * W1;
        const double *above = out - W1;
        row_prefix(image + (i >= H ? H - 1 : i) * W, W, pad, out);
        for (int64_t c = 0; c < W1; ++c) out[c] = above[c] + out[c];
    }
    for (int64_t r = pad - 1; r >= 0; --r) { /* upward: the replicated first row */
        double *out = table + r * W1;
        const double *below = out + W1;
        row_prefix(image, W, pad, out);
        for (int64_t c = 0; c < W1; ++c) out[c] = below[c] - out[c];
    }
}

/* Descriptors (B, K, 64 or 128) of the valid keypoints (valid (B, K) uint8; xy (B, K, 2), scale (B, K), both
 * float32, pixel-centre coordinates) of the images (B, H, W), read from each image's integral with a replicate
 * border of ``pad`` pixels; rows of invalid keypoints are left as they are (zero from the caller). Images are
 * shared among num_threads OpenMP threads (torch's own pool), each building its table once. Returns 0, or -1
 * when memory could not be had (the caller then runs its torch path). */
int usurf_describe(const float *images, int64_t B, int64_t H, int64_t W, int64_t pad, const float *xy,
                   const float *scale, const uint8_t *valid, int64_t K, int64_t extended, float *out,
                   int64_t num_threads) {
    double weight[SAMPLES * SAMPLES];
    for (int i = 0; i < SAMPLES; ++i)
        for (int j = 0; j < SAMPLES; ++j) {
            const double ri = i - (SAMPLES - 1) / 2.0, rj = j - (SAMPLES - 1) / 2.0;
            weight[i * SAMPLES + j] = exp(-(ri * ri) / (2 * SIGMA * SIGMA)) * exp(-(rj * rj) / (2 * SIGMA * SIGMA));
        }
    const int64_t length = extended ? 128 : 64, H1 = H + 2 * pad + 1, W1 = W + 2 * pad + 1;
    int failed = 0;
#pragma omp parallel num_threads(thread_count(num_threads, B))
    {
        double *table = scratch(H1 * W1, sizeof(double));
        const int ready = scratch_ready(table != NULL, &failed);
#pragma omp for schedule(dynamic, 1)
        for (int64_t b = 0; b < B; ++b) {
            if (!ready) continue;
            int any = 0;
            for (int64_t k = 0; k < K; ++k) any |= valid[b * K + k];
            if (!any) continue;
            padded_integral(images + b * H * W, H, W, pad, table);
            for (int64_t k = 0; k < K; ++k) {
                const int64_t p = b * K + k;
                if (!valid[p]) continue;
                const double s = scale[p] > 1e-3f ? (double)scale[p] : 1e-3;
                describe_one(table, H1, W1, pad, xy[2 * p], xy[2 * p + 1], s, (int)extended, weight,
                             out + p * length);
            }
        }
        free(table);
    }
    return failed ? -1 : 0;
}
