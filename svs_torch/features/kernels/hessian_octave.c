/* One octave of SURF's box-filter Hessian, for svs_torch.features.hessian (the no-gradient path), read straight
 * from the padded integral image.
 *
 * The eager torch path (hessian._det_trace) slices 32 integral-image corner views per level from the octave's
 * sub-lattices (integral.integral_phases: one contiguous copy of the whole table per phase) and makes about 40
 * elementwise passes over the grid, each through memory. Here every level of the octave is made in one call:
 * each grid point's 32 corners are read from the padded table at the octave's step (the same values the phases
 * hold) and finished at once. The arithmetic is _det_trace's, operation for operation, in the same order and
 * in float32 without contraction into FMAs, so the result is bit-identical:
 *   box_i = ((c[4i] - c[4i+1]) - c[4i+2]) + c[4i+3]
 *   dxx = (box_0 - 3 box_1) * lobe,  dyy = (box_2 - 3 box_3) * lobe,  dxy = (((box_4 - box_5) - box_6) + box_7) * gap
 *   det = dxx dyy - (0.9 dxy)^2,  trace = dxx + dyy
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp (see svs_torch/core/kernels/loader.py).
 */
#include <stdint.h>

#include "common.h"

/* One output row: corner k of grid point x sits at c[k][x * STEP]. */
#define ROW_LOOP(STEP)                                                                                            \
    for (int64_t x = 0; x < nx; ++x) {                                                                            \
        float box[8];                                                                                             \
        for (int i = 0; i < 8; ++i)                                                                               \
            box[i] = ((c[4 * i][x * (STEP)] - c[4 * i + 1][x * (STEP)]) - c[4 * i + 2][x * (STEP)])               \
                     + c[4 * i + 3][x * (STEP)];                                                                  \
        float dxx = (box[0] - 3.0f * box[1]) * lobe_factor;                                                       \
        float dyy = (box[2] - 3.0f * box[3]) * lobe_factor;                                                       \
        float dxy = (((box[4] - box[5]) - box[6]) + box[7]) * dxy_factor;                                         \
        float weighted = dxy_weight * dxy;                                                                        \
        d_out[x] = dxx * dyy - weighted * weighted;                                                               \
        t_out[x] = dxx + dyy;                                                                                     \
    }

/* padded: (B, PH, PW) float32, contiguous: the integral image (a leading zero row and column) extended by
 * ``pad`` on every side (integral.pad_integral). Grid point (i, j) of the octave is pixel (step i, step j); its
 * box rows [r0, r1) and columns [c0, c1) around the pixel read the table at (pad + step i + r, pad + step j + c).
 * sizes (S,): the filter sizes L; inverse_lobe_area, inverse_dxy_area (S,): each level's box normalisations.
 * det, trace: (B, S, ny, nx) contiguous. The B * S * ny rows are shared among num_threads OpenMP threads
 * (torch's own pool: see svs_torch/core/kernels/loader.py). */
void hessian_octave(const float *padded, int64_t B, int64_t PH, int64_t PW, int64_t pad, int64_t step,
                    const int64_t *sizes, int64_t S, int64_t ny, int64_t nx, const float *inverse_lobe_area,
                    const float *inverse_dxy_area, float dxy_weight, float *det, float *trace,
                    int64_t num_threads) {
    const int64_t rows = B * S * ny;
    const int threads = thread_count(num_threads, rows);
    /* Threads only for enough work: a parallel region costs a few microseconds. */
#pragma omp parallel for schedule(static) num_threads(threads) if (rows * nx >= 16384)
    for (int64_t r = 0; r < rows; ++r) {
        const int64_t b = r / (S * ny), s = r / ny % S, y = r % ny;
        const int64_t size = sizes[s], lobe = size / 3, half = size / 2;
        /* The boxes of hessian._level_corners, relative to the centre pixel: Dxx's whole band and middle lobe,
         * Dyy's (transposed), Dxy's four l x l boxes around a one-pixel gap. */
        const int64_t long_rows[2] = {-(lobe - 1), lobe}, outer[2] = {-half, half + 1};
        const int64_t centre[2] = {-(lobe / 2), lobe / 2 + 1}, before[2] = {-lobe, 0}, after[2] = {1, lobe + 1};
        const int64_t *box_rows[8] = {long_rows, long_rows, outer, centre, before, before, after, after};
        const int64_t *box_cols[8] = {outer, centre, long_rows, long_rows, before, after, before, after};
        const float *origin = padded + b * PH * PW + (pad + y * step) * PW + pad;
        const float *restrict c[32];
        for (int i = 0; i < 8; ++i) {
            const int64_t r0 = box_rows[i][0], r1 = box_rows[i][1], c0 = box_cols[i][0], c1 = box_cols[i][1];
            c[4 * i] = origin + r1 * PW + c1;     /* bottom-right */
            c[4 * i + 1] = origin + r0 * PW + c1; /* top-right */
            c[4 * i + 2] = origin + r1 * PW + c0; /* bottom-left */
            c[4 * i + 3] = origin + r0 * PW + c0; /* top-left */
        }
        const float lobe_factor = inverse_lobe_area[s], dxy_factor = inverse_dxy_area[s];
        float *restrict d_out = det + r * nx;
        float *restrict t_out = trace + r * nx;
        /* The outputs never overlap the table they are made from. */
        switch (step) {
            case 1: {
#pragma GCC ivdep
                ROW_LOOP(1)
                break;
            }
            case 2: {
#pragma GCC ivdep
                ROW_LOOP(2)
                break;
            }
            case 4: {
#pragma GCC ivdep
                ROW_LOOP(4)
                break;
            }
            default: {
                ROW_LOOP(step)
            }
        }
    }
}
