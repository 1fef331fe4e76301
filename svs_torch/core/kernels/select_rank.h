/* Order statistics by quickselect, shared by labelled_select.c and object_depths.c (the dense depth stage's
 * per-object median and percentiles) and ground_plane_fit.c (a large cell's median). Selection compares and moves values and does no arithmetic on them, so
 * the order statistics are the sorting torch path's exactly; NaN is not allowed (the callers exclude it). */
#ifndef SVS_TORCH_KERNELS_SELECT_RANK_H
#define SVS_TORCH_KERNELS_SELECT_RANK_H

#include <math.h>
#include <stdint.h>

/* One Hoare partition of a[left, right] (right > left) around a median of three; equal values stop both scans, so
 * runs of ties split evenly. Afterwards a[left, *j] <= pivot <= a[*i, right] and every element between *j and *i
 * equals the pivot. */
static inline void partition(float *a, int64_t left, int64_t right, int64_t *i_out, int64_t *j_out) {
    int64_t middle = left + (right - left) / 2;
    float x = a[left], y = a[middle], z = a[right];
    float pivot = x < y ? (y < z ? y : (x < z ? z : x)) : (x < z ? x : (y < z ? z : y));
    int64_t i = left, j = right;
    while (i <= j) {
        while (a[i] < pivot) ++i;
        while (pivot < a[j]) --j;
        if (i <= j) {
            float t = a[i];
            a[i] = a[j];
            a[j] = t;
            ++i;
            --j;
        }
    }
    *i_out = i;
    *j_out = j;
}

/* Puts the element of rank k of a[lo, hi) in place, smaller-or-equal ones before it, larger-or-equal after. */
static void select_rank(float *a, int64_t lo, int64_t hi, int64_t k) {
    int64_t left = lo, right = hi - 1, i, j;
    while (right > left) {
        partition(a, left, right, &i, &j);
        if (k <= j) right = j;
        else if (k >= i) left = i;
        else return;
    }
}

/* Puts the elements of the ranks ranks[r0, r1) (ascending, each in [lo, hi)) of a[lo, hi) in place, as
 * select_rank does one: each partition splits the wanted ranks between its two sides, and only a side that holds
 * one is partitioned again (numpy's partition with several kth, without a sort). A side is taken by recursion only
 * when both hold ranks, so the depth is at most the number of ranks. */
static void select_ranks(float *a, int64_t lo, int64_t hi, const int64_t *ranks, int64_t r0, int64_t r1) {
    while (r0 < r1 && hi - lo > 1) {
        if (r1 - r0 == 1) {
            select_rank(a, lo, hi, ranks[r0]);
            return;
        }
        int64_t i, j;
        partition(a, lo, hi - 1, &i, &j);
        /* Ranks between j and i are done (their elements equal the pivot). */
        int64_t below = r0, beyond;
        while (below < r1 && ranks[below] <= j) ++below;
        beyond = below;
        while (beyond < r1 && ranks[beyond] < i) ++beyond;
        if (below > r0 && beyond < r1) select_ranks(a, lo, j + 1, ranks, r0, below);
        if (beyond < r1) {
            lo = i;
            r0 = beyond;
        } else {
            hi = j + 1;
            r1 = below;
        }
    }
}

/* The members of rank floor / ceil of position = q[i] * (float)max(m - 1, 0) (float32, as the torch path
 * computes it) of ``members[0, m)``, for each of the Q quantiles, into below[i] / above[i] (0 when m is 0).
 * Reorders ``members``; ``ranks`` is scratch for 2 Q values. All the ranks are found in one multi-rank selection
 * (select_ranks): one after another, each selection passed again over most of what the one before had left (the
 * three quantiles of a real 320 x 240 nearness map: 0.67 -> 0.43 ms). */
static void order_statistics(float *members, int64_t m, const float *q, int64_t Q, int64_t *ranks, float *below,
                             float *above) {
    if (m == 0) {
        for (int64_t i = 0; i < Q; ++i) below[i] = above[i] = 0.0f;
        return;
    }
    /* The wanted ranks in ascending order, each once. */
    const float last = (float)(m - 1);
    for (int64_t i = 0; i < Q; ++i) {
        const float position = q[i] * last;
        ranks[2 * i] = (int64_t)floorf(position);
        ranks[2 * i + 1] = (int64_t)ceilf(position);
    }
    for (int64_t i = 1; i < 2 * Q; ++i)
        for (int64_t j = i; j > 0 && ranks[j - 1] > ranks[j]; --j) {
            int64_t t = ranks[j - 1];
            ranks[j - 1] = ranks[j];
            ranks[j] = t;
        }
    int64_t distinct = 0;
    for (int64_t i = 0; i < 2 * Q; ++i) {
        const int64_t k = ranks[i] < m - 1 ? ranks[i] : m - 1;
        if (distinct == 0 || k > ranks[distinct - 1]) ranks[distinct++] = k;
    }
    select_ranks(members, 0, m, ranks, 0, distinct);
    for (int64_t i = 0; i < Q; ++i) {
        const float position = q[i] * last;
        int64_t low = (int64_t)floorf(position), high = (int64_t)ceilf(position);
        below[i] = members[low < m - 1 ? low : m - 1];
        above[i] = members[high < m - 1 ? high : m - 1];
    }
}

#endif
