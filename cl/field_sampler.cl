/* Trilinear sampling of a vector field on a regular grid, and its two gradients, without atomics.
 *
 * The field: C planes of Z * Y * X reals, x fastest. Points: three planes (x, y, z) of P reals in
 * voxel units (voxel (i, j, k) at x = i, y = j, z = k), P padded to a multiple of 8 (the pad is
 * never stored). Outside the grid a coordinate is clamped to [0, n - 1] (the border value) and
 * its derivative is 0 there, on the border included, as torch's grid_sample with
 * padding_mode="border", align_corners=True. Every axis has n >= 2 (the host checks).
 *
 * Each point lies in a cell (i0, j0, k0) with i0 = min(floor(x), X - 2): the cell's eight corners
 * are its samples' support, weights (1 - fx or fx) (1 - fy or fy) (1 - fz or fz), corner number
 * dx + 2 dy + 4 dz.
 *
 * sample_fwd        out (C planes of Pp), cell id of each point     one work-item per 8 points
 * sample_grad_pts   gradient wrt the points                         one work-item per 8 points
 * sample_cell_sums  per cell and channel, the 8 corner weights times the upstream gradient summed
 *                   over the cell's points (points sorted by cell: order, cell_start)
 *                   one work-item per CELLS_PER_ITEM cells, points in sorted order
 * sample_grad_field gradient wrt the field: each voxel gathers its share from the (up to) eight
 *                   cells it is a corner of                          one work-item per 8 voxels in x
 *
 * The gradient wrt the field is thus a gather in a fixed order: the same input gives the same bits.
 */
#include "common.h"

#ifndef CELLS_PER_ITEM
#define CELLS_PER_ITEM 32
#endif

/* Clamp a coordinate to [0, n - 1]; cell index (at most n - 2), fraction in the cell, and the
 * derivative of the clamp (1 strictly inside, else 0). NaN goes to 0 with derivative 0. */
static inline void axis8(real8 x, int n, int8 *i0, real8 *f, real8 *d)
{
    const real hi = (real)(n - 1);
    real8 xc = select((real8)0, x, x > (real8)0);           /* NaN and x <= 0 -> 0 */
    xc = select((real8)hi, xc, xc < (real8)hi);
    *d = select((real8)0, (real8)1, (x > (real8)0) && (x < (real8)hi));
    int8 i = convert_int8(xc);                              /* xc >= 0: truncation is floor */
    i = select(i, (int8)(n - 2), i > (int8)(n - 2));
    *i0 = i;
    *f = xc - convert_real8(i);
}

static inline void axis1(real x, int n, int *i0, real *f)
{
    const real hi = (real)(n - 1);
    real xc = x > (real)0 ? (x < hi ? x : hi) : (real)0;
    int i = (int)xc;
    i = i > n - 2 ? n - 2 : i;
    *i0 = i;
    *f = xc - (real)i;
}

/* Where eight consecutive points fall: cell fractions, clamp derivatives, the flat index of each
 * cell's corner (0, 0, 0) and the cell number. */
typedef struct {
    real8 fx, fy, fz, dx, dy, dz;
    int8 base, cell;
} Where8;

static inline Where8 locate8(__global const real *pts, int g, int Pp, int X, int Y, int Z)
{
    Where8 w;
    int8 ix, iy, iz;
    axis8(vload8(g, pts), X, &ix, &w.fx, &w.dx);
    axis8(vload8(g, pts + Pp), Y, &iy, &w.fy, &w.dy);
    axis8(vload8(g, pts + 2 * Pp), Z, &iz, &w.fz, &w.dz);
    w.base = (iz * Y + iy) * X + ix;
    w.cell = (iz * (Y - 1) + iy) * (X - 1) + ix;
    return w;
}

/* The field plane's values at the eight corners of each point's cell, v[dx + 2 dy + 4 dz]. */
static inline void corners8(__global const real *fc, int8 b, int SY, int SZ, real8 *v)
{
    v[0] = GATHER8(fc, 0, b);
    v[1] = GATHER8(fc, 0, b + 1);
    v[2] = GATHER8(fc, 0, b + SY);
    v[3] = GATHER8(fc, 0, b + SY + 1);
    v[4] = GATHER8(fc, 0, b + SZ);
    v[5] = GATHER8(fc, 0, b + SZ + 1);
    v[6] = GATHER8(fc, 0, b + SZ + SY);
    v[7] = GATHER8(fc, 0, b + SZ + SY + 1);
}

__kernel void sample_fwd(__global const real *field, __global const real *pts, __global real *out,
                         __global int *cells, int Pp, int C, int X, int Y, int Z)
{
    const int g = get_global_id(0);
    const Where8 w = locate8(pts, g, Pp, X, Y, Z);
    const long plane = (long)X * Y * Z;
    const real8 gx = (real8)1 - w.fx, gy = (real8)1 - w.fy, gz = (real8)1 - w.fz;
    real8 v[8];
    for (int c = 0; c < C; ++c) {
        corners8(field + c * plane, w.base, X, X * Y, v);
        real8 a0 = gy * (gx * v[0] + w.fx * v[1]) + w.fy * (gx * v[2] + w.fx * v[3]);
        real8 a1 = gy * (gx * v[4] + w.fx * v[5]) + w.fy * (gx * v[6] + w.fx * v[7]);
        vstore8(gz * a0 + w.fz * a1, g, out + (long)c * Pp);
    }
    vstore8(w.cell, g, cells);
}

__kernel void sample_grad_pts(__global const real *field, __global const real *pts, __global const real *gout,
                              __global real *gpts, int Pp, int C, int X, int Y, int Z)
{
    const int g = get_global_id(0);
    const Where8 w = locate8(pts, g, Pp, X, Y, Z);
    const long plane = (long)X * Y * Z;
    const real8 gx = (real8)1 - w.fx, gy = (real8)1 - w.fy, gz = (real8)1 - w.fz;
    real8 ax = (real8)0, ay = (real8)0, az = (real8)0, v[8];
    for (int c = 0; c < C; ++c) {
        const real8 up = vload8(g, gout + (long)c * Pp);   /* the pad lanes hold zeros */
        corners8(field + c * plane, w.base, X, X * Y, v);
        real8 ex0 = gy * (v[1] - v[0]) + w.fy * (v[3] - v[2]);
        real8 ex1 = gy * (v[5] - v[4]) + w.fy * (v[7] - v[6]);
        real8 ey0 = gx * (v[2] - v[0]) + w.fx * (v[3] - v[1]);
        real8 ey1 = gx * (v[6] - v[4]) + w.fx * (v[7] - v[5]);
        real8 a0 = gy * (gx * v[0] + w.fx * v[1]) + w.fy * (gx * v[2] + w.fx * v[3]);
        real8 a1 = gy * (gx * v[4] + w.fx * v[5]) + w.fy * (gx * v[6] + w.fx * v[7]);
        ax += up * (gz * ex0 + w.fz * ex1);
        ay += up * (gz * ey0 + w.fz * ey1);
        az += up * (a1 - a0);
    }
    vstore8(ax * w.dx, g, gpts);
    vstore8(ay * w.dy, g, gpts + Pp);
    vstore8(az * w.dz, g, gpts + 2 * Pp);
}

/* sums[GUARD + (c * 8 + corner) * n_cells + cell]: one plane per channel and corner, cells in x-fastest
 * order, GUARD spare entries before the first plane and after the last (sample_grad_field reads
 * one entry before a row and up to eight past it, into lanes it discards). */
#define GUARD 16
__kernel void sample_cell_sums(__global const real *pts, __global const real *gout, __global const int *order,
                               __global const int *cell_start, __global real *sums, int n_cells, int Pp,
                               int C, int X, int Y, int Z)
{
    const int first = get_global_id(0) * CELLS_PER_ITEM;
    const int last = min(first + CELLS_PER_ITEM, n_cells);
    __global real *out = sums + GUARD;
    for (int cell = first; cell < last; ++cell) {
        real8 acc[4] = {(real8)0, (real8)0, (real8)0, (real8)0};  /* C <= 4 */
        for (int k = cell_start[cell]; k < cell_start[cell + 1]; ++k) {
            const int i = order[k];
            int ix, iy, iz;
            real fx, fy, fz;
            axis1(pts[i], X, &ix, &fx);
            axis1(pts[Pp + i], Y, &iy, &fy);
            axis1(pts[2 * Pp + i], Z, &iz, &fz);
            const real gx = (real)1 - fx, gy = (real)1 - fy, gz = (real)1 - fz;
            real8 w = (real8)(gz * gy * gx, gz * gy * fx, gz * fy * gx, gz * fy * fx,
                              fz * gy * gx, fz * gy * fx, fz * fy * gx, fz * fy * fx);
            for (int c = 0; c < C; ++c) acc[c] += w * gout[(long)c * Pp + i];
        }
        for (int c = 0; c < C; ++c) {
            real t[8];
            vstore8(acc[c], 0, t);
            for (int k = 0; k < 8; ++k) out[(long)(c * 8 + k) * n_cells + cell] = t[k];
        }
    }
}

/* One work-item per eight voxels along x: gfield[c][z][y][x] = the sum over the cells the voxel is
 * corner (dx, dy, dz) of, cell (x - dx, y - dy, z - dz), of that cell's corner sum. */
__kernel void sample_grad_field(__global const real *sums, __global real *gfield, int n_cells, int C, int X,
                                int Y, int Z)
{
    const int x0 = get_global_id(0) * 8, y = get_global_id(1), z = get_global_id(2);
    const int CX = X - 1, CY = Y - 1;
    const long plane = (long)X * Y * Z;
    const int8 lane = (int8)(0, 1, 2, 3, 4, 5, 6, 7) + x0;
    const int8 ok0 = lane < CX;                   /* cell x - 0 exists */
    const int8 ok1 = (lane >= 1) && (lane <= CX);  /* cell x - 1 exists */
    __global const real *base = sums + GUARD + x0;
    for (int c = 0; c < C; ++c) {
        real8 acc = (real8)0;
        for (int dz = 0; dz < 2; ++dz) {
            const int cz = z - dz;
            if (cz < 0 || cz >= Z - 1) continue;
            for (int dy = 0; dy < 2; ++dy) {
                const int cy = y - dy;
                if (cy < 0 || cy >= CY) continue;
                const long row = ((long)cz * CY + cy) * CX;
                const int k = 2 * dy + 4 * dz;
                __global const real *p0 = base + (long)(c * 8 + k) * n_cells + row;
                __global const real *p1 = base + (long)(c * 8 + k + 1) * n_cells + row - 1;
                acc += select((real8)0, vload8(0, p0), convert_mask8(ok0));
                acc += select((real8)0, vload8(0, p1), convert_mask8(ok1));
            }
        }
        __global real *o = gfield + c * plane + ((long)z * Y + y) * X;
        if (x0 + 8 <= X) {
            vstore8(acc, 0, o + x0);
        } else {
            real t[8];
            vstore8(acc, 0, t);
            for (int l = 0; x0 + l < X; ++l) o[x0 + l] = t[l];
        }
    }
}
