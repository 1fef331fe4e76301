/* Fused SAD block matching with winner-takes-all, for svs_torch.dense (the hard, non-differentiable path).
 *
 * The eager torch path (svs_torch/dense.py, _cost_volume + _winner + _right_winner) makes about 25 passes over
 * a B x D x h x w cost volume; here each output row's costs for every disparity are made and consumed while
 * they sit in cache. The arithmetic is the torch path's, operation for operation, in the same order, so the
 * results are bit-identical:
 *   A(y, x, d) = |L(y, x) - R(y, x + D - 1 - d)|                       (float32, the right crop is D - 1 wider)
 *   V(y, x, d) = ((A(y) + A(y + 1)) + ...) + A(y + K - 1)              (rows summed in order)
 *   C(y, x, d) = ((V(x) + V(x + 1)) + ...) + V(x + K - 1)              (columns summed in order)
 *   C = +inf where d >= count[b] or the right pixel x0 + x - (min_d + d) leaves [0, image_w)
 * then per pixel: the first minimum over d (best, best_cost), the costs at best -+ 1 (clamped to the range),
 * the least cost farther than 1 from best (rival, +inf if none), and the right view's winner
 * C_R(j, k) = C(j + k, k) (first minimum over k; -1 where it is +inf).
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -pthread (no -ffast-math: it would reorder the
 * sums). Loaded through ctypes by svs_torch/sad_kernel.py, which falls back to the torch path without a
 * compiler.
 */
#include <math.h>
#include <pthread.h>
#include <stdint.h>
#include <stdlib.h>

typedef struct {
    const float *left;   /* (B, HL, WL) */
    const float *right;  /* (B, HL, WL + D - 1) */
    int64_t B, HL, WL, D, K;
    const int64_t *x0, *min_d, *image_w, *counts;  /* (B,) each */
    float *best_cost, *before, *after, *rival;     /* (B, H, W) each, H = HL - K + 1, W = WL - K + 1 */
    int64_t *best, *right_best;                    /* (B, H, W) */
    int64_t bands, band_rows;
    int64_t next_task;
    pthread_mutex_t lock;
    int failed;
} Job;

static void run_band(Job *job, int64_t b, int64_t y_begin, int64_t y_end, float *ring, float *vsum, float *cost,
                     float *right_cost) {
    const int64_t HL = job->HL, WL = job->WL, D = job->D, K = job->K;
    const int64_t H = HL - K + 1, W = WL - K + 1, WR = WL + D - 1;
    const float *left = job->left + b * HL * WL;
    const float *right = job->right + b * HL * WR;
    const int64_t count = job->counts[b];
    /* Disparity index d is searched at crop column x when lo(d) <= x < hi(d). */
    const int64_t shift = job->min_d[b] - job->x0[b];
    for (int64_t y = y_begin; y < y_end; ++y) {
        /* Absolute differences of the input rows this output row needs that are not in the ring yet. */
        int64_t first_new = (y == y_begin) ? y : y + K - 1;
        for (int64_t r = first_new; r < y + K; ++r) {
            const float *lrow = left + r * WL;
            const float *rrow = right + r * WR;
            float *slot = ring + (r % K) * D * WL;
            for (int64_t d = 0; d < D; ++d) {
                const float *rr = rrow + (D - 1 - d);
                float *a = slot + d * WL;
                for (int64_t x = 0; x < WL; ++x) a[x] = fabsf(lrow[x] - rr[x]);
            }
        }
        for (int64_t d = 0; d < D; ++d) {
            const float *first = ring + (y % K) * D * WL + d * WL;
            for (int64_t x = 0; x < WL; ++x) vsum[x] = first[x];
            for (int64_t i = 1; i < K; ++i) {
                const float *a = ring + ((y + i) % K) * D * WL + d * WL;
                for (int64_t x = 0; x < WL; ++x) vsum[x] += a[x];
            }
            float *c = cost + d * W;
            for (int64_t x = 0; x < W; ++x) c[x] = vsum[x];
            for (int64_t j = 1; j < K; ++j) {
                const float *v = vsum + j;
                for (int64_t x = 0; x < W; ++x) c[x] += v[x];
            }
            int64_t lo = shift + d, hi = job->image_w[b] + shift + d;
            if (d >= count) lo = W;
            if (lo < 0) lo = 0;
            if (lo > W) lo = W;
            if (hi > W) hi = W;
            if (hi < lo) hi = lo;
            for (int64_t x = 0; x < lo; ++x) c[x] = INFINITY;
            for (int64_t x = hi; x < W; ++x) c[x] = INFINITY;
        }
        int64_t offset = (b * H + y) * W;
        float *best_cost = job->best_cost + offset;
        int64_t *best = job->best + offset;
        for (int64_t x = 0; x < W; ++x) {
            best_cost[x] = cost[x];
            best[x] = 0;
        }
        for (int64_t d = 1; d < D; ++d) {
            const float *c = cost + d * W;
            for (int64_t x = 0; x < W; ++x) {
                int better = c[x] < best_cost[x];
                best_cost[x] = better ? c[x] : best_cost[x];
                best[x] = better ? d : best[x];
            }
        }
        float *before = job->before + offset, *after = job->after + offset, *rival = job->rival + offset;
        for (int64_t x = 0; x < W; ++x) {
            int64_t k = best[x];
            before[x] = cost[(k > 0 ? k - 1 : 0) * W + x];
            after[x] = cost[(k < D - 1 ? k + 1 : D - 1) * W + x];
            rival[x] = INFINITY;
        }
        for (int64_t d = 0; d < D; ++d) {
            const float *c = cost + d * W;
            for (int64_t x = 0; x < W; ++x) {
                int64_t gap = d - best[x];
                int far = gap > 1 || gap < -1;
                rival[x] = (far && c[x] < rival[x]) ? c[x] : rival[x];
            }
        }
        int64_t *right_best = job->right_best + offset;
        for (int64_t x = 0; x < W; ++x) {
            right_cost[x] = cost[x];
            right_best[x] = 0;
        }
        for (int64_t k = 1; k < D && k < W; ++k) {
            const float *c = cost + k * W + k;
            for (int64_t j = 0; j < W - k; ++j) {
                int better = c[j] < right_cost[j];
                right_cost[j] = better ? c[j] : right_cost[j];
                right_best[j] = better ? k : right_best[j];
            }
        }
        for (int64_t x = 0; x < W; ++x)
            if (!isfinite(right_cost[x])) right_best[x] = -1;
    }
}

static void *worker(void *arg) {
    Job *job = (Job *)arg;
    const int64_t D = job->D, K = job->K, WL = job->WL, W = job->WL - job->K + 1;
    float *ring = malloc(sizeof(float) * (size_t)(K * D * WL));
    float *vsum = malloc(sizeof(float) * (size_t)WL);
    float *cost = malloc(sizeof(float) * (size_t)(D * W));
    float *right_cost = malloc(sizeof(float) * (size_t)W);
    if (!ring || !vsum || !cost || !right_cost) {
        pthread_mutex_lock(&job->lock);
        job->failed = 1;
        pthread_mutex_unlock(&job->lock);
    } else {
        const int64_t H = job->HL - K + 1, total = job->B * job->bands;
        for (;;) {
            pthread_mutex_lock(&job->lock);
            int64_t task = job->next_task++;
            pthread_mutex_unlock(&job->lock);
            if (task >= total) break;
            int64_t b = task / job->bands, band = task % job->bands;
            int64_t y0 = band * job->band_rows, y1 = y0 + job->band_rows;
            if (y1 > H) y1 = H;
            if (y0 < y1) run_band(job, b, y0, y1, ring, vsum, cost, right_cost);
        }
    }
    free(ring);
    free(vsum);
    free(cost);
    free(right_cost);
    return NULL;
}

/* Returns 0 on success, -1 when memory or threads could not be had (the caller then uses the torch path). */
int sad_wta(const float *left, const float *right, int64_t B, int64_t HL, int64_t WL, int64_t D, int64_t K,
            const int64_t *x0, const int64_t *min_d, const int64_t *image_w, const int64_t *counts,
            float *best_cost, int64_t *best, float *before, float *after, float *rival, int64_t *right_best,
            int64_t num_threads, int64_t band_rows) {
    if (B <= 0 || HL < K || WL < K || D < 1 || K < 1) return 0;
    Job job = {left, right, B, HL, WL, D, K, x0, min_d, image_w, counts, best_cost, before, after, rival,
               best, right_best, 0, 0, 0, PTHREAD_MUTEX_INITIALIZER, 0};
    const int64_t H = HL - K + 1;
    job.band_rows = band_rows < 1 ? H : band_rows;
    job.bands = (H + job.band_rows - 1) / job.band_rows;
    int64_t tasks = B * job.bands;
    if (num_threads > tasks) num_threads = tasks;
    if (num_threads < 1) num_threads = 1;
    pthread_t threads[64];
    if (num_threads > 64) num_threads = 64;
    int64_t started = 0;
    for (int64_t t = 1; t < num_threads; ++t) {
        if (pthread_create(&threads[t], NULL, worker, &job) != 0) break;
        started = t;
    }
    worker(&job);
    for (int64_t t = 1; t <= started; ++t) pthread_join(threads[t], NULL);
    pthread_mutex_destroy(&job.lock);
    return job.failed ? -1 : 0;
}
