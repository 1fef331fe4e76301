/* The scale-space maximum test of one SURF octave point, shared by local_maxima.c (the dense map of maxima) and
 * strongest_maxima.c (the strongest maxima of each image). Comparisons only, so both give the torch path's
 * (hessian._interior_maxima) answer exactly. */
#ifndef SVS_TORCH_KERNELS_MAXIMA_H
#define SVS_TORCH_KERNELS_MAXIMA_H

#include <stdint.h>

/* Whether the det value at ``centre`` (an interior point of a contiguous (S, ny, nx) octave, ``plane`` = ny * nx)
 * is kept: above ``threshold``, with support (``kept``), and no neighbour of its 3 x 3 x 3 block larger (a NaN
 * neighbour, which makes torch's running maximum NaN, also rejects it). Most points stop at the threshold; the
 * others take all 27 comparisons without a branch: stopping at the first larger neighbour mispredicted most of
 * the time. */
static inline int is_octave_maximum(const float *centre, int64_t plane, int64_t nx, float threshold, int kept) {
    const float c = *centre;
    if (!(c > threshold && kept)) return 0;
    int ok = 1;
    for (int ds = -1; ds <= 1; ++ds)
        for (int dy = -1; dy <= 1; ++dy) {
            const float *n = centre + ds * plane + dy * nx;
            /* n <= c is false for a NaN neighbour, which rejects the point. */
            ok &= (n[-1] <= c) & (n[0] <= c) & (n[1] <= c);
        }
    return ok;
}

#endif
