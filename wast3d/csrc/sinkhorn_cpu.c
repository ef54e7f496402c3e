/*
 * Fused log-domain soft-min for Sinkhorn iterations on the CPU, with no N x M buffer.
 *
 *   f_i    = -eps * log sum_j exp(h_j - |x_i - y_j|^2 / (2 eps))          (cost |x-y|^2 / 2, p = 2)
 *   bary_i = sum_j w_ij y_j,  w_ij = softmax_j(h_j - |x_i - y_j|^2 / (2 eps))  (optional)
 *
 * x [N,D] row-major; yT [D,M] (y transposed, so the inner loops run over contiguous j); h [M].
 * Online log-sum-exp over blocks of j. Exponents are clamped at -80 relative to the running max:
 * each clamped term is < 2e-35 of the largest, far below float32 resolution even summed over 1e6
 * terms, and the clamp keeps every exp in the fast, normal range (arguments below about -87 make
 * exp produce denormals, 10-40x slower). The distance is computed directly (not |x|^2 + |y|^2 - 2xy)
 * so that tiny eps with large coordinates does not cancel catastrophically.
 * One OpenMP task per block of rows. Compiled for REAL=float (_f32) and REAL=double (_f64).
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "fastmath.h"

#define BLOCK 256
#define MAXD 16
#define CLAMP_LO (-80.0)



void FN(softmin)(const REAL *x, const REAL *yT, const REAL *h, int64_t N, int64_t M, int D, REAL eps,
                 int nthreads, REAL *f, REAL *bary) {
    const REAL inv2eps = (REAL)0.5 / eps;
#pragma omp parallel for schedule(static) num_threads(nthreads)
    for (int64_t i = 0; i < N; ++i) {
        REAL s[BLOCK];
        REAL xi[MAXD], bsum[MAXD];
        for (int d = 0; d < D; ++d) { xi[d] = x[i * D + d]; bsum[d] = 0; }
        REAL run_max = -INFINITY, run_sum = 0;
        for (int64_t j0 = 0; j0 < M; j0 += BLOCK) {
            const int64_t nb = (M - j0) < BLOCK ? (M - j0) : BLOCK;
            for (int64_t j = 0; j < nb; ++j) s[j] = 0;
            for (int d = 0; d < D; ++d) {
                const REAL *yd = yT + (int64_t)d * M + j0;
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
#pragma omp simd reduction(+ : acc)
            for (int64_t j = 0; j < nb; ++j) {
                REAL a = s[j] - run_max;
                a = a < (REAL)CLAMP_LO ? (REAL)CLAMP_LO : a;
                s[j] = EXPR(a);
                acc += s[j];
            }
            run_sum += acc;
            if (bary) {
                for (int d = 0; d < D; ++d) {
                    const REAL *yd = yT + (int64_t)d * M + j0;
                    REAL b = 0;
#pragma omp simd reduction(+ : b)
                    for (int64_t j = 0; j < nb; ++j) b += s[j] * yd[j];
                    bsum[d] += b;
                }
            }
        }
        f[i] = -eps * (run_max + (REAL)log((double)run_sum));
        if (bary)
            for (int d = 0; d < D; ++d) bary[i * D + d] = bsum[d] / run_sum;
    }
}
