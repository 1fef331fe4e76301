/* The kept regions cut to their interior, for svs_torch.segmentation.interior.region_interiors (the no-gradient
 * path; its torch expression stays the reference).
 *
 * The torch path compares every pixel with every kept slot (a (B, N, H * W) mask), erodes the union with a
 * square, and sums, intersects and reduces that mask four times more: at B = 32 on one thread (the command line's
 * workers) 2.1 ms a 320 x 240 pair, a twentieth of the pipeline. Here each pair is read once per pass: which
 * pixels are kept (any slot's label), their erosion by the square as separable row and column minima over the
 * window clipped to the image (OpenCV's erode, whose border erodes nothing), each slot's pixel and interior counts,
 * and the output, where a kept pixel outside the interior of a cut slot's region becomes 0. A slot is cut where its
 * pair is asked for, it has pixels, and interior >= min_share * total in float32 (as torch compares the int64
 * counts with a Python float times them). Integer labels and counts: the torch path's labels exactly.
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp (svs_torch/core/kernels/loader.py). Loaded
 * through ctypes by svs_torch/segmentation/kernels/__init__.py; pairs are shared among num_threads OpenMP threads.
 */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "common.h"

/* 1 where some slot of the pair holds the pixel's label (slots <= 0 are empty). */
static void kept_pixels(const int64_t *labels, const int64_t *kept, int64_t N, int64_t P, uint8_t *mask) {
    memset(mask, 0, (size_t)P);
    for (int64_t n = 0; n < N; ++n) {
        const int64_t label = kept[n];
        if (label <= 0) continue;
        for (int64_t i = 0; i < P; ++i) mask[i] |= (uint8_t)(labels[i] == label);
    }
}

/* inside = mask eroded by a (2 r + 1)^2 square, the window clipped to the image: rows first (into tmp), then
 * columns. A minimum over a clipped rectangle is the minimum of its rows' clipped minima; each pass ANDs whole
 * rows shifted by one offset at a time (a column outside the image takes no part), which gcc vectorises. */
static void erode_square(const uint8_t *mask, int64_t H, int64_t W, int64_t r, uint8_t *tmp, uint8_t *inside) {
    for (int64_t y = 0; y < H; ++y) {
        const uint8_t *row = mask + y * W;
        uint8_t *eroded = tmp + y * W;
        memcpy(eroded, row, (size_t)W);
        for (int64_t d = 1; d <= r && d < W; ++d) {
            for (int64_t x = 0; x < W - d; ++x) eroded[x] &= row[x + d];
            for (int64_t x = d; x < W; ++x) eroded[x] &= row[x - d];
        }
    }
    for (int64_t y = 0; y < H; ++y) {
        const int64_t y0 = y - r < 0 ? 0 : y - r, y1 = y + r >= H ? H - 1 : y + r;
        uint8_t *eroded = inside + y * W;
        memcpy(eroded, tmp + y0 * W, (size_t)W);
        for (int64_t k = y0 + 1; k <= y1; ++k) {
            const uint8_t *other = tmp + k * W;
            for (int64_t x = 0; x < W; ++x) eroded[x] &= other[x];
        }
    }
}

/* labels (B, H, W) int64; kept (B, N) int64; pairs (B,) bytes, nonzero: cut this pair's regions; radius >= 0 (0:
 * the interior is the region, nothing is cut; the wrapper passes at most max(H, W), as a wider window is clipped to
 * the same); min_share as float32. Writes out (B, H, W) int64.
 * Returns -1 when memory could not be had (the caller runs the torch path). */
int region_interiors(const int64_t *labels, const int64_t *kept, const uint8_t *pairs, int64_t B, int64_t H,
                     int64_t W, int64_t N, int64_t radius, float min_share, int64_t *out, int64_t num_threads) {
    const int64_t P = H * W;
    const int threads = thread_count(num_threads, B);
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        uint8_t *mask = scratch(3 * P + 1, 1);
        int64_t *counts = scratch(2 * N + 1, sizeof(int64_t));
        uint8_t *cut = scratch(N + 1, 1);
        const int ready = scratch_ready(mask != NULL && counts != NULL && cut != NULL, &failed);
#pragma omp for schedule(dynamic, 1)
        for (int64_t b = 0; b < B; ++b) {
            if (!ready || P == 0) continue; /* an empty view: nothing to copy (its data may be a null pointer) */
            const int64_t *source = labels + b * P, *slots = kept + b * N;
            int64_t *target = out + b * P;
            memcpy(target, source, (size_t)P * sizeof(int64_t));
            if (pairs[b] == 0) continue;
            uint8_t *inside = mask + P, *tmp = mask + 2 * P;
            kept_pixels(source, slots, N, P, mask);
            erode_square(mask, H, W, radius, tmp, inside);
            int64_t *total = counts, *interior = counts + N;
            memset(counts, 0, (size_t)(2 * N) * sizeof(int64_t));
            for (int64_t i = 0; i < P; ++i) {
                if (!mask[i]) continue;
                for (int64_t n = 0; n < N; ++n)
                    if (slots[n] > 0 && source[i] == slots[n]) {
                        total[n] += 1;
                        interior[n] += inside[i];
                    }
            }
            int any = 0;
            for (int64_t n = 0; n < N; ++n) {
                cut[n] = (uint8_t)(total[n] > 0 && (float)interior[n] >= min_share * (float)total[n]);
                any |= cut[n];
            }
            if (!any) continue;
            for (int64_t i = 0; i < P; ++i) {
                if (!mask[i] || inside[i]) continue;
                for (int64_t n = 0; n < N; ++n)
                    if (cut[n] && source[i] == slots[n]) {
                        target[i] = 0;
                        break;
                    }
            }
        }
        free(mask);
        free(counts);
        free(cut);
    }
    return failed ? -1 : 0;
}
