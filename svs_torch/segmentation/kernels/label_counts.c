/* How many pixels of each labelled region a flag marks, for svs_torch.segmentation.nearness_regions._label_counts
 * (the nearness segmenter's measured area of each candidate region and its share clipped at white).
 *
 * The torch path converts the (B, P) bool flags to an int64 image and scatter-adds it at the labels: at 640 x 480
 * and B = 8 a 20 MB temporary and a scatter of 2.5 million elements, about 12 ms a call, 2 calls a batch (2.4 ms at
 * 320 x 240). Here one pass per pair reads each label and flag and counts:
 *   counts[b, l - 1] = #{p : labels[b, p] == l and flags[b, p]}     for l = 1 .. L (label 0: background)
 * Whole-number counts: the torch path's exactly.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp (svs_torch/core/kernels/loader.py). Loaded
 * through ctypes by svs_torch/segmentation/kernels/__init__.py; pairs are shared among num_threads OpenMP threads.
 */
#include <stdint.h>

#include "common.h"

/* labels (B, P) int64 in [0, L]; flags (B, P) bool as bytes (0 or 1); writes counts (B, L) int64. Returns 0, or -2
 * when a label lies outside [0, L] (the counts are then not to be read; the caller names the label image). */
int label_counts(const int64_t *labels, const uint8_t *flags, int64_t B, int64_t P, int64_t L, int64_t *counts,
                 int64_t num_threads) {
    const int threads = thread_count(num_threads, B);
    int outside = 0;
#pragma omp parallel for num_threads(threads) schedule(static) reduction(| : outside)
    for (int64_t b = 0; b < B; ++b) {
        const int64_t *l = labels + b * P;
        const uint8_t *f = flags + b * P;
        int64_t *n = counts + b * L; /* n[label - 1] */
        for (int64_t i = 0; i < L; ++i) n[i] = 0;
        for (int64_t p = 0; p < P; ++p) {
            const int64_t label = l[p];
            if (label < 0 || label > L) {
                outside = 1;
                continue;
            }
            if (label > 0 && f[p]) ++n[label - 1];
        }
    }
    return outside ? -2 : 0;
}
