/* The row fill of invalid dense disparities (svs_torch.depth.block_matching.fill_invalid_rows), shared by
 * fill_invalid_rows.c and object_depths.c. Each row is read twice, right to left (the next valid column) and left
 * to right (the last valid one, and the output):
 *   valid pixel:                   d
 *   valid neighbours on both sides: (dl + dr) / 2 where |dl - dr| <= 1, else min(dl, dr)
 *   one side only:                 that side's value;   none: 0, not reachable
 * The same float32 operations as the torch path, so the same values bit for bit. */
#ifndef SVS_TORCH_KERNELS_FILL_ROW_H
#define SVS_TORCH_KERNELS_FILL_ROW_H

#include <math.h>
#include <stdint.h>

/* One row of W pixels: ``d`` / ``ok`` in, ``out`` / ``reach`` out; ``next`` is scratch for W values. */
static void fill_row(const float *d, const uint8_t *ok, int64_t W, int64_t *next, float *out, uint8_t *reach) {
    int64_t upcoming = W; /* the first valid column at or right of x; W: none */
    for (int64_t x = W - 1; x >= 0; --x) {
        if (ok[x]) upcoming = x;
        next[x] = upcoming;
    }
    int64_t last = -1; /* the last valid column at or left of x; -1: none */
    for (int64_t x = 0; x < W; ++x) {
        if (ok[x]) {
            last = x;
            out[x] = d[x];
            reach[x] = 1;
            continue;
        }
        const int has_left = last >= 0, has_right = next[x] < W;
        if (has_left && has_right) {
            const float from_left = d[last], from_right = d[next[x]];
            /* torch.minimum's: NaN if either is NaN. */
            const float smaller = from_left < from_right || isnan(from_left) ? from_left : from_right;
            out[x] = fabsf(from_left - from_right) <= 1.0f ? (from_left + from_right) / 2.0f : smaller;
        } else if (has_left) {
            out[x] = d[last];
        } else if (has_right) {
            out[x] = d[next[x]];
        } else {
            out[x] = 0.0f;
        }
        reach[x] = (uint8_t)(has_left || has_right);
    }
}

#endif
