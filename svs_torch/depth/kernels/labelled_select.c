/* Order statistics of labelled values, for svs_torch.depth.quantiles.labelled_quantile (the dense depth stage's
 * per-object median and percentiles, the no-gradient path).
 *
 * The torch path sorts every pair's (B, P) values once (numpy's argsort), gathers, and finds each slot's ranks
 * through a (B, N, P) running count: on the depth stage's 8 x 80 000 values that is several passes and an
 * O(P log P) sort per pair. Only 2 Q order statistics per object are wanted, so here each object's members are
 * copied out in one pass over the pair and the wanted ranks are found by quickselect, O(P) each:
 *   count[b, n] = #{p : labels[b, p] == slots[b, n]}                     (0 where slots[b, n] <= 0)
 *   position    = q[i] * (float)max(count - 1, 0)                         (float32, as the torch path computes it)
 *   below[b, n, i] = the member of rank floor(position), above[...] = of rank ceil(position)
 * Selection compares and moves values and does no arithmetic on them, so these are the torch path's order
 * statistics exactly (the caller interpolates them with its own float32 ops). NaN is not allowed (the caller
 * checks); +-inf are ordinary values.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp. Loaded through ctypes by
 * svs_torch/depth/kernels/__init__.py; pairs are shared among num_threads OpenMP threads.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "common.h"
#include "select_rank.h"

/* Returns 0, or -1 when memory could not be had (the caller then runs the torch path). */
int labelled_select(const float *values, const int64_t *labels, const int64_t *slots, const float *q, int64_t B,
                    int64_t P, int64_t N, int64_t Q, int64_t *count, float *below, float *above,
                    int64_t num_threads) {
    const int threads = thread_count(num_threads, B);
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        float *members = scratch(P, sizeof(float));
        int64_t *ranks = scratch(2 * Q, sizeof(int64_t));
        const int ready = scratch_ready(members && ranks, &failed);
#pragma omp for schedule(dynamic, 1)
        for (int64_t b = 0; b < B; ++b) {
            if (!ready) continue;
            const float *v = values + b * P;
            const int64_t *l = labels + b * P;
            for (int64_t n = 0; n < N; ++n) {
                const int64_t slot = slots[b * N + n], out = (b * N + n) * Q;
                int64_t m = 0;
                if (slot > 0)
                    for (int64_t p = 0; p < P; ++p)
                        if (l[p] == slot) members[m++] = v[p];
                count[b * N + n] = m;
                order_statistics(members, m, q, Q, ranks, below + out, above + out);
            }
        }
        free(members);
        free(ranks);
    }
    return failed ? -1 : 0;
}
