/* Square median filter with replicated edges, for svs_torch.segmentation.nearness (the nearness map's denoising
 * median, the no-gradient path).
 *
 * The torch path pads the map, unfolds every K x K window and takes ``median(-1)``: it copies K^2 values per pixel
 * and sorts each window (49 values at K = 7): 16 ms a pair of 320x240 on one thread, most of the nearness
 * segmenter. Here each output row lays out its window's columns side by side (edge columns repeated), so the
 * window of every pixel is K^2 consecutive values, and the median is tracked along the row: the window's median
 * m is its value with fewer than R = (K^2 - 1) / 2 + 1 values below it and at least R at or below it; a step
 * right changes K of the K^2 values, so the new median is a few distinct values from the last one, and m moves
 * to the next smaller (or larger) window value until the counts hold. Each count or move is one branch-free pass
 * over K^2 values. The result is the element of rank (K^2 - 1) / 2, torch's (lower) median, one of the window's
 * own values: the torch path's values (a zero's sign aside where -0 and +0 meet in one window). NaN is not
 * allowed (the caller checks); +-inf are ordinary values.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp. Loaded through ctypes by
 * svs_torch/segmentation/kernels/__init__.py; image rows are shared among num_threads OpenMP threads.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "common.h"

static inline int64_t clamp_index(int64_t i, int64_t n) { return i < 0 ? 0 : (i >= n ? n - 1 : i); }

/* The element of rank ``rank`` of ``v[0, n)``, found from ``m``, one of its values (see the top). Each pass
 * counts the values below and equal to m and finds the nearest values on either side, so a move to the next
 * value needs no second pass. */
static float track_median(const float *v, int n, int rank, float m) {
    for (;;) {
        int below = 0, equal = 0;
        float under = -INFINITY, over = INFINITY;
#pragma omp simd reduction(+ : below, equal) reduction(max : under) reduction(min : over)
        for (int i = 0; i < n; ++i) {
            const float x = v[i], lower = x < m ? x : -INFINITY, upper = x > m ? x : INFINITY;
            below += x < m;
            equal += x == m;
            under = lower > under ? lower : under;
            over = upper < over ? upper : over;
        }
        if (below > rank) m = under;              /* the median is smaller: the largest value below m */
        else if (below + equal <= rank) m = over; /* larger: the smallest value above m */
        else return m;
    }
}

/* Returns 0, or -1 when memory could not be had (the caller then runs the torch path). */
int median_filter(const float *image, int64_t B, int64_t H, int64_t W, int64_t K, float *out, int64_t num_threads) {
    const int64_t rows = B * H, half = K / 2, n = K * K, rank = (K * K - 1) / 2;
    const int threads = thread_count(num_threads, rows);
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        /* Column px of the row's window band (image column px - half, clamped), its K values one after another. */
        float *band = scratch((W + 2 * half) * K, sizeof(float));
        const int ready = scratch_ready(band != NULL, &failed);
#pragma omp for schedule(static)
        for (int64_t r = 0; r < rows; ++r) {
            if (!ready) continue;
            const int64_t b = r / H, y = r % H;
            const float *plane = image + b * H * W;
            for (int64_t px = 0; px < W + 2 * half; ++px) {
                const int64_t x = clamp_index(px - half, W);
                for (int64_t dy = 0; dy < K; ++dy) band[px * K + dy] = plane[clamp_index(y + dy - half, H) * W + x];
            }
            float *row = out + r * W;
            float m = band[n / 2]; /* any of the first window's values will do */
            for (int64_t x = 0; x < W; ++x) {
                m = track_median(band + x * K, (int)n, (int)rank, m);
                row[x] = m;
            }
        }
        free(band);
    }
    return failed ? -1 : 0;
}
