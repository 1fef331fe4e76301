/* The nearness rule's split of a measured disparity map, for svs_torch.segmentation.nearness_split (the
 * no-gradient path of _otsu_split and _split_leaving_near, whose torch forms stay the reference and the fallback).
 *
 * The torch path makes about a dozen whole-map passes a pair (the clip at the 99.5th percentile, its extremes, the
 * scaled map, its levels, their histogram, the near share; again under the 90th percentile where the split is taken
 * again): 1.4-1.8 ms of a 320x240 camera frame at guide's B = 1. Here the map is read four times (its finiteness,
 * the extremes, the levels, the near share), twice more where the split is taken again: 0.3 ms.
 * Per pair, with the pixels of ``exclude`` (the floor) left out of every statistic:
 *   v = min(d, clip)                           clip: the 99.5th percentile (computed by the caller)
 *   low, high = extremes of v
 *   level = clamp(round-half-even(255 (v - low) / (high - low or 1)), 0, 255), counted in a 256-bin histogram
 *   t = Otsu's level of the histogram (float64, as svs_torch.segmentation.threshold.otsu_threshold_level)
 *   split = low + (t + 0.5) / 255 (high - low)
 * then, where less than ``min_near_share`` of the pixels lie above the split, the same again with the clip at the
 * 90th percentile (retaken). Every step is the torch path's operation in its dtype and order (float32 for the map,
 * float64 for Otsu's sums, which are whole numbers below 2^53 and so exact in any order), so the results are its
 * values bit for bit.
 *
 * A map with a NaN or an infinity is refused (returns 1; the caller runs the torch path, whose levels of a NaN are
 * not defined in C).
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp. Loaded through ctypes by
 * svs_torch/segmentation/kernels/__init__.py.
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "common.h"

#define LEVELS 256

/* torch.minimum(d, clip) for values without NaN: std::min's order, the first operand on a tie. */
static inline float clipped(float d, float clip) { return clip < d ? clip : d; }

/* Otsu's level of one histogram, as otsu_threshold_level: the first maximum of the between-class variance over
 * the admissible levels (class probability at least FLT_EPSILON on each side), 0 where none is admissible. */
static int64_t otsu_level(const int64_t *histogram) {
    const double eps = 1.1920928955078125e-07; /* torch.finfo(torch.float32).eps */
    double total = 0.0, level_sum = 0.0;
    for (int l = 0; l < LEVELS; ++l) {
        total += (double)histogram[l];
        level_sum += (double)histogram[l] * (double)l;
    }
    const double denominator = total < 1.0 ? 1.0 : total;
    double w1 = 0.0, s1 = 0.0, best_sigma = -INFINITY;
    int64_t best = 0;
    int any = 0;
    for (int t = 0; t < LEVELS; ++t) {
        w1 += (double)histogram[t];
        s1 += (double)histogram[t] * (double)t;
        const double w2 = total - w1, s2 = level_sum - s1;
        const double q1 = w1 / denominator, q2 = 1.0 - q1;
        const double lower = q2 < q1 ? q2 : q1, upper = q1 < q2 ? q2 : q1;
        const int admissible = lower >= eps && upper <= 1.0 - eps;
        double sigma = -1.0;
        if (admissible) {
            const double difference = s1 * w2 - s2 * w1;
            sigma = (difference * difference) / (w1 * w2);
            any = 1;
        }
        if (sigma > best_sigma) { /* strictly: the first maximum, as torch.argmax */
            best_sigma = sigma;
            best = t;
        }
    }
    return any ? best : 0;
}

/* One pair's Otsu split of its map clipped at ``clip`` (``keep``: 1 for a pixel in the statistics, or NULL: all). */
static float otsu_split(const float *d, const uint8_t *keep, int64_t P, float clip) {
    float low = INFINITY, high = -INFINITY;
    for (int64_t p = 0; p < P; ++p) {
        if (keep && !keep[p]) continue;
        const float v = clipped(d[p], clip);
        low = v < low ? v : low;
        high = v > high ? v : high;
    }
    const float spread = high - low;
    const float divisor = spread > 0.0f ? spread : 1.0f;
    int64_t histogram[LEVELS];
    memset(histogram, 0, sizeof histogram);
    for (int64_t p = 0; p < P; ++p) {
        if (keep && !keep[p]) continue;
        float level = nearbyintf(((clipped(d[p], clip) - low) / divisor) * 255.0f);
        level = level > 0.0f ? level : 0.0f;
        level = level < 255.0f ? level : 255.0f;
        ++histogram[(int)level];
    }
    const float t = ((float)otsu_level(histogram) + 0.5f) / 255.0f;
    return low + t * (high - low);
}

/* disparity: (B, P) float32; exclude: (B, P) uint8 (1: left out) or NULL (none); clip_high, clip_retry: (B,)
 * float32, the 99.5th and the 90th percentiles; min_near_share: the share below which the split is taken again
 * (as float32, the torch comparison's dtype), with retry 0: never. Writes split (B,) float32 and retaken (B,) uint8.
 * A pair that leaves out every pixel keeps them all. Returns 0, 1 for a non-finite value, -1 when scratch memory
 * ran out. */
int nearness_split(const float *disparity, const uint8_t *exclude, int64_t B, int64_t P, const float *clip_high,
                   const float *clip_retry, float min_near_share, int64_t retry, float *split, uint8_t *retaken,
                   int64_t num_threads) {
    for (int64_t b = 0; b < B; ++b)
        if (!isfinite(clip_high[b]) || !isfinite(clip_retry[b])) return 1;
    int refused = 0, failed = 0;
    const int threads = thread_count(num_threads, B);
#pragma omp parallel for num_threads(threads) schedule(dynamic, 1)
    for (int64_t b = 0; b < B; ++b) {
        const float *d = disparity + b * P;
        int finite = 1;
        for (int64_t p = 0; p < P; ++p) finite &= isfinite(d[p]) != 0;
        if (!finite) {
#pragma omp atomic write
            refused = 1;
            continue;
        }
        const uint8_t *left_out = exclude ? exclude + b * P : NULL;
        uint8_t *keep = NULL;
        int64_t kept = P;
        if (left_out) {
            kept = 0;
            for (int64_t p = 0; p < P; ++p) kept += left_out[p] == 0;
            if (kept > 0 && kept < P) {
                keep = scratch(P, 1);
                if (!scratch_ready(keep != NULL, &failed)) continue;
                for (int64_t p = 0; p < P; ++p) keep[p] = left_out[p] == 0;
            } else {
                kept = P; /* none left out, or all: then every pixel counts */
            }
        }
        float value = otsu_split(d, keep, P, clip_high[b]);
        uint8_t again = 0;
        if (retry) {
            int64_t near = 0;
            for (int64_t p = 0; p < P; ++p) near += (d[p] > value) && (!keep || keep[p]);
            /* torch: near.float().mean() (a sum, then / P) or an int64 count / an int64 count, both in float32 */
            const float share = (float)near / (float)(kept > 0 ? kept : 1);
            if (share < min_near_share) {
                value = otsu_split(d, keep, P, clip_retry[b]);
                again = 1;
            }
        }
        split[b] = value;
        retaken[b] = again;
        free(keep);
    }
    return failed ? -1 : refused;
}
