/* Exact transpose of ct_forward (Joseph's method), as a gather: no atomics, each output voxel is
 * written by exactly one work-item, so results are bitwise reproducible.
 *
 * A ray that steps along x reaches voxel (i, j, k) only on the plane x = i, with weight
 * (1 - |y - j|) (1 - |z - k|) times the ray's length per plane; likewise for rays stepping
 * along y. So the rays that touch the voxel cross the segment (i, j-1)-(i, j+1) or the segment
 * (i-1, j)-(i+1, j), whose points lie within one voxel of the centre: the candidate detector
 * columns are those within H columns of the centre's projection (H, per view, bounds the
 * detector footprint of one voxel at the nearest depth; host-computed), and the candidate rows
 * those within the projection of z in (k0 - 1, k0 + ZB) (with a margin for the depth change across
 * the segments). For each candidate column the ray set-up is the forward kernel's own
 * (ct_column, tabulated once per view and column by ct_columns), so weights agree with the
 * forward to rounding; the exact weights are zero for candidates that do not touch.
 *
 * The host has already multiplied each pixel by its ray's length scale |D| in mm (the forward
 * kernel applies the same factor per ray), so the inner loop has no square root.
 *
 * One work-item: a column (i, j) and ZB = 32 consecutive z voxels, so that the per-view and
 * per-column set-up is shared by many voxels; they are four float8 accumulators. Each row v of a
 * candidate column meets the column at height z and adds to the one or two blocks of eight that
 * hold the voxels around z (hat weights on the block's eight lanes).
 * Global size (nZp / ZB, nY, nX). Output layout: out[(i * nY + j) * nZp + k], z fastest.
 *
 * View record entries 12-15 (host): H (columns), delta (relative depth change across a voxel),
 * 1 / (z step per row), cone: cross(b0, bu) / parallel: 1 / cross(au, b0).
 */
#include "ct_project.cl"

inline real ct_cross(real ax, real ay, real bx, real by) { return ax * by - ay * bx; }

/* Per view and column: om, inv_dm, oo, dn, main_x (1 or 0), |inv_dm|. Global size (nU, n_views). */
__kernel void ct_columns(__global const real *views, __global real *table, int nU)
{
    const int u = get_global_id(0), n = get_global_id(1);
    column_t c = ct_column(views + n * VIEW_STRIDE, (real)u);
    __global real *row = table + ((size_t)n * nU + u) * 8;
    row[0] = c.om; row[1] = c.inv_dm; row[2] = c.oo; row[3] = c.dn;
    row[4] = c.main_x ? (real)1 : (real)0;
    row[5] = c.inv_dm < 0 ? -c.inv_dm : c.inv_dm;
    row[6] = 0; row[7] = 0;
}

#define ZB 32  /* z voxels per work-item: four float8 blocks */

/* hat weights max(0, 1 - |z - k|) of the eight voxels k = 0..7 of a block */
inline real8 ct_hat(real z, real8 k8)
{
    real8 d = (real8)z - k8;
    d = d < (real8)0 ? -d : d;
    d = (real8)1 - d;
    return d > (real8)0 ? d : (real8)0;
}
#define HAT(z) ct_hat(z, k8)

__kernel void ct_backward(__global const real *proj, __global const real *views, __global const real *table,
                          __global real *out, int n_views, int nX, int nY, int nZ, int nZp, int nU, int nV,
                          int nVp)
{
    const int g = get_global_id(0), j = get_global_id(1), i = get_global_id(2);
    const int k0 = g * ZB;
    const real fi = (real)i, fj = (real)j;
    const real zlo = (real)(k0 - 1), zhi = (real)(k0 + ZB);
    const real8 k8 = (real8)(0, 1, 2, 3, 4, 5, 6, 7);
    real8 acc0 = (real8)0, acc1 = (real8)0, acc2 = (real8)0, acc3 = (real8)0;

    for (int n = 0; n < n_views; ++n) {
        __global const real *view = views + n * VIEW_STRIDE;
        const real H = view[12];
#ifdef CONE
        real qx = fi - view[0], qy = fj - view[1];
        real inv = (real)1 / ct_cross(view[6], view[7], qx, qy);
        real uc = -ct_cross(view[4], view[5], qx, qy) * inv;
        real il = -view[15] * inv;                 /* 1 / lambda: detector distance / point distance */
        real e0 = (zlo - view[8]) * il, e1 = (zhi - view[8]) * il;   /* z - source z, scaled */
        real m0 = e0 < 0 ? -e0 : e0, m1 = e1 < 0 ? -e1 : e1;
        real margin = (m0 > m1 ? m0 : m1) * view[13];
        real r0 = (e0 - margin - view[10]) * view[14], r1 = (e1 + margin - view[10]) * view[14];
#else
        real uc = ct_cross(fi - view[0], fj - view[1], view[4], view[5]) * view[15];
        real r0 = (zlo - view[8]) * view[14], r1 = (zhi - view[8]) * view[14];
#endif
        real ua = uc - H, ub = uc + H;
        if (!(ub >= 0 && ua <= (real)(nU - 1))) continue;  /* also skips NaN */
        if (!(r1 >= 0 && r0 <= (real)(nV - 1))) continue;
        int ulo = ua < 0 ? 0 : (int)ua;
        int uhi = ub > (real)(nU - 1) ? nU - 1 : (int)ub + 1;
        if (uhi > nU - 1) uhi = nU - 1;
        int vlo = r0 < 0 ? 0 : (int)r0;
        int vhi = r1 > (real)(nV - 1) ? nV - 1 : (int)r1 + 1;
        if (vhi > nV - 1) vhi = nV - 1;
        __global const real *pview = proj + (size_t)n * nU * nVp;
        __global const real *tview = table + (size_t)n * nU * 8;

        for (int u = ulo; u <= uhi; ++u) {
            real8 c = vload8(u, tview);
            int main_x = c.s4 > (real)0.5;
            real plane = main_x ? fi : fj, other = main_x ? fj : fi;
            real t = (plane - c.s0) * c.s1;
#ifdef CONE
            if (!(t > 0)) continue;
#endif
            real co = c.s2 + t * c.s3;
            real d = co - other;
            d = d < 0 ? -d : d;
            real wo = (real)1 - d;
            if (!(wo > 0)) continue;
            /* local height of row v: lz = z - k0 = A + v B */
            real A = view[8] + t * view[10] - (real)k0, B = view[9] + t * view[11];
            real wcol = wo * c.s5;
            __global const real *pcol = pview + (size_t)u * nVp;
            for (int v = vlo; v <= vhi; ++v) {
                real lz = A + (real)v * B;
                if (!(lz > (real)-1 && lz < (real)ZB)) continue;
                real p = pcol[v] * wcol;
                /* the row touches voxels floor(lz) and floor(lz) + 1: one block of 8, or two */
                if (lz < (real)8) acc0 += p * HAT(lz);
                if (lz > (real)7 && lz < (real)16) acc1 += p * HAT(lz - (real)8);
                if (lz > (real)15 && lz < (real)24) acc2 += p * HAT(lz - (real)16);
                if (lz > (real)23) acc3 += p * HAT(lz - (real)24);
            }
        }
    }
    __global real *dst = out + ((size_t)i * nY + j) * nZp + k0;
    vstore8(acc0, 0, dst);
    vstore8(acc1, 1, dst);
    vstore8(acc2, 2, dst);
    vstore8(acc3, 3, dst);
}
