/* Gray levels and their histogram, for svs_torch.segmentation.threshold (the no-gradient path of gray_levels
 * followed by gray_histogram, whose torch forms stay the reference and the fallback).
 *
 * The torch path multiplies, rounds, clamps and converts the float image (four passes), then widens the levels
 * to int32, offsets them by image and counts them with one bincount (three more): about 0.3 ms a pair for the 16
 * images of a batch of 8 at 320x240. Here each image is read once: level = round-half-even(255 x) clamped to
 * [0, 255] in float32, as torch computes it (so the same levels), written as a byte and counted.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp. Loaded through ctypes by
 * svs_torch/segmentation/kernels/__init__.py.
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "common.h"

#define LEVELS 256
#define CHUNK 4096

/* image: (N, P) float32 in [0, 1] (N images of P pixels); writes levels (N, P) uint8 and histogram (N, 256)
 * int64. Images are shared among num_threads OpenMP threads. Returns 0. */
int gray_levels(const float *image, int64_t N, int64_t P, uint8_t *levels, int64_t *histogram,
                int64_t num_threads) {
    const int threads = thread_count(num_threads, N);
#pragma omp parallel for num_threads(threads) schedule(dynamic, 1)
    for (int64_t n = 0; n < N; ++n) {
        const float *x = image + n * P;
        uint8_t *out = levels + n * P;
        /* Four interleaved tables: consecutive equal levels (flat regions) would otherwise wait on each other's
         * increments. */
        uint32_t counts[4][LEVELS];
        memset(counts, 0, sizeof counts);
        for (int64_t begin = 0; begin < P; begin += CHUNK) {
            const int64_t end = begin + CHUNK < P ? begin + CHUNK : P;
            /* The levels of a chunk first (a loop gcc vectorises), then their counts. */
            for (int64_t p = begin; p < end; ++p) {
                float v = nearbyintf(x[p] * 255.0f);
                v = v > 0.0f ? v : 0.0f; /* no NaN here: svs_torch.core.checks.check_image rules it out */
                v = v < 255.0f ? v : 255.0f;
                out[p] = (uint8_t)v;
            }
            int64_t p = begin;
            for (; p + 4 <= end; p += 4) {
                ++counts[0][out[p]];
                ++counts[1][out[p + 1]];
                ++counts[2][out[p + 2]];
                ++counts[3][out[p + 3]];
            }
            for (; p < end; ++p) ++counts[0][out[p]];
        }
        for (int l = 0; l < LEVELS; ++l)
            histogram[n * LEVELS + l] = (int64_t)counts[0][l] + counts[1][l] + counts[2][l] + counts[3][l];
    }
    return 0;
}
