/* The lower median of every labelled region, for svs_torch.depth.quantiles.region_lower_median (the nearness
 * segmenter's ranking of its candidate regions, the no-gradient path).
 *
 * The torch path sorts each pair's (P,) values, then its labels stably in that order, so each region's values lie
 * together in ascending order, and reads the middle of each: two O(P log P) sorts and four gathers of the pair.
 * Here one pass counts each label's members, a second copies them into their region's stretch of one buffer, and
 * a quickselect per region finds its member of rank (count - 1) / 2 (select_rank.h), O(P) in all:
 *   count[b, l - 1]  = #{p : labels[b, p] == l}                 for l = 1 .. L (label 0: no region)
 *   median[b, l - 1] = the member of rank (count - 1) / 2, 0 for an empty label
 * Selection compares and moves values and does no arithmetic on them, so these are the torch path's medians
 * exactly. NaN is not allowed and every label is in [0, L] (the caller checks); +-inf are ordinary values.
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
int region_medians(const float *values, const int64_t *labels, int64_t B, int64_t P, int64_t L, int64_t *count,
                   float *median, int64_t num_threads) {
    const int threads = thread_count(num_threads, B);
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        float *members = scratch(P, sizeof(float));
        int64_t *next = scratch(L + 1, sizeof(int64_t)); /* where each label's next member goes */
        const int ready = scratch_ready(members && next, &failed);
#pragma omp for schedule(dynamic, 1)
        for (int64_t b = 0; b < B; ++b) {
            if (!ready || L == 0) continue;
            const float *v = values + b * P;
            const int64_t *l = labels + b * P;
            int64_t *n = count + b * L; /* n[label - 1] */
            for (int64_t i = 0; i < L; ++i) n[i] = 0;
            for (int64_t p = 0; p < P; ++p)
                if (l[p] > 0) ++n[l[p] - 1];
            next[1] = 0;
            for (int64_t i = 1; i < L; ++i) next[i + 1] = next[i] + n[i - 1];
            for (int64_t p = 0; p < P; ++p)
                if (l[p] > 0) members[next[l[p]]++] = v[p];
            int64_t start = 0;
            for (int64_t i = 0; i < L; ++i) {
                const int64_t m = n[i], k = start + (m - 1) / 2;
                if (m > 0) select_rank(members, start, start + m, k);
                median[b * L + i] = m > 0 ? members[k] : 0.0f;
                start += m;
            }
        }
        free(members);
        free(next);
    }
    return failed ? -1 : 0;
}
