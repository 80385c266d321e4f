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
 * One work-item: a column (i, j) and ZB = 32 consecutive z voxels (four float8 accumulators),
 * so the per-view and per-column set-up is shared by 32 voxels: per view the candidate columns
 * are set up once (up to UMAX at a time, in private arrays), then each block of eight voxels
 * gathers their rows in its own z range with hat weights on its eight lanes.
 * Global size (nZp / ZB, nY, nX). Output layout: out[(i * nY + j) * nZp + k], z fastest.
 *
 * View record entries 12-15 (host): H (columns), delta (relative depth change across a voxel),
 * 1 / (z step per row), cone: cross(b0, bu) / parallel: 1 / cross(au, b0).
 */
#include "ct_projector.cl"

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

#define ZB 32     /* z voxels per work-item: four blocks of eight */
#define UMAX 16   /* candidate columns set up at once */

/* hat weights max(0, 1 - |z - k|) of the eight voxels k = 0..7 of a block */
inline real8 ct_hat(real z, real8 k8)
{
    real8 d = (real8)z - k8;
    d = d < (real8)0 ? -d : d;
    d = (real8)1 - d;
    return d > (real8)0 ? d : (real8)0;
}

/* rows that can meet z in (zlo, zhi) for this voxel column and view (see the header) */
#ifdef CONE
#define ROW_RANGE(zlo, zhi, vlo, vhi) {                                              \
        real e0 = ((zlo) - view[8]) * il, e1 = ((zhi) - view[8]) * il;               \
        real m0 = e0 < 0 ? -e0 : e0, m1 = e1 < 0 ? -e1 : e1;                         \
        real margin = (m0 > m1 ? m0 : m1) * view[13];                                \
        real r0 = (e0 - margin - view[10]) * view[14], r1 = (e1 + margin - view[10]) * view[14]; \
        vlo = r0 < 0 ? 0 : (r0 > (real)nV ? nV : (int)r0);                           \
        vhi = r1 < 0 ? -1 : (r1 > (real)(nV - 1) ? nV - 1 : (int)r1 + 1);            \
        if (vhi > nV - 1) vhi = nV - 1; }
#else
#define ROW_RANGE(zlo, zhi, vlo, vhi) {                                              \
        real r0 = ((zlo) - view[8]) * view[14], r1 = ((zhi) - view[8]) * view[14];   \
        vlo = r0 < 0 ? 0 : (r0 > (real)nV ? nV : (int)r0);                           \
        vhi = r1 < 0 ? -1 : (r1 > (real)(nV - 1) ? nV - 1 : (int)r1 + 1);            \
        if (vhi > nV - 1) vhi = nV - 1; }
#endif

/* block b (0..3) of the work-item's column: every candidate column's rows in range */
#define BLOCK(b, acc) {                                                              \
        int vlo, vhi;                                                                \
        ROW_RANGE((real)(k0 + 8 * (b) - 1), (real)(k0 + 8 * (b) + 8), vlo, vhi);     \
        for (int c = 0; c < nc; ++c) {                                               \
            real A = cA[c] - (real)(8 * (b)), B = cB[c], w = cW[c];                  \
            __global const real *pcol = pview + (size_t)cU[c] * nVp;                 \
            for (int v = vlo; v <= vhi; ++v)                                         \
                acc += (pcol[v] * w) * ct_hat(A + (real)v * B, k8);                  \
        } }

__kernel void ct_backward(__global const real *proj, __global const real *views, __global const real *table,
                          __global real *out, int n_views, int nX, int nY, int nZ, int nZp, int nU, int nV,
                          int nVp)
{
    const int g = get_global_id(0), j = get_global_id(1), i = get_global_id(2);
    const int k0 = g * ZB;
    const real fi = (real)i, fj = (real)j;
    const real8 k8 = (real8)(0, 1, 2, 3, 4, 5, 6, 7);
    real8 acc0 = (real8)0, acc1 = (real8)0, acc2 = (real8)0, acc3 = (real8)0;
    real cA[UMAX], cB[UMAX], cW[UMAX];
    int cU[UMAX];

    for (int n = 0; n < n_views; ++n) {
        __global const real *view = views + n * VIEW_STRIDE;
        const real H = view[12];
#ifdef CONE
        real qx = fi - view[0], qy = fj - view[1];
        real inv = (real)1 / ct_cross(view[6], view[7], qx, qy);
        real uc = -ct_cross(view[4], view[5], qx, qy) * inv;
        real il = -view[15] * inv;                 /* 1 / lambda: detector distance / point distance */
#else
        real uc = ct_cross(fi - view[0], fj - view[1], view[4], view[5]) * view[15];
#endif
        real ua = uc - H, ub = uc + H;
        if (!(ub >= 0 && ua <= (real)(nU - 1))) continue;  /* also skips NaN */
        int vlo_all, vhi_all;
        ROW_RANGE((real)(k0 - 1), (real)(k0 + ZB), vlo_all, vhi_all);
        if (vhi_all < vlo_all) continue;
        int ulo = ua < 0 ? 0 : (int)ua;
        int uhi = ub > (real)(nU - 1) ? nU - 1 : (int)ub + 1;
        if (uhi > nU - 1) uhi = nU - 1;
        __global const real *pview = proj + (size_t)n * nU * nVp;
        __global const real *tview = table + (size_t)n * nU * 8;

        for (int u_start = ulo; u_start <= uhi; u_start += UMAX) {
            /* set up the candidate columns that do touch the voxel column */
            int nc = 0;
            int u_end = u_start + UMAX - 1 < uhi ? u_start + UMAX - 1 : uhi;
            for (int u = u_start; u <= u_end; ++u) {
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
                cA[nc] = view[8] + t * view[10] - (real)k0;   /* height of row v: A + v B */
                cB[nc] = view[9] + t * view[11];
                cW[nc] = wo * c.s5;
                cU[nc] = u;
                ++nc;
            }
            if (nc == 0) continue;
            BLOCK(0, acc0);
            BLOCK(1, acc1);
            BLOCK(2, acc2);
            BLOCK(3, acc3);
        }
    }
    __global real *dst = out + ((size_t)i * nY + j) * nZp + k0;
    vstore8(acc0, 0, dst);
    vstore8(acc1, 1, dst);
    vstore8(acc2, 2, dst);
    vstore8(acc3, 3, dst);
}
