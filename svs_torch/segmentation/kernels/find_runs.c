/* Horizontal runs of a batch of binary images, for svs_torch.segmentation.components (the no-gradient path of
 * _find_runs, whose torch form stays the reference and the fallback).
 *
 * The torch path clones the mask twice, ANDs shifted copies, clears the joined pixels and turns both maps into
 * positions with nonzero: about eight passes over the whole batch (16 images of 320x240 each segmentation) for a
 * few thousand runs. Here each row is read once to count its runs and once more to write them, rows split over
 * the threads: the same start and end positions (flat, inclusive) in the same raster order.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp. Loaded through ctypes by
 * svs_torch/segmentation/kernels/__init__.py.
 */
#include <stdint.h>
#include <string.h>

#include "common.h"

/* Eight pixels of a row as one word (memcpy: any alignment), and that word when all eight are set. */
static inline uint64_t eight(const uint8_t *pixels) {
    uint64_t word;
    memcpy(&word, pixels, sizeof word);
    return word;
}
#define ALL_SET 0x0101010101010101ULL

/* Whether pixels x - 1 and x of a row are in one run: both set and, given a value row, of equal value. */
static inline int joined(const uint8_t *row, const int64_t *value_row, int64_t x) {
    return row[x - 1] && row[x] && (!value_row || value_row[x - 1] == value_row[x]);
}

/* foreground: contiguous (rows, W) uint8, nonzero where set (a torch bool's bytes); value: (rows, W) int64 or NULL
 * (with it a run also ends where the value changes). With start NULL, writes each row's number of runs to counts
 * (rows,); otherwise counts holds each row's first output slot (the exclusive prefix sum of the counts) and the
 * runs' flat start and end (inclusive) positions are written to start and end. Returns 0. */
int find_runs(const uint8_t *foreground, const int64_t *value, int64_t rows, int64_t W, int64_t *counts,
              int64_t *start, int64_t *end, int64_t num_threads) {
    const int threads = thread_count(num_threads, rows);
#pragma omp parallel for num_threads(threads) schedule(static)
    for (int64_t r = 0; r < rows; ++r) {
        const uint8_t *row = foreground + r * W;
        const int64_t *value_row = value ? value + r * W : 0;
        if (!start) {  /* a run starts at each set pixel not joined to its left neighbour; branch-free */
            /* Any nonzero byte is set, as the writing pass below reads them: a bool tensor viewed from other
             * bytes (a uint8 mask) must count the runs it writes, or the writes overrun the counted slots. */
            int64_t n = W > 0 ? row[0] != 0 : 0;
            if (value_row)
                for (int64_t x = 1; x < W; ++x)
                    n += (row[x] != 0) & !((row[x - 1] != 0) & (value_row[x - 1] == value_row[x]));
            else
                for (int64_t x = 1; x < W; ++x) n += (row[x] != 0) & (row[x - 1] == 0);
            counts[r] = n;
            continue;
        }
        int64_t slot = counts[r];
        if (value_row) {
            for (int64_t x = 0; x < W; ++x) {
                if (!row[x]) continue;
                if (!(x > 0 && joined(row, value_row, x))) start[slot] = r * W + x;
                if (!(x + 1 < W && joined(row, value_row, x + 1))) end[slot++] = r * W + x;
            }
            continue;
        }
        /* A mask alone: run to run, eight pixels at a time through background and through run interiors. */
        int64_t x = 0;
        while (x < W) {
            while (x + 8 <= W && eight(row + x) == 0) x += 8;
            while (x < W && !row[x]) ++x;
            if (x == W) break;
            start[slot] = r * W + x;
            while (x + 9 <= W && eight(row + x + 1) == ALL_SET) x += 8;
            while (x + 1 < W && row[x + 1]) ++x;
            end[slot++] = r * W + x;
            ++x;
        }
    }
    return 0;
}
