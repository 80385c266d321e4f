/* Voxel-volume X-ray projector (Joseph's method), forward direction.
 *
 * Everything here works in voxel-index coordinates: voxel [k][j][i] has its centre at (i, j, k).
 * The host converts each view to that frame and packs it as 16 numbers (the first 12 here):
 *   in-plane origin   O(u) = (a0x + u aux, a0y + u auy)
 *   in-plane direction D(u) = (b0x + u bux, b0y + u buy)
 *   z origin / direction  Oz(v) = oz0 + v ozv,  Dz(v) = dz0 + v dzv
 * Cone beam: O is the source and D = pixel - source (so only t > 0 counts). Parallel beam: O is the
 * pixel and D the ray direction (the whole line counts). A point of a ray is O + t D.
 *
 * Joseph's method: a ray steps through the voxel-centre planes of its main in-plane axis (x when
 * |Dx| >= |Dy|, else y); on each plane the volume is interpolated bilinearly in (other in-plane
 * axis, z), and each plane contributes the length of ray between planes, |D_mm| / |D_main|.
 * The detector's v axis is z and its u axis is horizontal (circular orbit), so a ray never steps
 * along z: rays steeper than 45 degrees in voxel units would be sampled more coarsely in z
 * (the host warns about such geometries).
 *
 * The backprojector (ct_backprojector.cl) evaluates the same weights from the voxel's side, so the
 * pair is an exact transpose without atomics.
 *
 * Memory layouts (host prepares them):
 *   volume: padded, z fastest: vol[(i + 1) * SX + (j + 1) * SY + (k + 1)], with SY = nZ + 3,
 *           SX = (nY + 3) SY; one zero voxel before and two after each axis, so clamped
 *           coordinates read zeros without bounds checks.
 *   projections: proj[(view * nU + u) * nVp + v], v fastest, nVp = nV rounded up to 8.
 */
#include "common.h"

#define VIEW_STRIDE 16
/* a0x a0y aux auy b0x b0y bux buy oz0 ozv dz0 dzv, then four entries for the backprojector */

typedef struct {
    real ox, oy, dx, dy;  /* in-plane origin and direction of column u */
    int main_x;           /* 1: step along x planes, 0: along y planes */
    real om, inv_dm;      /* main-axis origin, 1 / main-axis direction */
    real oo, dn;          /* other in-plane axis origin and direction */
} column_t;

inline column_t ct_column(__global const real *view, real u)
{
    column_t c;
    c.ox = view[0] + u * view[2];
    c.oy = view[1] + u * view[3];
    c.dx = view[4] + u * view[6];
    c.dy = view[5] + u * view[7];
    real ax = c.dx < 0 ? -c.dx : c.dx;
    real ay = c.dy < 0 ? -c.dy : c.dy;
    c.main_x = ax >= ay;
    if (c.main_x) {
        c.om = c.ox; c.inv_dm = (real)1 / c.dx; c.oo = c.oy; c.dn = c.dy;
    } else {
        c.om = c.oy; c.inv_dm = (real)1 / c.dy; c.oo = c.ox; c.dn = c.dx;
    }
    return c;
}

/* Restrict the integer range [*lo, *hi] to planes i where A + B * i lies in (lo_v, hi_v),
 * with one plane of margin (the exact weights are zero outside, so a margin only costs time). */
inline void ct_restrict(real A, real B, real lo_v, real hi_v, int *lo, int *hi)
{
    if (B == 0) {
        if (!(A > lo_v && A < hi_v)) { *lo = 1; *hi = 0; }
        return;
    }
    real r0 = (lo_v - A) / B, r1 = (hi_v - A) / B;
    real a = r0 < r1 ? r0 : r1, b = r0 < r1 ? r1 : r0;
    a = a < -1e6f ? -1e6f : a;
    b = b > 1e6f ? 1e6f : b;
    int ia = (int)floor(a), ib = (int)ceil(b);  /* exact range is ceil(a) .. floor(b) */
    if (ia > *lo) *lo = ia;
    if (ib < *hi) *hi = ib;
}


/* One work-item: one view, one detector column u, eight consecutive rows v (a float8 of rays
 * sharing their in-plane path). Global size (nVp / 8, nU, n_views). */
__kernel void ct_forward(__global const real *vol, __global const real *views,
                         __global real *proj, int nX, int nY, int nZ, int nU, int nVp,
                         real sx, real sy, real sz)
{
    const int g = get_global_id(0), u = get_global_id(1), n = get_global_id(2);
    __global const real *view = views + n * VIEW_STRIDE;
    column_t c = ct_column(view, (real)u);

    const int SY = nZ + 3, SX = (nY + 3) * SY;
    int n_main = c.main_x ? nX : nY, n_other = c.main_x ? nY : nX;
    int stride_m = c.main_x ? SX : SY, stride_o = c.main_x ? SY : SX;

    real8 v8 = (real8)(0, 1, 2, 3, 4, 5, 6, 7) + (real)(g * 8);
    real8 zo = view[8] + v8 * view[9];
    real8 zd = view[10] + v8 * view[11];

    /* planes that can contribute */
    int lo = 0, hi = n_main - 1;
    real slope = c.dn * c.inv_dm;               /* other-axis change per plane */
    ct_restrict(c.oo - c.om * slope, slope, (real)-1, (real)n_other, &lo, &hi);
#ifdef CONE
    if (c.inv_dm > 0) { int f = (int)floor(c.om) + 1; if (f > lo) lo = f; }
    else { int f = (int)ceil(c.om) - 1; if (f < hi) hi = f; }
    /* z of the lowest and highest ray of the group: t = (i - om) inv_dm */
    ct_restrict(zo.s0 - c.om * c.inv_dm * zd.s0, c.inv_dm * zd.s0, (real)-1e30f, (real)nZ, &lo, &hi);
    ct_restrict(zo.s7 - c.om * c.inv_dm * zd.s7, c.inv_dm * zd.s7, (real)-1, (real)1e30f, &lo, &hi);
#else
    if (!(zo.s0 < (real)nZ && zo.s7 > (real)-1)) hi = lo - 1;
#endif
    if (lo < 0) lo = 0;
    if (hi > n_main - 1) hi = n_main - 1;

    real8 acc = (real8)0;
    const real hiZ = (real)nZ, hiO = (real)n_other;
    for (int i = lo; i <= hi; ++i) {
        real t = ((real)i - c.om) * c.inv_dm;
        real co = c.oo + t * c.dn;
        co = co < (real)-1 ? (real)-1 : (co > hiO ? hiO : co);
        int jc = (int)(co + (real)1);         /* padded index of floor(co) */
        real fc = co + (real)1 - (real)jc;
        real8 z = zo + t * zd;
        z = z < (real8)-1 ? (real8)-1 : z;
        z = z > (real8)hiZ ? (real8)hiZ : z;
        real8 zp = z + (real8)1;
        int8 kz = convert_int8(zp);            /* padded index of floor(z) */
        real8 fz = zp - convert_real8(kz);
        int base0 = (i + 1) * stride_m + jc * stride_o;
        int base1 = base0 + stride_o;
        real8 a0 = GATHER8(vol, base0, kz);
        real8 a1 = GATHER8(vol, base0 + 1, kz);
        real8 b0 = GATHER8(vol, base1, kz);
        real8 b1 = GATHER8(vol, base1 + 1, kz);
        real8 ca = a0 + fz * (a1 - a0);
        real8 cb = b0 + fz * (b1 - b0);
        acc += ca + fc * (cb - ca);
    }
    /* length of ray per plane, in mm */
    real wx = c.dx * sx, wy = c.dy * sy;
    real8 wz = zd * sz;
    real adm = c.inv_dm < 0 ? -c.inv_dm : c.inv_dm;
    real8 len = sqrt((real8)(wx * wx + wy * wy) + wz * wz) * adm;
    vstore8(acc * len, 0, proj + ((size_t)n * nU + u) * nVp + g * 8);
}
