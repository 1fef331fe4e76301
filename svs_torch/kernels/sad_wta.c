/* Fused SAD block matching with winner-takes-all, for svs_torch.dense (the hard, non-differentiable path).
 *
 * The eager torch path (svs_torch/dense.py, _cost_volume + _winner + _right_winner) makes about 25 passes over
 * a B x D x h x w cost volume; here each output row's costs for every disparity are made and consumed while
 * they sit in cache:
 *   A(y, x, d) = |L(y, x) - R(y, x + D - 1 - d)|                       (the right crop is D - 1 columns wider)
 *   V(y, x, d) = A(y) + ... + A(y + K - 1)                              (running: + the entering row - the leaving)
 *   C(y, x, d) = V(x) + ... + V(x + K - 1)
 *   C = +inf where d >= count[b] or the right pixel x0 + x - (min_d + d) leaves [0, image_w)
 * then per pixel: the first minimum over d (best, best_cost), the costs at best -+ 1 (clamped to the range),
 * the least cost farther than 1 from best (rival, +inf if none), and the right view's winner
 * C_R(j, k) = C(j + k, k) (first minimum over k; -1 where it is +inf). The left view's statistics are made
 * only for the columns [left_first, left_first + left_width) (the box; the columns on either side serve the
 * right view's winner). All of it streams over d: one row of
 * costs per disparity and a dozen running values per column stay in L1, the column sums in L2.
 *
 * The inputs are whole numbers (StereoBM's 8-bit levels, svs_torch.dense.quantize_levels), so every sum is an
 * exact float32 integer (K^2 * 510 < 2^24) in any order, and the results equal the torch path's bit for bit;
 * minima and selects do no arithmetic, so streaming over d changes no value either.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp (no -ffast-math: it could treat the
 * +inf costs as impossible). Loaded through ctypes by svs_torch/kernels/__init__.py, which falls back to the
 * torch path without a compiler.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

typedef struct {
    const float *left;   /* (B, HL, WL) */
    const float *right;  /* (B, HL, WL + D - 1) */
    int64_t B, HL, WL, D, K;
    int64_t left_first, left_width; /* the columns whose left-view statistics are wanted */
    const int64_t *x0, *min_d, *image_w, *counts;  /* (B,) each */
    float *best_cost, *before, *after, *rival;     /* (B, H, left_width) each, H = HL - K + 1 */
    int64_t *best;                                 /* (B, H, left_width) */
    int64_t *right_best;                           /* (B, H, W), W = WL - K + 1 */
    int64_t bands, band_rows;
} Job;

/* Per-row state of the streaming winner search over d, one entry per output column (indices kept as floats,
 * exact for any count here, so that every select is as wide as the costs and vectorises). */
typedef struct {
    float *cost, *best_cost, *best, *before, *after, *rival, *prefix1, *prefix2, *previous, *right_cost, *right_best;
} RowState;

/* One disparity of the streaming winner search (kept out of line, with restrict arguments, so that gcc
 * vectorises it: inlined into run_band it does not). The winner so far (first index on ties), the costs beside
 * it, and the rival: the least cost more than 1 from it; a new winner at d inherits as rival the least cost of
 * indices <= d - 2. Branch-free, every load unconditional. */
__attribute__((noinline)) static void step_left(int64_t W, float fd, const float *restrict c,
                                                float *restrict best_cost, float *restrict best,
                                                float *restrict rival, float *restrict after,
                                                float *restrict before, float *restrict prefix1,
                                                float *restrict prefix2, float *restrict previous) {
    for (int64_t x = 0; x < W; ++x) {
        float cx = c[x], b1 = best_cost[x], i1 = best[x], r = rival[x], a = after[x], p1 = prefix1[x];
        float p2 = prefix2[x], bf = before[x], pv = previous[x];
        int better = cx < b1;
        int take = (fd > i1 + 1.0f) & (cx < r);
        float kept_rival = take ? cx : r;
        float kept_after = (fd == i1 + 1.0f) ? cx : a;
        rival[x] = better ? p2 : kept_rival;
        after[x] = better ? cx : kept_after;
        before[x] = better ? pv : bf;
        best[x] = better ? fd : i1;
        best_cost[x] = better ? cx : b1;
        prefix2[x] = p1;
        prefix1[x] = cx < p1 ? cx : p1;
        previous[x] = cx;
    }
}

/* The right view's winner: C_R(j, d) = C(j + d, d), ``shifted`` = the cost row from column d. */
__attribute__((noinline)) static void step_right(int64_t n, float fd, const float *restrict shifted,
                                                 float *restrict right_cost, float *restrict right_best) {
    for (int64_t j = 0; j < n; ++j) {
        float s = shifted[j], rc = right_cost[j];
        int better = s < rc;
        right_cost[j] = better ? s : rc;
        right_best[j] = better ? fd : right_best[j];
    }
}

/* v += |l - r| over n columns. */
__attribute__((noinline)) static void add_row(int64_t n, const float *restrict l, const float *restrict r,
                                              float *restrict v) {
    for (int64_t x = 0; x < n; ++x) v[x] += fabsf(l[x] - r[x]);
}

/* v += |l_in - r_in| - |l_out - r_out|: the window slides down one row. */
__attribute__((noinline)) static void slide_row(int64_t n, const float *restrict l_in, const float *restrict r_in,
                                                const float *restrict l_out, const float *restrict r_out,
                                                float *restrict v) {
    for (int64_t x = 0; x < n; ++x) v[x] += fabsf(l_in[x] - r_in[x]) - fabsf(l_out[x] - r_out[x]);
}

/* c[x] = v[x] + v[x + 1] + ... + v[x + K - 1], n columns. */
__attribute__((noinline)) static void box_row(int64_t n, int64_t K, const float *restrict v, float *restrict c) {
    for (int64_t x = 0; x < n; ++x) c[x] = v[x];
    for (int64_t j = 1; j < K; ++j)
        for (int64_t x = 0; x < n; ++x) c[x] += v[x + j];
}

static void run_band(Job *job, int64_t b, int64_t y_begin, int64_t y_end, float *vsum,
                     RowState *st) {
    const int64_t HL = job->HL, WL = job->WL, D = job->D, K = job->K;
    const int64_t H = HL - K + 1, W = WL - K + 1, WR = WL + D - 1;
    const int64_t first = job->left_first, WC = job->left_width;
    const float *left = job->left + b * HL * WL;
    const float *right = job->right + b * HL * WR;
    const int64_t count = job->counts[b];
    /* Disparity index d is searched at crop column x when lo(d) <= x < hi(d). */
    const int64_t shift = job->min_d[b] - job->x0[b];
    float *restrict c = st->cost;
    float *restrict best_cost = st->best_cost, *restrict best = st->best, *restrict before = st->before;
    float *restrict after = st->after, *restrict rival = st->rival, *restrict prefix1 = st->prefix1;
    float *restrict prefix2 = st->prefix2, *restrict previous = st->previous;
    float *restrict right_cost = st->right_cost, *restrict right_best = st->right_best;
    for (int64_t y = y_begin; y < y_end; ++y) {
        /* Column sums of |L - R| over the window's K rows, for every d: the band's first row sums them, each
         * later row adds the row entering the window and subtracts the one leaving it (exact: whole numbers). */
        for (int64_t d = 0; d < D; ++d) {
            float *v = vsum + d * WL;
            if (y == y_begin) {
                for (int64_t x = 0; x < WL; ++x) v[x] = 0.0f;
                for (int64_t r = y; r < y + K; ++r)
                    add_row(WL, left + r * WL, right + r * WR + (D - 1 - d), v);
            } else {
                int64_t r = y + K - 1;
                slide_row(WL, left + r * WL, right + r * WR + (D - 1 - d), left + (y - 1) * WL,
                          right + (y - 1) * WR + (D - 1 - d), v);
            }
        }
        for (int64_t d = 0; d < D; ++d) {
            const float *vsum_d = vsum + d * WL;
            box_row(W, K, vsum_d, c);
            int64_t lo = shift + d, hi = job->image_w[b] + shift + d;
            if (d >= count) lo = W;
            if (lo < 0) lo = 0;
            if (lo > W) lo = W;
            if (hi > W) hi = W;
            if (hi < lo) hi = lo;
            for (int64_t x = 0; x < lo; ++x) c[x] = INFINITY;
            for (int64_t x = hi; x < W; ++x) c[x] = INFINITY;
            const float fd = (float)d;
            if (d == 0) {
                for (int64_t x = 0; x < WC; ++x) {
                    const float cx = c[first + x];
                    best_cost[x] = cx;
                    best[x] = 0.0f;
                    before[x] = cx;  /* the clamped neighbour of index 0 is index 0 */
                    after[x] = cx;   /* replaced at d = 1 when the range has one */
                    rival[x] = INFINITY;
                    prefix2[x] = INFINITY;
                    prefix1[x] = cx;
                    previous[x] = cx;
                }
                for (int64_t x = 0; x < W; ++x) {
                    right_cost[x] = c[x];
                    right_best[x] = 0.0f;
                }
                continue;
            }
            step_left(WC, fd, c + first, best_cost, best, rival, after, before, prefix1, prefix2, previous);
            step_right(W - d, fd, c + d, right_cost, right_best);
        }
        int64_t offset = (b * H + y) * WC;
        float *out_cost = job->best_cost + offset, *out_before = job->before + offset;
        float *out_after = job->after + offset, *out_rival = job->rival + offset;
        int64_t *out_best = job->best + offset, *out_right = job->right_best + (b * H + y) * W;
        for (int64_t x = 0; x < WC; ++x) {
            out_cost[x] = best_cost[x];
            out_best[x] = (int64_t)best[x];
            out_before[x] = before[x];
            out_after[x] = after[x];
            out_rival[x] = rival[x];
        }
        for (int64_t x = 0; x < W; ++x) out_right[x] = isfinite(right_cost[x]) ? (int64_t)right_best[x] : -1;
    }
}

/* Returns 0 on success, -1 when memory could not be had (the caller then uses the torch path). Pairs and
 * bands of rows are shared among num_threads OpenMP threads (torch's own pool: svs_torch/kernels/__init__.py). */
int sad_wta(const float *left, const float *right, int64_t B, int64_t HL, int64_t WL, int64_t D, int64_t K,
            const int64_t *x0, const int64_t *min_d, const int64_t *image_w, const int64_t *counts,
            float *best_cost, int64_t *best, float *before, float *after, float *rival, int64_t *right_best,
            int64_t left_first, int64_t left_width, int64_t num_threads, int64_t band_rows) {
    const int64_t H = HL - K + 1, W = WL - K + 1;
    if (B <= 0 || HL < K || WL < K || D < 1 || K < 1) return 0;
    if (left_first < 0 || left_width < 0 || left_first + left_width > W) return -1;
    Job job = {left, right, B, HL, WL, D, K, left_first, left_width, x0, min_d, image_w, counts, best_cost,
               before, after, rival, best, right_best, 0, 0};
    job.band_rows = band_rows < 1 ? H : band_rows;
    job.bands = (H + job.band_rows - 1) / job.band_rows;
    const int64_t tasks = B * job.bands;
    int threads = (int)(num_threads < 1 ? 1 : (num_threads > tasks ? tasks : num_threads));
    int failed = 0;
    /* Tasks (pair, band of rows) are handed out one at a time: bands differ in cost (the last is shorter). */
#pragma omp parallel num_threads(threads)
    {
        float *vsum = malloc(sizeof(float) * (size_t)(D * WL));
        float *rows = malloc(sizeof(float) * (size_t)(11 * W));
        RowState st = {rows, rows + W, rows + 2 * W, rows + 3 * W, rows + 4 * W, rows + 5 * W, rows + 6 * W,
                       rows + 7 * W, rows + 8 * W, rows + 9 * W, rows + 10 * W};
        if (!vsum || !rows) {
#pragma omp atomic write
            failed = 1;
        }
#pragma omp for schedule(dynamic, 1)
        for (int64_t task = 0; task < tasks; ++task) {
            if (!vsum || !rows) continue;
            int64_t b = task / job.bands, band = task % job.bands;
            int64_t y0 = band * job.band_rows, y1 = y0 + job.band_rows;
            if (y1 > H) y1 = H;
            if (y0 < y1) run_band(&job, b, y0, y1, vsum, &st);
        }
        free(vsum);
        free(rows);
    }
    return failed ? -1 : 0;
}
