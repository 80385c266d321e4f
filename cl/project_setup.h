/* Per-(Gaussian, view) set-up shared by the projector's forward and backward kernels.
 *
 * Compile-time switches (see clgs/ops/projector.py for when each is built):
 *   CONE    cone beam (rays from the source); otherwise parallel beam.
 *   EXACT   closed-form line integral along each pixel's own ray; otherwise the local affine
 *           (R2-Gaussian) splat. Input matrices: EXACT -> packed precision, affine -> packed
 *           covariance, both as (xx, xy, xz, yy, yz, zz).
 *
 * View parameters (VP reals per view, host-computed from Geometry.view_vectors, scene units):
 *   0-2  s: cone: the source; parallel: the detector centre
 *   3-5  eu, 6-8 ev: unit detector axes (u columns, v rows)
 *   9-11 w: unit normal from the source towards the detector (parallel: the ray direction)
 *   12 fx, 13 fy, 14 cx, 15 cy: pixel coordinates of a point with camera coordinates
 *        t = (eu.(x-s), ev.(x-s), w.(x-s)) are (fx tx/tz + cx, fy ty/tz + cy) (cone) or
 *        (fx tx + cx, fy ty + cy) (parallel); cx, cy carry the detector offset
 *   16 |gu|, 17 |gv|: pixel pitch; 18 D: source to detector plane distance (cone)
 *
 * Pixel (iu, iv) has coordinates (u, v) = (iu, iv); every Gaussian gets a centre (uc, vc) in
 * those coordinates and per-pixel quantities are polynomials in du = u - uc, dv = v - vc, which
 * keeps them free of cancellation for small Gaussians far from the source.
 *
 * A Gaussian contributes to the pixels whose ray passes within QCUT = 9 (3 sigma, Mahalanobis
 * squared) of its centre: q <= 9 below. The box holds every such pixel (plus a rounding margin). */
#ifndef CLGS_PROJECT_SETUP_H
#define CLGS_PROJECT_SETUP_H
#include "common.h"
#include "fastexp.h"

/* finite test without a builtin call (builtins are calls on PoCL): x - x is 0 unless x is Inf/NaN */
#define FINITE(x) ((x) - (x) == RC(0.0))
/* Square roots without calls: the OpenCL builtins are function calls on PoCL, and a call in a
 * loop also makes the compiler spill every live vector register around it. SQ (scalar) is the
 * compiler's own square-root instruction; sqrt8 applies it lane by lane, which the compiler
 * turns into one vector square root (correctly rounded, like the builtin). */
#ifdef REAL_DOUBLE
#define SQ(x) __builtin_sqrt(x)
#else
#define SQ(x) __builtin_sqrtf(x)
#endif
inline real8 sqrt8(real8 y)
{
    return (real8)(SQ(y.s0), SQ(y.s1), SQ(y.s2), SQ(y.s3), SQ(y.s4), SQ(y.s5), SQ(y.s6), SQ(y.s7));
}
#define VP 20
#define QCUT 9.0
#define TWO_PI 6.283185307179586
#ifndef NEAR_PLANE
#define NEAR_PLANE 0.2 /* affine cone: cull centres closer than this to the source plane (scene units) */
#endif
/* exact cone: a Gaussian whose KS-sigma extent along the axis clears the source plane is
 * integrated over the whole line (the t > 0 factor erfc(.)/2 differs from 1 by < 1e-8 there);
 * one reaching it "straddles" and is integrated per pixel with the erfc factor. */
#ifdef REAL_DOUBLE
#define KS 10.0
#else
#define KS 6.0
#endif

#ifdef EXACT
#ifdef CONE
#define REC 20
#else
#define REC 8
#endif
#else
#define REC 8
#endif
/* In the render's copies of the records (the tile lists, see preprocess), two slots the render
 * does not read carry the box's first and last row instead (integers, exact in a real): the
 * kappa and amplitude-per-density slots (exact cone), the straddle flag and amplitude-per-density
 * slots (otherwise; the affine set-up writes the rows there straight away, its backward does not
 * read the records). */
#if defined(EXACT) && defined(CONE)
#define ROW0_SLOT 18
#define ROW1_SLOT 19
#else
#define ROW0_SLOT 3
#define ROW1_SLOT 7
#endif

/* LD8G / ST8G (unaligned real8 access), mask1 / mask8 and convert_mask8 come from common.h */

/* 2^t for the splat loops, which keep only lanes with t in [-QCUT/2 log2(e), 0] and select
 * zero for every other lane: whatever comes out on the other lanes (t very negative, -Inf or
 * NaN) is never used, so there is no range handling at all (t <= 0 up to rounding where it is
 * used, and there the integer split below is exact). n = round(t) and f = t - n by adding and
 * taking away 1.5 2^23, where a float's last mantissa bits hold n itself (three operations
 * instead of four for a float-int-float round trip: these loops run one 2^t per pixel row, and
 * every operation there is about 5% of them); 2^f on [-1/2, 1/2] by a degree-5 polynomial
 * fitted for minimal relative error (7.5e-8 in exact arithmetic, 2.4e-7 evaluated in float); the
 * loops fold log2(e) into their own coefficients. (Needs round-to-nearest float additions that
 * are not reassociated: no -cl-fast-relaxed-math.) */
#define LOG2E 1.4426950408889634
#ifdef REAL_DOUBLE
#define splat_exp2_8(t) exp2(t)
#define splat_exp2_16(t) exp2(t)
#else
/* 2^n 2^f for f in [-1/2, 1/2] and an integer n */
#define CLGS_DEFINE_EXP2_SPLIT(W)                                                                 \
    inline float##W exp2_split_##W(float##W f, int##W n)                                          \
    {                                                                                             \
        float##W p = 0.00132764725f;                                                              \
        p = p * f + 0.00967554189f;                                                               \
        p = p * f + 0.0555071309f;                                                                \
        p = p * f + 0.240221202f;                                                                 \
        p = p * f + 0.693146944f;                                                                 \
        p = p * f + 1.00000012f;                                                                  \
        return as_float##W(as_int##W(p) + (n << 23));                                             \
    }
CLGS_DEFINE_EXP2_SPLIT(8)
CLGS_DEFINE_EXP2_SPLIT(16)
#define CLGS_DEFINE_SPLAT_EXP2(W)                                                                 \
    inline float##W splat_exp2_##W(float##W t)                                                    \
    {                                                                                             \
        const float##W y = t + 12582912.0f;                                                       \
        /* y's bits are 1.5 2^23's + n: shifted by 23, only n is left */                          \
        return exp2_split_##W(t - (y - 12582912.0f), as_int##W(y));                               \
    }
#if defined(__AVX512DQ__) && defined(__AVX512VL__) && !defined(PORTABLE_EXP)
/* On AVX-512 CPUs (PoCL compiles for the host, whose features clang announces) two instructions
 * give the same n and f: vreduceps (f = t - rint(t)) and vcvtps2dq (n = rint(t)), one fewer per
 * 2^t (render 4-7 %, backward 2-4 % faster side by side). Bit for bit the same as the portable
 * version above (round to nearest even both ways; tested by building with -DPORTABLE_EXP). The
 * vector types of x86 builtins and of OpenCL do not convert into each other, hence the unions. */
#define CLGS_DEFINE_SPLAT_EXP2_X86(W, RED, CVT)                                                   \
    typedef float v##W##sf_x86 __attribute__((vector_size(4 * W)));                               \
    typedef int v##W##si_x86 __attribute__((vector_size(4 * W)));                                 \
    inline float##W splat_exp2_##W(float##W t)                                                    \
    {                                                                                             \
        union { float##W o; v##W##sf_x86 x; } ut, uf, uz;                                         \
        union { int##W o; v##W##si_x86 x; } un, uzi;                                              \
        ut.o = t;                                                                                 \
        uz.o = (float##W)(0.0f);                                                                  \
        uzi.o = (int##W)(0);                                                                      \
        uf.x = RED;                                                                               \
        un.x = CVT;                                                                               \
        return exp2_split_##W(uf.o, un.o);                                                        \
    }
CLGS_DEFINE_SPLAT_EXP2_X86(8, __builtin_ia32_reduceps256_mask(ut.x, 8, uz.x, (unsigned char)0xff),
                           __builtin_ia32_cvtps2dq256(ut.x))
CLGS_DEFINE_SPLAT_EXP2_X86(16, __builtin_ia32_reduceps512_mask(ut.x, 8, uz.x, (unsigned short)0xffff, 4),
                           __builtin_ia32_cvtps2dq512_mask(ut.x, uzi.x, (unsigned short)0xffff, 4))
#else
CLGS_DEFINE_SPLAT_EXP2(8)
CLGS_DEFINE_SPLAT_EXP2(16)
#endif
#endif
/* dv = v - vc of row v0, reached by adding 1 row by row from the box's first row b0 (<= v0): the
 * splat loops step dv by one vector addition per row (instead of an integer-to-real conversion,
 * a subtraction and a broadcast), and starting from the Gaussian's own first row makes the
 * roundings of those additions (only where v - vc is not exact: centres near the detector's
 * first rows) the same whatever tile or segment the row falls in. */
inline real row_offset(int b0, int v0, real vc)
{
    real d = (real)b0 - vc;
    for (int v = b0; v < v0; v++) d += RC(1.0);
    return d;
}
/* the cut q <= QCUT as a bound on t = -q/2 log2(e) */
#define TCUT RC(-0.5 * QCUT * LOG2E)

typedef struct {
    real3 s, eu, ev, w;
    real fx, fy, cx, cy, gul, gvl, D;
} View;

typedef struct {
    real uc, vc, amp0;            /* centre (pixels), amplitude per unit density (mm) */
    real k0, k1, k2;              /* q = k0 du^2 + 2 k1 du dv + k2 dv^2 (exact cone: numerator N') */
    real a1, a2, a3, a4, a5;      /* exact cone: a' = 1 + 2(a1 du + a2 dv) + a3 du^2 + 2 a4 du dv + a5 dv^2 */
    real d0, d1, d2, d3, d4, d5;  /* exact cone: dd' = d0 + 2(d1 du + d2 dv) + d3 du^2 + 2 d4 du dv + d5 dv^2 */
    real kap;                     /* exact cone: source-to-pixel over source-to-centre ratio */
    int4 box;                     /* inclusive (u0, u1, v0, v1), clipped to the detector */
    int straddle;                 /* exact cone: evaluate per pixel with the erfc factor */
} Splat;

inline View load_view(__global const real *vp, int view)
{
    __global const real *q = vp + (size_t)view * VP;
    View V;
    V.s = (real3)(q[0], q[1], q[2]);
    V.eu = (real3)(q[3], q[4], q[5]);
    V.ev = (real3)(q[6], q[7], q[8]);
    V.w = (real3)(q[9], q[10], q[11]);
    V.fx = q[12]; V.fy = q[13]; V.cx = q[14]; V.cy = q[15];
    V.gul = q[16]; V.gvl = q[17]; V.D = q[18];
    return V;
}

inline real3 symv(const real *S, real3 v)
{
    return (real3)(S[0] * v.x + S[1] * v.y + S[2] * v.z,
                   S[1] * v.x + S[3] * v.y + S[4] * v.z,
                   S[2] * v.x + S[4] * v.y + S[5] * v.z);
}

inline real dot3(real3 a, real3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }

/* Pixel range [ceil(c - r), floor(c + r)] clipped to [0, n-1]; NaN or off-detector -> empty. */
inline int2 pixel_range(real c, real r, int n)
{
    const real m = RC(0.01) + RC(1e-4) * r;
    real lo = c - r - m, hi = c + r + m;
    if (!(lo <= (real)(n - 1)) || !(hi >= RC(0.0))) return (int2)(1, 0);
    lo = lo < RC(0.0) ? RC(0.0) : lo;
    hi = hi > (real)(n - 1) ? (real)(n - 1) : hi;
    int a = (int)lo;
    a += (real)a < lo; /* ceil and floor of numbers in [0, n-1] without builtins */
    return (int2)(a, (int)hi);
}

inline int set_box(Splat *sp, real cu, real cv, real ru, real rv, int U, int V)
{
    const int2 a = pixel_range(cu, ru, U), b = pixel_range(cv, rv, V);
    sp->box = (int4)(a.x, a.y, b.x, b.y);
    return a.x <= a.y && b.x <= b.y;
}

/* 8 Gaussians at once (one per lane): the set-ups that run on real8 across Gaussians */
typedef struct { real8 x, y, z; } vec8;

inline real8 dot8(vec8 a, vec8 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
inline vec8 symv8(const real8 *S, vec8 v)
{
    vec8 r;
    r.x = S[0] * v.x + S[1] * v.y + S[2] * v.z;
    r.y = S[1] * v.x + S[3] * v.y + S[4] * v.z;
    r.z = S[2] * v.x + S[4] * v.y + S[5] * v.z;
    return r;
}

/* pixel_range() on 8 lanes: .lo/.hi in *a / *b, returns the non-empty mask */
inline mask8 pixel_range8(real8 c, real8 r, int n, int8 *a, int8 *b)
{
    const real8 m = RC(0.01) + RC(1e-4) * r;
    real8 lo = c - r - m, hi = c + r + m;
    const mask8 ok = (lo <= (real)(n - 1)) & (hi >= RC(0.0));
    lo = lo < RC(0.0) ? (real8)(RC(0.0)) : lo;
    hi = hi > (real)(n - 1) ? (real8)((real)(n - 1)) : hi;
    lo = ok ? lo : (real8)(RC(0.0)); /* keeps NaN out of the conversions */
    hi = ok ? hi : (real8)(RC(0.0));
    int8 ia = convert_int8(lo);
    ia -= convert_int8(convert_real8(ia) < lo); /* ceil, as in pixel_range */
    *a = ia;
    *b = convert_int8(hi);
    return ok;
}

#ifdef EXACT
/* Fill *sp for Gaussian (p, S = packed precision) in view V. Returns 0 if culled. (The affine
 * set-up is setup_affine8, 8 Gaussians at a time.) */
inline int setup(real3 p, const real *S, View V, real scale, int U, int NV, Splat *sp)
{
    const real3 pm = p - V.s;
    const real tx = dot3(V.eu, pm), ty = dot3(V.ev, pm), tz = dot3(V.w, pm);
    sp->straddle = 0;
    sp->kap = RC(1.0);
    const real3 gu = V.gul * V.eu, gv = V.gvl * V.ev;
    const real3 Pgu = symv(S, gu), Pgv = symv(S, gv);
    const real H00 = dot3(gu, Pgu), H01 = dot3(gu, Pgv), H11 = dot3(gv, Pgv);
#ifndef CONE
    /* ---- exact, parallel: q is the 2D conic K = H - h h^T / a (Schur complement) ---- */
    const real3 Pr = symv(S, V.w);
    const real a = dot3(V.w, Pr);
    if (!(a > RC(0.0))) return 0;
    const real ia = RC(1.0) / a;
    const real hu = dot3(gu, Pr), hv = dot3(gv, Pr);
    sp->k0 = H00 - hu * hu * ia;
    sp->k1 = H01 - hu * hv * ia;
    sp->k2 = H11 - hv * hv * ia;
    const real det = sp->k0 * sp->k2 - sp->k1 * sp->k1;
    if (!(det > RC(0.0))) return 0;
    sp->uc = V.fx * tx + V.cx;
    sp->vc = V.fy * ty + V.cy;
    sp->amp0 = SQ(RC(TWO_PI) * ia) / scale;
    if (!FINITE(sp->amp0)) return 0;
    return set_box(sp, sp->uc, sp->vc, RC(3.0) * SQ(sp->k2 / det), RC(3.0) * SQ(sp->k0 / det), U, NV);
#else
    /* ---- exact, cone ---- */
    sp->amp0 = SQ(RC(TWO_PI)) / scale;
    /* extent along the axis: w^T P^-1 w through the adjugate */
    const real A00 = S[3] * S[5] - S[4] * S[4], A01 = S[2] * S[4] - S[1] * S[5], A02 = S[1] * S[4] - S[2] * S[3];
    const real A11 = S[0] * S[5] - S[2] * S[2], A12 = S[1] * S[2] - S[0] * S[4], A22 = S[0] * S[3] - S[1] * S[1];
    const real detP = S[0] * A00 + S[1] * A01 + S[2] * A02;
    if (!(detP > RC(0.0))) return 0;
    const real3 w = V.w;
    const real sw2 = (A00 * w.x * w.x + A11 * w.y * w.y + A22 * w.z * w.z
                      + RC(2.0) * (A01 * w.x * w.y + A02 * w.x * w.z + A12 * w.y * w.z)) / detP;
    if (!FINITE(sw2)) return 0;
    const int clear = tz * tz > RC(KS * KS) * sw2;
    if (clear && tz < RC(0.0)) return 0; /* wholly behind the source */
    if (clear) {
        const real iz = RC(1.0) / tz;
        const real kap = V.D * iz, ik = RC(1.0) / kap;
        sp->kap = kap;
        sp->uc = V.fx * tx * iz + V.cx;
        sp->vc = V.fy * ty * iz + V.cy;
        const real3 e = -pm;
        const real3 Pe = symv(S, e);
        const real c = dot3(e, Pe);
        const real hu = dot3(gu, Pe), hv = dot3(gv, Pe);
        const real ic = RC(1.0) / c, ikc = ic * ik, ikkc = ikc * ik;
        sp->k0 = (H00 - hu * hu * ic) * ik * ik;
        sp->k1 = (H01 - hu * hv * ic) * ik * ik;
        sp->k2 = (H11 - hv * hv * ic) * ik * ik;
        sp->a1 = -hu * ikc; sp->a2 = -hv * ikc;
        sp->a3 = H00 * ikkc; sp->a4 = H01 * ikkc; sp->a5 = H11 * ikkc;
        sp->d0 = dot3(e, e) * ic; sp->d1 = -dot3(gu, e) * ikc; sp->d2 = -dot3(gv, e) * ikc;
        sp->d3 = dot3(gu, gu) * ikkc; sp->d4 = dot3(gu, gv) * ikkc; sp->d5 = dot3(gv, gv) * ikkc;
        /* footprint: q <= 9  <=>  N' - 9 a' <= 0, the projected 3-sigma ellipsoid (an ellipse) */
        const real M00 = sp->k0 - RC(9.0) * sp->a3, M01 = sp->k1 - RC(9.0) * sp->a4, M11 = sp->k2 - RC(9.0) * sp->a5;
        const real m0 = RC(9.0) * sp->a1, m1 = RC(9.0) * sp->a2;
        const real detM = M00 * M11 - M01 * M01;
        if (detM > RC(0.0) && M00 > RC(0.0) && FINITE(detM) && FINITE(sp->k0) && FINITE(sp->a3)) {
            const real idm = RC(1.0) / detM;
            const real x0 = (M11 * m0 - M01 * m1) * idm, y0 = (M00 * m1 - M01 * m0) * idm;
            const real R = RC(9.0) + m0 * x0 + m1 * y0;
            if (!(R > RC(0.0))) return 0;
            return set_box(sp, sp->uc + x0, sp->vc + y0, SQ(R * M11 * idm), SQ(R * M00 * idm), U, NV);
        }
    }
    /* straddles the source plane (or a numerically degenerate ellipse): whole detector */
    sp->straddle = 1;
    sp->uc = RC(0.0);
    sp->vc = RC(0.0);
    sp->box = (int4)(0, U - 1, 0, NV - 1);
    return 1;
#endif
}

#ifdef CONE
/* setup() of the exact cone for 8 Gaussians (one per lane; p, S and rho per lane), straight into
 * their records: out[0..REC) as preprocess_one writes them, the box in bx (u0, u1, v0, v1).
 * Returns the lanes done here; *fb gets the lanes the scalar setup() must do (straddling the
 * source plane or a degenerate footprint: rare), every other lane is culled. The same arithmetic
 * as setup(), one vector instruction for 8 Gaussians instead of one scalar instruction each. */
inline mask8 setup_exact_cone8(vec8 p, const real8 *S, real8 rh, View V, real scale, int U, int NV, real8 *out,
                               int8 *bx, mask8 *fb)
{
    const real8 zero = (real8)(RC(0.0));
    vec8 pm, e, Pgu, Pgv, Pe;
    pm.x = p.x - V.s.x; pm.y = p.y - V.s.y; pm.z = p.z - V.s.z;
    const real8 tx = V.eu.x * pm.x + V.eu.y * pm.y + V.eu.z * pm.z;
    const real8 ty = V.ev.x * pm.x + V.ev.y * pm.y + V.ev.z * pm.z;
    const real8 tz = V.w.x * pm.x + V.w.y * pm.y + V.w.z * pm.z;
    const real3 gu = V.gul * V.eu, gv = V.gvl * V.ev;
    Pgu.x = S[0] * gu.x + S[1] * gu.y + S[2] * gu.z;
    Pgu.y = S[1] * gu.x + S[3] * gu.y + S[4] * gu.z;
    Pgu.z = S[2] * gu.x + S[4] * gu.y + S[5] * gu.z;
    Pgv.x = S[0] * gv.x + S[1] * gv.y + S[2] * gv.z;
    Pgv.y = S[1] * gv.x + S[3] * gv.y + S[4] * gv.z;
    Pgv.z = S[2] * gv.x + S[4] * gv.y + S[5] * gv.z;
    const real8 H00 = gu.x * Pgu.x + gu.y * Pgu.y + gu.z * Pgu.z;
    const real8 H01 = gu.x * Pgv.x + gu.y * Pgv.y + gu.z * Pgv.z;
    const real8 H11 = gv.x * Pgv.x + gv.y * Pgv.y + gv.z * Pgv.z;
    const real amp0 = SQ(RC(TWO_PI)) / scale;
    const real8 A00 = S[3] * S[5] - S[4] * S[4], A01 = S[2] * S[4] - S[1] * S[5], A02 = S[1] * S[4] - S[2] * S[3];
    const real8 A11 = S[0] * S[5] - S[2] * S[2], A12 = S[1] * S[2] - S[0] * S[4], A22 = S[0] * S[3] - S[1] * S[1];
    const real8 detP = S[0] * A00 + S[1] * A01 + S[2] * A02;
    const real3 w = V.w;
    const real8 sw2 = (A00 * w.x * w.x + A11 * w.y * w.y + A22 * w.z * w.z
                       + RC(2.0) * (A01 * w.x * w.y + A02 * w.x * w.z + A12 * w.y * w.z)) / detP;
    const mask8 valid = (detP > RC(0.0)) & FINITE(sw2);
    const mask8 clear = tz * tz > RC(KS * KS) * sw2;
    /* not clear of the source plane but in front of it: the scalar path (straddle) */
    mask8 keep = valid & clear & (tz >= RC(0.0));
    mask8 back = valid & ~clear;
    const real8 iz = RC(1.0) / tz;
    const real8 kap = V.D * iz, ik = RC(1.0) / kap;
    const real8 uc = V.fx * tx * iz + V.cx, vc = V.fy * ty * iz + V.cy;
    e.x = -pm.x; e.y = -pm.y; e.z = -pm.z;
    Pe.x = S[0] * e.x + S[1] * e.y + S[2] * e.z;
    Pe.y = S[1] * e.x + S[3] * e.y + S[4] * e.z;
    Pe.z = S[2] * e.x + S[4] * e.y + S[5] * e.z;
    const real8 c = e.x * Pe.x + e.y * Pe.y + e.z * Pe.z;
    const real8 hu = gu.x * Pe.x + gu.y * Pe.y + gu.z * Pe.z, hv = gv.x * Pe.x + gv.y * Pe.y + gv.z * Pe.z;
    const real8 ic = RC(1.0) / c, ikc = ic * ik, ikkc = ikc * ik;
    const real8 k0 = (H00 - hu * hu * ic) * ik * ik;
    const real8 k1 = (H01 - hu * hv * ic) * ik * ik;
    const real8 k2 = (H11 - hv * hv * ic) * ik * ik;
    const real8 a1 = -hu * ikc, a2 = -hv * ikc;
    const real8 a3 = H00 * ikkc, a4 = H01 * ikkc, a5 = H11 * ikkc;
    const real8 M00 = k0 - RC(9.0) * a3, M01 = k1 - RC(9.0) * a4, M11 = k2 - RC(9.0) * a5;
    const real8 m0 = RC(9.0) * a1, m1 = RC(9.0) * a2;
    const real8 detM = M00 * M11 - M01 * M01;
    const mask8 good = (detM > RC(0.0)) & (M00 > RC(0.0)) & FINITE(detM) & FINITE(k0) & FINITE(a3);
    back |= keep & ~good; /* a degenerate footprint: the scalar path too */
    keep &= good;
    const real8 idm = RC(1.0) / detM;
    const real8 x0 = (M11 * m0 - M01 * m1) * idm, y0 = (M00 * m1 - M01 * m0) * idm;
    const real8 R = RC(9.0) + m0 * x0 + m1 * y0;
    keep &= R > RC(0.0);
    const real8 Rk = keep ? R : zero; /* keeps NaN out of the square roots of dropped lanes */
    keep &= pixel_range8(uc + x0, sqrt8(Rk * M11 * idm), U, &bx[0], &bx[1]);
    keep &= pixel_range8(vc + y0, sqrt8(Rk * M00 * idm), NV, &bx[2], &bx[3]);
    keep &= convert_mask8((bx[0] <= bx[1]) & (bx[2] <= bx[3])); /* as set_box */
    out[0] = uc; out[1] = vc; out[2] = rh * amp0; out[3] = zero;
    out[4] = RC(-0.5) * k0; out[5] = -k1; out[6] = RC(-0.5) * k2;
    out[7] = a1; out[8] = a2; out[9] = a3; out[10] = a4; out[11] = a5;
    out[12] = (e.x * e.x + e.y * e.y + e.z * e.z) * ic;
    out[13] = -(gu.x * e.x + gu.y * e.y + gu.z * e.z) * ikc;
    out[14] = -(gv.x * e.x + gv.y * e.y + gv.z * e.z) * ikc;
    out[15] = dot3(gu, gu) * ikkc; out[16] = dot3(gu, gv) * ikkc; out[17] = dot3(gv, gv) * ikkc;
    out[18] = kap; out[19] = (real8)(amp0);
    *fb = back;
    return keep;
}
#endif
#endif

#ifndef EXACT
/* ---- affine set-up, 8 Gaussians at once (one per lane) ----
 * Ray-space covariance S3 = T Sigma T^T with T = J W the local affine Jacobian (rows T1, T2,
 * T3); the splat is the conic C = S2^-1 of its top-left 2x2 block S2, with amplitude
 * mu = sqrt(2 pi det S3 / det S2). Done on real8 across Gaussians because one Gaussian's
 * set-up is a few hundred scalar instructions: about 8x fewer this way. Lanes are independent;
 * culled ones get ok = 0 (their other fields are meaningless, possibly NaN). */

typedef struct {
    real8 uc, vc, amp0, k0, k1, k2;
    int8 u0, u1, v0, v1; /* inclusive box, as pixel_range() */
    mask8 ok;            /* -1: kept, 0: culled */
} Splat8;


/* What the affine backward needs besides the splat: ray-space Jacobian rows T1, T2, T3 (S3 =
 * T Sigma T^T), Sigma T_i, the entries and determinants of S3, camera coordinates. */
typedef struct {
    vec8 T1, T2, T3, ST1, ST2, ST3;
    real8 s00, s01, s02, s11, s12, s22, det2, det3;
    real8 tx, ty, iz, il;
} Frame8;

inline Splat8 setup_affine8(vec8 p, const real8 *S, View V, real scale, int U, int NV, Frame8 *f)
{
    Splat8 sp;
    vec8 pm, w, T1, T2, T3;
    pm.x = p.x - V.s.x; pm.y = p.y - V.s.y; pm.z = p.z - V.s.z;
    const real8 tx = V.eu.x * pm.x + V.eu.y * pm.y + V.eu.z * pm.z;
    const real8 ty = V.ev.x * pm.x + V.ev.y * pm.y + V.ev.z * pm.z;
    const real8 tz = V.w.x * pm.x + V.w.y * pm.y + V.w.z * pm.z;
    mask8 ok = (mask8)(-1);
#ifdef CONE
    w.x = (real8)(V.w.x); w.y = (real8)(V.w.y); w.z = (real8)(V.w.z);
    const real8 sw2 = dot8(w, symv8(S, w));
    ok &= (tz > RC(NEAR_PLANE)) & (tz * tz > RC(9.0) * sw2);
    const real8 iz = RC(1.0) / tz;
    const real8 il = RC(1.0) / sqrt8(tx * tx + ty * ty + tz * tz);
    const real8 fxz = V.fx * iz, fyz = V.fy * iz, txz = tx * iz, tyz = ty * iz;
    T1.x = fxz * (V.eu.x - txz * V.w.x); T1.y = fxz * (V.eu.y - txz * V.w.y); T1.z = fxz * (V.eu.z - txz * V.w.z);
    T2.x = fyz * (V.ev.x - tyz * V.w.x); T2.y = fyz * (V.ev.y - tyz * V.w.y); T2.z = fyz * (V.ev.z - tyz * V.w.z);
    T3.x = pm.x * il; T3.y = pm.y * il; T3.z = pm.z * il;
    sp.uc = V.fx * tx * iz + V.cx;
    sp.vc = V.fy * ty * iz + V.cy;
    f->iz = iz;
    f->il = il;
#else
    T1.x = (real8)(V.fx * V.eu.x); T1.y = (real8)(V.fx * V.eu.y); T1.z = (real8)(V.fx * V.eu.z);
    T2.x = (real8)(V.fy * V.ev.x); T2.y = (real8)(V.fy * V.ev.y); T2.z = (real8)(V.fy * V.ev.z);
    T3.x = (real8)(V.w.x); T3.y = (real8)(V.w.y); T3.z = (real8)(V.w.z);
    sp.uc = V.fx * tx + V.cx;
    sp.vc = V.fy * ty + V.cy;
#endif
    const vec8 ST1 = symv8(S, T1), ST2 = symv8(S, T2), ST3 = symv8(S, T3);
    const real8 s00 = dot8(T1, ST1), s01 = dot8(T1, ST2), s02 = dot8(T1, ST3);
    const real8 s11 = dot8(T2, ST2), s12 = dot8(T2, ST3), s22 = dot8(T3, ST3);
    const real8 det2 = s00 * s11 - s01 * s01;
    const real8 det3 = det2 * s22 - s00 * s12 * s12 - s11 * s02 * s02 + RC(2.0) * s01 * s02 * s12;
    ok &= (det2 > RC(0.0)) & (det3 > RC(0.0));
    f->T1 = T1; f->T2 = T2; f->T3 = T3; f->ST1 = ST1; f->ST2 = ST2; f->ST3 = ST3;
    f->s00 = s00; f->s01 = s01; f->s02 = s02; f->s11 = s11; f->s12 = s12; f->s22 = s22;
    f->det2 = det2; f->det3 = det3; f->tx = tx; f->ty = ty;
    const real8 id2 = RC(1.0) / det2;
    sp.k0 = s11 * id2;
    sp.k1 = -s01 * id2;
    sp.k2 = s00 * id2;
    const real8 a2 = RC(TWO_PI) * det3 * id2;
    sp.amp0 = sqrt8(ok ? a2 : (real8)(RC(0.0))) / scale;
    ok &= FINITE(sp.amp0) & FINITE(sp.k0) & FINITE(sp.k2);
    const real8 r0 = ok ? s00 : (real8)(RC(0.0)), r1 = ok ? s11 : (real8)(RC(0.0));
    ok &= pixel_range8(sp.uc, RC(3.0) * sqrt8(r0), U, &sp.u0, &sp.u1);
    ok &= pixel_range8(sp.vc, RC(3.0) * sqrt8(r1), NV, &sp.v0, &sp.v1);
    sp.ok = ok;
    return sp;
}
#endif

/* Straddling Gaussian, exact cone: everything per pixel along the 8 rays of one row segment.
 * Returns val0 (per unit density, with the t > 0 factor F), and what the backward needs. */
inline real8 straddle_eval(real3 p, const real *S, View V, real amp0, real8 u, real v,
                           real8 *w_out, real8 *d_out, real8 *ia_out, real8 *beta_out, real8 *vnf_out)
{
    const real3 gu = V.gul * V.eu, gv = V.gvl * V.ev;
    const real3 D0 = V.D * V.w - V.cx * gu - V.cy * gv + v * gv;
    const real3 e = V.s - p;
    const real3 Pe = symv(S, e);
    real8 d[3];
    d[0] = D0.x + u * gu.x; d[1] = D0.y + u * gu.y; d[2] = D0.z + u * gu.z;
    const real8 Pd0 = S[0] * d[0] + S[1] * d[1] + S[2] * d[2];
    const real8 Pd1 = S[1] * d[0] + S[3] * d[1] + S[4] * d[2];
    const real8 Pd2 = S[2] * d[0] + S[4] * d[1] + S[5] * d[2];
    const real8 a = d[0] * Pd0 + d[1] * Pd1 + d[2] * Pd2;
    const real8 b = Pe.x * d[0] + Pe.y * d[1] + Pe.z * d[2];
    const real8 ia = RC(1.0) / a;
    const real8 t = -b * ia;
    const real8 w0 = e.x + t * d[0], w1 = e.y + t * d[1], w2 = e.z + t * d[2];
    const real8 q = w0 * (Pe.x + t * Pd0) + w1 * (Pe.y + t * Pd1) + w2 * (Pe.z + t * Pd2);
    const real8 dd = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
    const real8 beta = b * sqrt(RC(0.5) * ia);
    const real8 F = RC(0.5) * erfc(beta);
    const real8 vnf = amp0 * sqrt(dd * ia) * fast_exp8(RC(-0.5) * q);
    const real8 vnf_m = (q <= RC(QCUT) ? vnf : (real8)(RC(0.0)));
    w_out[0] = w0; w_out[1] = w1; w_out[2] = w2;
    d_out[0] = d[0]; d_out[1] = d[1]; d_out[2] = d[2];
    *ia_out = ia; *beta_out = beta; *vnf_out = vnf_m;
    return vnf_m * F;
}

#endif
