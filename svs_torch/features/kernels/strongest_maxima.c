/* The k strongest scale-space maxima of each image over all its SURF octaves, for svs_torch.features.detector (the
 * no-gradient path of local_maxima_scores, their concatenation and torch.topk).
 *
 * That path writes each octave's dense map of maxima (det at a few hundred points, -inf at the other ~200 000 of
 * a 320x240 image), concatenates the maps and partially sorts every whole row with torch.topk: three passes
 * through memory and a sort of 200 000 entries per image for a few hundred. Here each image's octaves are read
 * once, with the test of local_maxima.c (maxima.h), the maxima are collected, and only they are sorted: largest
 * first, equal det in index order (an order torch.topk leaves open). Index i is the point's position in that
 * concatenation (octave after octave, each (S - 2, ny - 2, nx - 2) in order), as torch.topk's would be. The k
 * values are torch.topk's; past an image's last maximum, -inf at index 0.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp. Loaded through ctypes by
 * svs_torch/features/kernels/__init__.py; images are shared among num_threads OpenMP threads.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "common.h"
#include "maxima.h"

typedef struct {
    float value;
    int64_t index;
} candidate;

/* flags[x] = 1 where values[x] > threshold and keep[x] (0 or 1), n points. */
static void above_row(const float *restrict values, const uint8_t *restrict keep, int64_t n, float threshold,
                      uint8_t *restrict flags) {
    for (int64_t x = 0; x < n; ++x) flags[x] = (uint8_t)(values[x] > threshold) & keep[x];
}

/* Eight flags as one word (memcpy: any alignment), flag i in byte i counted from the least significant. */
static inline uint64_t flag_word(const uint8_t *flags) {
    uint64_t word;
    memcpy(&word, flags, sizeof word);
#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ == __ORDER_BIG_ENDIAN__
    word = __builtin_bswap64(word);
#endif
    return word;
}

/* qsort order: the larger value first, then the smaller index (the entries are distinct, so a total order). */
static int stronger_first(const void *a, const void *b) {
    const candidate *x = a, *y = b;
    if (x->value != y->value) return x->value > y->value ? -1 : 1;
    return (x->index > y->index) - (x->index < y->index);
}

/* Octave o: det[o] contiguous (B, S, ny, nx) float32 with (S, ny, nx) = shape[3 o .. 3 o + 2]; support[o]
 * (B or 1, S - 2, ny - 2, nx - 2) uint8, contiguous per image, support_stride[o] 0 when one serves every image
 * (an octave without interior points, ny or nx under 3, may pass NULL pointers). values (B, k) float32 and
 * index (B, k) int64. Returns 0, or -1 when memory could not be had (the caller then runs the torch path). */
int strongest_maxima(const int64_t *det, const int64_t *support, const int64_t *support_stride,
                     const int64_t *shape, int64_t octaves, int64_t B, float threshold, int64_t k, float *values,
                     int64_t *index, int64_t num_threads) {
    const int threads = thread_count(num_threads, B);
    int failed = 0;
    int64_t max_width = 8;
    for (int64_t o = 0; o < octaves; ++o)
        if (shape[3 * o + 2] > max_width) max_width = shape[3 * o + 2];
#pragma omp parallel for num_threads(threads) schedule(dynamic, 1)
    for (int64_t b = 0; b < B; ++b) {
        int64_t capacity = 1024, count = 0, offset = 0;
        candidate *found = scratch(capacity, sizeof(candidate));
        uint8_t *flags = scratch(max_width + 8, 1);
        int ok = scratch_ready(found != NULL && flags != NULL, &failed);
        for (int64_t o = 0; o < octaves && ok; ++o) {
            const int64_t S = shape[3 * o], ny = shape[3 * o + 1], nx = shape[3 * o + 2];
            const int64_t iy = ny - 2, ix = nx - 2, plane = ny * nx;
            if (S < 3 || iy < 1 || ix < 1) continue;  /* no interior point: nothing to read, nothing in the index */
            const float *maps = (const float *)(intptr_t)det[o] + b * S * plane;
            const uint8_t *keep = (const uint8_t *)(intptr_t)support[o] + b * support_stride[o];
            /* Row by row through every level: the three rows around y of all the levels stay in cache while each
             * level's candidates read their neighbours (level by level, the neighbouring levels' rows had left it
             * by the time they were read). The order of discovery does not matter: the candidates are sorted. */
            for (int64_t y = 1; y < ny - 1 && ok; ++y)
                for (int64_t s = 1; s < S - 1 && ok; ++s) {
                    const float *centre_row = maps + s * plane + y * nx;
                    const uint8_t *keep_row = keep + ((s - 1) * iy + (y - 1)) * ix;
                    /* Which points pass the threshold and the support, in a loop gcc vectorises; only those (8 %
                     * on the shared scenes) take the neighbour test, eight flags read as one word and its set
                     * bytes visited lowest first. A branch per point mispredicted too often. */
                    above_row(centre_row + 1, keep_row, ix, threshold, flags);
                    memset(flags + ix, 0, 8); /* the last word's bytes past the row */
                    for (int64_t word = 0; word < ix && ok; word += 8)
                        for (uint64_t set = flag_word(flags + word); set && ok; set &= set - 1) {
                            const int64_t x = word + __builtin_ctzll(set) / 8 + 1;
                            if (!is_octave_maximum(centre_row + x, plane, nx, threshold, 1)) continue;
                            if (count == capacity) {
                                candidate *grown = realloc(found, 2 * (size_t)capacity * sizeof(candidate));
                                if (!scratch_ready(grown != NULL, &failed)) {
                                    ok = 0;
                                    break;
                                }
                                found = grown;
                                capacity *= 2;
                            }
                            found[count].value = centre_row[x];
                            found[count].index = offset + ((s - 1) * iy + (y - 1)) * ix + (x - 1);
                            ++count;
                        }
                }
            offset += (S - 2) * iy * ix;
        }
        if (ok) {
            qsort(found, (size_t)count, sizeof(candidate), stronger_first);
            for (int64_t j = 0; j < k; ++j) {
                values[b * k + j] = j < count ? found[j].value : -INFINITY;
                index[b * k + j] = j < count ? found[j].index : 0;
            }
        }
        free(found);
        free(flags);
    }
    return failed ? -1 : 0;
}
