/* The seeded minimal samples of svs_torch.geometry.ransac_sampling.draw_minimal_samples, shared by the kernels that
 * draw them (ransac_fundamental.c: 7 matches for F; row_alignment_fit.c: 3 for the row alignment). Integer
 * arithmetic only, so the ranks are the torch path's exactly. */
#ifndef SVS_TORCH_KERNELS_MINIMAL_SAMPLES_H
#define SVS_TORCH_KERNELS_MINIMAL_SAMPLES_H

#include <stdint.h>

static const uint64_t GAMMA = 0x9E3779B97F4A7C15ULL, MIX1 = 0xBF58476D1CE4E5B9ULL, MIX2 = 0x94D049BB133111EBULL;

/* The SplitMix64 output function. */
static inline uint64_t splitmix64(uint64_t z) {
    z = (z ^ (z >> 30)) * MIX1;
    z = (z ^ (z >> 27)) * MIX2;
    return z ^ (z >> 31);
}

/* Hypothesis h of a pair of ``seed``: ``size`` distinct ranks in [0, max(n, size)) by Floyd's algorithm. */
static inline void draw_minimal_sample(uint64_t seed, int64_t h, int64_t n, int size, int64_t *ranks) {
    const int64_t population = n > size ? n : size;
    for (int slot = 0; slot < size; ++slot) {
        const uint64_t counter = (uint64_t)h * (uint64_t)size + (uint64_t)(slot + 1);
        const uint64_t bits = splitmix64(seed + counter * GAMMA) >> 11;
        const int64_t top = population - size + slot;
        int64_t pick = (int64_t)(bits % (uint64_t)(top + 1));
        for (int i = 0; i < slot; ++i) {
            if (ranks[i] == pick) {
                pick = top;
                break;
            }
        }
        ranks[slot] = pick;
    }
}

#endif
