/* Each kept object's depth statistics from the dense disparity map, for
 * svs_torch.depth.dense_objects.dense_object_depths (the dense depth stage's last step, the no-gradient path).
 *
 * The torch path crops every pair to the batch's largest box (one gather each for the disparity, its validity and
 * the labels), fills the invalid pixels row by row, converts to depth, takes each slot's order statistics and
 * counts each slot's measured pixels, all over (B, largest box): about twenty passes, and per pair as much work
 * as the batch's largest box (at B = 128 of synthetic scenes, 3.3 ms a pair against 1.7 at B = 32). Here each
 * pair is read once, at its own box, a row at a time:
 *   crop pixel (i, j) of box (x0, y0, w, h) = frame pixel (clamp(y0 + j), clamp(x0 + i))   (replicate border)
 *   fill (optional): fill_row.h on the row's valid pixels;  ok = reachable (or valid, without fill)
 *   den = d + doffs;  ok &= den > 0;  Z = scale / den  (scale = focal * baseline, made by the caller in float32)
 *   ok &= isfinite(Z) && Z > 0
 *   members of slot n: Z where ok and label == slots[n] (> 0);  measured[n]: those that were valid before the fill
 *   in_view[n]: those measured at a frame column >= in_view_from[b, n] (where the whole disparity range the object
 *   is allowed lands inside the right image: DepthConfig.min_object_pixels_in_view)
 * then the members grouped by slot (a counting sort) and each slot's order statistics by quickselect
 * (select_rank.h). The same float32 operations as the torch path,
 * so the same statistics bit for bit (the caller interpolates them with its own float32 ops).
 *
 * Build: cc -O3 -march=native -ffp-contract=off -fPIC -shared -fopenmp. Loaded through ctypes by
 * svs_torch/depth/kernels/__init__.py; pairs are shared among num_threads OpenMP threads.
 */
#include <float.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "common.h"
#include "fill_row.h"
#include "select_rank.h"

static inline int64_t clamp_index(int64_t i, int64_t n) { return i < 0 ? 0 : (i >= n ? n - 1 : i); }
static inline int64_t box_side(int64_t side) { return side > 0 ? side : 0; }

/* One crop row's depths and slots: slot_of[i] is the first slot holding label[i] where the depth is usable, else
 * -1. Simple loops, each of which gcc vectorises (``ok`` is scratch for w flags). */
__attribute__((noinline)) static void depth_row(const float *restrict values, const uint8_t *restrict usable,
                                                const int64_t *restrict label, int64_t w, float scale, float doffs,
                                                const int64_t *restrict slots, int64_t N, float *restrict depth,
                                                uint8_t *restrict ok, int8_t *restrict slot_of) {
    for (int64_t i = 0; i < w; ++i) {
        const float denominator = values[i] + doffs;
        depth[i] = scale / ((usable[i] != 0 && denominator > 0.0f) ? denominator : 1.0f);
    }
    for (int64_t i = 0; i < w; ++i) { /* finite (z <= FLT_MAX: z is never NaN) and positive */
        const float denominator = values[i] + doffs, z = depth[i];
        ok[i] = (uint8_t)((usable[i] != 0) & (denominator > 0.0f) & (z <= FLT_MAX) & (z > 0.0f));
    }
    for (int64_t i = 0; i < w; ++i) slot_of[i] = -1;
    for (int64_t n = N - 1; n >= 0; --n) { /* downwards: the first slot of a repeated label wins */
        const int64_t slot = slots[n];
        const int8_t mark = (int8_t)n;
        if (slot <= 0) continue; /* padding: no member */
        for (int64_t i = 0; i < w; ++i) slot_of[i] = label[i] == slot ? mark : slot_of[i];
    }
    for (int64_t i = 0; i < w; ++i) slot_of[i] = ok[i] ? slot_of[i] : (int8_t)-1;
}

/* ``disparity`` (B, H, W) float32, ``valid`` (B, H, W) uint8, ``labels`` (B, H, W) int64; ``boxes`` (B, 4) x0,
 * y0, width, height; ``slots`` (B, N) int64 (<= 0: padding); ``scale``, ``doffs`` (B,) float32; ``q`` (Q,)
 * float32; ``in_view_from`` (B, N) int64, each slot's first frame column in view. Out: ``count`` (B, N) members,
 * ``measured`` (B, N), ``in_view`` (B, N), ``below`` / ``above`` (B, N, Q). Returns 0, or -1
 * when memory could not be had or N > 126 (a slot's index is kept in 8 bits); the caller then runs the torch path. */
int object_depths(const float *disparity, const uint8_t *valid, const int64_t *labels, int64_t B, int64_t H,
                  int64_t W, const int64_t *boxes, const int64_t *slots, int64_t N, const float *scale,
                  const float *doffs, const int64_t *in_view_from, int64_t fill, const float *q, int64_t Q,
                  int64_t *count, int64_t *measured, int64_t *in_view, float *below, float *above,
                  int64_t num_threads) {
    int64_t largest_w = 0, largest_area = 0;
    for (int64_t b = 0; b < B; ++b) {
        const int64_t w = box_side(boxes[4 * b + 2]), h = box_side(boxes[4 * b + 3]);
        largest_w = w > largest_w ? w : largest_w;
        largest_area = w * h > largest_area ? w * h : largest_area;
    }
    const int threads = thread_count(num_threads, B);
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        /* Per thread: one crop row in (disparity, validity, labels) and out (filled, reachable), the fill's
         * scratch, the pair's depths with their slot (-1: none), and the members sorted by slot. */
        float *row_d = scratch(largest_w, sizeof(float)), *row_filled = scratch(largest_w, sizeof(float));
        uint8_t *row_ok = scratch(largest_w, 1), *row_reach = scratch(largest_w, 1);
        uint8_t *row_usable = scratch(largest_w, 1);
        int64_t *row_label = scratch(largest_w, sizeof(int64_t)), *next = scratch(largest_w, sizeof(int64_t));
        int64_t *ranks = scratch(2 * Q, sizeof(int64_t)), *start = scratch(N + 1, sizeof(int64_t));
        int64_t *first = scratch(N, sizeof(int64_t));
        float *depth = scratch(largest_area, sizeof(float)), *members = scratch(largest_area, sizeof(float));
        int8_t *slot_of = scratch(largest_area, 1);
        uint8_t *measured_of = scratch(largest_area, 1);
        /* N < 127: a slot's index fits the 8 bits of slot_of (else the call fails: the torch path runs). */
        const int ready = scratch_ready(row_d && row_filled && row_ok && row_reach && row_usable && row_label
                                            && next && ranks && start && first && depth && members && slot_of
                                            && measured_of && N < 127,
                                        &failed);
#pragma omp for schedule(dynamic, 1)
        for (int64_t b = 0; b < B; ++b) {
            if (!ready) continue;
            const int64_t x0 = boxes[4 * b], y0 = boxes[4 * b + 1];
            const int64_t w = box_side(boxes[4 * b + 2]), h = box_side(boxes[4 * b + 3]);
            const int64_t *pair_slots = slots + b * N;
            /* A slot repeating an earlier slot's label gets that slot's members: each pixel joins the first. */
            for (int64_t n = 0; n < N; ++n) {
                first[n] = n;
                for (int64_t e = 0; e < n; ++e)
                    if (pair_slots[e] == pair_slots[n]) {
                        first[n] = e;
                        break;
                    }
                count[b * N + n] = measured[b * N + n] = in_view[b * N + n] = 0;
            }
            const float pair_scale = scale[b], pair_doffs = doffs[b];
            const int64_t *view_from = in_view_from + b * N;
            /* The box columns inside the frame, [inside_lo, inside_hi); the others repeat its border column. */
            const int64_t inside_lo = x0 < 0 ? (-x0 < w ? -x0 : w) : 0;
            const int64_t inside_hi = x0 + w > W ? (W - x0 > inside_lo ? W - x0 : inside_lo) : w;
            int64_t p = 0;
            for (int64_t j = 0; j < h; ++j) {
                const int64_t row = b * H * W + clamp_index(y0 + j, H) * W;
                const float *d_row = disparity + row;
                const uint8_t *ok_row = valid + row;
                const int64_t *label_row = labels + row;
                for (int64_t i = 0; i < inside_lo; ++i) { /* left of the frame: its first column */
                    row_d[i] = d_row[0];
                    row_ok[i] = ok_row[0] != 0;
                    row_label[i] = label_row[0];
                }
                for (int64_t i = inside_lo; i < inside_hi; ++i) {
                    row_d[i] = d_row[x0 + i];
                    row_ok[i] = ok_row[x0 + i] != 0;
                    row_label[i] = label_row[x0 + i];
                }
                for (int64_t i = inside_hi; i < w; ++i) { /* right of the frame: its last column */
                    row_d[i] = d_row[W - 1];
                    row_ok[i] = ok_row[W - 1] != 0;
                    row_label[i] = label_row[W - 1];
                }
                const float *values = row_d;
                const uint8_t *usable = row_ok;
                if (fill) {
                    fill_row(row_d, row_ok, w, next, row_filled, row_reach);
                    values = row_filled;
                    usable = row_reach;
                }
                depth_row(values, usable, row_label, w, pair_scale, pair_doffs, pair_slots, N, depth + p,
                          row_usable, slot_of + p);
                /* bit 0: valid before the fill; bit 1: that, and at a frame column in view. */
                for (int64_t i = 0; i < w; ++i)
                    measured_of[p + i] = (uint8_t)(row_ok[i] * (1 + 2 * (slot_of[p + i] >= 0
                                                                         && clamp_index(x0 + i, W)
                                                                                >= view_from[slot_of[p + i]])));
                p += w;
            }
            /* The members grouped by slot (a counting sort), then each slot's order statistics. */
            for (int64_t k = 0; k < p; ++k)
                if (slot_of[k] >= 0) {
                    count[b * N + slot_of[k]] += 1;
                    measured[b * N + slot_of[k]] += measured_of[k] & 1;
                    in_view[b * N + slot_of[k]] += measured_of[k] >> 1;
                }
            start[0] = 0;
            for (int64_t n = 0; n < N; ++n) start[n + 1] = start[n] + count[b * N + n];
            for (int64_t k = 0; k < p; ++k)
                if (slot_of[k] >= 0) members[start[slot_of[k]]++] = depth[k];
            for (int64_t n = 0; n < N; ++n) {
                const int64_t m = count[b * N + n], out = b * N + n;
                order_statistics(members + start[n] - m, m, q, Q, ranks, below + out * Q, above + out * Q);
            }
            for (int64_t n = 0; n < N; ++n)
                if (first[n] != n) {
                    const int64_t from = b * N + first[n], out = b * N + n;
                    count[out] = count[from];
                    measured[out] = measured[from];
                    in_view[out] = in_view[from];
                    for (int64_t i = 0; i < Q; ++i) {
                        below[out * Q + i] = below[from * Q + i];
                        above[out * Q + i] = above[from * Q + i];
                    }
                }
        }
        free(row_d);
        free(row_filled);
        free(row_ok);
        free(row_reach);
        free(row_usable);
        free(row_label);
        free(next);
        free(ranks);
        free(start);
        free(first);
        free(depth);
        free(members);
        free(slot_of);
        free(measured_of);
    }
    return failed ? -1 : 0;
}
