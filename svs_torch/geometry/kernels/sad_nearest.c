/* Nearest and second-nearest neighbours by SAD (L1) between descriptor sets, for svs_torch.geometry.matching (the
 * no-gradient path of _match_group; the torch path, _allowed + torch.cdist + topk + argmin, stays the reference).
 *
 * The torch path builds the (B, K, K2) mask of allowed candidates (both valid, the same Laplacian sign, inside
 * the epipolar band), writes the whole distance matrix, masks it, and reads it three more times (the two smallest
 * per row, the argmin per column). Here the right descriptors of a pair that can be candidates at all (the valid
 * ones) are put in groups of equal Laplacian sign, transposed, in index order within a group; each left row's
 * distances to its own group only (the others are never allowed: about half the work with the sign gate) are made
 * in one pass over the descriptor dimension, vectorised across the group, and consumed at once with the band
 * test: the row's nearest and second-nearest allowed candidates, and each column's nearest left row. A distance is
 * summed in float32 over d in order, so it can differ from torch.cdist's (another summation order) in the last
 * bits. Candidates are visited in index order, so ties resolve as the torch path's (the first index).
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp (see svs_torch/core/kernels/loader.py).
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "common.h"

/* A valid right descriptor, ordered by its Laplacian sign, then its index. */
typedef struct {
    int64_t sign;
    int64_t index;
} column;

static int by_sign_then_index(const void *a, const void *b) {
    const column *x = a, *y = b;
    if (x->sign != y->sign) return x->sign < y->sign ? -1 : 1;
    return (x->index > y->index) - (x->index < y->index);
}

/* The valid right descriptors of pair b in groups of equal Laplacian sign, in index order within a group
 * (columns[0..n)), transposed into grouped (D, n). Returns n. */
static int64_t group_columns(const float *right, const uint8_t *valid_right, const int64_t *sign_right, int64_t b,
                             int64_t K2, int64_t D, column *columns, float *grouped) {
    int64_t n = 0;
    for (int64_t j = 0; j < K2; ++j) {
        if (valid_right[b * K2 + j]) {
            columns[n].sign = sign_right ? sign_right[b * K2 + j] : 0;
            columns[n].index = j;
            ++n;
        }
    }
    qsort(columns, (size_t)n, sizeof(column), by_sign_then_index);
    for (int64_t p = 0; p < n; ++p) {
        const float *r = right + (b * K2 + columns[p].index) * D;
        for (int64_t d = 0; d < D; ++d) grouped[d * n + p] = r[d];
    }
    return n;
}

/* Left rows [i0, i1) of pair b against its grouped columns: each row's best, second and best_index written, and
 * each column's nearest row among them written to column_best / column_index (+inf / 0 where none; strict <: the
 * first row on ties). distance: scratch of n floats. */
static void match_rows(const float *left, const uint8_t *valid_left, const int64_t *sign_left, const float *y_left,
                       const float *y_right, float band, int64_t b, int64_t K, int64_t K2, int64_t D, int64_t i0,
                       int64_t i1, const column *columns, int64_t n, const float *grouped, float *distance,
                       float *column_best, int64_t *column_index, float *best, float *second, int64_t *best_index) {
    for (int64_t j = 0; j < K2; ++j) {
        column_best[j] = INFINITY;
        column_index[j] = 0;
    }
    for (int64_t i = i0; i < i1; ++i) {
        float first = INFINITY, next = INFINITY;
        int64_t first_index = 0;
        /* The row's group: the columns of its sign (all of them without the sign gate). */
        int64_t start = 0, stop = valid_left[b * K + i] ? n : 0;
        if (sign_left && stop > 0) {
            const int64_t sign = sign_left[b * K + i];
            while (start < n && columns[start].sign < sign) ++start;
            stop = start;
            while (stop < n && columns[stop].sign == sign) ++stop;
        }
        const int64_t width = stop - start;
        const float *l = left + (b * K + i) * D;
        for (int64_t p = 0; p < width; ++p) distance[p] = 0.0f;
        for (int64_t d = 0; d < D; ++d) {
            const float value = l[d];
            const float *restrict group = grouped + d * n + start;
            float *restrict sum = distance;
            for (int64_t p = 0; p < width; ++p) sum[p] += fabsf(value - group[p]);
        }
        for (int64_t p = 0; p < width; ++p) {
            const int64_t j = columns[start + p].index;
            if (y_left && !(fabsf(y_left[b * K + i] - y_right[b * K2 + j]) <= band)) continue;
            const float c = distance[p];
            if (c < first) {
                next = first;
                first = c;
                first_index = j;
            } else if (c < next) {
                next = c;
            }
            if (c < column_best[j]) {
                column_best[j] = c;
                column_index[j] = i;
            }
        }
        best[b * K + i] = first;
        second[b * K + i] = next;
        best_index[b * K + i] = first_index;
    }
}

/* Fewer pairs than threads (guide's one pair a call): each pair's rows in one block per thread, each block with
 * its own column minima, merged in block order, so the first row still wins a tie; the same results as one block. */
static int nearest_by_row_blocks(const float *left, const float *right, const uint8_t *valid_left,
                                 const uint8_t *valid_right, const int64_t *sign_left, const int64_t *sign_right,
                                 const float *y_left, const float *y_right, float band, int64_t B, int64_t K,
                                 int64_t K2, int64_t D, float *best, float *second, int64_t *best_index,
                                 int64_t *back, int threads) {
    column *columns = scratch(K2, sizeof(column));
    float *grouped = scratch(D * K2, sizeof(float));
    float *block_best = scratch(threads * K2, sizeof(float));
    int64_t *block_index = scratch(threads * K2, sizeof(int64_t));
    float *distance = scratch(threads * K2, sizeof(float));
    const int ok = columns && grouped && block_best && block_index && distance;
    for (int64_t b = 0; ok && b < B; ++b) {
        const int64_t n = group_columns(right, valid_right, sign_right, b, K2, D, columns, grouped);
#pragma omp parallel for schedule(static) num_threads(threads)
        for (int t = 0; t < threads; ++t) {
            match_rows(left, valid_left, sign_left, y_left, y_right, band, b, K, K2, D, K * t / threads,
                       K * (t + 1) / threads, columns, n, grouped, distance + (int64_t)t * K2,
                       block_best + (int64_t)t * K2, block_index + (int64_t)t * K2, best, second, best_index);
        }
        for (int64_t j = 0; j < K2; ++j) {
            float nearest = INFINITY;
            int64_t row = 0;
            for (int t = 0; t < threads; ++t) {
                if (block_best[(int64_t)t * K2 + j] < nearest) {
                    nearest = block_best[(int64_t)t * K2 + j];
                    row = block_index[(int64_t)t * K2 + j];
                }
            }
            back[b * K2 + j] = row;
        }
    }
    free(columns);
    free(grouped);
    free(block_best);
    free(block_index);
    free(distance);
    return ok ? 0 : -1;
}

/* left: (B, K, D); right: (B, K2, D); valid_left (B, K), valid_right (B, K2) uint8; sign_left (B, K) and
 * sign_right (B, K2) int64, or both NULL (no sign gate); y_left (B, K) and y_right (B, K2) float32, or both NULL
 * (no band), else candidates need |y_left - y_right| <= band. Writes best, second (B, K) float32 (+inf when there
 * is no allowed candidate or only one), best_index (B, K) int64 (the first on ties; 0 when none), back (B, K2)
 * int64: the left row nearest to each right descriptor among its allowed rows (the first on ties; 0 when none),
 * as torch's argmin over the masked matrix. Pairs are shared among num_threads OpenMP threads, or, with fewer
 * pairs than threads, each pair's rows. Returns -1 when memory could not be had. */
int sad_nearest(const float *left, const float *right, const uint8_t *valid_left, const uint8_t *valid_right,
                const int64_t *sign_left, const int64_t *sign_right, const float *y_left, const float *y_right,
                float band, int64_t B, int64_t K, int64_t K2, int64_t D, float *best, float *second,
                int64_t *best_index, int64_t *back, int64_t num_threads) {
    if (B > 0 && B < num_threads && K > 1)
        return nearest_by_row_blocks(left, right, valid_left, valid_right, sign_left, sign_right, y_left, y_right,
                                     band, B, K, K2, D, best, second, best_index, back,
                                     thread_count(num_threads, K));
    const int threads = thread_count(num_threads, B);
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        float *distance = scratch(K2, sizeof(float));
        float *column_best = scratch(K2, sizeof(float));
        float *grouped = scratch(D * K2, sizeof(float));  /* (D, n): the valid right descriptors, grouped */
        column *columns = scratch(K2, sizeof(column));
        const int ready = scratch_ready(distance && column_best && grouped && columns, &failed);
#pragma omp for schedule(dynamic, 1)
        for (int64_t b = 0; b < B; ++b) {
            if (!ready) continue;
            const int64_t n = group_columns(right, valid_right, sign_right, b, K2, D, columns, grouped);
            match_rows(left, valid_left, sign_left, y_left, y_right, band, b, K, K2, D, 0, K, columns, n, grouped,
                       distance, column_best, back + b * K2, best, second, best_index);
        }
        free(distance);
        free(column_best);
        free(grouped);
        free(columns);
    }
    return failed ? -1 : 0;
}
