/* Order statistics by quickselect, shared by labelled_select.c and object_depths.c (the dense depth stage's
 * per-object median and percentiles). Selection compares and moves values and does no arithmetic on them, so
 * the order statistics are the sorting torch path's exactly; NaN is not allowed (the callers exclude it). */
#ifndef SVS_TORCH_KERNELS_SELECT_RANK_H
#define SVS_TORCH_KERNELS_SELECT_RANK_H

#include <math.h>
#include <stdint.h>

/* Puts the element of rank k of a[lo, hi) in place, smaller-or-equal ones before it, larger-or-equal after
 * (Hoare partition around a median of three; equal values stop both scans, so runs of ties split evenly). */
static void select_rank(float *a, int64_t lo, int64_t hi, int64_t k) {
    int64_t left = lo, right = hi - 1;
    while (right > left) {
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
        /* Now a[left, j] <= pivot <= a[i, right] and every element between j and i equals the pivot. */
        if (k <= j) right = j;
        else if (k >= i) left = i;
        else return;
    }
}

/* The members of rank floor / ceil of position = q[i] * (float)max(m - 1, 0) (float32, as the torch path
 * computes it) of ``members[0, m)``, for each of the Q quantiles, into below[i] / above[i] (0 when m is 0).
 * Reorders ``members``; ``ranks`` is scratch for 2 Q values. */
static void order_statistics(float *members, int64_t m, const float *q, int64_t Q, int64_t *ranks, float *below,
                             float *above) {
    if (m == 0) {
        for (int64_t i = 0; i < Q; ++i) below[i] = above[i] = 0.0f;
        return;
    }
    /* The wanted ranks in ascending order: each selection then works right of the one before. */
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
    int64_t start = 0;
    for (int64_t i = 0; i < 2 * Q; ++i) {
        int64_t k = ranks[i] < m - 1 ? ranks[i] : m - 1;
        if (k < start) continue; /* a repeated rank: already in place */
        select_rank(members, start, m, k);
        start = k;
    }
    for (int64_t i = 0; i < Q; ++i) {
        const float position = q[i] * last;
        int64_t low = (int64_t)floorf(position), high = (int64_t)ceilf(position);
        below[i] = members[low < m - 1 ? low : m - 1];
        above[i] = members[high < m - 1 ? high : m - 1];
    }
}

#endif
