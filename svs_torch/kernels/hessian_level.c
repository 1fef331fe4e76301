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
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -pthread (see svs_torch/kernels/__init__.py).
 */
#include <pthread.h>
#include <stdint.h>

typedef struct {
    const float *const *corners;
    const int64_t *batch_stride, *row_stride;
    int64_t B, ny, nx;
    float inverse_lobe_area, inverse_dxy_area, dxy_weight;
    float *det, *trace;
    int64_t out_batch_stride, out_row_stride;
    int64_t first_row, end_row; /* rows of the flattened (B * ny) grid this task makes */
} Level;

static void *level_rows(void *argument) {
    const Level *job = argument;
    for (int64_t r = job->first_row; r < job->end_row; ++r) {
        const int64_t b = r / job->ny, y = r % job->ny;
        const float *restrict c[32];
        for (int k = 0; k < 32; ++k) c[k] = job->corners[k] + b * job->batch_stride[k] + y * job->row_stride[k];
        float *restrict d_out = job->det + b * job->out_batch_stride + y * job->out_row_stride;
        float *restrict t_out = job->trace + b * job->out_batch_stride + y * job->out_row_stride;
        const float lobe = job->inverse_lobe_area, gap = job->inverse_dxy_area, weight = job->dxy_weight;
        /* The outputs never overlap the integral views they are made from. */
#pragma GCC ivdep
        for (int64_t x = 0; x < job->nx; ++x) {
            float box[8];
            for (int i = 0; i < 8; ++i)
                box[i] = ((c[4 * i][x] - c[4 * i + 1][x]) - c[4 * i + 2][x]) + c[4 * i + 3][x];
            float dxx = (box[0] - 3.0f * box[1]) * lobe;
            float dyy = (box[2] - 3.0f * box[3]) * lobe;
            float dxy = (((box[4] - box[5]) - box[6]) + box[7]) * gap;
            float weighted = weight * dxy;
            d_out[x] = dxx * dyy - weighted * weighted;
            t_out[x] = dxx + dyy;
        }
    }
    return NULL;
}

/* corners: 32 pointers to float32 views of shape (B, ny, nx) with strides (batch_stride[k], row_stride[k], 1);
 * det, trace: (B, ny, nx) with strides (out_batch_stride, out_row_stride, 1). The B * ny rows are split into
 * num_threads equal runs (each point costs the same), one per thread; this thread makes the first. */
void hessian_level(const float *const *corners, const int64_t *batch_stride, const int64_t *row_stride, int64_t B,
                   int64_t ny, int64_t nx, float inverse_lobe_area, float inverse_dxy_area, float dxy_weight,
                   float *det, float *trace, int64_t out_batch_stride, int64_t out_row_stride,
                   int64_t num_threads) {
    const int64_t rows = B * ny;
    /* A thread is worth starting only for enough work (about 20 us of it per 4096 points). */
    int64_t tasks = num_threads < 1 ? 1 : (num_threads > 64 ? 64 : num_threads);
    if (rows * nx < 4096 * tasks) tasks = 1;
    Level jobs[64];
    pthread_t threads[64];
    int started[64] = {0};
    for (int64_t t = 0; t < tasks; ++t) {
        jobs[t] = (Level){corners, batch_stride, row_stride, B, ny, nx, inverse_lobe_area, inverse_dxy_area,
                          dxy_weight, det, trace, out_batch_stride, out_row_stride,
                          rows * t / tasks, rows * (t + 1) / tasks};
    }
    for (int64_t t = 1; t < tasks; ++t) started[t] = pthread_create(&threads[t], NULL, level_rows, &jobs[t]) == 0;
    level_rows(&jobs[0]);
    for (int64_t t = 1; t < tasks; ++t) {
        if (started[t]) pthread_join(threads[t], NULL);
        else level_rows(&jobs[t]); /* no thread to be had: this one makes its rows */
    }
}
