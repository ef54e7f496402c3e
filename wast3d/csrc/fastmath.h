/* Shared by the C kernels: a branch-free exp that vectorizes, the REAL-generic dispatch and naming.
 *
 * fast_expf(x) for x in [-80, 0]: 2^k * p(r), k = round(x / ln2) by the 1.5 * 2^23 shifter (adding it
 * leaves k in the low mantissa bits: no floorf, no float->int conversion), r = x - k ln2 in
 * [-ln2/2, ln2/2] (Cody-Waite), degree-6 polynomial, 2^k built in the exponent bits; relative error
 * < 1e-7 on [-80, 0] (tests/test_sinkhorn.py). Callers clamp the argument: below about -87 float exp
 * produces denormals (10-40x slower), and at -80 the value (2e-35) is already negligible.
 *
 * fast_expf8: the same on 8 lanes with GCC/Clang vector types, where the bit casts are register moves.
 * The scalar version's memcpy casts left the loops that call it scalar whenever the loop also carries a
 * reduction (the soft-min's exp-and-sum: 4.6 ns per exp, though -fopt-info reported it vectorized);
 * written on vectors it is 0.5 ns. Vector types that the target lacks (no AVX) are split by the
 * compiler, so this stays portable C.
 */
#ifndef WAST3D_FASTMATH_H
#define WAST3D_FASTMATH_H
#include <math.h>
#include <stdint.h>
#include <string.h>

/* exp(r) on [-ln2/2, ln2/2], degree 6 (Horner); r a float or a vector of floats */
#define EXP_POLY(r) \
    ((((((1.9875691500E-4f * (r) + 1.3981999507E-3f) * (r) + 8.3334519073E-3f) * (r) + 4.1665795894E-2f) * (r) + \
       1.6666665459E-1f) * (r) + 5.0000001201E-1f) * (r) * (r) + (r) + 1.0f)

static inline float fast_expf(float x) {
    const float log2e = 1.44269504088896341f, c1 = 0.693359375f, c2 = -2.12194440e-4f;
    const float shifter = 12582912.0f; /* 1.5 * 2^23 */
    float kf = x * log2e + shifter;
    int32_t ki;
    memcpy(&ki, &kf, sizeof ki);
    kf -= shifter;
    const float r = x - kf * c1 - kf * c2;
    const float p = EXP_POLY(r);
    const int32_t bits = (ki - 0x4B400000 + 127) * (1 << 23); /* (k + 127) << 23 */
    float scale;
    memcpy(&scale, &bits, sizeof scale);
    return p * scale;
}

typedef float wast3d_vf8 __attribute__((vector_size(32)));
typedef int32_t wast3d_vi8 __attribute__((vector_size(32)));

static inline wast3d_vf8 fast_expf8(wast3d_vf8 x) {
    const float log2e = 1.44269504088896341f, c1 = 0.693359375f, c2 = -2.12194440e-4f;
    const wast3d_vf8 shifter = (wast3d_vf8){0} + 12582912.0f;
    wast3d_vf8 kf = x * log2e + shifter;
    const wast3d_vi8 ki = (wast3d_vi8)kf;
    kf -= shifter;
    const wast3d_vf8 r = x - kf * c1 - kf * c2;
    const wast3d_vf8 p = EXP_POLY(r);
    const wast3d_vi8 bits = (ki - 0x4B400000 + 127) * (1 << 23);
    return p * (wast3d_vf8)bits;
}

/* max(x, lo) lane by lane, by a bit select (C has no vector ?:) */
static inline wast3d_vf8 vmax_f8(wast3d_vf8 x, float lo) {
    const wast3d_vf8 l = (wast3d_vf8){0} + lo;
    const wast3d_vi8 m = x < l;
    return (wast3d_vf8)(((wast3d_vi8)x & ~m) | ((wast3d_vi8)l & m));
}

static inline double exp_real_d(double x) { return exp(x); }
static inline float exp_real_f(float x) { return fast_expf(x); }
/* float: the fast polynomial; double (reference and gradcheck builds): libm's exp */
#define EXPR(x) _Generic((x), float: exp_real_f, double: exp_real_d)(x)


/* each kernel is compiled twice: REAL=float with symbol suffix _f32, REAL=double with _f64 */
#ifndef REAL
#define REAL float
#define SFX _f32
#endif
#define CAT2(a, b) a##b
#define CAT(a, b) CAT2(a, b)
#define FN(name) CAT(name, SFX)

#endif
