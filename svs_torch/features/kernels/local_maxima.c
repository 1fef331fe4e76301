/* Scale-space maxima of one SURF octave, for svs_torch.features.hessian (the no-gradient path).
 *
 * hessian._interior_maxima takes three running maxima of 3 along x, y and scale (six passes over the octave's
 * maps), compares, masks and selects: about a dozen passes through memory for a few hundred maxima. Here each
 * interior point is tested at once (maxima.h), and most stop at the threshold test. Comparisons only, so the result is
 * the torch path's exactly: a point keeps its det where det > threshold, support holds and no neighbour of
 * its 3 x 3 x 3 block is larger (a NaN neighbour, which makes torch's running maximum NaN, also rejects it);
 * -inf elsewhere.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared (see svs_torch/core/kernels/loader.py).
 */
#include <math.h>
#include <stdint.h>

#include "maxima.h"

/* det: contiguous (B, S, ny, nx) float32; support: (B or 1, S - 2, ny - 2, nx - 2) uint8, contiguous per
 * pair, support_batch_stride 0 when one support serves every pair; out: contiguous (B, S - 2, ny - 2, nx - 2). */
void local_maxima(const float *det, const uint8_t *support, int64_t support_batch_stride, int64_t B, int64_t S,
                  int64_t ny, int64_t nx, float threshold, float *out) {
    const int64_t iy = ny - 2, ix = nx - 2, plane = ny * nx;
    for (int64_t b = 0; b < B; ++b) {
        for (int64_t s = 1; s < S - 1; ++s) {
            for (int64_t y = 1; y < ny - 1; ++y) {
                const float *centre_row = det + (b * S + s) * plane + y * nx;
                const uint8_t *keep_row = support + b * support_batch_stride + ((s - 1) * iy + (y - 1)) * ix;
                float *out_row = out + ((b * (S - 2) + (s - 1)) * iy + (y - 1)) * ix;
                for (int64_t x = 1; x < nx - 1; ++x)
                    out_row[x - 1] = is_octave_maximum(centre_row + x, plane, nx, threshold, keep_row[x - 1])
                                         ? centre_row[x] : -INFINITY;
            }
        }
    }
}
