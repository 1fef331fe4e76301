/* One level of SURF's box-filter Hessian, for svs_torch.hessian (the no-gradient path).
 *
 * The eager torch path (hessian._det_trace) reads 32 integral-image corner views and makes about 40
 * elementwise passes over the grid, each through memory; here each grid point is read and finished at once.
 * The arithmetic is _det_trace's, operation for operation, in the same order and in float32 without
 * contraction into FMAs, so the result is bit-identical:
 *   box_i = ((c[4i] - c[4i+1]) - c[4i+2]) + c[4i+3]
 *   dxx = (box_0 - 3 box_1) * lobe,  dyy = (box_2 - 3 box_3) * lobe,  dxy = (((box_4 - box_5) - box_6) + box_7) * gap
 *   det = dxx dyy - (0.9 dxy)^2,  trace = dxx + dyy
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp (see svs_torch/kernels/__init__.py).
 */
#include <stdint.h>

/* corners: 32 pointers to float32 views of shape (B, ny, nx) with strides (batch_stride[k], row_stride[k], 1);
 * det, trace: (B, ny, nx) with strides (out_batch_stride, out_row_stride, 1). The B * ny rows are shared
 * among num_threads OpenMP threads (torch's own pool: see svs_torch/kernels/__init__.py). */
void hessian_level(const float *const *corners, const int64_t *batch_stride, const int64_t *row_stride, int64_t B,
                   int64_t ny, int64_t nx, float inverse_lobe_area, float inverse_dxy_area, float dxy_weight,
                   float *det, float *trace, int64_t out_batch_stride, int64_t out_row_stride,
                   int64_t num_threads) {
    const int64_t rows = B * ny;
    const int threads = num_threads < 1 ? 1 : (int)num_threads;
    /* Threads only for enough work: a parallel region costs a few microseconds. */
#pragma omp parallel for schedule(static) num_threads(threads) if (rows * nx >= 16384)
    for (int64_t r = 0; r < rows; ++r) {
        const int64_t b = r / ny, y = r % ny;
        const float *restrict c[32];
        for (int k = 0; k < 32; ++k) c[k] = corners[k] + b * batch_stride[k] + y * row_stride[k];
        float *restrict d_out = det + b * out_batch_stride + y * out_row_stride;
        float *restrict t_out = trace + b * out_batch_stride + y * out_row_stride;
        /* The outputs never overlap the integral views they are made from. */
#pragma GCC ivdep
        for (int64_t x = 0; x < nx; ++x) {
            float box[8];
            for (int i = 0; i < 8; ++i)
                box[i] = ((c[4 * i][x] - c[4 * i + 1][x]) - c[4 * i + 2][x]) + c[4 * i + 3][x];
            float dxx = (box[0] - 3.0f * box[1]) * inverse_lobe_area;
            float dyy = (box[2] - 3.0f * box[3]) * inverse_lobe_area;
            float dxy = (((box[4] - box[5]) - box[6]) + box[7]) * inverse_dxy_area;
            float weighted = dxy_weight * dxy;
            d_out[x] = dxx * dyy - weighted * weighted;
            t_out[x] = dxx + dyy;
        }
    }
}
