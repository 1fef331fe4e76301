/* One step of a semi-global path (Hirschmueller 2008, Eq. (13)), shared by semi_global_columns.c (the columns as
 * the vector lanes) and semi_global_rows.c (the rows as the lanes):
 *   L = C + min(L_prev(d), min(L_prev(d-1), L_prev(d+1)) + P1, m + P2) - m,  m = min_d L_prev
 * where the path starts again (m = +inf: the previous pixel outside the pair's region) L = C + (+0). best - m is
 * made in every lane and masked by ``keep`` (all ones: the path goes on; 0: it starts again) rather than selected:
 * written as ``restart ? 0 : best - m``, the subtraction (inf - inf there) may raise a floating-point exception
 * only where it is taken, and GCC 12 vectorised that select only with AVX-512's masked operations, leaving the
 * loops scalar on AVX2. The torch path's float32 operations in its order: the same values bit for bit. */
#ifndef SVS_TORCH_KERNELS_PATH_STEP_H
#define SVS_TORCH_KERNELS_PATH_STEP_H

#include <stdint.h>

static inline float min2(float a, float b) { return b < a ? b : a; }

/* L at one disparity of one lane: ``cost`` C, ``mid`` / ``lo`` / ``hi`` the previous pixel's path at d, d - 1 and
 * d + 1 (+inf past the range), ``m`` its minimum over d. */
static inline float path_step(float cost, float mid, float lo, float hi, float m, uint32_t keep, float p1, float p2) {
    const float best = min2(min2(mid, min2(hi, lo) + p1), m + p2);
    const float step = best - m;
    uint32_t bits;
    __builtin_memcpy(&bits, &step, sizeof bits);
    bits &= keep;
    float kept;
    __builtin_memcpy(&kept, &bits, sizeof kept);
    return cost + kept;
}

#endif
