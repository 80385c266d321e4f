/* Gaussian X-ray projector: forward (pixel-centric, tile owner) and backward (Gaussian-centric
 * gather). Switches and conventions: project_setup.h and clgs/ops/projector.py.
 *
 * Forward, two kernels: preprocess (set-up of every (Gaussian, view) and the per-tile lists, all
 * on the device, in index order) and render: one work-item owns a TW x TH tile (TW = 8 or 16
 * pixels = one realW row) of one view and walks the tile's Gaussian list, touching only the rows
 * inside each Gaussian's box. Backward: one work-item per run of Gaussians walks
 * each one's own box in every view, in BW-pixel segments (8 or 16) from the box's left edge
 * (segments outer, rows inner), gathers dL/dI into moment sums, then applies the chain rule once
 * per view (affine: for 8 Gaussians at once, one per lane). Neither needs atomics; both are
 * reproducible.
 *
 * Vector widths: TW (the render's row) and BW (the backward's segment) are -D options, 8 or 16,
 * so that a device whose native float vector holds 16 lanes (AVX-512) gets whole registers. The
 * per-pixel arithmetic is the same lane by lane at either width, so the forward gives the same
 * bits at TW = 8 and 16; the backward's sums over a segment's lanes are added in another order
 * (rounding-level differences between widths, still fixed for each width). */
#include "project_setup.h"

#ifndef TW
#define TW 8
#endif
#ifndef TH
#define TH 16
#endif
#ifndef BW
#define BW TW
#endif
#if (TW != 8 && TW != 16) || (BW != 8 && BW != 16)
#error "TW and BW (vector widths of the render and the backward) must be 8 or 16"
#endif

/* ------------------------------------------------------------------ width-16 helpers */
/* project_setup.h's 8-lane helpers (splat_exp2_8, sqrt8) at 16 lanes; LD16G, ST16G and mask16
 * come from common.h, splat_exp2_16 and fast_exp16 from project_setup.h and fastexp.h */
inline real16 sqrt16(real16 y)
{
    return (real16)(SQ(y.s0), SQ(y.s1), SQ(y.s2), SQ(y.s3), SQ(y.s4), SQ(y.s5), SQ(y.s6), SQ(y.s7),
                    SQ(y.s8), SQ(y.s9), SQ(y.sa), SQ(y.sb), SQ(y.sc), SQ(y.sd), SQ(y.se), SQ(y.sf));
}
#define sqrt_8 sqrt8
#define sqrt_16 sqrt16
#define LANES8 ((real8)(RC(0.0), RC(1.0), RC(2.0), RC(3.0), RC(4.0), RC(5.0), RC(6.0), RC(7.0)))
#define LANES16 ((real16)(RC(0.0), RC(1.0), RC(2.0), RC(3.0), RC(4.0), RC(5.0), RC(6.0), RC(7.0), RC(8.0), \
                          RC(9.0), RC(10.0), RC(11.0), RC(12.0), RC(13.0), RC(14.0), RC(15.0)))

inline real hsum8(real8 x)
{
    const real4 a = x.lo + x.hi;
    const real2 b = a.lo + a.hi;
    return b.x + b.y;
}
inline real hsum16(real16 x) { return hsum8(x.lo + x.hi); }
inline real8 fold8_8(real8 x) { return x; }
inline real8 fold8_16(real16 x) { return x.lo + x.hi; } /* 16 lanes to 8 partial sums */

/* the names at the render's width W = TW and at the backward's B = BW */
#define realW CAT(real, TW)
#define LANESW CAT(LANES, TW)
#define expW CAT(splat_exp2_, TW)
#define sqrtW CAT(sqrt_, TW) /* (CAT(sqrt, ..) would expand the builtin's macro) */
#define STWG CAT(CAT(ST, TW), G)
#define hsumW CAT(hsum, TW)
#define fast_expW CAT(fast_exp, TW)
#define realB CAT(real, BW)
#define maskB CAT(mask, BW)
#define LANESB CAT(LANES, BW)
#define expB CAT(splat_exp2_, BW)
#define sqrtB CAT(sqrt_, BW)
#define hsumB CAT(hsum, BW)
#define fold8B CAT(fold8_, BW) /* realB to real8 */

inline void load_gauss(int g, __global const real *means, __global const real *mats, real3 *p, real *S)
{
    *p = (real3)(means[3 * g], means[3 * g + 1], means[3 * g + 2]);
    for (int k = 0; k < 6; k++) S[k] = mats[6 * g + k];
}

/* ------------------------------------------------------------------ per (Gaussian, view) set-up */
/* in[0..2] x, y, z, in[3..8] the packed matrix, in[9] the density of Gaussians g0 + lane (lanes
 * past N repeat Gaussian N - 1). A full run of 8 is read as contiguous vectors and
 * de-interleaved by shuffles (about 8% off the affine set-up kernel against element by element). */
inline void gather8(const int g0, const int N, __global const real *means, __global const real *mats,
                    __global const real *rho, real8 *in)
{
    if (g0 + 8 <= N) {
        __global const real *pm = means + 3 * (size_t)g0, *pS = mats + 6 * (size_t)g0;
        const real8 a = LD8G(pm), b = LD8G(pm + 8), c = LD8G(pm + 16);
        in[0] = (real8)(a.s0, a.s3, a.s6, b.s1, b.s4, b.s7, c.s2, c.s5);
        in[1] = (real8)(a.s1, a.s4, a.s7, b.s2, b.s5, c.s0, c.s3, c.s6);
        in[2] = (real8)(a.s2, a.s5, b.s0, b.s3, b.s6, c.s1, c.s4, c.s7);
        const real8 m0 = LD8G(pS), m1 = LD8G(pS + 8), m2 = LD8G(pS + 16), m3 = LD8G(pS + 24);
        const real8 m4 = LD8G(pS + 32), m5 = LD8G(pS + 40);
        in[3] = (real8)(m0.s0, m0.s6, m1.s4, m2.s2, m3.s0, m3.s6, m4.s4, m5.s2);
        in[4] = (real8)(m0.s1, m0.s7, m1.s5, m2.s3, m3.s1, m3.s7, m4.s5, m5.s3);
        in[5] = (real8)(m0.s2, m1.s0, m1.s6, m2.s4, m3.s2, m4.s0, m4.s6, m5.s4);
        in[6] = (real8)(m0.s3, m1.s1, m1.s7, m2.s5, m3.s3, m4.s1, m4.s7, m5.s5);
        in[7] = (real8)(m0.s4, m1.s2, m2.s0, m2.s6, m3.s4, m4.s2, m5.s0, m5.s6);
        in[8] = (real8)(m0.s5, m1.s3, m2.s1, m2.s7, m3.s5, m4.s3, m5.s1, m5.s7);
        in[9] = LD8G(rho + g0);
        return;
    }
    for (int j = 0; j < 8; j++) {
        const int g = g0 + j < N ? g0 + j : N - 1;
        for (int k = 0; k < 3; k++) ((real *)&in[k])[j] = means[3 * g + k];
        for (int k = 0; k < 6; k++) ((real *)&in[3 + k])[j] = mats[6 * g + k];
        ((real *)&in[9])[j] = rho[g];
    }
}

#ifdef EXACT /* (affine: preprocess8 below) */
inline void preprocess_one(const int g, const int view, const int N, const int U, const int V, const real scale,
                         __global const real *means, __global const real *mats, __global const real *rho,
                         __global const real *vparams, __global real *rec, __global int4 *box)
{
    real3 p;
    real S[6];
    load_gauss(g, means, mats, &p, S);
    Splat sp;
    const View Vw = load_view(vparams, view);
    const size_t idx = (size_t)view * N + g;
    if (!setup(p, S, Vw, scale, U, V, &sp)) {
        box[idx] = (int4)(1, 0, 1, 0);
        return;
    }
    box[idx] = sp.box;
    __global real *r = rec + idx * REC;
    r[0] = sp.uc; r[1] = sp.vc; r[2] = rho[g] * sp.amp0; r[3] = (real)sp.straddle;
    r[4] = RC(-0.5) * sp.k0; r[5] = -sp.k1; r[6] = RC(-0.5) * sp.k2; /* -q/2 coefficients */
#if defined(EXACT) && defined(CONE)
    r[7] = sp.a1; r[8] = sp.a2; r[9] = sp.a3; r[10] = sp.a4; r[11] = sp.a5;
    r[12] = sp.d0; r[13] = sp.d1; r[14] = sp.d2; r[15] = sp.d3; r[16] = sp.d4; r[17] = sp.d5;
    r[18] = sp.kap;
#endif
    r[REC - 1] = sp.amp0;
}

/* The set-up the forward stored (record + box), for a backward right after it */
inline int load_splat(__global const real *rec, __global const int4 *box, size_t idx, Splat *sp)
{
    sp->box = box[idx];
    if (sp->box.x > sp->box.y) return 0;
    __global const real *r = rec + idx * REC;
    sp->uc = r[0]; sp->vc = r[1]; sp->straddle = r[3] != RC(0.0);
    sp->k0 = RC(-2.0) * r[4]; sp->k1 = -r[5]; sp->k2 = RC(-2.0) * r[6];
#if defined(EXACT) && defined(CONE)
    sp->a1 = r[7]; sp->a2 = r[8]; sp->a3 = r[9]; sp->a4 = r[10]; sp->a5 = r[11];
    sp->d0 = r[12]; sp->d1 = r[13]; sp->d2 = r[14]; sp->d3 = r[15]; sp->d4 = r[16]; sp->d5 = r[17];
    sp->kap = r[18];
#else
    sp->kap = RC(1.0);
#endif
    sp->amp0 = r[REC - 1];
    return 1;
}

#ifdef CONE
/* Exact cone: Gaussians [g0, g0 + 8) of one view at once (setup_exact_cone8); the rare lanes it
 * leaves to the scalar set-up go through preprocess_one. */
inline void preprocess_exact8(const int g0, const int view, const int N, const int U, const int V, const real scale,
                              __global const real *means, __global const real *mats, __global const real *rho,
                              __global const real *vparams, __global real *rec, __global int4 *box)
{
    real8 in[10];
    gather8(g0, N, means, mats, rho, in);
    vec8 p;
    p.x = in[0]; p.y = in[1]; p.z = in[2];
    real8 out[REC];
    int8 bx[4];
    mask8 fb;
    const mask8 ok = setup_exact_cone8(p, in + 3, in[9], load_view(vparams, view), scale, U, V, out, bx, &fb);
    for (int j = 0; j < 8 && g0 + j < N; j++) {
        const size_t idx = (size_t)view * N + g0 + j;
        if (((const mask1 *)&fb)[j]) {
            preprocess_one(g0 + j, view, N, U, V, scale, means, mats, rho, vparams, rec, box);
            continue;
        }
        if (!((const mask1 *)&ok)[j]) {
            box[idx] = (int4)(1, 0, 1, 0);
            continue;
        }
        box[idx] = (int4)(((const int *)&bx[0])[j], ((const int *)&bx[1])[j], ((const int *)&bx[2])[j],
                          ((const int *)&bx[3])[j]);
        for (int i = 0; i < REC; i++) rec[idx * REC + i] = ((const real *)&out[i])[j];
    }
}
#endif

#endif

/* ------------------------------------------------------------------ tile lists */
/* The render's per-tile lists are built inside the set-up kernel, with no separate pass over
 * the Gaussians: every (chunk, view) work-item lays its own Gaussians out tile by tile (a
 * counting sort within the chunk: count, prefix, place) in a region of the lists it takes with
 * one integer atomic add on a shared counter. Regions land in any order, but the render walks
 * a tile's segment in every chunk's region, chunks in index order, so each tile still sees its
 * Gaussians in index order whatever the device does: the sums are bitwise reproducible, and the
 * same as with one global list per tile. (No float atomics; the one int atomic per chunk only
 * picks where a region lies, never an order of summation.) */

/* Count the tiles box b covers (kept == 0: none) into cnt, four arrays of ntiles counts, one
 * per corner of a box of up to 2 x 2 tiles (nearly all, with the tall CPU tiles): branch-free,
 * as the tile spans are random and a mispredicted loop exit costs more than the adds, and in
 * four arrays so that the adds of one box never wait for each other through memory (the
 * corners a box does not reach add 0). Larger boxes go into the first array. */
inline void count_box(const int4 b, const int kept, const int ntx, const int ntiles, __global int *cnt)
{
    const int tx0 = (uint)b.x / TW, tx1 = (uint)b.y / TW, ty0 = (uint)b.z / TH, ty1 = (uint)b.w / TH;
    if (tx1 - tx0 <= 1 && ty1 - ty0 <= 1) {
        const int ex = tx1 > tx0, ey = ty1 > ty0;
        cnt[ty0 * ntx + tx0] += kept;
        cnt[ntiles + ty0 * ntx + tx1] += kept & ex;
        cnt[2 * ntiles + ty1 * ntx + tx0] += kept & ey;
        cnt[3 * ntiles + ty1 * ntx + tx1] += kept & ex & ey;
        return;
    }
    if (!kept) return;
    for (int ty = ty0; ty <= ty1; ty++)
        for (int tx = tx0; tx <= tx1; tx++) cnt[ty * ntx + tx] += 1;
}

/* The counts (count_box) to tile starts, shifted by one: cs[0] = 0 and cs[t + 1] = tile t's
 * start, the cursor place_box advances to tile t + 1's start. Returns the chunk's pair count. */
inline int prefix_counts(const int ntiles, __global const int *cnt, __global int *cs)
{
    int s = 0;
    cs[0] = 0;
    for (int t = 0; t < ntiles; t++) {
        cs[t + 1] = s;
        s += cnt[t] + cnt[ntiles + t] + cnt[2 * ntiles + t] + cnt[3 * ntiles + t];
    }
    return s;
}

/* Copy Gaussian g's record (with its box's first and last row in the slots the render reads
 * them from) to the next entry of every tile segment its box b covers, in the chunk's region
 * lst / gidx. After the chunk's last Gaussian, cs[t] is tile t's start and cs[ntiles] the
 * region's size. (A branch-free variant for boxes of up to 2 x 2 tiles, as count_box, measured
 * no faster: this pass is bound by the stores.) */
inline void place_box(const int g, const int4 b, const int ntx, __global int *cs,
                      __global const real *r, __global real *lst, __global int *gidx)
{
    const int tx0 = (uint)b.x / TW, tx1 = (uint)b.y / TW, ty0 = (uint)b.z / TH, ty1 = (uint)b.w / TH;
#ifndef EXACT
    const real8 R = LD8G(r); /* the affine record already holds the rows (preprocess8) */
#endif
    for (int ty = ty0; ty <= ty1; ty++)
        for (int tx = tx0; tx <= tx1; tx++) {
            const int pos = cs[1 + ty * ntx + tx]++;
            __global real *P = lst + (size_t)pos * REC;
#ifndef EXACT
            ST8G(P) = R;
#else
            for (int i = 0; i + 8 <= REC; i += 8) ST8G(P + i) = LD8G(r + i);
            for (int i = REC / 8 * 8; i < REC; i++) P[i] = r[i];
            P[ROW0_SLOT] = (real)b.z;
            P[ROW1_SLOT] = (real)b.w;
#endif
#if defined(EXACT) && defined(CONE)
            gidx[pos] = g; /* the render needs it for straddling Gaussians only */
#endif
        }
}

#ifndef EXACT
/* 8 x 8 transpose, y[j] lane i = x[i] lane j, in three rounds of pairwise shuffles (the
 * records of 8 Gaussians as 8 vector stores: about 4% off the set-up kernel against 64 scalar
 * ones) */
inline void transpose8(const real8 *x, real8 *y)
{
    real8 a[8], b[8];
    /* a[i], a[i + 1] (i even): rows i and i + 1 interleaved, columns 0 1 4 5 and 2 3 6 7 */
    for (int i = 0; i < 8; i += 2) {
        a[i] = (real8)(x[i].s0, x[i + 1].s0, x[i].s1, x[i + 1].s1, x[i].s4, x[i + 1].s4, x[i].s5, x[i + 1].s5);
        a[i + 1] = (real8)(x[i].s2, x[i + 1].s2, x[i].s3, x[i + 1].s3, x[i].s6, x[i + 1].s6, x[i].s7, x[i + 1].s7);
    }
    /* b[i + m] (i = 0, 4; m = 0 .. 3): rows i .. i + 3 of column m, then of column m + 4 */
    for (int i = 0; i < 8; i += 4)
        for (int h = 0; h < 2; h++) {
            const real8 p = a[i + h], q = a[i + 2 + h];
            b[i + 2 * h] = (real8)(p.s01, q.s01, p.s45, q.s45);
            b[i + 2 * h + 1] = (real8)(p.s23, q.s23, p.s67, q.s67);
        }
    for (int m = 0; m < 4; m++) {
        y[m] = (real8)(b[m].lo, b[4 + m].lo);
        y[m + 4] = (real8)(b[m].hi, b[4 + m].hi);
    }
}

/* Affine: Gaussians [g0, g0 + 8) of one view at once, one per lane (setup_affine8): their
 * records and boxes (culled: (1, 0, 1, 0)) into rec and box, and their tiles counted into cnt.
 * Lanes past N repeat Gaussian N - 1 and are neither written nor counted. */
inline void preprocess8(const int g0, const int view, const int N, const int U, const int V, const real scale,
                        const int ntx, __global const real *means, __global const real *mats,
                        __global const real *rho, __global const real *vparams, __global real *rec,
                        __global int4 *box, const int ntiles, __global int *cnt)
{
    real8 in[10];
    gather8(g0, N, means, mats, rho, in);
    vec8 p;
    p.x = in[0]; p.y = in[1]; p.z = in[2];
    Frame8 f;
    const Splat8 sp = setup_affine8(p, in + 3, load_view(vparams, view), scale, U, V, &f);
    const int8 ok = convert_int8(sp.ok) & (sp.u0 <= sp.u1) & (sp.v0 <= sp.v1); /* kept, box not empty */
    const int8 u0 = ok ? sp.u0 : (int8)(1), u1 = ok ? sp.u1 : (int8)(0);
    const int8 v0 = ok ? sp.v0 : (int8)(1), v1 = ok ? sp.v1 : (int8)(0);
    /* the record: centre, amplitude, first row of the box, -q/2 log2(e) coefficients, last row
     * (the backward recomputes its set-up, so the record only serves the render) */
    const real8 out[8] = {sp.uc, sp.vc, in[9] * sp.amp0, convert_real8(v0), (RC(-0.5) * sp.k0) * RC(LOG2E),
                          -sp.k1 * RC(LOG2E), (RC(-0.5) * sp.k2) * RC(LOG2E), convert_real8(v1)};
    const size_t idx0 = (size_t)view * N + g0;
    if (g0 + 8 <= N) {
        real8 r[8];
        transpose8(out, r);
        for (int j = 0; j < 8; j++) ST8G(rec + (idx0 + j) * REC) = r[j];
        box[idx0] = (int4)(u0.s0, u1.s0, v0.s0, v1.s0);
        box[idx0 + 1] = (int4)(u0.s1, u1.s1, v0.s1, v1.s1);
        box[idx0 + 2] = (int4)(u0.s2, u1.s2, v0.s2, v1.s2);
        box[idx0 + 3] = (int4)(u0.s3, u1.s3, v0.s3, v1.s3);
        box[idx0 + 4] = (int4)(u0.s4, u1.s4, v0.s4, v1.s4);
        box[idx0 + 5] = (int4)(u0.s5, u1.s5, v0.s5, v1.s5);
        box[idx0 + 6] = (int4)(u0.s6, u1.s6, v0.s6, v1.s6);
        box[idx0 + 7] = (int4)(u0.s7, u1.s7, v0.s7, v1.s7);
    } else {
        for (int j = 0; j < 8 && g0 + j < N; j++) {
            box[idx0 + j] = (int4)(((const int *)&u0)[j], ((const int *)&u1)[j], ((const int *)&v0)[j],
                                   ((const int *)&v1)[j]);
            for (int i = 0; i < REC; i++) rec[(idx0 + j) * REC + i] = ((const real *)&out[i])[j];
        }
    }
    for (int j = 0; j < 8 && g0 + j < N; j++)
        count_box((int4)(((const int *)&u0)[j], ((const int *)&u1)[j], ((const int *)&v0)[j], ((const int *)&v1)[j]),
                  ((const int *)&ok)[j] & 1, ntx, ntiles, cnt);
}
#endif

/* Work-item (c, view) handles the Gaussians [c chunk, (c + 1) chunk) of one view (affine:
 * chunk is a multiple of 8): their records and boxes into rec and box (the exact backward reuses
 * them), then their tile lists (see above): tile starts within the region in row view nchunks
 * + c of cst (its last entry the region's size), the region's first entry in rbase. alloc[0]
 * counts the entries taken (zero before the launch); a region that does not fit below cap is not
 * written and gets rbase -1 (the host sees the count, grows the lists and runs again), and
 * alloc[1] gets 1 if the count passed 2^31 - 1. */
__kernel void preprocess(const int N, const int chunk, const int nchunks, const int U, const int V,
                         const real scale, const int ntx, const int ntiles, const int cap,
                         __global const real *means, __global const real *mats, __global const real *rho,
                         __global const real *vparams, __global real *rec, __global int4 *box,
                         __global int *cnts, __global int *cst, __global int *rbase, volatile __global int *alloc,
                         __global real *lst, __global int *gidx)
{
    const int c = get_global_id(0);
    const int view = get_global_id(1);
    if (c >= nchunks) return;
    const int ga = c * chunk, g1 = min(N, (c + 1) * chunk);
    const size_t region = (size_t)view * nchunks + c;
    __global int *cs = cst + region * (ntiles + 1), *cnt = cnts + region * 4 * ntiles;
    for (int t = 0; t < 4 * ntiles; t++) cnt[t] = 0;
#if !defined(EXACT)
    for (int g = ga; g < g1; g += 8)
        preprocess8(g, view, N, U, V, scale, ntx, means, mats, rho, vparams, rec, box, ntiles, cnt);
#else
#if defined(CONE)
    for (int g = ga; g < g1; g += 8)
        preprocess_exact8(g, view, N, U, V, scale, means, mats, rho, vparams, rec, box);
#else
    for (int g = ga; g < g1; g++)
        preprocess_one(g, view, N, U, V, scale, means, mats, rho, vparams, rec, box);
#endif
    for (int g = ga; g < g1; g++) {
        const int4 b = box[(size_t)view * N + g];
        count_box(b, b.x <= b.y && b.z <= b.w, ntx, ntiles, cnt);
    }
#endif
    const int n = prefix_counts(ntiles, cnt, cs);
    const int base = atomic_add(alloc, n);
    if (n < 0 || base < 0 || (long)base + n > (long)INT_MAX) atomic_or(alloc + 1, 1);
    const int fits = n >= 0 && base >= 0 && (long)base + n <= (long)cap;
    rbase[region] = fits ? base : -1;
    if (!fits) return;
    __global real *l = lst + (size_t)base * REC;
    __global int *gi = gidx + base;
    for (int g = ga; g < g1; g++) {
        const size_t idx = (size_t)view * N + g;
        const int4 b = box[idx];
        if (b.x > b.y || b.z > b.w) continue;
        place_box(g, b, ntx, cs, rec + idx * REC, l, gi);
    }
}

/* ------------------------------------------------------------------ forward */
#if defined(EXACT) && defined(CONE)
/* straddle_eval's value on a render row of TW pixels (it works on 8: twice for 16) */
inline realW straddle_row(real3 p, const real *S, View Vw, real amp0, realW uu, real v)
{
    real8 w[3], d[3], ia, beta, vnf;
#if TW == 8
    return straddle_eval(p, S, Vw, amp0, uu, v, w, d, &ia, &beta, &vnf);
#else
    const real8 lo = straddle_eval(p, S, Vw, amp0, uu.lo, v, w, d, &ia, &beta, &vnf);
    return (real16)(lo, straddle_eval(p, S, Vw, amp0, uu.hi, v, w, d, &ia, &beta, &vnf));
#endif
}
#endif

/* One work-item per TW x TH tile; a tile row is one realW (TW lanes). The tile's list is its
 * segment in every chunk's region (preprocess), chunks in order. */
__kernel void render(const int U, const int V, const int ntx, const int ntiles, const int nchunks,
                     __global const real *lst, __global const int *cst, __global const int *rbase,
                     __global const int *gidx, __global const real *means, __global const real *mats,
                     __global const real *rho, __global const real *vparams, const real scale,
                     __global real *out)
{
    const int tx = get_global_id(0), ty = get_global_id(1), view = get_global_id(2);
    if (tx >= ntx || ty * TH >= V) return;
    const int tile = ty * ntx + tx;
    const int u0 = tx * TW, v0 = ty * TH;
    const realW zero = (realW)(RC(0.0));
    realW acc[TH];
    for (int r = 0; r < TH; r++) acc[r] = zero;
    const realW uu = (real)u0 + LANESW;
    for (int c = 0; c < nchunks; c++) {
        const size_t region = (size_t)view * nchunks + c;
        __global const int *cs = cst + region * (ntiles + 1);
        const int base = rbase[region];
        if (base < 0) continue; /* the region did not fit: the call runs again */
        const int end = base + cs[tile + 1];
        for (int k = base + cs[tile]; k < end; k++) {
            __global const real *R = lst + (size_t)k * REC;
            const int2 b = (int2)((int)R[ROW0_SLOT], (int)R[ROW1_SLOT]);
            const int r0 = (b.x > v0 ? b.x : v0) - v0, r1 = (b.y < v0 + TH - 1 ? b.y : v0 + TH - 1) - v0;
            const real uc = R[0], vc = R[1], amp = R[2];
            /* t = -q/2 log2(e), so that the exponential is expW(t) (splat_exp2_8 / _16); the
             * affine record holds these coefficients already */
#if defined(EXACT)
            const real lk0 = R[4] * RC(LOG2E), lk1 = R[5] * RC(LOG2E), lk2 = R[6] * RC(LOG2E);
#else
            const real lk0 = R[4], lk1 = R[5], lk2 = R[6];
#endif
            const realW du = uu - uc;
#if defined(EXACT) && defined(CONE)
            if (R[3] != RC(0.0)) {
                const int g = gidx[k];
                real3 p;
                real S[6];
                load_gauss(g, means, mats, &p, S);
                const View Vw = load_view(vparams, view);
                for (int r = r0; r <= r1; r++)
                    acc[r] += rho[g] * straddle_row(p, S, Vw, sqrt(RC(TWO_PI)) / scale, uu, (real)(v0 + r));
                continue;
            }
            /* numerator -N'/2 log2(e), a' and dd' as polynomials in dv with the du parts once */
            const real a1 = R[7], a2 = R[8], a3 = R[9], a4 = R[10], a5 = R[11];
            const real d0 = R[12], d1 = R[13], d2 = R[14], d3 = R[15], d4 = R[16], d5 = R[17];
            const realW Ndu = lk0 * du * du, NB = lk1 * du;
            const realW Adu = RC(1.0) + (RC(2.0) * a1 + a3 * du) * du, AB = RC(2.0) * (a4 * du + a2);
            const realW Ddu = d0 + (RC(2.0) * d1 + d3 * du) * du, DB = RC(2.0) * (d4 * du + d2);
            realW dv = (realW)(row_offset(b.x, v0 + r0, vc));
            for (int r = r0; r <= r1; r++, dv += RC(1.0)) {
                const realW A = Adu + dv * (AB + a5 * dv);
                const realW DD = Ddu + dv * (DB + d5 * dv);
                const realW ia = RC(1.0) / A;
                const realW t = (Ndu + dv * (NB + lk2 * dv)) * ia;
                const realW val = amp * sqrtW(DD * ia) * expW(t);
                acc[r] += (t >= TCUT ? val : zero);
            }
#else
            const realW P = lk0 * du * du, Q = lk1 * du; /* t = P + dv (Q + lk2 dv): the du parts once */
            realW dv = (realW)(row_offset(b.x, v0 + r0, vc));
            for (int r = r0; r <= r1; r++, dv += RC(1.0)) {
                const realW t = P + dv * (Q + lk2 * dv);
                acc[r] += (t >= TCUT ? amp * expW(t) : zero);
            }
#endif
        }
    }
    __global real *o = out + (size_t)view * V * U;
    for (int r = 0; r < TH; r++) {
        const int v = v0 + r;
        if (v >= V) break;
        if (u0 + TW <= U) {
            STWG(o + (size_t)v * U + u0) = acc[r];
        } else {
            real tmp[TW];
            CAT(vstore, TW)(acc[r], 0, tmp);
            for (int i = 0; i < U - u0; i++) o[(size_t)v * U + u0 + i] = tmp[i];
        }
    }
}

/* ------------------------------------------------------------------ backward */

/* dL/dI of the 8 (16) pixels of row v from column s (lanes past the detector edge repeat its
 * last pixel; the caller masks lanes outside the Gaussian's box, which lies on the detector) */
#define DEFINE_LOAD_ROW(NAME, W)                                                                 \
    inline real##W NAME(__global const real *gimg, int U, int v, int s)                           \
    {                                                                                             \
        __global const real *row = gimg + (size_t)v * U;                                          \
        if (s + W <= U) return LD##W##G(row + s);                                                 \
        real tmp[W];                                                                              \
        for (int i = 0; i < W; i++) tmp[i] = row[min(s + i, U - 1)];                              \
        return vload##W(0, tmp);                                                                  \
    }
DEFINE_LOAD_ROW(load_row, 8)
DEFINE_LOAD_ROW(load_row16, 16)
#if BW == 8
#define load_rowB load_row
#else
#define load_rowB load_row16
#endif

inline void add_sym_outer(real *G, real c, real3 a, real3 b)
{ /* G (packed matrix gradient, off-diagonals as the sum of both entries) += c sym(a b^T) * 2 / 2 */
    G[0] += c * a.x * b.x;
    G[1] += c * (a.x * b.y + a.y * b.x);
    G[2] += c * (a.x * b.z + a.z * b.x);
    G[3] += c * a.y * b.y;
    G[4] += c * (a.y * b.z + a.z * b.y);
    G[5] += c * a.z * b.z;
}

/* Moments (sum over the box of g E times 1, du, dv, du^2, du dv, dv^2) of dL/dI (g) against a
 * conic splat E = exp(-q/2), q = k0 du^2 + 2 k1 du dv + k2 dv^2 (q <= 9 kept), du = u - uc, dv =
 * v - vc: everything the chain rule of a conic splat needs from the pixels. BW-pixel segments
 * from the box's left edge outer, rows inner (the du parts once per segment). Each moment comes
 * back as a realB whose lanes still have to be added. */
inline void conic_moments(__global const real *gi, int U, int4 b, real uc, real vc, real k0, real k1, real k2,
                          realB *mo)
{
    const realB zero = (realB)(RC(0.0));
    /* t = -q/2 log2(e), so that E = expB(t) */
    const real nk0 = RC(-0.5 * LOG2E) * k0, nk1 = RC(-LOG2E) * k1, nk2 = RC(-0.5 * LOG2E) * k2;
    realB S0 = zero, Su = zero, Sv = zero, Suu = zero, Suv = zero, Svv = zero;
    for (int s = b.x; s <= b.y; s += BW) {
        const realB uu = (real)s + LANESB;
        const maskB lm = uu <= (real)b.y;
        const realB du = uu - uc;
        const realB A8 = nk0 * du * du, B8 = nk1 * du;
        realB c0 = zero, cv = zero, cvv = zero;
        realB dv8 = (realB)(row_offset(b.z, b.z, vc));
        for (int v = b.z; v <= b.w; v++, dv8 += RC(1.0)) {
            const realB t = A8 + dv8 * (B8 + nk2 * dv8);
            const realB gE = ((lm & (t >= TCUT)) ? load_rowB(gi, U, v, s) * expB(t) : zero);
            c0 += gE; cv += gE * dv8; cvv += gE * (dv8 * dv8);
        }
        S0 += c0; Su += du * c0; Suu += du * du * c0;
        Sv += cv; Suv += du * cv; Svv += cvv;
    }
    mo[0] = S0; mo[1] = Su; mo[2] = Sv; mo[3] = Suu; mo[4] = Suv; mo[5] = Svv;
}

/* (sum of v[0], ..., sum of v[7]): eight horizontal sums at once, 7 additions instead of 8 x 3
 * (each lane's sum still adds only its own vector's numbers, in a fixed order) */
inline real8 pairsum8(real8 a, real8 b) { return (real8)(a.s0246, b.s0246) + (real8)(a.s1357, b.s1357); }
inline real8 hsum8x8(const real8 *v)
{
    return pairsum8(pairsum8(pairsum8(v[0], v[1]), pairsum8(v[2], v[3])),
                    pairsum8(pairsum8(v[4], v[5]), pairsum8(v[6], v[7])));
}

#ifdef EXACT
inline void backward_one(const int g, const int N, const int nviews, const int U, const int V, const real scale,
                         const int cached, __global const real *rec, __global const int4 *box,
                         __global const real *means, __global const real *mats, __global const real *rho,
                         __global const real *vparams, __global const real *gimg,
                         __global real *g_means, __global real *g_mats, __global real *g_rho)
{
    real3 p;
    real S[6];
    load_gauss(g, means, mats, &p, S);
    const real rh = rho[g];
    real3 gp = (real3)(RC(0.0));
    real gM[6] = {RC(0.0), RC(0.0), RC(0.0), RC(0.0), RC(0.0), RC(0.0)};
    real grho = RC(0.0);
    const real8 lane = (real8)(RC(0.0), RC(1.0), RC(2.0), RC(3.0), RC(4.0), RC(5.0), RC(6.0), RC(7.0));
    const real8 zero = (real8)(RC(0.0));

    for (int view = 0; view < nviews; view++) {
        const View Vw = load_view(vparams, view);
        Splat sp;
        if (cached) {
            if (!load_splat(rec, box, (size_t)view * N + g, &sp)) continue;
        } else if (!setup(p, S, Vw, scale, U, V, &sp)) {
            continue;
        }
        __global const real *gi = gimg + (size_t)view * V * U;
        const int4 b = sp.box;
        const int s0 = b.x; /* unaligned 8-pixel segments from the box edge: fewest segments */
#if defined(EXACT) && defined(CONE)
        if (sp.straddle) {
            /* per-pixel closed form with the erfc factor; sums in world coordinates */
            real8 Sw0 = zero, Sw1 = zero, Sw2 = zero, Sd0 = zero, Sd1 = zero, Sd2 = zero, S0 = zero;
            real8 M0 = zero, M1 = zero, M2 = zero, M3 = zero, M4 = zero, M5 = zero;
            for (int v = b.z; v <= b.w; v++) {
                for (int s = s0; s <= b.y; s += 8) {
                    const real8 uu = (real)s + lane;
                    const real8 gg = (((uu >= (real)b.x) & (uu <= (real)b.y)) ? load_row(gi, U, v, s) : zero);
                    real8 w[3], d[3], ia, beta, vnf;
                    const real8 val0 = straddle_eval(p, S, Vw, sp.amp0, (real)s + lane, (real)v, w, d, &ia, &beta, &vnf);
                    const real8 gv0 = gg * val0;
                    const real8 fp = RC(-0.5641895835477563) * fast_exp8(-beta * beta); /* dF/dbeta */
                    const real8 gvn = gg * vnf * fp;
                    const real8 isq = sqrt(RC(0.5) * ia);
                    S0 += gv0;
                    Sw0 += gv0 * w[0]; Sw1 += gv0 * w[1]; Sw2 += gv0 * w[2];
                    const real8 cd = gvn * isq;
                    Sd0 += cd * d[0]; Sd1 += cd * d[1]; Sd2 += cd * d[2];
                    const real8 cw = RC(-0.5) * gv0;
                    const real8 cdd = RC(-0.5) * (gv0 + gvn * beta) * ia;
                    M0 += cw * w[0] * w[0] + cdd * d[0] * d[0];
                    M1 += RC(2.0) * (cw * w[0] * w[1] + cdd * d[0] * d[1]);
                    M2 += RC(2.0) * (cw * w[0] * w[2] + cdd * d[0] * d[2]);
                    M3 += cw * w[1] * w[1] + cdd * d[1] * d[1];
                    M4 += RC(2.0) * (cw * w[1] * w[2] + cdd * d[1] * d[2]);
                    M5 += cw * w[2] * w[2] + cdd * d[2] * d[2];
                }
            }
            const real3 Sw = (real3)(hsum8(Sw0), hsum8(Sw1), hsum8(Sw2));
            const real3 Sd = (real3)(hsum8(Sd0), hsum8(Sd1), hsum8(Sd2));
            gp += rh * (symv(S, Sw) - symv(S, Sd));
            gM[0] += rh * hsum8(M0); gM[1] += rh * hsum8(M1); gM[2] += rh * hsum8(M2);
            gM[3] += rh * hsum8(M3); gM[4] += rh * hsum8(M4); gM[5] += rh * hsum8(M5);
            add_sym_outer(gM, rh, Sd, Vw.s - p);
            grho += hsum8(S0);
            continue;
        }
        {
            /* exact cone, clear of the source: closest-point residual w = alpha e + beta G du */
            const real3 gu = Vw.gul * Vw.eu, gv = Vw.gvl * Vw.ev;
            const real3 e = Vw.s - p;
            const real ik = RC(1.0) / sp.kap;
            /* -N'/2 log2(e), so that the exponential is splat_exp2_8 */
            const real nk0 = RC(-0.5 * LOG2E) * sp.k0, nk1 = RC(-LOG2E) * sp.k1, nk2 = RC(-0.5 * LOG2E) * sp.k2;
            /* w = al e + (be du) gu + (be dv) gv with al = Pal / a', be = Pbe / a' (Pal quadratic
             * and Pbe linear in dv for a fixed du): the sums of g I w and g I w w^T need the nine
             * moments of al and be, and the gradient of a' the six moments of g I / a' in du, dv.
             * Rows inner, the row loop only sums h = g I / a' (per unit amplitude) times 1, dv,
             * dv^2 and h / a' times 1 .. dv^4; the du parts are applied once per segment (fewer
             * operations and live vectors per row than the sixteen sums per pixel: about 1.1-1.2x
             * faster on the 50k-Gaussian benchmark). */
            const realB zb = (realB)(RC(0.0));
            realB S0 = zb, Ma = zb, Mbu = zb, Mbv = zb, Maa = zb, Mabu = zb, Mabv = zb;
            realB Mbbuu = zb, Mbbuv = zb, Mbbvv = zb;
            realB Q0 = zb, Qu = zb, Qv = zb, Quu = zb, Quv = zb, Qvv = zb;
            for (int s = s0; s <= b.y; s += BW) {
                /* BW-pixel segment outer, rows inner: the du parts of every polynomial once */
                const realB uu = (real)s + LANESB;
                const maskB lm = (uu >= (real)b.x) & (uu <= (real)b.y);
                const realB du = uu - sp.uc;
                const realB Ndu = nk0 * du * du, NB = nk1 * du;
                const realB Adu = RC(1.0) + (RC(2.0) * sp.a1 + sp.a3 * du) * du, AB = RC(2.0) * (sp.a4 * du + sp.a2);
                const realB Ddu = sp.d0 + (RC(2.0) * sp.d1 + sp.d3 * du) * du, DB = RC(2.0) * (sp.d4 * du + sp.d2);
                realB H0 = zb, H1 = zb, H2 = zb, K0 = zb, K1 = zb, K2 = zb, K3 = zb, K4 = zb;
                real dv = row_offset(b.z, b.z, sp.vc);
                for (int v = b.z; v <= b.w; v++, dv += RC(1.0)) {
                    const real dv2 = dv * dv;
                    const realB dv8 = (realB)(dv);
                    const realB A = Adu + dv8 * (AB + sp.a5 * dv8);
                    const realB ia = RC(1.0) / A;
                    const realB t = (Ndu + dv8 * (NB + nk2 * dv8)) * ia;
                    const realB DD = Ddu + dv8 * (DB + sp.d5 * dv8);
                    const realB h = ((lm & (t >= TCUT)) ?
                                     load_rowB(gi, U, v, s) * sqrtB(DD * ia) * expB(t) * ia : zb);
                    const realB h2 = h * ia;
                    H0 += h; H1 += h * dv; H2 += h * dv2;
                    K0 += h2; K1 += h2 * dv; K2 += h2 * dv2; K3 += h2 * (dv * dv2); K4 += h2 * (dv2 * dv2);
                }
                /* al a' = p0 + p1 dv + p2 dv^2, be a' = b0 + b1 dv */
                const realB p0 = (sp.a3 * du + sp.a1) * du, p1 = RC(2.0) * sp.a4 * du + sp.a2;
                const real p2 = sp.a5;
                const realB b0 = (RC(1.0) + sp.a1 * du) * ik;
                const real b1 = sp.a2 * ik;
                S0 += Adu * H0 + AB * H1 + sp.a5 * H2; /* g I = h a' */
                Ma += p0 * H0 + p1 * H1 + p2 * H2;
                Mbu += du * (b0 * H0 + b1 * H1);
                Mbv += b0 * H1 + b1 * H2;
                Maa += p0 * p0 * K0 + RC(2.0) * p0 * p1 * K1 + (p1 * p1 + RC(2.0) * p0 * p2) * K2
                       + RC(2.0) * p1 * p2 * K3 + (p2 * p2) * K4;
                const realB c0 = p0 * b0, c1 = p0 * b1 + p1 * b0, c2 = p1 * b1 + p2 * b0, c3 = p2 * b1;
                Mabu += du * (c0 * K0 + c1 * K1 + c2 * K2 + c3 * K3);
                Mabv += c0 * K1 + c1 * K2 + c2 * K3 + c3 * K4;
                const realB e0 = b0 * b0, e1 = RC(2.0) * b0 * b1;
                const real e2 = b1 * b1;
                const realB Z0 = e0 * K0 + e1 * K1 + e2 * K2, Z1 = e0 * K1 + e1 * K2 + e2 * K3;
                Mbbuu += du * du * Z0; Mbbuv += du * Z1; Mbbvv += e0 * K2 + e1 * K3 + e2 * K4;
                Q0 += H0; Qu += du * H0; Quu += du * du * H0;
                Qv += H1; Quv += du * H1; Qvv += H2;
            }
            /* the sixteen lane sums, times the amplitude (the sums above are per unit amplitude) */
            const real8 ha[8] = {fold8B(S0), fold8B(Ma), fold8B(Mbu), fold8B(Mbv), fold8B(Maa), fold8B(Mabu),
                                 fold8B(Mabv), fold8B(Mbbuu)};
            const real8 hb[8] = {fold8B(Mbbuv), fold8B(Mbbvv), fold8B(Q0), fold8B(Qu), fold8B(Qv), fold8B(Quu),
                                 fold8B(Quv), fold8B(Qvv)};
            const real8 Ha = sp.amp0 * hsum8x8(ha), Hb = sp.amp0 * hsum8x8(hb);
            const real3 Sw = Ha.s1 * e + Ha.s2 * gu + Ha.s3 * gv;
            gp += rh * symv(S, Sw);
            /* sum g I d d^T / a with d = -kap e + G du, a = kap^2 c a' */
            const real c = dot3(e, symv(S, e));
            const real f = RC(1.0) / (sp.kap * sp.kap * c);
            const real q0 = Hb.s2, qu = Hb.s3, qv = Hb.s4, quu = Hb.s5, quv = Hb.s6, qvv = Hb.s7;
            /* G = B C B^T with B = [e gu gv]: the sums above give C's entries (the e m^T term,
             * m = qu gu + qv gv, goes into C's e-gu and e-gv entries); three outer products
             * instead of eleven */
            const real fk = f * sp.kap;
            const real cee = Ha.s4 + fk * sp.kap * q0, ceu = Ha.s5 - fk * qu, cev = Ha.s6 - fk * qv;
            const real cuu = Ha.s7 + f * quu, cuv = Hb.s0 + f * quv, cvv = Hb.s1 + f * qvv;
            real G[6] = {RC(0.0), RC(0.0), RC(0.0), RC(0.0), RC(0.0), RC(0.0)};
            add_sym_outer(G, RC(1.0), e, cee * e + ceu * gu + cev * gv);
            add_sym_outer(G, RC(1.0), gu, ceu * e + cuu * gu + cuv * gv);
            add_sym_outer(G, RC(1.0), gv, cev * e + cuv * gu + cvv * gv);
            for (int k = 0; k < 6; k++) gM[k] += RC(-0.5) * rh * G[k];
            grho += Ha.s0;
        }
#else
        /* conic splat (exact parallel): 6 moments of g E over the box */
        realB mv[6];
        conic_moments(gi, U, sp.box, sp.uc, sp.vc, sp.k0, sp.k1, sp.k2, mv);
        const real s0_ = hsumB(mv[0]), su = hsumB(mv[1]), sv = hsumB(mv[2]), suu = hsumB(mv[3]), suv = hsumB(mv[4]),
                   svv = hsumB(mv[5]);
        const real amp = rh * sp.amp0;
        grho += sp.amp0 * s0_;
        /* exact parallel: w = du w_u + dv w_v, w_u = gu - (h_u / a) r; envelope theorem */
        {
            const real3 r = Vw.w;
            const real3 gu = Vw.gul * Vw.eu, gv = Vw.gvl * Vw.ev;
            const real3 Pr = symv(S, r);
            const real a = dot3(r, Pr), ia = RC(1.0) / a;
            const real3 wu = gu - (dot3(gu, Pr) * ia) * r, wv = gv - (dot3(gv, Pr) * ia) * r;
            gp += symv(S, amp * (su * wu + sv * wv));
            const real c = RC(-0.5) * amp;
            add_sym_outer(gM, c * suu, wu, wu);
            add_sym_outer(gM, RC(2.0) * c * suv, wu, wv);
            add_sym_outer(gM, c * svv, wv, wv);
            add_sym_outer(gM, c * s0_ * ia, r, r);
        }
#endif
    }
#ifndef NO_GRAD_MEAN
    g_means[3 * g] = gp.x; g_means[3 * g + 1] = gp.y; g_means[3 * g + 2] = gp.z;
#endif
#ifndef NO_GRAD_COV
    for (int k = 0; k < 6; k++) g_mats[6 * g + k] = gM[k];
#endif
#ifndef NO_GRAD_DENSITY
    g_rho[g] = grho;
#endif
}

#endif

#ifndef EXACT
inline void add_sym_outer8(real8 *G, vec8 a, vec8 b, mask8 ok)
{ /* G += sym(a b^T) (packed, off-diagonals as the sum of both entries) on the lanes in ok */
    const real8 zero = (real8)(RC(0.0));
    G[0] += ok ? a.x * b.x : zero;
    G[1] += ok ? a.x * b.y + a.y * b.x : zero;
    G[2] += ok ? a.x * b.z + a.z * b.x : zero;
    G[3] += ok ? a.y * b.y : zero;
    G[4] += ok ? a.y * b.z + a.z * b.y : zero;
    G[5] += ok ? a.z * b.z : zero;
}

inline vec8 comb8(real8 a, vec8 A, real8 b, vec8 B, real8 c, vec8 C)
{
    vec8 r;
    r.x = a * A.x + b * B.x + c * C.x;
    r.y = a * A.y + b * B.y + c * C.y;
    r.z = a * A.z + b * B.z + c * C.z;
    return r;
}

inline real8 dot8s(vec8 a, real3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }

/* Affine backward of Gaussians [g0, g0 + 8), one per lane: per view the set-up (setup_affine8,
 * the very code the forward ran, so it matches the forward's records bit for bit), then each
 * Gaussian's pixel moments (conic_moments), then the chain rule for all 8 at once in real8:
 * back through C = S2^-1, mu = sqrt(2 pi det S3 / det S2), S3 = T Sigma T^T and T(p). */
inline void backward8(const int g0, const int N, const int nviews, const int U, const int V, const real scale,
                      __global const real *means, __global const real *mats, __global const real *rho,
                      __global const real *vparams, __global const real *gimg,
                      __global real *g_means, __global real *g_mats, __global real *g_rho)
{
    const real8 zero = (real8)(RC(0.0));
    real8 in[10];
    gather8(g0, N, means, mats, rho, in);
    vec8 p;
    p.x = in[0]; p.y = in[1]; p.z = in[2];
    const real8 *S = in + 3, rh = in[9];
    vec8 gp;
    gp.x = zero; gp.y = zero; gp.z = zero;
    real8 gM[6] = {zero, zero, zero, zero, zero, zero};
    real8 grho = zero;
    const int nlanes = N - g0 < 8 ? N - g0 : 8;
    for (int view = 0; view < nviews; view++) {
        const View Vw = load_view(vparams, view);
        Frame8 f;
        const Splat8 sp = setup_affine8(p, S, Vw, scale, U, V, &f);
        const mask8 ok = sp.ok;
        __global const real *gi = gimg + (size_t)view * V * U;
        real8 pm[8][6]; /* per lane j (Gaussian g0 + j): its pixel moments, lanes not yet added */
        for (int j = 0; j < 8; j++) {
            if (j >= nlanes || !((const mask1 *)&ok)[j]) {
                for (int k = 0; k < 6; k++) pm[j][k] = zero;
                continue;
            }
            const int4 b = (int4)(((const int *)&sp.u0)[j], ((const int *)&sp.u1)[j], ((const int *)&sp.v0)[j],
                                  ((const int *)&sp.v1)[j]);
            realB mb[6];
            conic_moments(gi, U, b, ((const real *)&sp.uc)[j], ((const real *)&sp.vc)[j], ((const real *)&sp.k0)[j],
                          ((const real *)&sp.k1)[j], ((const real *)&sp.k2)[j], mb);
            for (int k = 0; k < 6; k++) pm[j][k] = fold8B(mb[k]);
        }
        real8 mo[6]; /* lane j: moment of Gaussian g0 + j */
        for (int k = 0; k < 6; k++) {
            real8 col[8];
            for (int j = 0; j < 8; j++) col[j] = pm[j][k];
            mo[k] = hsum8x8(col);
        }
        const real8 s0_ = mo[0], su = mo[1], sv = mo[2], suu = mo[3], suv = mo[4], svv = mo[5];
        const real8 amp = rh * sp.amp0;
        grho += ok ? sp.amp0 * s0_ : zero;
        const real8 k0 = sp.k0, k1 = sp.k1, k2 = sp.k2;
        const real8 gc00 = RC(-0.5) * amp * suu, gc01 = RC(-0.5) * amp * suv, gc11 = RC(-0.5) * amp * svv;
        const real8 X00 = gc00 * k0 + gc01 * k1, X01 = gc00 * k1 + gc01 * k2;
        const real8 X10 = gc01 * k0 + gc11 * k1, X11 = gc01 * k1 + gc11 * k2;
        const real8 G00 = -(k0 * X00 + k1 * X10), G01 = -(k0 * X01 + k1 * X11), G11 = -(k1 * X01 + k2 * X11);
        const real8 Guc = amp * (k0 * su + k1 * sv), Gvc = amp * (k1 * su + k2 * sv);
        const real8 s00 = f.s00, s01 = f.s01, s02 = f.s02, s11 = f.s11, s12 = f.s12, s22 = f.s22;
        const real8 mu = sp.amp0 * scale;
        const real8 hm = RC(0.5) * (rh / scale) * s0_ * mu;
        const real8 id3 = hm / f.det3;
        /* G3 = hm S3^-1 (adjugate / det) + top-left (G2 - hm C) */
        real8 g3[6];
        g3[0] = (s11 * s22 - s12 * s12) * id3 + G00 - hm * k0;
        g3[1] = (s02 * s12 - s01 * s22) * id3 + G01 - hm * k1;
        g3[2] = (s01 * s12 - s02 * s11) * id3;
        g3[3] = (s00 * s22 - s02 * s02) * id3 + G11 - hm * k2;
        g3[4] = (s01 * s02 - s00 * s12) * id3;
        g3[5] = f.det2 * id3;
        /* dL/dSigma = T^T G3 T */
        add_sym_outer8(gM, f.T1, comb8(g3[0], f.T1, g3[1], f.T2, g3[2], f.T3), ok);
        add_sym_outer8(gM, f.T2, comb8(g3[1], f.T1, g3[3], f.T2, g3[4], f.T3), ok);
        add_sym_outer8(gM, f.T3, comb8(g3[2], f.T1, g3[4], f.T2, g3[5], f.T3), ok);
#ifdef CONE
        /* dL/dT = 2 G3 T Sigma, then T(t) and (uc, vc)(t) */
        const vec8 GT1 = comb8(RC(2.0) * g3[0], f.ST1, RC(2.0) * g3[1], f.ST2, RC(2.0) * g3[2], f.ST3);
        const vec8 GT2 = comb8(RC(2.0) * g3[1], f.ST1, RC(2.0) * g3[3], f.ST2, RC(2.0) * g3[4], f.ST3);
        const vec8 GT3 = comb8(RC(2.0) * g3[2], f.ST1, RC(2.0) * g3[4], f.ST2, RC(2.0) * g3[5], f.ST3);
        const real8 iz = f.iz, tx = f.tx, ty = f.ty;
        const real8 fxz2 = Vw.fx * iz * iz, fyz2 = Vw.fy * iz * iz;
        const real8 g1w = dot8s(GT1, Vw.w), g2w = dot8s(GT2, Vw.w);
        const real8 gtx = Guc * Vw.fx * iz - fxz2 * g1w;
        const real8 gty = Gvc * Vw.fy * iz - fyz2 * g2w;
        const real8 gtz = -Guc * fxz2 * tx - Gvc * fyz2 * ty
                          - fxz2 * dot8s(GT1, Vw.eu) + RC(2.0) * fxz2 * tx * iz * g1w
                          - fyz2 * dot8s(GT2, Vw.ev) + RC(2.0) * fyz2 * ty * iz * g2w;
        const real8 g3t = GT3.x * f.T3.x + GT3.y * f.T3.y + GT3.z * f.T3.z;
        gp.x += ok ? gtx * Vw.eu.x + gty * Vw.ev.x + gtz * Vw.w.x + (GT3.x - g3t * f.T3.x) * f.il : zero;
        gp.y += ok ? gtx * Vw.eu.y + gty * Vw.ev.y + gtz * Vw.w.y + (GT3.y - g3t * f.T3.y) * f.il : zero;
        gp.z += ok ? gtx * Vw.eu.z + gty * Vw.ev.z + gtz * Vw.w.z + (GT3.z - g3t * f.T3.z) * f.il : zero;
#else
        gp.x += ok ? Guc * Vw.fx * Vw.eu.x + Gvc * Vw.fy * Vw.ev.x : zero;
        gp.y += ok ? Guc * Vw.fx * Vw.eu.y + Gvc * Vw.fy * Vw.ev.y : zero;
        gp.z += ok ? Guc * Vw.fx * Vw.eu.z + Gvc * Vw.fy * Vw.ev.z : zero;
#endif
    }
    for (int j = 0; j < nlanes; j++) {
        const int g = g0 + j;
#ifndef NO_GRAD_MEAN
        g_means[3 * g] = ((real *)&gp.x)[j]; g_means[3 * g + 1] = ((real *)&gp.y)[j];
        g_means[3 * g + 2] = ((real *)&gp.z)[j];
#endif
#ifndef NO_GRAD_COV
        for (int k = 0; k < 6; k++) g_mats[6 * g + k] = ((real *)&gM[k])[j];
#endif
#ifndef NO_GRAD_DENSITY
        g_rho[g] = ((real *)&grho)[j];
#endif
    }
}
#endif

/* work-item i handles Gaussians [i per, (i + 1) per), each over every view. Exact: cached != 0
 * reuses the set-up the forward left in rec and box (same inputs and views), else recomputes
 * it. Affine (per a multiple of 8): the set-up is recomputed 8 Gaussians at a time, which costs
 * about what reading the records back would, and gives the same bits. */
__kernel void backward(const int N, const int per, const int nviews, const int U, const int V, const real scale,
                       const int cached, __global const real *rec, __global const int4 *box,
                       __global const real *means, __global const real *mats, __global const real *rho,
                       __global const real *vparams, __global const real *gimg,
                       __global real *g_means, __global real *g_mats, __global real *g_rho)
{
    const int g1 = min(N, (int)(get_global_id(0) + 1) * per);
#ifndef EXACT
    for (int g = get_global_id(0) * per; g < g1; g += 8)
        backward8(g, N, nviews, U, V, scale, means, mats, rho, vparams, gimg, g_means, g_mats, g_rho);
#else
    for (int g = get_global_id(0) * per; g < g1; g++)
        backward_one(g, N, nviews, U, V, scale, cached, rec, box, means, mats, rho, vparams, gimg, g_means, g_mats,
                     g_rho);
#endif
}

/* ------------------------------------------------------------------ exp throughput probe */
/* fast_exp8 (TW = 8) or fast_exp16 (TW = 16) in a loop: TW exps per iteration and work-item */
__kernel void exp_probe(const int n, __global real *out)
{
    const int i = get_global_id(0);
    realW x = (realW)(RC(-0.001)) * (real)(i & 1023) - RC(0.1) * LANESW;
    realW acc = (realW)(RC(0.0));
    for (int k = 0; k < n; k++) {
        acc += fast_expW(x);
        x -= RC(0.0004);
    }
    out[i] = hsumW(acc);
}
