/* Connected components of horizontal runs, for svs_torch.segmentation.components (the no-gradient path of
 * _label_runs and _paint, whose torch form stays the reference and the fallback).
 *
 * The torch path finds the touching runs of consecutive rows by binary search, merges them in rounds of
 * min-hooking and pointer jumping (each round a handful of passes over every run and edge, and a host sync), and
 * paints the label image with a cumulative sum over marks: about 0.6 ms a pair for the 16 masks of a batch of 8
 * at 320x240. Here each image is one task: a sweep over its runs row by row unions every run with the runs of
 * the next row that touch it (two pointers: both rows are in raster order), a union-find whose root is the
 * component's smallest run index (the larger root is hooked under the smaller, as the torch path does), then
 * one pass numbers the components in order of their first run and paints them. The same labels: 1, 2, ... per
 * image in raster order of each region's first pixel.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp. Loaded through ctypes by
 * svs_torch/segmentation/kernels/__init__.py.
 */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "common.h"

static int64_t find_root(int64_t *parent, int64_t i) {
    while (parent[i] != i) {
        parent[i] = parent[parent[i]]; /* path halving: parents only move towards the root */
        i = parent[i];
    }
    return i;
}

static void join(int64_t *parent, int64_t a, int64_t b) {
    a = find_root(parent, a);
    b = find_root(parent, b);
    if (a < b) parent[b] = a;
    else if (b < a) parent[a] = b;
}

/* The first run of ``runs`` (sorted flat starts) at or after flat position ``position``. */
static int64_t first_run_from(const int64_t *start, int64_t runs, int64_t position) {
    int64_t lo = 0, hi = runs;
    while (lo < hi) {
        const int64_t mid = lo + (hi - lo) / 2;
        if (start[mid] < position) lo = mid + 1;
        else hi = mid;
    }
    return lo;
}

/* start, end (R,): the runs' flat start and end (inclusive) positions over a (B, H, W) batch in raster order
 * (svs_torch.segmentation.kernels.find_runs); connectivity 4 or 8. Writes each run's label (R,) (1-based within its
 * image), each image's number of labels (B,), and, when ``labels`` is not NULL, the (B, H, W) label image (0 off
 * the runs). Images are shared among num_threads OpenMP threads. Returns 0, or -1 when memory could not be had. */
int label_runs(const int64_t *start, const int64_t *end, int64_t R, int64_t B, int64_t H, int64_t W,
               int64_t connectivity, int64_t *run_label, int64_t *num_labels, int64_t *labels, int64_t num_threads) {
    int64_t *parent = malloc(sizeof(int64_t) * (size_t)(R > 0 ? R : 1));
    if (!parent) return -1;
    const int64_t area = H * W, reach = connectivity == 8 ? 1 : 0;
    const int threads = thread_count(num_threads, B);
#pragma omp parallel for num_threads(threads) schedule(dynamic, 1)
    for (int64_t b = 0; b < B; ++b) {
        const int64_t lo = first_run_from(start, R, b * area), hi = first_run_from(start, R, (b + 1) * area);
        for (int64_t i = lo; i < hi; ++i) parent[i] = i;
        /* j: the first run of the row below run i that may touch it; it only moves forward. */
        int64_t j = lo;
        for (int64_t i = lo; i < hi; ++i) {
            const int64_t position = start[i] - b * area, y = position / W;
            if (y == H - 1) break; /* the last row has no row below in this image */
            const int64_t x0 = position % W, x1 = (end[i] - b * area) % W;
            const int64_t below = (y + 1) * W + b * area;
            while (j < hi && (start[j] < below || (start[j] < below + W && end[j] - below < x0 - reach))) ++j;
            for (int64_t k = j; k < hi && start[k] < below + W && start[k] - below <= x1 + reach; ++k)
                join(parent, i, k);
        }
        int64_t count = 0;
        for (int64_t i = lo; i < hi; ++i) {
            const int64_t root = find_root(parent, i);
            run_label[i] = root == i ? ++count : run_label[root];
        }
        num_labels[b] = count;
        if (labels) {
            int64_t *image = labels + b * area;
            memset(image, 0, sizeof(int64_t) * (size_t)area);
            for (int64_t i = lo; i < hi; ++i)
                for (int64_t p = start[i]; p <= end[i]; ++p) image[p - b * area] = run_label[i];
        }
    }
    free(parent);
    return 0;
}
