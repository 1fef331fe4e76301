/* The MSAC cost of every row-alignment hypothesis, for svs_torch.geometry.row_alignment.fit_row_alignment (the
 * no-gradient path; its torch expression, _msac_cost, stays the reference).
 *
 * The torch path writes the (B, M, K) residuals of M hypotheses against K matches and passes over them five more
 * times (abs, clamp, square, mask, sum): float64 arrays of B x 256 x K, where K is the batch's largest match count,
 * so the stage's time per pair grew with the batch (5.7 ms a pair at B = 32, 9.2 at B = 128, one thread). Here each
 * hypothesis's cost is summed in one pass over its pair's valid matches, held in registers. Every residual is the
 * torch path's value (the same float64 operations in the same order; no contraction to fused multiply-adds); the
 * sum runs over the matches in index order, so it can differ from torch's (vectorised) summation in the last
 * bits, which can only matter between two hypotheses whose costs tie to those bits.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp (svs_torch/core/kernels/loader.py). Loaded
 * through ctypes by svs_torch/geometry/kernels/__init__.py; pairs are shared among num_threads OpenMP threads.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "common.h"

/* params (B, M, 3) float64, (a, b, t_y) of each hypothesis (NaN in any: a degenerate sample); left_y, right_x,
 * right_y (B, K) float64; valid (B, K) uint8. Writes cost (B, M) float64: the sum over the pair's valid matches of
 * min(|b x_r + a y_r + t_y - y_l|, threshold)^2, +inf for a degenerate hypothesis. Returns -1 when memory could not
 * be had (cost is then incomplete; the caller runs the torch path). */
int row_alignment_cost(const double *params, const double *left_y, const double *right_x, const double *right_y,
                       const uint8_t *valid, int64_t B, int64_t M, int64_t K, double threshold, double *cost,
                       int64_t num_threads) {
    const int threads = thread_count(num_threads, B);
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        /* The pair's valid matches, packed in index order, so that each hypothesis is one branch-free pass. */
        double *packed = scratch(3 * K, sizeof(double));
        const int ready = scratch_ready(packed != NULL, &failed);
#pragma omp for schedule(dynamic, 1)
        for (int64_t p = 0; p < B; ++p) {
            if (!ready) continue;
            double *xs = packed, *ys = packed + K, *ls = packed + 2 * K;
            int64_t n = 0;
            for (int64_t k = 0; k < K; ++k) {
                if (valid[p * K + k]) {
                    xs[n] = right_x[p * K + k];
                    ys[n] = right_y[p * K + k];
                    ls[n] = left_y[p * K + k];
                    ++n;
                }
            }
            for (int64_t m = 0; m < M; ++m) {
                const double *h = params + (p * M + m) * 3;
                const double a = h[0], b = h[1], t = h[2];
                if (isnan(a) || isnan(b) || isnan(t)) {
                    cost[p * M + m] = INFINITY;
                    continue;
                }
                double total = 0.0;
                for (int64_t i = 0; i < n; ++i) {
                    double r = fabs((b * xs[i] + a * ys[i]) + t - ls[i]);
                    r = r > threshold ? threshold : r;  /* torch's clamp(max=...): a NaN stays NaN */
                    total += r * r;
                }
                cost[p * M + m] = total;
            }
        }
        free(packed);
    }
    return failed ? -1 : 0;
}
