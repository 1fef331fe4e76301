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
 * minima and selects do no arithmetic, so streaming over d changes no value either. Where a band's costs fit
 * 16 bits (K^2 * max|L - R| < 65535: StereoBM's x-Sobel levels at any usual K) the same search runs on int16
 * samples and uint16 costs, twice the lanes per instruction (8 real pairs' crops at K = 9, one thread: 70 -> 42
 * ms), with the same whole numbers and so the same results.
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

/* The streaming winner search is written once, for the two cost types of the header (COST: float, or uint16_t
 * with 65535 standing for +inf; StereoBM's levels have |L - R| <= 62, so any K up to 32 fits). Indices are kept
 * in the cost type (exact: D < 65535), so that every select is as wide as the costs and vectorises. */
#define U16_INF ((uint16_t)0xFFFF)

#define BOX_CASE(COST, KK)                                                                                        \
    case KK:                                                                                                      \
        for (int64_t x = 0; x < n; ++x) {                                                                         \
            COST sum = v[x];                                                                                      \
            for (int64_t j = 1; j < KK; ++j) sum += v[x + j];                                                     \
            c[x] = sum;                                                                                           \
        }                                                                                                         \
        return;

/* Per-row state of the streaming winner search over d, one entry per output column: 11 rows of W laid out
 * one after the other in rows. */
#define DEFINE_ROW_STATE(COST, SUFFIX)                                                                            \
    typedef struct {                                                                                              \
        COST *cost, *best_cost, *best, *before, *after, *rival, *prefix1, *prefix2, *previous, *right_cost,       \
            *right_best;                                                                                          \
    } RowState_##SUFFIX;                                                                                          \
    static RowState_##SUFFIX row_state_##SUFFIX(COST *rows, int64_t W) {                                         \
        RowState_##SUFFIX st = {rows, rows + W, rows + 2 * W, rows + 3 * W, rows + 4 * W, rows + 5 * W,         \
                                rows + 6 * W, rows + 7 * W, rows + 8 * W, rows + 9 * W, rows + 10 * W};          \
        return st;                                                                                                \
    }

/* One disparity of the streaming winner search (kept out of line, with restrict arguments, so that gcc
 * vectorises it: inlined into run_band it does not). The winner so far (first index on ties), the costs beside
 * it, and the rival: the least cost more than 1 from it; a new winner at d inherits as rival the least cost of
 * indices <= d - 2. Branch-free, every load unconditional. */
#define DEFINE_STEPS(COST, SUFFIX)                                                                                \
    __attribute__((noinline)) static void step_left_##SUFFIX(                                                    \
        int64_t W, COST fd, const COST *restrict c, COST *restrict best_cost, COST *restrict best,               \
        COST *restrict rival, COST *restrict after, COST *restrict before, COST *restrict prefix1,                \
        COST *restrict prefix2, COST *restrict previous) {                                                        \
        const COST next_to = (COST)(fd - 1); /* i1 + 1 == fd  <=>  i1 == fd - 1 (no overflow for any type) */    \
        for (int64_t x = 0; x < W; ++x) {                                                                        \
            COST cx = c[x], b1 = best_cost[x], i1 = best[x], r = rival[x], a = after[x], p1 = prefix1[x];       \
            COST p2 = prefix2[x], bf = before[x], pv = previous[x];                                              \
            int better = cx < b1;                                                                                \
            int take = (i1 < next_to) & (cx < r);                                                                \
            COST kept_rival = take ? cx : r;                                                                     \
            COST kept_after = (i1 == next_to) ? cx : a;                                                          \
            rival[x] = better ? p2 : kept_rival;                                                                 \
            after[x] = better ? cx : kept_after;                                                                 \
            before[x] = better ? pv : bf;                                                                        \
            best[x] = better ? fd : i1;                                                                          \
            best_cost[x] = better ? cx : b1;                                                                     \
            prefix2[x] = p1;                                                                                     \
            prefix1[x] = cx < p1 ? cx : p1;                                                                      \
            previous[x] = cx;                                                                                    \
        }                                                                                                        \
    }                                                                                                            \
    /* The right view's winner: C_R(j, d) = C(j + d, d), ``shifted`` = the cost row from column d. */            \
    __attribute__((noinline)) static void step_right_##SUFFIX(int64_t n, COST fd, const COST *restrict shifted,  \
                                                              COST *restrict right_cost,                         \
                                                              COST *restrict right_best) {                       \
        for (int64_t j = 0; j < n; ++j) {                                                                        \
            COST s = shifted[j], rc = right_cost[j];                                                             \
            int better = s < rc;                                                                                 \
            right_cost[j] = better ? s : rc;                                                                     \
            right_best[j] = better ? fd : right_best[j];                                                         \
        }                                                                                                        \
    }                                                                                                            \
    /* c[x] = v[x] + v[x + 1] + ... + v[x + K - 1], n columns. For the usual window sizes the sum is kept in a  \
     * register (a constant K: the j loop unrolls and x vectorises); else K passes over c. */                    \
    __attribute__((noinline)) static void box_row_##SUFFIX(int64_t n, int64_t K, const COST *restrict v,         \
                                                           COST *restrict c) {                                   \
        switch (K) {                                                                                             \
            BOX_CASE(COST, 3) BOX_CASE(COST, 5) BOX_CASE(COST, 7) BOX_CASE(COST, 9) BOX_CASE(COST, 11)          \
            BOX_CASE(COST, 13) BOX_CASE(COST, 15) BOX_CASE(COST, 17) BOX_CASE(COST, 19) BOX_CASE(COST, 21)      \
            default:                                                                                             \
                for (int64_t x = 0; x < n; ++x) c[x] = v[x];                                                     \
                for (int64_t j = 1; j < K; ++j)                                                                  \
                    for (int64_t x = 0; x < n; ++x) c[x] += v[x + j];                                            \
        }                                                                                                        \
    }

DEFINE_ROW_STATE(float, f32)
DEFINE_ROW_STATE(uint16_t, u16)
DEFINE_STEPS(float, f32)
DEFINE_STEPS(uint16_t, u16)

/* v += |l - r| over n columns. */
__attribute__((noinline)) static void add_row_f32(int64_t n, const float *restrict l, const float *restrict r,
                                                  float *restrict v) {
    for (int64_t x = 0; x < n; ++x) v[x] += fabsf(l[x] - r[x]);
}

/* v += |l_in - r_in| - |l_out - r_out|: the window slides down one row. */
__attribute__((noinline)) static void slide_row_f32(int64_t n, const float *restrict l_in,
                                                    const float *restrict r_in, const float *restrict l_out,
                                                    const float *restrict r_out, float *restrict v) {
    for (int64_t x = 0; x < n; ++x) v[x] += fabsf(l_in[x] - r_in[x]) - fabsf(l_out[x] - r_out[x]);
}

/* The same on 16-bit samples in [-255, 255] (differences fit int16; sums wrap modulo 2^16 but end in range). */
__attribute__((noinline)) static void add_row_u16(int64_t n, const int16_t *restrict l, const int16_t *restrict r,
                                                  uint16_t *restrict v) {
    for (int64_t x = 0; x < n; ++x) {
        int16_t d = (int16_t)(l[x] - r[x]);
        v[x] = (uint16_t)(v[x] + (uint16_t)(d < 0 ? -d : d));
    }
}

__attribute__((noinline)) static void slide_row_u16(int64_t n, const int16_t *restrict l_in,
                                                    const int16_t *restrict r_in, const int16_t *restrict l_out,
                                                    const int16_t *restrict r_out, uint16_t *restrict v) {
    for (int64_t x = 0; x < n; ++x) {
        int16_t a = (int16_t)(l_in[x] - r_in[x]), b = (int16_t)(l_out[x] - r_out[x]);
        v[x] = (uint16_t)(v[x] + (uint16_t)(a < 0 ? -a : a) - (uint16_t)(b < 0 ? -b : b));
    }
}

static inline float cost_to_float_f32(float c) { return c; }
static inline float cost_to_float_u16(uint16_t c) { return c == U16_INF ? INFINITY : (float)c; }
static inline int cost_finite_f32(float c) { return isfinite(c); }
static inline int cost_finite_u16(uint16_t c) { return c != U16_INF; }

/* The band of output rows [y_begin, y_end) of pair b. ``left`` / ``right`` hold the crop rows from ``row0`` on
 * (row r at (r - row0) * stride), as float or as 16-bit samples. */
#define DEFINE_RUN_BAND(COST, SAMPLE, SUFFIX, INF)                                                                \
    static void run_band_##SUFFIX(Job *job, int64_t b, int64_t y_begin, int64_t y_end, const SAMPLE *left,      \
                                  const SAMPLE *right, int64_t row0, COST *vsum, RowState_##SUFFIX *st) {       \
        const int64_t HL = job->HL, WL = job->WL, D = job->D, K = job->K;                                        \
        const int64_t H = HL - K + 1, W = WL - K + 1, WR = WL + D - 1;                                           \
        const int64_t first = job->left_first, WC = job->left_width;                                             \
        const int64_t count = job->counts[b];                                                                    \
        /* Disparity index d is searched at crop column x when lo(d) <= x < hi(d). */                           \
        const int64_t shift = job->min_d[b] - job->x0[b];                                                        \
        COST *restrict c = st->cost;                                                                             \
        COST *restrict best_cost = st->best_cost, *restrict best = st->best, *restrict before = st->before;     \
        COST *restrict after = st->after, *restrict rival = st->rival, *restrict prefix1 = st->prefix1;         \
        COST *restrict prefix2 = st->prefix2, *restrict previous = st->previous;                                 \
        COST *restrict right_cost = st->right_cost, *restrict right_best = st->right_best;                      \
        for (int64_t y = y_begin; y < y_end; ++y) {                                                              \
            /* Column sums of |L - R| over the window's K rows, for every d: the band's first row sums them,    \
             * each later row adds the row entering the window and subtracts the one leaving it (exact). */      \
            for (int64_t d = 0; d < D; ++d) {                                                                    \
                COST *v = vsum + d * WL;                                                                         \
                if (y == y_begin) {                                                                              \
                    for (int64_t x = 0; x < WL; ++x) v[x] = 0;                                                   \
                    for (int64_t r = y; r < y + K; ++r)                                                          \
                        add_row_##SUFFIX(WL, left + (r - row0) * WL, right + (r - row0) * WR + (D - 1 - d), v); \
                } else {                                                                                         \
                    int64_t r = y + K - 1;                                                                       \
                    slide_row_##SUFFIX(WL, left + (r - row0) * WL, right + (r - row0) * WR + (D - 1 - d),       \
                                       left + (y - 1 - row0) * WL, right + (y - 1 - row0) * WR + (D - 1 - d),  \
                                       v);                                                                       \
                }                                                                                                \
            }                                                                                                    \
            for (int64_t d = 0; d < D; ++d) {                                                                    \
                box_row_##SUFFIX(W, K, vsum + d * WL, c);                                                        \
                int64_t lo = shift + d, hi = job->image_w[b] + shift + d;                                        \
                if (d >= count) lo = W;                                                                          \
                if (lo < 0) lo = 0;                                                                              \
                if (lo > W) lo = W;                                                                              \
                if (hi > W) hi = W;                                                                              \
                if (hi < lo) hi = lo;                                                                            \
                for (int64_t x = 0; x < lo; ++x) c[x] = INF;                                                     \
                for (int64_t x = hi; x < W; ++x) c[x] = INF;                                                     \
                const COST fd = (COST)d;                                                                         \
                if (d == 0) {                                                                                    \
                    for (int64_t x = 0; x < WC; ++x) {                                                           \
                        const COST cx = c[first + x];                                                            \
                        best_cost[x] = cx;                                                                       \
                        best[x] = 0;                                                                             \
                        before[x] = cx; /* the clamped neighbour of index 0 is index 0 */                        \
                        after[x] = cx;  /* replaced at d = 1 when the range has one */                           \
                        rival[x] = INF;                                                                          \
                        prefix2[x] = INF;                                                                        \
                        prefix1[x] = cx;                                                                         \
                        previous[x] = cx;                                                                        \
                    }                                                                                            \
                    for (int64_t x = 0; x < W; ++x) {                                                            \
                        right_cost[x] = c[x];                                                                    \
                        right_best[x] = 0;                                                                       \
                    }                                                                                            \
                    continue;                                                                                    \
                }                                                                                                \
                step_left_##SUFFIX(WC, fd, c + first, best_cost, best, rival, after, before, prefix1, prefix2,   \
                                   previous);                                                                    \
                step_right_##SUFFIX(W - d, fd, c + d, right_cost, right_best);                                   \
            }                                                                                                    \
            int64_t offset = (b * H + y) * WC;                                                                   \
            float *out_cost = job->best_cost + offset, *out_before = job->before + offset;                       \
            float *out_after = job->after + offset, *out_rival = job->rival + offset;                            \
            int64_t *out_best = job->best + offset, *out_right = job->right_best + (b * H + y) * W;             \
            for (int64_t x = 0; x < WC; ++x) {                                                                   \
                out_cost[x] = cost_to_float_##SUFFIX(best_cost[x]);                                              \
                out_best[x] = (int64_t)best[x];                                                                  \
                out_before[x] = cost_to_float_##SUFFIX(before[x]);                                               \
                out_after[x] = cost_to_float_##SUFFIX(after[x]);                                                 \
                out_rival[x] = cost_to_float_##SUFFIX(rival[x]);                                                 \
            }                                                                                                    \
            for (int64_t x = 0; x < W; ++x)                                                                      \
                out_right[x] = cost_finite_##SUFFIX(right_cost[x]) ? (int64_t)right_best[x] : -1;               \
        }                                                                                                        \
    }

DEFINE_RUN_BAND(float, float, f32, INFINITY)
DEFINE_RUN_BAND(uint16_t, int16_t, u16, U16_INF)

/* Per-thread buffers, sized for the 16-bit or the float path (the larger of the two layouts). */
typedef struct {
    void *vsum, *rows;
    int16_t *left16, *right16;
} Buffers;

/* The band's crop rows [y0, y1 + K - 1) as 16-bit samples, when every window cost of the band fits below 65535
 * (K^2 * max|L - R| over those rows); returns 0 (the float path runs) otherwise. */
static int to_samples16(const Job *job, int64_t b, int64_t y0, int64_t y1, int16_t *left16, int16_t *right16) {
    const int64_t WL = job->WL, WR = job->WL + job->D - 1, K = job->K, rows = y1 - y0 + K - 1;
    const float *left = job->left + (b * job->HL + y0) * WL, *right = job->right + (b * job->HL + y0) * WR;
    float lmin = INFINITY, lmax = -INFINITY, rmin = INFINITY, rmax = -INFINITY;
    for (int64_t i = 0; i < rows * WL; ++i) {
        lmin = fminf(lmin, left[i]);
        lmax = fmaxf(lmax, left[i]);
    }
    for (int64_t i = 0; i < rows * WR; ++i) {
        rmin = fminf(rmin, right[i]);
        rmax = fmaxf(rmax, right[i]);
    }
    if (!(lmin >= -255.0f && lmax <= 255.0f && rmin >= -255.0f && rmax <= 255.0f)) return 0;
    const float spread = fmaxf(lmax - rmin, rmax - lmin);
    if ((double)K * (double)K * (double)spread >= 65535.0) return 0;
    for (int64_t i = 0; i < rows * WL; ++i) left16[i] = (int16_t)left[i];
    for (int64_t i = 0; i < rows * WR; ++i) right16[i] = (int16_t)right[i];
    return 1;
}

static void run_task(Job *job, int64_t b, int64_t y0, int64_t y1, Buffers *buffers) {
    const int64_t W = job->WL - job->K + 1;
    if (to_samples16(job, b, y0, y1, buffers->left16, buffers->right16)) {
        RowState_u16 st = row_state_u16(buffers->rows, W);
        run_band_u16(job, b, y0, y1, buffers->left16, buffers->right16, y0, buffers->vsum, &st);
    } else {
        RowState_f32 st = row_state_f32(buffers->rows, W);
        const int64_t WR = job->WL + job->D - 1;
        run_band_f32(job, b, y0, y1, job->left + b * job->HL * job->WL, job->right + b * job->HL * WR, 0,
                     buffers->vsum, &st);
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
        const int64_t band_input_rows = job.band_rows + K - 1;
        Buffers buffers = {malloc(sizeof(float) * (size_t)(D * WL)), malloc(sizeof(float) * (size_t)(11 * W)),
                           malloc(sizeof(int16_t) * (size_t)(band_input_rows * WL)),
                           malloc(sizeof(int16_t) * (size_t)(band_input_rows * (WL + D - 1)))};
        const int ok = buffers.vsum && buffers.rows && buffers.left16 && buffers.right16;
        if (!ok) {
#pragma omp atomic write
            failed = 1;
        }
#pragma omp for schedule(dynamic, 1)
        for (int64_t task = 0; task < tasks; ++task) {
            if (!ok) continue;
            int64_t b = task / job.bands, band = task % job.bands;
            int64_t y0 = band * job.band_rows, y1 = y0 + job.band_rows;
            if (y1 > H) y1 = H;
            if (y0 < y1) run_task(&job, b, y0, y1, &buffers);
        }
        free(buffers.vsum);
        free(buffers.rows);
        free(buffers.left16);
        free(buffers.right16);
    }
    return failed ? -1 : 0;
}
