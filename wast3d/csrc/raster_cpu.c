/*
 * Tile-based front-to-back alpha compositing of projected 2D Gaussians on the CPU, with the
 * analytic backward of the reference 3DGS CUDA rasterizer (Kerbl et al. 2023).
 *
 * Layout of the work: one OpenMP task per tile (16x16 pixels); inside a tile the Gaussians are the
 * outer loop and the tile's pixels the inner, vectorized loop (each pixel a SIMD lane with its own
 * transmittance and "done" mask), as a GPU warp would process them. A tile stops when every pixel
 * is done.
 *
 * Inputs (row-major, contiguous):
 *   means2d [N,2] pixel coordinates (pixel (i,j) centre at (i+.5, j+.5)); conics [N,3] = (a,b,c) of
 *   the inverse 2D covariance; colors [N,C]; opac [N] activated opacity;
 *   isect_gid [M] Gaussian id of every (tile, Gaussian) intersection, sorted by tile then depth;
 *   tile_off [n_tiles+1] start of each tile's run in isect_gid.
 * Per pixel: sigma = .5(a dx^2 + c dy^2) + b dx dy with d = mean - pixel; alpha = min(.99, o e^-sigma);
 *   a Gaussian is skipped when sigma < 0 or alpha < 1/255; compositing stops before a Gaussian that
 *   would bring T below 1e-4. The exponent is clamped at 80 (float exp below -87 gives denormals).
 * Outputs: out [H,W,C] = sum_i c_i alpha_i T_i; T_final [H,W]; last [H,W] = 1 + position (in the
 *   tile's run) of the last blended Gaussian, 0 if none.
 * Backward: per-intersection gradients [M,*] (each intersection belongs to one tile: deterministic,
 *   no atomics); the caller sums them per Gaussian.
 *
 * Compiled twice, REAL=float and REAL=double, with suffixed symbol names.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "fastmath.h"

#define ALPHA_MAX ((REAL)0.99)
#define ALPHA_MIN ((REAL)(1.0 / 255.0))
#define T_MIN ((REAL)1e-4)
#define MAXC 16
#define MAXP 1024 /* tile <= 32 */

typedef struct {
    REAL mx, my, a, b, c, o;
} G2;

static inline G2 load_g(const REAL *means2d, const REAL *conics, const REAL *opac, int32_t i) {
    G2 q = {means2d[2 * i], means2d[2 * i + 1], conics[3 * i], conics[3 * i + 1], conics[3 * i + 2], opac[i]};
    return q;
}

/* lanes [*p0, *p1) of the tile rows that the Gaussian's box (centre my, radius r) reaches: outside the
 * box alpha < 1/255, so skipping them is exact */
static inline int row_span(REAL my, REAL r, int y0, int tile, int *p0, int *p1) {
    int lo = (int)ceil((double)(my - r - (REAL)0.5)) - y0, hi = (int)floor((double)(my + r - (REAL)0.5)) - y0;
    lo = lo < 0 ? 0 : lo;
    hi = hi > tile - 1 ? tile - 1 : hi;
    *p0 = lo * tile;
    *p1 = (hi + 1) * tile;
    return hi >= lo;
}

/* pixel centres of a tile; lanes outside the image get inside[p] = 0 */
static inline int tile_pixels(int t, int tx_n, int tile, int W, int H, REAL *px, REAL *py, REAL *inside) {
    const int x0 = (t % tx_n) * tile, y0 = (t / tx_n) * tile, P = tile * tile;
    for (int p = 0; p < P; ++p) {
        const int x = x0 + p % tile, y = y0 + p / tile;
        px[p] = (REAL)x + (REAL)0.5;
        py[p] = (REAL)y + (REAL)0.5;
        inside[p] = (x < W && y < H) ? (REAL)1 : (REAL)0;
    }
    return P;
}

void FN(raster_fwd)(const REAL *means2d, const REAL *conics, const REAL *colors, const REAL *opac,
                    const REAL *radii, const int32_t *gid, const int64_t *tile_off, int W, int H, int tile, int C,
                    int nthreads, REAL *out, REAL *T_final, int32_t *last) {
    const int tx_n = (W + tile - 1) / tile, ty_n = (H + tile - 1) / tile, n_tiles = tx_n * ty_n;
#pragma omp parallel for schedule(dynamic, 1) num_threads(nthreads)
    for (int t = 0; t < n_tiles; ++t) {
        REAL px[MAXP], py[MAXP], inside[MAXP], T[MAXP], done[MAXP], lastf[MAXP], w[MAXP];
        REAL acc[MAXC][MAXP];
        const int P = tile_pixels(t, tx_n, tile, W, H, px, py, inside);
        for (int p = 0; p < P; ++p) {
            T[p] = 1; lastf[p] = 0; done[p] = 1 - inside[p];
        }
        for (int ch = 0; ch < C; ++ch) memset(acc[ch], 0, sizeof(REAL) * P);
        const int64_t s = tile_off[t], n = tile_off[t + 1] - s;
        const int y0 = (t / tx_n) * tile;
        for (int64_t k = 0; k < n; ++k) {
            const G2 q = load_g(means2d, conics, opac, gid[s + k]);
            const REAL kk = (REAL)(k + 1);
            int p0, p1;
            if (!row_span(q.my, radii[gid[s + k]], y0, tile, &p0, &p1)) continue;
#pragma omp simd
            for (int p = p0; p < p1; ++p) {
                const REAL dx = q.mx - px[p], dy = q.my - py[p];
                const REAL sigma = (REAL)0.5 * (q.a * dx * dx + q.c * dy * dy) + q.b * dx * dy;
                const REAL sc = sigma < 0 ? 0 : (sigma > 80 ? 80 : sigma);
                REAL alpha = q.o * EXPR(-sc);
                alpha = alpha > ALPHA_MAX ? ALPHA_MAX : alpha;
                const int valid = (sigma >= 0) & (alpha >= ALPHA_MIN) & (done[p] == 0);
                const REAL nT = T[p] * (1 - alpha);
                const int term = valid & (nT < T_MIN);
                const int blend = valid & !term;
                w[p] = blend ? alpha * T[p] : 0;
                T[p] = blend ? nT : T[p];
                lastf[p] = blend ? kk : lastf[p];
                done[p] = term ? 1 : done[p];
            }
            const REAL *col = colors + (int64_t)gid[s + k] * C;
            for (int ch = 0; ch < C; ++ch) {
                const REAL cv = col[ch];
                REAL *a = acc[ch];
#pragma omp simd
                for (int p = p0; p < p1; ++p) a[p] += w[p] * cv;
            }
            if ((k & 7) == 7) { /* stop the tile once every pixel is done */
                REAL n_done = 0;
#pragma omp simd reduction(+ : n_done)
                for (int p = 0; p < P; ++p) n_done += done[p];
                if (n_done == (REAL)P) break;
            }
        }
        const int x0 = (t % tx_n) * tile;
        for (int p = 0; p < P; ++p) {
            if (inside[p] == 0) continue;
            const int64_t pix = (int64_t)(y0 + p / tile) * W + x0 + p % tile;
            for (int ch = 0; ch < C; ++ch) out[pix * C + ch] = acc[ch][p];
            T_final[pix] = T[p];
            last[pix] = (int32_t)lastf[p];
        }
    }
}

/* grad_out [H,W,C], grad_T [H,W] -> per-intersection g_means2d [M,2], g_conics [M,3], g_colors [M,C],
 * g_opac [M] (written for every intersection of a tile that has contributors; zero-initialized by the
 * caller). */
void FN(raster_bwd)(const REAL *means2d, const REAL *conics, const REAL *colors, const REAL *opac,
                    const REAL *radii, const int32_t *gid, const int64_t *tile_off, int W, int H, int tile, int C,
                    int nthreads, const REAL *T_final, const int32_t *last, const REAL *grad_out,
                    const REAL *grad_T, REAL *g_means2d, REAL *g_conics, REAL *g_colors, REAL *g_opac) {
    const int tx_n = (W + tile - 1) / tile, ty_n = (H + tile - 1) / tile, n_tiles = tx_n * ty_n;
#pragma omp parallel for schedule(dynamic, 1) num_threads(nthreads)
    for (int t = 0; t < n_tiles; ++t) {
        REAL px[MAXP], py[MAXP], inside[MAXP], T[MAXP], Tf[MAXP], gT[MAXP], lastf[MAXP];
        REAL last_alpha[MAXP], valid[MAXP], alph[MAXP], G[MAXP], w[MAXP], dla[MAXP];
        REAL go[MAXC][MAXP], acc_rec[MAXC][MAXP], last_col[MAXC][MAXP];
        const int P = tile_pixels(t, tx_n, tile, W, H, px, py, inside);
        const int x0 = (t % tx_n) * tile, y0 = (t / tx_n) * tile;
        int kmax = 0;
        for (int p = 0; p < P; ++p) {
            if (inside[p] != 0) {
                const int64_t pix = (int64_t)(y0 + p / tile) * W + x0 + p % tile;
                Tf[p] = T_final[pix];
                gT[p] = grad_T[pix];
                lastf[p] = (REAL)last[pix];
                if (last[pix] > kmax) kmax = last[pix];
                for (int ch = 0; ch < C; ++ch) go[ch][p] = grad_out[pix * C + ch];
            } else {
                Tf[p] = 1; gT[p] = 0; lastf[p] = 0;
                for (int ch = 0; ch < C; ++ch) go[ch][p] = 0;
            }
            T[p] = Tf[p];
            last_alpha[p] = 0;
            for (int ch = 0; ch < C; ++ch) { acc_rec[ch][p] = 0; last_col[ch][p] = 0; }
        }
        const int64_t s = tile_off[t];
        for (int64_t k = kmax - 1; k >= 0; --k) {
            const int64_t m = s + k;
            const G2 q = load_g(means2d, conics, opac, gid[m]);
            const REAL *col = colors + (int64_t)gid[m] * C;
            const REAL kk = (REAL)k;
            int p0, p1;
            if (!row_span(q.my, radii[gid[m]], y0, tile, &p0, &p1)) continue;
            /* A: which pixels this Gaussian was blended into, and the transmittance in front of it */
#pragma omp simd
            for (int p = p0; p < p1; ++p) {
                const REAL dx = q.mx - px[p], dy = q.my - py[p];
                const REAL sigma = (REAL)0.5 * (q.a * dx * dx + q.c * dy * dy) + q.b * dx * dy;
                const REAL sc = sigma < 0 ? 0 : (sigma > 80 ? 80 : sigma);
                const REAL g = EXPR(-sc);
                REAL alpha = q.o * g;
                const REAL clamped = alpha > ALPHA_MAX ? (REAL)1 : (REAL)0;
                alpha = alpha > ALPHA_MAX ? ALPHA_MAX : alpha;
                const int v = (kk < lastf[p]) & (sigma >= 0) & (alpha >= ALPHA_MIN);
                valid[p] = v ? (REAL)1 : (REAL)0;
                T[p] = v ? T[p] / (1 - alpha) : T[p];
                alph[p] = alpha;
                G[p] = v && clamped == 0 ? g : 0; /* alpha = 0.99 does not depend on o, G */
                w[p] = v ? alpha * T[p] : 0;
                dla[p] = 0;
            }
            /* B: colour terms (acc_rec: colour behind this Gaussian, normalized by its T) */
            for (int ch = 0; ch < C; ++ch) {
                const REAL cv = col[ch];
                REAL *ar = acc_rec[ch], *lc = last_col[ch];
                const REAL *gop = go[ch];
                REAL gc = 0;
#pragma omp simd reduction(+ : gc)
                for (int p = p0; p < p1; ++p) {
                    const REAL nr = last_alpha[p] * lc[p] + (1 - last_alpha[p]) * ar[p];
                    ar[p] = valid[p] != 0 ? nr : ar[p];
                    dla[p] += valid[p] * (cv - ar[p]) * gop[p];
                    lc[p] = valid[p] != 0 ? cv : lc[p];
                    gc += w[p] * gop[p];
                }
                g_colors[m * C + ch] = gc;
            }
            /* C: opacity and geometry gradients, reduced over the tile's pixels */
            REAL r_o = 0, r_mx = 0, r_my = 0, r_a = 0, r_b = 0, r_c = 0;
#pragma omp simd reduction(+ : r_o, r_mx, r_my, r_a, r_b, r_c)
            for (int p = p0; p < p1; ++p) {
                /* T_final = prod (1 - alpha_j): d T_final / d alpha = -T_final / (1 - alpha) */
                const REAL d = valid[p] * (dla[p] * T[p] - Tf[p] / (1 - alph[p]) * gT[p]);
                last_alpha[p] = valid[p] != 0 ? alph[p] : last_alpha[p];
                r_o += G[p] * d;
                const REAL dsig = -G[p] * q.o * d; /* dG/dsigma = -G */
                const REAL dx = q.mx - px[p], dy = q.my - py[p];
                r_mx += dsig * (q.a * dx + q.b * dy);
                r_my += dsig * (q.c * dy + q.b * dx);
                r_a += dsig * (REAL)0.5 * dx * dx;
                r_b += dsig * dx * dy;
                r_c += dsig * (REAL)0.5 * dy * dy;
            }
            g_opac[m] = r_o;
            g_means2d[2 * m] = r_mx;
            g_means2d[2 * m + 1] = r_my;
            g_conics[3 * m] = r_a;
            g_conics[3 * m + 1] = r_b;
            g_conics[3 * m + 2] = r_c;
        }
    }
}
