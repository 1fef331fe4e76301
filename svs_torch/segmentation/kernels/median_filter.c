/* Square median filter with replicated edges, for svs_torch.segmentation.nearness (the nearness map's denoising
 * median, the no-gradient path).
 *
 * The torch path pads the map, unfolds every K x K window and takes ``median(-1)``: it copies K^2 values per pixel
 * and sorts each window (49 values at K = 7): 16 ms a pair of 320x240 on one thread, most of the nearness
 * segmenter. Here each output row lays out its window's columns side by side (edge columns repeated), so the
 * window of every pixel is K^2 consecutive values, and the median is tracked along the row: the window's median
 * m is its value with fewer than R = (K^2 - 1) / 2 + 1 values below it and at least R at or below it; a step
 * right changes K of the K^2 values, so the new median is a few distinct values from the last one, and m moves
 * to the next smaller (or larger) window value until the counts hold. Each count or move is one branch-free pass
 * over K^2 values. The result is the element of rank (K^2 - 1) / 2, torch's (lower) median, one of the window's
 * own values: the torch path's values (a zero's sign aside where -0 and +0 meet in one window). NaN is not
 * allowed (the caller checks); +-inf are ordinary values.
 *
 * Windows of up to 64 values (K <= 7, the nearness map's default) take a selection network instead, NET_LANES
 * pixels of a row at a time in vector registers: Batcher's odd-even merge sort of 64 values, its comparators that
 * touch the padding (+inf, which never moves) dropped, then every comparator that cannot reach the rank's output
 * dropped (a backward pass), 319 compare-exchanges at K = 7. Min and max copy values, so the output is the same
 * element of rank (K^2 - 1) / 2 (a zero's sign aside, as above), without the tracker's data-dependent passes
 * (64 real 320x240 pairs in the pipeline, one thread: the nearness map's median 2.3 -> 0.9 ms a pair).
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp. Loaded through ctypes by
 * svs_torch/segmentation/kernels/__init__.py; image rows are shared among num_threads OpenMP threads.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "common.h"

static inline int64_t clamp_index(int64_t i, int64_t n) { return i < 0 ? 0 : (i >= n ? n - 1 : i); }

/* The element of rank ``rank`` of ``v[0, n)``, found from ``m``, one of its values (see the top). Each pass
 * counts the values below and equal to m and finds the nearest values on either side, so a move to the next
 * value needs no second pass. */
static float track_median(const float *v, int n, int rank, float m) {
    for (;;) {
        int below = 0, equal = 0;
        float under = -INFINITY, over = INFINITY;
#pragma omp simd reduction(+ : below, equal) reduction(max : under) reduction(min : over)
        for (int i = 0; i < n; ++i) {
            const float x = v[i], lower = x < m ? x : -INFINITY, upper = x > m ? x : INFINITY;
            below += x < m;
            equal += x == m;
            under = lower > under ? lower : under;
            over = upper < over ? upper : over;
        }
        if (below > rank) m = under;              /* the median is smaller: the largest value below m */
        else if (below + equal <= rank) m = over; /* larger: the smallest value above m */
        else return m;
    }
}

#define NET_MAX 64   /* the most values a window may hold for the network path */
#define NET_LANES (VECTOR_BYTES / 4) /* pixels of a row through the network side by side: a register of floats */
#define NET_MAX_COMPARATORS 544 /* Batcher's odd-even merge sort of 64 values has 543 */

/* The compare-exchanges that leave the element of rank ``rank`` of ``n`` <= NET_MAX values at index ``rank``
 * (see the top): from[c] gets the smaller, to[c] the larger. Returns their number. */
static int median_network(int n, int rank, uint8_t *from, uint8_t *to) {
    int N = 1, count = 0;
    while (N < n) N *= 2;
    uint8_t all_from[NET_MAX_COMPARATORS], all_to[NET_MAX_COMPARATORS];
    for (int p = 1; p < N; p *= 2)
        for (int k = p; k >= 1; k /= 2)
            for (int j = k % p; j <= N - 1 - k; j += 2 * k)
                for (int i = 0; i <= k - 1 && i <= N - j - k - 1; ++i)
                    if ((i + j) / (2 * p) == (i + j + k) / (2 * p) && i + j + k < n) {
                        all_from[count] = (uint8_t)(i + j);
                        all_to[count] = (uint8_t)(i + j + k);
                        ++count;
                    }
    /* Backward: a comparator matters if it touches an index that a later kept comparator, or the output, reads. */
    uint8_t needed[NET_MAX] = {0}, keep[NET_MAX_COMPARATORS] = {0};
    needed[rank] = 1;
    for (int c = count - 1; c >= 0; --c)
        if (needed[all_from[c]] || needed[all_to[c]]) keep[c] = 1, needed[all_from[c]] = needed[all_to[c]] = 1;
    int kept = 0;
    for (int c = 0; c < count; ++c)
        if (keep[c]) from[kept] = all_from[c], to[kept] = all_to[c], ++kept;
    return kept;
}

/* NET_LANES floats in one vector (GCC / Clang vector extensions: one register, VECTOR_BYTES of common.h), and a
 * comparison's lanes (-1 or 0). Written as vectors, not as a loop over lanes: a loop's two rows of
 * one comparator may alias as far as the compiler knows, and it then compiled each lane to a compare and a
 * branch (64 real 320x240 maps: 2.3 -> 20 ms a pair instead of faster). */
typedef float lanes_f32 __attribute__((vector_size(4 * NET_LANES)));
typedef int32_t lanes_i32 __attribute__((vector_size(4 * NET_LANES)));

static inline lanes_f32 pick_f32(lanes_i32 where, lanes_f32 a, lanes_f32 b) {
    return (lanes_f32)(((lanes_i32)a & where) | ((lanes_i32)b & ~where));
}

/* NET_LANES outputs of one row by the network: ``rows[dy]`` is the row y + dy - half of the image, edge columns
 * repeated, from image column x0 - half on. */
static void network_lanes(const float *const *rows, int64_t K, int64_t x0, int count, const uint8_t *from,
                          const uint8_t *to, int64_t rank, float *out) {
    lanes_f32 v[NET_MAX];
    for (int64_t dy = 0; dy < K; ++dy)
        for (int64_t dx = 0; dx < K; ++dx) __builtin_memcpy(&v[dy * K + dx], rows[dy] + x0 + dx, sizeof v[0]);
    for (int c = 0; c < count; ++c) {
        const lanes_f32 a = v[from[c]], b = v[to[c]];
        const lanes_i32 less = a < b;
        v[from[c]] = pick_f32(less, a, b);
        v[to[c]] = pick_f32(less, b, a);
    }
    __builtin_memcpy(out, &v[rank], sizeof v[0]);
}

/* median_filter for n <= NET_MAX by the network (see the top). */
static int median_filter_network(const float *image, int64_t B, int64_t H, int64_t W, int64_t K, float *out,
                                 int64_t num_threads) {
    const int64_t rows = B * H, half = K / 2, n = K * K, rank = (K * K - 1) / 2;
    const int64_t span = W + 2 * half + NET_LANES; /* a padded row: the last lanes read past the image's end */
    uint8_t from[NET_MAX_COMPARATORS], to[NET_MAX_COMPARATORS];
    const int count = median_network((int)n, (int)rank, from, to);
    const int threads = thread_count(num_threads, rows);
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        float *band = scratch(span * K + NET_LANES, sizeof(float));
        const int ready = scratch_ready(band != NULL, &failed);
        const float *row_of[NET_MAX];
#pragma omp for schedule(static)
        for (int64_t r = 0; r < rows; ++r) {
            if (!ready) continue;
            const int64_t b = r / H, y = r % H;
            const float *plane = image + b * H * W;
            float *lanes = band + span * K;
            for (int64_t dy = 0; dy < K; ++dy) {
                const float *source = plane + clamp_index(y + dy - half, H) * W;
                float *padded = band + dy * span;
                for (int64_t px = 0; px < span; ++px) padded[px] = source[clamp_index(px - half, W)];
                row_of[dy] = padded;
            }
            float *row = out + r * W;
            for (int64_t x0 = 0; x0 < W; x0 += NET_LANES) {
                network_lanes(row_of, K, x0, count, from, to, rank, lanes);
                const int64_t m = W - x0 < NET_LANES ? W - x0 : NET_LANES;
                for (int64_t l = 0; l < m; ++l) row[x0 + l] = lanes[l];
            }
        }
        free(band);
    }
    return failed ? -1 : 0;
}

/* Returns 0, or -1 when memory could not be had (the caller then runs the torch path). */
int median_filter(const float *image, int64_t B, int64_t H, int64_t W, int64_t K, float *out, int64_t num_threads) {
    if (K * K <= NET_MAX) return median_filter_network(image, B, H, W, K, out, num_threads);
    const int64_t rows = B * H, half = K / 2, n = K * K, rank = (K * K - 1) / 2;
    const int threads = thread_count(num_threads, rows);
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        /* Column px of the row's window band (image column px - half, clamped), its K values one after another. */
        float *band = scratch((W + 2 * half) * K, sizeof(float));
        const int ready = scratch_ready(band != NULL, &failed);
#pragma omp for schedule(static)
        for (int64_t r = 0; r < rows; ++r) {
            if (!ready) continue;
            const int64_t b = r / H, y = r % H;
            const float *plane = image + b * H * W;
            for (int64_t px = 0; px < W + 2 * half; ++px) {
                const int64_t x = clamp_index(px - half, W);
                for (int64_t dy = 0; dy < K; ++dy) band[px * K + dy] = plane[clamp_index(y + dy - half, H) * W + x];
            }
            float *row = out + r * W;
            float m = band[n / 2]; /* any of the first window's values will do */
            for (int64_t x = 0; x < W; ++x) {
                m = track_median(band + x * K, (int)n, (int)rank, m);
                row[x] = m;
            }
        }
        free(band);
    }
    return failed ? -1 : 0;
}
