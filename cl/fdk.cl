/* FDK / FBP weighted backprojection, voxel-driven (a gather: one work-item per eight voxels).
 *
 * The host has filtered the projections and folded every view- and pixel-dependent factor into
 * them (cosine weight, short-scan weight, angular step); this kernel adds the distance weight
 * (DSO / depth)^2 for cone beam and interpolates bilinearly on the detector.
 *
 * World coordinates in mm, as clgs/geometry.py: source at DSO (cos b, sin b, 0), detector
 * u axis (-sin b, cos b, 0), v axis z, pixel (iv, iu) at ((iu - cu) dU + ou, (iv - cv) dV + ov).
 *
 * Layouts: filtered projections q[(n * (nU + 3) + iu + 1) * (nV + 3) + iv + 1], v fastest, with a
 * zero border (one before, two after) so clamped coordinates read zeros; output
 * out[(i * nY + j) * nZp + k], z fastest. Global size (nZp / 8, nY, nX).
 * geo: x0 y0 z0 (centre of voxel 0), sx sy sz, DSO DSD, dU dV ou ov cu cv.
 */
#include "common.h"

/* Bilinear sample of one view's padded filtered projection qv (rows of SV values) at padded
 * coordinates (uf, vf), eight lanes: the gather both x-lane kernels share. */
inline real8 bilinear8(__global const real *qv, const int SV, const real8 uf, const real8 vf)
{
    int8 ku = convert_int8(uf), kv = convert_int8(vf);
    real8 fu = uf - convert_real8(ku), fv = vf - convert_real8(kv);
    int8 idx = ku * SV + kv;
    real8 a0 = GATHER8(qv, 0, idx);
    real8 a1 = GATHER8(qv, 1, idx);
    real8 b0 = GATHER8(qv, SV, idx);
    real8 b1 = GATHER8(qv, SV + 1, idx);
    real8 ca = a0 + fv * (a1 - a0);
    real8 cb = b0 + fv * (b1 - b0);
    return ca + fu * (cb - ca);
}

__kernel void fdk_backproject(__global const real *q, __global const real *trig, __global real *out,
                              __global const real *geo, int n_views, int nX, int nY, int nZp,
                              int nU, int nV)
{
    const int g = get_global_id(0), j = get_global_id(1), i = get_global_id(2);
    const real x = geo[0] + (real)i * geo[3];
    const real y = geo[1] + (real)j * geo[4];
    const real8 z = geo[2] + ((real8)(0, 1, 2, 3, 4, 5, 6, 7) + (real)(g * 8)) * geo[5];
    const real DSO = geo[6], DSD = geo[7], dU = geo[8], dV = geo[9], ou = geo[10], ov = geo[11];
    const real cu = geo[12], cv = geo[13];
    const real hiU = (real)nU, hiV = (real)nV;
    const int SV = nV + 3, SU = (nU + 3) * SV;
    real8 acc = (real8)0;

    for (int n = 0; n < n_views; ++n) {
        real c = trig[2 * n], s = trig[2 * n + 1];
        real xu = y * c - x * s;
#ifdef CONE
        real depth = DSO - (x * c + y * s);
        real mag = DSD / depth;
        real w = DSO / depth;
        w = w * w;
        real uf = (xu * mag - ou) / dU + cu;
        real8 vf = (z * mag - ov) / dV + cv;
#else
        real w = (real)1;
        real uf = (xu - ou) / dU + cu;
        real8 vf = (z - ov) / dV + cv;
#endif
        if (!(uf > (real)-1 && uf < hiU)) continue;
        int iu = (int)(uf + (real)1);            /* padded index of floor(uf) */
        real fu = uf + (real)1 - (real)iu;
        vf = vf < (real8)-1 ? (real8)-1 : vf;
        vf = vf > (real8)hiV ? (real8)hiV : vf;
        real8 vp = vf + (real8)1;
        int8 kv = convert_int8(vp);
        real8 fv = vp - convert_real8(kv);
        __global const real *qv = q + (size_t)n * SU;
        int base0 = iu * SV, base1 = base0 + SV;
        real8 a0 = GATHER8(qv, base0, kv);
        real8 a1 = GATHER8(qv, base0 + 1, kv);
        real8 b0 = GATHER8(qv, base1, kv);
        real8 b1 = GATHER8(qv, base1 + 1, kv);
        real8 ca = a0 + fv * (a1 - a0);
        real8 cb = b0 + fv * (b1 - b0);
        acc += w * (ca + fu * (cb - ca));
    }
    vstore8(acc, 0, out + ((size_t)i * nY + j) * nZp + g * 8);
}

/* The same backprojection with the eight lanes along x instead of z, for thin volumes (a single
 * slice would leave seven of eight z lanes idle). Output layout out[(k * nY + j) * nXp + i], x
 * fastest. Global size (nXp / 8, nY, nZ). */
__kernel void fdk_backproject_x(__global const real *q, __global const real *trig, __global real *out,
                                __global const real *geo, int n_views, int nXp, int nY, int nU, int nV)
{
    const int g = get_global_id(0), j = get_global_id(1), k = get_global_id(2);
    const real8 x = geo[0] + ((real8)(0, 1, 2, 3, 4, 5, 6, 7) + (real)(g * 8)) * geo[3];
    const real y = geo[1] + (real)j * geo[4];
    const real z = geo[2] + (real)k * geo[5];
    const real DSO = geo[6], DSD = geo[7], dU = geo[8], dV = geo[9], ou = geo[10], ov = geo[11];
    const real cu = geo[12], cv = geo[13];
    const real hiU = (real)nU, hiV = (real)nV;
    const int SV = nV + 3, SU = (nU + 3) * SV;
    real8 acc = (real8)0;

    for (int n = 0; n < n_views; ++n) {
        real c = trig[2 * n], s = trig[2 * n + 1];
        real8 xu = y * c - x * s;
#ifdef CONE
        real8 depth = DSO - (x * c + y * s);
        real8 mag = DSD / depth;
        real8 w = DSO / depth;
        w = w * w;
        real8 uf = (xu * mag - ou) / dU + cu;
        real8 vf = (z * mag - ov) / dV + cv;
#else
        real8 w = (real8)1;
        real8 uf = (xu - ou) / dU + cu;
        real8 vf = (real8)((z - ov) / dV + cv);
#endif
        uf = uf < (real8)-1 ? (real8)-1 : uf;
        uf = uf > (real8)hiU ? (real8)hiU : uf;
        vf = vf < (real8)-1 ? (real8)-1 : vf;
        vf = vf > (real8)hiV ? (real8)hiV : vf;
        acc += w * bilinear8(q + (size_t)n * SU, SV, uf + (real8)1, vf + (real8)1);
    }
    vstore8(acc, 0, out + ((size_t)k * nY + j) * nXp + g * 8);
}

/* The same weighted backprojection for a per-view (vector) geometry: each view's own 3 x 4
 * projection matrix (row-major, mats[12 n ...]) takes a voxel centre (x, y, z, 1), mm in the
 * scanner's frame, to (u' w, v' w, w): u', v' its padded detector coordinates (pixel index + 1)
 * and, for cone beam, w the voxel's depth from the source along the detector normal over that of
 * the frame's origin (the isocentre: DSO for a circular scan), so the distance weight 1 / w^2 is
 * the circular (DSO / depth)^2; the host folds each view's constant factors into the filtered
 * projections. Parallel beam: w = 1, weight 1. A voxel at or behind the source plane
 * (w <= 1e-4) gets nothing from that view.
 *
 * Eight lanes per work-item along one volume axis, chosen by the host: voxel (l, k1, k2) of
 * work-item (g, k1, k2) sits at p0 + (8 g + l) e0 + k1 e1 + k2 e2, and is written to
 * out[(k2 * n1 + k1) * nLp + 8 g + l]. geo: p0 (3), e0 (3), e1 (3), e2 (3), mm.
 * Global size (nLp / 8, n1, n2). Same padded layout of q as above. */
__kernel void fdk_backproject_vec(__global const real *q, __global const real *mats, __global real *out,
                                  __global const real *geo, int n_views, int nLp, int n1, int nU, int nV)
{
    const int g = get_global_id(0), k1 = get_global_id(1), k2 = get_global_id(2);
    const real px = geo[0] + (real)(g * 8) * geo[3] + (real)k1 * geo[6] + (real)k2 * geo[9];
    const real py = geo[1] + (real)(g * 8) * geo[4] + (real)k1 * geo[7] + (real)k2 * geo[10];
    const real pz = geo[2] + (real)(g * 8) * geo[5] + (real)k1 * geo[8] + (real)k2 * geo[11];
    const real ex = geo[3], ey = geo[4], ez = geo[5];
    const real8 lane = (real8)(0, 1, 2, 3, 4, 5, 6, 7);
    const real hiU = (real)(nU + 1), hiV = (real)(nV + 1);
    const int SV = nV + 3, SU = (nU + 3) * SV;
    real8 acc = (real8)0;

    for (int n = 0; n < n_views; ++n) {
        __global const real *m = mats + 12 * n;
        real8 uf = (m[0] * px + m[1] * py + m[2] * pz + m[3]) + lane * (m[0] * ex + m[1] * ey + m[2] * ez);
        real8 vf = (m[4] * px + m[5] * py + m[6] * pz + m[7]) + lane * (m[4] * ex + m[5] * ey + m[6] * ez);
#ifdef CONE
        real8 w = (m[8] * px + m[9] * py + m[10] * pz + m[11]) + lane * (m[8] * ex + m[9] * ey + m[10] * ez);
        const real8 inv = (real8)1 / (w > (real8)1e-4 ? w : (real8)1);
        const real8 wt = w > (real8)1e-4 ? inv * inv : (real8)0;
        uf *= inv;
        vf *= inv;
#else
        const real8 wt = (real8)1;
#endif
        uf = uf < (real8)0 ? (real8)0 : uf;     /* padded coordinates: 0 and nU + 1 are zero */
        uf = uf > (real8)hiU ? (real8)hiU : uf;
        vf = vf < (real8)0 ? (real8)0 : vf;
        vf = vf > (real8)hiV ? (real8)hiV : vf;
        acc += wt * bilinear8(q + (size_t)n * SU, SV, uf, vf);
    }
    vstore8(acc, 0, out + ((size_t)k2 * n1 + k1) * nLp + g * 8);
}
