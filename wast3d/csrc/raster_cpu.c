/*
 * Tile-based front-to-back alpha compositing of projected 2D Gaussians on the CPU, with the
 * analytic backward of the reference 3DGS CUDA rasterizer (Kerbl et al. 2023), one OpenMP task per
 * 16x16 tile.
 *
 * Inputs (row-major, contiguous):
 *   means2d [N,2] pixel coordinates (pixel (i,j) centre at (i+.5, j+.5)); conics [N,3] = (a,b,c) of
 *   the inverse 2D covariance; colors [N,C]; opac [N] activated opacity;
 *   isect_gid [M] Gaussian id of every (tile, Gaussian) intersection, sorted by tile then depth;
 *   tile_off [n_tiles+1] start of each tile's run in isect_gid.
 * Per pixel: sigma = .5(a dx^2 + c dy^2) + b dx dy with d = mean - pixel; alpha = min(.99, o e^-sigma);
 *   skipped when sigma < 0 or alpha < 1/255 (tested as sigma > log(255 o) before exp: no exp of
 *   large arguments, no denormals); stop before a Gaussian that would bring T below 1e-4.
 * Outputs: out [H,W,C] = sum_i c_i alpha_i T_i; T_final [H,W]; last [H,W] = 1 + position (in the
 *   tile's run) of the last blended Gaussian, 0 if none.
 * Backward: per-intersection gradients [M,*] (each intersection belongs to one tile, so tiles never
 *   write to the same slot: deterministic, no atomics); the caller sums them per Gaussian.
 *
 * Compiled twice, REAL=float and REAL=double, with suffixed symbol names.
 */
#include <math.h>
#include <stdint.h>
#include <string.h>
#include <stdlib.h>

#ifndef REAL
#define REAL float
#define SFX _f32
#endif
#define CAT2(a, b) a##b
#define CAT(a, b) CAT2(a, b)
#define FN(name) CAT(name, SFX)

#define ALPHA_MAX ((REAL)0.99)
#define ALPHA_MIN ((REAL)(1.0 / 255.0))
#define T_MIN ((REAL)1e-4)
#define MAXC 16

typedef struct {
    REAL mx, my, a, b, c, o, logo;
} G2;

static inline void load_tile(const REAL *means2d, const REAL *conics, const REAL *opac, const int32_t *gid,
                             int64_t s, int64_t e, G2 *g) {
    for (int64_t k = s; k < e; ++k) {
        int32_t i = gid[k];
        G2 *q = &g[k - s];
        q->mx = means2d[2 * i]; q->my = means2d[2 * i + 1];
        q->a = conics[3 * i]; q->b = conics[3 * i + 1]; q->c = conics[3 * i + 2];
        q->o = opac[i];
        q->logo = q->o > 0 ? (REAL)log((double)q->o * 255.0) : (REAL)-1;
    }
}

void FN(raster_fwd)(const REAL *means2d, const REAL *conics, const REAL *colors, const REAL *opac,
                    const int32_t *gid, const int64_t *tile_off, int W, int H, int tile, int C,
                    int nthreads, REAL *out, REAL *T_final, int32_t *last) {
    const int tx_n = (W + tile - 1) / tile, ty_n = (H + tile - 1) / tile, n_tiles = tx_n * ty_n;
#pragma omp parallel num_threads(nthreads)
    {
        int64_t cap = 0;
        G2 *g = NULL;
#pragma omp for schedule(dynamic, 1)
        for (int t = 0; t < n_tiles; ++t) {
            const int64_t s = tile_off[t], e = tile_off[t + 1], n = e - s;
            if (n > cap) { free(g); cap = n * 2; g = (G2 *)malloc(sizeof(G2) * cap); }
            if (n > 0) load_tile(means2d, conics, opac, gid, s, e, g);
            const int x0 = (t % tx_n) * tile, y0 = (t / tx_n) * tile;
            for (int py = y0; py < y0 + tile && py < H; ++py) {
                for (int px = x0; px < x0 + tile && px < W; ++px) {
                    const REAL fx = (REAL)px + (REAL)0.5, fy = (REAL)py + (REAL)0.5;
                    REAL T = 1, acc[MAXC];
                    for (int ch = 0; ch < C; ++ch) acc[ch] = 0;
                    int32_t lastk = 0;
                    for (int64_t k = 0; k < n; ++k) {
                        const G2 *q = &g[k];
                        const REAL dx = q->mx - fx, dy = q->my - fy;
                        const REAL sigma = (REAL)0.5 * (q->a * dx * dx + q->c * dy * dy) + q->b * dx * dy;
                        if (sigma < 0 || sigma > q->logo) continue;  /* alpha < 1/255 */
                        REAL alpha = q->o * (REAL)exp(-sigma);
                        if (alpha > ALPHA_MAX) alpha = ALPHA_MAX;
                        if (alpha < ALPHA_MIN) continue;
                        const REAL nT = T * (1 - alpha);
                        if (nT < T_MIN) break;
                        const REAL w = alpha * T;
                        const REAL *col = colors + (int64_t)gid[s + k] * C;
                        for (int ch = 0; ch < C; ++ch) acc[ch] += w * col[ch];
                        T = nT;
                        lastk = (int32_t)(k + 1);
                    }
                    const int64_t p = (int64_t)py * W + px;
                    for (int ch = 0; ch < C; ++ch) out[p * C + ch] = acc[ch];
                    T_final[p] = T;
                    last[p] = lastk;
                }
            }
        }
        free(g);
    }
}

/* grad_out [H,W,C], grad_T [H,W] -> per-intersection g_means2d [M,2], g_conics [M,3], g_colors [M,C],
 * g_opac [M] (must be zero-initialized by the caller). */
void FN(raster_bwd)(const REAL *means2d, const REAL *conics, const REAL *colors, const REAL *opac,
                    const int32_t *gid, const int64_t *tile_off, int W, int H, int tile, int C,
                    int nthreads, const REAL *T_final, const int32_t *last, const REAL *grad_out,
                    const REAL *grad_T, REAL *g_means2d, REAL *g_conics, REAL *g_colors, REAL *g_opac) {
    const int tx_n = (W + tile - 1) / tile, ty_n = (H + tile - 1) / tile, n_tiles = tx_n * ty_n;
#pragma omp parallel num_threads(nthreads)
    {
        int64_t cap = 0;
        G2 *g = NULL;
#pragma omp for schedule(dynamic, 1)
        for (int t = 0; t < n_tiles; ++t) {
            const int64_t s = tile_off[t], e = tile_off[t + 1], n = e - s;
            if (n == 0) continue;
            if (n > cap) { free(g); cap = n * 2; g = (G2 *)malloc(sizeof(G2) * cap); }
            load_tile(means2d, conics, opac, gid, s, e, g);
            const int x0 = (t % tx_n) * tile, y0 = (t / tx_n) * tile;
            for (int py = y0; py < y0 + tile && py < H; ++py) {
                for (int px = x0; px < x0 + tile && px < W; ++px) {
                    const int64_t p = (int64_t)py * W + px;
                    const int32_t lastk = last[p];
                    if (lastk == 0) continue;
                    const REAL fx = (REAL)px + (REAL)0.5, fy = (REAL)py + (REAL)0.5;
                    const REAL Tf = T_final[p], gT = grad_T[p];
                    const REAL *go = grad_out + p * C;
                    REAL T = Tf, acc_rec[MAXC], last_col[MAXC], last_alpha = 0;
                    for (int ch = 0; ch < C; ++ch) { acc_rec[ch] = 0; last_col[ch] = 0; }
                    for (int64_t k = lastk - 1; k >= 0; --k) {
                        const G2 *q = &g[k];
                        const REAL dx = q->mx - fx, dy = q->my - fy;
                        const REAL sigma = (REAL)0.5 * (q->a * dx * dx + q->c * dy * dy) + q->b * dx * dy;
                        if (sigma < 0 || sigma > q->logo) continue;
                        const REAL G = (REAL)exp(-sigma);
                        REAL alpha = q->o * G;
                        int clamped = 0;
                        if (alpha > ALPHA_MAX) { alpha = ALPHA_MAX; clamped = 1; }
                        if (alpha < ALPHA_MIN) continue;
                        T = T / (1 - alpha);  /* transmittance in front of this Gaussian */
                        const int64_t m = s + k;
                        const REAL *col = colors + (int64_t)gid[m] * C;
                        const REAL w = alpha * T;
                        REAL dL_dalpha = 0;
                        for (int ch = 0; ch < C; ++ch) {
                            /* colour accumulated behind this Gaussian, normalized by its T */
                            acc_rec[ch] = last_alpha * last_col[ch] + (1 - last_alpha) * acc_rec[ch];
                            last_col[ch] = col[ch];
                            dL_dalpha += (col[ch] - acc_rec[ch]) * go[ch];
                            g_colors[m * C + ch] += w * go[ch];
                        }
                        dL_dalpha *= T;
                        /* T_final = prod (1 - alpha_j): d T_final / d alpha = -T_final / (1 - alpha) */
                        dL_dalpha += -Tf / (1 - alpha) * gT;
                        last_alpha = alpha;
                        if (clamped) continue;  /* alpha = 0.99 does not depend on o, G */
                        g_opac[m] += G * dL_dalpha;
                        const REAL dL_dG = q->o * dL_dalpha;
                        /* G = exp(-sigma): dG/dsigma = -G */
                        const REAL dL_dsig = -G * dL_dG;
                        g_means2d[2 * m] += dL_dsig * (q->a * dx + q->b * dy);
                        g_means2d[2 * m + 1] += dL_dsig * (q->c * dy + q->b * dx);
                        g_conics[3 * m] += dL_dsig * (REAL)0.5 * dx * dx;
                        g_conics[3 * m + 1] += dL_dsig * dx * dy;
                        g_conics[3 * m + 2] += dL_dsig * (REAL)0.5 * dy * dy;
                    }
                }
            }
        }
        free(g);
    }
}
