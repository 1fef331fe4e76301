/* Nearest and second-nearest neighbours by SAD (L1) between descriptor sets, for svs_torch.matching (the
 * no-gradient path of _match_group; the torch path, torch.cdist + topk + argmin, stays the reference).
 *
 * The torch path writes the whole (B, K, K2) distance matrix, masks it, and reads it three more times (the
 * two smallest per row, the argmin per column). Here each left row's distances to every right descriptor are
 * made in one pass over the descriptor dimension, vectorised across right descriptors (the right set is
 * given transposed, (B, D, K2)), and consumed at once: the row's nearest and second-nearest allowed
 * candidates, and each column's nearest left row. A distance is summed in float32 over d in order, so it can
 * differ from torch.cdist's (another summation order) in the last bits.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp (see svs_torch/kernels/__init__.py).
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "common.h"

/* left: (B, K, D); right_t: (B, D, K2); allowed: (B, K, K2) uint8. Writes best, second (B, K) float32 (+inf
 * when there is no allowed candidate or only one), best_index (B, K) int64 (the first on ties; 0 when none),
 * back (B, K2) int64: the left row nearest to each right descriptor among its allowed rows (the first on
 * ties; 0 when none), as torch's argmin over the masked matrix. Returns -1 when memory could not be had. */
int sad_nearest(const float *left, const float *right_t, const uint8_t *allowed, int64_t B, int64_t K,
                int64_t K2, int64_t D, float *best, float *second, int64_t *best_index, int64_t *back,
                int64_t num_threads) {
    const int threads = thread_count(num_threads, B);
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        float *distance = scratch(K2, sizeof(float));
        float *column_best = scratch(K2, sizeof(float));
        const int ready = scratch_ready(distance && column_best, &failed);
#pragma omp for schedule(dynamic, 1)
        for (int64_t b = 0; b < B; ++b) {
            if (!ready) continue;
            const float *rt = right_t + b * D * K2;
            int64_t *column_index = back + b * K2;
            for (int64_t j = 0; j < K2; ++j) {
                column_best[j] = INFINITY;
                column_index[j] = 0;
            }
            for (int64_t i = 0; i < K; ++i) {
                const float *l = left + (b * K + i) * D;
                const uint8_t *ok = allowed + (b * K + i) * K2;
                for (int64_t j = 0; j < K2; ++j) distance[j] = 0.0f;
                for (int64_t d = 0; d < D; ++d) {
                    const float value = l[d];
                    const float *restrict column = rt + d * K2;
                    float *restrict sum = distance;
                    for (int64_t j = 0; j < K2; ++j) sum[j] += fabsf(value - column[j]);
                }
                float first = INFINITY, next = INFINITY;
                int64_t first_index = 0;
                for (int64_t j = 0; j < K2; ++j) {
                    const float c = ok[j] ? distance[j] : INFINITY;
                    if (c < first) {
                        next = first;
                        first = c;
                        first_index = j;
                    } else if (c < next) {
                        next = c;
                    }
                    if (c < column_best[j]) {
                        column_best[j] = c;
                        column_index[j] = i;
                    }
                }
                best[b * K + i] = first;
                second[b * K + i] = next;
                best_index[b * K + i] = first_index;
            }
        }
        free(distance);
        free(column_best);
    }
    return failed ? -1 : 0;
}
