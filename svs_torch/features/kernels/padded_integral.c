/* The padded, mean-removed integral image of SURF's Hessian (svs_torch.features.hessian, the no-gradient path) in
 * one pass per image.
 *
 * The torch path makes five passes over the image and the table: the mean's subtraction, a cumulative sum down
 * the columns, one along the rows, a zero row and column in front (F.pad), then a replicate pad of ``pad`` on
 * every side (integral.pad_integral). Here each row is finished at once, in the torch path's arithmetic: the
 * subtraction in float32, each cumulative sum carried in double and rounded to float32 at every element (torch's
 * CPU cumsum accumulates float32 in double), the row sums over the rounded column sums. So the table is
 * bit-identical (tests/core/test_kernels.py).
 *
 * Without ``means`` (NULL) each image's mean is taken here as svs_torch.features.integral.image_means takes it: its
 * pixels summed in order in double (what torch's cumsum of the flattened image carries to its last element),
 * rounded to float32, then divided by the pixel count in float32. Torch's cumsum wrote every running sum to keep
 * the last (0.2 ms a 320 x 240 pair).
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp (see svs_torch/core/kernels/loader.py).
 */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "common.h"

/* image: (B, H, W) float32 contiguous; means: (B,) float32, subtracted from every pixel; out: (B, PH, PW) with
 * PH = H + 1 + 2 pad, PW = W + 1 + 2 pad: out[pad + 1 + y][pad + 1 + x] = the sum over [0, y] x [0, x], row and
 * column pad of zeros, every border replicated outwards; means NULL: each image's own (above). Images are shared
 * among num_threads OpenMP threads.
 * Returns 0, or -1 when memory could not be had (nothing is written; the caller runs its torch path). */
int padded_integral(const float *image, const float *means, int64_t B, int64_t H, int64_t W, int64_t pad,
                    float *out, int64_t num_threads) {
    const int64_t PH = H + 1 + 2 * pad, PW = W + 1 + 2 * pad;
    const int threads = thread_count(num_threads, B);
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        double *columns = scratch(W, sizeof(double));
        float *rounded = scratch(W, sizeof(float));
        scratch_ready(columns && rounded, &failed);
#pragma omp barrier
        if (!failed) {
#pragma omp for schedule(static)
            for (int64_t b = 0; b < B; ++b) {
                const float *source = image + b * H * W;
                float mean;
                if (means) {
                    mean = means[b];
                } else {
                    double sum = 0.0;
                    for (int64_t i = 0; i < H * W; ++i) sum += (double)source[i];
                    mean = (float)sum / (float)(H * W);
                }
                float *table = out + b * PH * PW;
                /* Rows 0 .. pad: the zero row in front, replicated upwards. */
                memset(table, 0, sizeof(float) * (size_t)((pad + 1) * PW));
                for (int64_t x = 0; x < W; ++x) columns[x] = 0.0;
                for (int64_t y = 0; y < H; ++y) {
                    const float *row = source + y * W;
                    for (int64_t x = 0; x < W; ++x) {
                        columns[x] += (double)(row[x] - mean);
                        rounded[x] = (float)columns[x];
                    }
                    float *target = table + (pad + 1 + y) * PW;
                    for (int64_t x = 0; x <= pad; ++x) target[x] = 0.0f; /* the zero column, replicated left */
                    double along = 0.0;
                    for (int64_t x = 0; x < W; ++x) {
                        along += (double)rounded[x];
                        target[pad + 1 + x] = (float)along;
                    }
                    const float last = W > 0 ? target[pad + W] : 0.0f;
                    for (int64_t x = pad + 1 + W; x < PW; ++x) target[x] = last;
                }
                /* Rows past the last: the last row replicated downwards. */
                const float *last_row = table + (pad + H) * PW;
                for (int64_t y = pad + 1 + H; y < PH; ++y) memcpy(table + y * PW, last_row, sizeof(float) * (size_t)PW);
            }
        }
        free(columns);
        free(rounded);
    }
    return failed ? -1 : 0;
}
