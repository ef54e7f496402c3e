/*
 * Fused log-domain soft-min for Sinkhorn iterations on the CPU, with no N x M buffer.
 *
 *   f_i    = -eps * log sum_j exp(h_j - |x_i - y_j|^2 / (2 eps))          (cost |x-y|^2 / 2, p = 2)
 *   bary_i = sum_j w_ij y_j,  w_ij = softmax_j(h_j - |x_i - y_j|^2 / (2 eps))  (optional)
 *
 * Ragged batch of K independent problems (the clusters of eq. 9), packed, no padding:
 * problem k maps rows x[xoff[k] : xoff[k+1]] against columns y[yoff[k] : yoff[k+1]] at its own eps[k].
 * x [R,D] row-major; yT [D,C] (all y packed then transposed, so the inner loops run over contiguous j);
 * h [C]; only the problems listed in active[0:A] are computed (the others' rows of f and bary are not
 * written). One problem (K = 1, xoff = {0, N}, yoff = {0, M}) is the plain soft-min.
 * Online log-sum-exp over blocks of j. Exponents are clamped at -80 relative to the running max:
 * each clamped term is < 2e-35 of the largest, far below float32 resolution even summed over 1e6
 * terms, and the clamp keeps every exp in the fast, normal range (arguments below about -87 make
 * exp produce denormals, 10-40x slower). The distance is computed directly (not |x|^2 + |y|^2 - 2xy)
 * so that tiny eps with large coordinates does not cancel catastrophically.
 * Work items are blocks of ROWS rows of the active problems, handed out dynamically to the threads
 * (problems of very different sizes share the cores without one thread waiting on the largest).
 * Compiled for REAL=float (_f32) and REAL=double (_f64).
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "fastmath.h"

#define BLOCK 256
#define MAXD 16
#define CLAMP_LO (-80.0)

#define ROWS 16

/* one row i against columns [c0, c1) of yT (leading dimension C) */
static inline void FN(softmin_row)(const REAL *xi_, const REAL *yT, int64_t C, const REAL *h, int64_t c0,
                                   int64_t c1, int D, REAL inv2eps, REAL eps, REAL *f, REAL *bary) {
    REAL s[BLOCK];
    REAL xi[MAXD], bsum[MAXD];
    for (int d = 0; d < D; ++d) { xi[d] = xi_[d]; bsum[d] = 0; }
    REAL run_max = -INFINITY, run_sum = 0;
    for (int64_t j0 = c0; j0 < c1; j0 += BLOCK) {
        const int64_t nb = (c1 - j0) < BLOCK ? (c1 - j0) : BLOCK;
        for (int64_t j = 0; j < nb; ++j) s[j] = 0;
        for (int d = 0; d < D; ++d) {
            const REAL *yd = yT + (int64_t)d * C + j0;
            const REAL xd = xi[d];
#pragma omp simd
            for (int64_t j = 0; j < nb; ++j) { const REAL t = xd - yd[j]; s[j] += t * t; }
        }
        REAL bmax = -INFINITY;
#pragma omp simd reduction(max : bmax)
        for (int64_t j = 0; j < nb; ++j) {
            s[j] = h[j0 + j] - s[j] * inv2eps;
            bmax = s[j] > bmax ? s[j] : bmax;
        }
        if (bmax > run_max) {  /* rescale what was summed so far */
            const REAL sc = run_max == -INFINITY ? 0 : (REAL)exp((double)(run_max - bmax));
            run_sum *= sc;
            for (int d = 0; d < D; ++d) bsum[d] *= sc;
            run_max = bmax;
        }
        REAL acc = 0;
        if (sizeof(REAL) == sizeof(float)) {  /* float: 8 lanes at a time (fastmath.h); s[] holds BLOCK */
            const int64_t nv = (nb + 7) & ~(int64_t)7;
            const float rm = (float)run_max;
            wast3d_vf8 acc8 = {0};
            for (int64_t j = nb; j < nv; ++j) s[j] = run_max;  /* defined lanes, zeroed below */
            for (int64_t j = 0; j < nv; j += 8) {
                wast3d_vf8 a;
                memcpy(&a, (const float *)s + j, sizeof a);
                wast3d_vf8 e = fast_expf8(vmax_f8(a - rm, (float)CLAMP_LO));
                if (j + 8 > nb) {  /* lanes past the block's end (never read from y) count zero */
                    const wast3d_vi8 lane = {0, 1, 2, 3, 4, 5, 6, 7};
                    e = (wast3d_vf8)((wast3d_vi8)e & (lane < (int32_t)(nb - j)));
                }
                memcpy((float *)s + j, &e, sizeof e);
                acc8 += e;
            }
            for (int l = 0; l < 8; ++l) acc += acc8[l];
        } else {
#pragma omp simd reduction(+ : acc)
            for (int64_t j = 0; j < nb; ++j) {
                REAL a = s[j] - run_max;
                a = a < (REAL)CLAMP_LO ? (REAL)CLAMP_LO : a;
                s[j] = EXPR(a);
                acc += s[j];
            }
        }
        run_sum += acc;
        if (bary) {
            for (int d = 0; d < D; ++d) {
                const REAL *yd = yT + (int64_t)d * C + j0;
                REAL b = 0;
#pragma omp simd reduction(+ : b)
                for (int64_t j = 0; j < nb; ++j) b += s[j] * yd[j];
                bsum[d] += b;
            }
        }
    }
    *f = -eps * (run_max + (REAL)log((double)run_sum));
    if (bary)
        for (int d = 0; d < D; ++d) bary[d] = bsum[d] / run_sum;
}

/* returns 0, or -1 when the work list could not be allocated */
int FN(softmin_ragged)(const REAL *x, const int64_t *xoff, const REAL *yT, const int64_t *yoff, int64_t C,
                       const REAL *h, const REAL *eps, const int64_t *active, int64_t A, int D, int nthreads,
                       REAL *f, REAL *bary) {
    /* first[a]: index of the first row block of active problem a; blocks numbered over all of them */
    int64_t *first = (int64_t *)malloc((size_t)(A + 1) * sizeof(int64_t));
    if (!first) return -1;
    first[0] = 0;
    for (int64_t a = 0; a < A; ++a) {
        const int64_t k = active[a], n = xoff[k + 1] - xoff[k];
        first[a + 1] = first[a] + (n + ROWS - 1) / ROWS;
    }
    const int64_t T = first[A];
#pragma omp parallel for schedule(dynamic, 1) num_threads(nthreads)
    for (int64_t t = 0; t < T; ++t) {
        int64_t lo = 0, hi = A - 1;  /* the active problem a with first[a] <= t < first[a+1] */
        while (lo < hi) {
            const int64_t mid = (lo + hi + 1) / 2;
            if (first[mid] <= t) lo = mid; else hi = mid - 1;
        }
        const int64_t k = active[lo];
        const int64_t r0 = xoff[k] + (t - first[lo]) * ROWS;
        const int64_t r1 = r0 + ROWS < xoff[k + 1] ? r0 + ROWS : xoff[k + 1];
        const REAL e = eps[k], inv2eps = (REAL)0.5 / e;
        for (int64_t i = r0; i < r1; ++i)
            FN(softmin_row)(x + i * D, yT, C, h, yoff[k], yoff[k + 1], D, inv2eps, e, f + i,
                            bary ? bary + i * D : 0);
    }
    free(first);
    return 0;
}

/* out[i] = exp(x[i]) as the kernels compute it (fast_expf8 / fast_expf for float, libm for double); for the
 * accuracy test */
void FN(exp_array)(const REAL *x, int64_t n, REAL *out) {
    int64_t i = 0;
    if (sizeof(REAL) == sizeof(float))  /* the 8-lane exp the soft-min uses, then the scalar one */
        for (; i + 8 <= n; i += 8) {
            wast3d_vf8 v;
            memcpy(&v, (const float *)x + i, sizeof v);
            v = fast_expf8(v);
            memcpy((float *)out + i, &v, sizeof v);
        }
    for (; i < n; ++i) out[i] = EXPR(x[i]);
}
