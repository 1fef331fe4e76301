/* The k strongest SURF candidates of each image, for svs_torch.detector (the no-gradient path of its torch.topk).
 *
 * The detector's candidate scores (B, N) hold det(H) at each image's scale-space maxima, a few hundred, and -inf
 * at the other points of its octaves, about 200 000 at 320x240. torch.topk partially sorts every whole row
 * (2.5 ms for 8 images on one thread). Here each row is scanned once for its finite entries, which alone are
 * sorted: largest first, equal scores in index order (an order torch.topk leaves open). The k values are
 * torch.topk's; positions past a row's last candidate get -inf at index 0.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp. Loaded through ctypes by
 * svs_torch/kernels/__init__.py; rows are shared among num_threads OpenMP threads.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "common.h"

/* Scores tested at once when collecting the candidates. */
#define BLOCK 64

typedef struct {
    float value;
    int64_t index;
} candidate;

/* qsort order: the larger value first, then the smaller index (the entries are distinct, so a total order). */
static int stronger_first(const void *a, const void *b) {
    const candidate *x = a, *y = b;
    if (x->value != y->value) return x->value > y->value ? -1 : 1;
    return (x->index > y->index) - (x->index < y->index);
}

/* scores: contiguous (B, N) float32; values (B, k) float32 and index (B, k) int64, k <= N. Returns 0; 1 when a
 * row holds a NaN (torch.topk ranks NaN above every number; the caller then runs it); -1 when memory could not
 * be had (the caller then runs torch.topk). */
int top_candidates(const float *scores, int64_t B, int64_t N, int64_t k, float *values, int64_t *index,
                   int64_t num_threads) {
    const int threads = thread_count(num_threads, B);
    int failed = 0, saw_nan = 0;
#pragma omp parallel for num_threads(threads) schedule(static)
    for (int64_t b = 0; b < B; ++b) {
        const float *row = scores + b * N;
        int64_t count = 0, nan = 0;
        for (int64_t i = 0; i < N; ++i) {  /* one vectorised pass: most entries are -inf */
            count += row[i] > -INFINITY;
            nan |= row[i] != row[i];
        }
        if (nan) {
#pragma omp atomic write
            saw_nan = 1;
            continue;
        }
        candidate *found = scratch(count, sizeof(candidate));
        if (!scratch_ready(found != NULL, &failed)) continue;
        /* Collected a block at a time: a block without a candidate (nearly all) costs one vectorised test. */
        int64_t n = 0;
        for (int64_t start = 0; start < N && n < count; start += BLOCK) {
            const int64_t stop = start + BLOCK < N ? start + BLOCK : N;
            int any = 0;
            for (int64_t i = start; i < stop; ++i) any |= row[i] > -INFINITY;
            if (!any) continue;
            for (int64_t i = start; i < stop; ++i)
                if (row[i] > -INFINITY) {
                    found[n].value = row[i];
                    found[n].index = i;
                    ++n;
                }
        }
        qsort(found, (size_t)count, sizeof(candidate), stronger_first);
        for (int64_t j = 0; j < k; ++j) {
            values[b * k + j] = j < count ? found[j].value : -INFINITY;
            index[b * k + j] = j < count ? found[j].index : 0;
        }
        free(found);
    }
    return failed ? -1 : (saw_nan ? 1 : 0);
}
