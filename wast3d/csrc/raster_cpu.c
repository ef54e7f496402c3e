/*
 * Tile-based front-to-back alpha compositing of projected 2D Gaussians on the CPU, with the
 * analytic backward of the reference 3DGS CUDA rasterizer (Kerbl et al. 2023).
 *
 * Layout of the work: one OpenMP task per tile (16x16 pixels); inside a tile the Gaussians are the
 * outer loop and the tile's pixels the inner loop, written on 8-lane vector types (each pixel a lane
 * with its own transmittance and "done" mask), as a GPU warp would process them: alpha, exp
 * (fast_expf8 in float, libm's exp lane by lane in double), blending and the backward's reductions run
 * on vectors, the branches as lane masks. A tile stops when every pixel is done.
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

/* 8 lanes of REAL and the matching integer lanes (what a comparison yields: int32 for float, int64 for
 * double). Tile pixel arrays are padded to whole vectors; padding lanes are never valid. */
#define VL 8
typedef REAL vr __attribute__((vector_size(VL * sizeof(REAL))));
typedef __typeof__(_Generic((REAL)0, float: (int32_t)0, double: (int64_t)0)) ireal;
typedef ireal vi __attribute__((vector_size(VL * sizeof(REAL))));
#pragma GCC diagnostic ignored "-Wpsabi" /* 64-byte double vectors without AVX-512: static inline, no ABI */
#define MAXV (MAXP / VL)

static inline vr vbr(REAL x) { return (vr){0} + x; }
static inline vr vsel(vi m, vr a, vr b) { return (vr)((m & (vi)a) | (~m & (vi)b)); }
static inline REAL vsum(vr x) {
    REAL s = 0;
    for (int i = 0; i < VL; ++i) s += x[i];
    return s;
}
static inline int vany(vi m) {
    vi r = m;
    for (int i = 1; i < VL; ++i) r[0] |= m[i];
    return r[0] != 0;
}
static inline vr vexp(vr x) {
    vr r;
    if (sizeof(REAL) == sizeof(float)) {
        wast3d_vf8 y;
        memcpy(&y, &x, sizeof y);
        y = fast_expf8(y);
        memcpy(&r, &y, sizeof y);
    } else {
        for (int i = 0; i < VL; ++i) r[i] = (REAL)exp((double)x[i]);
    }
    return r;
}

/* Per lane of pixels v*VL.. : the Gaussian's sigma (and dx, dy), clamped exponent, and whether the lane
 * lies in [p0, p1) */
typedef struct {
    vr dx, dy, sigma, g;
    vi in;
} Lane;

static inline Lane lane_eval(const G2 *q, const vr *PX, const vr *PY, int v, int p0, int p1) {
    const vi idx = (vi){0, 1, 2, 3, 4, 5, 6, 7} + v * VL;
    Lane l;
    l.in = (idx >= p0) & (idx < p1);
    l.dx = vbr(q->mx) - PX[v];
    l.dy = vbr(q->my) - PY[v];
    l.sigma = (REAL)0.5 * (q->a * l.dx * l.dx + q->c * l.dy * l.dy) + q->b * l.dx * l.dy;
    vr sc = vsel(l.sigma < vbr(0), vbr(0), l.sigma);
    sc = vsel(sc > vbr(80), vbr(80), sc);
    l.g = vexp(-sc);
    return l;
}

/* pixel centres of a tile, padded to whole vectors; lanes outside the image or the tile get inside[p] = 0 */
static inline int tile_pixels(int t, int tx_n, int tile, int W, int H, REAL *px, REAL *py, REAL *inside) {
    const int x0 = (t % tx_n) * tile, y0 = (t / tx_n) * tile, P = tile * tile;
    for (int p = 0; p < (P + VL - 1) / VL * VL; ++p) {
        const int x = x0 + p % tile, y = y0 + p / tile;
        px[p] = (REAL)x + (REAL)0.5;
        py[p] = (REAL)y + (REAL)0.5;
        inside[p] = (p < P && x < W && y < H) ? (REAL)1 : (REAL)0;
    }
    return P;
}

void FN(raster_fwd)(const REAL *means2d, const REAL *conics, const REAL *colors, const REAL *opac,
                    const REAL *radii, const int32_t *gid, const int64_t *tile_off, int W, int H, int tile, int C,
                    int nthreads, REAL *out, REAL *T_final, int32_t *last) {
    const int tx_n = (W + tile - 1) / tile, ty_n = (H + tile - 1) / tile, n_tiles = tx_n * ty_n;
#pragma omp parallel for schedule(dynamic, 1) num_threads(nthreads)
    for (int t = 0; t < n_tiles; ++t) {
        vr PX[MAXV], PY[MAXV], IN[MAXV], T[MAXV], DONE[MAXV], LAST[MAXV], Wt[MAXV];
        vr ACC[MAXC][MAXV];
        const int P = tile_pixels(t, tx_n, tile, W, H, (REAL *)PX, (REAL *)PY, (REAL *)IN);
        const int NV = (P + VL - 1) / VL;
        for (int v = 0; v < NV; ++v) {
            T[v] = vbr(1); LAST[v] = vbr(0); DONE[v] = 1 - IN[v];
            for (int ch = 0; ch < C; ++ch) ACC[ch][v] = vbr(0);
        }
        const int64_t s = tile_off[t], n = tile_off[t + 1] - s;
        const int y0 = (t / tx_n) * tile;
        for (int64_t k = 0; k < n; ++k) {
            const G2 q = load_g(means2d, conics, opac, gid[s + k]);
            const REAL kk = (REAL)(k + 1);
            int p0, p1;
            if (!row_span(q.my, radii[gid[s + k]], y0, tile, &p0, &p1)) continue;
            const int v0 = p0 / VL, v1 = (p1 + VL - 1) / VL;
            vi any = {0};
            for (int v = v0; v < v1; ++v) {
                const Lane l = lane_eval(&q, PX, PY, v, p0, p1);
                vr alpha = q.o * l.g;
                alpha = vsel(alpha > vbr(ALPHA_MAX), vbr(ALPHA_MAX), alpha);
                const vi valid = l.in & (l.sigma >= vbr(0)) & (alpha >= vbr(ALPHA_MIN)) & (DONE[v] == vbr(0));
                const vr nT = T[v] * (1 - alpha);
                const vi term = valid & (nT < vbr(T_MIN));
                const vi blend = valid & ~term;
                Wt[v] = vsel(blend, alpha * T[v], vbr(0));
                T[v] = vsel(blend, nT, T[v]);
                LAST[v] = vsel(blend, vbr(kk), LAST[v]);
                DONE[v] = vsel(term, vbr(1), DONE[v]);
                any |= blend;
            }
            if (vany(any)) {
                const REAL *col = colors + (int64_t)gid[s + k] * C;
                for (int ch = 0; ch < C; ++ch) {
                    const REAL cv = col[ch];
                    for (int v = v0; v < v1; ++v) ACC[ch][v] += Wt[v] * cv;
                }
            }
            if ((k & 7) == 7) { /* stop the tile once every pixel is done */
                vr n_done = vbr(0);
                for (int v = 0; v < NV; ++v) n_done += DONE[v];
                if (vsum(n_done) == (REAL)(NV * VL)) break;
            }
        }
        const int x0 = (t % tx_n) * tile;
        const REAL *Tp = (const REAL *)T, *Lp = (const REAL *)LAST, *Ip = (const REAL *)IN;
        for (int p = 0; p < P; ++p) {
            if (Ip[p] == 0) continue;
            const int64_t pix = (int64_t)(y0 + p / tile) * W + x0 + p % tile;
            for (int ch = 0; ch < C; ++ch) out[pix * C + ch] = ((const REAL *)ACC[ch])[p];
            T_final[pix] = Tp[p];
            last[pix] = (int32_t)Lp[p];
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
        vr PX[MAXV], PY[MAXV], IN[MAXV], T[MAXV], Tf[MAXV], GT[MAXV], LASTF[MAXV];
        vr LAST_A[MAXV], VALID[MAXV], ALPH[MAXV], G[MAXV], Wt[MAXV], DLA[MAXV];
        vr GO[MAXC][MAXV], ACC_REC[MAXC][MAXV], LAST_COL[MAXC][MAXV];
        const int P = tile_pixels(t, tx_n, tile, W, H, (REAL *)PX, (REAL *)PY, (REAL *)IN);
        const int NV = (P + VL - 1) / VL;
        REAL *tf = (REAL *)Tf, *gt = (REAL *)GT, *lf = (REAL *)LASTF;
        const REAL *inside = (const REAL *)IN;
        const int x0 = (t % tx_n) * tile, y0 = (t / tx_n) * tile;
        int kmax = 0;
        for (int p = 0; p < NV * VL; ++p) {
            if (inside[p] != 0) {
                const int64_t pix = (int64_t)(y0 + p / tile) * W + x0 + p % tile;
                tf[p] = T_final[pix];
                gt[p] = grad_T[pix];
                lf[p] = (REAL)last[pix];
                if (last[pix] > kmax) kmax = last[pix];
                for (int ch = 0; ch < C; ++ch) ((REAL *)GO[ch])[p] = grad_out[pix * C + ch];
            } else {
                tf[p] = 1; gt[p] = 0; lf[p] = 0;
                for (int ch = 0; ch < C; ++ch) ((REAL *)GO[ch])[p] = 0;
            }
        }
        for (int v = 0; v < NV; ++v) {
            T[v] = Tf[v];
            LAST_A[v] = vbr(0);
            for (int ch = 0; ch < C; ++ch) { ACC_REC[ch][v] = vbr(0); LAST_COL[ch][v] = vbr(0); }
        }
        const int64_t s = tile_off[t];
        for (int64_t k = kmax - 1; k >= 0; --k) {
            const int64_t m = s + k;
            const G2 q = load_g(means2d, conics, opac, gid[m]);
            const REAL *col = colors + (int64_t)gid[m] * C;
            const vr kk = vbr((REAL)k);
            int p0, p1;
            if (!row_span(q.my, radii[gid[m]], y0, tile, &p0, &p1)) continue;
            const int v0 = p0 / VL, v1 = (p1 + VL - 1) / VL;
            /* A: which pixels this Gaussian was blended into, and the transmittance in front of it */
            vi any = {0};
            for (int v = v0; v < v1; ++v) {
                const Lane l = lane_eval(&q, PX, PY, v, p0, p1);
                const vr alpha0 = q.o * l.g;
                const vi clamped = alpha0 > vbr(ALPHA_MAX);
                const vr alpha = vsel(clamped, vbr(ALPHA_MAX), alpha0);
                const vi ok = l.in & (kk < LASTF[v]) & (l.sigma >= vbr(0)) & (alpha >= vbr(ALPHA_MIN));
                VALID[v] = vsel(ok, vbr(1), vbr(0));
                T[v] = vsel(ok, T[v] / (1 - alpha), T[v]);
                ALPH[v] = alpha;
                G[v] = vsel(ok & ~clamped, l.g, vbr(0)); /* alpha = 0.99 does not depend on o, G */
                Wt[v] = vsel(ok, alpha * T[v], vbr(0));
                DLA[v] = vbr(0);
                any |= ok;
            }
            if (!vany(any)) continue; /* blended into no pixel: its gradients stay zero */
            /* B: colour terms (ACC_REC: colour behind this Gaussian, normalized by its T) */
            for (int ch = 0; ch < C; ++ch) {
                const vr cv = vbr(col[ch]);
                vr *ar = ACC_REC[ch], *lc = LAST_COL[ch];
                const vr *gop = GO[ch];
                vr gc = vbr(0);
                for (int v = v0; v < v1; ++v) {
                    const vi ok = VALID[v] != vbr(0);
                    const vr nr = LAST_A[v] * lc[v] + (1 - LAST_A[v]) * ar[v];
                    ar[v] = vsel(ok, nr, ar[v]);
                    DLA[v] += VALID[v] * (cv - ar[v]) * gop[v];
                    lc[v] = vsel(ok, cv, lc[v]);
                    gc += Wt[v] * gop[v];
                }
                g_colors[m * C + ch] = vsum(gc);
            }
            /* C: opacity and geometry gradients, reduced over the tile's pixels */
            vr r_o = vbr(0), r_mx = vbr(0), r_my = vbr(0), r_a = vbr(0), r_b = vbr(0), r_c = vbr(0);
            for (int v = v0; v < v1; ++v) {
                /* T_final = prod (1 - alpha_j): d T_final / d alpha = -T_final / (1 - alpha) */
                const vr d = VALID[v] * (DLA[v] * T[v] - Tf[v] / (1 - ALPH[v]) * GT[v]);
                LAST_A[v] = vsel(VALID[v] != vbr(0), ALPH[v], LAST_A[v]);
                r_o += G[v] * d;
                const vr dsig = -G[v] * q.o * d; /* dG/dsigma = -G */
                const vr dx = vbr(q.mx) - PX[v], dy = vbr(q.my) - PY[v];
                r_mx += dsig * (q.a * dx + q.b * dy);
                r_my += dsig * (q.c * dy + q.b * dx);
                r_a += dsig * (REAL)0.5 * dx * dx;
                r_b += dsig * dx * dy;
                r_c += dsig * (REAL)0.5 * dy * dy;
            }
            g_opac[m] = vsum(r_o);
            g_means2d[2 * m] = vsum(r_mx);
            g_means2d[2 * m + 1] = vsum(r_my);
            g_conics[3 * m] = vsum(r_a);
            g_conics[3 * m + 1] = vsum(r_b);
            g_conics[3 * m + 2] = vsum(r_c);
        }
    }
}
