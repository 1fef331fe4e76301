/* The kept regions of the left view moved into the right view, for
 * svs_torch.segmentation.nearness_regions.shift_regions_to_right (the no-gradient path; its torch expression stays
 * the reference).
 *
 * The torch path makes, for each kept slot, a gather of the whole int64 label image at the shifted columns and a
 * dozen whole-image comparisons and selections: about 1 ms for one 320 x 240 pair, most of the nearness
 * segmenter's time after its block matcher at guide's B = 1. Here each output row is written once per slot from
 * the left row it reads, with the same rules: a slot's shift is its disparity rounded half to even (torch.round);
 * a pixel takes the slot whose left pixel, shift columns to its right, holds the slot's label; where two slots
 * land, the one of the larger (unrounded) shift wins, the earlier slot on ties. Integer labels and comparisons of
 * the same float32 shifts: the torch path's labels exactly.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp (svs_torch/core/kernels/loader.py). Loaded
 * through ctypes by svs_torch/segmentation/kernels/__init__.py; rows are shared among num_threads OpenMP threads.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "common.h"

/* labels (B, H, W) int64; kept (B, N) int64 (a slot <= 0 is empty); shift (B, N) float32, finite. Writes out
 * (B, H, W) int64. Returns -1 when memory could not be had (the caller runs the torch path). */
int shift_regions(const int64_t *labels, const int64_t *kept, const float *shift, int64_t B, int64_t H, int64_t W,
                  int64_t N, int64_t *out, int64_t num_threads) {
    const int threads = thread_count(num_threads, B * H);
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        float *best = scratch(W, sizeof(float));
        const int ready = scratch_ready(best != NULL, &failed);
#pragma omp for schedule(static)
        for (int64_t row = 0; row < B * H; ++row) {
            if (!ready) continue;
            const int64_t b = row / H;
            const int64_t *source = labels + row * W;
            int64_t *target = out + row * W;
            for (int64_t x = 0; x < W; ++x) {
                target[x] = 0;
                best[x] = -1.0f;
            }
            for (int64_t n = 0; n < N; ++n) {
                const int64_t label = kept[b * N + n];
                const float s = shift[b * N + n];
                if (label <= 0) continue;
                const double rounded = nearbyint((double)s); /* half to even, as torch.round */
                if (!(rounded > -(double)W && rounded < (double)W)) continue; /* no column lands inside */
                const int64_t offset = (int64_t)rounded;
                const int64_t first = offset < 0 ? -offset : 0, last = offset > 0 ? W - offset : W;
                for (int64_t x = first; x < last; ++x)
                    if (source[x + offset] == label && s > best[x]) {
                        target[x] = label;
                        best[x] = s;
                    }
            }
        }
        free(best);
    }
    return failed ? -1 : 0;
}
