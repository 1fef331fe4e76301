/* Sub-pixel, sub-scale refinement of SURF's strongest maxima, for svs_torch.features.detector (the no-gradient
 * path of the index decoding, _octave_reader and _refine in detect_surf_keypoints, whose torch form stays the
 * reference and the fallback).
 *
 * The torch path gathers each keypoint's 3 x 3 x 3 neighbourhood from every octave and picks its own octave's,
 * then fits the quadratic with about forty small elementwise ops and a batched 3 x 3 solve: about 1 ms a pair at
 * the command line's settings, nearly all of it per-op overhead on (B, K) tensors. Here each keypoint is one
 * loop iteration: its octave, level, row and column from its index into the octaves' concatenated interiors
 * (strongest_maxima's indices), its 27 det values read as they lie (the torch path's clamped reads), the same
 * finite differences in double in the same order, and Brown & Lowe's 3 x 3 system solved by LU with partial
 * pivoting (small_lu.h, shared with the geometry kernels). torch solves it with LAPACK's LU, whose rounding differs
 * in the last bits: offsets agree to about 1e-15 (tests/core/test_kernels.py).
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp. Loaded through ctypes by
 * svs_torch/features/kernels/__init__.py.
 */
#include <math.h>
#include <stdint.h>

#include "common.h"
#include "small_lu.h"

static inline int64_t clamp_cell(int64_t i, int64_t n) { return i < 0 ? 0 : (i >= n ? n - 1 : i); }

/* Octave o (each with an interior: S, ny, nx >= 3): det[o], trace[o] contiguous (B, S, ny, nx) float32 with
 * (S, ny, nx) = shape[3 o .. 3 o + 2], its grid step, first filter size and size increment. score, index (B, K):
 * strongest_maxima's values and indices. Writes per keypoint xy (B, K, 2) and size (B, K) in input pixels
 * (``factor``: the detector's upsampling), the fitted peak (B, K), the sign of the trace (B, K) and valid (B, K):
 * found (a finite score), solved, and every offset within max_offset grid steps. Keypoints are shared among
 * num_threads OpenMP threads. Returns 0. */
int refine_maxima(const int64_t *det, const int64_t *trace, const int64_t *shape, const int64_t *step,
                  const int64_t *size0, const int64_t *size_inc, int64_t octaves, const float *score,
                  const int64_t *index, int64_t B, int64_t K, double factor, double max_offset, double *xy,
                  double *size, double *peak, int64_t *sign, uint8_t *valid, int64_t num_threads) {
    const int threads = thread_count(num_threads, B * K);
#pragma omp parallel for num_threads(threads) schedule(static)
    for (int64_t row = 0; row < B * K; ++row) {
        const int64_t b = row / K, at_index = index[row];
        /* The octave: the last whose interiors start at or before the index (torch.searchsorted, right). */
        int64_t o = 0, offset = 0, start = 0;
        for (int64_t q = 0; q < octaves; ++q) {
            if (start <= at_index) o = q, offset = start;
            start += (shape[3 * q] - 2) * (shape[3 * q + 1] - 2) * (shape[3 * q + 2] - 2);
        }
        const int64_t S = shape[3 * o], ny = shape[3 * o + 1], nx = shape[3 * o + 2];
        /* local >= 0: the indices are into the interiors (0 past an image's last maximum), every octave has one */
        const int64_t inner_nx = nx - 2, inner_plane = (ny - 2) * inner_nx, local = at_index - offset;
        const int64_t level = local / inner_plane + 1, row_in = local % inner_plane / inner_nx + 1;
        const int64_t col = local % inner_nx + 1;
        const int64_t plane = ny * nx, cells = S * plane, position = level * plane + row_in * nx + col;
        const float *map = (const float *)(intptr_t)det[o] + b * cells;
        const float *trace_map = (const float *)(intptr_t)trace[o] + b * cells;
#define AT(dx, dy, ds) ((double)map[clamp_cell(position + (dx) + (dy) * nx + (ds) * plane, cells)])
        const double centre = AT(0, 0, 0);
        const double g[3] = {(AT(1, 0, 0) - AT(-1, 0, 0)) / 2, (AT(0, 1, 0) - AT(0, -1, 0)) / 2,
                             (AT(0, 0, 1) - AT(0, 0, -1)) / 2};
        const double dxx = AT(1, 0, 0) + AT(-1, 0, 0) - 2 * centre;
        const double dyy = AT(0, 1, 0) + AT(0, -1, 0) - 2 * centre;
        const double dss = AT(0, 0, 1) + AT(0, 0, -1) - 2 * centre;
        const double dxy = (AT(1, 1, 0) - AT(-1, 1, 0) - AT(1, -1, 0) + AT(-1, -1, 0)) / 4;
        const double dxs = (AT(1, 0, 1) - AT(-1, 0, 1) - AT(1, 0, -1) + AT(-1, 0, -1)) / 4;
        const double dys = (AT(0, 1, 1) - AT(0, -1, 1) - AT(0, 1, -1) + AT(0, -1, -1)) / 4;
#undef AT
        double a[9] = {dxx, dxy, dxs, dxy, dyy, dys, dxs, dys, dss}, x[3] = {-g[0], -g[1], -g[2]};
        int pivot[3], singular;
        lu_factor(a, 3, pivot, &singular);
        if (!singular) lu_solve(a, 3, pivot, x);
        int solved = !singular && isfinite(x[0]) && isfinite(x[1]) && isfinite(x[2]);
        if (!solved) x[0] = x[1] = x[2] = 0.0;
        peak[row] = centre + 0.5 * (g[0] * x[0] + g[1] * x[1] + g[2] * x[2]);
        valid[row] = isfinite(score[row]) && solved && fabs(x[0]) <= max_offset && fabs(x[1]) <= max_offset
                     && fabs(x[2]) <= max_offset;
        const double grid = (double)step[o];
        xy[2 * row] = (((double)col + x[0]) * grid + 0.5) / factor - 0.5;
        xy[2 * row + 1] = (((double)row_in + x[1]) * grid + 0.5) / factor - 0.5;
        size[row] = ((double)size0[o] + ((double)level + x[2]) * (double)size_inc[o]) / factor;
        sign[row] = (double)trace_map[clamp_cell(position, cells)] >= 0 ? 1 : -1;
    }
    return 0;
}
