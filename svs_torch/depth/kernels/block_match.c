/* Fused dense SAD block matching for svs_torch.depth.block_matching (the hard, non-differentiable path): from the
 * images (pre-filtered here a crop row at a time, or given as pre-filtered levels) to the disparity map, each pair
 * over its own box and its own disparity range.
 *
 * The eager torch path (svs_torch/depth/: cost_volume._cost_volume + winner._winner + winner._right_winner +
 * block_matching._match_box) makes about 40 passes over a B x D x h x w cost volume and its verdicts, with one box
 * size and one disparity count for the whole batch (the largest); here each pair is cropped at its own box
 * (replicate border) and each output row's costs for every disparity are made and consumed while they sit in cache:
 *   A(y, x, d) = |L(y, x) - R(y, x + D - 1 - d)|                       (the right crop is D - 1 columns wider)
 *   V(y, x, d) = A(y) + ... + A(y + K - 1)                              (running: + the entering row - the leaving)
 *   C(y, x, d) = V(x) + ... + V(x + K - 1)
 *   C = +inf where the right pixel x0 + x - (min_d + d) leaves [0, image_w)
 * then per pixel: the first minimum over d (best, best_cost), the costs at best -+ 1 (clamped to the range),
 * the least cost farther than 1 from best (rival, +inf if none), and the right view's winner
 * C_R(j, k) = C(j + k, k) (first minimum over k; -1 where it is +inf), over D - 1 extra columns on each side of
 * the box. The column sums of a row stay in L2; the float search streams over d (one row of costs per
 * disparity and a dozen running values per column in L1), the 16-bit one makes the row's D rows of costs and
 * then takes 32 columns at a time through every d with the running values in vector registers (on 64 real
 * 320x240 pairs at the command line's B = 8, one thread: the dense stage 5.8 -> 4.8 ms a pair against
 * streaming, which loaded and stored every running value at each d). Each finished row then gets the torch
 * path's rejections (range edge, uniqueness, left-right check, texture from its own window sums of |x-Sobel|)
 * and equiangular sub-pixel fit, in the same float32 operations, and goes straight into the full-frame map.
 *
 * A pair's result never depends on its batch (the torch path discards what lies outside a pair's own box and
 * range), so cropping each pair at its own size changes no value, only the work: no pair pays for the batch's
 * largest box or range.
 *
 * The inputs are whole numbers (StereoBM's 8-bit levels, svs_torch.depth.cost_volume.quantize_levels), so every sum
 * is an exact float32 integer (K^2 * 510 < 2^24) in any order, and the results equal the torch path's bit for bit;
 * minima and selects do no arithmetic, so streaming over d changes no value either. Where a band's costs fit
 * 16 bits (K^2 * max|L - R| < 65535: StereoBM's x-Sobel levels at any usual K) the same search runs on int16
 * samples and uint16 costs, twice the lanes per instruction (8 real pairs' crops at K = 9, one thread: 70 -> 42
 * ms), with the same whole numbers and so the same results.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp (no -ffast-math: it could treat the
 * +inf costs as impossible). Loaded through ctypes by svs_torch/depth/kernels/__init__.py, which falls back to the
 * torch path without a compiler.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "common.h"

/* Two cost types (COST): float, or uint16_t with 65535 standing for +inf (StereoBM's levels have |L - R| <= 62,
 * so any K up to 32 fits). The column sums and the box sums are written once for both (macros); the winner
 * search twice: streaming over d with its state in rows for float (step_left_f32, step_right_f32), blocked with
 * its state in vector registers for uint16_t (left_winner_lanes, right_winner_lanes). Indices are kept in the
 * cost type (exact: D < 65535), so that every select is as wide as the costs and vectorises. */
#define U16_INF ((uint16_t)0xFFFF)

#define BOX_CASE(COST, KK)                                                                                        \
    case KK:                                                                                                      \
        for (int64_t x = 0; x < n; ++x) {                                                                         \
            COST sum = v[x];                                                                                      \
            for (int64_t j = 1; j < KK; ++j) sum += v[x + j];                                                     \
            c[x] = sum;                                                                                           \
        }                                                                                                         \
        return;

/* Columns of a wide window's sums made at a time through sums of three (BOX3_CASE), which sit in a stack row. */
#define BOX_CHUNK 256

/* As BOX_CASE for a wide window (KK >= 9), through sums of three: t[x] = v[x] + v[x + 1] + v[x + 2], then
 * c[x] = t[x] + t[x + 3] + ... + the KK mod 3 values left, 4 adds a column for K = 9 where BOX_CASE takes 8. The
 * block matching of 8 real 320x240 pairs, one thread, 80 disparities: K = 9 and 11 2-6 % faster, K = 13 47.9 ->
 * 40.3 ms, K = 19 and 21 94 and 84 -> 43 and 45 ms (there the unrolled sum had not vectorised); no faster at K = 7.
 * Whole numbers, so the same sums in any order. */
#define BOX3_CASE(COST, KK)                                                                                       \
    case KK:                                                                                                      \
        for (int64_t x0 = 0; x0 < n; x0 += BOX_CHUNK) {                                                           \
            const int64_t m = n - x0 < BOX_CHUNK ? n - x0 : BOX_CHUNK;                                           \
            const COST *restrict w = v + x0;                                                                     \
            for (int64_t x = 0; x < m + 3 * (KK / 3 - 1); ++x) t[x] = w[x] + w[x + 1] + w[x + 2];               \
            for (int64_t x = 0; x < m; ++x) {                                                                    \
                COST sum = t[x];                                                                                 \
                for (int64_t j = 1; j < KK / 3; ++j) sum += t[x + 3 * j];                                        \
                for (int64_t j = 3 * (KK / 3); j < KK; ++j) sum += w[x + j];                                     \
                c[x0 + x] = sum;                                                                                 \
            }                                                                                                    \
        }                                                                                                        \
        return;

/* c[x] = v[x] + v[x + 1] + ... + v[x + K - 1], n columns. For the usual window sizes the sum is kept in a register
 * (a constant K: the j loops unroll and x vectorises); else K passes over c. */
#define DEFINE_BOX_ROW(COST, SUFFIX)                                                                              \
    __attribute__((noinline)) static void box_row_##SUFFIX(int64_t n, int64_t K, const COST *restrict v,         \
                                                           COST *restrict c) {                                   \
        COST t[BOX_CHUNK + 3 * (21 / 3 - 1)];                                                                    \
        switch (K) {                                                                                             \
            BOX_CASE(COST, 3) BOX_CASE(COST, 5) BOX_CASE(COST, 7) BOX3_CASE(COST, 9) BOX3_CASE(COST, 11)        \
            BOX3_CASE(COST, 13) BOX3_CASE(COST, 15) BOX3_CASE(COST, 17) BOX3_CASE(COST, 19)                     \
            BOX3_CASE(COST, 21)                                                                                  \
            default:                                                                                             \
                for (int64_t x = 0; x < n; ++x) c[x] = v[x];                                                     \
                for (int64_t j = 1; j < K; ++j)                                                                  \
                    for (int64_t x = 0; x < n; ++x) c[x] += v[x + j];                                            \
        }                                                                                                        \
    }

DEFINE_BOX_ROW(float, f32)
DEFINE_BOX_ROW(uint16_t, u16)

/* The float search's state, one entry per output column: 11 rows of W laid out one after the other. */
typedef struct {
    float *cost, *best_cost, *best, *before, *after, *rival, *prefix1, *prefix2, *previous, *right_cost,
        *right_best;
} RowState;

static RowState row_state(float *rows, int64_t W) {
    RowState st = {rows, rows + W, rows + 2 * W, rows + 3 * W, rows + 4 * W, rows + 5 * W,
                   rows + 6 * W, rows + 7 * W, rows + 8 * W, rows + 9 * W, rows + 10 * W};
    return st;
}

/* One disparity of the streaming winner search (kept out of line, with restrict arguments, so that gcc
 * vectorises it: inlined into run_row_f32 it does not). The winner so far (first index on ties), the costs beside
 * it, and the rival: the least cost more than 1 from it; a new winner at d inherits as rival the least cost of
 * indices <= d - 2. Branch-free, every load unconditional. */
__attribute__((noinline)) static void step_left_f32(int64_t W, float fd, const float *restrict c,
                                                    float *restrict best_cost, float *restrict best,
                                                    float *restrict rival, float *restrict after,
                                                    float *restrict before, float *restrict prefix1,
                                                    float *restrict prefix2, float *restrict previous) {
    const float next_to = fd - 1; /* i1 + 1 == fd  <=>  i1 == fd - 1 */
    for (int64_t x = 0; x < W; ++x) {
        float cx = c[x], b1 = best_cost[x], i1 = best[x], r = rival[x], a = after[x], p1 = prefix1[x];
        float p2 = prefix2[x], bf = before[x], pv = previous[x];
        int better = cx < b1;
        int take = (i1 < next_to) & (cx < r);
        float kept_rival = take ? cx : r;
        float kept_after = (i1 == next_to) ? cx : a;
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
__attribute__((noinline)) static void step_right_f32(int64_t n, float fd, const float *restrict shifted,
                                                     float *restrict right_cost, float *restrict right_best) {
    for (int64_t j = 0; j < n; ++j) {
        float s = shifted[j], rc = right_cost[j];
        int better = s < rc;
        right_cost[j] = better ? s : rc;
        right_best[j] = better ? fd : right_best[j];
    }
}

/* The 16-bit search, blocked: GROUPS x LANES columns at a time go through every disparity with the winner's
 * state in vector registers (GCC / Clang vector extensions), where the streaming search loads and stores every
 * state row again at each disparity. The row's costs, every disparity's, are made first into a D x ``stride``
 * block, which both views' winners then read a vector at a time. The same selects in the same order as
 * step_left_f32 / step_right_f32, so the same winners.
 *
 * A vector is one register (VECTOR_BYTES, common.h). GROUPS vectors of columns go through the disparities side by
 * side: independent chains of selects, so that each hides the latency of the other's comparisons (with AVX-512,
 * 64 real 320x240 pairs at the command line's B = 8, one thread: the block matching 3.7 -> 2.7 ms a pair with the
 * needed columns above; with AVX2, a 320x240 frame's 48 disparities 8.7 -> 6.4 ms); the eight state vectors of
 * two groups fill the 16 registers of AVX2 or SSE2. */
#define LANES (VECTOR_BYTES / 2)
#define GROUPS 2
typedef uint16_t lanes_u16 __attribute__((vector_size(2 * LANES)));
typedef int16_t lanes_mask __attribute__((vector_size(2 * LANES))); /* a comparison's lanes: -1 or 0 */

static inline lanes_u16 load_lanes(const uint16_t *source) {
    lanes_u16 v;
    __builtin_memcpy(&v, source, sizeof v); /* unaligned */
    return v;
}

static inline lanes_u16 pick(lanes_mask where, lanes_u16 a, lanes_u16 b) {
    return (lanes_u16)(((lanes_mask)a & where) | ((lanes_mask)b & ~where));
}

/* The left view's winner statistics of GROUPS x LANES output columns whose costs at disparity d sit at costs +
 * d * stride: best_cost, best, before, after, rival into ``out`` (5 x GROUPS x LANES), as step_left_f32 makes
 * them. */
static void left_winner_lanes(const uint16_t *costs, int64_t stride, int64_t D, uint16_t *out) {
    const lanes_u16 inf = (lanes_u16){0} + U16_INF;
    lanes_u16 best_cost[GROUPS], best[GROUPS], before[GROUPS], after[GROUPS], rival[GROUPS], prefix1[GROUPS];
    lanes_u16 prefix2[GROUPS], previous[GROUPS];
    for (int g = 0; g < GROUPS; ++g) {
        const lanes_u16 c = load_lanes(costs + g * LANES);
        /* d = 0: the clamped neighbours of index 0 are index 0 (after is replaced at d = 1 when the range has
         * one) */
        best_cost[g] = c, best[g] = (lanes_u16){0}, before[g] = c, after[g] = c, rival[g] = inf, prefix1[g] = c;
        prefix2[g] = inf, previous[g] = c;
    }
    for (int64_t d = 1; d < D; ++d) {
        const uint16_t next_to = (uint16_t)(d - 1);
        for (int g = 0; g < GROUPS; ++g) {
            const lanes_u16 c = load_lanes(costs + d * stride + g * LANES);
            const lanes_mask better = c < best_cost[g];
            const lanes_u16 kept_rival = pick((best[g] < next_to) & (c < rival[g]), c, rival[g]);
            const lanes_u16 kept_after = pick(best[g] == next_to, c, after[g]);
            rival[g] = pick(better, prefix2[g], kept_rival);
            after[g] = pick(better, c, kept_after);
            before[g] = pick(better, previous[g], before[g]);
            best[g] = pick(better, (lanes_u16){0} + (uint16_t)d, best[g]);
            best_cost[g] = pick(better, c, best_cost[g]);
            prefix2[g] = prefix1[g];
            prefix1[g] = pick(c < prefix1[g], c, prefix1[g]);
            previous[g] = c;
        }
    }
    for (int g = 0; g < GROUPS; ++g) {
        uint16_t *o = out + g * LANES;
        __builtin_memcpy(o, &best_cost[g], sizeof best_cost[g]);
        __builtin_memcpy(o + GROUPS * LANES, &best[g], sizeof best[g]);
        __builtin_memcpy(o + 2 * GROUPS * LANES, &before[g], sizeof before[g]);
        __builtin_memcpy(o + 3 * GROUPS * LANES, &after[g], sizeof after[g]);
        __builtin_memcpy(o + 4 * GROUPS * LANES, &rival[g], sizeof rival[g]);
    }
}

/* The right view's winner of LANES columns j: the first least C(j + d, d) over d (at costs + d * stride + d),
 * its cost into out[0, LANES) and its index into out[LANES, 2 LANES), as step_right_f32. */
static void right_winner_lanes(const uint16_t *costs, int64_t stride, int64_t D, uint16_t *out) {
    lanes_u16 right_cost[GROUPS], right_best[GROUPS];
    for (int g = 0; g < GROUPS; ++g) right_cost[g] = load_lanes(costs + g * LANES), right_best[g] = (lanes_u16){0};
    for (int64_t d = 1; d < D; ++d) {
        for (int g = 0; g < GROUPS; ++g) {
            const lanes_u16 shifted = load_lanes(costs + d * stride + d + g * LANES);
            const lanes_mask better = shifted < right_cost[g];
            right_cost[g] = pick(better, shifted, right_cost[g]);
            right_best[g] = pick(better, (lanes_u16){0} + (uint16_t)d, right_best[g]);
        }
    }
    for (int g = 0; g < GROUPS; ++g) {
        __builtin_memcpy(out + g * LANES, &right_cost[g], sizeof right_cost[g]);
        __builtin_memcpy(out + (GROUPS + g) * LANES, &right_best[g], sizeof right_best[g]);
    }
}

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


/* One pair's geometry. Its box holds the output pixels [x0, x0 + width) x [y0, y0 + height); the search runs
 * over ``extra`` more columns on each side (the "wide" box, WW columns) that serve only the right view's
 * winner. The left crop (WL = WW + K - 1 columns, K - 1 more rows than the output) starts K / 2 pixels up and
 * left of the wide box; the right crop is D - 1 columns wider and starts min_d + D - 1 columns further left,
 * so that its columns [D - 1 - d, D - 1 - d + WL) face the left crop at disparity min_d + d. */
typedef struct {
    int64_t x0, y0, width, height, min_d, D, extra, WW, WL, WR, image_h, image_w;
    int lower_is_limit;
} Pair;

/* One output row's winner statistics: the left view's for the box columns, the right view's winner for the
 * columns the left-right check looks up (right_columns; -1 where all its candidates are +inf). */
typedef struct {
    float *best_cost, *before, *after, *rival;
    int64_t *best, *right_best;
} RowOut;

/* The wide-box columns whose cost at disparity index d some winner reads: [needed_from(d), + needed_count).
 * The left view's winner reads the box, columns [extra, extra + width); the right view's winner of column j
 * reads C(j + d, d), and the left-right check looks it up only at j = extra + x - best, j in [0, width + D - 1)
 * (extra = D - 1). So disparity d needs columns [d, d + width + D - 1), not the whole wide box (width + 2D - 2):
 * on 64 real 320x240 pairs that is a sixth less of every pass. Without the check (extra = 0) the box alone. */
static inline int64_t needed_from(const Pair *p, int64_t d) { return p->extra ? d : 0; }
static inline int64_t needed_count(const Pair *p) { return p->extra ? p->width + p->extra : p->WW; }

/* The columns of the right view's winner that the left-right check looks up: none without the check. */
static inline int64_t right_columns(const Pair *p) { return p->extra ? p->width + p->extra : 0; }

/* Output row y of a band whose crop rows (K - 1 more than its output rows) sit from ``left`` / ``right`` on,
 * row y's window starting at crop row y: the column sums of disparity index d (row d of D rows of WL), over the
 * columns the needed costs read. ``fresh``: the band's first row, whose column sums are made from scratch; each
 * later row slides them down by one (exact whole numbers). */
#define DEFINE_COLUMN_SUMS(COST, SAMPLE, SUFFIX)                                                                  \
    static void column_sums_##SUFFIX(const Pair *p, int64_t K, int64_t y, int fresh, const SAMPLE *left,        \
                                     const SAMPLE *right, int64_t d, COST *vsum) {                               \
        const int64_t D = p->D, WL = p->WL, WR = p->WR, n = needed_count(p) + K - 1;                             \
        const int64_t c0 = needed_from(p, d), o = D - 1 - d + c0;                                                \
        COST *v = vsum + d * WL + c0;                                                                            \
        if (fresh) {                                                                                             \
            for (int64_t x = 0; x < n; ++x) v[x] = 0;                                                            \
            for (int64_t r = y; r < y + K; ++r) add_row_##SUFFIX(n, left + r * WL + c0, right + r * WR + o, v);  \
        } else {                                                                                                 \
            int64_t r = y + K - 1;                                                                               \
            slide_row_##SUFFIX(n, left + r * WL + c0, right + r * WR + o, left + (y - 1) * WL + c0,             \
                               right + (y - 1) * WR + o, v);                                                     \
        }                                                                                                        \
    }

/* The costs of disparity index d over its needed columns of the wide box (needed_from, needed_count) from
 * its column sums: the window sums, +inf where the right pixel x0 - extra + x - min_d - d leaves [0, image_w)
 * (searched only where lo(d) <= x < hi(d)). Other columns of ``c`` are left as they were: no winner reads
 * them. */
#define DEFINE_ROW_COSTS(COST, SUFFIX, INF)                                                                       \
    static void row_costs_##SUFFIX(const Pair *p, int64_t K, int64_t d, const COST *vsum, COST *c) {            \
        const int64_t from = needed_from(p, d), to = from + needed_count(p);                                     \
        const int64_t shift = p->min_d - (p->x0 - p->extra);                                                     \
        box_row_##SUFFIX(to - from, K, vsum + d * p->WL + from, c + from);                                       \
        int64_t lo = shift + d, hi = p->image_w + shift + d;                                                     \
        if (lo < from) lo = from;                                                                                \
        if (lo > to) lo = to;                                                                                    \
        if (hi > to) hi = to;                                                                                    \
        if (hi < lo) hi = lo;                                                                                    \
        for (int64_t x = from; x < lo; ++x) c[x] = INF;                                                          \
        for (int64_t x = hi; x < to; ++x) c[x] = INF;                                                            \
    }

DEFINE_COLUMN_SUMS(float, float, f32)
DEFINE_COLUMN_SUMS(uint16_t, int16_t, u16)
DEFINE_ROW_COSTS(float, f32, INFINITY)
DEFINE_ROW_COSTS(uint16_t, u16, U16_INF)

/* Output row y in float costs: the column sums, then the streaming search over d, one cost row at a time. */
static void run_row_f32(const Pair *p, int64_t K, int64_t y, int fresh, const float *left, const float *right,
                        float *vsum, RowState *st, RowOut *out) {
    const int64_t D = p->D, first = p->extra, WC = p->width, R = right_columns(p);
    for (int64_t d = 0; d < D; ++d) column_sums_f32(p, K, y, fresh, left, right, d, vsum);
    float *restrict c = st->cost;
    float *restrict best_cost = st->best_cost, *restrict best = st->best, *restrict before = st->before;
    float *restrict after = st->after, *restrict rival = st->rival, *restrict prefix1 = st->prefix1;
    float *restrict prefix2 = st->prefix2, *restrict previous = st->previous;
    float *restrict right_cost = st->right_cost, *restrict right_best = st->right_best;
    for (int64_t d = 0; d < D; ++d) {
        row_costs_f32(p, K, d, vsum, c);
        if (d == 0) {
            for (int64_t x = 0; x < WC; ++x) {
                const float cx = c[first + x];
                best_cost[x] = cx;
                best[x] = 0;
                before[x] = cx; /* the clamped neighbour of index 0 is index 0 */
                after[x] = cx;  /* replaced at d = 1 when the range has one */
                rival[x] = INFINITY;
                prefix2[x] = INFINITY;
                prefix1[x] = cx;
                previous[x] = cx;
            }
            for (int64_t x = 0; x < R; ++x) {
                right_cost[x] = c[x];
                right_best[x] = 0;
            }
            continue;
        }
        step_left_f32(WC, (float)d, c + first, best_cost, best, rival, after, before, prefix1, prefix2, previous);
        step_right_f32(R, (float)d, c + d, right_cost, right_best);
    }
    for (int64_t x = 0; x < WC; ++x) {
        out->best_cost[x] = best_cost[x];
        out->best[x] = (int64_t)best[x];
        out->before[x] = before[x];
        out->after[x] = after[x];
        out->rival[x] = rival[x];
    }
    for (int64_t x = 0; x < R; ++x) out->right_best[x] = isfinite(right_cost[x]) ? (int64_t)right_best[x] : -1;
}

/* The stride of run_row_u16's cost block: the wide box, and past it +inf columns (cost_block_edges) that the
 * right view's winner reads at d columns further on and the last vectors read up to LANES - 1 further on. */
static int64_t cost_stride(const Pair *p) { return p->WW + p->D + GROUPS * LANES; }

static void cost_block_edges(const Pair *p, uint16_t *costs) {
    const int64_t stride = cost_stride(p);
    for (int64_t d = 0; d < p->D; ++d)
        for (int64_t x = p->WW; x < stride; ++x) costs[d * stride + x] = U16_INF;
}

static inline float cost_to_float(uint16_t c) { return c == U16_INF ? INFINITY : (float)c; }

/* Output row y in 16-bit costs: the column sums, every disparity's costs into ``costs`` (D rows of
 * cost_stride, edges set by cost_block_edges), then the blocked winners a vector of columns at a time. */
static void run_row_u16(const Pair *p, int64_t K, int64_t y, int fresh, const int16_t *left, const int16_t *right,
                        uint16_t *vsum, uint16_t *costs, RowOut *out) {
    const int64_t D = p->D, R = right_columns(p), first = p->extra, WC = p->width, stride = cost_stride(p);
    for (int64_t d = 0; d < D; ++d) { /* each row of column sums boxed while it is in L1 */
        column_sums_u16(p, K, y, fresh, left, right, d, vsum);
        row_costs_u16(p, K, d, vsum, costs + d * stride);
    }
    enum { SPAN = GROUPS * LANES };
    uint16_t lanes[5 * SPAN];
    for (int64_t x = 0; x < WC; x += SPAN) {
        left_winner_lanes(costs + first + x, stride, D, lanes);
        const int64_t n = WC - x < SPAN ? WC - x : SPAN;
        for (int64_t i = 0; i < n; ++i) {
            out->best_cost[x + i] = cost_to_float(lanes[i]);
            out->best[x + i] = lanes[SPAN + i];
            out->before[x + i] = cost_to_float(lanes[2 * SPAN + i]);
            out->after[x + i] = cost_to_float(lanes[3 * SPAN + i]);
            out->rival[x + i] = cost_to_float(lanes[4 * SPAN + i]);
        }
    }
    for (int64_t j = 0; j < R; j += SPAN) {
        right_winner_lanes(costs + j, stride, D, lanes);
        const int64_t n = R - j < SPAN ? R - j : SPAN;
        for (int64_t i = 0; i < n; ++i) out->right_best[j + i] = lanes[i] != U16_INF ? lanes[SPAN + i] : -1;
    }
}

static inline int64_t clamp_index(int64_t i, int64_t n) { return i < 0 ? 0 : (i >= n ? n - 1 : i); }

/* The pre-filter of svs_torch.depth.block_matching._match_compiled for image row y (all W columns), so that the
 * caller need not make whole pre-filtered images: the levels that the block matching compares (SOURCE_RAW:
 * round(255 x); SOURCE_XSOBEL: round(255 clip(Sobel_x, -cap, cap)), svs_torch.depth.cost_volume.quantize_levels of
 * prefilter_xsobel) and, when ``texture`` is given, |clip(Sobel_x, -cap, cap)| (the texture image). Replicate border
 * as the torch path's padding; the Sobel taps in its order, (((((t02 - t00) - 2 t10) + 2 t12) - t20) + t22), each
 * step rounded to float32 (2 t is exact, so the fused multiply-add of torch's alpha gives the same), then its clamp,
 * then the product by 255 rounded to float32 and rounded half to even (torch.round): the same values bit for bit. */
enum { SOURCE_LEVELS = 0, SOURCE_RAW = 1, SOURCE_XSOBEL = 2 };

/* The clipped x-Sobel of one column from its left (a) and right (b) taps, and what prefilter_row keeps of it. */
static inline void sobel_at(const float *above, const float *row, const float *below, int64_t a, int64_t b,
                            int source, float cap, float *levels, float *texture, int64_t x) {
    float s = above[b] - above[a];
    s = s - 2.0f * row[a];
    s = s + 2.0f * row[b];
    s = s - below[a];
    s = s + below[b];
    s = s < -cap ? -cap : (s > cap ? cap : s);
    if (source == SOURCE_XSOBEL) levels[x] = nearbyintf(s * 255.0f);
    if (texture) texture[x] = fabsf(s);
}

/* Columns [x_begin, x_end) with their taps clamped to the row (replicate border). */
static void sobel_columns(const float *above, const float *row, const float *below, int64_t W, int64_t x_begin,
                          int64_t x_end, int source, float cap, float *levels, float *texture) {
    for (int64_t x = x_begin; x < x_end; ++x)
        sobel_at(above, row, below, x > 0 ? x - 1 : 0, x < W - 1 ? x + 1 : W - 1, source, cap, levels, texture, x);
}

/* n columns whose taps are all inside the row, from column 1 on (the pointers are shifted to it). */
__attribute__((noinline)) static void sobel_columns_inner(const float *restrict above, const float *restrict row,
                                                          const float *restrict below, int64_t n, int source,
                                                          float cap, float *restrict levels,
                                                          float *restrict texture) {
    for (int64_t x = 0; x < n; ++x) sobel_at(above + 1, row + 1, below + 1, x - 1, x + 1, source, cap, levels,
                                             texture, x);
}

static void prefilter_row(const float *image, int64_t H, int64_t W, int64_t y, int source, float cap,
                          float *restrict levels, float *restrict texture) {
    const float *above = image + clamp_index(y - 1, H) * W, *row = image + y * W;
    const float *below = image + clamp_index(y + 1, H) * W;
    if (source == SOURCE_RAW)
        for (int64_t x = 0; x < W; ++x) levels[x] = nearbyintf(row[x] * 255.0f);
    if (source != SOURCE_XSOBEL && !texture) return;
    /* The two border columns clamp their taps; the others read straight neighbours, so that the loop vectorises
     * with plain loads (clamped indices made gcc gather every tap). */
    sobel_columns(above, row, below, W, 0, W < 2 ? W : 1, source, cap, levels, texture);
    if (W > 2) sobel_columns_inner(above, row, below, W - 2, source, cap, levels + 1, texture ? texture + 1 : NULL);
    if (W > 1) sobel_columns(above, row, below, W, W - 1, W, source, cap, levels, texture);
}

/* cols values of ``row`` (W long) from column col0 on, clamped to the row (replicate border). */
static void crop_row(const float *row, int64_t W, int64_t col0, int64_t cols, float *out) {
    int64_t c = 0;
    for (; c < cols && col0 + c < 0; ++c) out[c] = row[0];
    for (; c < cols && col0 + c < W; ++c) out[c] = row[col0 + c];
    for (; c < cols; ++c) out[c] = row[W - 1];
}

/* The crop rows of output rows [y_begin, y_end) (K - 1 more), clamped to the image (replicate border). */
static void gather_rows(const float *image, int64_t H, int64_t W, int64_t row0, int64_t col0, int64_t rows,
                        int64_t cols, float *out) {
    for (int64_t r = 0; r < rows; ++r) {
        crop_row(image + clamp_index(row0 + r, H) * W, W, col0, cols, out + r * cols);
    }
}

/* Whether all n values lie in [-255, 255] (NaN does not): compares OR-ed together, which gcc vectorises (a
 * float min / max reduction it does not, without -ffast-math). */
static int within_levels(const float *restrict values, int64_t n) {
    int outside = 0;
    /* Bitwise |, not ||: a short circuit is control flow, which keeps the loop scalar. */
    for (int64_t i = 0; i < n; ++i) outside |= !(values[i] >= -255.0f) | !(values[i] <= 255.0f);
    return !outside;
}

/* values -> int16 samples (whole numbers in [-255, 255]: exact), with their least and greatest, in integers
 * (vectorised). */
static void to_int16_span(const float *restrict values, int64_t n, int16_t *restrict samples, int *low,
                          int *high) {
    int16_t lo = 255, hi = -255;
    for (int64_t i = 0; i < n; ++i) {
        const int16_t v = (int16_t)values[i];
        samples[i] = v;
        lo = v < lo ? v : lo;
        hi = v > hi ? v : hi;
    }
    *low = lo;
    *high = hi;
}

/* The crops as 16-bit samples when every window cost fits below 65535 (K^2 * max|L - R| over them); returns 0
 * (the float path runs) otherwise. */
static int to_samples16(const float *left, int64_t left_size, const float *right, int64_t right_size, int64_t K,
                        int16_t *restrict left16, int16_t *restrict right16) {
    if (!within_levels(left, left_size) || !within_levels(right, right_size)) return 0;
    int lmin, lmax, rmin, rmax;
    to_int16_span(left, left_size, left16, &lmin, &lmax);
    to_int16_span(right, right_size, right16, &rmin, &rmax);
    const int spread = lmax - rmin > rmax - lmin ? lmax - rmin : rmax - lmin;
    return (double)K * (double)K * (double)spread < 65535.0;
}

/* The rejections and the sub-pixel fit of svs_torch.depth.block_matching._match_box, in its float32 operations and
 * order. */
typedef struct {
    float uniqueness_factor; /* 1 + uniqueness_ratio; 0: no uniqueness check */
    float lr_max_diff;       /* < 0: no left-right check */
    float texture_min;       /* the least window sum of |x-Sobel| (used when the texture image is given) */
    int whole_range_in_view;
} Rules;

static void finish_row(const Pair *p, const Rules *rules, int64_t y, const RowOut *o, const float *texture_sum,
                       int64_t x_begin, int64_t x_end, float *disparity, uint8_t *valid, float *best_cost) {
    const int64_t row = p->y0 + y, count = p->D;
    if (row < 0 || row >= p->image_h) return;
    for (int64_t x = x_begin; x < x_end; ++x) {
        const int64_t best = o->best[x], column = p->x0 + x;
        const float cost = o->best_cost[x], before = o->before[x], after = o->after[x];
        if (best_cost) best_cost[x] = cost; /* the winner's cost, kept or not (the pair's matching residual) */
        int ok = isfinite(cost) && best < count - 1 && (best > 0 || p->lower_is_limit);
        if (rules->uniqueness_factor > 0) ok = ok && o->rival[x] > rules->uniqueness_factor * cost;
        if (rules->lr_max_diff >= 0) {
            const int64_t seen = o->right_best[p->extra + x - best];
            ok = ok && seen >= 0 && (float)llabs(seen - best) <= rules->lr_max_diff;
        }
        if (texture_sum) ok = ok && texture_sum[x] >= rules->texture_min;
        ok = ok && column >= 0 && column < p->image_w;
        if (rules->whole_range_in_view) ok = ok && column >= p->min_d + count - 1;
        if (!ok) continue;
        float offset = 0.0f; /* the equiangular fit, where best has finite neighbours inside the range */
        if (best > 0 && best < count - 1 && isfinite(before) && isfinite(after)) {
            /* Selects, not fmaxf / fminf calls: every value here is finite (no NaN), so they agree. */
            const float rise = 2.0f * ((before > after ? before : after) - cost);
            if (rise > 0) {
                const float ratio = (before - after) / rise;
                offset = ratio < -0.5f ? -0.5f : (ratio > 0.5f ? 0.5f : ratio);
            }
        }
        disparity[x] = ((float)p->min_d + (float)best) + offset;
        valid[x] = 1;
    }
}

/* Window sums of the texture image for output row y of the band whose texture crop rows (the box's columns
 * and K - 1 more, from K / 2 left of the box) start at ``rows``: down the rows first, then along the columns,
 * each in order (the float sums of svs_torch.depth.cost_volume._box_sum), vectorised across columns. */
static void texture_row(const float *rows, int64_t width, int64_t K, int64_t y, float *restrict column_sums,
                        float *restrict sums) {
    const int64_t n = width + K - 1;
    const float *first = rows + y * n;
    for (int64_t c = 0; c < n; ++c) column_sums[c] = first[c];
    for (int64_t dy = 1; dy < K; ++dy) {
        const float *restrict row = rows + (y + dy) * n;
        for (int64_t c = 0; c < n; ++c) column_sums[c] += row[c];
    }
    for (int64_t x = 0; x < width; ++x) sums[x] = column_sums[x];
    for (int64_t j = 1; j < K; ++j)
        for (int64_t x = 0; x < width; ++x) sums[x] += column_sums[x + j];
}

typedef struct {
    float *left, *right, *texture, *row_stats, *column_sums, *texture_sums;
    int16_t *left16, *right16;
    void *vsum, *rows;
    int64_t *indices;
    float *row_levels, *row_texture; /* one image row pre-filtered (raw sources) */
    uint16_t *costs;                 /* run_row_u16's cost block */
} Buffers;

/* The images of one pair and where its levels and texture come from (see block_match). */
typedef struct {
    const float *left, *right, *texture;
    int source, textured;
    float cap;
    const uint8_t *mask; /* (H, W) where depth is wanted, or NULL: the whole box */
    int64_t margin;
} Views;

/* The first and the last column of the nonzero bytes of a mask row of W; 0 when the row has none. */
static int mask_row_span(const uint8_t *row, int64_t W, int64_t *first, int64_t *last) {
    int64_t a = 0, z = W - 1;
    while (a < W && !row[a]) ++a;
    if (a == W) return 0;
    while (!row[z]) --z;
    *first = a;
    *last = z;
    return 1;
}

/* The output columns of box row y (box coordinates) that the mask asks for: those within ``margin`` of a mask
 * pixel's column span in that image row, inside the box; an empty range where the row has no mask pixel. */
static void wanted_columns(const Views *views, const Pair *p, int64_t W, int64_t y, int64_t *begin, int64_t *end) {
    *begin = 0;
    *end = p->width;
    if (!views->mask) return;
    const int64_t row = p->y0 + y;
    int64_t first, last;
    if (row < 0 || row >= p->image_h || !mask_row_span(views->mask + row * W, W, &first, &last)) {
        *end = 0;
        return;
    }
    const int64_t a = first - views->margin - p->x0, z = last + 1 + views->margin - p->x0;
    if (a > *begin) *begin = a;
    if (z < *end) *end = z;
    if (*end < *begin) *end = *begin;
}

/* The pair's geometry for the band of box rows [y_begin, y_end): its box narrowed to the columns those rows want
 * (wanted_columns). Returns 0 when they want none (the band is skipped). Each pixel's result stays the whole
 * box's: only which pixels are computed changes. */
static int band_pair(const Views *views, const Pair *p, int64_t W, int64_t K, int64_t y_begin, int64_t y_end,
                     Pair *band) {
    *band = *p;
    if (!views->mask) return 1;
    int64_t lo = p->width, hi = 0;
    for (int64_t y = y_begin; y < y_end; ++y) {
        int64_t a, z;
        wanted_columns(views, p, W, y, &a, &z);
        if (z > a) {
            lo = a < lo ? a : lo;
            hi = z > hi ? z : hi;
        }
    }
    if (hi <= lo) return 0;
    band->x0 = p->x0 + lo;
    band->width = hi - lo;
    band->WW = band->width + 2 * band->extra;
    band->WL = band->WW + K - 1;
    band->WR = band->WL + band->D - 1;
    return 1;
}

static void run_task(const Views *views, int64_t H, int64_t W, int64_t K, const Pair *p, const Rules *rules,
                     int64_t y_begin, int64_t y_end, Buffers *buf, float *disparity, uint8_t *valid,
                     float *best_cost) {
    const int64_t radius = K / 2, rows = y_end - y_begin + K - 1, row0 = p->y0 + y_begin - radius;
    const int64_t left_col0 = p->x0 - p->extra - radius, right_col0 = left_col0 - p->min_d - (p->D - 1);
    const int64_t texture_cols = p->width + K - 1;
    if (views->source == SOURCE_LEVELS) {
        gather_rows(views->left, H, W, row0, left_col0, rows, p->WL, buf->left);
        gather_rows(views->right, H, W, row0, right_col0, rows, p->WR, buf->right);
        if (views->textured) gather_rows(views->texture, H, W, row0, p->x0 - radius, rows, texture_cols,
                                         buf->texture);
    } else {
        /* Each crop row pre-filtered from the raw image row it replicates (rows past the image edge repeat it). */
        for (int64_t r = 0; r < rows; ++r) {
            const int64_t y = clamp_index(row0 + r, H);
            prefilter_row(views->left, H, W, y, views->source, views->cap, buf->row_levels,
                          views->textured ? buf->row_texture : NULL);
            crop_row(buf->row_levels, W, left_col0, p->WL, buf->left + r * p->WL);
            if (views->textured) crop_row(buf->row_texture, W, p->x0 - radius, texture_cols,
                                          buf->texture + r * texture_cols);
            prefilter_row(views->right, H, W, y, views->source, views->cap, buf->row_levels, NULL);
            crop_row(buf->row_levels, W, right_col0, p->WR, buf->right + r * p->WR);
        }
    }
    const int small = to_samples16(buf->left, rows * p->WL, buf->right, rows * p->WR, K, buf->left16, buf->right16);
    if (small) cost_block_edges(p, buf->costs);
    RowOut out = {buf->row_stats, buf->row_stats + p->width, buf->row_stats + 2 * p->width,
                  buf->row_stats + 3 * p->width, buf->indices, buf->indices + p->width};
    for (int64_t y = y_begin; y < y_end; ++y) {
        if (small) {
            run_row_u16(p, K, y - y_begin, y == y_begin, buf->left16, buf->right16, buf->vsum, buf->costs, &out);
        } else {
            RowState st = row_state(buf->rows, p->WW);
            run_row_f32(p, K, y - y_begin, y == y_begin, buf->left, buf->right, buf->vsum, &st, &out);
        }
        const float *sums = NULL;
        if (views->textured) {
            texture_row(buf->texture, p->width, K, y - y_begin, buf->column_sums, buf->texture_sums);
            sums = buf->texture_sums;
        }
        int64_t x_begin, x_end;
        wanted_columns(views, p, W, y, &x_begin, &x_end);
        const int64_t offset = (p->y0 + y) * W + p->x0;
        finish_row(p, rules, y, &out, sums, x_begin, x_end, disparity + offset, valid + offset,
                   best_cost ? best_cost + offset : NULL);
    }
}

/* Dense SAD block matching of B pairs, each over its own box and its own disparity range, straight to the
 * disparity map (svs_torch.depth.block_matching._match_box's result, bit for bit):
 *   left, right: (B, H, W) images: with source SOURCE_LEVELS the pre-filtered images in whole levels, and
 *   texture (B, H, W) |x-Sobel| or NULL; with SOURCE_RAW or SOURCE_XSOBEL the raw intensities, pre-filtered
 *   here a crop row at a time (prefilter_row, x-Sobel clipped at prefilter_cap), and texture is ignored: the
 *   texture rule then runs on the left image's clipped x-Sobel when raw_texture is set;
 *   boxes (B, 4): x0, y0, width, height (width or height 0: nothing); min_d, counts (B,): the range
 *   [min_d, min_d + count); image_hw (B, 2): each pair's size before padding; lower_is_limit (B,): a winner at
 *   index 0 is kept (the range starts at 0, so it is no range edge);
 *   mask (B, H, W) uint8 or NULL: where depth is wanted; then only the pixels of a box row within mask_margin
 *   columns of that image row's mask span [first, last] are written, and a band of rows is searched only over
 *   the columns its rows want (a pixel's value is the whole box's: only the work shrinks);
 *   disparity (B, H, W) float32 and valid (B, H, W) uint8, zero on entry: written inside the boxes;
 *   best_cost (B, H, W) float32 or NULL: each computed pixel's winning cost, kept or not (+inf: no candidate).
 * Returns 0, or -1 when memory could not be had (then nothing is valid; the caller runs its torch path). Pairs
 * and bands of rows are shared among num_threads OpenMP threads. */
int block_match(const float *left, const float *right, const float *texture, int64_t source, float prefilter_cap,
                int64_t raw_texture, int64_t B, int64_t H, int64_t W,
                int64_t K, const int64_t *boxes, const int64_t *min_d, const int64_t *counts,
                const int64_t *image_hw, const uint8_t *lower_is_limit, float uniqueness_factor,
                float lr_max_diff, float texture_min, int64_t whole_range_in_view, const uint8_t *mask,
                int64_t mask_margin, float *disparity, uint8_t *valid, float *best_cost, int64_t num_threads,
                int64_t band_rows) {
    if (B <= 0 || H <= 0 || W <= 0 || K < 1 || K % 2 == 0) return 0;
    if (source != SOURCE_LEVELS && source != SOURCE_RAW && source != SOURCE_XSOBEL) return -1;
    Pair *pairs = malloc(sizeof(Pair) * (size_t)B);
    if (!pairs) return -1;
    const Rules rules = {uniqueness_factor, lr_max_diff, texture_min, whole_range_in_view != 0};
    int64_t max_height = 0, max_WL = 0, max_WR = 0, max_D = 1, max_width = 1;
    for (int64_t b = 0; b < B; ++b) {
        Pair *p = &pairs[b];
        p->x0 = boxes[4 * b];
        p->y0 = boxes[4 * b + 1];
        p->width = boxes[4 * b + 2];
        p->height = boxes[4 * b + 3];
        p->min_d = min_d[b];
        p->D = counts[b] < 1 ? 1 : counts[b];
        p->extra = lr_max_diff >= 0 ? p->D - 1 : 0;
        p->WW = p->width + 2 * p->extra;
        p->WL = p->WW + K - 1;
        p->WR = p->WL + p->D - 1;
        p->image_h = image_hw[2 * b];
        p->image_w = image_hw[2 * b + 1];
        p->lower_is_limit = lower_is_limit[b] != 0;
        if (p->width <= 0 || p->height <= 0) p->width = p->height = 0;
        if (p->height > max_height) max_height = p->height;
        if (p->WL > max_WL) max_WL = p->WL;
        if (p->WR > max_WR) max_WR = p->WR;
        if (p->D > max_D) max_D = p->D;
        if (p->width > max_width) max_width = p->width;
    }
    if (band_rows < 1) band_rows = max_height < 1 ? 1 : max_height;
    const int64_t bands = (max_height + band_rows - 1) / band_rows, tasks = B * bands;
    const int64_t input_rows = band_rows + K - 1;
    const int threads = thread_count(num_threads, tasks);
    int failed = 0;
    /* Tasks (pair, band of rows) are handed out one at a time: pairs and bands differ in cost. */
#pragma omp parallel num_threads(threads)
    {
        Buffers buf = {scratch(input_rows * max_WL, sizeof(float)),
                       scratch(input_rows * max_WR, sizeof(float)),
                       scratch(input_rows * (max_width + K - 1), sizeof(float)),
                       scratch(4 * max_width, sizeof(float)),
                       scratch(max_width + K - 1, sizeof(float)),
                       scratch(max_width, sizeof(float)),
                       scratch(input_rows * max_WL, sizeof(int16_t)),
                       scratch(input_rows * max_WR, sizeof(int16_t)),
                       scratch(max_D * max_WL, sizeof(float)),
                       scratch(11 * max_WL, sizeof(float)),
                       scratch(max_width + max_WL, sizeof(int64_t)),
                       scratch(W, sizeof(float)),
                       scratch(W, sizeof(float)),
                       scratch(max_D * (max_WL + max_D + GROUPS * LANES), sizeof(uint16_t))};
        const int ok = scratch_ready(buf.left && buf.right && buf.texture && buf.row_stats && buf.column_sums
                                         && buf.texture_sums && buf.left16 && buf.right16 && buf.vsum && buf.rows
                                         && buf.indices && buf.row_levels && buf.row_texture
                                         && buf.costs,
                                     &failed);
#pragma omp for schedule(dynamic, 1)
        for (int64_t task = 0; task < tasks; ++task) {
            if (!ok) continue;
            const int64_t b = task / bands, y0 = (task % bands) * band_rows;
            const Pair *p = &pairs[b];
            int64_t y1 = y0 + band_rows;
            if (y1 > p->height) y1 = p->height;
            if (y0 >= y1) continue;
            const Views views = {left + b * H * W, right + b * H * W, texture ? texture + b * H * W : NULL,
                                 (int)source, source == SOURCE_LEVELS ? texture != NULL : raw_texture != 0,
                                 prefilter_cap, mask ? mask + b * H * W : NULL, mask_margin};
            Pair band;
            if (!band_pair(&views, p, W, K, y0, y1, &band)) continue;
            run_task(&views, H, W, K, &band, &rules, y0, y1, &buf, disparity + b * H * W, valid + b * H * W,
                     best_cost ? best_cost + b * H * W : NULL);
        }
        free(buf.left);
        free(buf.right);
        free(buf.texture);
        free(buf.row_stats);
        free(buf.column_sums);
        free(buf.texture_sums);
        free(buf.left16);
        free(buf.right16);
        free(buf.vsum);
        free(buf.rows);
        free(buf.indices);
        free(buf.row_levels);
        free(buf.row_texture);
        free(buf.costs);
    }
    free(pairs);
    return failed ? -1 : 0;
}
