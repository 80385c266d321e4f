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

#ifdef REAL_DOUBLE
#define convert_real8 convert_double8
#else
#define convert_real8 convert_float8
#endif

#define GATHER8(ptr, base, idx) \
    (real8)((ptr)[(base) + (idx).s0], (ptr)[(base) + (idx).s1], (ptr)[(base) + (idx).s2], \
            (ptr)[(base) + (idx).s3], (ptr)[(base) + (idx).s4], (ptr)[(base) + (idx).s5], \
            (ptr)[(base) + (idx).s6], (ptr)[(base) + (idx).s7])

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
        real8 up = uf + (real8)1, vp = vf + (real8)1;
        int8 ku = convert_int8(up), kv = convert_int8(vp);
        real8 fu = up - convert_real8(ku), fv = vp - convert_real8(kv);
        __global const real *qv = q + (size_t)n * SU;
        int8 idx = ku * SV + kv;
        real8 a0 = GATHER8(qv, 0, idx);
        real8 a1 = GATHER8(qv, 1, idx);
        real8 b0 = GATHER8(qv, SV, idx);
        real8 b1 = GATHER8(qv, SV + 1, idx);
        real8 ca = a0 + fv * (a1 - a0);
        real8 cb = b0 + fv * (b1 - b0);
        acc += w * (ca + fu * (cb - ca));
    }
    vstore8(acc, 0, out + ((size_t)k * nY + j) * nXp + g * 8);
}
