/* The fused TV patch (clgs.ops.tv_patch): built on the voxelizer's file, whose binning helpers
 * and vox_grid kernel it runs with its own kernels below (a program of its own, variants as the
 * voxelizer's: REAL, BRICK_Y, BRICK_Z, WANT_MEAN, WANT_PREC, WANT_RHO). */
#include "voxelizer.cl"

/* TV patch: the anisotropic total variation of the field on a small block (a random 32^3 patch)
 * and its gradient, from all N Gaussians, in one batch of launches with no host round trip:
 *   patch_cull  (per chunk of Gaussians) keeps those whose box meets the block's bricks, counts
 *               them per brick;
 *   patch_scan  (one work-item) offsets of chunks and of (chunk, brick) runs, in Gaussian order;
 *   patch_fill  (per chunk) packs the kept Gaussians' records in index order and fills the brick
 *               lists with their rank, so they are the lists bin_small makes for the same rows;
 *   vox_grid    the field (indexed lists);
 *   patch_tv    dTV/dmu per sample and the per-slice sums of |differences|;
 *   patch_grad  one kept Gaussian at a time: gradient rows in rank order.
 * Capacities are the host's: if the lists would overflow, patch_scan empties every list and sets
 * meta[2]; the host grows the buffer and runs again. meta = (kept, pairs, overflow, kept or 0). */

/* 8 consecutive Gaussians' (x, y, z) rows (stride 3) as three real8 of lanes: two contiguous
 * loads and shuffles */
inline void rows3(global const real *a, int i0, real8 *x, real8 *y, real8 *z)
{
    real16 u = vload16(0, a + (size_t)i0 * 3);
    real8 v = vload8(0, a + (size_t)i0 * 3 + 16);
    *x = (real8)(u.s0369, u.sc, u.sf, v.s25);
    *y = (real8)(u.s147a, u.sd, v.s036);
    *z = (real8)(u.s258b, u.se, v.s147);
}

/* (ox, oy, oz): the bricks' near corner, (hix, hiy, hiz) their far corner. A box that misses
 * [near - slack, far + slack] on an axis meets no brick (cell_range, which decides, widens cells
 * by less): 8 Gaussians are tested at a time (reading all N rows is what this kernel costs), and
 * the few that pass go through cell_range. Chunk c keeps its Gaussians' indices, in order, at
 * kept[c * chunk ...], their count in count[c] and its per-brick counts in hist[c * ncells ...]. */
__kernel void patch_cull(global const real *means, global const real *ext, int n, int chunk, int nchunks, CELL_ARGS,
                         real hix, real hiy, real hiz, real slack, global int *hist, global int *count, global int *kept)
{
    int c = get_global_id(0);
    if (c >= nchunks)
        return;
    int ncells = ncx * ncy * ncz;
    global int *h = hist + (size_t)c * ncells;
    for (int cell = 0; cell < ncells; cell++)
        h[cell] = 0;
    int i0 = c * chunk, i1 = min(n, i0 + chunk), cnt = 0;
    for (int b = i0; b < i1; b += 8) {
        int m = min(8, i1 - b);
        mask1 pass[8];
        if (m == 8) {
            real8 px, py, pz, ex, ey, ez;
            rows3(means, b, &px, &py, &pz);
            rows3(ext, b, &ex, &ey, &ez);
            ex += slack;
            ey += slack;
            ez += slack;
            mask8 in = (px + ex >= ox) & (px - ex <= hix) & (py + ey >= oy) & (py - ey <= hiy)
                      & (pz + ez >= oz) & (pz - ez <= hiz);
            /* NaN fails every comparison: such rows are dropped here as cell_range drops them */
            mask8 t = in;
            t.lo |= t.hi;
            t.s01 |= t.s23;
            if (!(t.s0 | t.s1)) /* no lane passed (any() is a call on PoCL) */
                continue;
            vstore8(in, 0, pass);
        } else {
            for (int l = 0; l < m; l++)
                pass[l] = 1;
        }
        for (int l = 0; l < m; l++) {
            if (!pass[l])
                continue;
            int i = b + l, x0, x1, y0, y1, z0, z1;
            global const real *p = means + (size_t)i * 3, *e = ext + (size_t)i * 3;
            if (!(cell_range(p[0], e[0], ox, isx, ncx, &x0, &x1) && cell_range(p[1], e[1], oy, isy, ncy, &y0, &y1)
                  && cell_range(p[2], e[2], oz, isz, ncz, &z0, &z1)))
                continue;
            kept[i0 + cnt++] = i;
            for (int z = z0; z <= z1; z++)
                for (int y = y0; y <= y1; y++)
                    for (int x = x0; x <= x1; x++)
                        h[(z * ncy + y) * ncx + x] += 1;
        }
    }
    count[c] = cnt;
}

__kernel void patch_scan(global const int *count, global int *hist, int nchunks, int ncells, int cap_list,
                         global int *koff, global int *start, global int *meta)
{
    if (get_global_id(0) != 0)
        return;
    int s = 0;
    for (int c = 0; c < nchunks; c++) {
        koff[c] = s;
        s += count[c];
    }
    long t = 0;
    for (int cell = 0; cell < ncells; cell++) {
        start[cell] = (int)min(t, (long)INT_MAX);
        for (int c = 0; c < nchunks; c++) {
            global int *h = hist + (size_t)c * ncells + cell;
            int v = *h;
            *h = (int)min(t, (long)INT_MAX);
            t += v;
        }
    }
    int over = t > (long)cap_list;
    if (over)
        for (int cell = 0; cell < ncells; cell++)
            start[cell] = 0;
    start[ncells] = over ? 0 : (int)t;
    meta[0] = s;
    meta[1] = (int)min(t, (long)INT_MAX);
    meta[2] = over;
    meta[3] = over ? 0 : s;
}

__kernel void patch_fill(global const real *means, global const real *prec, global const real *dens,
                         global const real *ext, int chunk, int nchunks, CELL_ARGS, global const int *count,
                         global const int *kept, global const int *koff, global int *hist, global const int *meta,
                         global real *packed, global int *kidx, global int *list)
{
    int c = get_global_id(0);
    if (c >= nchunks || meta[2])
        return;
    int ncells = ncx * ncy * ncz;
    global int *h = hist + (size_t)c * ncells;
    int cnt = count[c], k0 = koff[c];
    for (int j = 0; j < cnt; j++) {
        int i = kept[c * chunk + j], k = k0 + j;
        global const real *p = means + (size_t)i * 3, *e = ext + (size_t)i * 3, *q = prec + (size_t)i * 6;
        global real *r = packed + (size_t)k * GSTRIDE;
        r[0] = p[0]; r[1] = p[1]; r[2] = p[2]; r[3] = dens[i];
        r[4] = q[0]; r[5] = q[1]; r[6] = q[2]; r[7] = q[3]; r[8] = q[4]; r[9] = q[5];
        r[10] = e[0]; r[11] = e[1]; r[12] = e[2]; r[13] = 0; r[14] = 0; r[15] = 0;
        kidx[k] = i;
        int x0, x1, y0, y1, z0, z1;
        cell_range(p[0], e[0], ox, isx, ncx, &x0, &x1);
        cell_range(p[1], e[1], oy, isy, ncy, &y0, &y1);
        cell_range(p[2], e[2], oz, isz, ncz, &z0, &z1);
        for (int z = z0; z <= z1; z++)
            for (int y = y0; y <= y1; y++)
                for (int x = x0; x <= x1; x++)
                    list[h[(z * ncy + y) * ncx + x]++] = k;
    }
}

inline real8 sign8(real8 d)
{
    return (d > (real)0 ? (real8)(1) : (real8)(0)) - (d < (real)0 ? (real8)(1) : (real8)(0));
}

/* One work-item per z slice. The field f and the gradient g are (nz, ny) rows of pitch reals, row
 * r's sample x at [8 + r * pitch + x], pitch >= nx rounded up to 8, plus 16 (f's pads are never
 * read into a result; g's are written as zeros). With s_a(v) = sign(f(v + e_a) - f(v)) where v + e_a
 * is a sample, g(v) = sum_a (s_a(v - e_a) - s_a(v)) w_a, w_a = 1 / (number of differences along a)
 * (0 for an axis of one sample): the gradient of sum_a w_a sum |differences along a| (torch's sign(0)
 * = 0 convention). part[3 z + a]: that slice's sum of |differences| along x, y, z (z: to the next
 * slice). */
__kernel void patch_tv(global const real *f, int nx, int ny, int nz, int pitch, real wx, real wy, real wz,
                       global real *g, global real *part)
{
    int z = get_global_id(0);
    if (z >= nz)
        return;
    real8 ax = (real8)(0), ay = ax, az = ax;
    const real8 lane = (real8)(0, 1, 2, 3, 4, 5, 6, 7);
    for (int y = 0; y < ny; y++) {
        size_t row = 8 + ((size_t)z * ny + y) * pitch;
        global const real *fr = f + row;
        global const real *fyp = y > 0 ? fr - pitch : fr, *fyn = y + 1 < ny ? fr + pitch : fr;
        global const real *fzp = z > 0 ? fr - (size_t)ny * pitch : fr, *fzn = z + 1 < nz ? fr + (size_t)ny * pitch : fr;
        global real *gr = g + row;
        vstore8((real8)(0), 0, gr - 8);
        for (int x = 0; x < nx; x += 8) {
            real8 xl = lane + (real)x;
            real8 v = vload8(0, fr + x);
            /* lanes of samples; x differences need a sample on the other side too */
            real8 in = xl < (real)nx ? (real8)(1) : (real8)(0);
            real8 hasn = xl + (real)1 < (real)nx ? (real8)(1) : (real8)(0);
            real8 hasp = ((xl >= (real)1) & (xl < (real)nx)) ? (real8)(1) : (real8)(0);
            real8 dxn = vload8(0, fr + x + 1) - v, dxp = v - vload8(0, fr + x - 1);
            real8 dyn = vload8(0, fyn + x) - v, dyp = v - vload8(0, fyp + x);
            real8 dzn = vload8(0, fzn + x) - v, dzp = v - vload8(0, fzp + x);
            dxn = hasn != (real)0 ? dxn : (real8)(0);
            dxp = hasp != (real)0 ? dxp : (real8)(0);
            dyn = in != (real)0 ? dyn : (real8)(0);
            dyp = in != (real)0 ? dyp : (real8)(0);
            dzn = in != (real)0 ? dzn : (real8)(0);
            dzp = in != (real)0 ? dzp : (real8)(0);
            ax += fabs(dxn);
            ay += fabs(dyn);
            az += fabs(dzn);
            real8 gv = (sign8(dxp) - sign8(dxn)) * wx + (sign8(dyp) - sign8(dyn)) * wy + (sign8(dzp) - sign8(dzn)) * wz;
            vstore8(gv, 0, gr + x);
        }
        for (int x = (nx + 7) / 8 * 8; x < pitch - 8; x += 8)
            vstore8((real8)(0), 0, gr + x);
    }
    part[3 * z] = hsum8(ax);
    part[3 * z + 1] = hsum8(ay);
    part[3 * z + 2] = hsum8(az);
}

/* Gradient rows of the kept Gaussians (rank k, meta[3] of them) from dL/dmu = g (patch_tv's
 * layout); a fixed number of work-items, each taking ranks gid, gid + size, ... */
__kernel void patch_grad(global const real *packed, global const int *meta, global const real *xs,
                         global const real *ys, global const real *zs, int nx, int ny, int nz, int pitch,
                         global const real *g, global real *grad)
{
    int n = meta[3], step = get_global_size(0);
    for (int k = get_global_id(0); k < n; k += step) {
        gauss_t gs = load_gauss(packed, k);
        write_grad(grad, k, gs, grid_moments(gs, xs, ys, zs, nx, ny, nz, g + 8, pitch, 1));
    }
}
