/* L1 and SSIM of rendered projections a (B, H, W) against a fixed target b, with the gradient of
 * lambda_l1 * mean|a - b| + lambda_ssim * mean SSIM with respect to a (clgs/ops/ssim.py).
 *
 * SSIM as clgs/fit/losses.py: separable 11-tap Gaussian window, zero padding, constants C1, C2. The
 * target's blurred mean mu_b and second moment bb are cached by the host (one per view).
 *
 * Host defines: REAL, WT0 (centre weight) .. WT5 (outermost), SC1, SC2 (the SSIM constants).
 *
 * Layouts (all row-major; nseg = ceil(W / 8) segments of 8 pixels per row):
 *   a, out         (B, H, W) as given (rows need not be 8-aligned: unaligned vector access,
 *                  masked in the last segment of a row)
 *   b, mub, bbm    (B, H, nseg) real8, the target and its maps padded with zeros to 8 columns
 *   S, T           (B, H + 10, nseg, 3) real8 scratch: image row y at padded row y + 5; rows 0-4
 *                  and H+5..H+9 hold zeros (the vertical pass's zero padding, never written)
 *   rows           (2, B, H): per-row sums of |a - b| (written by ssim_h) and of the SSIM map
 *                  (ssim_v), summed on the host in a fixed order (deterministic means, no atomics);
 *                  B is the global size along the second axis
 *
 * Passes (one work-item per band of RB rows of one image, real8 over 8 columns):
 *   ssim_h     horizontal pass of (a, a*a, a*b) into S; row sums of |a - b|
 *   ssim_v     vertical pass -> mu_a, aa, ab; SSIM map and its row sums; when asked, the
 *              per-pixel coefficients of the SSIM's gradient wrt (mu_a, aa, ab) and their
 *              horizontal pass into T (the window is symmetric, so the filter is self-adjoint)
 *   ssim_grad  vertical pass of T, combined per pixel with a, b and the weights into dL/da
 * The horizontal pass slides over a row with three segments in registers (previous, current,
 * next: the 5-pixel reach fits in one segment either side) and builds the shifted vectors with
 * swizzles; builtins (fabs, select, vload8) are avoided, they are calls on PoCL. */
#include "common.h"

#ifndef RB
#define RB 8
#endif
#ifndef WT0 /* the host always defines these; the defaults (window 11, sigma 1.5, C1 = 0.01^2,
               C2 = 0.03^2) let the file build on its own, e.g. when checking an installation */
#define WT0 0.26601171f
#define WT1 0.21300554f
#define WT2 0.10936068f
#define WT3 0.03600077f
#define WT4 0.00759876f
#define WT5 0.00102838f
#define SC1 0.0001f
#define SC2 0.0009f
#endif
/* RC, LD8G and ST8G come from common.h */
#ifdef REAL_DOUBLE
#define AS_BITS8 as_long8
#define AS_REAL8 as_double8
#define SIGN_BITS ((long)0x8000000000000000UL)
#define ONE_BITS ((long)0x3ff0000000000000L)
#else
#define AS_BITS8 as_int8
#define AS_REAL8 as_float8
#define SIGN_BITS ((int)0x80000000U)
#define ONE_BITS ((int)0x3f800000)
#endif

inline real8 abs8(real8 x) { return AS_REAL8(AS_BITS8(x) & ~SIGN_BITS); }

/* sign(x) in {-1, 0, 1} (torch.sign; the gradient of |x|) */
inline real8 sign8(real8 x)
{
    return AS_REAL8(((AS_BITS8(x) & SIGN_BITS) | ONE_BITS) & (x != RC(0.0)));
}

inline real hsum8(real8 v) { return ((v.s0 + v.s4) + (v.s2 + v.s6)) + ((v.s1 + v.s5) + (v.s3 + v.s7)); }

/* the first n lanes of v (n < 8), zero elsewhere */
inline real8 keep8(real8 v, int n)
{
    const real z = RC(0.0);
    return (real8)(n > 0 ? v.s0 : z, n > 1 ? v.s1 : z, n > 2 ? v.s2 : z, n > 3 ? v.s3 : z, n > 4 ? v.s4 : z,
                   n > 5 ? v.s5 : z, n > 6 ? v.s6 : z, z);
}

/* 8 reals from p, of which n are inside the row (zero beyond) */
inline real8 load8(__global const real *p, int n)
{
    if (n >= 8)
        return LD8G(p);
    const real z = RC(0.0);
    return (real8)(n > 0 ? p[0] : z, n > 1 ? p[1] : z, n > 2 ? p[2] : z, n > 3 ? p[3] : z, n > 4 ? p[4] : z,
                   n > 5 ? p[5] : z, n > 6 ? p[6] : z, z);
}

inline void store8(__global real *p, real8 v, int n)
{
    if (n >= 8) {
        ST8G(p) = v;
        return;
    }
    if (n > 0) p[0] = v.s0;
    if (n > 1) p[1] = v.s1;
    if (n > 2) p[2] = v.s2;
    if (n > 3) p[3] = v.s3;
    if (n > 4) p[4] = v.s4;
    if (n > 5) p[5] = v.s5;
    if (n > 6) p[6] = v.s6;
}

/* the 11-tap filter along a row at segment c, given the segments either side (p before, n after) */
inline real8 hblur(real8 p, real8 c, real8 n)
{
    const real8 m1 = (real8)(p.s7, c.s0123, c.s456), p1 = (real8)(c.s1234, c.s567, n.s0);
    const real8 m2 = (real8)(p.s67, c.s0123, c.s45), p2 = (real8)(c.s2345, c.s67, n.s01);
    const real8 m3 = (real8)(p.s567, c.s0123, c.s4), p3 = (real8)(c.s3456, c.s7, n.s012);
    const real8 m4 = (real8)(p.s4567, c.s0123), p4 = (real8)(c.s4567, n.s0123);
    const real8 m5 = (real8)(p.s3, p.s4567, c.s012), p5 = (real8)(c.s5, c.s67, n.s0123, n.s4);
    return RC(WT0) * c + RC(WT1) * (m1 + p1) + RC(WT2) * (m2 + p2) + RC(WT3) * (m3 + p3) + RC(WT4) * (m4 + p4) +
           RC(WT5) * (m5 + p5);
}

/* the 11-tap filter along a column: p points at the centre row, rows are st real8 apart */
inline real8 vblur(__global const real8 *p, size_t st)
{
    return RC(WT0) * p[0] + RC(WT1) * (p[-(long)st] + p[st]) + RC(WT2) * (p[-2 * (long)st] + p[2 * st]) +
           RC(WT3) * (p[-3 * (long)st] + p[3 * st]) + RC(WT4) * (p[-4 * (long)st] + p[4 * st]) +
           RC(WT5) * (p[-5 * (long)st] + p[5 * st]);
}

__kernel void ssim_h(const int H, const int W, const int nseg, __global const real *a, __global const real8 *b,
                     __global real8 *S, __global real *rows)
{
    const int img = get_global_id(1);
    const int y0 = get_global_id(0) * RB;
    const int y1 = y0 + RB < H ? y0 + RB : H;
    for (int y = y0; y < y1; y++) {
        __global const real *ar = a + ((size_t)img * H + y) * W;
        __global const real8 *br = b + ((size_t)img * H + y) * nseg;
        __global real8 *so = S + ((size_t)img * (H + 10) + y + 5) * nseg * 3;
        const real8 zero = RC(0.0);
        real8 p0 = zero, p1 = zero, p2 = zero;
        real8 av = load8(ar, W), bv = br[0];
        real8 c0 = av, c1 = av * av, c2 = av * bv;
        real8 acc = abs8(av - bv);
        for (int s = 0; s < nseg; s++) {
            real8 n0 = zero, n1 = zero, n2 = zero;
            if (s + 1 < nseg) {
                av = load8(ar + 8 * (s + 1), W - 8 * (s + 1));
                bv = br[s + 1];
                n0 = av;
                n1 = av * av;
                n2 = av * bv;
                acc += abs8(av - bv);
            }
            so[3 * s] = hblur(p0, c0, n0);
            so[3 * s + 1] = hblur(p1, c1, n1);
            so[3 * s + 2] = hblur(p2, c2, n2);
            p0 = c0; p1 = c1; p2 = c2;
            c0 = n0; c1 = n1; c2 = n2;
        }
        rows[(size_t)img * H + y] = hsum8(acc);
    }
}

__kernel void ssim_v(const int H, const int W, const int nseg, const int grad, __global const real8 *S,
                     __global const real8 *mub, __global const real8 *bbm, __global real8 *T,
                     __global real *rows)
{
    const int img = get_global_id(1);
    const int y0 = get_global_id(0) * RB;
    const int y1 = y0 + RB < H ? y0 + RB : H;
    const size_t st = (size_t)nseg * 3;
    const real c1 = RC(SC1), c2 = RC(SC2), two = RC(2.0);
    for (int y = y0; y < y1; y++) {
        __global const real8 *sc = S + ((size_t)img * (H + 10) + y + 5) * st;
        __global real8 *to = T + ((size_t)img * (H + 10) + y + 5) * st;
        __global const real8 *mr = mub + ((size_t)img * H + y) * nseg;
        __global const real8 *br = bbm + ((size_t)img * H + y) * nseg;
        const real8 zero = RC(0.0);
        real8 acc = zero;
        real8 p0 = zero, p1 = zero, p2 = zero, c0 = zero, c1v = zero, c2v = zero;
        for (int s = 0; s <= nseg; s++) {
            real8 n0 = zero, n1 = zero, n2 = zero;
            if (s < nseg) {
                const real8 ma = vblur(sc + 3 * s, st), aa = vblur(sc + 3 * s + 1, st), ab = vblur(sc + 3 * s + 2, st);
                const real8 mb = mr[s], bb = br[s];
                const real8 a1 = two * ma * mb + c1, a2 = two * (ab - ma * mb) + c2;
                const real8 b1 = ma * ma + mb * mb + c1, b2 = (aa - ma * ma) + (bb - mb * mb) + c2;
                const real8 q = RC(1.0) / (b1 * b2);
                real8 sv = a1 * a2 * q;
                const int nv = W - 8 * s;
                if (nv < 8)
                    sv = keep8(sv, nv);
                acc += sv;
                if (grad) {
                    /* d SSIM / d(a1, a2, b1, b2), then chained to (mu_a, aa, ab) */
                    const real8 da1 = q * a2, da2 = q * a1, dden = -(q * sv);
                    const real8 db1 = dden * b2, db2 = dden * b1;
                    n0 = two * (mb * (da1 - da2) + ma * (db1 - db2));
                    n1 = db2;
                    n2 = two * da2;
                    if (nv < 8) {
                        n0 = keep8(n0, nv);
                        n1 = keep8(n1, nv);
                        n2 = keep8(n2, nv);
                    }
                }
            }
            if (grad && s > 0) {
                to[3 * (s - 1)] = hblur(p0, c0, n0);
                to[3 * (s - 1) + 1] = hblur(p1, c1v, n1);
                to[3 * (s - 1) + 2] = hblur(p2, c2v, n2);
            }
            p0 = c0; p1 = c1v; p2 = c2v;
            c0 = n0; c1v = n1; c2v = n2;
        }
        rows[((size_t)get_global_size(1) + img) * H + y] = hsum8(acc);
    }
}

/* out = wl * sign(a - b) + ws * (G0 + 2 a G1 + b G2), (G0, G1, G2) = vertical pass of T */
__kernel void ssim_grad(const int H, const int W, const int nseg, const real wl, const real ws,
                        __global const real8 *T, __global const real *a, __global const real8 *b,
                        __global real *out)
{
    const int img = get_global_id(1);
    const int y0 = get_global_id(0) * RB;
    const int y1 = y0 + RB < H ? y0 + RB : H;
    const size_t st = (size_t)nseg * 3;
    for (int y = y0; y < y1; y++) {
        __global const real8 *tc = T + ((size_t)img * (H + 10) + y + 5) * st;
        __global const real *ar = a + ((size_t)img * H + y) * W;
        __global real *orow = out + ((size_t)img * H + y) * W;
        __global const real8 *br = b + ((size_t)img * H + y) * nseg;
        for (int s = 0; s < nseg; s++) {
            const real8 g0 = vblur(tc + 3 * s, st), g1 = vblur(tc + 3 * s + 1, st), g2 = vblur(tc + 3 * s + 2, st);
            const int nv = W - 8 * s;
            const real8 av = load8(ar + 8 * s, nv), bv = br[s];
            const real8 g = wl * sign8(av - bv) + ws * (g0 + RC(2.0) * av * g1 + bv * g2);
            store8(orow + 8 * s, g, nv);
        }
    }
}
