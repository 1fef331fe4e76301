/* LU with partial pivoting for the kernels' small dense systems (3 x 3 samples and refits, the keystone's 5 x 5 normal
 * equations, SURF's quadratic fit), shared by row_alignment_fit.c, ground_plane_fit.c and refine_maxima.c. Rows are
 * swapped for the largest pivot (the first of equal ones), as LAPACK's getrf; the arithmetic is not LAPACK's
 * (which the torch paths call), so solutions agree with theirs to about 1e-15 relative, not bit for bit. */
#ifndef SVS_TORCH_KERNELS_SMALL_LU_H
#define SVS_TORCH_KERNELS_SMALL_LU_H

#include <math.h>

/* LU of the n x n row-major a in place; returns the determinant, and *singular where a pivot is exactly 0 (LAPACK's
 * info > 0: that column is then not eliminated, and lu_solve divides by the 0). */
static inline double lu_factor(double *a, int n, int *pivot, int *singular) {
    double det = 1.0;
    *singular = 0;
    for (int j = 0; j < n; ++j) {
        int p = j;
        for (int i = j + 1; i < n; ++i)
            if (fabs(a[i * n + j]) > fabs(a[p * n + j])) p = i;
        pivot[j] = p;
        if (p != j) {
            for (int c = 0; c < n; ++c) {
                const double t = a[j * n + c];
                a[j * n + c] = a[p * n + c];
                a[p * n + c] = t;
            }
            det = -det;
        }
        det *= a[j * n + j];
        if (a[j * n + j] == 0.0) {
            *singular = 1;
            continue;
        }
        const double inverse = 1.0 / a[j * n + j];
        for (int i = j + 1; i < n; ++i) {
            const double l = a[i * n + j] * inverse;
            a[i * n + j] = l;
            for (int c = j + 1; c < n; ++c) a[i * n + c] -= l * a[j * n + c];
        }
    }
    return det;
}

/* Solves with lu_factor's factors: b (n) is overwritten by x. */
static inline void lu_solve(const double *a, int n, const int *pivot, double *b) {
    for (int j = 0; j < n; ++j) {  /* every interchange first: the stored multipliers are those of P a */
        const double t = b[j];
        b[j] = b[pivot[j]];
        b[pivot[j]] = t;
    }
    for (int j = 0; j < n; ++j)
        for (int i = j + 1; i < n; ++i) b[i] -= a[i * n + j] * b[j];
    for (int j = n - 1; j >= 0; --j) {
        b[j] /= a[j * n + j];
        for (int i = 0; i < j; ++i) b[i] -= a[i * n + j] * b[j];
    }
}

#endif
